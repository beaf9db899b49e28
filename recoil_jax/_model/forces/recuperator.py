"""The gas recuperator (`docs/model.md`, *Gas recuperator*): its parameters
(`Recuperator`), its gas spring, the preload on its gas column, the spring's potential,
and the ceiling that keeps the barrel off the column's bottom."""

from __future__ import annotations

from typing import Any, ClassVar

import jax.numpy as jnp

from ..._model.forces.family import Design, Force, registered
from ..._model.registry import GROUPS, Group

__all__ = [
    "BOTTOM",
    "Recuperator",
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


def metric_ceilings(params: Design) -> dict[str, jnp.ndarray] | None:
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


class Recuperator(Force):
    """The gas recuperator, a nonlinear air spring (`docs/model.md`, *Gas recuperator*):
    `F_g = F_r ((L_r / (L_r - x_M))^γ - 1)`.

    - `recuperator_force` F_r (N), `recuperator_length` L_r (m), `polytropic_index` γ.

    A solve in which `x_M` reaches `0.95 L_r` fails with `Status.bottomed_out`.
    """

    recuperator_force: Any = registered("recuperator_force")
    recuperator_length: Any = registered("recuperator_length")
    polytropic_index: Any = registered("polytropic_index")
    recuperator_preload: Any = registered("recuperator_preload")

    GROUP: ClassVar[Group] = GROUPS["recuperator"]

    def anchoring(self, y, t, design: Design, smoothing) -> dict[str, Any]:
        """The gas spring `F_g` and, with a battery stop (which a preload needs), the
        preload on its gas column `F_p` (N)."""
        shares = {"recuperator": recuperator_force(y[0], self)}
        if design.battery_stop is not None:  # without a stop the preload is 0: left out
            shares["preload"] = preload_force(y[0], self)
        return shares

    def potential(self, x_M, design: Design) -> Any:
        """The gas spring's potential (`recuperator_energy`)."""
        return recuperator_energy(x_M, self)

    def anchoring_bound(self, reach, two_energy, design: Design) -> Any:
        """`F_g` at the reach (it grows with `x_M`)."""
        return jnp.maximum(recuperator_force(reach, self), 0.0)

    def held_change(self, design: Design) -> Any:
        """0: the gas spring's force is the barrel's position's."""
        return 0.0
