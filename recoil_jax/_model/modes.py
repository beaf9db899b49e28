"""A discrete mode carried by the stepping loop beside the state: the modes of a hybrid
system (a barrel held by its rails' friction, or sliding on them), and the root of a
mode's guard on a step's dense polynomial, where the loop switches modes."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp

__all__ = ["Modes", "guard_root"]


class Modes(eqx.Module):
    """The modes of a hybrid system, as `PeakLoop`'s configuration (`modes=`): four static
    functions of the loop's `args`.

    - `enter(args, mode) -> args`: the arguments of the vector field (and of every other
      function of the loop) in `mode`, a float scalar carried by the loop.
    - `settle(t, z, args) -> (z, mode)`, with `args` as the loop was given them: the
      mode a state is met in afresh (at t = 0, and after a load's jump), and the state
      projected onto it.
    - `guard(t, z, args) -> g`, with `args` entered: not negative while the mode holds.
      A step whose end has `g < 0` is not kept; the next attempt ends at the root of `g`
      on the step's dense polynomial (`guard_root`), and there the state and mode become
      `switch(t, z, args)` (`args` still in the old mode), as at a load's stop.

    Each switch costs one rejected attempt. A guard that dips below 0 and back within a
    step is not seen (steps are short against the modes' time scales).
    """

    enter: Callable[[Any, Any], Any]
    settle: Callable[[Any, Any, Any], tuple[Any, Any]]
    guard: Callable[[Any, Any, Any], Any]
    switch: Callable[[Any, Any, Any], tuple[Any, Any]]


#: Steps of the Illinois method (regula falsi, the side that stays halved: superlinear
#: on a smooth guard, and the bracket kept) before Newton's steps.
_ILLINOIS = 10
_NEWTON = 2
#: The shortest step to a root, as a fraction of the step that crossed it.
_SHORTEST = 1e-12


def guard_root(guard_at: Callable[[Any], Any], t0, t1):
    """The first time in `(t0, t1]` where `guard_at(t)` (not negative at `t0`, negative
    at `t1`) comes down to 0: the Illinois method on the bracket and Newton's steps
    within it, without derivatives, then one more Newton step unclipped, which carries the
    derivatives of the implicit function `guard_at(t) = 0` (forward mode: its tangent is
    `−(∂g/∂p)/(∂g/∂t)`, its value moved by a rounding). Never before
    `t0 + 1e-12 (t1 − t0)` nor at `t0` itself: a step of zero length has no rate."""
    sg = jax.lax.stop_gradient

    def illinois(_, bracket):
        low, high, g_low, g_high, side = bracket
        span = g_low - g_high  # > 0 while the bracket holds a sign change
        secant = high - g_high * (high - low) / jnp.where(span > 0, span, 1.0)
        inside = (span > 0) & (secant > low) & (secant < high)
        t = jnp.where(inside, secant, 0.5 * (low + high))
        g = guard_at(t)
        holds = g >= 0
        # The end that stays twice running has its value halved (Illinois).
        g_low = jnp.where(holds, g, jnp.where(side < 0, 0.5 * g_low, g_low))
        g_high = jnp.where(holds, jnp.where(side > 0, 0.5 * g_high, g_high), g)
        side = jnp.where(holds, 1, -1).astype(jnp.int32)
        return jnp.where(holds, t, low), jnp.where(holds, high, t), g_low, g_high, side

    start = (sg(t0), sg(t1), sg(guard_at(t0)), sg(guard_at(t1)), jnp.zeros((), jnp.int32))
    low, high, *_ = jax.lax.fori_loop(0, _ILLINOIS, illinois, start)

    def rated(t):
        g, rate = jax.jvp(guard_at, (t,), (jnp.ones_like(t),))
        moving = rate != 0
        return jnp.where(moving, g / jnp.where(moving, rate, 1.0), 0.0)

    def newton(_, t):
        return jnp.clip(t - sg(rated(t)), low, high)

    t = sg(jax.lax.fori_loop(0, _NEWTON, newton, high))
    t = t - rated(t)  # (the tangent flows through `g` only: `t` and the rate are values)
    floor = jnp.maximum(t0 + _SHORTEST * (t1 - t0), jnp.nextafter(sg(t0), jnp.inf))
    return jnp.where(t > floor, t, floor)
