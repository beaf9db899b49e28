"""The hydraulic buffer's throttling orifice (`docs/model.md`, *Hydraulic buffer*): its
parameters (`Buffer`), its area profile, its force, and where a step crosses one of its
knots."""

from __future__ import annotations

from typing import Any, ClassVar

import jax.numpy as jnp
import numpy as np

from ..._model.forces.family import Design, Force, registered
from ..._model.forces.smoothing import smooth_relu
from ..._model.parameter_table import PARAMETERS
from ..._model.registry import (
    GROUPS,
    MAX_KNOTS,
    MIN_KNOTS,
    Group,
    ParameterError,
    check_value,
    float_leaf,
    is_concrete,
)

__all__ = ["Buffer", "buffer_coefficient", "buffer_force", "knot_crossing", "orifice_area"]


class Buffer(Force):
    """The hydraulic recoil buffer with a throttling orifice (`docs/model.md`,
    *Hydraulic buffer*): `F_h = ρ A_p³ v|v| / (2 C_d² A_o(x)²)`.

    - `oil_density` ρ (kg/m³), `piston_area` A_p (m², 0: no buffer force),
      `discharge_coefficient` C_d, `orifice_length` x_a (m).
    - `orifice` (m², shape `(K,)`, 2 <= K <= 32): the orifice area at `x = x_a i/(K-1)`,
      linear between knots and constant outside `[0, x_a]`; flat names `orifice_<i>`.
    """

    oil_density: Any = registered("oil_density")
    piston_area: Any = registered("piston_area")
    discharge_coefficient: Any = registered("discharge_coefficient")
    orifice_length: Any = registered("orifice_length")
    orifice: Any = float_leaf(None)

    GROUP: ClassVar[Group] = GROUPS["buffer"]

    def __check_init__(self):
        super().__check_init__()
        if self.orifice is None:
            if is_concrete(self.piston_area) and np.any(np.asarray(self.piston_area) > 0):
                raise ParameterError(
                    "Buffer.piston_area > 0 needs the orifice: give the knots orifice_0 ... "
                    f"orifice_<K-1> ({MIN_KNOTS} <= K <= {MAX_KNOTS}), areas in m^2"
                )
            return
        count = self.knots
        if not MIN_KNOTS <= count <= MAX_KNOTS:
            raise ParameterError(
                f"Buffer.orifice has {count} knots: valid {MIN_KNOTS} to {MAX_KNOTS} "
                "(orifice_0 ... orifice_<K-1>)"
            )
        if is_concrete(self.orifice):
            knots = np.asarray(self.orifice, dtype=np.float64).reshape(-1, count)
            for i in range(count):
                name = f"orifice_{i}"
                check_value("Buffer", name, knots[:, i].squeeze(), PARAMETERS[name])

    @property
    def knots(self) -> int:
        """K, the number of orifice knots (0 without an orifice)."""
        return 0 if self.orifice is None else int(jnp.shape(self.orifice)[-1])

    def anchoring(self, y, t, design: Design, smoothing) -> dict[str, Any]:
        """The orifice's `F_h` (N; none without an orifice), its knots smoothed over
        `knot_width_fraction` of their spacing."""
        if self.orifice is None:
            return {}
        return {"buffer": buffer_force(y[0], y[1], self, smoothing.knot_width_fraction)}

    def potential(self, x_M, design: Design) -> Any:
        """0: the orifice only dissipates."""
        return 0.0

    def anchoring_bound(self, reach, two_energy, design: Design) -> Any:
        """`ρ A_p³ v² / (2 C_d² min A_o²)` with `v² <= 2E*/M`."""
        if self.orifice is None:
            return 0.0
        smallest = jnp.min(jnp.asarray(self.orifice))
        return buffer_coefficient(self) * (two_energy / design.barrel.M) / smallest**2

    def held_change(self, design: Design) -> Any:
        """0: the orifice's force is the barrel's speed's, 0 on a held barrel."""
        return 0.0


def orifice_area(x, buffer: Buffer, width_fraction=0.0):
    """The orifice area `A_o(x)` (m²): linear between the knots at `x_a i/(K−1)`,
    constant outside `[0, x_a]`, written as a sum of ramps at the knots,
    `A_0 + Σ_i (s_i − s_{i−1}) max(0, x − x_i)` with `s_i` the slope after knot `i`. With
    `width_fraction > 0` each ramp is `smooth_relu` over that fraction of the knot
    spacing, so the profile is C² (exact outside the bands)."""
    knots = jnp.asarray(buffer.orifice)
    count = knots.shape[-1]
    spacing = buffer.orifice_length / (count - 1)
    positions = spacing * jnp.arange(count)
    slopes = jnp.diff(knots) / spacing
    turns = jnp.diff(jnp.concatenate([jnp.zeros(1), slopes, jnp.zeros(1)]))
    ramps = smooth_relu(x - positions, width_fraction * spacing)
    return knots[0] + jnp.sum(turns * ramps)


def buffer_coefficient(buffer: Buffer):
    """`ρ A_p³ / (2 C_d²)` (kg·m³): `F_h = coefficient · v|v| / A_o²`."""
    return buffer.oil_density * buffer.piston_area**3 / (2.0 * buffer.discharge_coefficient**2)


def buffer_force(x, v, buffer: Buffer, width_fraction=0.0):
    """The throttling orifice's force `F_h = ρ A_p³ v|v| / (2 C_d² A_o(x)²)` (N); the
    profile's knots smoothed over `width_fraction` of their spacing."""
    area = orifice_area(x, buffer, width_fraction)
    return buffer_coefficient(buffer) * v * jnp.abs(v) / area**2


def knot_crossing(t0, dt, evaluate, y0, y1, params: Design):
    """The time in the step `[t0, t0 + dt]` at which the barrel crosses the orifice knot
    next in its direction of motion, shape `(1,)` (`t0` if it crosses none): where the
    orifice force may have a corner. From the straight line between the step's ends, then
    one Newton step on the dense polynomial `evaluate(t)`."""
    buffer = params.buffer
    assert buffer is not None
    count = jnp.shape(buffer.orifice)[-1]
    spacing = buffer.orifice_length / (count - 1)
    x0, x1 = y0[0], y1[0]
    forward = x1 > x0
    index = jnp.where(forward, jnp.floor(x0 / spacing) + 1.0, jnp.ceil(x0 / spacing) - 1.0)
    knot = jnp.clip(index, 0.0, count - 1.0) * spacing
    moved = x1 - x0
    crossed = (moved != 0) & ((knot - x0) * (knot - x1) < 0)
    fraction = jnp.where(crossed, (knot - x0) / jnp.where(moved != 0, moved, 1.0), 0.0)
    t = t0 + fraction * dt
    state = evaluate(t)
    speed = state[1]
    newton = jnp.where(speed != 0, (knot - state[0]) / jnp.where(speed != 0, speed, 1.0), 0.0)
    t = jnp.clip(t + newton, t0, t0 + dt)
    return jnp.where(crossed, t, t0)[None]
