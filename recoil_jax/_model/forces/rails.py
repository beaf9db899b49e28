"""The rails (`docs/model.md`, *Firing envelope*): their parameters (`Rails`), gravity
along them at the elevation, the absorber's sag and the recoiling parts' axial weight,
and the most their friction holds."""

from __future__ import annotations

from typing import Any, ClassVar

import jax.numpy as jnp

from ..._model.forces.family import Design, Part, registered
from ..._model.registry import GROUPS, Group

__all__ = ["GRAVITY", "Rails", "absorber_sag", "axial_weight", "friction_bound", "sin_cos"]

#: Standard gravity (m/s²), as `docs/model.md` fixes it.
GRAVITY = 9.80665


class Rails(Part):
    """The rails the recoiling parts slide on: their elevation and Coulomb friction
    (`docs/model.md`, *Firing envelope*).

    - `elevation` θ (degrees above horizontal, -10 to 85): gravity pulls the barrel and
      the absorber rearward along the rails with `g sin θ`.
    - `friction_force` F_0 (N) and `friction_coefficient` μ: the friction's largest
      value `F_max = F_0 + μ (M + m) g cos θ`, which holds a barrel at rest as long as
      the net force on it is within `±F_max`.
    """

    elevation: Any = registered("elevation")
    friction_force: Any = registered("friction_force")
    friction_coefficient: Any = registered("friction_coefficient")

    GROUP: ClassVar[Group] = GROUPS["rails"]


def absorber_sag(params: Design):
    """The absorber's static sag on the barrel, `m g sin θ / k_r` (m, rearward; 0 on level
    rails or without an absorber): where it starts, and where it rests on a held barrel."""
    if params.rails is None or params.absorber is None:
        return 0.0
    sin, _ = sin_cos(params)
    return params.absorber.m * GRAVITY * sin / params.absorber.k_r


def sin_cos(params: Design):
    """`(sin θ, cos θ)` of the rails' elevation θ (0 and 1 on level rails, or without)."""
    theta = jnp.deg2rad(params.rails.elevation) if params.rails is not None else 0.0
    return jnp.sin(theta), jnp.cos(theta)


def friction_bound(params: Design):
    """`F_max = F_0 + μ (M + m) g cos θ` (N), the most the rails' friction holds."""
    rails = params.rails
    assert rails is not None
    _, cos = sin_cos(params)
    mass = params.barrel.M + (0.0 if params.absorber is None else params.absorber.m)
    return rails.friction_force + rails.friction_coefficient * mass * GRAVITY * cos


def axial_weight(params: Design):
    """`(M + m) g sin θ` (N): the recoiling parts' weight along `+x` (0 on level rails or
    without rails), which the mechanism holds at rest."""
    if params.rails is None:
        return 0.0
    sin, _ = sin_cos(params)
    mass = params.barrel.M + (0.0 if params.absorber is None else params.absorber.m)
    return mass * GRAVITY * sin
