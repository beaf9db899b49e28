"""Sweeps on a Dask cluster (`client=`, `sweep --workers N`): the results of a run in
one process, bit for bit, also when a worker is killed mid-sweep; each chunk is stored
once."""

import json
import os
import signal
import sqlite3
import threading
import time

import numpy as np
import pytest

import recoil_jax as rj
import recoil_jax.extend as rjx
from recoil_jax.apps import main
from recoil_jax.apps._bench.speed import bench_designs

distributed = pytest.importorskip("distributed")

pytestmark = pytest.mark.slow  # each test starts a cluster of worker processes

#: 4096 designs in 16 chunks of 256, each solved in two parts.
PLAN = dict(chunk_size=256, workers=2)


@pytest.fixture(scope="module")
def plain():
    designs = bench_designs(4096, seed=3)
    return designs, rj.sweep(designs, progress=False, **PLAN)


@pytest.fixture
def client():
    with (
        distributed.LocalCluster(
            n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0"
        ) as cluster,
        distributed.Client(cluster) as client,
    ):
        yield client


def _assert_same(a: rj.SweepResult, b: rj.SweepResult):
    for field in rjx.PEAK_FIELDS:
        assert np.array_equal(a.peaks[field], b.peaks[field], equal_nan=True), field
    assert np.array_equal(rjx.status_codes(a.status), rjx.status_codes(b.status))


def _chunks(store) -> tuple[int, int, int]:
    with sqlite3.connect(store) as db:
        chunks = db.execute("SELECT COUNT(*) FROM chunks").fetchone()[0]
        points, distinct = db.execute(
            "SELECT COUNT(*), COUNT(DISTINCT point) FROM points"
        ).fetchone()
    return chunks, points, distinct


def test_two_workers_give_the_single_process_results(plain, client, tmp_path):
    designs, expected = plain
    store = tmp_path / "cluster.sqlite"
    result = rj.sweep(designs, client=client, store=store, progress=False, **PLAN)
    _assert_same(result, expected)
    assert _chunks(store) == (16, 4096, 4096)
    # Both workers took chunks.
    assert len(client.run(os.getpid)) == 2


def test_a_worker_killed_mid_sweep_loses_nothing(plain, client, tmp_path):
    designs, expected = plain
    store = tmp_path / "killed.sqlite"
    pids = list(client.run(os.getpid).values())
    killed = []

    def kill_one_worker():
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline:
            try:
                if rj.campaign_progress(store).done > 0:  # mid-sweep
                    os.kill(pids[0], signal.SIGKILL)
                    killed.append(pids[0])
                    return
            except rj.ParameterError:  # the store is not made yet
                pass
            time.sleep(0.02)

    killer = threading.Thread(target=kill_one_worker)
    killer.start()
    result = rj.sweep(designs, client=client, store=store, progress=False, **PLAN)
    killer.join()
    assert killed, "the sweep ended before a worker could be killed"
    assert rj.campaign_progress(store).done == 4096
    _assert_same(result, expected)
    assert _chunks(store) == (16, 4096, 4096)  # each chunk once
    assert pids[0] not in client.run(os.getpid).values()  # it was really killed


def test_sweep_command_on_a_cluster(client, capsys):
    argv = ["sweep", "m=500,1500", "gap=0:0.09:10", "k_r=13000", "--json"]
    assert main(argv) == 0
    alone = capsys.readouterr().out
    assert main([*argv, "--workers", "2"]) == 0
    captured = capsys.readouterr()
    assert captured.out == alone
    assert "local cluster of 2 worker processes" in captured.err
    # A running cluster, by its scheduler's address (as one started by dask-jobqueue).
    assert main([*argv, "--scheduler", client.scheduler.address]) == 0
    captured = capsys.readouterr()
    assert captured.out == alone
    assert f"2 workers at {client.scheduler.address}" in captured.err
    assert main([*argv, "--workers", "0"]) == 2
    assert "--workers 0 is invalid" in capsys.readouterr().err
    assert main([*argv, "--workers", "2", "--scheduler", "tcp://127.0.0.1:1"]) == 2
    assert "not both" in capsys.readouterr().err


def test_a_force_of_ones_own_is_solved_on_the_workers(client):
    """A force defined in a notebook or a script's `__main__`, which Dask sends to the
    workers by value, gives there the results of one process, bit for bit; before its
    class was made whole where it landed, the workers solved every design as if its
    spring were 0."""
    import sys
    import types

    from conftest import SCRIPT_FORCE

    # Defined in a `__main__` of its own, as a notebook's cell defines it (its string
    # annotations read there); sent once this process's `__main__` is back, in which
    # Dask cannot find it by name, so that it goes by value.
    notebook = types.ModuleType("__main__")
    with pytest.MonkeyPatch.context() as patch:
        patch.setitem(sys.modules, "__main__", notebook)
        exec(SCRIPT_FORCE, notebook.__dict__)
    force = notebook.MainSpring
    try:
        assert force.__module__ == "__main__"
        designs = [dict(k_r=20000.0, main_spring_stiffness=k) for k in (0.0, 2500.0, 7500.0)]
        alone = rj.sweep(designs, progress=False, chunk_size=2)
        spread = rj.sweep(designs, progress=False, chunk_size=2, client=client)
        _assert_same(spread, alone)
        forces = alone.peaks["peak_anchoring_force"]
        assert forces[0] < forces[1] < forces[2]  # the spring counts
    finally:
        rjx.forget_part(force)


def test_a_force_the_workers_cannot_import_is_named_not_waited_for(client, tmp_path):
    """A force from a module on this process's path but not on the workers' (a package
    not installed on the cluster) is refused with the module and the workers named,
    before a chunk is sent: a worker that cannot unpickle a task left the sweep waiting
    for ever."""
    import sys
    import threading

    from conftest import SCRIPT_FORCE

    (tmp_path / "spring_here_only.py").write_text(SCRIPT_FORCE)
    outcome = {}

    def run():
        try:
            rj.sweep(designs, progress=False, chunk_size=2, client=client)
        except ImportError as error:
            outcome["error"] = error

    with pytest.MonkeyPatch.context() as patch:
        patch.syspath_prepend(str(tmp_path))  # here, after the workers started
        import spring_here_only  # type: ignore[import-not-found]

        force = spring_here_only.MainSpring
        try:
            designs = [dict(k_r=20000.0, main_spring_stiffness=k) for k in (0.0, 2500.0)]
            thread = threading.Thread(target=run, daemon=True)
            thread.start()
            thread.join(120.0)
            assert not thread.is_alive(), "the sweep waited for workers that cannot import"
        finally:
            rjx.forget_part(force)
            sys.modules.pop("spring_here_only", None)
    error = outcome["error"]
    assert error.name == "spring_here_only"
    message = str(error)
    assert "'spring_here_only'" in message and "MainSpring" in message
    assert all(address in message for address in client.nthreads())


def test_a_search_and_the_tuning_baselines_on_a_cluster(client, tmp_path, capsys):
    """The optimiser's global phase and the benchmark's batched baselines go through the
    cluster: the same samples, the same best design, the same penalised objectives."""
    from recoil_jax.apps._bench.tuning import _Evaluator

    problem = rj.DesignProblem(
        params=rj.params_from_values(m=1500.0, gap=0.05),
        objective=rj.Objective({"peak_anchoring_force": 1.0}),
        tune=("gap", "k_r"),
        bounds={"gap": (0.0, 0.12)},
        constraints=(rj.Constraint("max_stroke", upper=0.15),),
    )
    settings = dict(global_phase=rj.SobolStarts(64, 1), progress=False)
    alone = rj.search(problem, **settings)
    spread = rj.search(problem, client=client, **settings)
    for name in ("objective", "violation", "ok"):
        assert np.array_equal(spread.samples[name], alone.samples[name]), name
    assert np.array_equal(spread.best_theta, alone.best_theta)
    z = np.random.default_rng(0).uniform(size=(40, 2))
    assert np.array_equal(
        _Evaluator(problem, 60.0, client).batch(z), _Evaluator(problem, 60.0).batch(z)
    )
    # The command line: a study's global phase on a running cluster, by its address.
    study = tmp_path / "gap.toml"
    study.write_text(
        'description = "gap"\n[design]\nm = 1500.0\n[tune]\ngap = [0.0, 0.12]\n'
        "[objective]\npeak_anchoring_force = 1.0\n"
        '[optimiser]\nmethod = "search"\nsamples = 32\nstarts = 1\n'
    )
    argv = ["optimise", str(study), "--json"]
    assert main([*argv, "--out", str(tmp_path / "a")]) == 0
    first = capsys.readouterr().out
    assert main([*argv, "--out", str(tmp_path / "b"), "--scheduler", client.scheduler.address]) == 0
    captured = capsys.readouterr()
    assert f"2 workers at {client.scheduler.address}" in captured.err
    import json

    assert (
        json.loads(captured.out.splitlines()[-1])["best"]
        == json.loads(first.splitlines()[-1])["best"]
    )


def test_a_sensitivity_analysis_on_a_cluster(client, tmp_path, capsys):
    """`sensitivity --scheduler`: its designs go through the sweep's chunks on the
    cluster; the indices equal those of a run in this process."""
    (tmp_path / "s.toml").write_text(
        "[design]\nm = 1500.0\n[ranges]\nk = { relative = 0.1 }\ngap = [0.05, 0.07]\n"
        '[metrics]\nnames = ["peak_anchoring_force"]\n[method]\nname = "sobol"\nsamples = 256\n'
    )
    argv = ["sensitivity", str(tmp_path / "s.toml"), "--out", str(tmp_path / "o"), "--json"]
    assert main(argv) == 0
    alone = json.loads(capsys.readouterr().out)
    assert main([*argv, "--scheduler", client.scheduler.address]) == 0
    captured = capsys.readouterr()
    assert json.loads(captured.out)["indices"] == alone["indices"]
    assert f"2 workers at {client.scheduler.address}" in captured.err
