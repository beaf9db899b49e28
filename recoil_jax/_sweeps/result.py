"""A sweep's results: in memory (`SweepResult`), or in its store (`StoredSweep`, read
back whole by `load_sweep`)."""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from .._campaigns.sweep_reader import lowest_row, read_sweep_store
from .._model.hazards import hazard_flags
from .._model.metrics import (
    METRICS,
    PEAK_FIELDS,
    gradient_key,
    is_return_field,
    reported_value,
)
from .._model.registry import ParameterError
from .._model.status import Status, status_codes, status_item, status_messages
from .batches import ABSORBER

__all__ = ["StoredSweep", "SweepResult", "load_sweep"]


@dataclasses.dataclass
class SweepResult:
    """Results of a sweep, one entry per design, in input order (NumPy arrays, shape
    `(n,)`).

    - `values`: every parameter of every design by flat name, as requested (`m = 0`: no
      absorber, whose other parameters then have no effect), and `t1` if given per point.
    - `peaks`: the reported `Peaks` fields by name (`peak_anchoring_force`,
      `peak_anchoring_force_time`, ..., `num_steps`). Points whose solve failed hold NaN
      there, and say why in `status`.
    - `status`: a `Status` item of shape `(n,)`; `ok`, `messages()` and `failures()` read
      it.
    - `gradients`: with `wrt`, `{metric: {parameter: (n,) derivative}}`, else None. For the
      simplified model (`m = 0`) the derivatives with respect to absorber parameters are 0.
    - `swept`, `grid_shape`: for a cartesian grid, the swept names and the grid's shape
      (`reshape` the arrays to it, C order over `swept`).
    - `seconds`: the wall time of this run; `stored`: how many of the designs were read
      from the store (a resumed sweep) rather than solved in it.
    """

    values: dict[str, np.ndarray]
    peaks: dict[str, np.ndarray]
    status: Any
    gradients: dict[str, dict[str, np.ndarray]] | None = None
    swept: tuple[str, ...] = ()
    grid_shape: tuple[int, ...] | None = None
    seconds: float = 0.0
    stored: int = 0

    def __len__(self) -> int:
        return int(status_codes(self.status).shape[0])

    @property
    def ok(self) -> np.ndarray:
        return np.asarray(self.status == Status.ok)

    @property
    def codes(self) -> np.ndarray:
        """`(n,)`: each point's integer `Status` code."""
        return status_codes(self.status)

    def messages(self) -> list[str]:
        return status_messages(self.status)

    def failures(self) -> list[tuple[int, str]]:
        """`(index, reason)` of every failed point."""
        messages = self.messages()
        return [(int(i), messages[i]) for i in np.flatnonzero(~self.ok)]

    def parameters(self, index: int) -> dict[str, float]:
        """The parameters of point `index`, as `simulate --json` reports them (no
        absorber parameters for the simplified model, no knots it does not have)."""
        simplified = "m" in self.values and self.values["m"][index] == 0
        return {
            name: float(v[index])
            for name, v in self.values.items()
            if not (simplified and name in ABSORBER and name != "m") and not np.isnan(v[index])
        }

    def hazards(self) -> list[list[str]]:
        """Each point's hazards by name (`rjx.HAZARDS`, named unasked: `docs/model.md`), in
        input order; none where its solve failed."""
        shape = self.ok.shape
        flags = {
            n: np.broadcast_to(f, shape) for n, f in hazard_flags(self.values, self.peaks).items()
        }
        return [[n for n, f in flags.items() if f[i]] if ok else [] for i, ok in enumerate(self.ok)]

    def reported_peaks(self) -> dict[str, np.ndarray]:
        """The peaks' arrays as reported (`records`, `sweep.npz`): a return's metrics NaN
        where the barrel has not returned."""
        away = np.asarray(self.peaks["returned"]) == 0
        return {
            field: np.where(away, np.nan, v) if is_return_field(field) else v
            for field, v in self.peaks.items()
        }

    def records(self, model: str = "smoothed") -> list[dict]:
        """One dict per point, in input order, with the keys of `recoil-jax simulate
        --json` (`PEAK_FIELDS`, `reported_value`): the peaks (None where the solve failed,
        where the design has no such metric, and a return's where the barrel has not
        returned), `status` ("ok" or the reason), `hazards` (their names, `hazards`),
        `model`, `parameters`; with gradients also `gradients` ({metric key: {parameter:
        derivative}})."""
        out = []
        messages = self.messages()
        hazards = self.hazards()
        for i in range(len(self)):
            ok = bool(self.ok[i])
            record: dict[str, Any] = {
                key: None
                if not ok
                else reported_value(field, self.peaks[field][i], self.peaks["returned"][i])
                for field, key in PEAK_FIELDS.items()
            }
            record["status"] = messages[i]
            record["hazards"] = hazards[i]
            record["model"] = model
            record["parameters"] = self.parameters(i)
            if self.gradients:
                record["gradients"] = {
                    METRICS[name].key: {p: float(v[i]) if ok else None for p, v in by.items()}
                    for name, by in self.gradients.items()
                }
            out.append(record)
        return out


class StoredSweep(NamedTuple):
    """What `sweep_to_store` returns: the sweep's results are in its store, not in memory.

    - `path`: the store; `designs`: how many designs the sweep has, `stored` of them read
      from the store (a resumed sweep) rather than solved in this run, `failed` of them
      failed (their peaks NULL, their `status` says why); `seconds`: this run's wall time.
    """

    path: Path
    designs: int
    stored: int
    failed: int
    seconds: float

    def load(self) -> SweepResult:
        """The results as a `SweepResult` (`load_sweep`): every design in memory."""
        return load_sweep(self.path)

    def lowest(self, metric: str = "peak_anchoring_force") -> dict[str, float] | None:
        """The design with the lowest `metric` (a `PEAK_FIELDS` name) of those whose solve
        succeeded, as its store row by column name (None if none did), found by SQLite."""
        if metric not in PEAK_FIELDS:
            raise ParameterError(
                f"lowest: unknown peak {metric!r}; known: {', '.join(PEAK_FIELDS)}"
            )
        return lowest_row(self.path, PEAK_FIELDS[metric], int(status_codes(Status.ok)))


def load_sweep(store: str | os.PathLike) -> SweepResult:
    """The results of a finished sweep, read from its store (`sweep --store`,
    `sweep_to_store`), in input order. `values` holds the parameters the sweep was given
    (not the defaults of the others); `stored` is every design.

    **Raises:** `ParameterError` for a file that is not a sweep's store, or a sweep that
    has not finished (run it again with its store to finish it)."""
    meta, points, data = read_sweep_store(store)
    order = np.argsort(points)
    data = {name: column[order] for name, column in data.items()}
    description = json.loads(meta["description"])
    wrt = description.get("wrt") or []
    gradients = None
    if wrt:
        gradients = {m: {w: data[gradient_key(m, w)] for w in wrt} for m in METRICS}
    return SweepResult(
        values={name: data[name] for name in description["names"]},
        peaks={field: data[key] for field, key in PEAK_FIELDS.items()},
        status=status_item(data["status_code"]),
        gradients=gradients,
        seconds=float(meta["seconds"]),
        stored=len(points),
    )
