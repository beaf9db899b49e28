"""The one feasibility rule of every optimiser, study, store and benchmark: which designs
count as feasible (`feasible`, `FEASIBILITY_TOLERANCE`), the largest violation, the
closest design, and how a best feasible objective is said. Pure NumPy functions of
arrays, below the design layer, so that a campaign's store and progress judge
feasibility without importing it."""

from __future__ import annotations

import numpy as np

__all__ = [
    "FEASIBILITY_TOLERANCE",
    "best_feasible_note",
    "closest_index",
    "feasible",
    "largest_violation",
]

#: The one feasibility rule of every optimiser, study and benchmark (`feasible`): a
#: design counts as feasible when its solve succeeded, its objective is finite and every
#: normalised limit violation is at most `-FEASIBILITY_TOLERANCE`. The margin keeps the
#: limits held on any re-solve of the design: a plain solve and a forward-sensitivity
#: solve of one design differ by ~5e-7 (relative) in a stroke.
FEASIBILITY_TOLERANCE = 1e-6


def feasible(ok, objective, violations) -> np.ndarray:
    """The one feasibility rule (`FEASIBILITY_TOLERANCE`): `ok (...)` whether each solve
    succeeded, `objective (...)`, `violations (..., C)` (normalised, `<= 0` where held: the design
    layer's `metric_violations`).

    **Returns:** `(...)` booleans (NumPy)."""
    violations = np.asarray(violations, dtype=float)
    held = np.all(violations <= -FEASIBILITY_TOLERANCE, axis=-1)
    return np.asarray(ok, dtype=bool) & np.isfinite(np.asarray(objective, dtype=float)) & held


def largest_violation(violations) -> np.ndarray:
    """`violations (..., C)` → `(...)`: the largest normalised violation of each point
    (`-inf` where there are no limits)."""
    return np.max(np.asarray(violations, dtype=float), axis=-1, initial=-np.inf)


def closest_index(ok, objective, violation) -> int | None:
    """The index of the least violating point (`violation (n,)`, its largest normalised
    violation) among those whose solve succeeded (`ok (n,)`) with a finite objective:
    the first of equals; None if there is none."""
    violation = np.asarray(violation, dtype=float)
    valid = np.asarray(ok, dtype=bool) & np.isfinite(np.asarray(objective, dtype=float))
    valid &= ~np.isnan(violation)
    if not np.any(valid):
        return None
    return int(np.argmin(np.where(valid, violation, np.inf)))


def best_feasible_note(best: float) -> str:
    """How a progress line and a store's summary give the best feasible objective so far."""
    return f"best feasible objective {best:.7g}" if np.isfinite(best) else "none feasible yet"
