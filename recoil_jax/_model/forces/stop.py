"""The battery stop (`docs/model.md`, *Firing envelope*): a Hunt–Crossley contact the
barrel cannot pass forward."""

from __future__ import annotations

from ..._model.forces.smoothing import onset_ramp, positive_power, smooth_relu
from ..._model.params import BatteryStop
from ..._model.settings import Smoothing

__all__ = ["stop_force"]


def stop_force(x_M, v_M, stop: BatteryStop, smoothing: Smoothing):
    """The battery stop's `F_s = k_s δ^n_s (1 + λ_s δ̇)` (N, >= 0), `δ = −x_M`, pushing
    the barrel back: its onset smoothed over `stop_width` on the stop's side only
    (`onset_ramp`: a barrel at rest in battery feels none of it), and its no-pull clamp
    `max(0, 1 + λ_s δ̇)` with `δ̇ = −v_M`, smoothed as the contact's."""
    depth = onset_ramp(-x_M, smoothing.stop_width)
    elastic = stop.stop_stiffness * positive_power(depth, stop.stop_exponent)
    factor = smooth_relu(1.0 - stop.stop_damping * v_M, stop.stop_damping * smoothing.damping_width)
    return elastic * factor
