"""The mount (`docs/model.md`, *Firing envelope*): the gun on the ground, whose
parameters (`Mount`) the stability margin reads. It pushes on nothing: a part, not a
force."""

from __future__ import annotations

from typing import Any, ClassVar

from ..._model.forces.family import Part, registered
from ..._model.registry import GROUPS, Group

__all__ = ["Mount"]


class Mount(Part):
    """The gun on the ground, for the stability margin (its wheels must not lift).

    - `mount_mass` m_g (kg): the whole gun, recoiling parts included; 0 is no mount,
      else at least `M + m`.
    - `cg_distance` L_w (m): from the spade forward to the gun's centre of gravity, in
      battery, horizontally.
    - `trunnion_height` h (m): the bore axis at the trunnion above the spade's ground
      contact.
    - `spade_distance` L_s (m): from the spade forward to the trunnion, horizontally.
    """

    mount_mass: Any = registered("mount_mass")
    cg_distance: Any = registered("cg_distance")
    trunnion_height: Any = registered("trunnion_height")
    spade_distance: Any = registered("spade_distance")

    GROUP: ClassVar[Group] = GROUPS["mount"]
