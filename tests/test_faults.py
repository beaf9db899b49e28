"""What the outside world does to a run ends in one line and a documented status (issue
45): Ctrl-C, a closed pipe, a full disk, a bad cache folder, bad cluster addresses, a
port in use; work and memory bounded before they start; one writer per store, lost rows
solved again, `progress` never writing; a refused run leaving no empty folder behind."""

from __future__ import annotations

import errno
import json
import math
import os
import signal
import socket
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import recoil_jax as rj
import recoil_jax._sweeps.memory as memory_module
import recoil_jax.extend as rjx
from recoil_jax._campaigns.store import _hold
from recoil_jax.apps import main
from recoil_jax.apps._cli import sweep as sweep_app

CLI = [sys.executable, "-m", "recoil_jax.apps._cli"]


def _one_line(err: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def _raising(error):
    def command(args):
        raise error

    return command


def test_ctrl_c_is_one_line_saying_what_was_kept_and_status_130(monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(sweep_app, "run_sweep", _raising(KeyboardInterrupt()))
    store = tmp_path / "s.sqlite"
    assert main(["sweep", "m=500,1500", "--store", str(store)]) == 130
    line = _one_line(capsys.readouterr().err)
    assert f"every finished part is in {store}" in line and "to resume" in line
    assert main(["sweep", "m=500,1500"]) == 130
    assert "give --store FILE.sqlite" in _one_line(capsys.readouterr().err)


def test_a_full_disk_is_one_line_naming_the_file_and_other_errors_keep_their_traceback(
    monkeypatch, capsys
):
    full = OSError(errno.ENOSPC, "No space left on device", "out/result.json")
    monkeypatch.setattr(sweep_app, "run_sweep", _raising(full))
    assert main(["sweep", "m=500,1500"]) == 1
    line = _one_line(capsys.readouterr().err)
    assert line == "recoil-jax: error: out/result.json: No space left on device"
    # A bug is not an input fault: its traceback stays, so that tests find it.
    monkeypatch.setattr(sweep_app, "run_sweep", _raising(FileNotFoundError(2, "gone", "x")))
    with pytest.raises(FileNotFoundError):
        main(["sweep", "m=500,1500"])
    monkeypatch.setattr(sweep_app, "run_sweep", _raising(RuntimeError("a bug")))
    with pytest.raises(RuntimeError, match="a bug"):
        main(["sweep", "m=500,1500"])


def test_a_cache_folder_that_cannot_be_made_is_a_warning(monkeypatch, tmp_path, capsys):
    (tmp_path / "file").write_text("not a folder")
    monkeypatch.setenv("RECOIL_JAX_CACHE", str(tmp_path / "file"))
    assert main(["progress", str(tmp_path / "none.sqlite")]) == 2  # the command still runs
    err = capsys.readouterr().err
    assert "warning: the compilation cache" in err and "running without it" in err
    assert "no such file" in err


@pytest.mark.parametrize("address", ["garbage!!", "", "http://127.0.0.1:8786", "tcp://host"])
def test_a_bad_scheduler_address_is_one_line(address, capsys):
    argv = ["sweep", "m=500,1500", "gap=0.05", "--scheduler", address]
    started = time.perf_counter()
    assert main(argv) == 2
    assert "is not a scheduler's address" in _one_line(capsys.readouterr().err)
    assert time.perf_counter() - started < 30.0  # no Dask asked, no timeout waited


@pytest.mark.parametrize(
    "options, message",
    [
        (["--workers", "0"], "--workers 0 is invalid"),
        (["--scheduler", "garbage!!"], "is not a scheduler's address"),
        (["--workers", "2", "--scheduler", "tcp://127.0.0.1:1"], "not both"),
    ],
)
def test_optimise_refuses_its_cluster_options_before_it_starts(options, message, tmp_path, capsys):
    argv = ["optimise", "tuned_absorber", "--out", str(tmp_path / "out"), *options]
    assert main(argv) == 2
    assert message in _one_line(capsys.readouterr().err)  # the study's first line not printed
    assert not (tmp_path / "out").exists()


def test_more_workers_than_cores_are_capped_with_a_warning(monkeypatch, capsys):
    distributed = pytest.importorskip("distributed")
    from recoil_jax.apps._files.cluster import _cores, dask_client

    made = {}

    class Cluster:
        def __init__(self, n_workers, **kwargs):
            made["workers"] = n_workers

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return None

    class Client(Cluster):
        def __init__(self, cluster):
            pass

    monkeypatch.setattr(distributed, "LocalCluster", Cluster)
    monkeypatch.setattr(distributed, "Client", Client)
    with dask_client(1000, None):
        pass
    assert made["workers"] == _cores()
    assert f"--workers 1000 is more than the {_cores()} cores" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (["--port", "70000"], "--port 70000 is invalid"),
        (["--port", "-5"], "--port -5 is invalid"),
        (["--address", "not an address!"], "is not an address of this machine"),
    ],
)
def test_explore_refuses_what_it_cannot_listen_on_before_printing_a_url(options, message, capsys):
    pytest.importorskip("panel")
    assert main(["explore", "--no-browser", *options]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and message in _one_line(captured.err)


@pytest.mark.slow  # the explorer's first solve compiles
def test_explore_refuses_a_port_in_use_and_prints_the_address_it_serves(monkeypatch, capsys):
    panel = pytest.importorskip("panel")
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        argv = ["explore", "--no-browser", "--address", "127.0.0.1", "--port", str(port)]
        assert main(argv) == 2
        assert "cannot listen on 127.0.0.1" in _one_line(capsys.readouterr().err)
    served = {}
    monkeypatch.setattr(panel, "serve", lambda *a, **k: served.update(k))
    assert main(argv) == 0
    assert capsys.readouterr().out == f"recoil-jax explore: http://127.0.0.1:{port}/\n"
    assert served["address"] == "127.0.0.1" and f"127.0.0.1:{port}" in served["websocket_origin"]


def test_an_axis_or_a_grid_too_large_for_memory_is_refused_with_its_size(monkeypatch, capsys):
    assert main(["sweep", "m=10:2000:1000000000", "gap=0.05", "--json"]) == 2
    assert "1,000,000,000 values on one axis" in _one_line(capsys.readouterr().err)
    # As on a machine with 1 GB free (whatever this one has).
    monkeypatch.setattr(memory_module, "_available_memory", lambda: 10**9)
    assert main(["sweep", "m=10:2000:100000", "gap=0:0.1:100000", "--json"]) == 2
    line = _one_line(capsys.readouterr().err)
    assert "a sweep in memory of 10,000,000,000 designs needs about" in line
    assert "keep the results in a store instead (--store FILE.sqlite" in line
    with pytest.raises(rj.ParameterError, match=r"a grid of 200,000,000 designs needs about 3\.2"):
        rj.grid({"m": np.ones(20_000), "gap": np.ones(10_000)})
    with pytest.raises(rj.ParameterError, match="a sweep in memory of 3,000,000 designs"):
        rj.sweep({"m": np.full(3_000_000, 1000.0)}, progress=False)


@pytest.mark.slow
def test_a_refused_huge_sweep_stays_small_in_a_real_process(tmp_path):
    """The resident memory of the refused sweep, measured in its own process."""
    if not Path("/proc/self/status").exists():
        pytest.skip("no /proc here")
    # VmHWM, this program's own peak: ru_maxrss would carry over the forked parent's.
    script = (
        "import re\n"
        "import recoil_jax._sweeps.memory as memory\n"
        "memory._available_memory = lambda: 10**9  # as on a machine with 1 GB free\n"
        "from recoil_jax.apps import main\n"
        "status = main(['sweep', 'm=10:2000:100000', 'gap=0:0.1:100000', '--json'])\n"
        "text = open('/proc/self/status').read()\n"
        "print(re.search(r'VmHWM:\\s+(\\d+) kB', text).group(1), status)\n"
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=120)  # fmt: skip
    peak_kb, status = done.stdout.split()
    assert status == "2" and "a sweep in memory of 10,000,000,000 designs" in done.stderr
    assert int(peak_kb) < 1_500_000, peak_kb  # KB: the refusal allocates nothing big


@pytest.mark.slow
def test_a_streamed_grid_keeps_its_memory_whatever_its_size(tmp_path):
    """A grid of 10^10 designs streamed to a store runs in the memory of one of 10^4: its
    columns are made a chunk at a time (the solves stubbed, so that only the sweep's own
    memory is measured; the run is stopped after its first chunks)."""
    if not Path("/proc/self/status").exists():
        pytest.skip("no /proc here")
    script = (
        "import re, sys\n"
        "import numpy as np\n"
        "import recoil_jax as rj, recoil_jax.extend as rjx\n"
        "import recoil_jax._sweeps.dispatch as dispatch\n"
        "solved = []\n"
        "def stub(batch, t1, count, *args):\n"
        "    solved.append(count)\n"
        "    if len(solved) > 6:\n"
        "        raise KeyboardInterrupt\n"
        "    peaks = {key: np.ones(count) for key in rjx.PEAK_FIELDS.values()}\n"
        "    return peaks | {'status_code': np.zeros(count, np.int32)}, 0.01\n"
        "dispatch._solve_chunk = stub\n"
        "side = int(sys.argv[1])\n"
        "grid = rjx.Grid({'m': np.linspace(10, 2000, side), 'gap': np.linspace(0, 0.1, side)})\n"
        "try:\n"
        "    rj.sweep_to_store(grid, sys.argv[2], chunk_size=4096, progress=False)\n"
        "except KeyboardInterrupt:\n"
        "    pass\n"
        "stored = rj.campaign_progress(sys.argv[2])\n"
        "text = open('/proc/self/status').read()\n"
        "print(re.search(r'VmHWM:\\s+(\\d+) kB', text).group(1), stored.done, stored.total)\n"
    )
    peaks = {}
    for side in (100, 100_000):
        store = tmp_path / f"grid{side}.sqlite"
        done = subprocess.run(
            [sys.executable, "-c", script, str(side), str(store)],
            capture_output=True, text=True, timeout=300,
        )  # fmt: skip
        assert done.returncode == 0, done.stderr
        peak_kb, stored, total = map(int, done.stdout.split())
        assert total == side**2 and stored == min(6 * 4096, side**2)
        peaks[side] = peak_kb
    # The columns of 10^10 designs alone would take 160 GB; the two runs differ by the
    # axes (1.6 MB) and noise.
    assert peaks[100_000] < peaks[100] + 100_000, peaks


STUDY = """
[tune]
gap = [0.0, 0.12]
[objective]
peak_anchoring_force = 1.0
[optimiser]
steps = 2
[check]
"""


@pytest.mark.parametrize(
    ("check", "message"),
    [
        ("grid = { gap = [0.0, 0.2, 1000000000] }", "1,000,000,000 points, more than 100,000"),
        ("grid = { gap = [0.0, 0.2, 0] }", "an integer count >= 1"),
        ("grid = { gap = [0.2, 0.0, 5] }", "lo <= hi"),
        ("grid = { spring = [0.0, 0.2, 5] }", "unknown parameter 'spring'"),
        ("local = -1", "local = -1: a fraction of each bound's width, in (0, 1]"),
        ("hard = 'yes'", "hard = 'yes': give true or false"),
    ],
)
def test_every_count_of_a_study_is_checked_at_load(tmp_path, capsys, check, message):
    (tmp_path / "s.toml").write_text(STUDY + check + "\n")
    out = tmp_path / "out"
    assert main(["optimise", str(tmp_path / "s.toml"), "--out", str(out)]) == 2
    assert message in _one_line(capsys.readouterr().err)
    assert not out.exists()


def test_a_refused_run_leaves_no_empty_output_folder(tmp_path, capsys):
    (tmp_path / "s.toml").write_text(STUDY)
    foreign = tmp_path / "sweep.sqlite"
    rj.sweep({"m": [500.0, 1000.0]}, store=foreign, progress=False)
    out = tmp_path / "new" / "out"
    argv = ["optimise", str(tmp_path / "s.toml"), "--out", str(out), "--store", str(foreign)]
    assert main(argv) == 2  # refused after the folder was made: the store is a sweep's
    err = capsys.readouterr().err
    assert "Traceback" not in err and "not of this one" in err.strip().splitlines()[-1]
    assert not (tmp_path / "new").exists()


def test_a_second_writer_is_refused_naming_the_holder(tmp_path, capsys):
    store = tmp_path / "s.sqlite"
    holder = _hold(store)
    try:
        assert main(["sweep", "m=500,1500", "gap=0.05", "--store", str(store)]) == 2
        line = _one_line(capsys.readouterr().err)
        assert f"in use by process {os.getpid()} on {socket.gethostname()} since" in line
    finally:
        holder.close()
    assert main(["sweep", "m=500,1500", "gap=0.05", "--store", str(store)]) == 0


def test_lost_rows_are_solved_again_not_read_as_zeros(tmp_path, capsys):
    designs = {"m": np.linspace(200.0, 2000.0, 300), "gap": np.full(300, 0.05)}
    plain = rj.sweep(designs, progress=False)
    store = tmp_path / "s.sqlite"
    rj.sweep(designs, store=store, progress=False, chunk_size=128, workers=1)
    with sqlite3.connect(store) as db:
        db.execute("DELETE FROM points WHERE point IN (3, 200)")
    capsys.readouterr()
    again = rj.sweep(designs, store=store, chunk_size=128, workers=1)
    assert "rows missing or doubled" in capsys.readouterr().err
    assert again.ok.all() and again.stored < 300
    np.testing.assert_allclose(
        again.peaks["peak_anchoring_force"], plain.peaks["peak_anchoring_force"], rtol=1e-12
    )
    with sqlite3.connect(store) as db:
        assert db.execute("SELECT COUNT(*), COUNT(DISTINCT point) FROM points").fetchone() == (
            300,
            300,
        )


def test_progress_never_writes_into_the_store(tmp_path, capsys):
    store = tmp_path / "s.sqlite"
    rj.sweep({"m": [500.0, 1000.0]}, store=store, progress=False)
    before = (store.stat().st_size, store.stat().st_mtime_ns, store.read_bytes())
    assert main(["progress", str(store)]) == 0
    assert (store.stat().st_size, store.stat().st_mtime_ns, store.read_bytes()) == before
    empty = tmp_path / "empty.sqlite"
    empty.write_bytes(b"")
    assert main(["progress", str(empty)]) == 2
    assert empty.stat().st_size == 0


def _wait_for(predicate, seconds: float) -> None:
    end = time.monotonic() + seconds
    while not predicate():
        assert time.monotonic() < end, "timed out"
        time.sleep(0.2)


def _stored(store: Path) -> int:
    try:
        return rj.campaign_progress(store).done
    except rj.ParameterError:
        return 0


@pytest.mark.slow
def test_real_processes_ctrl_c_a_second_writer_and_a_resume(tmp_path):
    """A sweep in its own process holds its store: a second writer is refused naming
    it; SIGINT stops it with one line and status 130; the same command resumes."""
    store = tmp_path / "s.sqlite"
    # 397,261 designs: about 20 s on 2 cores, long enough for the second process.
    argv = [*CLI, "sweep", "m=100:3000:601", "gap=0:0.15:661", "--store", str(store)]
    env = os.environ | {"RECOIL_JAX_CACHE": str(tmp_path / "cache")}
    first = subprocess.Popen(argv, stderr=subprocess.PIPE, text=True, env=env)
    try:
        _wait_for(lambda: _stored(store) > 0, 240)
        second = subprocess.run(argv, capture_output=True, text=True, env=env, timeout=120)
        assert second.returncode == 2
        assert f"is in use by process {first.pid}" in _one_line(second.stderr)
        first.send_signal(signal.SIGINT)
        _, err = first.communicate(timeout=120)
    finally:
        first.kill()
    assert first.returncode == 130, err
    last = err.strip().splitlines()[-1]
    assert "Traceback" not in err and last.startswith("recoil-jax: interrupted; every")
    assert f"--store {store} to resume" in last
    kept = _stored(store)
    assert 0 < kept < 601 * 661
    resumed = subprocess.run(argv, capture_output=True, text=True, env=env, timeout=600)
    assert resumed.returncode == 0, resumed.stderr
    assert f"resuming from {store}: {kept} of 397261" in resumed.stderr
    assert rj.campaign_progress(store).done == 397261


@pytest.mark.slow
def test_real_processes_a_closed_pipe_is_quiet_and_a_full_disk_one_line(tmp_path):
    env = os.environ | {"RECOIL_JAX_CACHE": str(tmp_path / "cache")}
    sweep = subprocess.Popen(
        [*CLI, "sweep", "m=100:3000:30", "gap=0:0.15:31", "--json"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env,
    )  # fmt: skip
    assert sweep.stdout is not None and sweep.stderr is not None
    sweep.stdout.read(100)
    sweep.stdout.close()  # as `| head -c 100` does
    err = sweep.stderr.read().decode()
    assert sweep.wait(timeout=300) == 1
    assert "Traceback" not in err and "Broken pipe" not in err and "Exception" not in err, err
    if not Path("/dev/full").exists():
        pytest.skip("no /dev/full here")
    with open("/dev/full", "w") as full:
        done = subprocess.run([*CLI, "simulate", "--json"], stdout=full, stderr=subprocess.PIPE,
                              text=True, env=env, timeout=300)  # fmt: skip
    assert done.returncode == 1
    # The write fails inside the command (no file name), or at its final flush.
    assert _one_line(done.stderr) in (
        "recoil-jax: error: No space left on device",
        "recoil-jax: error: cannot write standard output: No space left on device",
    )


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["simulate", "--plot", "{tmp}/file.txt/h.png"], "--plot's folder"),
        (["simulate", "--plot", "/proc/recoil/h.png"], "--plot's folder /proc/recoil cannot"),
        (["simulate", "--plot", "{tmp}"], "is a folder"),
        (["sweep", "m=500,1500", "--out", "/proc/recoil"], "--out /proc/recoil cannot be made"),
        (["sweep", "m=500,1500", "--out", "{tmp}/file.txt"], "is a file, not a folder"),
    ],
)
def test_an_output_that_cannot_be_written_is_refused_before_solving(
    tmp_path, capsys, argv, message
):
    (tmp_path / "file.txt").write_text("a file")
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    if argv[-1] == str(tmp_path):  # a folder given as the figure's file
        argv[-1] = str(tmp_path / "dir.png")
        (tmp_path / "dir.png").mkdir()
    assert main(argv) == 2
    assert message in _one_line(capsys.readouterr().err)


def test_a_store_that_is_not_a_regular_file_is_refused(tmp_path, capsys):
    out = tmp_path / "out"
    argv = ["sweep", "m=500,1500", "--store", os.devnull, "--out", str(out)]
    assert main(argv) == 2
    assert f"store {os.devnull} is not a regular file" in _one_line(capsys.readouterr().err)
    assert not out.exists() and not Path(os.devnull + ".lock").exists()
    assert main(["progress", os.devnull]) == 2
    assert "not a regular file" in _one_line(capsys.readouterr().err)


def test_a_link_to_a_store_in_use_is_refused_too(tmp_path, capsys):
    store = tmp_path / "s.sqlite"
    (tmp_path / "link.sqlite").symlink_to(store)
    holder = _hold(store)
    try:
        argv = ["sweep", "m=500,1500", "gap=0.05", "--store", str(tmp_path / "link.sqlite")]
        assert main(argv) == 2
        assert f"in use by process {os.getpid()}" in _one_line(capsys.readouterr().err)
    finally:
        holder.close()


def test_loading_a_store_with_lost_rows_says_so(tmp_path):
    store = tmp_path / "s.sqlite"
    rj.sweep_to_store({"m": np.linspace(200.0, 2000.0, 40)}, store, progress=False)
    with sqlite3.connect(store) as db:
        db.execute("DELETE FROM points WHERE point = 7")
    with pytest.raises(rj.ParameterError, match="39 distinct of its 40 designs"):
        rj.load_sweep(store)


# --- calibrate, sensitivity and progress (issue 52, item 5) ----------------------------

CALIBRATE_TOML = '[fit]\nk = [1e4, 1e5]\n[[experiment]]\ntrace = "t.csv"\n'


class _Reached(BaseException):
    """The fit (or the sensitivity run) was about to start: every check had passed."""


def _not_reached(*args, **kwargs):
    raise _Reached


@pytest.fixture
def traces(tmp_path, monkeypatch):
    """A folder with a varying trace `t.csv` and a calibration file `c.toml` naming it;
    the fit and the sensitivity run stubbed (these are checks made before them)."""
    ts = np.linspace(0.0, 0.5, 51)
    lines = ["t,x_M", *(f"{t:.4g},{0.01 * np.sin(9 * t):.6g}" for t in ts)]
    (tmp_path / "t.csv").write_text("\n".join(lines) + "\n")
    (tmp_path / "c.toml").write_text(CALIBRATE_TOML)
    monkeypatch.setattr(rj, "calibrate", _not_reached)
    monkeypatch.setattr(rj, "sensitivity", _not_reached)
    monkeypatch.chdir(tmp_path)
    return tmp_path


def _refused(capsys, argv, fragment, status=2):
    assert main(argv) == status
    line = _one_line(capsys.readouterr().err)
    assert line.startswith("recoil-jax: error:") and fragment in line, line
    return line


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs here")
def test_what_is_not_a_regular_file_is_refused_without_reading_it(traces, capsys):
    """A FIFO would wait forever for a writer, /dev/zero be read until memory runs out:
    every file the commands read is refused unless it is a regular file."""
    fifo = traces / "fifo"
    os.mkfifo(fifo)
    started = time.perf_counter()
    not_regular = "is not a regular file (a pipe, a device or a socket)"
    for argv in (
        ["calibrate", str(fifo), "--fit", "k"],
        ["calibrate", "t.csv", "--fit", "k", "--validate", str(fifo)],
        ["calibrate", "t.csv", "--fit", "k", "--force-table", str(fifo)],
        ["calibrate", "/dev/zero", "--fit", "k"],
        ["sensitivity", "/dev/urandom"],
        ["sweep", "--points", str(fifo)],
        ["optimise", str(fifo)],
    ):
        _refused(capsys, argv, not_regular)
    (traces / "c.toml").write_text(CALIBRATE_TOML.replace("t.csv", "fifo"))
    _refused(capsys, ["calibrate", "c.toml"], f"trace fifo {not_regular}")
    assert time.perf_counter() - started < 10


def test_a_file_over_the_byte_limit_is_refused_naming_the_limit(traces, capsys, monkeypatch):
    import recoil_jax._model.text_files as text_files

    assert rjx.MAX_TEXT_BYTES == 64 * 2**20
    monkeypatch.setattr(text_files, "MAX_TEXT_BYTES", 500)
    _refused(capsys, ["calibrate", "t.csv", "--fit", "k"],
             "trace t.csv is larger than 0.000476837 MiB, the most a file read whole may "
             "hold (MAX_TEXT_BYTES)")  # fmt: skip


@pytest.mark.parametrize(
    ("argv", "toml", "fragment"),
    [
        (["--starts", "1000000000"], None, "--starts 1000000000: give an integer from 1 to 1,024"),
        ([], "starts = 1000000000\n", "starts = 1000000000: valid an integer from 1 to 1,024"),
        ([], "fit_steps = 1000000000000\n", "fit_steps = 1000000000000: valid an integer from 1"),
        ([], "[[experiment]]\ntrace = 't.csv'\n" * 300, "301 experiments (fitted and valid"),
        (["--validate", "t.csv"] * 60, None, "61 experiments (fitted and validation), more"),
    ],
)
def test_every_count_of_a_calibration_is_bounded_before_it_starts(
    traces, capsys, argv, toml, fragment
):
    if toml is None:
        argv = ["calibrate", "t.csv", "--fit", "k", *argv]
    else:
        (traces / "c.toml").write_text(toml + CALIBRATE_TOML)
        argv = ["calibrate", "c.toml", *argv]
    started = time.perf_counter()
    _refused(capsys, argv, fragment)
    assert time.perf_counter() - started < 10


def test_starts_that_would_not_fit_in_memory_are_refused(traces, capsys, monkeypatch):
    monkeypatch.setattr(memory_module, "_available_memory", lambda: 10**6)  # 1 MB free
    line = _refused(capsys, ["calibrate", "t.csv", "--fit", "k", "--starts", "1000"],
                    "a calibration of 1,000 starts at once needs about")  # fmt: skip
    assert "--store FILE.sqlite" in line
    # With a store, 8 at a time.
    monkeypatch.setattr(memory_module, "_available_memory", lambda: 10**7)
    with pytest.raises(_Reached):
        main(["calibrate", "t.csv", "--fit", "k", "--starts", "1000", "--store", "c.sqlite"])


@pytest.mark.parametrize(
    ("argv", "toml", "fragment"),
    [
        (["c.toml", "v0=0.5"], None,
         "v0=0.5 is given on the command line beside the calibration file c.toml: give it "
         "in one place"),
        (["t.csv", "--fit", "k", "k=3e4"], None,
         "k is given both on the command line (k=3e4) and in --fit k: give it in one place"),
        (["c.toml"], "[design]\nk = 3e4\n",
         "k is given both in [design] (k = 30000) and in [fit]: give it in one place"),
        (["t.csv", "--fit", "k,c_out,k"], None, "--fit k,c_out,k: k is given twice"),
        (["c.toml"], "description = [1, 2]\n", "description = [1, 2]: give a string"),
        (["c.toml"], CALIBRATE_TOML + "per_experiment = ['v0', 'v0']\n",
         "[[experiment]] 1.per_experiment: v0 is given twice"),
        (["t.csv", "--fit", "k", "--predict", "bogus=1"], None,
         "--predict: unknown parameter 'bogus'"),
        (["t.csv", "--fit", "k", "v0=heavy"], None, "v0 = 'heavy' is not a number"),
    ],
)  # fmt: skip
def test_conflicts_and_repeats_are_refused_before_the_fit(traces, capsys, argv, toml, fragment):
    if toml is not None:
        body = toml if toml.startswith("[fit]") else toml + CALIBRATE_TOML
        (traces / "c.toml").write_text(body)
    line = _refused(capsys, ["calibrate", *argv], fragment)
    assert line.endswith(fragment) or "is not a number" not in fragment  # nothing glued on


def test_a_non_integer_option_is_one_line(capsys):
    with pytest.raises(SystemExit) as exit:
        main(["calibrate", "t.csv", "--fit", "k", "--starts", "x"])
    assert exit.value.code == 2
    assert _one_line(capsys.readouterr().err) == (
        "recoil-jax: error: calibrate: argument --starts: invalid int value: 'x' (see "
        "recoil-jax calibrate --help)"
    )


@pytest.mark.parametrize(
    ("signal_", "fragment"),
    [
        ("0.01", "t.csv, column x_M: every sample is 0.01; a signal with no variation cannot"),
        ("0", "t.csv, column x_M: every sample is 0; a signal with no variation cannot"),
        ("1e300 * t", "t.csv, column x_M: a value of 5e+299 is beyond 1e+150, where its"),
    ],
)
def test_a_signal_the_fit_cannot_use_is_refused_naming_file_and_column(
    traces, capsys, signal_, fragment
):
    ts = np.linspace(0.0, 0.5, 51)
    rows = [f"{t:.4g},{eval(signal_, {'t': t}):.6g}" for t in ts]
    (traces / "t.csv").write_text("t,x_M\n" + "\n".join(rows) + "\n")
    _refused(capsys, ["calibrate", "t.csv", "--fit", "k"], fragment)
    _refused(capsys, ["calibrate", "c.toml"], fragment)


@pytest.mark.parametrize(
    ("scale", "offset", "warning"),
    [
        (1000.0, 0.0, "t.csv spans 0 to 500 s, outside the documented range of t1 0.1 to 60 s"),
        (1.0, 3e7, "t.csv starts at t = 3e+07 s: are its times epoch seconds?"),
    ],
)
def test_a_trace_not_in_seconds_from_the_firing_is_warned_of(traces, capsys, scale, offset,
                                                              warning):  # fmt: skip
    ts = np.linspace(0.0, 0.5, 51)
    rows = [f"{offset + scale * t:.12g},{0.01 * np.sin(9 * t):.6g}" for t in ts]
    (traces / "t.csv").write_text("t,x_M\n" + "\n".join(rows) + "\n")
    with pytest.raises(_Reached):
        main(["calibrate", "t.csv", "--fit", "k"])
    assert f"recoil-jax: warning: {warning}" in capsys.readouterr().err


def test_a_trace_in_epoch_seconds_is_refused(traces, capsys):
    """Past the longest solve (1e6 times t1's documented top), a trace is refused, not
    solved for 54 years."""
    ts = np.linspace(0.0, 0.5, 51)
    rows = [f"{1.7e9 + t:.12g},{0.01 * np.sin(9 * t):.6g}" for t in ts]
    (traces / "t.csv").write_text("t,x_M\n" + "\n".join(rows) + "\n")
    _refused(capsys, ["calibrate", "t.csv", "--fit", "k"],
             "t.csv runs to t = 1.7e+09 s, past the longest solve (6e+07 s): are its times "
             "epoch seconds?")  # fmt: skip


def test_the_sensitivity_file_refuses_repeated_metrics(tmp_path, capsys):
    body = ('[ranges]\nk = { relative = 0.1 }\n[metrics]\nnames = ["max_stroke", '
            '"max_stroke"]\n[method]\nname = "sobol"\nsamples = 64\n')  # fmt: skip
    (tmp_path / "s.toml").write_text(body)
    _refused(capsys, ["sensitivity", str(tmp_path / "s.toml")],
             "[metrics] names: max_stroke is given twice")  # fmt: skip


def test_ranges_from_a_covariance_that_is_not_positive_are_refused_naming_it(tmp_path):
    hardware = {"names": ["k", "c_out"], "values": [28000.0, 6000.0],
                "covariance": [[-4.0, 0.0], [0.0, 9.0]], "lower": [1e4, 1e3],
                "upper": [1e5, 3e4], "identifiable": [True, True], "design": {}}  # fmt: skip
    (tmp_path / "result.json").write_text(json.dumps({"hardware": hardware}))
    fitted = rjx.FittedParameters.from_json(tmp_path / "result.json")
    with pytest.raises(rj.ParameterError, match=r"^k: its variance in the calibration's "
                       r"covariance is -4, not a positive number"):  # fmt: skip
        fitted.box(2.0)
    hardware["covariance"][1][1] = None  # as a result.json writes a NaN now
    (tmp_path / "result.json").write_text(json.dumps({"hardware": hardware}))
    with pytest.raises(rj.ParameterError, match=r"^k: "):
        rjx.FittedParameters.from_json(tmp_path / "result.json").box(2.0)


def test_every_result_json_writes_null_beside_its_reason_never_nan(tmp_path):
    from recoil_jax.apps._cli import calibrate as _calibration
    from recoil_jax.apps._files import json_writer as _json

    report = {"aic": math.inf, "rms": {"x_M": np.float64("nan")}, "c": [[1.0, -math.inf]]}
    text = _json.dumps(report)
    assert json.loads(text) == {
        "aic": None, "aic_null": "inf (not a finite number; JSON has none)",
        "rms": {"x_M": None, "x_M_null": "nan (not a finite number; JSON has none)"},
        "c": [[1.0, None]], "c_null": "1 values written null: -inf (not finite; JSON has none)",
    }  # fmt: skip
    assert "Infinity" not in text and "NaN" not in text
    # calibrate's writes are this writer's (whole or not at all)
    assert _calibration.write_json is _json.write and _calibration.dumps is _json.dumps
    path = _json.write(tmp_path / "result.json", report)
    assert json.loads(path.read_text())["aic"] is None
    assert [p.name for p in tmp_path.iterdir()] == ["result.json"]


def test_a_full_disk_names_the_file_and_leaves_no_truncated_one(tmp_path, monkeypatch, capsys):
    from recoil_jax.apps._cli import sensitivity as sensitivity_app
    from recoil_jax.apps._files import json_writer as _json

    class Full:
        def __init__(self, *args, **kwargs):
            pass

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

        def write(self, text):
            raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(_json, "open", Full, raising=False)
    with pytest.raises(OSError) as error:
        _json.write_text(tmp_path / "samples.csv", "a,b\n1,2\n")
    assert error.value.filename == str(tmp_path / "samples.csv")
    assert list(tmp_path.iterdir()) == []
    # A library's write with no file name is said to be into the output folder.
    monkeypatch.setattr(sensitivity_app, "run_sensitivity",
                        _raising(OSError(errno.ENOSPC, "No space left on device")))  # fmt: skip
    out = tmp_path / "out"
    assert main(["sensitivity", "x.toml", "--out", str(out)]) == 1
    assert _one_line(capsys.readouterr().err) == (
        f"recoil-jax: error: writing into {out}: No space left on device"
    )


@pytest.mark.parametrize("command", ["calibrate", "sensitivity", "progress"])
def test_a_damaged_store_is_named_with_what_to_do(tmp_path, monkeypatch, capsys, command):
    from recoil_jax.apps._cli import calibrate as _calibration, sensitivity as sensitivity_app

    damaged = sqlite3.DatabaseError("database disk image is malformed")
    monkeypatch.setattr(_calibration, "run_calibration", _raising(damaged))
    monkeypatch.setattr(sensitivity_app, "run_sensitivity", _raising(damaged))
    monkeypatch.setattr(rj, "campaign_progress", _raising(damaged))
    store = str(tmp_path / "s.sqlite")
    argv = {"calibrate": ["calibrate", "t.csv", "--fit", "k", "--store", store],
            "sensitivity": ["sensitivity", "x.toml", "--store", store],
            "progress": ["progress", store]}[command]  # fmt: skip
    assert main(argv) == 2
    assert _one_line(capsys.readouterr().err) == (
        f"recoil-jax: error: store {store} is damaged (database disk image is malformed): "
        "move it aside to keep it, or delete it to start again"
    )


def test_a_store_damaged_inside_is_named_in_a_real_run(tmp_path, capsys):
    store = tmp_path / "s.sqlite"
    argv = ["sweep", "m=200:2000:4000", "--store", str(store), "--out", str(tmp_path / "o")]
    assert main(argv) == 0
    capsys.readouterr()
    data = bytearray(store.read_bytes())
    data[len(data) // 2 : len(data) // 2 + 5000] = b"\x07" * 5000
    store.write_bytes(bytes(data))
    assert main(argv) == 2
    assert f"store {store} is damaged" in _one_line(capsys.readouterr().err)


ENTRY = [sys.executable, "-m", "recoil_jax_entry"]


@pytest.mark.slow
@pytest.mark.parametrize("delay", [0.05, 0.3, 0.8])
def test_real_processes_ctrl_c_while_starting_and_again_is_one_line(tmp_path, delay):
    """Ctrl-C during the imports, and three in a row: one line, status 130, never a
    traceback, an atexit KeyboardInterrupt or an abort (134)."""
    root = Path(__file__).resolve().parents[1]
    env = os.environ | {"RECOIL_JAX_CACHE": str(tmp_path / "cache"), "PYTHONPATH": str(root)}
    argv = [*ENTRY, "sweep", "m=100:3000:300", "gap=0:0.1:300"]
    for attempt in range(6):
        process = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                   text=True, env=env)  # fmt: skip
        time.sleep(delay * 2**attempt)
        for _ in range(3):
            process.send_signal(signal.SIGINT)
            time.sleep(0.02)
        _, err = process.communicate(timeout=120)
        # On a loaded machine the first signal can come while Python itself still starts
        # (its `site` module, the editable install's finder, or runpy compiling the entry
        # point), before any code of ours exists to catch it: a traceback with no frame of
        # ours. Try again, a little later each time (on a loaded machine Python's own start
        # outlasted 0.05 s three times running), or while the entry point's own module
        # still imports `signal`, before the handler can be set (the entry point's
        # `<module>` frame alone: a frame of the package's counts, as an import of it
        # moved above the handler would print one). The virtual environment may sit
        # inside the checkout: its frames are not ours.
        entry = f'File "{root / "recoil_jax_entry.py"}"'
        ours = [line for line in err.splitlines()
                if f'File "{root}' in line and f'File "{sys.prefix}' not in line
                and not (entry in line and line.rstrip().endswith("in <module>"))]  # fmt: skip
        if "Traceback" not in err or ours:
            break
    assert process.returncode == 130, err
    assert _one_line(err).startswith("recoil-jax: interrupted")


@pytest.mark.slow
def test_real_processes_a_closed_standard_output_is_no_traceback(tmp_path):
    root = Path(__file__).resolve().parents[1]
    env = os.environ | {"RECOIL_JAX_CACHE": str(tmp_path / "cache"), "PYTHONPATH": str(root)}
    store = tmp_path / "s.sqlite"
    rj.sweep_to_store({"m": np.linspace(200.0, 2000.0, 4)}, store, progress=False)
    for argv in (ENTRY, CLI):
        done = subprocess.run(["sh", "-c", '"$@" >&-', "sh", *argv, "progress", str(store)],
                              capture_output=True, text=True, env=env, timeout=120)  # fmt: skip
        assert done.returncode == 0 and done.stderr == "", done.stderr
