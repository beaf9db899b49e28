"""The smoothed switches the forces are built from: `max(0, x)` and the step, smoothed
over a band and exact outside it, and powers with finite gradients at 0."""

from __future__ import annotations

import jax.numpy as jnp

__all__ = ["onset_ramp", "positive_power", "smooth_relu", "smooth_step"]


def smooth_relu(x, width):
    """`max(0, x)` smoothed over `|x| < width` by a C² quartic; exact outside the band.

    `r(x) = w · (s + 1)³ (3 − s) / 16` with `s = x / w` for `|s| < 1`. It matches value,
    slope and curvature of `max(0, x)` at `s = ±1`, is convex (so `r >= max(0, x)`),
    monotone, and satisfies `r(x) − r(−x) = x`. `width = 0` gives the exact `max(0, x)`
    (same code path; double-`where` keeps gradients finite).
    """
    width = jnp.asarray(width)
    smooth = width > 0
    safe_width = jnp.where(smooth, width, 1.0)
    s = jnp.clip(x / safe_width, -1.0, 1.0)
    inside = safe_width * (s + 1.0) ** 3 * (3.0 - s) / 16.0
    in_band = smooth & (jnp.abs(x) < width)
    return jnp.where(in_band, inside, jnp.maximum(x, 0.0))


def smooth_step(x, width):
    """The step `x > 0` (0 or 1) smoothed over `|x| < width` into the slope of
    `smooth_relu`, `(s + 1)² (2 − s) / 4` with `s = x / w` (C¹, monotone); exact outside
    the band, and the exact step for `width = 0`."""
    width = jnp.asarray(width)
    smooth = width > 0
    safe_width = jnp.where(smooth, width, 1.0)
    s = jnp.clip(x / safe_width, -1.0, 1.0)
    inside = (s + 1.0) ** 2 * (2.0 - s) / 4.0
    in_band = smooth & (jnp.abs(x) < width)
    return jnp.where(in_band, inside, jnp.where(x > 0, 1.0, 0.0))


def onset_ramp(x, width):
    """`max(0, x)` smoothed over `0 < x < width` only, by the C¹ cubic
    `x² (2w − x) / w²`: exactly 0 for `x <= 0` and exactly `x` for `x >= width` (so a
    barrel at rest in battery, `x_M = 0`, feels no stop force at all); the exact ramp for
    `width = 0`. Below `max(0, x)` inside the band."""
    width = jnp.asarray(width)
    smooth = width > 0
    safe_width = jnp.where(smooth, width, 1.0)
    inside = smooth & (x > 0) & (x < width)
    safe_x = jnp.where(inside, x, 0.0)
    return jnp.where(
        inside, safe_x**2 * (2.0 * safe_width - safe_x) / safe_width**2, jnp.maximum(x, 0.0)
    )


def positive_power(x, exponent):
    """`x ** exponent` for `x >= 0`, 0 for `x <= 0`, with finite gradients everywhere
    (also with respect to `exponent` at `x = 0`, where the naive form gives NaN)."""
    positive = x > 0
    safe_x = jnp.where(positive, x, 1.0)
    return jnp.where(positive, safe_x**exponent, 0.0)
