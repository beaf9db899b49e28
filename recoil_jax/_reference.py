"""An independent reference solver: scipy `solve_ivp`, hard switches, event-located.

Shares no model code with the JAX model: the equations are written out again here in
NumPy. Each switch (contact onset `δ = 0`, damping sign `v_M = 0`, the no-pull clamp
`1 + λ_c δ̇ = 0`) ends an integration segment at an exactly located event, so every
segment is smooth and the integrator keeps its full order. Peaks are located as events of
their time derivatives (and checked at every segment end), not read off a grid.

Used by the tests as ground truth across the documented ranges, and as the serial
baseline of the benchmarks.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping

import numpy as np
from scipy.integrate import solve_ivp

from ._params import params_from_values, params_to_values

__all__ = ["reference_peaks"]


@dataclasses.dataclass(frozen=True)
class _Mode:
    """Which side of each switch the state is on; fixed within a segment."""

    moving_out: bool  # v_M > 0: damping c_out
    contact: bool  # δ > 0
    clamped: bool  # 1 + λ δ̇ < 0 while in contact: F_ct = 0


@dataclasses.dataclass(frozen=True)
class _Event:
    """A `solve_ivp` event: the zeros of `surface(t, y, mode)` crossed in `direction`
    (0: either way); `terminal` ends the segment there."""

    surface: Callable[[float, np.ndarray, _Mode], float]
    direction: float = 0.0
    terminal: bool = False

    def __call__(self, t, y, mode) -> float:
        return self.surface(t, y, mode)


class _HardModel:
    """The model with hard switches, for flat parameter values."""

    def __init__(self, p: Mapping[str, float]):
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

    def damping(self, mode: _Mode) -> float:
        return self.c_out if mode.moving_out else self.c_ret

    def contact_force(self, y, mode: _Mode) -> float:
        if not self.absorber or not mode.contact or mode.clamped:
            return 0.0
        delta = max(y[0] - y[2] - self.gap, 0.0)
        return self.k_c * delta**self.n_c * (1.0 + self.lam * (y[1] - y[3]))

    def rhs(self, t, y, mode: _Mode):
        x_M, v_M, x_m, v_m = y
        coupling = (self.k_r * (x_M - x_m) + self.c_r * (v_M - v_m)) if self.absorber else 0.0
        f_ct = self.contact_force(y, mode)
        a_M = (-self.damping(mode) * v_M - self.k * x_M - coupling - f_ct) / self.M
        a_m = (coupling + f_ct) / self.m if self.absorber else 0.0
        return np.array([v_M, a_M, v_m, a_m])

    def anchoring(self, y, mode: _Mode) -> float:
        return self.k * y[0] + self.damping(mode) * y[1]

    def rates(self, y, mode: _Mode) -> tuple[float, float]:
        """Time derivatives of F_AN and F_ct within a mode."""
        a = self.rhs(0.0, y, mode)
        d_anchor = self.k * y[1] + self.damping(mode) * a[1]
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

    def peak_events(self) -> list[_Event]:
        """Non-terminal surfaces where a tracked quantity may peak: the falling zeros of
        v_M, dF_AN/dt and dF_ct/dt, and every zero of the stroke rate."""
        return [
            _Event(lambda t, y, mode: y[1], direction=-1.0),
            _Event(lambda t, y, mode: self.rates(y, mode)[0], direction=-1.0),
            _Event(lambda t, y, mode: self.rates(y, mode)[1], direction=-1.0),
            _Event(lambda t, y, mode: y[1] - y[3]),
        ]

    def switch_events(self, mode: _Mode) -> list[_Event]:
        """Terminal events that fire only when leaving the current mode's region, so a
        segment that starts on a switching surface cannot re-detect it. In order:
        velocity, contact, clamp (those that apply)."""
        events = [
            _Event(
                lambda t, y, mode: y[1], direction=-1.0 if mode.moving_out else 1.0, terminal=True
            )
        ]
        if self.absorber:
            events.append(
                _Event(
                    lambda t, y, mode: y[0] - y[2] - self.gap,
                    direction=-1.0 if mode.contact else 1.0,
                    terminal=True,
                )
            )
            if mode.contact and self.lam > 0:
                events.append(
                    _Event(
                        lambda t, y, mode: 1.0 + self.lam * (y[1] - y[3]),
                        direction=1.0 if mode.clamped else -1.0,
                        terminal=True,
                    )
                )
        return events

    def initial_mode(self, y) -> _Mode:
        delta = y[0] - y[2] - self.gap
        contact = self.absorber and (delta > 0 or (delta == 0 and y[1] - y[3] > 0))
        clamped = contact and self.lam * (y[1] - y[3]) < -1.0
        return _Mode(moving_out=y[1] > 0, contact=bool(contact), clamped=bool(clamped))

    def next_mode(self, mode: _Mode, fired: list[bool], y) -> _Mode:
        """The mode after the switch events flagged in `fired` (same order as
        `switch_events`)."""
        velocity, contact, clamp = [*fired, False, False][:3]
        moving_out = (not mode.moving_out) if velocity else mode.moving_out
        in_contact = (not mode.contact) if contact else mode.contact
        clamped = (not mode.clamped) if clamp else mode.clamped
        if not in_contact:
            clamped = False
        elif contact:  # a new contact
            clamped = self.lam * (y[1] - y[3]) < -1.0
        return _Mode(moving_out=moving_out, contact=in_contact, clamped=bool(clamped))


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
    t1: float = 10.0,
    rtol: float = 1e-12,
    atol: float = 1e-14,
    method: str = "DOP853",
    max_segments: int = 20000,
) -> dict:
    """Peaks of the hard-switch model, by an independent scipy solver.

    **Arguments:**

    - `values`: flat parameter values (names as `params_from_values`; defaults fill in).
    - `t1`: end time (s).
    - `rtol`, `atol`, `method`: `scipy.integrate.solve_ivp` settings per segment.
    - `max_segments`: the most integration segments (one per switch event).

    **Returns:** the metrics by name with the times of the timed ones
    (`peak_anchoring_force`, `peak_anchoring_force_time`, ..., `min_stroke`,
    `max_stroke`), and `segments`.

    **Raises:** `RuntimeError` if more than `max_segments` switch events occur (contact
    chatter when the system comes to rest on the contact boundary, at gap 0 after
    ~1.5 s: use a shorter `t1` for such designs), or if scipy fails.
    """
    flat = params_to_values(params_from_values(values or {}))
    model = _HardModel({name: float(np.asarray(v)) for name, v in flat.items()})
    peak_events = model.peak_events()
    running = _RunningPeaks()
    t, y = 0.0, np.array([0.0, model.v0, 0.0, 0.0])
    mode = model.initial_mode(y)
    running.consider(model, t, y, mode)
    segments = 0
    while t < t1:
        segments += 1
        if segments > max_segments:
            raise RuntimeError(
                f"reference solver: more than {max_segments} switch events before t1 = {t1} "
                f"(stopped at t = {t:.6g} s); use a shorter t1"
            )
        switches = model.switch_events(mode)
        sol = solve_ivp(
            model.rhs,
            (t, t1),
            y,
            method=method,
            rtol=rtol,
            atol=atol,
            args=(mode,),
            events=peak_events + switches,
        )
        if sol.status < 0:
            raise RuntimeError(f"reference solver failed: {sol.message}")
        assert sol.t_events is not None and sol.y_events is not None
        for index in range(len(peak_events)):
            for te, ye in zip(sol.t_events[index], sol.y_events[index], strict=True):
                running.consider(model, te, ye, mode)
        t, y = sol.t[-1], sol.y[:, -1].copy()
        running.consider(model, t, y, mode)
        if sol.status == 1:
            fired = [sol.t_events[len(peak_events) + i].size > 0 for i in range(len(switches))]
            mode = model.next_mode(mode, fired, y)
    return running.metrics() | {"segments": segments}
