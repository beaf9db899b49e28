"""Campaign stores: a sweep committed chunk by chunk to SQLite resumes after an
interruption (an exception here, a `kill -9` of a real process in the slow tier) with
the bits of an uninterrupted run, each chunk stored once; foreign files are refused."""

import importlib.util
import json
import os
import random
import re
import shutil
import signal
import sqlite3
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import SMALL_STUDY, gap_problem, study_text

import recoil_jax as rj
import recoil_jax._sweeps.dispatch as dispatch_module
import recoil_jax.extend as rjx
from recoil_jax._campaigns.store import StudyStore, read_meta
from recoil_jax.apps import main
from recoil_jax.apps._bench.speed import bench_designs

#: 1500 designs in chunks of 512 (3 chunks), two parts per chunk.
PLAN = dict(chunk_size=512, workers=2)


def _assert_same(a: rj.SweepResult, b: rj.SweepResult):
    assert len(a) == len(b)
    for field in rjx.PEAK_FIELDS:
        assert np.array_equal(a.peaks[field], b.peaks[field], equal_nan=True), field
    assert np.array_equal(rjx.status_codes(a.status), rjx.status_codes(b.status))


def _rows(path) -> dict:
    with sqlite3.connect(path) as db:
        return {
            "points": db.execute("SELECT COUNT(*), COUNT(DISTINCT point) FROM points").fetchone(),
            "chunks": db.execute("SELECT COUNT(*) FROM chunks").fetchone()[0],
            "integrity": db.execute("PRAGMA integrity_check").fetchone()[0],
        }


@pytest.fixture(scope="module")
def uninterrupted():
    designs = bench_designs(1500, seed=0)
    return designs, rj.sweep(designs, progress=False, **PLAN)


def test_interrupted_sweep_resumes_to_the_same_bits(uninterrupted, tmp_path, monkeypatch, capsys):
    designs, plain = uninterrupted
    store = tmp_path / "campaign.sqlite"
    real = dispatch_module._run_chunk
    solved = []

    def stop_after_two(*args, **kwargs):
        if len(solved) == 2:
            raise KeyboardInterrupt  # as a user's Ctrl-C, or a crash, between chunks
        solved.append(args[2])  # the chunk's real designs
        return real(*args, **kwargs)

    monkeypatch.setattr(dispatch_module, "_run_chunk", stop_after_two)
    with pytest.raises(KeyboardInterrupt):
        rj.sweep(designs, store=store, **PLAN)
    assert _rows(store) == {"points": (1024, 1024), "chunks": 2, "integrity": "ok"}
    progress = rj.campaign_progress(store)
    assert (progress.kind, progress.total, progress.done, progress.runs) == ("sweep", 1500, 1024, 1)
    assert progress.rate > 0 and progress.seconds_left > 0
    assert "1024/1500 designs" in progress.line()

    monkeypatch.setattr(dispatch_module, "_run_chunk", real)
    resumed = rj.sweep(designs, store=store, **PLAN)
    captured = capsys.readouterr()
    assert "resuming from" in captured.err
    _assert_same(resumed, plain)
    assert resumed.stored == 1024
    assert _rows(store) == {"points": (1500, 1500), "chunks": 3, "integrity": "ok"}
    finished = rj.campaign_progress(store)
    assert (finished.done, finished.runs, finished.seconds_left) == (1500, 2, 0.0)
    assert finished.line().endswith("finished")

    # The rows hold what the result holds, by the CSV's names, read without this project.
    with sqlite3.connect(store) as db:
        db.row_factory = sqlite3.Row
        rows = db.execute("SELECT * FROM points ORDER BY point").fetchall()
    force = np.array([r["peak_anchoring_force_N"] for r in rows], dtype=float)
    assert np.array_equal(force, plain.peaks["peak_anchoring_force"], equal_nan=True)
    assert np.array_equal([r["gap"] for r in rows], designs["gap"])
    assert {r["status"] for r in rows} <= {"ok", *rjx.status_table().values()}

    # Done: a third run solves nothing and gives the same results.
    monkeypatch.setattr(dispatch_module, "_run_chunk", stop_after_two)  # would raise if called
    again = rj.sweep(designs, store=store, progress=False, **PLAN)
    _assert_same(again, plain)
    assert again.stored == 1500


def test_a_store_resumes_with_its_own_chunks(uninterrupted, tmp_path):
    """Resumed with other settings, the chunks are still those of the run that made the
    store (the results do not depend on how the resumed run would cut them)."""
    designs, plain = uninterrupted
    store = tmp_path / "plan.sqlite"
    first = rj.sweep(designs, store=store, progress=False, **PLAN)
    _assert_same(first, plain)
    other = rj.sweep(designs, store=store, progress=False, chunk_size=256, workers=1)
    _assert_same(other, plain)
    assert other.stored == 1500


def test_a_streamed_sweep_keeps_its_results_in_the_store_only(uninterrupted, tmp_path, monkeypatch):
    """`sweep_to_store`: the same results as `sweep`, read back from the store; resumed
    like a sweep; a sweep that has not finished cannot be loaded."""
    designs, plain = uninterrupted
    store = tmp_path / "streamed.sqlite"
    real = dispatch_module._run_chunk
    calls = []

    def stop_after_one(*args, **kwargs):
        if calls:
            raise KeyboardInterrupt
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(dispatch_module, "_run_chunk", stop_after_one)
    with pytest.raises(KeyboardInterrupt):
        rj.sweep_to_store(designs, store, progress=False, **PLAN)
    monkeypatch.setattr(dispatch_module, "_run_chunk", real)
    with pytest.raises(rj.ParameterError, match="holds 512 of 1500 designs"):
        rj.load_sweep(store)
    streamed = rj.sweep_to_store(designs, store, progress=False, **PLAN)
    assert (streamed.designs, streamed.stored, streamed.failed) == (1500, 512, 0)
    loaded = streamed.load()
    _assert_same(loaded, plain)
    assert loaded.stored == 1500 and set(loaded.values) == set(designs)
    for name, column in designs.items():
        assert np.array_equal(loaded.values[name], column)
    # The lowest peak, found by SQLite, is the sweep's.
    lowest = streamed.lowest("peak_anchoring_force")
    force = np.where(plain.ok, plain.peaks["peak_anchoring_force"], np.nan)
    assert lowest["peak_anchoring_force_N"] == np.nanmin(force)
    assert lowest["point"] == int(np.nanargmin(force))
    with pytest.raises(rj.ParameterError, match="unknown peak"):
        streamed.lowest("peak_force")


def test_a_store_keeps_names_that_differ_only_in_case(tmp_path):
    """The barrel's `M` and the absorber's `m` in one sweep: SQLite's names ignore case,
    so the second is stored as `m~2`, and reads back under its own name."""
    designs = {"M": np.array([5000.0, 6000.0]), "m": np.array([500.0, 1500.0]),
               "gap": np.array([0.03, 0.06])}  # fmt: skip
    store = tmp_path / "case.sqlite"
    plain = rj.sweep(designs, progress=False)
    stored = rj.sweep_to_store(designs, store, progress=False)
    loaded = stored.load()
    _assert_same(loaded, plain)
    for name, column in designs.items():
        assert np.array_equal(loaded.values[name], column)
    lowest = stored.lowest("peak_anchoring_force")
    assert (lowest["M"], lowest["m"]) == tuple(
        designs[n][int(np.argmin(plain.peaks["peak_anchoring_force"]))] for n in ("M", "m")
    )
    assert rj.sweep(designs, store=store, progress=False).stored == 2


def test_the_sweep_command_streams_to_its_store(tmp_path, capsys):
    """`sweep --store` without `--out` or `--json` keeps nothing in memory and says the
    same as with them, the lowest peak read from the store."""
    argv = ["sweep", "m=500,1500", "gap=0:0.09:10", "k_r=13000"]
    assert main([*argv, "--out", str(tmp_path / "kept")]) == 0
    kept = capsys.readouterr().out.splitlines()
    assert main([*argv, "--store", str(tmp_path / "streamed.sqlite")]) == 0
    streamed = capsys.readouterr().out.splitlines()
    assert (
        streamed[0].startswith("swept 20 designs: 20 solved")
        and "the results are in" in streamed[0]
    )
    assert streamed[1] == kept[1]  # lowest peak anchoring force: ... N at m=..., gap=...
    loaded = rj.load_sweep(tmp_path / "streamed.sqlite")
    assert len(loaded) == 20 and loaded.gradients is not None  # a gap sweep: d/d(gap) too


def test_foreign_and_broken_stores_are_refused(uninterrupted, tmp_path):
    designs, _ = uninterrupted
    store = tmp_path / "made.sqlite"
    # A store is identified before anything is compiled or solved: a store made by
    # these designs ...
    rj.sweep({k: v[:5] for k, v in designs.items()}, store=store, progress=False)
    # ... refuses other designs, other smoothing, other gradients ...
    others = [
        dict(designs={k: v[:6] for k, v in designs.items()}),
        dict(designs={k: v[:5] for k, v in designs.items()}, smoothing=rj.Smoothing(5e-4)),
        dict(designs={k: v[:5] for k, v in designs.items()}, wrt=("gap",)),
    ]
    for other in others:
        with pytest.raises(rj.ParameterError, match="holds the results of a different sweep"):
            rj.sweep(other.pop("designs"), store=store, progress=False, **other)
    # ... and files that are not stores are refused, not overwritten.
    text = tmp_path / "notes.sqlite"
    text.write_text("not a database " * 100)
    with pytest.raises(rj.ParameterError, match="not a recoil-jax store"):
        rj.sweep(designs, store=text)
    assert text.read_text().startswith("not a database")
    other_db = tmp_path / "other.sqlite"
    with sqlite3.connect(other_db) as db:
        db.execute("CREATE TABLE results (x REAL)")
    with pytest.raises(rj.ParameterError, match="SQLite file, but not a recoil-jax store"):
        rj.sweep(designs, store=other_db)
    with pytest.raises(rj.ParameterError, match="is a folder"):
        rj.sweep(designs, store=tmp_path)
    with pytest.raises(rj.ParameterError, match="no such file"):
        rj.campaign_progress(tmp_path / "missing.sqlite")


def test_sweep_command_resumes_from_its_store(tmp_path, capsys):
    store = tmp_path / "grid.sqlite"
    argv = ["sweep", "m=500,1500", "gap=0:0.09:10", "k_r=13000", "--store", str(store)]
    assert main([*argv, "--out", str(tmp_path / "a")]) == 0
    assert "swept 20 designs: 20 solved" in capsys.readouterr().out
    assert main([*argv, "--out", str(tmp_path / "b")]) == 0
    captured = capsys.readouterr()
    assert "swept 20 designs (20 read from the store): 0 solved" in captured.out
    assert "resuming from" in captured.err
    # The files of the resumed run (gradients included) are those of the first.
    assert (tmp_path / "a" / "sweep.csv").read_bytes() == (
        tmp_path / "b" / "sweep.csv"
    ).read_bytes()
    with sqlite3.connect(store) as db:
        names = [row[1] for row in db.execute("PRAGMA table_info(points)")]
    assert "d(peak_anchoring_force_N)/d(gap)" in names and "peak_displacement_m" in names
    assert main(["progress", str(store)]) == 0
    assert "20/20 designs (100.0 %), 2 runs, finished" in capsys.readouterr().out
    assert main(["progress", str(store), "--json"]) == 0
    progress = json.loads(capsys.readouterr().out)
    assert progress["done"] == progress["total"] == 20
    # Another grid with the same store: refused with a message, exit status 2.
    assert main(["sweep", "m=500,1500", "gap=0:0.09:11", "--store", str(store)]) == 2
    assert "holds the results of a different sweep" in capsys.readouterr().err


def test_dask_is_imported_only_when_a_cluster_is_asked_for():
    code = textwrap.dedent(
        """
        import sys
        import recoil_jax, recoil_jax.apps._cli, recoil_jax.apps._cli.sweep
        from recoil_jax.apps._files.cluster import dask_client
        with dask_client(None, None) as client:
            assert client is None
        print(sorted(m for m in sys.modules if m.split(".")[0] in ("dask", "distributed")))
        """
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]"


_KILLED_SWEEP = textwrap.dedent(
    """
    import sys
    import recoil_jax as rj
    from recoil_jax.apps._bench.speed import bench_designs
    designs = bench_designs(8192, seed=1)
    rj.sweep(designs, store=sys.argv[1], chunk_size=256, workers=2, progress=False)
    """
)


def _kill_after_a_new_commit(process, store, done_before: int, moments) -> bool:
    """Wait for `process` to commit past `done_before` (so that the kill lands mid-run),
    then SIGKILL it at a random moment within 0.3 s (`moments`, a seeded `Random`): a
    later moment may find a fast machine past the end. Returns whether it was still
    running when killed."""
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and process.poll() is None:
        try:
            if rj.campaign_progress(store).done > done_before:
                break
        except rj.ParameterError:  # not made yet
            pass
        time.sleep(0.02)
    time.sleep(moments.uniform(0.0, 0.3))
    running = process.poll() is None
    if running:
        os.kill(process.pid, signal.SIGKILL)
    process.wait()
    return running


@pytest.mark.slow
def test_kill_9_at_random_moments_loses_only_the_chunk_in_flight(tmp_path):
    """A real process killed with SIGKILL at random moments, three times, then resumed
    to the end: the store is always readable, each chunk is in it once, and the results
    are an uninterrupted run's, bit for bit."""
    script = tmp_path / "campaign.py"
    script.write_text(_KILLED_SWEEP)
    store = tmp_path / "killed.sqlite"
    seed = random.randrange(1 << 30)
    moments = random.Random(seed)
    done_before = 0
    for kill in range(3):
        process = subprocess.Popen([sys.executable, str(script), str(store)])
        running = _kill_after_a_new_commit(process, store, done_before, moments)
        rows = _rows(store)
        assert rows["integrity"] == "ok", (seed, kill)
        assert rows["points"][0] == rows["points"][1] == rj.campaign_progress(store).done
        done_before = rows["points"][0]
        # A busy machine's last few chunks may all commit within the random moment: the
        # run then ends on its own before the kill.
        assert 0 < done_before <= 8192 and (running or done_before == 8192), (seed, kill)
    namespace: dict = {}
    exec(_KILLED_SWEEP.split("rj.sweep(")[0], namespace)
    designs = namespace["designs"]
    resumed = rj.sweep(designs, store=store, progress=False, chunk_size=256, workers=2)
    plain = rj.sweep(designs, progress=False, chunk_size=256, workers=2)
    _assert_same(resumed, plain)
    assert _rows(store) == {"points": (8192, 8192), "chunks": 32, "integrity": "ok"}
    assert rj.campaign_progress(store).runs == 4


def test_the_guide_reads_a_store_with_pandas(uninterrupted, tmp_path):
    """The snippet of docs/campaigns.md that reads a store with pandas runs on a store."""
    pytest.importorskip("pandas")
    designs, plain = uninterrupted
    store = tmp_path / "map.sqlite"
    rj.sweep(designs, store=store, progress=False, **PLAN)
    guide = (Path(__file__).resolve().parents[1] / "docs" / "campaigns.md").read_text()
    (snippet,) = [b for b in re.findall(r"```python\n(.*?)```", guide, re.S) if "FROM points" in b]
    namespace: dict = {}
    exec(snippet.replace("results/map.sqlite", str(store)), namespace)
    force = plain.peaks["peak_anchoring_force"]
    assert namespace["best"]["peak_anchoring_force_N"] == np.nanmin(force)
    assert len(namespace["points"]) == len(force)


@pytest.mark.slow
def test_bench_store_measures_each_way():
    from recoil_jax.apps._bench.store import format_store_bench, run_store_bench

    result = run_store_bench(2048)
    for way in ("plain", "store", "cluster"):
        assert result[f"{way}_seconds"] > 0 and result[f"{way}_peak_rss_mb"] > 100
    assert result["store_mb"] > 0
    assert "2 Dask workers" in format_store_bench(result)


# Studies: every evaluation committed as it is made; a resumed study reads the stored
# ones back bit for bit and retraces a seeded run's path to the same best design.


SEARCH = dict(
    global_phase=rj.SobolStarts(32, 2), hopping=rj.BasinHopping(hops=2), workers=1, progress=False
)


def _study_rows(path) -> dict:
    with sqlite3.connect(path) as db:
        return {
            "rows": db.execute("SELECT COUNT(*), COUNT(DISTINCT key) FROM evaluations").fetchone(),
            "phases": dict(db.execute("SELECT phase, COUNT(*) FROM evaluations GROUP BY phase")),
            "runs": db.execute("SELECT COUNT(*) FROM runs").fetchone()[0],
            "integrity": db.execute("PRAGMA integrity_check").fetchone()[0],
        }


def test_interrupted_search_resumes_to_the_same_design(tmp_path, monkeypatch, capsys):
    problem = gap_problem()
    plain = rj.search(problem, **SEARCH)
    store = tmp_path / "study.sqlite"
    real = StudyStore.commit
    commits = []

    def stop_after_ten(self, rows):
        if len(commits) == 10:
            raise KeyboardInterrupt  # a Ctrl-C, or a crash, in the local phase
        commits.append(len(rows))
        return real(self, rows)

    monkeypatch.setattr(StudyStore, "commit", stop_after_ten)
    with pytest.raises(KeyboardInterrupt):
        rj.search(problem, store=store, **SEARCH)
    monkeypatch.setattr(StudyStore, "commit", real)
    cut = _study_rows(store)
    assert cut["phases"] == {"sample": 32, "local": 9}  # the samples in one commit
    resumed = rj.search(problem, store=store, **(SEARCH | {"progress": True}))
    captured = capsys.readouterr()
    assert "resuming from" in captured.err
    # The same evaluations (the given start's run and the samples interleave by the
    # threads' timing), to the same best design, bit for bit.
    assert np.array_equal(resumed.best_theta, plain.best_theta)
    assert np.array_equal(resumed.best_objective, plain.best_objective)
    assert np.array_equal(np.sort(resumed.trace["objective"]), np.sort(plain.trace["objective"]))
    for a, b in zip(resumed.runs, plain.runs, strict=True):
        assert np.array_equal(a["theta"], b["theta"]) and a["objective"] == b["objective"]
        assert a["best_objective"] == b["best_objective"]
        assert a["evaluations"] == b["evaluations"] and a["region"] == b["region"]
    assert resumed.agreement() == plain.agreement() and plain.agreement().reached >= 1
    assert resumed.replayed >= 41
    # Each evaluation stored once; the store's best is the search's.
    done = _study_rows(store)
    assert done["rows"][0] == done["rows"][1] and done["runs"] == 2
    assert done["phases"]["sample"] == 32 and done["phases"]["local"] <= plain.gradient_solves
    progress = rj.campaign_progress(store)
    assert progress.kind == "study" and progress.done == done["rows"][0]
    assert progress.best == plain.best_objective[0]
    with sqlite3.connect(store) as db:
        gaps, objectives = zip(*db.execute("SELECT gap, objective FROM evaluations"), strict=True)
    # The rows hold the designs' SI values and exact objectives: re-solved, they agree.
    i = int(np.argmin(np.where(np.isfinite(objectives), objectives, np.inf)))
    again = rj.peaks(
        rj.with_values(problem.params, ("gap",), np.asarray([gaps[i]])),
        problem.smoothing,
        problem.options,
    )
    assert float(again.peak_anchoring_force) == pytest.approx(objectives[i], rel=1e-6)


def test_interrupted_optimise_resumes_to_the_same_bits(tmp_path):
    problem = gap_problem()
    settings = dict(starts=3, steps=16, stopping=rj.Stopping(min_steps=6), progress=False)
    plain = rj.optimise(problem, **settings)
    store = tmp_path / "adam.sqlite"

    def stop_at_seven(step, record):
        if step == 7:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        rj.optimise(problem, store=store, callback=stop_at_seven, **settings)
    with sqlite3.connect(store) as db:
        assert db.execute("SELECT COUNT(*) FROM checkpoints").fetchone()[0] == 7
    resumed = rj.optimise(problem, store=store, **settings)
    assert len(resumed.history["objective"]) == len(plain.history["objective"])
    for name, history in plain.history.items():
        assert np.array_equal(resumed.history[name], history, equal_nan=True), name
    assert np.array_equal(resumed.best_theta, plain.best_theta)
    for a, b in zip(resumed.runs, plain.runs, strict=True):
        assert (a["iterations"], a["converged"]) == (b["iterations"], b["converged"])
    # One row per run per step it took (the trace's "step" evaluations; a stopped run is
    # evaluated again where it stopped); the store's best is the result's.
    took = plain.trace["phase"] == "step"
    assert _study_rows(store)["rows"][0] == took.sum()
    assert sum(run.iterations for run in plain.runs) == took.sum()
    assert sum(run.evaluations for run in plain.runs) == len(took)
    assert np.array_equal(resumed.trace["objective"], plain.trace["objective"])
    assert rj.campaign_progress(store).best == float(plain.best_objective[0])


def test_foreign_study_stores_are_refused(tmp_path):
    problem = gap_problem()
    store = tmp_path / "seed0.sqlite"
    small = dict(global_phase=rj.SobolStarts(4, 0), use_design=False, progress=False)
    rj.search(problem, store=store, **small)
    before = store.read_bytes()
    with pytest.raises(rj.ParameterError, match="holds the results of a different study"):
        rj.search(problem, store=store, **(small | {"seed": 1}))
    with pytest.raises(rj.ParameterError, match="holds the results of a different study"):
        rj.optimise(problem, store=store, starts=1, steps=1, progress=False)
    with pytest.raises(rj.ParameterError, match="holds the results of a study"):
        rj.sweep({"gap": [0.05]}, store=store, progress=False)
    swept = tmp_path / "sweep.sqlite"
    rj.sweep({"gap": [0.05]}, store=swept, progress=False)
    with pytest.raises(rj.ParameterError, match="holds the results of a sweep"):
        rj.search(problem, store=swept, **small)
    # Another optax schedule is another study, though its functions are not data.
    adam = tmp_path / "adam.sqlite"
    rj.optimise(problem, store=adam, starts=1, steps=2, progress=False)
    with pytest.raises(rj.ParameterError, match="a different study"):
        rj.optimise(
            problem, store=adam, starts=1, steps=2, progress=False,
            optimiser=rj.default_optimiser(0.05, 2),
        )  # fmt: skip
    assert store.read_bytes()[:100] == before[:100]


_SMALL_STUDY = study_text(
    description="The gap for the lowest peak anchoring force, stroke within 0.15 m.",
    optimiser='method = "search"\nsamples = 32\nstarts = 2\nhops = 2',
    **SMALL_STUDY,
)


def test_optimise_command_resumes_from_its_store(tmp_path, capsys):
    study = tmp_path / "gap.toml"
    study.write_text(_SMALL_STUDY)
    store = tmp_path / "gap.sqlite"
    argv = ["optimise", str(study), "--store", str(store)]
    assert main([*argv, "--out", str(tmp_path / "a")]) == 0
    assert main([*argv, "--out", str(tmp_path / "b")]) == 0
    captured = capsys.readouterr()
    assert "resuming from" in captured.err
    first, second = (json.loads((tmp_path / d / "result.json").read_text()) for d in "ab")
    assert first["best"] == second["best"] and first["objective"] == second["objective"]
    assert second["optimiser"]["replayed"] >= first["optimiser"]["gradient_solves"]
    # Each summary says how many starts reached its best design.
    agreement = [r["optimiser"]["agreement"] for r in (first, second)]
    assert agreement[0] == agreement[1] and agreement[0]["reached"] >= 1
    # Where every local run ended (starts and hops), best first, the same when resumed;
    # no run beats the best design (a sample may have found it).
    groups = first["optimiser"]["where_starts_ended"]
    assert groups == second["optimiser"]["where_starts_ended"]
    assert sum(g["count"] for g in groups) == len(first["optimiser"]["local_runs"]) == 5
    ends = [g["objective"] for g in groups if g["objective"] is not None]
    assert ends == sorted(ends) and ends[0] >= first["objective"] * (1 - 1e-6)
    assert captured.out.count(rj.Agreement(**agreement[0]).line()) == 2
    assert main(["progress", str(store)]) == 0
    line = capsys.readouterr().out
    # The store's best is the gradient solve's; result.json's the design re-solved.
    best = float(
        re.search(r"study: \d+ evaluations, 2 runs, best feasible objective (\S+)", line)[1]
    )
    assert best == pytest.approx(first["objective"], rel=1e-6)
    # The guide's pandas snippet finds the same best in the store.
    pd = pytest.importorskip("pandas")
    guide = (Path(__file__).resolve().parents[1] / "docs" / "campaigns.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", guide, re.S)
    (snippet,) = [b for b in blocks if "FROM evaluations" in b]
    namespace: dict = {"sqlite3": sqlite3, "pd": pd}
    exec(snippet.replace("results/tuned.sqlite", str(store)), namespace)
    assert float(namespace["best"].objective) == pytest.approx(best, rel=1e-6)
    # A cluster spreads a global phase: an optax study has none.
    adam = tmp_path / "adam.toml"
    adam.write_text(_SMALL_STUDY.split("[optimiser]")[0] + '[optimiser]\nmethod = "adam"\n')
    assert main(["optimise", str(adam), "--workers", "2"]) == 2
    assert "has none" in capsys.readouterr().err


_KILLED_STUDY = textwrap.dedent(
    """
    import sys
    from recoil_jax.apps._studies.study import run_study
    run_study(sys.argv[1], sys.argv[2], progress=False, store=sys.argv[3])
    """
)


@pytest.mark.slow
def test_kill_9_of_a_study_at_random_moments_resumes_to_the_same_design(tmp_path):
    """A study killed with SIGKILL at random moments of its optimiser, three times, then
    resumed to the end: the store is always readable with each evaluation once, and the
    best design is an uninterrupted run's, bit for bit."""
    from recoil_jax.apps._studies.study import run_study

    study = tmp_path / "gap.toml"
    # About 600 gradient solves: a few seconds of local runs, killed within the first.
    study.write_text(_SMALL_STUDY.replace("starts = 2\nhops = 2", "starts = 8\nhops = 48"))
    script = tmp_path / "study.py"
    script.write_text(_KILLED_STUDY)
    store = tmp_path / "killed.sqlite"
    seed = random.randrange(1 << 30)
    moments = random.Random(seed)
    done_before = 0
    for kill in range(3):
        process = subprocess.Popen(
            [sys.executable, str(script), str(study), str(tmp_path / "out"), str(store)]
        )
        running = _kill_after_a_new_commit(process, store, done_before, moments)
        assert running, f"the study ended before kill {kill} (seed {seed})"
        rows = _study_rows(store)
        assert rows["integrity"] == "ok", (seed, kill)
        assert rows["rows"][0] == rows["rows"][1] == rj.campaign_progress(store).done
        assert rows["rows"][0] > done_before, (seed, kill)
        done_before = rows["rows"][0]
    resumed = run_study(study, tmp_path / "resumed", progress=False, store=store)
    plain = run_study(study, tmp_path / "plain", progress=False)
    assert resumed["best"] == plain["best"] and resumed["objective"] == plain["objective"]
    assert _study_rows(store)["runs"] == 4 and _study_rows(store)["integrity"] == "ok"


#: Stores' names of the library's local methods as 5fbba6d wrote them, when every method
#: carried the minimax's settings too (`fingerprint` of the method).
NAMES_BEFORE = {
    "SLSQP()": ("d9e99039d12ad515991be2474bed32f135859149a9401a75f05d10ab0f45c93b"),
    "SLSQP(schedule=(1.0, 1/3, 1/9, 1/30), maxiter=7)": (
        "39076a511ceda4ad31d984eafb1b92c4eaaa3a36d259a49c491368cbe8248b03"
    ),
    "EpigraphMinimax()": ("0f35a65f27e8abbb1f57d2c9c9257ac8c2a2629f5f626c86aa42c14376ab2e88"),
    "EpigraphMinimax(maxiter=9, peak_times=32)": (
        "10df5daa10b7d7e6ef6a5c4a2bbd7cd88e745955259cf1331bdb401b747b9cd8"
    ),
    "TrustRegionLP()": ("8939b241d1df7c96b02bca7815a2cd87584bd165b70a5f4c0545e6dd7b8f32a1"),
    "TrustRegionLP(radius=0.05, stall_solves=None)": (
        "14cbc35613820c7f584e25baca583df9f19951e501d5b3cb58d71a3af44e7745"
    ),
    "OptaxLocal()": ("0834f01fb1e808b3e779ff0e6e183d4576e4bc2d5ca6f216d3225e467fb3a9ff"),
    "OptaxLocal(maxiter=45, update_every=10)": (
        "8473f087682590935cff910faeb7f5b66d2e03a315362a453d9e2c9b471cebc1"
    ),
}


def test_a_store_names_a_local_method_as_before_its_settings_moved():
    # The minimax's settings live on the minimax methods now; a store still names a
    # search by the layout it had, so every store written before resumes.
    from recoil_jax._campaigns.store import fingerprint
    from recoil_jax._design.local import store_form

    methods = {
        "SLSQP()": rj.SLSQP(),
        "SLSQP(schedule=(1.0, 1/3, 1/9, 1/30), maxiter=7)": rj.SLSQP(
            schedule=(1.0, 1 / 3, 1 / 9, 1 / 30), maxiter=7
        ),
        "EpigraphMinimax()": rj.EpigraphMinimax(),
        "EpigraphMinimax(maxiter=9, peak_times=32)": rj.EpigraphMinimax(maxiter=9, peak_times=32),
        "TrustRegionLP()": rj.TrustRegionLP(),
        "TrustRegionLP(radius=0.05, stall_solves=None)": rj.TrustRegionLP(
            radius=0.05, stall_solves=None
        ),
        "OptaxLocal()": rj.OptaxLocal(),
        "OptaxLocal(maxiter=45, update_every=10)": rj.OptaxLocal(maxiter=45, update_every=10),
    }
    assert {name: fingerprint(store_form(m)) for name, m in methods.items()} == NAMES_BEFORE
    # Another setting is another name.
    assert fingerprint(store_form(rj.SLSQP(maxiter=8))) != NAMES_BEFORE["SLSQP()"]


#: The identity each campaign gave its store before issue 53 moved the opening of stores
#: into one opener and the sweep's settings into one object (the version fixed: a new
#: version is a new campaign). A store written before resumes only while these hold.
#: Issue 54 changed them on purpose (the firing envelope's parameter groups, smoothing
#: widths and result columns are in every identity; a design problem's firing conditions
#: and a limit's conditions in the search's and optimise's): these are its. Issue 62
#: changed them again (the counter-recoil buffer's smoothing width, 1e-5 to 1e-6 m, in
#: every identity; the calibration's predictions' metrics); a store made before it is
#: refused by its model revision first
#: (`test_a_store_made_by_an_earlier_revision_of_the_model_is_refused`). Issue 63
#: changed the calibration's (the fit's third stopping test, `lm_gain`, is a field of its
#: settings: a fit stopped by the old tests is another fit). The calibration's is of an
#: arithmetic trace since issue 65 (its sine's digest differed between CPUs). Issue 66
#: changed every one on purpose (the friction's smoothing widths are gone from
#: `Smoothing`); a store made before it is refused by its model revision first. Then
#: the calibration's again: the fits off the jumps (`jump_passes`) are a field of its
#: settings (a fit on every sample is another fit). And the calibration's again: it holds
#: what the calibration was given, not what it computed from it (a noise guessed from a
#: trace, the starts' box coordinates), whose last bits differ between CPUs (the kept
#: store was refused on another machine).
IDENTITIES_BEFORE = {
    "sweep": "7a9305e228472ca89de9ffb1e25b5f8616da476fb90b99550fba540415896136",
    "sweep of a force table": "951f82b9995e45619a8f6ba6cf4decd97ea5283e52f4a4324728dbbd682abf73",
    "grid": "186a5717ac55d6856b1eb42a42cce9bb963e50aa5685ff87868f91cfafd54192",
    "search": "13a8bacf90893e64d1c036ac143514b2f0768419c08ade550211a00bddc0268e",
    "optimise": "54a83ffbbc154f2f3bd33c4d8106746fb51d9be93949f4078dea0947efbf7508",
    "calibration": "dcc17156e50ef7ed1371025a72e0c5bfa051e5930e73d6b7ac3417234a0e984a",
}


def test_campaigns_name_their_stores_as_before(monkeypatch):
    """Each campaign hands its store the identity it did before (the same parts hashed,
    in the same order): stores written before resume. Each run stops as its store is
    made, before anything is solved."""
    import recoil_jax._campaigns.store as store_module

    monkeypatch.setattr(store_module, "__version__", "0.0+identity-test")

    class Opened(Exception):
        pass

    def opened(self, path, **kwargs):
        raise Opened(kwargs)

    for store_class in (store_module.SweepStore, StudyStore, store_module.CalibrationStore):
        monkeypatch.setattr(store_class, "__init__", opened)
    problem = gap_problem()
    designs = [{"gap": 0.01, "k": 28000.0}, {"gap": 0.05, "m": 0.0}]
    table = rj.ForceTable(t=np.array([0.0, 0.01, 0.02]), F=np.array([0.0, 1e5, 0.0]))
    steps = dict(starts=3, steps=16, stopping=rj.Stopping(min_steps=6), progress=False)
    ts = np.linspace(0.0, 0.6, 61)
    # Arithmetic only: a sine's last bits differ between CPUs (numpy's vector kernels).
    trace = rjx.Trace.of(ts, x_M=ts * (0.6 - ts) / 9.0)
    calibration = rj.Calibration([rjx.Experiment(trace)], fit={"k": (1e4, 1e5), "gap": (0.0, 0.1)})
    campaigns = {
        "sweep": lambda: rj.sweep(designs, store="s", wrt=("gap",), workers=2),
        "sweep of a force table": lambda: rj.sweep_to_store(
            designs, "s", force_table=table, chunk_size=512, lanes=64, sort_by_gap=False, workers=1
        ),
        "grid": lambda: rj.sweep_grid(
            {"gap": [0.01, 0.03], "k": [2e4, 3e4, 4e4]}, {"m": 1200.0}, store="s", workers=1
        ),
        "search": lambda: rj.search(problem, store="s", **SEARCH),
        "optimise": lambda: rj.optimise(problem, store="s", **steps),
        "calibration": lambda: rj.calibrate(calibration, starts=3, progress=False, store="s"),
    }
    identities = {}
    for name, run in campaigns.items():
        with pytest.raises(Opened) as made:
            run()
        identities[name] = made.value.args[0]["identity"]
        assert "created" in made.value.args[0]["description"], name
    assert identities == IDENTITIES_BEFORE


def test_a_calibration_store_holds_what_it_was_given_not_what_it_computed(monkeypatch):
    """A calibration's identity holds a noise the user gave, and not one it guessed from
    the trace; and its starts' count and seed, or their values, and not their box
    coordinates. What it computes has last bits that differ between CPUs (the kept store,
    made on one machine, was refused on another), and the inputs it comes from are in the
    identity."""
    import recoil_jax._calibration.calibrate as calibrate_module
    import recoil_jax._calibration.layout as layout_module
    import recoil_jax._campaigns.store as store_module

    class Opened(Exception):
        pass

    def opened(self, path, **kwargs):
        raise Opened(kwargs["identity"])

    monkeypatch.setattr(store_module.CalibrationStore, "__init__", opened)
    ts = np.linspace(0.0, 0.6, 61)
    trace = rjx.Trace.of(ts, x_M=ts * (0.6 - ts) / 9.0, F_AN=2e5 * ts * (0.6 - ts))

    def identity(starts=1, seed=0, **sigma) -> str:
        experiment = rjx.Experiment(trace, sigma=sigma)
        calibration = rj.Calibration([experiment], fit={"k": (1e2, 1e6)})  # (log bounds)
        with pytest.raises(Opened) as made:
            rj.calibrate(calibration, starts=starts, seed=seed, progress=False, store="s")
        return made.value.args[0]

    guessed, given = identity(), identity(F_AN=50.0)
    values = identity(starts=np.array([[3e4], [5e5]]))
    # Another CPU's guess and logarithms: the same to a few units in their last place.
    guess, start_points = layout_module._noise_guess, calibrate_module.start_points
    monkeypatch.setattr(layout_module, "_noise_guess", lambda v: guess(v) * (1 + 4e-16))
    monkeypatch.setattr(calibrate_module, "start_points",
                        lambda *a: start_points(*a) * (1 + 4e-16))  # fmt: skip
    assert identity() == guessed
    assert identity(F_AN=50.0) == given != guessed
    assert identity(starts=np.array([[3e4], [5e5]])) == values
    # What the user gives is told apart, to its last bit.
    assert identity(F_AN=50.000000001) != given
    assert len({guessed, identity(starts=2), identity(starts=2, seed=1), values}) == 4


def test_a_campaign_opens_says_it_resumes_and_closes_its_store(tmp_path, capsys):
    """`open_campaign`: None without a path (nothing hashed); one resume notice, as each
    store says what it holds; the store closed whatever happens, its lock let go."""
    from recoil_jax._campaigns.opener import open_campaign
    from recoil_jax._campaigns.store import CalibrationStore

    path = tmp_path / "fit.sqlite"

    def opening(progress=True, identity=lambda: "fit"):
        return open_campaign(
            CalibrationStore, path, label="calibrate", identity=identity, total=3,
            plan={"starts_per_chunk": 8}, description={"fit": ["k"], "starts": 3},
            progress=progress, columns=(),
        )  # fmt: skip

    def unused() -> str:
        raise AssertionError("hashed without a store")

    with open_campaign(
        CalibrationStore, None, label="calibrate", identity=unused, total=3, plan={},
        description={}, progress=True, columns=(),
    ) as nothing:  # fmt: skip
        assert nothing is None
    with opening() as store:
        store.commit("fit:0", 3, {"x": np.arange(3.0)}, 0.1)
    assert capsys.readouterr().err == ""  # nothing stored before
    with pytest.raises(KeyboardInterrupt), opening() as store:
        raise KeyboardInterrupt
    assert capsys.readouterr().err == f"calibrate: resuming from {path}: 3 fits already done\n"
    with opening(progress=False) as store:  # the lock was let go: it opens again
        assert np.array_equal(store.stored("fit:0")["x"], np.arange(3.0))
        store.close()  # closed before it is left: closing again does nothing
    assert capsys.readouterr().err == ""
    made = json.loads(read_meta(sqlite3.connect(path))["description"])
    assert list(made) == ["fit", "starts", "created"]
    with pytest.raises(rj.ParameterError, match="holds the results of a different"):
        opening(identity=lambda: "another").__enter__()


def test_a_resumed_sweep_says_its_plan_its_dropped_chunks_then_what_it_has(
    tmp_path, monkeypatch, capsys
):
    """The sweep's notices in their order: the plan kept from the store, the chunks
    dropped as incomplete, then the one resume notice (the solves stubbed)."""
    import recoil_jax._sweeps.dispatch as dispatch_module

    solved = []

    def stub(batch, t1, count, *args):
        solved.append(count)
        if len(solved) == 3:
            raise KeyboardInterrupt
        peaks = {key: np.ones(count) for key in rjx.PEAK_FIELDS.values()}
        return peaks | {"status_code": np.zeros(count, np.int32)}, 0.01

    monkeypatch.setattr(dispatch_module, "_solve_chunk", stub)
    designs = {"gap": np.linspace(0.0, 0.1, 40)}
    store = tmp_path / "notes.sqlite"
    with pytest.raises(KeyboardInterrupt):
        rj.sweep_to_store(designs, store, chunk_size=8, workers=1, progress=False)
    with sqlite3.connect(store) as db:
        db.execute("DELETE FROM points WHERE chunk = '0:8' AND point % 2 = 0")
    capsys.readouterr()
    done = rj.sweep_to_store(designs, store, chunk_size=16, workers=1, progress=None)
    assert (done.designs, done.stored) == (40, 8)
    lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith("sweep:")]
    plan = "{'workers': 1, 'lanes': 128, 'chunk_size': %d, 'sort_by_gap': True}"
    assert lines == [
        f"sweep: resuming with the plan of the run that made {store} ({plan % 8}), not "
        f"{plan % 16}: the same chunks give the same results",
        f"sweep: {store} had chunks with rows missing or doubled (8 designs dropped): "
        "those chunks are solved again",
        f"sweep: resuming from {store}: 8 of 40 designs (1 chunk) already done",
    ]


def test_stored_outputs_are_unpacked_one_header_at_a_time(monkeypatch):
    """`np.load` parses headers with `ast`, which CPython 3.11 does not make safe across
    threads (python/cpython#106905; a resumed study's local runs replay from threads):
    `unpack` must never run two loads at once, and must return the arrays it packed."""
    import threading

    import recoil_jax._campaigns.store as store_module

    real_load, inside, most = np.load, [0], [0]
    count_lock = threading.Lock()

    def slow_load(*args, **kwargs):
        with count_lock:
            inside[0] += 1
            most[0] = max(most[0], inside[0])
        time.sleep(0.002)  # long enough for the other threads to try to enter
        try:
            return real_load(*args, **kwargs)
        finally:
            with count_lock:
                inside[0] -= 1

    monkeypatch.setattr(store_module.np, "load", slow_load)
    arrays = {"peak": np.float64(1.5), "gradient": np.arange(6.0).reshape(2, 3)}
    blob = store_module.pack(arrays)
    results: list = []

    def work():
        for _ in range(20):
            results.append(store_module.unpack(blob))

    threads = [threading.Thread(target=work) for _ in range(6)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert len(results) == 120 and most[0] == 1
    for out in results:
        assert set(out) == set(arrays)
        np.testing.assert_array_equal(out["gradient"], arrays["gradient"])


def _stores_script():
    """`tests/data/stores/make_stores.py`, which made the stores read below."""
    path = Path(__file__).parent / "data" / "stores" / "make_stores.py"
    spec = importlib.util.spec_from_file_location("make_stores", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _resume(kind: str, made, store):
    """The campaign `kind` of `make_stores.py` run on `store` (None: without one)."""
    if kind == "sweep":
        return rj.sweep(made.SWEEP, store=store, progress=False, **made.SWEEP_PLAN)
    if kind == "search":
        return rj.search(made.gap_problem(), store=store, progress=False, **made.SEARCH)
    if kind == "optimise":
        return rj.optimise(made.gap_problem(), store=store, progress=False, **made.OPTIMISE)
    return rj.calibrate(made.calibration(), starts=2, store=store, progress=False)


def _assert_json_close(a, b, path="result"):
    """`a` and `b` hold the same keys, lengths, strings and flags, and numbers equal to
    1e-9 relative (1e-12 absolute near zero)."""
    if isinstance(a, dict) and isinstance(b, dict):
        assert a.keys() == b.keys(), path
        for key in a:
            _assert_json_close(a[key], b[key], f"{path}.{key}")
    elif isinstance(a, list) and isinstance(b, list):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _assert_json_close(x, y, f"{path}[{i}]")
    elif isinstance(a, float | int) and not isinstance(a, bool) and isinstance(b, float | int):
        assert a == pytest.approx(b, rel=1e-9, abs=1e-12), path
    else:
        assert a == b, path


def _rows_kept(store) -> int:
    """How many results a store holds: a sweep's designs, a study's evaluations, a
    calibration's parts."""
    with sqlite3.connect(store) as db:
        tables = {row[0] for row in db.execute("SELECT name FROM sqlite_master")}
        table = next(t for t in ("points", "evaluations", "chunks") if t in tables)
        return db.execute(f"SELECT COUNT(*) FROM {table}").fetchone()[0]


@pytest.mark.parametrize(
    "kind",
    [
        "sweep",
        pytest.param("search", marks=pytest.mark.slow),
        pytest.param("optimise", marks=pytest.mark.slow),
        pytest.param("calibration", marks=pytest.mark.slow),
    ],
)
def test_stores_made_before_the_redraw_resume(kind, tmp_path):
    """Stores made at 66a0bae, before issue 53 moved the package's modules and classes
    (`tests/data/stores/make_stores.py`; made again for issue 54, which changed every
    identity on purpose, and the calibration's for issue 63, whose new stopping test
    changed every calibration's, and again at d4bfe79 from a trace kept as numbers, and
    all four for the model's revision 3, issue 66, which changed every identity, and the
    calibration's for the fits off the jumps, which changed its identity, and again when
    its identity held what it was given instead of what it computed (a noise guessed from
    the trace, the starts' box coordinates), whose last bits differ between CPUs), are
    taken as the same campaigns: everything is read back, nothing is solved again, and
    the result is a fresh run's, bit for bit (a calibration's to 1e-9: see below)."""
    made = _stores_script()
    store = tmp_path / f"{kind}.sqlite"
    shutil.copy(Path(__file__).parent / "data" / "stores" / f"{kind}.sqlite", store)
    kept = _rows_kept(store)
    assert kept > 0
    resumed, fresh = _resume(kind, made, store), _resume(kind, made, None)
    assert _rows_kept(store) == kept  # nothing new: every result was read back
    if kind == "sweep":
        assert resumed.stored == len(resumed) == 8
        _assert_same(resumed, fresh)
    elif kind == "calibration":
        # The store was made on another CPU, and a fit's last bits may differ between CPUs
        # (its trace does not: `calibration_trace.csv` holds it as numbers).
        _assert_json_close(resumed.to_json() | {"seconds": 0}, fresh.to_json() | {"seconds": 0})
    else:
        assert np.array_equal(resumed.best_theta, fresh.best_theta)
        assert np.array_equal(resumed.best_objective, fresh.best_objective)
        # The same evaluations (a resumed search's trace lists the stored ones first).
        objectives = [np.sort(r.trace["objective"]) for r in (resumed, fresh)]
        assert np.array_equal(*objectives)


@pytest.mark.parametrize("use", ["resume", "load"])
@pytest.mark.parametrize(
    ("revision", "changed"),
    [(1, "the firing envelope's revision 2"), (2, "the barrel's stick on its rails is a mode")],
)
def test_a_store_made_by_an_earlier_revision_of_the_model_is_refused(
    use, revision, changed, tmp_path
):
    """A store made by an earlier revision of the model's semantics (1: before the firing
    envelope's revision 2, the rest, the whole gun's margin, the pull and the mount load;
    2: before the stick was a mode) is refused with one line saying why, what changed
    since and what to do, before anything is solved: never resumed, nor read back on the
    old semantics."""
    made = _stores_script()
    store = tmp_path / "sweep.sqlite"
    fixture = Path(__file__).parent / "data" / "stores" / f"sweep_revision{revision}.sqlite"
    shutil.copy(fixture, store)
    kept = store.read_bytes()
    with pytest.raises(rj.ParameterError) as refused:
        if use == "resume":
            rj.sweep(made.SWEEP, store=store, progress=False, **made.SWEEP_PLAN)
        else:
            rj.load_sweep(store)
    message = str(refused.value)
    assert "\n" not in message
    assert f"revision {revision} of the model" in message and "this is revision 3" in message
    assert changed in message and "the barrel's stick on its rails is a mode" in message
    assert "new store path" in message
    assert store.read_bytes() == kept  # untouched


def test_a_store_made_by_a_newer_revision_of_the_model_says_so(tmp_path):
    """A store a newer recoil-jax made (a later revision of the model) is refused naming
    that, not as an older one."""
    made = _stores_script()
    store = tmp_path / "sweep.sqlite"
    shutil.copy(Path(__file__).parent / "data" / "stores" / "sweep.sqlite", store)
    with sqlite3.connect(store) as db:
        db.execute("UPDATE meta SET value = '9' WHERE key = 'model'")
    with pytest.raises(rj.ParameterError, match="revision 9 of the model, by a newer recoil-jax"):
        rj.sweep(made.SWEEP, store=store, progress=False, **made.SWEEP_PLAN)
