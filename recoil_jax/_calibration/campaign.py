"""A calibration kept in a store, so that a killed one resumes to the same result: the
store's opening, with its identity and resume notice (`open_store`), and its parts, each
read or computed and committed (`stored_part`).

A store is identified by `campaign_identity("calibration", data, static, *starts,
profiles)`: a digest of pytrees whose structure names their classes (`layout._Data`,
`least_squares._Static`) and their fields' order, which must not change, or every store
made before the change is refused. What the calibration computed from its inputs
enters as those inputs, as its last bits may differ between CPUs (numpy's and LAPACK's
kernels) and a store must resume on another machine: a noise guessed from a trace is
left out (`_as_given`), and the starts are their count and seed or their values
(`_starts_as_given`), not their box coordinates (logarithms on log bounds).
"""

from __future__ import annotations

import os
import time

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._campaigns.opener import open_campaign
from .._campaigns.store import CalibrationStore, campaign_identity
from .continuation import Continuation
from .layout import CalibrationData, Layout
from .least_squares import FitSettings
from .profiles import PROFILE_POINTS
from .spec import Calibration

__all__ = ["STARTS_PER_CHUNK", "open_store", "stored_part"]

#: Starts fitted per part of a calibration kept in a store (each part committed).
STARTS_PER_CHUNK = 8


def open_store(
    path: str | os.PathLike | None,
    calibration: Calibration,
    layout: Layout,
    data: CalibrationData,
    static: FitSettings,
    z0: np.ndarray,
    profiles: bool,
    progress: bool | None,
    continuation: Continuation | None = None,
    *,
    starts,
    seed: int,
):
    """The calibration's store at `path` (None: none), as a context manager
    (`open_campaign`): made, or checked to be this calibration's from its arrays,
    settings, starts (`z0 (N, P)`, made from `calibrate`'s `starts` and `seed`),
    whether it profiles and its `continuation`'s widths
    (in the identity only where there is one, so that a store of a design without one
    keeps its identity); saying on stderr how many fits
    it already holds (unless `progress` is False); closed on leaving.

    **Raises:** `ParameterError` for a store that holds another calibration.
    """
    total = len(z0) + (PROFILE_POINTS * len(layout.labels) if profiles else 0)
    description = {
        "fit": list(layout.labels),
        "starts": len(z0),
        "experiments": [e.label for e in calibration.experiments],
    }
    return open_campaign(
        CalibrationStore, path, label="calibrate",
        identity=lambda: campaign_identity(
            "calibration", _as_given(data), static, *_starts_as_given(starts, seed),
            bool(profiles),
            *(() if continuation is None else continuation.identity()),
        ),
        total=total, plan={"starts_per_chunk": STARTS_PER_CHUNK}, description=description,
        progress=progress, columns=(),
    )  # fmt: skip


def _as_given(data: CalibrationData) -> CalibrationData:
    """`data` with each noise guessed from its trace (not given: `sigma_given` False) set
    to 0: a function of the trace, which the identity holds, whose last bits depend on
    the CPU (a store made on one machine was refused on another)."""
    return eqx.tree_at(lambda d: d.sigma, data, jnp.where(data.sigma_given, data.sigma, 0.0))


def _starts_as_given(starts, seed: int) -> tuple:
    """What a calibration's starts are made from, as `calibrate` was given it: a count and
    the Sobol points' seed (the first start is the design's values, which the data hold),
    or the start values themselves (SI units)."""
    if isinstance(starts, int) and not isinstance(starts, bool):  # (as `start_points`)
        return np.asarray(starts), np.asarray(seed)
    return (np.asarray(starts, dtype=float),)


def stored_part(
    store: CalibrationStore | None, part: str, fits: int, compute
) -> dict[str, np.ndarray]:
    """A part of the calibration: read from the store, or computed (`compute()`, named
    arrays) and committed there with its `fits`; without a store, computed."""
    if store is not None and (arrays := store.stored(part)) is not None:
        return arrays
    started = time.perf_counter()
    arrays = {name: np.asarray(value) for name, value in compute().items()}
    if store is not None:
        store.commit(part, fits, arrays, time.perf_counter() - started)
    return arrays
