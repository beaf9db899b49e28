"""The counter-recoil buffer (`docs/model.md`, *Firing envelope*): its parameters
(`CounterRecoilBuffer`), a dashpot on the way back over the last stretch before
battery."""

from __future__ import annotations

from typing import Any, ClassVar

from ..._model.forces.family import Design, Force, registered
from ..._model.forces.smoothing import onset_ramp, smooth_step
from ..._model.registry import GROUPS, Group
from ..._model.settings import Smoothing

__all__ = ["CounterRecoilBuffer", "counter_recoil_force"]


class CounterRecoilBuffer(Force):
    """The counter-recoil buffer, a dashpot acting only on the way back over the last
    stretch before battery: `F_cb = c_b v_M` while `v_M < 0` and `x_M < L_b`.

    - `buffer_damping` c_b (N·s/m), `buffer_length` L_b (m).
    """

    buffer_damping: Any = registered("buffer_damping")
    buffer_length: Any = registered("buffer_length")

    GROUP: ClassVar[Group] = GROUPS["counter_recoil_buffer"]

    def anchoring(self, y, t, design: Design, smoothing) -> dict[str, Any]:
        """`F_cb` (N, <= 0; `counter_recoil_force`)."""
        return {"counter_recoil": counter_recoil_force(y, self, smoothing)}

    def potential(self, x_M, design: Design) -> Any:
        """0: it only dissipates."""
        return 0.0

    def anchoring_bound(self, reach, two_energy, design: Design) -> Any:
        """0: its share is never positive (`F_cb <= 0`)."""
        return 0.0

    def held_change(self, design: Design) -> Any:
        """0: its speed ramp is one-sided: a barrel at rest feels none of it."""
        return 0.0


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
