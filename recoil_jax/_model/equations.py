"""The recoil models as a diffrax ODE term, their forces, the signals whose extremes are
the metrics, and the energy bounds that let a solve stop early (`docs/model.md`).

State `y = (x_M, v_M, x_m, v_m)` (m, m/s), recoil is +x. The simplified model is the
absorber-free case (`params.absorber is None`): the absorber states stay at zero.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._model.metrics import EXTREMES, METRICS
from .._model.params import Buffer, CounterRecoilBuffer, Load, RecoilParams, Recuperator
from .._model.registry import ParameterError, is_concrete
from .._model.settings import Smoothing

#: Standard gravity (m/s²), as `docs/model.md` fixes it.
GRAVITY = 9.80665
#: The barrel is back in battery once it comes forward through this `x_M` (m).
BATTERY = 1e-3

__all__ = [
    "BATTERY",
    "BOTTOM",
    "GRAVITY",
    "RECOIL_TERM",
    "UNTRACKED",
    "Forces",
    "ModelArgs",
    "absorber_sag",
    "axial_weight",
    "breech_force",
    "buffer_force",
    "characteristic_penetration",
    "check_envelope_metrics",
    "contact_width",
    "counter_recoil_force",
    "forces",
    "friction_bound",
    "future_metric_bounds",
    "has_envelope",
    "held_bounds",
    "initial_state",
    "knot_crossing",
    "load_jump",
    "load_stops",
    "metric_ceilings",
    "model_args",
    "mounted",
    "net_force",
    "onset_ramp",
    "orifice_area",
    "positive_power",
    "recuperator_energy",
    "recuperator_force",
    "remaining_impulse",
    "rest_root",
    "restart_step",
    "signals",
    "smooth_relu",
    "smooth_step",
    "static_anchoring",
    "static_rest",
    "tracked_metrics",
    "tracked_names",
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


class Forces(NamedTuple):
    """The forces of the system at one state (N). Signs: as they act on the barrel's
    equation `M a_M = breech − anchoring − coupling_spring − coupling_damper − contact`,
    with `anchoring = recoil_spring + recoil_damper + buffer + recuperator`. Elements the
    design does not have are `None`."""

    recoil_spring: jnp.ndarray  # k x_M
    recoil_damper: jnp.ndarray  # c(v_M) v_M
    coupling_spring: jnp.ndarray  # k_r (x_M − x_m)
    coupling_damper: jnp.ndarray  # c_r (v_M − v_m)
    contact: jnp.ndarray  # F_ct (>= 0, pushes the absorber forward)
    contact_elastic: jnp.ndarray  # k_c δ₊^n_c, the conservative part of F_ct
    buffer: jnp.ndarray | None = None  # F_h, the hydraulic buffer's orifice force
    recuperator: jnp.ndarray | None = None  # F_g, the gas recuperator
    breech: jnp.ndarray | None = None  # F_b(t), the breech force (pulse or table loads)
    # The firing envelope (`docs/model.md`):
    preload: jnp.ndarray | None = None  # F_p, the recuperator's preload on its gas column
    counter_recoil: jnp.ndarray | None = None  # F_cb, the counter-recoil buffer (<= 0)
    stop: jnp.ndarray | None = None  # F_s (>= 0), the battery stop pushing the barrel back
    friction: jnp.ndarray | None = None  # F_f, rail friction
    gravity: jnp.ndarray | None = None  # M g sin θ, along +x on the barrel
    absorber_gravity: jnp.ndarray | None = None  # m g sin θ on the absorber

    @property
    def anchoring(self):
        """F_AN = k x_M + c(v_M) v_M + F_h + F_g + F_p + F_cb + F_f − F_s: the load into
        the mounting (wall P)."""
        total = self.recoil_spring + self.recoil_damper
        for part in (self.buffer, self.recuperator, self.preload, self.counter_recoil):
            if part is not None:
                total = total + part
        if self.friction is not None:
            total = total + self.friction
        if self.stop is not None:
            total = total - self.stop
        return total


def contact_width(params: RecoilParams, smoothing: Smoothing):
    """The contact-onset smoothing width in metres (see `Smoothing`)."""
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


# The gas column is held at 0.99 L_r at most, so the force stays finite: a solve fails
# (Status.bottomed_out) well before, once x_M reaches BOTTOM · L_r.
BOTTOM = 0.95
_HOLD = 0.99


def recuperator_force(x, recuperator: Recuperator):
    """The gas spring `F_g = F_r ((L_r / (L_r − x))^γ − 1)` (N), for `x < 0.99 L_r`."""
    length = recuperator.recuperator_length
    held = jnp.minimum(x, _HOLD * length)
    ratio = length / (length - held)
    return recuperator.recuperator_force * (ratio**recuperator.polytropic_index - 1.0)


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


# Jitted so that JAX traces it once per shape: a gradient program evaluates the forces
# in about 30 places (stages, rates, jumps, peaks), and re-running this Python for each
# was a third of its trace time. XLA inlines the call: the compiled code is the same.
@jax.jit
def forces(y, params: RecoilParams, smoothing: Smoothing, width_contact=None, t=None) -> Forces:
    """All forces at state `y` (shape `(4,)`), smoothed as `smoothing` says; the breech
    force (designs with a pulse or table load) needs the time `t` (s).

    `width_contact` (m) may be passed precomputed (it depends only on the parameters).
    """
    x_M, v_M, x_m, v_m = y[0], y[1], y[2], y[3]
    barrel = params.barrel
    width_v = smoothing.damping_width
    # c(v) v = c_ret v + (c_out − c_ret) max(0, v): continuous, only its slope switches.
    recoil_damper = barrel.c_ret * v_M + (barrel.c_out - barrel.c_ret) * smooth_relu(v_M, width_v)
    recoil_spring = barrel.k * x_M
    hardware = {}
    if params.buffer is not None and params.buffer.orifice is not None:
        hardware["buffer"] = buffer_force(x_M, v_M, params.buffer, smoothing.knot_width_fraction)
    if params.recuperator is not None:
        hardware["recuperator"] = recuperator_force(x_M, params.recuperator)
    if params.load is not None and t is not None:
        hardware["breech"] = breech_force(t, params)
    hardware |= _envelope_forces(y, params, smoothing)
    absorber = params.absorber
    if absorber is None:
        zero = jnp.zeros_like(x_M)
        return _with_friction(
            Forces(recoil_spring, recoil_damper, zero, zero, zero, zero, **hardware),
            y,
            params,
            smoothing,
        )
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
    together = Forces(
        recoil_spring=recoil_spring,
        recoil_damper=recoil_damper,
        coupling_spring=absorber.k_r * (x_M - x_m),
        coupling_damper=absorber.c_r * (v_M - v_m),
        contact=elastic * damping_factor,
        contact_elastic=elastic,
        **hardware,
    )
    return _with_friction(together, y, params, smoothing)


def has_envelope(params: RecoilParams) -> bool:
    """Whether the design has any part of the firing envelope (rails, the battery stop,
    the counter-recoil buffer, a mount): static, from the structure. Such a design is
    solved to `t1` (its return and its rest are metrics), the others stop once their
    peaks are certain."""
    return any(
        getattr(params, group) is not None
        for group in ("rails", "battery_stop", "counter_recoil_buffer", "mount")
    )


#: The parameters that give a design the firing envelope, named in refusals.
_ENVELOPE_PARTS = "elevation, friction_force, stop_stiffness, buffer_damping or mount_mass"


def check_envelope_metrics(params: RecoilParams, names, where: str) -> None:
    """Refuse (`ParameterError`, one line) metrics `names` the design has not got: the
    firing envelope's (`Metric.envelope`) on a design without any part of it, and
    `stability_margin` without a mount (`mount_mass > 0`). `where` says who asks."""
    for name in names:
        m = METRICS.get(name)
        if m is None or not m.envelope:
            continue
        if not has_envelope(params):
            raise ParameterError(
                f"{where}: {name} is a metric of the firing envelope, and this design has "
                f"none of it: give one of {_ENVELOPE_PARTS}"
            )
        mount = params.mount
        no_mount = mount is None or (
            is_concrete(mount.mount_mass) and not np.all(np.asarray(mount.mount_mass) > 0)
        )
        if name == "stability_margin" and no_mount:
            raise ParameterError(
                f"{where}: stability_margin needs a mount: mount_mass > 0 (0 is no mount)"
            )


def absorber_sag(params: RecoilParams):
    """The absorber's static sag on the barrel, `m g sin θ / k_r` (m, rearward; 0 on level
    rails or without an absorber): where it starts, and where it rests on a held barrel."""
    if params.rails is None or params.absorber is None:
        return 0.0
    sin, _ = _sin_cos(params)
    return params.absorber.m * GRAVITY * sin / params.absorber.k_r


def mounted(params: RecoilParams):
    """Whether the design has a mount (`mount_mass > 0`; False without the group)."""
    return False if params.mount is None else params.mount.mount_mass > 0


def _sin_cos(params: RecoilParams):
    theta = jnp.deg2rad(params.rails.elevation) if params.rails is not None else 0.0
    return jnp.sin(theta), jnp.cos(theta)


def _envelope_forces(y, params: RecoilParams, smoothing: Smoothing) -> dict:
    """The envelope's forces at `y` but friction (`_with_friction`), by `Forces` field:
    each only where the design has its group (else the paper's forces, operation for
    operation)."""
    x_M, v_M = y[0], y[1]
    out = {}
    recuperator = params.recuperator
    if recuperator is not None and params.battery_stop is not None:
        # A preload needs the stop (`check_design`): without one it is 0 and left out.
        held = jnp.minimum(x_M, _HOLD * recuperator.recuperator_length)
        ratio = recuperator.recuperator_length / (recuperator.recuperator_length - held)
        out["preload"] = recuperator.recuperator_preload * ratio**recuperator.polytropic_index
    stop = params.battery_stop
    if stop is not None:
        depth = onset_ramp(-x_M, smoothing.stop_width)
        elastic = stop.stop_stiffness * positive_power(depth, stop.stop_exponent)
        # No-pull clamp max(0, 1 + λ_s δ̇) with δ̇ = −v_M, smoothed as the contact's.
        factor = smooth_relu(
            1.0 - stop.stop_damping * v_M, stop.stop_damping * smoothing.damping_width
        )
        out["stop"] = elastic * factor
    counter = params.counter_recoil_buffer
    if counter is not None:
        out["counter_recoil"] = counter_recoil_force(y, counter, smoothing)
    if params.rails is not None:
        sin, _ = _sin_cos(params)
        out["gravity"] = params.barrel.M * GRAVITY * sin
        if params.absorber is not None:
            out["absorber_gravity"] = params.absorber.m * GRAVITY * sin
    return out


def counter_recoil_force(y, counter: CounterRecoilBuffer, smoothing: Smoothing, lead=False):
    """The counter-recoil buffer's `F_cb = c_b v_M` while `v_M < 0` and `x_M < L_b` (N,
    <= 0). Its speed ramp is one-sided, so that a barrel at rest feels none of it. Its
    engagement at `x_M = L_b` is a jump of `F_AN` in the exact model, smoothed over
    `buffer_width` `w`: the dynamics' step is centred on `L_b` (over `[L_b − w, L_b + w]`,
    so that its impulse is the jump's to `O(w²)`), and with `lead` (the signals',
    `signals`) it lies all before the dynamics' (over `[L_b + w, L_b + 3w]`). So the
    signals reach the exact jump's value as the barrel enters the dynamics' step, before
    the smoothed buffer has slowed it: a pull or a margin whose extreme is the jump is the
    exact model's to the approach's `O(w)`, not `c_b w / (M v)` of itself low
    (`docs/model.md`). With `w = 0` both are the exact switch."""
    x_M, v_M = y[0], y[1]
    width = smoothing.buffer_width
    edge = counter.buffer_length + (2.0 * width if lead else 0.0)
    inside = smooth_step(edge - x_M, width)
    returning = onset_ramp(-v_M, smoothing.damping_width)
    return -counter.buffer_damping * returning * inside


def friction_bound(params: RecoilParams):
    """`F_max = F_0 + μ (M + m) g cos θ` (N), the most the rails' friction holds."""
    rails = params.rails
    assert rails is not None
    _, cos = _sin_cos(params)
    mass = params.barrel.M + (0.0 if params.absorber is None else params.absorber.m)
    return rails.friction_force + rails.friction_coefficient * mass * GRAVITY * cos


def net_force(f: Forces):
    """`N` (N): the force along `+x` on the barrel from everything but friction (the
    breech's, where `f` has it, gravity's, and less all that holds the barrel back)."""
    net = -(f.anchoring + f.coupling_spring + f.coupling_damper + f.contact)
    if f.friction is not None:
        net = net + f.friction  # (`anchoring` holds it)
    if f.gravity is not None:
        net = net + f.gravity
    if f.breech is not None:
        net = net + f.breech
    return net


def _with_friction(f: Forces, y, params: RecoilParams, smoothing: Smoothing) -> Forces:
    """`f` with the rails' friction (`docs/model.md`, *Sticking*):
    `F_f = clamp(N_h + M v_M / τ, ±F_max)` with `τ = stick_time`, where `N` is the net
    force on the barrel from everything but friction (the breech force included, so
    `forces` needs the time `t` for a design with a pulse or table load), and

    - inside the band, `|N| <= F_max`: `N_h = N`. A barrel at rest stays at rest
      (friction takes `N`), and any speed it has is relaxed to 0 over `τ`: no creep;
    - outside it: `N_h = ±F_max`, opposing the motion: `−sign(N) F_max` while the
      barrel moves against `N` (slowing to reverse) and `+sign(N) F_max` once it moves
      with it (or starts from rest). The friction is then `F_max` against the motion,
      switching as `v_M` crosses 0 within `slip_width`, as the exact law's sign does.
      Over `|N| − F_max < friction_width` the two join continuously.
    """
    if params.rails is None:
        return f
    net = net_force(f)
    bound, width = friction_bound(params), smoothing.friction_width
    direction = jnp.where(net >= 0, 1.0, -1.0)
    # 1 moving with N or at rest (a barrel at rest starts in N's direction, with the
    # full friction against it), 0 moving against it faster than 2 slip_width.
    along = 1.0 - smooth_step(-direction * y[1] - smoothing.slip_width, smoothing.slip_width)
    excess = jnp.abs(net) - bound
    safe_width = jnp.where(width > 0, width, 1.0)
    against = jnp.where(width > 0, jnp.clip(excess / safe_width, 0.0, 1.0), 1.0)
    outside = direction * bound * (1.0 - 2.0 * (1.0 - along) * against)
    held = jnp.where(excess <= 0, net, outside)
    relaxing = held + params.barrel.M * y[1] / smoothing.stick_time
    return f._replace(friction=jnp.clip(relaxing, -bound, bound))


# max over s in [0, 1] of s (1 − s)³ (3 + s) / 16 = 0.021472 (at s = 0.2649), rounded up.
_SWITCH_POWER = 0.0215


def signals(t, y, args: ModelArgs) -> dict[str, jnp.ndarray]:
    """The time signals whose extremes are the metrics (`Metric.signal`): the recoil
    `x_M − x_r` from the static rest (m), anchoring force `F_AN` (N), its pull on the
    mount `−F_AN` (N; 0 for a design without the firing envelope, whose solve stops
    before the return), contact force `F_ct` (N), the absorber's
    travel `stroke = x_m − x_M` (m; 0 for the simplified model) and the mount's
    stability `margin`. `args = model_args(params, smoothing)`; the time `t` (s) for the
    breech force, which the friction's sticking sees."""
    params = args.params
    f = forces(y, params, args.smoothing, args.contact_width, t=t)
    # The simplified model has no absorber, hence no stroke.
    stroke = jnp.zeros_like(y[0]) if params.absorber is None else y[2] - y[0]
    anchoring = f.anchoring
    counter = params.counter_recoil_buffer
    if counter is not None:  # its engagement as the signals see it (`counter_recoil_force`)
        lead = counter_recoil_force(y, counter, args.smoothing, lead=True)
        anchoring = anchoring - f.counter_recoil + lead
    out = {"recoil": y[0] - args.rest, "F_AN": anchoring, "F_ct": f.contact, "stroke": stroke}
    out["pull"] = -anchoring if has_envelope(params) else jnp.zeros_like(anchoring)
    out["margin"] = stability(y, params, anchoring, args.rest)
    return out


def stability(y, params: RecoilParams, anchoring, rest):
    """The mount's stability margin at state `y` with anchoring force `anchoring` (N),
    the gun having started at its static rest `rest` (m, `x_r`):
    `(S − K d) / (m_g g L_w)`, the stabilising moment about the spade less the
    overturning one, over the gun's weight's moment (`docs/model.md`, revision 2). The
    whole gun's moments: the overturning force is the resistance to recoil net of the
    recoiling parts' axial weight, `K = F_AN − (M + m) g sin θ` (that weight is in the
    stabilising moment already), on the bore axis's arm `d = h cos θ − L_s sin θ`, and
    the recoiling parts' move from their rest shifts the weight's moment. 1 without a
    mount (no load on it: the margin is then not reported, `Peaks`)."""
    mount = params.mount
    if mount is None:
        return jnp.ones_like(y[0])
    sin, cos = _sin_cos(params)
    lever = mount.trunnion_height * cos - mount.spade_distance * sin
    moved = params.barrel.M * (y[0] - rest)
    if params.absorber is not None:
        moved = moved + params.absorber.m * (y[2] - rest - absorber_sag(params))
    present = mounted(params)
    weight_moment = jnp.where(present, mount.mount_mass, 1.0) * GRAVITY * mount.cg_distance
    resistance = anchoring - axial_weight(params)
    margin = (weight_moment - GRAVITY * moved * cos - resistance * lever) / weight_moment
    return jnp.where(present, margin, jnp.ones_like(margin))


#: The value of each extreme metric a design's structure holds constant, which the peak
#: loop does not track (`tracked_names`): no absorber, no contact and no stroke; no
#: envelope, no pull (its solve stops before the return).
UNTRACKED = {
    "peak_contact_force": 0.0,
    "min_stroke": 0.0,
    "max_stroke": 0.0,
    "peak_pull_force": 0.0,
}


def tracked_names(params: RecoilParams) -> tuple[str, ...]:
    """The extreme metrics the peak loop tracks for the structure of `params` (static):
    every one of `EXTREMES` but those the structure holds constant (`UNTRACKED`). Each
    tracked quantity costs every step its share of the loop's carry (its running
    maximum and the step holding it)."""
    absent = set()
    if params.absorber is None:
        absent |= {"peak_contact_force", "min_stroke", "max_stroke"}
    if not has_envelope(params):
        absent.add("peak_pull_force")
    return tuple(name for name in EXTREMES if name not in absent)


def tracked_metrics(t, y, args: ModelArgs) -> dict[str, jnp.ndarray]:
    """What the peak loop maximises, by metric name: `sign · signal` of each extreme
    metric the design tracks (`tracked_names`; the negated stroke for `min_stroke`, so
    that its minimum is a maximum)."""
    values = signals(t, y, args)
    return {
        name: EXTREMES[name].sign * values[str(EXTREMES[name].signal)]
        for name in tracked_names(args.params)
    }


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
    # Only designs without the envelope stop early (`has_envelope`): without a mount the
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


#: A held barrel is settled once its speed is below this (m/s): what it can still creep,
#: `|v_M| τ`, is then below 1e-9 m for τ <= 1 ms.
_SETTLED_SPEED = 1e-6
#: A barrel held with its net force within `friction_width` of the band's edge (it slid
#: to rest with friction all but saturated) creeps at the steady speed the smoothed
#: clamp leaves it: settled once that is below this (m/s), its creep to `t1` bounded by
#: speed × (t1 − t) (< 1e-7 m for t1 <= 100 s).
_SETTLED_EDGE_SPEED = 1e-9


def held_bounds(y, args, t, t1) -> dict[str, jnp.ndarray]:
    """Bounds on every tracked metric from `t` to `t1`, by name, for a design with the
    firing envelope: finite only once the barrel is held for good, `+inf` before. Held
    for good means all rounds fired and their breech force spent, the barrel at rest
    (`|v_M| < 1e-6 m/s`) with the net force on it inside the friction's band by more
    than what the absorber can still change (its energy about its rest on the barrel,
    bounding the coupling's swing; nor can it reach the wall), and by the band's
    smoothing width (or, within it, at a creep below 1e-9 m/s); the coupling's swing
    counted from one side to the other, since it may be at either now: nothing moves the barrel
    again, so its peaks, return (found, or never) and rest `x_M(t1)` are known now (to
    its creep, `|v_M| τ < 1e-9 m`, or `|v_M| (t1 − t)` at the band's edge). The loop
    then stops (`PeakLoop`)."""
    params, smoothing, width_contact = args.params, args.smoothing, args.contact_width
    f = forces(y, params, smoothing, width_contact, t=t)
    values = tracked_metrics(t, y, args)
    inf = jnp.full_like(y[0], jnp.inf)
    if params.rails is None:
        return {name: inf for name in values}
    bound = friction_bound(params)
    speed = jnp.abs(y[1])
    swing = jnp.zeros_like(y[0])  # the coupling force's possible change from now (N)
    reach = jnp.zeros_like(y[0])  # the absorber's possible travel from now (m)
    quiet = jnp.array(True)
    if params.absorber is not None:
        absorber = params.absorber
        rest = -absorber_sag(params)  # x_M − x_m at rest
        relative = y[0] - y[2]
        energy = 0.5 * absorber.m * (y[3] - y[1]) ** 2 + 0.5 * absorber.k_r * (relative - rest) ** 2
        amplitude = jnp.sqrt(2.0 * energy / absorber.k_r)  # about its rest, either way
        quiet = rest + amplitude + speed * smoothing.stick_time < absorber.gap - width_contact
        # From one side of its swing to the other: twice the amplitude, from now.
        reach = 2.0 * amplitude
        swing = 2.0 * (
            absorber.k_r * amplitude + absorber.c_r * jnp.sqrt(2.0 * energy / absorber.m)
        )
    force_change = swing + params.barrel.M * speed / smoothing.stick_time
    spent = remaining_impulse(t, params) <= 1e-12 * params.barrel.M * jnp.abs(params.barrel.v0)
    load = jnp.abs(net_force(f)) + force_change
    inside = (speed < _SETTLED_SPEED) & (load < bound - smoothing.friction_width)
    at_edge = (speed < _SETTLED_EDGE_SPEED) & (load < bound)
    held = spent & quiet & (inside | at_edge)
    creep = speed * jnp.where(inside, smoothing.stick_time, jnp.maximum(t1 - t, 0.0))
    mount = params.mount
    margin_change = jnp.zeros_like(y[0])
    if mount is not None:
        sin, cos = _sin_cos(params)
        lever = jnp.abs(mount.trunnion_height * cos - mount.spade_distance * sin)
        mass = params.barrel.M * creep + (
            0.0 if params.absorber is None else params.absorber.m * reach
        )
        weight_moment = jnp.maximum(mount.mount_mass, 1.0) * GRAVITY * mount.cg_distance
        margin_change = (force_change * lever + GRAVITY * mass) / weight_moment
    travel = jnp.zeros_like(y[0]) if params.absorber is None else reach + creep
    change = {
        "peak_displacement": creep,
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
    if params.recuperator is not None:
        energy = energy + recuperator_energy(x_M, params.recuperator)
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
    if params.buffer is not None and params.buffer.orifice is not None:
        smallest = jnp.min(jnp.asarray(params.buffer.orifice))
        anchoring = (
            anchoring + buffer_coefficient(params.buffer) * (two_energy / barrel.M) / smallest**2
        )
    if params.recuperator is not None:
        anchoring = anchoring + jnp.maximum(
            recuperator_force(displacement, params.recuperator), 0.0
        )
    return displacement, anchoring


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


def metric_ceilings(params: RecoilParams) -> dict[str, jnp.ndarray] | None:
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


def vector_field(t, y, args):
    """`dy/dt` for `args = model_args(params, smoothing)` (`ModelArgs`); the diffrax
    vector field."""
    params = args.params
    f = forces(y, params, args.smoothing, args.contact_width, t=t)
    internal = f.anchoring + f.coupling_spring + f.coupling_damper + f.contact
    if f.gravity is not None:
        internal = internal - f.gravity
    if f.breech is None:
        a_M = -internal / params.barrel.M
    else:
        a_M = (f.breech - internal) / params.barrel.M
    if params.absorber is None:
        a_m = jnp.zeros_like(a_M)
    else:
        pushed = f.coupling_spring + f.coupling_damper + f.contact
        if f.absorber_gravity is not None:
            pushed = pushed + f.absorber_gravity
        a_m = pushed / params.absorber.m
    return jnp.stack([y[1], a_M, y[3], a_m])


#: The recoil models as one diffrax term; `args = model_args(params, smoothing)`.
RECOIL_TERM = diffrax.ODETerm(vector_field)


class ModelArgs(eqx.Module):
    """The `args` that `RECOIL_TERM` and the model's signals take (`model_args`):

    - `params`, `smoothing`: the design and its switch widths;
    - `contact_width` (m): the contact onset's smoothing width (`contact_width`);
    - `rest` (m): the barrel's static rest in battery `x_r` (`static_rest`), from which
      the displacement metrics and the mount's moments are measured; differentiable in
      the parameters. None where only the vector field reads them (it does not read
      the rest)."""

    params: RecoilParams
    smoothing: Smoothing
    contact_width: Any
    rest: Any


def model_args(params: RecoilParams, smoothing: Smoothing, rest_guess=None) -> ModelArgs:
    """The `args` that `RECOIL_TERM` takes. `rest_guess`: the rest `x_r` found already
    for these values (`rest_root`; its value only), so that only its polishing Newton
    step (which carries the derivatives) is done again; default: found here."""
    width = contact_width(params, smoothing)
    if rest_guess is None:
        rest_guess = rest_root(params, smoothing, width)
    return ModelArgs(params, smoothing, width, static_rest(params, smoothing, width, rest_guess))


def axial_weight(params: RecoilParams):
    """`(M + m) g sin θ` (N): the recoiling parts' weight along `+x` (0 on level rails or
    without rails), which the mechanism holds at rest."""
    if params.rails is None:
        return 0.0
    sin, _ = _sin_cos(params)
    mass = params.barrel.M + (0.0 if params.absorber is None else params.absorber.m)
    return mass * GRAVITY * sin


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


def _impulse(load: Load):
    """Whether each round is an impulse (a velocity jump of `v0`): no table and
    `pulse_time == 0`."""
    return jnp.logical_and(load.table is None, load.pulse_time <= 0)


def initial_state(args: ModelArgs):
    """`y(0) = (x_r, v0, x_r + sag, 0)` for an impulse load, the barrel at rest for a
    pulse or table load: the gun at its static rest in battery (`static_rest`, 0 without
    a battery stop), the absorber hanging at rest on its spring, `m g sin θ / k_r`
    behind the barrel (0 on level rails). `args = model_args(params, smoothing)`."""
    params = args.params
    v0 = jnp.asarray(params.barrel.v0, dtype=float)
    zero = jnp.zeros_like(v0)
    if params.load is not None:
        v0 = jnp.where(_impulse(params.load), v0, zero)
    rest = zero + args.rest
    return jnp.stack([rest, v0, rest + absorber_sag(params), zero])


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
    fired = jnp.any(firing == t) & _impulse(load)
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
