"""The battery stop (`docs/model.md`, *Firing envelope*): its parameters (`BatteryStop`),
a Hunt–Crossley contact the barrel cannot pass forward."""

from __future__ import annotations

from typing import Any, ClassVar

from ..._model.forces.family import Design, Force, registered
from ..._model.forces.smoothing import onset_ramp, positive_power, smooth_relu
from ..._model.registry import GROUPS, Group
from ..._model.settings import Smoothing

__all__ = ["BatteryStop", "stop_force"]


class BatteryStop(Force):
    """The battery stop at `x_M = 0`, a Hunt–Crossley contact the barrel cannot pass
    forward: `F_s = k_s δ^n_s (1 + λ_s δ̇)`, `δ = −x_M > 0`, never pulling.

    - `stop_stiffness` k_s (N/m^n_s; 0 is no stop), `stop_exponent` n_s (1 to 2),
      `stop_damping` λ_s (s/m).
    """

    stop_stiffness: Any = registered("stop_stiffness")
    stop_exponent: Any = registered("stop_exponent")
    stop_damping: Any = registered("stop_damping")

    GROUP: ClassVar[Group] = GROUPS["battery_stop"]

    #: The gun's limit: summed after the friction (`Force`).
    REACTION: ClassVar[bool] = True

    def anchoring(self, y, t, design: Design, smoothing) -> dict[str, Any]:
        """`F_s` (N, >= 0): the stop pushes the barrel back; a reaction, which `F_AN`
        loses."""
        return {"stop": stop_force(y[0], y[1], self, smoothing)}

    def held_change(self, design: Design) -> Any:
        """0: the stop's force is the barrel's state's."""
        return 0.0


def stop_force(x_M, v_M, stop: BatteryStop, smoothing: Smoothing):
    """The battery stop's `F_s = k_s δ^n_s (1 + λ_s δ̇)` (N, >= 0), `δ = −x_M`, pushing
    the barrel back: its onset smoothed over `stop_width` on the stop's side only
    (`onset_ramp`: a barrel at rest in battery feels none of it), and its no-pull clamp
    `max(0, 1 + λ_s δ̇)` with `δ̇ = −v_M`, smoothed as the contact's."""
    depth = onset_ramp(-x_M, smoothing.stop_width)
    elastic = stop.stop_stiffness * positive_power(depth, stop.stop_exponent)
    factor = smooth_relu(1.0 - stop.stop_damping * v_M, stop.stop_damping * smoothing.damping_width)
    return elastic * factor
