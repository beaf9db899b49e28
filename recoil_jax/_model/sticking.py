"""Stick and slip as modes of the solve (`STICKING`, `docs/model.md`, *Sticking*): a barrel
held by its rails' friction is still, to the bit, and costs no steps; sliding, the
friction is its bound against the motion. The loop switches at the exact roots: the
barrel's speed coming to 0 (it sticks, or turns back if the net force exceeds the band),
and the net force on a held barrel leaving the band (it slips the way it is pushed).

Modes: 0 held, +1 sliding rearward (recoil), −1 sliding forward. Every function of the
loop sees its mode in `ModelArgs.mode`."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp

from .._model.equations import ModelArgs
from .._model.forces.rails import friction_bound
from .._model.forces.system import forces, friction_mode, net_force
from .._model.modes import Modes

__all__ = ["STICKING", "net_and_bound"]


def net_and_bound(t, y, args: ModelArgs):
    """`(N, F_max)` (N): the net force on the barrel from everything but friction at
    `(t, y)`, and the most the friction holds."""
    f = forces(y, args.params, args.smoothing, args.contact_width, t=t, mode=0.0)
    return net_force(f), friction_bound(args.params)


def _enter(args: ModelArgs, mode) -> ModelArgs:
    return dataclasses.replace(args, mode=mode)


def _settle(t, y, args: ModelArgs):
    """The mode at t = 0 and after a round's jump (`friction_mode`: held only where the
    barrel is still, so the state stands as it is)."""
    net, bound = net_and_bound(t, y, args)
    return y, friction_mode(net, bound, y[1])


def _guard(t, y, args: ModelArgs):
    """Sliding: the speed the mode's way (it turns at 0). Held: the band's margin
    `F_max − |N|` (it slips at 0)."""
    net, bound = net_and_bound(t, y, args)
    return jnp.where(args.mode != 0, args.mode * y[1], bound - jnp.abs(net))


def _switch(t, y, args: ModelArgs):
    """At a root: a sliding barrel stops (speed 0) and is held within the band, else
    turns the way it is pushed; a held one slips the way it is pushed."""
    y = y.at[1].set(0.0)
    net, bound = net_and_bound(t, y, args)
    slips = jnp.sign(net)
    mode = jnp.where(args.mode == 0, slips, friction_mode(net, bound, jnp.zeros_like(net)))
    return y, mode


#: The stick–slip modes of a design with rails (`Modes`), for `args = model_args(...)`.
STICKING = Modes(enter=_enter, settle=_settle, guard=_guard, switch=_switch)
