"""An independent reference solver: scipy `solve_ivp`, hard switches, event-located.

Shares no model code with the JAX model: the equations are written out again here in
NumPy. Each switch (contact onset `δ = 0`, damping sign `v_M = 0`, the no-pull clamp
`1 + λ_c δ̇ = 0`, the barrel crossing an orifice knot) ends an integration segment at an
exactly located event, and each round's firing and each point of a force table ends one
too, so every segment is smooth and the integrator keeps its full order. Peaks are located
as events of their time derivatives (and checked at every segment end), not read off a
grid. A barrel that reaches 0.95 of the recuperator's gas column is reported
(`status`), like the JAX model does.

Used by the tests as ground truth across the documented ranges, and as the serial
baseline of the benchmarks.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping

import numpy as np

from .._model.params import params_from_values, params_to_values

__all__ = ["reference_history", "reference_peaks"]

_BOTTOM = 0.95  # the recuperator's gas column may be compressed to this fraction


@dataclasses.dataclass(frozen=True)
class _Mode:
    """Which side of each switch the state is on; fixed within a segment."""

    moving_out: bool  # v_M > 0: damping c_out
    contact: bool  # δ > 0
    clamped: bool  # 1 + λ δ̇ < 0 while in contact: F_ct = 0
    piece: int = 0  # the orifice piece x_M lies in: -1 below 0, K-1 beyond x_a


@dataclasses.dataclass(frozen=True)
class _Event:
    """A `solve_ivp` event: the zeros of `surface(t, y, mode)` crossed in `direction`
    (0: either way); `terminal` ends the segment there, `kind` says which switch."""

    surface: Callable[[float, np.ndarray, _Mode], float]
    direction: float = 0.0
    terminal: bool = False
    kind: str = ""

    def __call__(self, t, y, mode) -> float:
        return self.surface(t, y, mode)


class _HardModel:
    """The model with hard switches, for flat parameter values and an optional force
    table `(t, F)` of one round."""

    def __init__(self, p: Mapping[str, float], table=None):
        self.M, self.k, self.c_out, self.c_ret, self.v0 = (
            p["M"],
            p["k"],
            p["c_out"],
            p["c_ret"],
            p["v0"],
        )
        self.absorber = p["m"] > 0
        self.m = p["m"] if self.absorber else 1.0
        self.gap = p.get("gap", 0.0)
        self.k_r = p.get("k_r", 0.0)
        self.c_r = p.get("c_r", 0.0)
        self.k_c, self.n_c, self.lam = p["k_c"], p["n_c"], p["lambda_c"]
        # Load: rounds at j·T; impulse (pulse_time = 0), gamma pulse, or table.
        self.shots = int(p.get("shots", 1))
        self.interval = p.get("fire_interval", 0.5)
        self.pulse_time = p.get("pulse_time", 0.0)
        self.table = None if table is None else (np.asarray(table[0]), np.asarray(table[1]))
        self.impulse = self.table is None and self.pulse_time == 0.0
        # Hydraulic buffer.
        knots = [p[f"orifice_{i}"] for i in range(32) if f"orifice_{i}" in p]
        self.knots = np.asarray(knots)
        area = p.get("piston_area", 0.0)
        self.buffer = len(knots) > 0
        if self.buffer:
            self.knot_x = p["orifice_length"] * np.arange(len(knots)) / (len(knots) - 1)
            cd = p["discharge_coefficient"]
            self.coefficient = p["oil_density"] * area**3 / (2.0 * cd**2)
        # Gas recuperator.
        # A zero force is no recuperator (no gas column to bottom).
        self.recuperator = p.get("recuperator_force", 0.0) > 0
        if self.recuperator:
            self.F_r = p["recuperator_force"]
            self.L_r = p["recuperator_length"]
            self.gamma = p["polytropic_index"]

    # --- forces -----------------------------------------------------------------------
    def firing_times(self) -> np.ndarray:
        return self.interval * np.arange(self.shots)

    def breech(self, t) -> float:
        if self.impulse:
            return 0.0
        total = 0.0
        for tj in self.firing_times():
            tau = t - tj
            if self.table is not None:
                times, force = self.table
                if times[0] <= tau <= times[-1]:
                    total += float(np.interp(tau, times, force))
            elif tau >= 0.0:
                u = tau / self.pulse_time
                total += self.M * self.v0 / self.pulse_time * u * np.exp(-u)
        return total

    def area(self, x, mode: _Mode) -> tuple[float, float]:
        """The orifice area and its slope dA/dx on the mode's piece."""
        K = len(self.knots)
        if mode.piece < 0:
            return self.knots[0], 0.0
        if mode.piece >= K - 1:
            return self.knots[-1], 0.0
        i = mode.piece
        slope = (self.knots[i + 1] - self.knots[i]) / (self.knot_x[i + 1] - self.knot_x[i])
        return self.knots[i] + slope * (x - self.knot_x[i]), slope

    def orifice(self, y, mode: _Mode) -> float:
        if not self.buffer:
            return 0.0
        area, _ = self.area(y[0], mode)
        return self.coefficient * y[1] * abs(y[1]) / area**2

    def gas(self, x) -> float:
        if not self.recuperator:
            return 0.0
        return self.F_r * ((self.L_r / (self.L_r - x)) ** self.gamma - 1.0)

    def damping(self, mode: _Mode) -> float:
        return self.c_out if mode.moving_out else self.c_ret

    def contact_force(self, y, mode: _Mode) -> float:
        if not self.absorber or not mode.contact or mode.clamped:
            return 0.0
        delta = max(y[0] - y[2] - self.gap, 0.0)
        return self.k_c * delta**self.n_c * (1.0 + self.lam * (y[1] - y[3]))

    def anchoring(self, y, mode: _Mode) -> float:
        return self.k * y[0] + self.damping(mode) * y[1] + self.orifice(y, mode) + self.gas(y[0])

    def rhs(self, t, y, mode: _Mode):
        x_M, v_M, x_m, v_m = y
        coupling = (self.k_r * (x_M - x_m) + self.c_r * (v_M - v_m)) if self.absorber else 0.0
        f_ct = self.contact_force(y, mode)
        a_M = (self.breech(t) - self.anchoring(y, mode) - coupling - f_ct) / self.M
        a_m = (coupling + f_ct) / self.m if self.absorber else 0.0
        return np.array([v_M, a_M, v_m, a_m])

    def rates(self, t, y, mode: _Mode) -> tuple[float, float]:
        """Time derivatives of F_AN and F_ct within a mode."""
        a = self.rhs(t, y, mode)
        d_anchor = self.k * y[1] + self.damping(mode) * a[1]
        if self.buffer:
            area, slope = self.area(y[0], mode)
            d_anchor += self.coefficient * (
                2.0 * abs(y[1]) * a[1] / area**2 - 2.0 * y[1] * abs(y[1]) * slope * y[1] / area**3
            )
        if self.recuperator:
            ratio = self.L_r / (self.L_r - y[0])
            d_anchor += self.F_r * self.gamma * ratio**self.gamma / (self.L_r - y[0]) * y[1]
        d_contact = 0.0
        if self.absorber and mode.contact and not mode.clamped:
            delta = max(y[0] - y[2] - self.gap, 0.0)
            rate = y[1] - y[3]
            accel = a[1] - a[3]
            d_contact = self.k_c * (
                self.n_c * delta ** (self.n_c - 1.0) * rate * (1.0 + self.lam * rate)
                + delta**self.n_c * self.lam * accel
            )
        return d_anchor, d_contact

    # --- events -----------------------------------------------------------------------
    def peak_events(self) -> list[_Event]:
        """Non-terminal surfaces where a tracked quantity may peak: the falling zeros of
        v_M, dF_AN/dt and dF_ct/dt, and every zero of the stroke rate."""
        return [
            _Event(lambda t, y, mode: y[1], direction=-1.0),
            _Event(lambda t, y, mode: self.rates(t, y, mode)[0], direction=-1.0),
            _Event(lambda t, y, mode: self.rates(t, y, mode)[1], direction=-1.0),
            _Event(lambda t, y, mode: y[1] - y[3]),
        ]

    def switch_events(self, mode: _Mode) -> list[_Event]:
        """Terminal events that fire only when leaving the current mode's region, so a
        segment that starts on a switching surface cannot re-detect it."""
        events = [
            _Event(
                lambda t, y, mode: y[1],
                direction=-1.0 if mode.moving_out else 1.0,
                terminal=True,
                kind="velocity",
            )
        ]
        if self.absorber:
            events.append(
                _Event(
                    lambda t, y, mode: y[0] - y[2] - self.gap,
                    direction=-1.0 if mode.contact else 1.0,
                    terminal=True,
                    kind="contact",
                )
            )
            if mode.contact and self.lam > 0:
                events.append(
                    _Event(
                        lambda t, y, mode: 1.0 + self.lam * (y[1] - y[3]),
                        direction=1.0 if mode.clamped else -1.0,
                        terminal=True,
                        kind="clamp",
                    )
                )
        if self.buffer:
            K = len(self.knots)
            if mode.piece >= 0:
                low = self.knot_x[min(mode.piece, K - 1)]
                events.append(_Event(lambda t, y, mode, b=low: y[0] - b, -1.0, True, "piece down"))
            if mode.piece <= K - 2:
                high = self.knot_x[mode.piece + 1]
                events.append(_Event(lambda t, y, mode, b=high: y[0] - b, 1.0, True, "piece up"))
        if self.recuperator:
            bottom = _BOTTOM * self.L_r
            events.append(_Event(lambda t, y, mode: y[0] - bottom, 1.0, True, "bottom"))
        return events

    def piece(self, x, v) -> int:
        """The orifice piece of position `x` (on a knot, the one `v` moves into)."""
        if not self.buffer:
            return 0
        if x == 0.0 or np.any(x == self.knot_x):  # on a knot: step off it the way v goes
            x = x + np.copysign(1e-12 * self.knot_x[-1], v if v != 0 else 1.0)
        if x < 0:
            return -1
        return int(min(np.searchsorted(self.knot_x, x, side="right") - 1, len(self.knots) - 1))

    def initial_mode(self, y) -> _Mode:
        delta = y[0] - y[2] - self.gap
        contact = self.absorber and (delta > 0 or (delta == 0 and y[1] - y[3] > 0))
        clamped = contact and self.lam * (y[1] - y[3]) < -1.0
        moving_out = y[1] > 0 or (y[1] == 0 and self.breech(0.0) > 0)
        return _Mode(
            moving_out=bool(moving_out),
            contact=bool(contact),
            clamped=bool(clamped),
            piece=self.piece(y[0], y[1]),
        )

    def next_mode(self, mode: _Mode, fired: set[str], y) -> _Mode:
        """The mode after the switch events of the kinds in `fired`."""
        moving_out = (not mode.moving_out) if "velocity" in fired else mode.moving_out
        in_contact = (not mode.contact) if "contact" in fired else mode.contact
        clamped = (not mode.clamped) if "clamp" in fired else mode.clamped
        if not in_contact:
            clamped = False
        elif "contact" in fired:  # a new contact
            clamped = self.lam * (y[1] - y[3]) < -1.0
        piece = mode.piece + ("piece up" in fired) - ("piece down" in fired)
        return _Mode(moving_out=moving_out, contact=in_contact, clamped=bool(clamped), piece=piece)

    def stops(self, t1: float) -> np.ndarray:
        """Segment ends known in advance: later rounds, and every table point."""
        times = list(self.firing_times()[1:])
        if self.table is not None:
            times += [tj + ti for tj in self.firing_times() for ti in self.table[0]]
        return np.unique([s for s in times if 0.0 < s < t1])


class _RunningPeaks:
    """Running maxima (value, time) of x_M, F_AN and F_ct, and the stroke's range."""

    def __init__(self):
        self.displacement = (-np.inf, 0.0)
        self.anchoring = (-np.inf, 0.0)
        self.contact = (0.0, 0.0)
        self.min_stroke = 0.0
        self.max_stroke = 0.0

    def consider(self, model: _HardModel, t, y, mode: _Mode) -> None:
        if y[0] > self.displacement[0]:
            self.displacement = (y[0], t)
        anchoring = model.anchoring(y, mode)
        if anchoring > self.anchoring[0]:
            self.anchoring = (anchoring, t)
        contact = model.contact_force(y, mode)
        if contact > self.contact[0]:
            self.contact = (contact, t)
        stroke = y[2] - y[0]
        self.min_stroke = min(self.min_stroke, stroke)
        self.max_stroke = max(self.max_stroke, stroke)

    def metrics(self) -> dict[str, float]:
        return {
            "peak_displacement": self.displacement[0],
            "peak_displacement_time": self.displacement[1],
            "peak_anchoring_force": self.anchoring[0],
            "peak_anchoring_force_time": self.anchoring[1],
            "peak_contact_force": self.contact[0],
            "peak_contact_force_time": self.contact[1],
            "min_stroke": self.min_stroke,
            "max_stroke": self.max_stroke,
        }


def reference_peaks(
    values: Mapping[str, float] | None = None,
    t1: float | None = None,
    rtol: float = 1e-12,
    atol: float = 1e-14,
    method: str = "DOP853",
    max_segments: int = 20000,
    force_table=None,
) -> dict:
    """Peaks of the hard-switch model, by an independent scipy solver.

    **Arguments:**

    - `values`: flat parameter values (names as `params_from_values`; defaults fill in).
    - `t1`: end time (s); default 10 s after the last round.
    - `rtol`, `atol`, `method`: `scipy.integrate.solve_ivp` settings per segment.
    - `max_segments`: the most integration segments (one per switch event or stop).
    - `force_table`: `(t, F)` of one round (s, N), replacing the impulse or pulse.

    **Returns:** the metrics by name with the times of the timed ones
    (`peak_anchoring_force`, `peak_anchoring_force_time`, ..., `min_stroke`,
    `max_stroke`), `segments`, and `status`: `"ok"`, or `"bottomed_out"` when x_M
    reaches 0.95 of the recuperator's gas column (the peaks are then those up to there).

    **Raises:** `RuntimeError` if more than `max_segments` segments are needed (contact
    chatter when the system comes to rest on the contact boundary, at gap 0 after
    ~1.5 s: use a shorter `t1` for such designs), or if scipy fails.
    """
    model = _model_of(values, force_table)
    if t1 is None:
        t1 = 10.0 + (model.shots - 1) * model.interval
    running, segments, status = _integrate(model, t1, rtol, atol, method, max_segments)
    return running.metrics() | {"segments": segments, "status": status}


def _model_of(values, force_table) -> _HardModel:
    flat = params_to_values(params_from_values(values or {}))
    return _HardModel({name: float(np.asarray(v)) for name, v in flat.items()}, force_table)


def reference_history(
    values: Mapping[str, float] | None = None,
    ts=None,
    rtol: float = 1e-12,
    atol: float = 1e-14,
    method: str = "DOP853",
    max_segments: int = 20000,
    force_table=None,
) -> dict[str, np.ndarray]:
    """Time histories of the hard-switch model by the independent scipy solver (as
    `reference_peaks`), at the sorted times `ts` (s, shape `(n,)`, from 0): the state
    `x_M, v_M, x_m, v_m` and the forces `F_AN`, `F_ct`, by name, shape `(n,)` each; from
    each segment's dense output. At a round's firing the value is the one after it (its
    impulse applied), as at `t = 0` and as `rj.simulate` gives it."""
    model = _model_of(values, force_table)
    ts = np.asarray(ts, dtype=float)
    samples = {
        name: np.full(ts.shape, np.nan) for name in ("x_M", "v_M", "x_m", "v_m", "F_AN", "F_ct")
    }
    _integrate(model, float(ts[-1]), rtol, atol, method, max_segments, ts, samples)
    return samples


def _integrate(model, t1, rtol, atol, method, max_segments, ts=None, samples=None):
    """The segment loop: `(running peaks, segments, status)`; with `ts`, `samples` filled
    in place."""
    import scipy.integrate  # when used: `import recoil_jax` stays quick

    peak_events = model.peak_events()
    running = _RunningPeaks()
    t = 0.0
    y = np.array([0.0, model.v0 if model.impulse else 0.0, 0.0, 0.0])
    mode = model.initial_mode(y)
    running.consider(model, t, y, mode)
    if ts is not None:
        _sample_at(model, mode, 0.0, y, ts, samples)
    stops = [*model.stops(t1), t1]
    segments = 0
    status = "ok"
    while t < t1 and status == "ok":
        segments += 1
        if segments > max_segments:
            raise RuntimeError(
                f"reference solver: more than {max_segments} switch events before t1 = {t1} "
                f"(stopped at t = {t:.6g} s); use a shorter t1"
            )
        end = next(s for s in stops if s > t)
        switches = model.switch_events(mode)
        sol = scipy.integrate.solve_ivp(
            model.rhs,
            (t, end),
            y,
            method=method,
            rtol=rtol,
            atol=atol,
            args=(mode,),
            events=peak_events + switches,
            dense_output=ts is not None,
        )
        if sol.status < 0:
            raise RuntimeError(f"reference solver failed: {sol.message}")
        assert sol.t_events is not None and sol.y_events is not None
        for index in range(len(peak_events)):
            for te, ye in zip(sol.t_events[index], sol.y_events[index], strict=True):
                running.consider(model, te, ye, mode)
        if ts is not None:
            _sample(model, sol, mode, t, sol.t[-1], ts, samples)
        t, y = sol.t[-1], sol.y[:, -1].copy()
        running.consider(model, t, y, mode)
        if sol.status == 1:
            fired = {
                event.kind
                for i, event in enumerate(switches)
                if sol.t_events[len(peak_events) + i].size > 0
            }
            if "bottom" in fired:
                status = "bottomed_out"
            mode = model.next_mode(mode, fired, y)
        elif t < t1:  # a stop: a round fires (a velocity jump for an impulse load)
            if model.impulse and np.any(
                np.isclose(t, model.firing_times()[1:], rtol=0, atol=1e-12)
            ):
                y[1] += model.v0
            mode = (
                model.initial_mode(y)
                if not model.buffer
                else dataclasses.replace(model.initial_mode(y), piece=mode.piece)
            )
            running.consider(model, t, y, mode)
            if ts is not None:  # a sample at the firing itself: after it, as at t = 0
                _sample_at(model, mode, t, y, ts, samples)
    return running, segments, status


def _sample(model, sol, mode, start, end, ts, samples):
    """Fill the samples at the times in `(start, end]` from a segment's dense output."""
    inside = (ts > start) & (ts <= end)
    if inside.any():
        _fill(model, mode, inside, sol.sol(ts[inside]), samples)


def _sample_at(model, mode, t, y, ts, samples):
    """Fill the samples at exactly `t` (the start, or a firing: after its impulse) with
    the state `y`."""
    inside = ts == t
    if inside.any():
        _fill(model, mode, inside, np.repeat(y[:, None], inside.sum(), 1), samples)


def _fill(model, mode, inside, states, samples):
    for name, row in zip(("x_M", "v_M", "x_m", "v_m"), states, strict=True):
        samples[name][inside] = row
    samples["F_AN"][inside] = [model.anchoring(y, mode) for y in states.T]
    samples["F_ct"][inside] = [model.contact_force(y, mode) for y in states.T]
