"""Parts the optimisers share: the augmented Lagrangian that holds metric limits in a
first-order method (`optimise`'s vmapped steps, `OptaxLocal`'s runs), and the optax
optimiser with a cosine-decayed step both of them use.

The Lagrangian is written once for NumPy and JAX alike (`_xp`): `optimise` updates it
inside its compiled, vmapped step, `OptaxLocal` on the host.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from .._model.registry import ParameterError

__all__ = ["AugmentedLagrangian", "LagrangianState", "cosine_decayed"]


class LagrangianState(NamedTuple):
    """The augmented Lagrangian's state: `multipliers (C,)` and the `penalty` ρ."""

    multipliers: Any
    penalty: Any


def _xp(*arrays):
    """`jax.numpy` for JAX arrays (traced or not), else `numpy`."""
    return jnp if any(isinstance(a, jax.Array) for a in arrays) else np


class AugmentedLagrangian(eqx.Module):
    """Metric limits `g(θ) <= 0` held by an augmented Lagrangian (PHR), in the style of
    an optax transformation (`init`, then `update` after each step):

    `L = f / scale + Σ(max(λ + ρ(g + margin), 0)² − λ²) / 2ρ`; every `update_every`
    steps the multipliers become `max(λ + ρ(g + margin), 0)`, and the penalty ρ is
    multiplied by `penalty_growth` (up to `max_penalty`) while a limit is violated.
    """

    penalty: float = 10.0
    penalty_growth: float = 2.0
    max_penalty: float = 1e4
    update_every: int = 20

    def __check_init__(self):
        if not (self.penalty > 0 and self.penalty_growth >= 1 and self.update_every >= 1):
            raise ParameterError(
                f"AugmentedLagrangian: need penalty > 0, penalty_growth >= 1, update_every >= 1 "
                f"(got {self.penalty}, {self.penalty_growth}, {self.update_every})"
            )

    def init(self, violations) -> LagrangianState:
        """The state before the first step: zero multipliers, the starting penalty."""
        xp = _xp(violations)
        return LagrangianState(xp.zeros_like(violations), self.penalty)

    def value(self, state: LagrangianState, violations):
        """The penalty term `Σ(max(λ + ρg, 0)² − λ²) / 2ρ`."""
        xp = _xp(violations, state.multipliers)
        lam, rho = state.multipliers, state.penalty
        return xp.sum(xp.maximum(lam + rho * violations, 0.0) ** 2 - lam**2) / (2.0 * rho)

    def weights(self, state: LagrangianState, violations, margin: float = 0.0):
        """`max(λ + ρ(g + margin), 0)`: the penalty term's gradient is `weights @ dg`."""
        xp = _xp(violations, state.multipliers)
        shifted = violations if margin == 0 else violations + margin  # (no op added)
        return xp.maximum(state.multipliers + state.penalty * shifted, 0.0)

    def update(
        self, state: LagrangianState, violations, step, margin: float = 0.0, moved: Any = True
    ) -> LagrangianState:
        """The state after step `step` (counted from 0) at violations `g`: at every
        `update_every`-th step that `moved`, the first-order multiplier update, and the
        penalty grown while any limit is violated."""
        xp = _xp(violations, state.multipliers, step)
        at_update = moved & ((step + 1) % self.update_every == 0)
        multipliers = xp.where(
            at_update, self.weights(state, violations, margin), state.multipliers
        )
        violated = xp.any(violations > 0)
        penalty = xp.where(
            at_update & violated,
            xp.minimum(state.penalty * self.penalty_growth, self.max_penalty),
            state.penalty,
        )
        return LagrangianState(multipliers, penalty)


def cosine_decayed(
    name: str, learning_rate: float, steps: int, final_fraction: float
) -> optax.GradientTransformation:
    """`optax.<name>` (e.g. `"adam"`) with its step cosine-decayed from `learning_rate`
    to `final_fraction` of it over `steps`."""
    step = optax.cosine_decay_schedule(learning_rate, steps, alpha=final_fraction)
    transformation = getattr(optax, name)(step)
    if not isinstance(transformation, optax.GradientTransformation):
        raise TypeError(f"optax.{name}(learning_rate) is not an optimiser")
    return transformation
