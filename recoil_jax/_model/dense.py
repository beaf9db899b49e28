"""Locating maxima between solver steps: the cubic Hermite maximum of a step, and the
refinement of a maximum on the solver's own dense polynomial."""

from __future__ import annotations

import jax
import jax.numpy as jnp

__all__ = ["hermite_max", "placeholder_steps", "polish"]


def _safe_divide(numerator, denominator):
    ok = denominator != 0
    return jnp.where(ok, numerator / jnp.where(ok, denominator, 1.0), jnp.inf)


def hermite_max(p0, d0, p1, d1):
    """Max over `s ∈ [0, 1]` of the cubic with values `p0, p1` and slopes `d0, d1` (per
    unit `s`) at the ends; elementwise. Returns `(value, s)`.

    The interior critical points are the roots of the quadratic `p'(s)`, taken in the
    cancellation-free form; double-`where`s keep gradients finite when the discriminant
    or the leading coefficients vanish.
    """
    a = p0
    b = d0
    c = -3.0 * p0 - 2.0 * d0 + 3.0 * p1 - d1
    d = 2.0 * p0 + d0 - 2.0 * p1 + d1

    def cubic(s):
        return a + s * (b + s * (c + s * d))

    # p'(s) = b + 2c s + 3d s².
    disc = c * c - 3.0 * d * b
    real = disc > 0
    root = jnp.sqrt(jnp.where(real, disc, 1.0))
    q = -(c + jnp.where(c >= 0, root, -root))
    s1 = _safe_divide(q, 3.0 * d)
    s2 = _safe_divide(b, q)
    candidates = [jnp.zeros_like(p0), jnp.ones_like(p1)]
    for s in (s1, s2):
        inside = real & (s > 0) & (s < 1)
        candidates.append(jnp.where(inside, s, 1.0))
    s_all = jnp.stack(candidates)
    values = cubic(s_all)
    best = jnp.argmax(values, axis=0)
    value = jnp.take_along_axis(values, best[None], axis=0)[0]
    s_best = jnp.take_along_axis(s_all, best[None], axis=0)[0]
    return value, s_best


def placeholder_steps(t0, y0, count):
    """Placeholder dense info (a zero-length step at t0) for each tracked metric."""
    step = dict(t0=t0, t1=t0, y0=y0, y1=y0, k=jnp.zeros((7, *y0.shape), y0.dtype))
    return jax.tree.map(lambda x: jnp.broadcast_to(x, (count, *jnp.shape(x))), step)


_REFINE_ITERATIONS = 4
_GRID = 16
_ZOOMS = 4


def polish(
    solver, args, vector_fn, best, best_time, best_step, search: bool = False, step_args=None
):
    """Refine each peak on the solver's own dense polynomial (Tsit5's 4th-order
    interpolant of the step holding it) by successive parabolic interpolation, started
    from the Hermite estimate, or with `search` (static) from the best of it and nested
    grids over the step (`_ZOOMS` levels of `_GRID` cells); kept where it raises the
    interpolated value. (The search is for quantities that are strongly nonlinear
    functions of the state, as the orifice force is: there the estimate can sit far from
    the polynomial's maximum.) Maxima at a step's end are solver points and keep their
    value. Derivative-free, so it adds little to compile times under `jacfwd`/`grad`.

    `vector_fn(t, y, args)` is the stacked vector of tracked quantities, shape `(n,)`;
    `best`, `best_time` (`(n,)`) and `best_step` (per quantity, the dense info of the step
    holding its maximum) are the running maxima. `step_args`, if given, are the arguments
    of each quantity's step (a pytree with a leading axis `n`: a hybrid system's modes),
    in place of `args`.

    Returns `(values, times, states)`: the state at each peak (interpolated), shape
    `(n, n_state)`."""

    def polish_one(i, best, best_time, step, args):
        dt = step["t1"] - step["t0"]
        has_step = dt > 0
        safe_dt = jnp.where(has_step, dt, 1.0)
        interp = solver.interpolation_cls(**step)

        def state(t):
            return interp.evaluate(jnp.clip(t, step["t0"], step["t0"] + safe_dt))

        def values(ts):  # one traced copy of the interpolant for several times
            return jax.vmap(lambda t: vector_fn(t, state(t), args)[i])(ts)

        def refine(_, carry):
            # Vertex of the parabola through three points of the interpolant, with a
            # shrinking spacing: converges on the maximum of the solver's polynomial.
            t, h = carry
            a, b, c = values(jnp.stack([t - h, t, t + h]))
            curvature = a - 2.0 * b + c
            concave = curvature < 0
            shift = jnp.where(concave, 0.5 * h * (a - c) / jnp.where(concave, curvature, -1.0), 0.0)
            t = jnp.clip(t + jnp.clip(shift, -h, h), step["t0"], step["t0"] + safe_dt)
            return t, 0.1 * h

        # The best of the Hermite estimate and nested grids over the step, each zooming
        # into the two cells around the last one's best point.
        begin, start = best_time, values(best_time[None])[0]
        low, width = step["t0"], safe_dt
        if not search:
            width = 2e-2 * safe_dt  # the refinement's first spacing: 1 % of the step

        def zoom(_, carry):
            begin, start, low, width = carry
            grid = low + width * jnp.linspace(0.0, 1.0, _GRID + 1)
            sampled = values(grid)
            j = jnp.argmax(jnp.where(jnp.isfinite(sampled), sampled, -jnp.inf))
            found = sampled[j] > start
            begin = jnp.where(found, grid[j], begin)
            start = jnp.where(found, sampled[j], start)
            spacing = width / _GRID
            low = jnp.clip(begin - spacing, step["t0"], step["t0"] + safe_dt - 2.0 * spacing)
            return begin, start, low, 2.0 * spacing

        if search:  # a loop, so that the interpolant and the quantities are traced once
            begin, start, low, width = jax.lax.fori_loop(
                0, _ZOOMS, zoom, (begin, start, low, width)
            )
        t, _ = jax.lax.fori_loop(0, _REFINE_ITERATIONS, refine, (begin, width / 2.0))
        polished = values(t[None])[0]
        interior = has_step & (best_time > step["t0"]) & (best_time < step["t1"])
        better = (polished > start) & jnp.isfinite(polished)
        value_i = jnp.where(interior, jnp.where(better, polished, start), best)
        time_i = jnp.where(interior, jnp.where(better, t, begin), best_time)
        state_i = jnp.where(has_step, state(time_i), step["y0"])
        return value_i, time_i, state_i

    # One traced copy for all metrics (vmap over the metric index), not five.
    indices = jnp.arange(best.shape[0])
    if step_args is None:
        return jax.vmap(polish_one, in_axes=(0, 0, 0, 0, None))(
            indices, best, best_time, best_step, args
        )
    return jax.vmap(polish_one)(indices, best, best_time, best_step, step_args)
