"""Cartesian grids of designs: `Grid`, whose columns are made a chunk at a time (so that a
streamed grid's memory does not grow with it), and `grid`, which makes them all."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from .._model.registry import ParameterError
from .batches import is_knot
from .memory import check_memory

__all__ = ["Grid", "grid"]


class Grid:
    """The cartesian product of `axes` (name -> values; C order, as `itertools.product`
    gives it) plus `fixed` values (name -> value), without its columns made: `sweep` and
    `sweep_to_store` make them a chunk at a time, so a streamed grid's memory does not
    grow with it (`docs/campaigns.md`); `grid` makes them all.

    - `shape`: the axes' lengths; `len(grid)`: the number of designs;
    - `columns(rows)`: `name -> (len(rows),)` values of the designs at flat indices `rows`
      (a slice or an integer array; None: every design).

    **Raises:** `ParameterError` for an axis without values, or a name both swept and
    fixed. The values are checked by `sweep`, before anything is compiled."""

    def __init__(
        self, axes: Mapping[str, Sequence[float]], fixed: Mapping[str, float] | None = None
    ):
        self.axes = {n: np.asarray(v, dtype=float).reshape(-1) for n, v in axes.items()}
        self.fixed = {n: float(v) for n, v in (fixed or {}).items()}
        for name, values in self.axes.items():
            if not len(values):
                raise ParameterError(f"the grid's axis {name} has no values")
            if name in self.fixed:
                raise ParameterError(f"{name} is both swept and fixed")
        if not self.axes and not self.fixed:
            raise ParameterError("a grid needs at least one axis or fixed value")
        self.shape = tuple(len(a) for a in self.axes.values())

    def __len__(self) -> int:
        return math.prod(self.shape)

    @property
    def names(self) -> list[str]:
        return [*self.axes, *self.fixed]

    def columns(self, rows: slice | np.ndarray | None = None) -> dict[str, np.ndarray]:
        n = len(self)
        if rows is None:  # every design, by broadcasting (no index arrays)
            shape, d = self.shape, len(self.shape)
            out = {
                name: np.broadcast_to(a.reshape([-1 if i == j else 1 for i in range(d)]), shape)
                .reshape(-1)
                .copy()
                for j, (name, a) in enumerate(self.axes.items())
            }
            count = n
        else:
            flat = np.arange(*rows.indices(n)) if isinstance(rows, slice) else np.asarray(rows)
            index = np.unravel_index(flat, self.shape) if self.shape else ()
            out = {name: a[i] for (name, a), i in zip(self.axes.items(), index, strict=True)}
            count = len(flat)
        return out | {name: np.full(count, value) for name, value in self.fixed.items()}

    def probe(self) -> tuple[Grid, np.ndarray]:
        """The small grid that meets every check that involves more than one value of a
        design (its structure, its load against its end time, the orifice a piston
        needs): each of those axes reduced to its extremes, its zero and its NaN (those
        checks are monotone in each value), an orifice knot's to one value present and
        one absent, every other axis to its first value (its values are checked one by
        one); and the index in this grid of each of its designs (for messages)."""
        reduced, positions = {}, []
        for name, values in self.axes.items():
            kept = [0]  # positions on the axis
            missing = np.isnan(values)
            if is_knot(name):  # its checks ask only whether it is there
                kept += [int(np.argmax(missing))] * bool(missing.any())
                kept += [int(np.argmax(~missing))] * bool(not missing.all())
            elif name in _CROSS_CHECKED:
                if not missing.all():
                    kept = [int(np.nanargmin(values)), int(np.nanargmax(values))]
                kept += [int(np.argmax(values == 0))] * bool(np.any(values == 0))
                kept += [int(np.argmax(missing))] * bool(missing.any())
            # One position per distinct value (NaN once).
            distinct = dict.fromkeys(kept)
            by_value = {("nan" if np.isnan(values[i]) else values[i]): i for i in distinct}
            positions.append(np.array(sorted(by_value.values())))
            reduced[name] = values[positions[-1]]
        probe = Grid(reduced, self.fixed)
        index = np.unravel_index(np.arange(len(probe)), probe.shape) if probe.shape else ()
        where = [kept[i] for kept, i in zip(positions, index, strict=True)]
        flat = np.ravel_multi_index(where, self.shape) if self.shape else np.zeros(1, int)
        return probe, np.asarray(flat).reshape(-1)


#: Names whose checks involve other values of the same design: the structure (`m = 0`,
#: `shots`), the load against the end time, and the piston area against the orifice.
_CROSS_CHECKED = ("m", "shots", "fire_interval", "pulse_time", "t1", "piston_area")


def grid(axes: Mapping[str, Sequence[float]], fixed: Mapping[str, float] | None = None):
    """Cartesian product of `axes` (name -> values), C order, plus `fixed` values:
    returns `(columns, shape)` for `sweep`, made in memory (`Grid` makes them on demand)."""
    designs = Grid(axes, fixed)
    check_memory(
        len(designs), 8 * len(designs.names), "a grid",
        "give a smaller grid, or sweep Grid(axes, fixed) to a store (its columns are made "
        "a chunk at a time)",
    )  # fmt: skip
    return designs.columns(), designs.shape
