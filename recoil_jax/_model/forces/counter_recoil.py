"""The counter-recoil buffer (`docs/model.md`, *Firing envelope*): a dashpot on the way
back over the last stretch before battery."""

from __future__ import annotations

from ..._model.forces.smoothing import onset_ramp, smooth_step
from ..._model.params import CounterRecoilBuffer
from ..._model.settings import Smoothing

__all__ = ["counter_recoil_force"]


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
