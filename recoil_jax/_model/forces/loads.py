"""The breech force (`docs/model.md`, *Load*): a round's impulse, pulse or force table,
the rounds of a burst, where a step must end for them, the velocity jumps of impulse
rounds, and the momentum still to come."""

from __future__ import annotations

import jax.numpy as jnp

from ..._model.params import Load, RecoilParams

__all__ = [
    "breech_force",
    "is_impulse",
    "load_jump",
    "load_stops",
    "remaining_impulse",
    "restart_step",
]


def breech_force(t, params: RecoilParams):
    """The breech force `F_b(t)` (N) of the design's rounds, fired at `j · fire_interval`:
    a gamma pulse of momentum `M v0` each (`pulse_time > 0`), or the force table; zero
    for impulse loads (their momentum enters as velocity jumps) and before each round."""
    load = params.load
    assert load is not None
    delay = t - jnp.arange(load.shots) * load.fire_interval
    if load.table is not None:
        table = load.table
        return jnp.sum(jnp.interp(delay, table.t, table.F, left=0.0, right=0.0))
    tp = load.pulse_time
    pulse = tp > 0
    safe_tp = jnp.where(pulse, tp, 1.0)
    started = delay >= 0
    u = jnp.where(started, delay, 0.0) / safe_tp
    momentum = params.barrel.M * params.barrel.v0
    each = jnp.where(started, momentum / safe_tp * u * jnp.exp(-u), 0.0)
    return jnp.where(pulse, jnp.sum(each), 0.0)


def is_impulse(load: Load):
    """Whether each round is an impulse (a velocity jump of `v0`): no table and
    `pulse_time == 0`."""
    return jnp.logical_and(load.table is None, load.pulse_time <= 0)


def load_stops(params: RecoilParams):
    """The times (s) at which a step must end, shape `(n,)`, or None (no load): the
    firing of every later round, and with a force table each of its points for every
    round, so that no short pulse or kink is stepped over."""
    load = params.load
    if load is None:
        return None
    firing = jnp.arange(load.shots) * jnp.asarray(load.fire_interval, dtype=float)
    if load.table is None:
        return firing[1:] if load.shots > 1 else None
    knots = (firing[:, None] + jnp.asarray(load.table.t)[None, :]).reshape(-1)
    return jnp.concatenate([firing[1:], knots])


def load_jump(t, y, params: RecoilParams):
    """The state right after a stop at time `t`: at a later round's firing under an
    impulse load the barrel's velocity jumps by `v0`; otherwise unchanged."""
    load = params.load
    if load is None or load.shots == 1:
        return y
    firing = jnp.arange(1, load.shots) * jnp.asarray(load.fire_interval, dtype=float)
    fired = jnp.any(firing == t) & is_impulse(load)
    return y.at[1].add(jnp.where(fired, params.barrel.v0, 0.0))


def restart_step(params: RecoilParams):
    """The longest first step at the start and after a stop (s): a fraction of the
    pulse's rise time, so that the step-size controller cannot step over a pulse; no
    limit (inf) for impulse and table loads (a table's points are stops)."""
    load = params.load
    if load is None or load.table is not None:
        return jnp.inf
    return jnp.where(load.pulse_time > 0, 0.25 * load.pulse_time, jnp.inf)


def remaining_impulse(t, params: RecoilParams):
    """An upper bound on the breech's momentum still to come after time `t` (N·s):
    `∫_t^∞ |F_b|` plus the impulses of later rounds (0 without a load)."""
    load = params.load
    if load is None:
        return 0.0
    firing = jnp.arange(load.shots) * jnp.asarray(load.fire_interval, dtype=float)
    delay = t - firing
    momentum = params.barrel.M * params.barrel.v0
    table = load.table
    if table is not None:
        times, force = jnp.asarray(table.t), jnp.abs(jnp.asarray(table.F))
        # |F| is convex on each linear piece: the trapezoid of |F| bounds its integral.
        pieces = 0.5 * (force[1:] + force[:-1]) * jnp.diff(times)
        after = jnp.concatenate([jnp.cumsum(pieces[::-1])[::-1], jnp.zeros(1)])

        def rest(d):
            i = jnp.clip(jnp.searchsorted(times, d, side="right") - 1, 0, times.shape[0] - 2)
            here = jnp.abs(jnp.interp(d, times, jnp.asarray(table.F)))
            partial = 0.5 * (here + force[i + 1]) * (times[i + 1] - d) + after[i + 1]
            return jnp.where(d <= times[0], after[0], jnp.where(d >= times[-1], 0.0, partial))

        return jnp.sum(jnp.vectorize(rest)(delay))
    tp = load.pulse_time
    pulse = tp > 0
    u = jnp.maximum(delay, 0.0) / jnp.where(pulse, tp, 1.0)
    pulses = jnp.sum(momentum * (1.0 + u) * jnp.exp(-u))
    impulses = momentum * jnp.sum(firing > t)
    return jnp.where(pulse, pulses, impulses)
