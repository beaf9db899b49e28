"""Bounds on what a solve can still reach, which let the peak loop stop early: from the
energy (`future_metric_bounds`, a design without the firing envelope), and from a barrel
held for good by its friction (`held_bounds`)."""

from __future__ import annotations

import jax.numpy as jnp

from .._model.equations import tracked_metrics
from .._model.forces.barrel import Barrel
from .._model.forces.family import Force
from .._model.forces.loads import remaining_impulse
from .._model.forces.rails import GRAVITY, absorber_sag, friction_bound, sin_cos
from .._model.forces.smoothing import positive_power
from .._model.forces.system import forces, net_force
from .._model.params import RecoilParams

__all__ = ["future_metric_bounds", "held_bounds"]


# max over s in [0, 1] of s (1 − s)³ (3 + s) / 16 = 0.021472 (at s = 0.2649), rounded up.
_SWITCH_POWER = 0.0215


def future_metric_bounds(y, args, t, t1) -> dict[str, jnp.ndarray]:
    """Upper bounds, valid from time `t` to the end `t1` (s), on every tracked metric
    (`tracked_metrics`: x_M, F_AN, F_ct, x_m − x_M and x_M − x_m), by metric name, from
    the mechanical energy at state `y`.

    The energy `E = ½M v_M² + ½m v_m² + ½k x_M² + ½k_r (x_M − x_m)² + U(δ) + U_g(x_M)`
    (with the contact potential `U` and the recuperator's `U_g`) never increases by
    itself: the dampers, the buffer, the contact's Hunt–Crossley part and its no-pull
    clamp only dissipate. Two things can add energy:

    - the smoothed damping switch, at most `0.0215 |c_out − c_ret| w²` watts (0.0215
      bounds `|v| (r(v) − max(v, 0)) / w²` over the band), added for the time left;
    - the breech force still to come: with `I` the momentum still to be delivered
      (`remaining_impulse`), `√E` grows by at most `I / √(2M)` (its power is
      `F_b v <= |F_b| √(2E/M)`; an impulse `M v0` raises the kinetic energy's root by
      `v0 √(M/2)`), so `√E* = √(E + switch energy) + I / √(2M)`.

    With `E*` bounding every later energy (Cauchy–Schwarz throughout):

    - `x_M ≤ √(2E*/k)` and `F_AN ≤ √((k + c_out²/M) 2E*) + |c_out − c_ret| 3w/16`, plus
      the buffer's `ρA_p³ (2E*/M) / (2C_d² min A_o²)` and the recuperator's
      `F_g(√(2E*/k))`;
    - `|x_M − x_m| ≤ √(2E*/k_r)`, `δ ≤ ((n_c+1) E*/k_c)^(1/(n_c+1))` and
      `|δ̇| ≤ √(2E* (1/M + 1/m))`, which bound the stroke and `F_ct`;
    - `F_ct = 0` once the wall can no longer reach the absorber.

    Returns `+inf` bounds where the dissipation argument fails (`λ_c w ≥ 1`). The peak
    loop stops once every bound is below its running peak. `args = model_args(params,
    smoothing)`.
    """
    params, smoothing, width_contact = args.params, args.smoothing, args.contact_width
    width_v = smoothing.damping_width
    energy, spread = _energy_ceiling(y, args, t, t1)
    two_energy = 2.0 * energy
    displacement, anchoring = _barrel_bounds(params, two_energy, spread, width_v)
    # Only designs without the envelope stop early (`Structure`): without a mount the
    # tracked margin is the constant −1, and the pull and mount load are the constant 0
    # (`signals`; not reported, `envelope_values`).
    margin = -jnp.ones_like(displacement)
    untracked = {
        "stability_margin": margin,
        "peak_pull_force": jnp.full_like(displacement, -jnp.inf),
    }
    if params.absorber is None:
        zero = jnp.zeros_like(displacement)
        return {
            "peak_displacement": displacement,
            "peak_anchoring_force": anchoring,
            "peak_contact_force": zero,
            "min_stroke": zero,
            "max_stroke": zero,
        } | untracked
    relative_max, penetration, contact_force = _contact_bounds(
        params, energy, two_energy, width_contact, width_v
    )
    # The no-pull clamp dissipates only while r(1) = 1, i.e. λ_c w < 1.
    valid = params.contact.lambda_c * width_v < 1.0
    inf = jnp.full_like(displacement, jnp.inf)
    # x_M − x_m = gap + δ, and `penetration` already respects relative_max.
    bounds = {
        "peak_displacement": displacement,
        "peak_anchoring_force": anchoring,
        "peak_contact_force": contact_force,
        "min_stroke": params.absorber.gap + penetration,
        "max_stroke": relative_max,
    }
    bounds = {name: jnp.where(valid, bound, inf) for name, bound in bounds.items()}
    return bounds | untracked


def held_bounds(y, args, t, t1) -> dict[str, jnp.ndarray]:
    """Bounds on every tracked metric from `t` to `t1`, by name, for a design with the
    firing envelope: finite only once the barrel is held for good, `+inf` before. Held
    for good means all rounds fired and their breech force spent, the barrel held (the
    stick mode, `sticking`: still, to the bit) with the net force on it inside the
    friction's band by more than what the absorber can still change (its energy about
    its rest on the barrel, bounding the coupling's swing, counted from one side to the
    other since it may be at either now; nor can it reach the wall): nothing moves the
    barrel again, so its peaks, return (found, or never) and rest `x_M(t1)` are known
    now. The loop then stops (`PeakLoop`). `args.mode` is the loop's (`ModelArgs`)."""
    params, smoothing, width_contact = args.params, args.smoothing, args.contact_width
    f = forces(y, params, smoothing, width_contact, t=t, mode=args.mode)
    values = tracked_metrics(t, y, args)
    inf = jnp.full_like(y[0], jnp.inf)
    if params.rails is None:
        return {name: inf for name in values}
    swing = jnp.zeros_like(y[0])  # the coupling force's possible change from now (N)
    reach = jnp.zeros_like(y[0])  # the absorber's possible travel from now (m)
    quiet = jnp.array(True)
    if params.absorber is not None:
        absorber = params.absorber
        rest = -absorber_sag(params)  # x_M − x_m at rest
        relative = y[0] - y[2]
        energy = 0.5 * absorber.m * (y[3] - y[1]) ** 2 + 0.5 * absorber.k_r * (relative - rest) ** 2
        amplitude = jnp.sqrt(2.0 * energy / absorber.k_r)  # about its rest, either way
        quiet = rest + amplitude < absorber.gap - width_contact
        # From one side of its swing to the other: twice the amplitude, from now.
        reach = 2.0 * amplitude
        swing = 2.0 * (
            absorber.k_r * amplitude + absorber.c_r * jnp.sqrt(2.0 * energy / absorber.m)
        )
    force_change = swing
    still = jnp.zeros_like(y[0])  # a held barrel does not creep
    for force in params.forces():  # (a force that cannot say keeps the solve running)
        force_change = _plus(force_change, force.held_change(params))
    spent = remaining_impulse(t, params) <= 1e-12 * params.barrel.M * jnp.abs(params.barrel.v0)
    load = jnp.abs(net_force(f)) + force_change
    held = spent & quiet & (args.mode == 0) & (load < friction_bound(params))
    mount = params.mount
    margin_change = jnp.zeros_like(y[0])
    if mount is not None:
        sin, cos = sin_cos(params)
        lever = jnp.abs(mount.trunnion_height * cos - mount.spade_distance * sin)
        mass = 0.0 if params.absorber is None else params.absorber.m * reach
        weight_moment = jnp.maximum(mount.mount_mass, 1.0) * GRAVITY * mount.cg_distance
        margin_change = (force_change * lever + GRAVITY * mass) / weight_moment
    travel = jnp.zeros_like(y[0]) if params.absorber is None else reach
    change = {
        "peak_displacement": still,
        "peak_anchoring_force": force_change,
        "peak_pull_force": force_change,
        "peak_contact_force": jnp.zeros_like(y[0]),  # (`quiet`: out of reach)
        "min_stroke": travel,
        "max_stroke": travel,
        "stability_margin": margin_change,
    }
    return {name: jnp.where(held, value + change[name], inf) for name, value in values.items()}


def _energy_ceiling(y, args, t, t1):
    """`(E*, spread)`: a bound on the mechanical energy from `t` to `t1` at state `y`
    (J; see `future_metric_bounds`), and `|c_out − c_ret|` (N·s/m)."""
    params, smoothing, width_contact = args.params, args.smoothing, args.contact_width
    barrel, absorber, contact = params.barrel, params.absorber, params.contact
    x_M, v_M, x_m, v_m = y[0], y[1], y[2], y[3]
    width_v = smoothing.damping_width
    spread = jnp.abs(barrel.c_out - barrel.c_ret)
    energy = 0.5 * barrel.M * v_M**2 + 0.5 * barrel.k * x_M**2
    energy = energy + spread * _SWITCH_POWER * width_v**2 * jnp.maximum(t1 - t, 0.0)
    for force in _others(params):  # (the barrel's is above)
        energy = _plus(energy, force.potential(x_M, params))
    if absorber is not None:
        # U(δ) <= k_c (δ + w)₊^(n+1) / (n+1), since the smoothed ramp r(s) <= (s + w)₊.
        relative = x_M - x_m
        reach = jnp.maximum(relative - absorber.gap + width_contact, 0.0)
        energy = energy + (
            0.5 * absorber.m * v_m**2
            + 0.5 * absorber.k_r * relative**2
            + contact.k_c * positive_power(reach, contact.n_c + 1.0) / (contact.n_c + 1.0)
        )
    if params.load is not None:
        root = jnp.sqrt(energy) + remaining_impulse(t, params) / jnp.sqrt(2.0 * barrel.M)
        energy = root**2
    return energy, spread


def _barrel_bounds(params: RecoilParams, two_energy, spread, width_v):
    """`(x_M, F_AN)` bounds (m, N) from `2E*` (J): the spring's reach, and the spring,
    damper, buffer and recuperator forces there (see `future_metric_bounds`)."""
    barrel = params.barrel
    damper_offset = spread * 3.0 * width_v / 16.0
    # No spring (k = 0, a gun returned by its recuperator): no reach from the energy.
    sprung = barrel.k > 0
    displacement = jnp.where(
        sprung, jnp.sqrt(two_energy / jnp.where(sprung, barrel.k, 1.0)), jnp.inf
    )
    anchoring = jnp.sqrt((barrel.k + barrel.c_out**2 / barrel.M) * two_energy) + damper_offset
    for force in _others(params):
        anchoring = _plus(anchoring, force.anchoring_bound(displacement, two_energy, params))
    return displacement, anchoring


def _others(params: RecoilParams) -> list[Force]:
    """The forces of the design's mechanism but the barrel's (whose energy and bounds are
    the ceiling's base), in the family's order."""
    return [f for f in params.forces() if not isinstance(f, Barrel) and not f.REACTION]


def _plus(total, share):
    """`total + share`, where a force's `share` of a bound may be None (not known: the
    bound is then `+inf`) or the number 0 (nothing to add)."""
    if share is None:
        return jnp.full_like(total, jnp.inf)
    if isinstance(share, float) and share == 0.0:
        return total
    return total + share


def _contact_bounds(params: RecoilParams, energy, two_energy, width_contact, width_v):
    """`(|x_M − x_m|, δ, F_ct)` bounds (m, m, N) from `E*` and `2E*` (J) for a design
    with an absorber: the coupling spring's reach, the penetration the energy allows and
    the contact force there (see `future_metric_bounds`)."""
    barrel, absorber, contact = params.barrel, params.absorber, params.contact
    assert absorber is not None
    relative_max = jnp.sqrt(two_energy / absorber.k_r)
    # U(δ) >= k_c δ₊^(n+1) / (n+1), since r(s) >= max(s, 0).
    penetration = positive_power(
        (contact.n_c + 1.0) * energy / contact.k_c, 1.0 / (contact.n_c + 1.0)
    )
    penetration = jnp.minimum(penetration, relative_max - absorber.gap)
    reachable = penetration > -width_contact
    rate = jnp.sqrt(two_energy * (1.0 / barrel.M + 1.0 / absorber.m))
    elastic = contact.k_c * positive_power(penetration + width_contact, contact.n_c)
    factor = 1.0 + contact.lambda_c * (rate + 3.0 * width_v / 16.0)
    contact_force = jnp.where(reachable, elastic * factor, 0.0)
    return relative_max, penetration, contact_force
