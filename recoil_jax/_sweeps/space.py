"""The normalised box a search or a fit moves in (`SearchSpace`): the tuned values `θ` of
coordinates `z ∈ [0, 1]^P`, linear or logarithmic (`log_coordinates`). Shared by the
optimisation layer and calibration, so that calibration stands on it without the
optimiser."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["SearchSpace", "log_coordinates"]


def log_coordinates(lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Which parameters move in log coordinates: bounds positive and at least a factor
    1000 (three decades) apart."""
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    return (lower > 0) & (upper >= 1000 * np.where(lower > 0, lower, 1.0))


class SearchSpace(eqx.Module):
    """`θ(z)`: the tuned values (SI units, shape `(P,)`) of normalised coordinates
    `z ∈ [0, 1]^P`, linear between the bounds or logarithmic (`log_coordinates`).

    `search` moves in `z`; `optimise` in `u` with `z = sigmoid(u)` (no bound is ever
    clipped, so no gradient is zeroed); the tuning benchmark gives every method `z`.
    """

    lower: jax.Array
    upper: jax.Array
    log: jax.Array

    @classmethod
    def of(cls, problem) -> SearchSpace:
        """The space of a design problem's tuned parameters within `problem.box()` (any
        object with a `box()` giving `(lower, upper)`: the space knows nothing else of
        the problem, so that calibration stands on it without the optimiser)."""
        lower, upper = problem.box()
        log = log_coordinates(lower, upper)
        return cls(jnp.asarray(lower), jnp.asarray(upper), jnp.asarray(log))

    def theta(self, z):
        """`z (..., P)` → `θ (..., P)` (JAX; differentiable)."""
        lo = jnp.where(self.log, jnp.log(jnp.where(self.log, self.lower, 1.0)), self.lower)
        hi = jnp.where(self.log, jnp.log(jnp.where(self.log, self.upper, 1.0)), self.upper)
        x = lo + (hi - lo) * z
        return jnp.where(self.log, jnp.exp(jnp.where(self.log, x, 0.0)), x)

    def z(self, theta) -> np.ndarray:
        """`θ (..., P)` → `z (..., P)` (NumPy), θ clipped to the bounds first."""
        lower, upper, log = (np.asarray(a) for a in (self.lower, self.upper, self.log))
        theta = np.clip(np.asarray(theta, float), lower, upper)
        safe = np.where(log, 1.0, upper - lower)
        linear = (theta - lower) / safe
        logged = np.log(np.where(log, theta, 1.0) / np.where(log, lower, 1.0)) / np.log(
            np.where(log, upper / np.where(log, lower, 1.0), np.e)
        )
        return np.clip(np.where(log, logged, linear), 0.0, 1.0)
