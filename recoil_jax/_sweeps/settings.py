"""A sweep's settings, made once by `sweep` and handed down whole (`SweepSettings`), its
plan (how its designs are cut into chunks: `make_plan`), and their defaults."""

from __future__ import annotations

import dataclasses
import os
from typing import Any

from .._model.params import ForceTable
from .._model.registry import ParameterError
from .._model.settings import Smoothing, SolverOptions

__all__ = ["CHUNK_SIZE", "DEFAULT_LANES", "SweepSettings", "make_plan"]

#: The most designs per compiled call of a sweep, unless the caller says.
CHUNK_SIZE = 16384

#: Designs in flight per part. On XLA:CPU a loop step's cost per lane grows once the
#: lanes' working set leaves the core's cache: measured at 16,384 designs (2 cores), 128
#: lanes ran the paper model 1.14x, the hardware designs 1.19x and 4-parameter Jacobians
#: 2.15x faster than 1024 (capped to 512 there), and 64 lanes no faster (docs/speed.md).
DEFAULT_LANES = 128


@dataclasses.dataclass(frozen=True)
class SweepSettings:
    """How a sweep runs, as `sweep` was asked (its defaults filled in), shared by every
    chunk. A campaign's identity is made of some of these fields (`campaign_identity`),
    never of this object.

    - `smoothing`, `options`: the switch widths and the solver's options of every design;
    - `wrt`: the parameters to differentiate with respect to (None: no gradients);
    - `force_table`: the breech force of every design, or None;
    - `plan`: how the designs are cut (`make_plan`); a resumed sweep takes its store's;
    - `devices`: where a chunk's parts run; `client`: a Dask client, or None;
    - `progress`: as given to `sweep` (`False`: nothing printed);
    - `store`: the store's path as given, or None; `in_memory`: the results returned
      (`sweep`), or kept in the store only (`sweep_to_store`)."""

    smoothing: Smoothing
    options: SolverOptions
    wrt: tuple[str, ...] | None
    force_table: ForceTable | None
    plan: dict
    devices: tuple[Any, ...]
    client: Any
    progress: bool | None
    store: str | os.PathLike | None
    in_memory: bool

    def shipped(self) -> SweepSettings:
        """These settings as a Dask task takes them: no client, no devices (a worker
        uses its own)."""
        return dataclasses.replace(self, client=None, devices=())


def make_plan(workers: int, lanes: int, chunk_size: int, sort_by_gap: bool) -> dict:
    """A sweep's plan, as its store keeps it: `workers` parts per chunk, `lanes` designs
    in flight per part, at most `chunk_size` designs per chunk, sorted by gap or not.

    **Raises:** `ParameterError` for `workers < 1`."""
    if workers < 1:
        raise ParameterError(f"workers = {workers} is invalid: valid >= 1")
    return {
        "workers": int(workers),
        "lanes": int(lanes),
        "chunk_size": int(chunk_size),
        "sort_by_gap": bool(sort_by_gap),
    }
