"""Sweeps on a Dask cluster (`client=`, `sweep --workers N`): the results of a run in
one process, bit for bit, also when a worker is killed mid-sweep; each chunk is stored
once."""

import os
import signal
import sqlite3
import threading
import time

import numpy as np
import pytest

import recoil_jax as rj
from recoil_jax.apps import main
from recoil_jax.apps._bench import bench_designs

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
    for field in rj.PEAK_FIELDS:
        assert np.array_equal(a.peaks[field], b.peaks[field], equal_nan=True), field
    assert np.array_equal(rj.status_codes(a.status), rj.status_codes(b.status))


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
