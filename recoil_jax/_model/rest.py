"""The gun at rest in battery before the shot (`docs/model.md`, revision 2): the static
balance of the mechanism against the recoiling parts' axial weight, its root by
bisection, and the one Newton step that carries its derivatives."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .._model.forces.rails import absorber_sag, axial_weight
from .._model.forces.system import forces
from .._model.params import RecoilParams
from .._model.settings import Smoothing

__all__ = ["rest_root", "static_anchoring", "static_rest"]


def static_anchoring(x_M, params: RecoilParams, smoothing: Smoothing, width_contact):
    """`F_AN(x_M, v = 0)` (N) with friction aside: what connects the barrel to the mount
    at rest at `x_M`, the absorber hanging at its rest on it (as the model's forces have
    it, smoothing included, so that the model's rest is its own exactly)."""
    x_M = jnp.asarray(x_M, dtype=float)
    zero = jnp.zeros_like(x_M)
    y = jnp.stack([x_M, zero, x_M + absorber_sag(params), zero])
    f = forces(y, params, smoothing, width_contact)
    return f.anchoring - (0.0 if f.friction is None else f.friction)


def _rest_balance(x_M, params: RecoilParams, smoothing: Smoothing, width_contact):
    """`F_AN(x_M, 0) − (M + m) g sin θ` (N): the static rest's balance, zero at `x_r`."""
    return static_anchoring(x_M, params, smoothing, width_contact) - axial_weight(params)


#: Bisections of the rest's bracket (each halves it): 2^-64 of a bracket of millimetres.
_REST_BISECTIONS = 64


def rest_root(params: RecoilParams, smoothing: Smoothing, width_contact):
    """The static rest `x_r` (m, <= 0) by bisection, its value only (no derivatives flow
    through it: `static_rest` polishes it with one Newton step that carries them).

    `x_r` is the root of `F_AN(x, 0) = (M + m) g sin θ` (`static_anchoring`,
    `axial_weight`) nearest battery with `x <= 0`: with a battery stop and a preload
    above the axial weight the barrel presses into the stop, where the stop's force takes
    the difference. `F_AN(x, 0)` rises with `x`, so the root is unique and the bracket
    `[−2 ((F_AN(0, 0) − W) / k_s)^(1/n_s) − 2 w_s, 0]` holds it. 0 where there is no root
    (no stop, or a preload that cannot hold the weight): the barrel starts at battery and
    may sag (`docs/model.md`)."""
    if params.battery_stop is None:
        return 0.0
    params, smoothing, width_contact = jax.lax.stop_gradient((params, smoothing, width_contact))

    def balance(x):
        return _rest_balance(x, params, smoothing, width_contact)

    stop = params.battery_stop
    assert stop is not None  # (its static structure, unchanged by stop_gradient)
    excess = balance(jnp.zeros(()))
    stiff = stop.stop_stiffness > 0
    held = stiff & (excess > 0)
    safe_stiffness = jnp.where(stiff, stop.stop_stiffness, 1.0)
    depth = 2.0 * (
        (jnp.maximum(excess, 0.0) / safe_stiffness) ** (1.0 / stop.stop_exponent)
        + smoothing.stop_width
    )

    def bisect(_, bracket):
        low, high = bracket
        middle = 0.5 * (low + high)
        above = balance(middle) > 0
        return jnp.where(above, low, middle), jnp.where(above, middle, high)

    low, high = jax.lax.fori_loop(0, _REST_BISECTIONS, bisect, (-depth, jnp.zeros_like(depth)))
    return jnp.where(held, 0.5 * (low + high), 0.0)


def static_rest(params: RecoilParams, smoothing: Smoothing, width_contact, guess):
    """The static rest `x_r` (m) from its root `guess` (`rest_root`): one Newton step on
    the balance, `x_r = x̃ − h(x̃) / h'(x̃)`, whose value is the root's and whose
    derivatives are the implicit function's, `dx_r/dθ = −(∂h/∂θ) / (∂h/∂x)`, in every
    parameter. 0 (no derivatives) where there is no root, and for a design without a
    battery stop (the paper's model, unchanged)."""
    if params.battery_stop is None:
        return jnp.zeros(())
    guess = jax.lax.stop_gradient(jnp.asarray(guess, dtype=float))
    value, slope = jax.jvp(
        lambda x: _rest_balance(x, params, smoothing, width_contact),
        (guess,),
        (jnp.ones_like(guess),),
    )
    held = (guess < 0) & (slope > 0)
    return jnp.where(held, guess - value / jnp.where(held, slope, 1.0), 0.0)
