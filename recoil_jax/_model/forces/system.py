"""All forces of a design at one state (`Forces`, `forces`): the paper's spring, dampers,
coupling and contact, and each part of the hardware and of the firing envelope the
design has, with the rails' friction taking what the others leave (`docs/model.md`).

State `y = (x_M, v_M, x_m, v_m)` (m, m/s), recoil is +x. The simplified model is the
absorber-free case (`params.absorber is None`): the absorber states stay at zero.
"""

from __future__ import annotations

import functools
import operator
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..._model.forces.absorber import contact_width, coupling_forces
from ..._model.forces.loads import breech_force
from ..._model.forces.rails import GRAVITY, friction_bound, sin_cos
from ..._model.metrics import METRICS
from ..._model.params import RecoilParams
from ..._model.registry import ParameterError, is_concrete
from ..._model.settings import Smoothing

__all__ = [
    "Forces",
    "Structure",
    "check_envelope_metrics",
    "forces",
    "friction_mode",
    "has_envelope",
    "moded_friction",
    "net_force",
]


class Forces(eqx.Module):
    """The forces of the system at one state (N). Signs: as they act on the barrel's
    equation `M a_M = breech − anchoring − coupling_spring − coupling_damper − contact`
    (+ gravity's pull along the rails).

    - `shares`: the parts of the anchoring force `F_AN`, in the order they are summed,
      named by `names` (static): each force's (`Force.anchoring`: the recoil spring and
      damper, the buffer, the recuperator and its preload, the counter-recoil buffer,
      any force added outside the package), the rails' friction, then the reactions
      (the battery stop's `F_s`), which `F_AN` loses (`reactions`, static: how many of
      the last are). Read one by its name (`share`), or by the attributes below; those
      the design has not got are None.
    - `coupling_spring`, `coupling_damper`, `contact` (`F_ct`, >= 0, pushing the absorber
      forward), `contact_elastic` (its conservative part): between barrel and absorber,
      0 without one;
    - `breech` (`F_b(t)`, pulse or table loads), `gravity` (`M g sin θ`, along `+x` on
      the barrel) and `absorber_gravity` (`m g sin θ`): None where absent."""

    shares: tuple[Any, ...]
    names: tuple[str, ...] = eqx.field(static=True)
    reactions: int = eqx.field(static=True)
    coupling_spring: Any
    coupling_damper: Any
    contact: Any
    contact_elastic: Any
    breech: Any = None
    gravity: Any = None
    absorber_gravity: Any = None

    def share(self, name: str) -> Any:
        """The share of `F_AN` named `name` (N), or None if the design has none."""
        return self.shares[self.names.index(name)] if name in self.names else None

    @property
    def anchoring(self):
        """`F_AN`, the load into the mounting (wall P): the shares summed in order, less
        the reactions."""
        added = len(self.shares) - self.reactions
        total = functools.reduce(operator.add, self.shares[:added])
        return functools.reduce(operator.sub, self.shares[added:], total)

    @property
    def recoil_spring(self):
        """`k x_M` (N), the recoil spring."""
        return self.share("recoil_spring")

    @property
    def recoil_damper(self):
        """`c(v_M) v_M` (N), the recoil damper."""
        return self.share("recoil_damper")

    @property
    def buffer(self):
        """`F_h` (N), the throttling orifice's force; None without one."""
        return self.share("buffer")

    @property
    def recuperator(self):
        """`F_g` (N), the gas recuperator; None without one."""
        return self.share("recuperator")

    @property
    def preload(self):
        """`F_p` (N), the preload on the recuperator's gas column; None without."""
        return self.share("preload")

    @property
    def counter_recoil(self):
        """`F_cb` (N, <= 0), the counter-recoil buffer; None without one."""
        return self.share("counter_recoil")

    @property
    def friction(self):
        """`F_f` (N), rail friction; None without rails."""
        return self.share("friction")

    @property
    def stop(self):
        """`F_s` (N, >= 0), the battery stop pushing the barrel back; None without."""
        return self.share("stop")


# Jitted so that JAX traces it once per shape: a gradient program evaluates the forces
# in about 30 places (stages, rates, jumps, peaks), and re-running this Python for each
# was a third of its trace time. XLA inlines the call: the compiled code is the same.
@jax.jit
def forces(
    y, params: RecoilParams, smoothing: Smoothing, width_contact=None, t=None, mode=None
) -> Forces:
    """All forces at state `y` (shape `(4,)`), smoothed as `smoothing` says; the breech
    force (designs with a pulse or table load) needs the time `t` (s). `mode`: the
    barrel's on its rails (`sticking`: 0 held, ±1 sliding that way), as the stepping
    loop carries it; None: as the state has it (`friction_mode`). The family's sum
    (`Force`): each force the design has gives its shares of `F_AN`, the mechanism's
    first, then the rails' friction (which takes what the others leave), then the
    reactions (the battery stop).

    `width_contact` (m) may be passed precomputed (it depends only on the parameters).
    """
    mechanism, reactions = {}, {}
    for force in params.forces():
        shares = force.anchoring(y, t, params, smoothing)
        taken = set(shares) & (set(mechanism) | set(reactions) | {"friction"})
        if taken:  # (one name a share: `Forces.share` reads it by its name)
            raise ParameterError(
                f"{type(force).__name__}.anchoring: the share {sorted(taken)[0]!r} is "
                "another force's: give it another name"
            )
        (reactions if force.REACTION else mechanism).update(shares)
    external = {}
    if params.load is not None and t is not None:
        external["breech"] = breech_force(t, params)
    if params.rails is not None:
        sin, _ = sin_cos(params)
        external["gravity"] = params.barrel.M * GRAVITY * sin
        if params.absorber is not None:
            external["absorber_gravity"] = params.absorber.m * GRAVITY * sin
    if params.absorber is None:
        zero = jnp.zeros_like(y[0])
        between = dict.fromkeys(
            ("coupling_spring", "coupling_damper", "contact", "contact_elastic"), zero
        )
    else:
        if width_contact is None:
            width_contact = contact_width(params, smoothing)
        between = coupling_forces(y, params, smoothing, width_contact)
    shares = mechanism | reactions
    unheld = Forces(tuple(shares.values()), tuple(shares), len(reactions), **between, **external)
    if params.rails is None:
        return unheld
    net, bound = net_force(unheld), friction_bound(params)
    if mode is None:  # a state met outside the loop: its mode from the state itself
        mode = friction_mode(net, bound, y[1])
    friction = moded_friction(net, bound, mode)
    shares = mechanism | {"friction": friction} | reactions
    return Forces(tuple(shares.values()), tuple(shares), len(reactions), **between, **external)


class Structure(eqx.Module):
    """Which parts a design has: static, from its pytree's structure (the groups present),
    not from its values. A program resolves it once (`Structure.of`) and carries it in
    its `args` (`ModelArgs.structure`), where the signals (and through them the bounds)
    and the loop's wiring read it.

    - `absorber`: the absorber (else the simplified model: no contact, no stroke);
    - `envelope`: any part of the firing envelope (`Group.envelope`: rails, the battery
      stop, the counter-recoil buffer, a mount). Such a design is solved to `t1` (its
      return and its rest are metrics), the others stop once their peaks are certain."""

    absorber: bool = eqx.field(static=True)
    envelope: bool = eqx.field(static=True)

    @classmethod
    def of(cls, params: RecoilParams) -> Structure:
        return cls(
            absorber=params.absorber is not None,
            envelope=any(part.GROUP.envelope for part in params.parts().values()),
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


def friction_mode(net, bound, speed):
    """The stick–slip mode of a barrel met afresh (`sticking`): moving, sliding its way
    (±1); still, held (0) within the band `|net| <= bound`, else sliding the way it is
    pushed."""
    still = jnp.where(jnp.abs(net) <= bound, 0.0, jnp.sign(net))
    return jnp.where(speed != 0, jnp.sign(speed), still)


def moded_friction(net, bound, mode):
    """The rails' friction (N) in a mode of the stick–slip (`sticking`), where the net
    force on the barrel from everything but friction is `net` and the most the friction
    holds `bound`: held (mode 0), all of `net` (within the band, which the mode's guard
    keeps); sliding the way `mode = ±1` says, `bound` against the motion."""
    return jnp.where(mode == 0, jnp.clip(net, -bound, bound), mode * bound)
