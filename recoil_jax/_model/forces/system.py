"""All forces of a design at one state (`Forces`, `forces`): the paper's spring, dampers,
coupling and contact, and each part of the hardware and of the firing envelope the
design has, with the rails' friction taking what the others leave (`docs/model.md`).

State `y = (x_M, v_M, x_m, v_m)` (m, m/s), recoil is +x. The simplified model is the
absorber-free case (`params.absorber is None`): the absorber states stay at zero.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..._model.forces.absorber import contact_width
from ..._model.forces.counter_recoil import counter_recoil_force
from ..._model.forces.loads import breech_force
from ..._model.forces.orifice import buffer_force
from ..._model.forces.rails import GRAVITY, friction_bound, sin_cos
from ..._model.forces.recuperator import preload_force, recuperator_force
from ..._model.forces.smoothing import positive_power, smooth_relu, smooth_step
from ..._model.forces.stop import stop_force
from ..._model.metrics import METRICS
from ..._model.params import RecoilParams
from ..._model.registry import ENVELOPE_GROUPS, ParameterError, is_concrete
from ..._model.settings import Smoothing

__all__ = [
    "Forces",
    "Structure",
    "check_envelope_metrics",
    "forces",
    "has_envelope",
    "net_force",
]


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


class Structure(eqx.Module):
    """Which parts a design has: static, from its pytree's structure (the groups present),
    not from its values. A program resolves it once (`Structure.of`) and carries it in
    its `args` (`ModelArgs.structure`), where the signals (and through them the bounds)
    and the loop's wiring read it.

    - `absorber`: the absorber (else the simplified model: no contact, no stroke);
    - `envelope`: any part of the firing envelope (`ENVELOPE_GROUPS`: rails, the battery
      stop, the counter-recoil buffer, a mount). Such a design is solved to `t1` (its
      return and its rest are metrics), the others stop once their peaks are certain."""

    absorber: bool = eqx.field(static=True)
    envelope: bool = eqx.field(static=True)

    @classmethod
    def of(cls, params: RecoilParams) -> Structure:
        return cls(
            absorber=params.absorber is not None,
            envelope=any(getattr(params, group) is not None for group in ENVELOPE_GROUPS),
        )


def has_envelope(params: RecoilParams) -> bool:
    """`Structure.of(params).envelope`, for a caller that holds the design alone."""
    return Structure.of(params).envelope


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


def _envelope_forces(y, params: RecoilParams, smoothing: Smoothing) -> dict:
    """The envelope's forces at `y` but friction (`_with_friction`), by `Forces` field:
    each only where the design has its group (else the paper's forces, operation for
    operation)."""
    x_M, v_M = y[0], y[1]
    out = {}
    recuperator = params.recuperator
    if recuperator is not None and params.battery_stop is not None:
        # A preload needs the stop (`check_design`): without one it is 0 and left out.
        out["preload"] = preload_force(x_M, recuperator)
    stop = params.battery_stop
    if stop is not None:
        out["stop"] = stop_force(x_M, v_M, stop, smoothing)
    counter = params.counter_recoil_buffer
    if counter is not None:
        out["counter_recoil"] = counter_recoil_force(y, counter, smoothing)
    if params.rails is not None:
        sin, _ = sin_cos(params)
        out["gravity"] = params.barrel.M * GRAVITY * sin
        if params.absorber is not None:
            out["absorber_gravity"] = params.absorber.m * GRAVITY * sin
    return out


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
