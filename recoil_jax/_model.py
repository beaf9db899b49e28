"""The recoil models as a diffrax ODE term, their forces, the signals whose extremes are
the metrics, and the energy bounds that let a solve stop early (`docs/model.md`).

State `y = (x_M, v_M, x_m, v_m)` (m, m/s), recoil is +x. The simplified model is the
absorber-free case (`params.absorber is None`): the absorber states stay at zero.
"""

from __future__ import annotations

from typing import NamedTuple

import diffrax
import jax.numpy as jnp

from ._metrics import METRICS
from ._params import RecoilParams, Smoothing

__all__ = [
    "RECOIL_TERM",
    "Forces",
    "characteristic_penetration",
    "contact_width",
    "forces",
    "future_metric_bounds",
    "initial_state",
    "model_args",
    "positive_power",
    "signals",
    "smooth_relu",
    "tracked_metrics",
    "vector_field",
]


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


def positive_power(x, exponent):
    """`x ** exponent` for `x >= 0`, 0 for `x <= 0`, with finite gradients everywhere
    (also with respect to `exponent` at `x = 0`, where the naive form gives NaN)."""
    positive = x > 0
    safe_x = jnp.where(positive, x, 1.0)
    return jnp.where(positive, safe_x**exponent, 0.0)


class Forces(NamedTuple):
    """Internal forces of the system at one state (N). Signs: as they act on the barrel's
    equation `M a_M = −recoil_spring − recoil_damper − coupling_spring − coupling_damper
    − contact`."""

    recoil_spring: jnp.ndarray  # k x_M
    recoil_damper: jnp.ndarray  # c(v_M) v_M
    coupling_spring: jnp.ndarray  # k_r (x_M − x_m)
    coupling_damper: jnp.ndarray  # c_r (v_M − v_m)
    contact: jnp.ndarray  # F_ct (>= 0, pushes the absorber forward)
    contact_elastic: jnp.ndarray  # k_c δ₊^n_c, the conservative part of F_ct

    @property
    def anchoring(self):
        """F_AN = k x_M + c(v_M) v_M: the load into the mounting (wall P)."""
        return self.recoil_spring + self.recoil_damper


def contact_width(params: RecoilParams, smoothing: Smoothing):
    """The contact-onset smoothing width in metres (see `Smoothing`)."""
    if smoothing.hard:
        return 0.0
    if smoothing.contact_width is not None:
        return smoothing.contact_width
    return smoothing.contact_width_fraction * characteristic_penetration(params)


def characteristic_penetration(params: RecoilParams):
    """Peak penetration (m) of a free head-on impact at the barrel's initial speed:
    `δ* = ((n_c+1) μ v0² / (2 k_c))^(1/(n_c+1))`, `μ = M m / (M + m)` (elastic contact).
    Sets the scale of the contact smoothing. Zero for the simplified model."""
    if params.absorber is None:
        return 0.0
    barrel, absorber, contact = params.barrel, params.absorber, params.contact
    reduced_mass = barrel.M * absorber.m / (barrel.M + absorber.m)
    energy = 0.5 * reduced_mass * barrel.v0**2
    return ((contact.n_c + 1.0) * energy / contact.k_c) ** (1.0 / (contact.n_c + 1.0))


def forces(y, params: RecoilParams, smoothing: Smoothing, width_contact=None) -> Forces:
    """All internal forces at state `y` (shape `(4,)`), smoothed as `smoothing` says.

    `width_contact` (m) may be passed precomputed (it depends only on the parameters).
    """
    x_M, v_M, x_m, v_m = y[0], y[1], y[2], y[3]
    barrel = params.barrel
    width_v = 0.0 if smoothing.hard else smoothing.damping_width
    # c(v) v = c_ret v + (c_out − c_ret) max(0, v): continuous, only its slope switches.
    recoil_damper = barrel.c_ret * v_M + (barrel.c_out - barrel.c_ret) * smooth_relu(v_M, width_v)
    recoil_spring = barrel.k * x_M
    absorber = params.absorber
    if absorber is None:
        zero = jnp.zeros_like(x_M)
        return Forces(recoil_spring, recoil_damper, zero, zero, zero, zero)
    contact = params.contact
    if width_contact is None:
        width_contact = contact_width(params, smoothing)
    penetration = x_M - x_m - absorber.gap
    penetration_rate = v_M - v_m
    elastic = contact.k_c * positive_power(smooth_relu(penetration, width_contact), contact.n_c)
    # No-pull clamp max(0, 1 + λ δ̇), smoothed over a relative-velocity band width_v.
    damping_factor = smooth_relu(
        1.0 + contact.lambda_c * penetration_rate, contact.lambda_c * width_v
    )
    return Forces(
        recoil_spring=recoil_spring,
        recoil_damper=recoil_damper,
        coupling_spring=absorber.k_r * (x_M - x_m),
        coupling_damper=absorber.c_r * (v_M - v_m),
        contact=elastic * damping_factor,
        contact_elastic=elastic,
    )


# max over s in [0, 1] of s (1 − s)³ (3 + s) / 16 = 0.021472 (at s = 0.2649), rounded up.
_SWITCH_POWER = 0.0215


def signals(y, args) -> dict[str, jnp.ndarray]:
    """The time signals whose extremes are the metrics (`Metric.signal`): barrel
    displacement `x_M` (m), anchoring force `F_AN` (N), contact force `F_ct` (N) and the
    absorber's travel `stroke = x_m − x_M` (m; 0 for the simplified model).
    `args = model_args(params, smoothing)`."""
    params, smoothing, width_contact = args
    f = forces(y, params, smoothing, width_contact)
    # The simplified model has no absorber, hence no stroke.
    stroke = jnp.zeros_like(y[0]) if params.absorber is None else y[2] - y[0]
    return {"x_M": y[0], "F_AN": f.anchoring, "F_ct": f.contact, "stroke": stroke}


def tracked_metrics(y, args) -> dict[str, jnp.ndarray]:
    """What the peak loop maximises, by metric name: `sign · signal` of each metric of
    `METRICS` (the negated stroke for `min_stroke`, so that its minimum is a maximum)."""
    values = signals(y, args)
    return {name: m.sign * values[m.signal] for name, m in METRICS.items()}


def future_metric_bounds(y, args, time_left) -> dict[str, jnp.ndarray]:
    """Upper bounds, valid for the rest of the run, on every tracked metric
    (`tracked_metrics`: x_M, F_AN, F_ct, x_m − x_M and x_M − x_m), by metric name, from
    the mechanical energy at state `y`.

    The energy `E = ½M v_M² + ½m v_m² + ½k x_M² + ½k_r (x_M − x_m)² + U(δ)` (with the
    contact potential `U`) never increases: the dampers, the contact's Hunt–Crossley
    part and its no-pull clamp only dissipate. The one exception is the smoothed damping
    switch, which can create at most `0.0215 |c_out − c_ret| w²` watts (0.0215 bounds
    `|v| (r(v) − max(v, 0)) / w²` over the band); that is added for `time_left` seconds.
    With `E*` bounding every later energy (Cauchy–Schwarz throughout):

    - `x_M ≤ √(2E*/k)` and `F_AN ≤ √((k + c_out²/M) 2E*) + |c_out − c_ret| 3w/16`;
    - `|x_M − x_m| ≤ √(2E*/k_r)`, `δ ≤ ((n_c+1) E*/k_c)^(1/(n_c+1))` and
      `|δ̇| ≤ √(2E* (1/M + 1/m))`, which bound the stroke and `F_ct`;
    - `F_ct = 0` once the wall can no longer reach the absorber.

    Returns `+inf` bounds where the dissipation argument fails (`λ_c w ≥ 1`). The peak
    loop stops once every bound is below its running peak. `args = model_args(params,
    smoothing)`; `time_left` (s).
    """
    params, smoothing, width_contact = args
    barrel, absorber, contact = params.barrel, params.absorber, params.contact
    x_M, v_M, x_m, v_m = y[0], y[1], y[2], y[3]
    width_v = 0.0 if smoothing.hard else smoothing.damping_width
    spread = jnp.abs(barrel.c_out - barrel.c_ret)
    energy = 0.5 * barrel.M * v_M**2 + 0.5 * barrel.k * x_M**2
    energy = energy + spread * _SWITCH_POWER * width_v**2 * jnp.maximum(time_left, 0.0)
    if absorber is not None:
        # U(δ) <= k_c (δ + w)₊^(n+1) / (n+1), since the smoothed ramp r(s) <= (s + w)₊.
        relative = x_M - x_m
        reach = jnp.maximum(relative - absorber.gap + width_contact, 0.0)
        energy = energy + (
            0.5 * absorber.m * v_m**2
            + 0.5 * absorber.k_r * relative**2
            + contact.k_c * positive_power(reach, contact.n_c + 1.0) / (contact.n_c + 1.0)
        )
    two_energy = 2.0 * energy
    damper_offset = spread * 3.0 * width_v / 16.0
    displacement = jnp.sqrt(two_energy / barrel.k)
    anchoring = jnp.sqrt((barrel.k + barrel.c_out**2 / barrel.M) * two_energy) + damper_offset
    if absorber is None:
        zero = jnp.zeros_like(displacement)
        return {
            "peak_displacement": displacement,
            "peak_anchoring_force": anchoring,
            "peak_contact_force": zero,
            "min_stroke": zero,
            "max_stroke": zero,
        }
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
    # The no-pull clamp dissipates only while r(1) = 1, i.e. λ_c w < 1.
    valid = contact.lambda_c * width_v < 1.0
    inf = jnp.full_like(displacement, jnp.inf)
    # x_M − x_m = gap + δ, and `penetration` already respects relative_max.
    bounds = {
        "peak_displacement": displacement,
        "peak_anchoring_force": anchoring,
        "peak_contact_force": contact_force,
        "min_stroke": absorber.gap + penetration,
        "max_stroke": relative_max,
    }
    return {name: jnp.where(valid, bound, inf) for name, bound in bounds.items()}


def vector_field(t, y, args):
    """`dy/dt` for `args = (params, smoothing, contact_width)`; the diffrax vector field."""
    del t
    params, smoothing, width_contact = args
    f = forces(y, params, smoothing, width_contact)
    a_M = -(f.anchoring + f.coupling_spring + f.coupling_damper + f.contact) / params.barrel.M
    if params.absorber is None:
        a_m = jnp.zeros_like(a_M)
    else:
        a_m = (f.coupling_spring + f.coupling_damper + f.contact) / params.absorber.m
    return jnp.stack([y[1], a_M, y[3], a_m])


#: The recoil models as one diffrax term; `args = model_args(params, smoothing)`.
RECOIL_TERM = diffrax.ODETerm(vector_field)


def model_args(params: RecoilParams, smoothing: Smoothing):
    """The `args` that `RECOIL_TERM` takes."""
    return (params, smoothing, contact_width(params, smoothing))


def initial_state(params: RecoilParams):
    """`y(0) = (0, v0, 0, 0)`."""
    v0 = jnp.asarray(params.barrel.v0, dtype=float)
    zero = jnp.zeros_like(v0)
    return jnp.stack([zero, v0, zero, zero])
