"""Dask clusters for the command line: `--workers N` (a local cluster) or `--scheduler
ADDRESS` (a running one). Dask is imported only when one is asked for."""

from __future__ import annotations

import contextlib
import os
import re
import sys
from collections.abc import Iterator
from typing import Any

import recoil_jax as rj

__all__ = ["check_cluster", "dask_client"]

#: The address forms of a Dask scheduler: `[protocol://]host:port`.
_ADDRESS = re.compile(r"^((tcp|tls|inproc|ucx|ws|wss)://)?[A-Za-z0-9_.\-\[\]:]+:\d{1,5}$")


def _cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def _check_address(scheduler: str) -> None:
    """A scheduler's address in a form Dask takes (before Dask is asked, which may start a
    cluster of its own for an empty one, or fail in many ways for others)."""
    if not _ADDRESS.match(scheduler):
        raise rj.ParameterError(
            f"--scheduler {scheduler!r} is not a scheduler's address: give "
            "[tcp://]host:port, as the scheduler prints it (e.g. tcp://10.0.0.5:8786)"
        )


def check_cluster(workers: int | None, scheduler: str | None) -> None:
    """Refuse `--workers` and `--scheduler` given together, a worker count below 1 and an
    address that is not one, before any work (`dask_client` checks them too)."""
    if workers is not None and scheduler is not None:
        raise rj.ParameterError(
            "give --workers N (a local cluster) or --scheduler ADDRESS, not both"
        )
    if workers is not None and workers < 1:
        raise rj.ParameterError(f"--workers {workers} is invalid: valid is an integer >= 1")
    if scheduler is not None:
        _check_address(scheduler)


@contextlib.contextmanager
def dask_client(workers: int | None, scheduler: str | None) -> Iterator[Any]:
    """A `distributed.Client` for the run: on a `LocalCluster` of `workers` worker
    processes (one thread each; each solves a chunk in parts on every core), or on the
    running cluster at `scheduler`; None when neither is given."""
    if workers is None and scheduler is None:
        yield None
        return
    check_cluster(workers, scheduler)
    if workers is not None and workers > (cores := _cores()):
        # Each worker solves its chunk on every core already: more processes than cores
        # only add memory (about 0.5 GB each) and contention.
        print(f"recoil-jax: warning: --workers {workers} is more than the {cores} cores "
              f"here; using {cores}", file=sys.stderr)  # fmt: skip
        workers = cores
    from distributed import Client, LocalCluster

    if scheduler is not None:
        try:
            client = Client(scheduler, timeout="10s")
        except (OSError, ValueError, TypeError, RuntimeError) as error:  # incl. TimeoutError
            reason = str(error).splitlines()[0] if str(error) else type(error).__name__
            raise rj.ParameterError(
                f"--scheduler {scheduler}: no Dask scheduler answered ({reason})"
            ) from None
        with client:
            print(
                f"dask: {len(client.scheduler_info()['workers'])} workers at {scheduler}",
                file=sys.stderr,
            )
            yield client
        return
    with (
        LocalCluster(
            n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0"
        ) as cluster,
        Client(cluster) as client,
    ):
        print(f"dask: a local cluster of {workers} worker processes", file=sys.stderr)
        yield client
