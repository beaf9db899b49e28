"""The recoil models as a diffrax ODE term (`RECOIL_TERM`, its `ModelArgs`), the state
they start from, and the signals whose extremes are the metrics (`docs/model.md`).

State `y = (x_M, v_M, x_m, v_m)` (m, m/s), recoil is +x. The simplified model is the
absorber-free case (`params.absorber is None`): the absorber states stay at zero. The
forces are `forces.system`'s; the bounds that let a solve stop early are `bounds`'.
"""

from __future__ import annotations

from typing import Any

import diffrax
import equinox as eqx
import jax.numpy as jnp

from .._model.forces.absorber import contact_width
from .._model.forces.counter_recoil import counter_recoil_force
from .._model.forces.loads import is_impulse
from .._model.forces.rails import GRAVITY, absorber_sag, axial_weight, sin_cos
from .._model.forces.system import Structure, forces
from .._model.metrics import EXTREMES
from .._model.params import RecoilParams
from .._model.rest import rest_root, static_rest
from .._model.settings import Smoothing

__all__ = [
    "BATTERY",
    "RECOIL_TERM",
    "UNTRACKED",
    "ModelArgs",
    "initial_state",
    "model_args",
    "mounted",
    "signals",
    "stability",
    "tracked_metrics",
    "tracked_names",
    "vector_field",
]


#: The barrel is back in battery once it comes forward through this `x_M` (m).
BATTERY = 1e-3


def mounted(params: RecoilParams):
    """Whether the design has a mount (`mount_mass > 0`; False without the group)."""
    return False if params.mount is None else params.mount.mount_mass > 0


def signals(t, y, args: ModelArgs) -> dict[str, jnp.ndarray]:
    """The time signals whose extremes are the metrics (`Metric.signal`): the recoil
    `x_M − x_r` from the static rest (m), anchoring force `F_AN` (N), its pull on the
    mount `−F_AN` (N; 0 for a design without the firing envelope, whose solve stops
    before the return), contact force `F_ct` (N), the absorber's
    travel `stroke = x_m − x_M` (m; 0 for the simplified model) and the mount's
    stability `margin`. `args = model_args(params, smoothing)`; the time `t` (s) for the
    breech force, which the friction's sticking sees."""
    params = args.params
    f = forces(y, params, args.smoothing, args.contact_width, t=t, mode=args.mode)
    # The simplified model has no absorber, hence no stroke.
    stroke = jnp.zeros_like(y[0]) if params.absorber is None else y[2] - y[0]
    anchoring = f.anchoring
    counter = params.counter_recoil_buffer
    if counter is not None:  # its engagement as the signals see it (`counter_recoil_force`)
        lead = counter_recoil_force(y, counter, args.smoothing, lead=True)
        anchoring = anchoring - f.counter_recoil + lead
    out = {"recoil": y[0] - args.rest, "F_AN": anchoring, "F_ct": f.contact, "stroke": stroke}
    out["pull"] = -anchoring if args.parts.envelope else jnp.zeros_like(anchoring)
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
    sin, cos = sin_cos(params)
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


def tracked_names(structure: Structure) -> tuple[str, ...]:
    """The extreme metrics the peak loop tracks for a design's `structure` (static):
    every one of `EXTREMES` but those the structure holds constant (`UNTRACKED`). Each
    tracked quantity costs every step its share of the loop's carry (its running
    maximum and the step holding it)."""
    absent = set()
    if not structure.absorber:
        absent |= {"peak_contact_force", "min_stroke", "max_stroke"}
    if not structure.envelope:
        absent.add("peak_pull_force")
    return tuple(name for name in EXTREMES if name not in absent)


def tracked_metrics(t, y, args: ModelArgs) -> dict[str, jnp.ndarray]:
    """What the peak loop maximises, by metric name: `sign · signal` of each extreme
    metric the design tracks (`tracked_names`; the negated stroke for `min_stroke`, so
    that its minimum is a maximum)."""
    values = signals(t, y, args)
    return {
        name: EXTREMES[name].sign * values[str(EXTREMES[name].signal)]
        for name in tracked_names(args.parts)
    }


def vector_field(t, y, args):
    """`dy/dt` for `args = model_args(params, smoothing)` (`ModelArgs`); the diffrax
    vector field."""
    params = args.params
    f = forces(y, params, args.smoothing, args.contact_width, t=t, mode=args.mode)
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
    v_M = y[1]
    if args.mode is not None:  # held: still, to the bit (its friction takes the rest)
        held = args.mode == 0
        v_M, a_M = jnp.where(held, 0.0, v_M), jnp.where(held, 0.0, a_M)
    return jnp.stack([v_M, a_M, y[3], a_m])


#: The recoil models as one diffrax term; `args = model_args(params, smoothing)`.
RECOIL_TERM = diffrax.ODETerm(vector_field)


class ModelArgs(eqx.Module):
    """The `args` that `RECOIL_TERM` and the model's signals take (`model_args`):

    - `params`, `smoothing`: the design and its switch widths;
    - `contact_width` (m): the contact onset's smoothing width (`contact_width`);
    - `rest` (m): the barrel's static rest in battery `x_r` (`static_rest`), from which
      the displacement metrics and the mount's moments are measured; differentiable in
      the parameters. None where only the vector field reads them (it does not read
      the rest);
    - `structure`: which parts the design has (`Structure`), resolved once by the
      program (`model_args`); None (a hand-built `args`, or the vector field's): resolved
      where it is read (`ModelArgs.parts`);
    - `mode`: the barrel's mode on its rails, set by the stepping loop (`sticking`: 0
      held, ±1 sliding that way); None: read from the state (`friction_mode`: sliding
      the way the barrel moves, held where it is still inside the friction's band), as
      outside the loop."""

    params: RecoilParams
    smoothing: Smoothing
    contact_width: Any
    rest: Any
    structure: Any = None
    mode: Any = None

    @property
    def parts(self) -> Structure:
        """`structure`, or where it is None the design's (`Structure.of`)."""
        return self.structure or Structure.of(self.params)


def model_args(
    params: RecoilParams, smoothing: Smoothing, rest_guess=None, structure=None
) -> ModelArgs:
    """The `args` that `RECOIL_TERM` takes. `rest_guess`: the rest `x_r` found already
    for these values (`rest_root`; its value only), so that only its polishing Newton
    step (which carries the derivatives) is done again; default: found here.
    `structure`: the design's `Structure`, where the program has resolved it already."""
    width = contact_width(params, smoothing)
    if rest_guess is None:
        rest_guess = rest_root(params, smoothing, width)
    rest = static_rest(params, smoothing, width, rest_guess)
    return ModelArgs(params, smoothing, width, rest, structure or Structure.of(params))


def initial_state(args: ModelArgs):
    """`y(0) = (x_r, v0, x_r + sag, 0)` for an impulse load, the barrel at rest for a
    pulse or table load: the gun at its static rest in battery (`static_rest`, 0 without
    a battery stop), the absorber hanging at rest on its spring, `m g sin θ / k_r`
    behind the barrel (0 on level rails). `args = model_args(params, smoothing)`."""
    params = args.params
    v0 = jnp.asarray(params.barrel.v0, dtype=float)
    zero = jnp.zeros_like(v0)
    if params.load is not None:
        v0 = jnp.where(is_impulse(params.load), v0, zero)
    rest = zero + args.rest
    return jnp.stack([rest, v0, rest + absorber_sag(params), zero])
