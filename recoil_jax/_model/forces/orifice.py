"""The hydraulic buffer's throttling orifice (`docs/model.md`, *Hydraulic buffer*): its
area profile, its force, and where a step crosses one of its knots."""

from __future__ import annotations

import jax.numpy as jnp

from ..._model.forces.smoothing import smooth_relu
from ..._model.params import Buffer, RecoilParams

__all__ = ["buffer_coefficient", "buffer_force", "knot_crossing", "orifice_area"]


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


def knot_crossing(t0, dt, evaluate, y0, y1, params: RecoilParams):
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
