"""The reference's segment loop: `solve_ivp` from event to event, each segment smooth, with
the running peaks and the firing envelope's metrics kept on the way."""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import numpy as np

from ..._model.reference.physics import MAX_EMPTY, Event, Mode
from ..._model.reference.switching import HardModel

__all__ = ["Done", "EnvelopeMetrics", "RunningPeaks", "initial_state", "integrate"]


class RunningPeaks:
    """Running maxima (value, time) of x_M, F_AN and F_ct, the running minimum of F_AN,
    and the stroke's range."""

    def __init__(self):
        self.displacement = (-np.inf, 0.0)
        self.anchoring = (-np.inf, 0.0)
        self.low = (np.inf, 0.0)  # the least F_AN
        self.contact = (0.0, 0.0)
        self.min_stroke = np.inf  # the first state considered (t = 0) sets both
        self.max_stroke = -np.inf

    def consider(self, model: HardModel, t, y, mode: Mode) -> None:
        if y[0] > self.displacement[0]:
            self.displacement = (y[0], t)
        anchoring = model.anchoring(y, mode, t)
        if anchoring > self.anchoring[0]:
            self.anchoring = (anchoring, t)
        if anchoring < self.low[0]:
            self.low = (anchoring, t)
        contact = model.contact_force(y, mode)
        if contact > self.contact[0]:
            self.contact = (contact, t)
        stroke = y[2] - y[0]
        self.min_stroke = min(self.min_stroke, stroke)
        self.max_stroke = max(self.max_stroke, stroke)

    def consider_low(self, model: HardModel, t, y, mode: Mode) -> None:
        """The least F_AN only (at a local minimum of it)."""
        anchoring = model.anchoring(y, mode, t)
        if anchoring < self.low[0]:
            self.low = (anchoring, t)

    def metrics(self, x_r: float = 0.0) -> dict[str, float]:
        pull = max(0.0, -self.low[0])
        mount = self.anchoring if self.anchoring[0] >= -self.low[0] else (-self.low[0], self.low[1])
        return {
            "peak_displacement": self.displacement[0] - x_r,
            "peak_displacement_time": self.displacement[1],
            "peak_anchoring_force": self.anchoring[0],
            "peak_anchoring_force_time": self.anchoring[1],
            "peak_contact_force": self.contact[0],
            "peak_contact_force_time": self.contact[1],
            "min_stroke": self.min_stroke,
            "max_stroke": self.max_stroke,
            "peak_pull_force": pull,
            "peak_pull_force_time": self.low[1],
            "peak_mount_load": mount[0],
            "peak_mount_load_time": mount[1],
            "rest_position": x_r,
        }


class EnvelopeMetrics:
    """The envelope's metrics as the solve goes: the barrel's forward crossings of
    `x_M = x_r + 1 mm` (time, speed), the stability margin's running minimum (with a mount),
    and the times the barrel sticks and slips."""

    def __init__(self, model: HardModel):
        self.model = model
        self.returns: list[tuple[float, float]] = []
        self.margin = (np.inf, 0.0)
        self.sticks: list[float] = []
        self.slips: list[float] = []

    def consider(self, t, y, mode: Mode) -> None:
        if self.model.mount:
            margin = self.model.margin(t, y, mode)
            if margin < self.margin[0]:
                self.margin = (margin, t)

    def switched(self, t, before: Mode, after: Mode) -> None:
        """Note the barrel sticking or slipping at `t`, where the mode went from `before`
        to `after`."""
        if after.stuck and not before.stuck:
            self.sticks.append(t)
        elif before.stuck and not after.stuck:
            self.slips.append(t)

    def metrics(self, t_end: float, y_end: np.ndarray) -> dict:
        """`return_time` (s from the last round's firing; None if the barrel never came
        back), `battery_speed` (m/s, `−v_M` then; None likewise), `returned`,
        `residual_displacement` (m, `x_M − x_r` at the end), `stability_margin` and its time
        (None without a mount), `sticks` and `slips` (the times, s)."""
        last = float(self.model.firing_times()[-1])
        after = [(t, v) for t, v in self.returns if t > last]
        first = min(after) if after else None
        return {
            "return_time": None if first is None else first[0] - last,
            "battery_speed": None if first is None else -first[1],
            "returned": first is not None,
            "residual_displacement": float(y_end[0] - self.model.x_r),
            "stability_margin": self.margin[0] if self.model.mount else None,
            "stability_margin_time": self.margin[1] if self.model.mount else None,
            "end_time": float(t_end),
            "sticks": list(self.sticks),
            "slips": list(self.slips),
        }


def initial_state(model: HardModel) -> np.ndarray:
    """From the static rest in battery: `x_M = x_r`, `v_M = v0` under an impulse (else
    0), the absorber at rest at its sag on the barrel, `x_m = x_r + m g sin θ / k_r`."""
    return np.array([model.x_r, model.v0 if model.impulse else 0.0, model.x_m0, 0.0])


@dataclasses.dataclass
class Done:
    """What `integrate` ends with."""

    running: RunningPeaks
    envelope: EnvelopeMetrics
    segments: int
    status: str
    t: float
    y: np.ndarray


class _Events(NamedTuple):
    """The events every segment watches, beside its mode's switches: where a tracked
    quantity may peak, where `F_AN` may have its minimum, and the envelope's."""

    peaks: list[Event]
    lows: list[Event]
    envelope: list[Event]

    def all(self, switches: list[Event]) -> list[Event]:
        return self.peaks + self.lows + self.envelope + switches


def integrate(model, t1, rtol, atol, method, max_segments, ts=None, samples=None, audit=False):
    """The segment loop; with `ts`, `samples` filled in place; with `audit`, the state
    carries the breech force's work and the dissipated energy (`reference_energy`)."""
    import scipy.integrate  # when used: `import recoil_jax` stays quick

    watched = _Events(model.peak_events(), model.low_events(), model.envelope_events())
    running = RunningPeaks()
    envelope = EnvelopeMetrics(model)
    t = 0.0
    y = initial_state(model)
    if audit:
        y = np.concatenate([y, [0.5 * model.M * y[1] ** 2, 0.0]])  # the impulse's work
    mode = model.classify(t, y) if model.envelope else model.initial_mode(y)
    running.consider(model, t, y, mode)
    envelope.consider(t, y, mode)
    if mode.stuck:
        envelope.sticks.append(t)
    if ts is not None:
        _sample_at(model, mode, 0.0, y, ts, samples)
    stops = [*model.stops(t1), t1]
    segments = 0
    empty = 0
    status = "ok"
    fun = model.rhs if not audit else _audited(model)
    while t < t1 and status == "ok":
        segments += 1
        if segments > max_segments:
            raise RuntimeError(
                f"reference solver: more than {max_segments} switch events before t1 = {t1} "
                f"(stopped at t = {t:.6g} s); use a shorter t1"
            )
        end = next(s for s in stops if s > t)
        switches = model.switch_events(mode)
        options = {}
        if model.envelope:
            switches = [_off_the_surface(event, t) for event in switches]
            options = model.step_limit(t, end, mode)
        sol = scipy.integrate.solve_ivp(
            fun,
            (t, end),
            y,
            method=method,
            rtol=rtol,
            atol=atol,
            args=(mode,),
            events=watched.all(switches),
            dense_output=ts is not None,
            **options,
        )
        if sol.status < 0:
            raise RuntimeError(f"reference solver failed: {sol.message}")
        _record_events(model, sol, mode, watched, running, envelope)
        if ts is not None:
            _sample(model, sol, mode, t, sol.t[-1], ts, samples)
        empty = empty + 1 if sol.t[-1] == t else 0
        if empty > MAX_EMPTY:
            raise RuntimeError(
                f"reference solver: {MAX_EMPTY} switch events in a row at t = {t:.17g} s "
                f"without progress (mode {mode})"
            )
        t, y = sol.t[-1], sol.y[:, -1].copy()
        running.consider(model, t, y, mode)
        envelope.consider(t, y, mode)
        if sol.status == 1:
            first = len(watched.all([]))
            fired = {
                event.kind for i, event in enumerate(switches) if sol.t_events[first + i].size > 0
            }
            if "bottom" in fired:
                status = "bottomed_out"
            mode = _after_switch(model, t, y, mode, fired, running, envelope)
        elif t < t1:  # a stop: a round fires (a velocity jump for an impulse load)
            mode = _after_stop(model, t, y, mode, audit, running, envelope)
            if ts is not None:  # a sample at the firing itself: after it, as at t = 0
                _sample_at(model, mode, t, y, ts, samples)
    return Done(running, envelope, segments, status, t, y)


def _record_events(model, sol, mode: Mode, watched: _Events, running, envelope) -> None:
    """Keep what the segment's watched events found: candidate peaks, lows of `F_AN`,
    the barrel's returns and the margin at the envelope's events."""
    assert sol.t_events is not None and sol.y_events is not None
    found = list(zip(sol.t_events, sol.y_events, strict=True))
    for te, ye in _located(found[: len(watched.peaks)]):
        running.consider(model, te, ye, mode)
    lows = found[len(watched.peaks) : len(watched.peaks) + len(watched.lows)]
    for te, ye in _located(lows):
        running.consider_low(model, te, ye, mode)
    start = len(watched.peaks) + len(watched.lows)
    envelope_found = found[start : start + len(watched.envelope)]
    for event, (times, states) in zip(watched.envelope, envelope_found, strict=True):
        for te, ye in zip(times, states, strict=True):
            if event.kind == "return":
                envelope.returns.append((float(te), float(ye[1])))
            envelope.consider(te, ye, mode)


def _located(found):
    """Every `(t, y)` located by the events of `found` (`(times, states)` per event)."""
    for times, states in found:
        yield from zip(times, states, strict=True)


def _after_switch(model, t, y, mode: Mode, fired: set[str], running, envelope) -> Mode:
    """The mode after the switches `fired` at `(t, y)`."""
    if not model.envelope:
        return model.next_mode(mode, fired, y)
    new = model.next_envelope_mode(t, mode, fired, y)
    envelope.switched(t, mode, new)
    # Friction, the counter-recoil buffer and the stop's clamp can make F_AN jump at a
    # switch: both sides count.
    running.consider(model, t, y, new)
    envelope.consider(t, y, new)
    return new


def _after_stop(model, t, y, mode: Mode, audit: bool, running, envelope) -> Mode:
    """The state (in place) and the mode after a stop at `t`: a round fired there jumps
    the barrel's velocity by `v0` under an impulse load."""
    if model.impulse and np.any(np.isclose(t, model.firing_times()[1:], rtol=0, atol=1e-12)):
        if audit:
            y[4] += 0.5 * model.M * ((y[1] + model.v0) ** 2 - y[1] ** 2)
        y[1] += model.v0
    if model.envelope:
        new = model.classify(t, y, previous=mode)
        new = new if not model.buffer else dataclasses.replace(new, piece=mode.piece)
        envelope.switched(t, mode, new)
    else:
        new = model.initial_mode(y)
        new = new if not model.buffer else dataclasses.replace(new, piece=mode.piece)
    running.consider(model, t, y, new)
    envelope.consider(t, y, new)
    return new


def _off_the_surface(event: Event, start: float) -> Event:
    """`event` for a segment from `start` whose state may lie exactly on the event's
    surface (a barrel at rest at t = 0, or slipping from a stick): there its value, 0,
    reads as just inside the mode's side, so that a crossing after a first excursion
    is located where it is, not at the start (scipy takes a zero at a step's start for
    a crossing whenever the step ends across the surface)."""
    inside = -math.copysign(1e-300, event.direction) if event.direction else 0.0

    def surface(t, y, mode):
        value = event.surface(t, y, mode)
        return inside if value == 0 and t == start else value

    return dataclasses.replace(event, surface=surface)


def _audited(model: HardModel):
    """The vector field with the breech force's power and the dissipated power."""

    def fun(t, y, mode):
        breech, lost = model.powers(t, y, mode)
        return np.concatenate([model.rhs(t, y, mode), [breech, lost]])

    return fun


def _sample(model, sol, mode, start, end, ts, samples):
    """Fill the samples at the times in `(start, end]` from a segment's dense output."""
    inside = (ts > start) & (ts <= end)
    if inside.any():
        _fill(model, mode, inside, ts[inside], sol.sol(ts[inside]), samples)


def _sample_at(model, mode, t, y, ts, samples):
    """Fill the samples at exactly `t` (the start, or a firing: after its impulse) with
    the state `y`."""
    inside = ts == t
    if inside.any():
        _fill(model, mode, inside, ts[inside], np.repeat(y[:, None], inside.sum(), 1), samples)


def _fill(model, mode, inside, times, states, samples):
    for name, row in zip(("x_M", "v_M", "x_m", "v_m"), states[:4], strict=True):
        samples[name][inside] = row
    samples["F_AN"][inside] = [
        model.anchoring(y, mode, t) for t, y in zip(times, states.T, strict=True)
    ]
    samples["F_ct"][inside] = [model.contact_force(y, mode) for y in states.T]
