"""Where a calibration's fits start (`start_points`): the given start, then scrambled Sobol
points in the box, or start points given as values; each a little inside the bounds."""

from __future__ import annotations

import math

import numpy as np

from .._model.registry import ParameterError, check_integer
from .layout import Layout

__all__ = ["start_points"]


def _starts(layout: Layout, starts: int, seed: int) -> np.ndarray:
    """`(starts, P)` points in box coordinates: the given start (or the box's middle where
    the design's value lies outside it), then scrambled Sobol points."""
    first = layout.start_z()
    if starts == 1:
        return first[None]
    import scipy.stats  # when used: it takes 0.4 s to import

    sobol = scipy.stats.qmc.Sobol(
        len(layout.labels), scramble=True, rng=np.random.default_rng(seed)
    )
    points = sobol.random_base2(max(0, math.ceil(math.log2(starts - 1))))
    return np.concatenate([first[None], points[: starts - 1]])


#: Starts are moved this far (box coordinates) inside the bounds: on a bound the bounded
#: transform's slope is 0, and the fit could never move the value.
_START_MARGIN = 1e-3


def start_points(layout: Layout, starts, seed: int) -> np.ndarray:
    """`starts` (a count, or `(N, P)` values) as points in box coordinates, a little
    inside the bounds (`_START_MARGIN`).

    **Raises:** `ParameterError` as `_given_starts`.
    """
    return np.clip(_given_starts(layout, starts, seed), _START_MARGIN, 1 - _START_MARGIN)


def _given_starts(layout: Layout, starts, seed: int) -> np.ndarray:
    """`starts` as points `(N, P)` in box coordinates: a count (`_starts`), or values in
    SI units, one row per start in the order of `layout.labels`.

    **Raises:** `ParameterError` for a count below 1, rows of the wrong size, or a value
    outside its bounds (or not finite).
    """
    if isinstance(starts, int) and not isinstance(starts, bool):
        return _starts(layout, check_integer("starts", starts, 1), seed)
    points = np.asarray(starts, dtype=float)
    if points.ndim != 2 or points.shape[1] != len(layout.labels) or len(points) == 0:
        raise ParameterError(
            f"starts: give a count, or one row of {len(layout.labels)} values per start "
            f"({', '.join(layout.labels)})"
        )
    outside = (points < layout.lower) | (points > layout.upper) | ~np.isfinite(points)
    if outside.any():
        row, column = np.argwhere(outside)[0]
        raise ParameterError(
            f"starts[{row}]: {layout.labels[column]} = {points[row, column]:g} is outside "
            f"its bounds [{layout.lower[column]:g}, {layout.upper[column]:g}]"
        )
    return layout.space.z(points)
