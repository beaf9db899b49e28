"""Dask clusters for the command line: `--workers N` (a local cluster) or `--scheduler
ADDRESS` (a running one). Dask is imported only when one is asked for."""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Iterator
from typing import Any

import recoil_jax as rj

__all__ = ["dask_client"]


@contextlib.contextmanager
def dask_client(workers: int | None, scheduler: str | None) -> Iterator[Any]:
    """A `distributed.Client` for the run: on a `LocalCluster` of `workers` worker
    processes (one thread each; each solves a chunk in parts on every core), or on the
    running cluster at `scheduler`; None when neither is given."""
    if workers is None and scheduler is None:
        yield None
        return
    if workers is not None and scheduler is not None:
        raise rj.ParameterError(
            "give --workers N (a local cluster) or --scheduler ADDRESS, not both"
        )
    if workers is not None and workers < 1:
        raise rj.ParameterError(f"--workers {workers} is invalid: valid is an integer >= 1")
    from distributed import Client, LocalCluster

    if scheduler is not None:
        try:
            client = Client(scheduler, timeout="10s")
        except OSError as error:
            raise rj.ParameterError(
                f"--scheduler {scheduler}: no Dask scheduler answered ({error})"
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
