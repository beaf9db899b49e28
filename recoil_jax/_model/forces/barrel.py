"""The barrel and the paper's recoil spring and direction-dependent damper
(`docs/model.md`): the family's first member."""

from __future__ import annotations

from typing import Any, ClassVar

from ..._model.forces.family import Design, Force, registered
from ..._model.forces.smoothing import smooth_relu
from ..._model.parameter_table import PAPER_BARREL_MASS
from ..._model.registry import GROUPS, Group, Limits, check_value

__all__ = ["Barrel"]


class Barrel(Force):
    """The recoiling barrel, its recoil spring and its direction-dependent damper.

    Defaults are the paper's values. Units: kg, N/m, N·s/m, m/s.

    - `M`: recoiling mass.
    - `k`: recoil spring stiffness (barrel to mounting wall P).
    - `c_out`: recoil damping while the barrel moves rearwards (`v_M > 0`).
    - `c_ret`: damping on the return stroke (`v_M < 0`).
    - `v0`: barrel velocity right after the shot; see `Barrel.from_shot`.
    """

    M: Any = registered("M")
    k: Any = registered("k")
    c_out: Any = registered("c_out")
    c_ret: Any = registered("c_ret")
    v0: Any = registered("v0")

    GROUP: ClassVar[Group] = GROUPS["barrel"]

    def anchoring(self, y, t, design: Design, smoothing) -> dict[str, Any]:
        """The recoil spring `k x_M` and the damper `c(v_M) v_M` (N), with
        `c(v) v = c_ret v + (c_out − c_ret) max(0, v)`: continuous, only its slope
        switches (smoothed over `damping_width`)."""
        x_M, v_M = y[0], y[1]
        width_v = smoothing.damping_width
        damper = self.c_ret * v_M + (self.c_out - self.c_ret) * smooth_relu(v_M, width_v)
        return {"recoil_spring": self.k * x_M, "recoil_damper": damper}

    def held_change(self, design: Design) -> Any:
        """0: the spring's and damper's forces are the barrel's state's."""
        return 0.0

    @classmethod
    def from_shot(
        cls, projectile_mass: Any, muzzle_velocity: Any, M: Any = PAPER_BARREL_MASS, **kwargs
    ) -> Barrel:
        """Barrel whose initial velocity comes from momentum conservation at the shot:
        `v0 = projectile_mass * muzzle_velocity / M` (kg, m/s, kg)."""
        check_value(
            "Barrel.from_shot",
            "projectile_mass",
            projectile_mass,
            Limits(unit="kg", lower=0.0, lower_open=True),
        )
        check_value(
            "Barrel.from_shot",
            "muzzle_velocity",
            muzzle_velocity,
            Limits(unit="m/s", lower=0.0, lower_open=True),
        )
        check_value("Barrel", "M", M, cls.LIMITS["M"])
        return cls(M=M, v0=projectile_mass * muzzle_velocity / M, **kwargs)
