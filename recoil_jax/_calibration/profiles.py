"""Profile likelihood (`calibrate(..., profiles=True)`, as lmfit's `conf_interval`): each
fitted value held at points around its optimum while the others are refitted, every
point of every value one lane of one batched program, and the 95 % interval where the
refitted cost's rise crosses the χ² threshold.

The pieces are separate so that a calibration's store can keep the refits as one part:
the points (`profile_grid`), the refits (`refit_profiles`), and the profiles and
intervals they give (`with_profiles`).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from .._model.programs import structure_jit
from .layout import CalibrationData, Layout
from .least_squares import FitSettings, fit_off_the_jumps
from .result import CalibrationResult

__all__ = ["PROFILE_POINTS", "ProfileGrid", "profile_grid", "refit_profiles", "with_profiles"]

#: Where a profile is evaluated, in standard errors from the optimum (each side).
_PROFILE_STEPS = (1.0, 1.5, 2.0, 2.5, 3.0, 4.0)
#: The points of each value's profile (refits), on both sides.
PROFILE_POINTS = 2 * len(_PROFILE_STEPS)
#: The 95 % threshold of a profile's Δχ² (one degree of freedom): `chi2.ppf(0.95, 1)`,
#: the square of the normal's 97.5 % point (a literal: importing scipy.stats takes 0.4 s
#: of the command line's start; a test checks it against scipy).
_PROFILE_THRESHOLD = 1.959963984540054**2


@dataclasses.dataclass(frozen=True)
class ProfileGrid:
    """The profile points of a fit's P values, `m` (`points`) per value: the optimum
    `theta (P,)` (SI units), which value each refit holds, `held (P·m, P)` (value i's
    points are rows `i·m` to `(i + 1)·m`), and where, `held_theta (P·m, P)` (the others
    at the optimum)."""

    theta: np.ndarray
    held: np.ndarray
    held_theta: np.ndarray
    points: int


def profile_grid(result: CalibrationResult, layout: Layout) -> ProfileGrid:
    """Each fitted value's profile points: `_PROFILE_STEPS` standard errors each side of
    the optimum where the data determine it, else evenly across its bounds (box
    coordinates, clipped to the box)."""
    space = layout.space
    theta = np.asarray([result.values[label] for label in layout.labels])
    z = space.z(theta)
    P = len(theta)
    # The standard error in box coordinates, from the slope there (not by moving θ, which
    # the bounds would clip at a value on its bound).
    dtheta_dz = np.asarray(jax.jvp(space.theta, (jnp.asarray(z),), (jnp.ones(P),))[1])
    grids = []
    for i, label in enumerate(layout.labels):
        f = result.fitted[label]
        if f.identifiable and f.stderr:
            sd_z = max(f.stderr / max(abs(dtheta_dz[i]), 1e-300), 1e-12)
            steps = np.asarray(_PROFILE_STEPS)
            points = np.concatenate([z[i] - sd_z * steps[::-1], z[i] + sd_z * steps])
        else:  # not determined: across the bounds
            points = np.linspace(0.0, 1.0, PROFILE_POINTS)
        grids.append(np.clip(points, 0.0, 1.0))
    m = len(grids[0])
    held = np.zeros((P * m, P), dtype=bool)
    held_z = np.tile(z, (P * m, 1))
    for i, points in enumerate(grids):
        held[i * m : (i + 1) * m, i] = True
        held_z[i * m : (i + 1) * m, i] = points
    held_theta = np.asarray(jax.vmap(space.theta)(jnp.asarray(held_z)))
    return ProfileGrid(theta, held, held_theta, m)


@structure_jit
def _profile_program(u0, held, held_theta, data: CalibrationData, static: FitSettings):
    """The least cost with the values `held (B, P)` fixed at `held_theta (B, P)`, the
    others refitted from `u0 (B, P)` (one lane per profile point): `(cost (B,),
    converged (B,))`."""

    def one(u, h, t):
        # Off the jumps, as the fit (`fit_off_the_jumps`); each sample left out counted
        # at the χ² it expects (1), as `with_profiles` counts the optimum's: the points
        # leave out others than it.
        fit = fit_off_the_jumps(u, data, static, h, t)
        return fit.cost + jnp.sum(fit.jumps), fit.converged

    return jax.lax.map(lambda a: one(*a), (u0, held, held_theta))


def refit_profiles(
    grid: ProfileGrid, data: CalibrationData, static: FitSettings, u_best
) -> dict[str, jax.Array]:
    """Every profile point's refit from the optimum `u_best (P,)` (the fit's coordinates),
    under the fit's noise (`data.sigma`), in one program: `{"cost": (P·m,), "converged":
    (P·m,)}`."""
    u0 = jnp.broadcast_to(u_best, grid.held.shape)
    # Under the fit's noise: none estimated again.
    static = dataclasses.replace(static, estimate_noise=False)
    cost, converged = _profile_program(
        u0, jnp.asarray(grid.held), jnp.asarray(grid.held_theta), data, static
    )
    return {"cost": cost, "converged": converged}


def with_profiles(
    result: CalibrationResult, layout: Layout, grid: ProfileGrid, refits
) -> CalibrationResult:
    """`result` with every fitted value's profile (`CalibrationResult.profiles`) and its
    profile-likelihood interval (`Fitted.profile_ci95`, not where the interval is
    withheld), from the `refits` of `grid` (`refit_profiles`' arrays)."""
    theta, held_theta, m = grid.theta, grid.held_theta, grid.points
    cost, converged = refits["cost"], refits["converged"]
    # A point whose refit did not converge is left out (NaN); a rise below 0 (a better
    # optimum than the fit's) is kept, and shows in the profile.
    # The optimum's cost as the points' (`_profile_program`): each sample it left out
    # beside a jump at 1.
    best = result.chi2 + sum(e.get("left_out", 0) for e in result.experiments)
    delta = np.where(np.asarray(converged), (np.asarray(cost) - best) / result.reduced_chi2,
                     np.nan)  # fmt: skip
    profiles, fitted = {}, dict(result.fitted)
    for i, label in enumerate(layout.labels):
        values = np.concatenate([held_theta[i * m : (i + 1) * m, i], [theta[i]]])
        rise = np.concatenate([delta[i * m : (i + 1) * m], [0.0]])
        order = np.argsort(values, kind="stable")
        values, rise = values[order], rise[order]
        profiles[label] = {"values": values, "delta_chi2": rise}
        if not fitted[label].withheld:  # the profile's interval assumes the model too
            fitted[label] = dataclasses.replace(
                fitted[label], profile_ci95=_crossings(values, rise, theta[i])
            )
    return dataclasses.replace(result, fitted=fitted, profiles=profiles)


def _crossings(values, rise, best) -> tuple[float | None, float | None]:
    """Where the profile `rise` first reaches the 95 % threshold on each side of `best`
    (linear between points), or None where it stays below it to the last point."""
    sides = []
    for lower in (True, False):
        side = values < best if lower else values > best
        side &= np.isfinite(rise)
        xs, ys = values[side], rise[side]
        if lower:  # nearest first
            xs, ys = xs[::-1], ys[::-1]
        x0, y0, found = best, 0.0, None
        for x, y in zip(xs, ys, strict=True):
            if y >= _PROFILE_THRESHOLD:
                found = x0 + (x - x0) * (_PROFILE_THRESHOLD - y0) / max(y - y0, 1e-300)
                break
            x0, y0 = x, y
        sides.append(None if found is None else float(found))
    return sides[0], sides[1]
