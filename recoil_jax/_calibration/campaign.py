"""A calibration kept in a store, so that a killed one resumes to the same result: the
store's opening, with its identity and resume notice (`open_store`), and its parts, each
read or computed and committed (`stored_part`).

A store is identified by `campaign_identity("calibration", data, static, z0, profiles)`:
a digest of pytrees whose structure names their classes (`layout._Data`,
`least_squares._Static`) and their fields' order, which must not change, or every store
made before the change is refused.
"""

from __future__ import annotations

import os
import sys
import time

import numpy as np

from .._campaigns.store import CalibrationStore, campaign_identity
from .layout import CalibrationData, Layout
from .least_squares import FitSettings
from .profiles import PROFILE_POINTS
from .spec import Calibration

__all__ = ["STARTS_PER_CHUNK", "open_store", "stored_part"]

#: Starts fitted per part of a calibration kept in a store (each part committed).
STARTS_PER_CHUNK = 8


def open_store(
    path: str | os.PathLike,
    calibration: Calibration,
    layout: Layout,
    data: CalibrationData,
    static: FitSettings,
    z0: np.ndarray,
    profiles: bool,
    progress: bool | None,
) -> CalibrationStore:
    """The calibration's store at `path` (made, or checked to be this calibration's, from
    its arrays, settings, starts `z0 (N, P)` and whether it profiles), after saying on
    stderr how many fits it already holds (unless `progress` is False). The caller
    closes it.

    **Raises:** `ParameterError` for a store that holds another calibration.
    """
    identity = campaign_identity("calibration", data, static, np.asarray(z0), bool(profiles))
    total = len(z0) + (PROFILE_POINTS * len(layout.labels) if profiles else 0)
    description = {
        "fit": list(layout.labels),
        "starts": len(z0),
        "experiments": [e.label for e in calibration.experiments],
        "created": time.strftime("%Y-%m-%d %H:%M:%S"),
    }
    store = CalibrationStore(path, identity=identity, total=total,
                             plan={"starts_per_chunk": STARTS_PER_CHUNK}, columns=(),
                             description=description)  # fmt: skip
    if (done := store.stored_fits()) and progress is not False:
        print(f"calibrate: resuming from {path}: {done} fits already done",
              file=sys.stderr)  # fmt: skip
    return store


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
