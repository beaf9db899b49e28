"""The gas recuperator (`docs/model.md`, *Gas recuperator*): its gas spring, the preload
on its gas column, the spring's potential, and the ceiling that keeps the barrel off the
column's bottom."""

from __future__ import annotations

import jax.numpy as jnp

from ..._model.params import RecoilParams, Recuperator

__all__ = [
    "BOTTOM",
    "metric_ceilings",
    "preload_force",
    "recuperator_energy",
    "recuperator_force",
]


#: A solve fails (`Status.bottomed_out`) once `x_M` reaches `BOTTOM · L_r`.
BOTTOM = 0.95
# The gas column is held at 0.99 L_r at most, so the force stays finite (the solve has
# failed well before, at BOTTOM).
_HOLD = 0.99


def recuperator_force(x, recuperator: Recuperator):
    """The gas spring `F_g = F_r ((L_r / (L_r − x))^γ − 1)` (N), for `x < 0.99 L_r`."""
    length = recuperator.recuperator_length
    held = jnp.minimum(x, _HOLD * length)
    ratio = length / (length - held)
    return recuperator.recuperator_force * (ratio**recuperator.polytropic_index - 1.0)


def preload_force(x, recuperator: Recuperator):
    """The preload on the gas column, `F_p (L_r / (L_r − x))^γ` (N), for `x < 0.99 L_r`:
    what the gas pushes the barrel into battery with, beyond the recuperator's own
    `F_g`."""
    held = jnp.minimum(x, _HOLD * recuperator.recuperator_length)
    ratio = recuperator.recuperator_length / (recuperator.recuperator_length - held)
    return recuperator.recuperator_preload * ratio**recuperator.polytropic_index


def recuperator_energy(x, recuperator: Recuperator):
    """The gas spring's potential `∫_0^x F_g` (J), >= 0, for `x < 0.99 L_r`:
    `F_r (L_r (r^(γ−1) − 1)/(γ − 1) − x)` with `r = L_r / (L_r − x)` (`L_r ln r − x` at γ = 1)."""
    length = recuperator.recuperator_length
    held = jnp.minimum(x, _HOLD * length)
    log_ratio = jnp.log(length / (length - held))
    g = recuperator.polytropic_index - 1.0
    positive = g > 1e-12
    safe_g = jnp.where(positive, g, 1.0)
    integral = jnp.where(positive, jnp.expm1(g * log_ratio) / safe_g, log_ratio)
    return recuperator.recuperator_force * (length * integral - held)


def metric_ceilings(params: RecoilParams) -> dict[str, jnp.ndarray] | None:
    """Values a tracked metric must stay below, by name, or None: the barrel must not
    bottom the recuperator's gas column (`x_M < 0.95 L_r`). A zero `recuperator_force`
    is no recuperator: there is no gas column to bottom."""
    if params.recuperator is None:
        return None
    recuperator = params.recuperator
    bottom = BOTTOM * recuperator.recuperator_length
    gas = recuperator.recuperator_force > 0
    if params.battery_stop is not None:  # a preload is on the same gas column
        gas = gas | (recuperator.recuperator_preload > 0)
    return {"peak_displacement": jnp.where(gas, bottom, jnp.inf)}
