"""An independent reference solver: scipy `solve_ivp`, hard switches, event-located.

Shares no model code with the JAX model: the equations are written out again here in
NumPy. Each switch (contact onset `δ = 0`, damping sign `v_M = 0`, the no-pull clamp
`1 + λ_c δ̇ = 0`, the barrel crossing an orifice knot) ends an integration segment at an
exactly located event, and each round's firing and each point of a force table ends one
too, so every segment is smooth and the integrator keeps its full order. Peaks are located
as events of their time derivatives (and checked at every segment end), not read off a
grid. A barrel that reaches 0.95 of the recuperator's gas column is reported
(`status`), like the JAX model does.

The firing envelope (`docs/model.md`) is in it with hard switches too: gravity
along the rails, the recuperator preload, the battery stop (Hunt–Crossley, its onset and
its no-pull clamp events), the counter-recoil buffer (events at `x_M = L_b` and
`v_M = 0`) and **exact stick–slip** Coulomb friction. Sliding, the friction is
`F_max·sign(v_M)`; at `v_M = 0` the barrel sticks if the net force on it from everything
but friction, `N`, is within `±F_max`: a stick mode holds `x_M` and `v_M = 0` while the
friction takes `N`, and ends at the event `|N| = F_max`, where the barrel slips the way
`N` pushes. Its metrics (`return_time`, `battery_speed`, `residual_displacement`,
`stability_margin`) come from the event-located solution. A design whose envelope
parameters have no effect (zero elevation, friction, stop, buffer and preload) runs the
paper's code path, operation for operation.

Revision 2 of the envelope (`docs/model.md`): the gun fires from its **static rest**
`x_r <= 0`, the root of `F_AN(x, v = 0) = (M + m) g sin θ` (friction aside) in the
battery stop where a preload above the axial weight presses the barrel into it
(`reference_rest`; else `x_r = 0`); displacements and the return are measured from it;
the **stability margin** takes the recoiling parts' axial weight out of the overturning
force, `K = F_AN − (M + m) g sin θ`, and the stabilising moment counts their travel from
the start; and two metrics join,
`peak_pull_force` (the largest `−F_AN`, located at the rising zeros of `dF_AN/dt`) and
`peak_mount_load` (the largest `|F_AN|`).

Used by the tests as ground truth across the documented ranges, and as the serial
baseline of the benchmarks.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping

import numpy as np

from .._model.params import params_from_values, params_to_values

__all__ = ["reference_energy", "reference_history", "reference_peaks", "reference_rest"]

_BOTTOM = 0.95  # the recuperator's gas column may be compressed to this fraction
#: Standard gravity (m/s²), as `docs/model.md` fixes it.
GRAVITY = 9.80665
#: In battery to within this (m): the return is the barrel coming forward through it.
BATTERY = 1e-3
#: Pulse times from a round's firing over which a stuck barrel's steps are held short.
_PULSE_WINDOW = 50.0
#: The friction band's relative margin for rounding (`_HardModel.band`).
_BAND = 1e-9
#: Segments in a row that may end where they started (a state exactly on a switching
#: surface crosses it in a zero-length segment) before the solve is declared stuck.
_MAX_EMPTY = 50


@dataclasses.dataclass(frozen=True)
class _Mode:
    """Which side of each switch the state is on; fixed within a segment."""

    moving_out: bool  # v_M > 0: damping c_out (and friction +F_max)
    contact: bool  # δ > 0
    clamped: bool  # 1 + λ δ̇ < 0 while in contact: F_ct = 0
    piece: int = 0  # the orifice piece x_M lies in: -1 below 0, K-1 beyond x_a
    stuck: bool = False  # held by friction: x_M fixed, v_M = 0
    stop: bool = False  # in the battery stop: x_M < 0
    stop_clamped: bool = False  # 1 − λ_s v_M < 0 while in the stop: F_s = 0
    in_buffer: bool = False  # x_M < L_b: the counter-recoil buffer acts while v_M < 0


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
        # Gas recuperator: its force F_r and its preload P act on one gas column. Zero
        # both is no recuperator (no gas column to bottom).
        self.F_r = p.get("recuperator_force", 0.0)
        self.P = p.get("recuperator_preload", 0.0)
        self.recuperator = self.F_r > 0 or self.P > 0
        if self.recuperator:
            self.L_r = p["recuperator_length"]
            self.gamma = p["polytropic_index"]
        # The firing envelope. Each part is on only where it has an effect, so that a
        # design without one runs the paper's code path, operation for operation.
        theta = math.radians(p.get("elevation", 0.0))
        self.sin, self.cos = math.sin(theta), math.cos(theta)
        self.gravity = self.sin != 0.0
        self.mass_m = p["m"]  # the absorber's mass, 0 without one
        self.sag = self.mass_m * GRAVITY * self.sin / self.k_r if self.absorber else 0.0
        self.F_max = (
            p.get("friction_force", 0.0)
            + p.get("friction_coefficient", 0.0) * (self.M + self.mass_m) * GRAVITY * self.cos
        )
        self.friction = self.F_max > 0
        # The band of net forces friction holds: F_max, and a relative 1e-9 for the
        # rounding of N where a barrel comes to rest at the band's edge (an overdamped
        # approach to it: N = ∓F_max in the limit, and v_M crosses 0 by rounding alone).
        self.band = self.F_max * (1.0 + _BAND)
        self.k_s = p.get("stop_stiffness", 0.0)
        self.stop = self.k_s > 0
        self.n_s = p.get("stop_exponent", 1.5)
        self.lam_s = p.get("stop_damping", 0.6)
        self.c_b = p.get("buffer_damping", 0.0)
        self.L_b = p.get("buffer_length", 0.1)
        self.counter_buffer = self.c_b > 0
        self.preload = self.P > 0
        self.envelope = (
            self.gravity or self.friction or self.stop or self.counter_buffer or self.preload
        )
        self.mount_mass = p.get("mount_mass", 0.0)
        self.mount = self.mount_mass > 0
        if self.mount:
            self.L_w = p["cg_distance"]
            self.lever = p["trunnion_height"] * self.cos - p["spade_distance"] * self.sin
        # The static rest (revision 2): the axial weight of the recoiling parts, and the
        # rest x_r <= 0 it and the preload give in the stop; the start x_M(0) = x_r with
        # the absorber hanging at rest on its spring, x_m(0) = x_r + m g sin θ / k_r.
        self.weight = (self.M + self.mass_m) * GRAVITY * self.sin
        self.x_r = self.rest()
        self.x_m0 = self.x_r + self.sag

    def static_force(self, x) -> float:
        """F_AN(x, v = 0) less the friction: `k x + F_g + F_p − k_s δ^n_s` (δ = −x)."""
        force = self.k * x + self.gas(x) + self.preload_force(x)
        if self.stop and x < 0:
            force -= self.k_s * (-x) ** self.n_s
        return force

    def rest(self) -> float:
        """x_r: the root, `<= 0`, of `F_AN(x, 0) = (M + m) g sin θ` (friction aside), with
        a battery stop and `F_AN(0, 0)` above the axial weight; else 0. The balance rises
        with x (each term does), so its root is unique; at `−δ_0`, with
        `k_s δ_0^n_s = F_AN(0, 0) − W`, it is `<= 0`: the bracket."""
        if not self.stop:
            return 0.0
        excess = self.static_force(0.0) - self.weight
        if not excess > 0:
            return 0.0
        import scipy.optimize  # when used: `import recoil_jax` stays quick

        def balance(x):
            return self.static_force(x) - self.weight

        low = -((excess / self.k_s) ** (1.0 / self.n_s))
        for _ in range(100):
            if balance(low) <= 0:
                break
            low *= 2.0
        root = scipy.optimize.brentq(
            balance, low, 0.0, xtol=1e-300, rtol=4 * np.finfo(float).eps, maxiter=500,
            full_output=False,
        )  # fmt: skip
        return float(root)  # pyright: ignore[reportArgumentType]

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

    def breech_rate(self, t) -> float:
        """dF_b/dt (the right-hand slope at a table point: segments start there)."""
        if self.impulse:
            return 0.0
        total = 0.0
        for tj in self.firing_times():
            tau = t - tj
            if self.table is not None:
                times, force = self.table
                if times[0] <= tau < times[-1]:
                    i = int(np.searchsorted(times, tau, side="right")) - 1
                    total += (force[i + 1] - force[i]) / (times[i + 1] - times[i])
            elif tau >= 0.0:
                u = tau / self.pulse_time
                total += self.M * self.v0 / self.pulse_time**2 * (1.0 - u) * np.exp(-u)
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

    def preload_force(self, x) -> float:
        """F_p = P (L_r / (L_r − x_M))^γ, on the recuperator's gas column."""
        if not self.preload:
            return 0.0
        return self.P * (self.L_r / (self.L_r - x)) ** self.gamma

    def damping(self, mode: _Mode) -> float:
        return self.c_out if mode.moving_out else self.c_ret

    def contact_force(self, y, mode: _Mode) -> float:
        if not self.absorber or not mode.contact or mode.clamped:
            return 0.0
        delta = max(y[0] - y[2] - self.gap, 0.0)
        return self.k_c * delta**self.n_c * (1.0 + self.lam * (y[1] - y[3]))

    def stop_force(self, y, mode: _Mode) -> float:
        """F_s = k_s δ^n_s (1 + λ_s δ̇), δ = −x_M, in the stop and unclamped."""
        if not self.stop or not mode.stop or mode.stop_clamped:
            return 0.0
        delta = max(-y[0], 0.0)
        return self.k_s * delta**self.n_s * (1.0 - self.lam_s * y[1])

    def counter_force(self, y, mode: _Mode) -> float:
        """F_cb = c_b v_M while v_M < 0 and x_M < L_b."""
        if not self.counter_buffer or not mode.in_buffer or mode.moving_out or mode.stuck:
            return 0.0
        return self.c_b * y[1]

    def coupling(self, y) -> float:
        if not self.absorber:
            return 0.0
        return self.k_r * (y[0] - y[2]) + self.c_r * (y[1] - y[3])

    def held(self, y, mode: _Mode) -> float:
        """F_AN less the friction: everything else between the barrel and the mounting."""
        return (
            self.k * y[0]
            + self.damping(mode) * y[1]
            + self.orifice(y, mode)
            + self.gas(y[0])
            + self.preload_force(y[0])
            + self.counter_force(y, mode)
            - self.stop_force(y, mode)
        )

    def net_force(self, t, y, mode: _Mode) -> float:
        """N: the force on a barrel at rest (`v_M = 0`) from everything but friction."""
        rest = np.array([y[0], 0.0, y[2], y[3]])
        still = dataclasses.replace(mode, stop_clamped=False)
        force = (
            self.breech(t)
            - self.held(rest, still)
            - self.coupling(rest)
            - self.contact_force(rest, still)
        )
        return force + self.M * GRAVITY * self.sin

    def friction_force(self, t, y, mode: _Mode) -> float:
        """F_f: ±F_max sliding; held at rest, the net force N."""
        if not self.friction:
            return 0.0
        if mode.stuck:
            return self.net_force(t, y, mode)
        return self.F_max if mode.moving_out else -self.F_max

    def anchoring(self, y, mode: _Mode, t: float = 0.0) -> float:
        if not self.envelope:
            return (
                self.k * y[0] + self.damping(mode) * y[1] + self.orifice(y, mode) + self.gas(y[0])
            )
        return self.held(y, mode) + self.friction_force(t, y, mode)

    def rhs(self, t, y, mode: _Mode):
        x_M, v_M, x_m, v_m = y[:4]
        coupling = (self.k_r * (x_M - x_m) + self.c_r * (v_M - v_m)) if self.absorber else 0.0
        f_ct = self.contact_force(y, mode)
        a_m = (coupling + f_ct) / self.m if self.absorber else 0.0
        if self.gravity and self.absorber:
            a_m += GRAVITY * self.sin
        if mode.stuck:
            return np.array([0.0, 0.0, v_m, a_m])
        a_M = (self.breech(t) - self.anchoring(y, mode, t) - coupling - f_ct) / self.M
        if self.gravity:
            a_M += GRAVITY * self.sin
        return np.array([v_M, a_M, v_m, a_m])

    def rates(self, t, y, mode: _Mode) -> tuple[float, float]:
        """Time derivatives of F_AN and F_ct within a mode."""
        a = self.rhs(t, y, mode)
        d_contact = 0.0
        if self.absorber and mode.contact and not mode.clamped:
            delta = max(y[0] - y[2] - self.gap, 0.0)
            rate = y[1] - y[3]
            accel = a[1] - a[3]
            d_contact = self.k_c * (
                self.n_c * delta ** (self.n_c - 1.0) * rate * (1.0 + self.lam * rate)
                + delta**self.n_c * self.lam * accel
            )
        if mode.stuck:  # F_AN = F_b − coupling − F_ct + M g sin θ, with v_M = a_M = 0
            d_anchor = self.breech_rate(t) - d_contact
            if self.absorber:
                d_anchor += self.k_r * y[3] + self.c_r * a[3]
            return d_anchor, d_contact
        d_anchor = self.k * y[1] + self.damping(mode) * a[1]
        if self.buffer:
            area, slope = self.area(y[0], mode)
            d_anchor += self.coefficient * (
                2.0 * abs(y[1]) * a[1] / area**2 - 2.0 * y[1] * abs(y[1]) * slope * y[1] / area**3
            )
        if self.recuperator:
            ratio = self.L_r / (self.L_r - y[0])
            d_anchor += self.F_r * self.gamma * ratio**self.gamma / (self.L_r - y[0]) * y[1]
            if self.preload:
                d_anchor += self.P * self.gamma * ratio**self.gamma / (self.L_r - y[0]) * y[1]
        if self.counter_buffer and mode.in_buffer and not mode.moving_out:
            d_anchor += self.c_b * a[1]
        if self.stop and mode.stop and not mode.stop_clamped:
            delta = max(-y[0], 0.0)
            d_anchor -= self.k_s * (
                self.n_s * delta ** (self.n_s - 1.0) * (-y[1]) * (1.0 - self.lam_s * y[1])
                + delta**self.n_s * self.lam_s * (-a[1])
            )
        return d_anchor, d_contact

    def margin(self, t, y, mode: _Mode) -> float:
        """(S − O) / (m_g g L_w): the share of the stabilising moment left (with a mount).
        `O = K d`, `K = F_AN − (M + m) g sin θ` (the resistance net of the axial weight),
        and `S = g (m_g L_w − (M (x_M − x_M(0)) + m (x_m − x_m(0))) cos θ)`."""
        moved = self.M * (y[0] - self.x_r)
        if self.absorber:
            moved += self.mass_m * (y[2] - self.x_m0)
        stabilising = GRAVITY * (self.mount_mass * self.L_w - moved * self.cos)
        overturning = (self.anchoring(y, mode, t) - self.weight) * self.lever
        return (stabilising - overturning) / (self.mount_mass * GRAVITY * self.L_w)

    def margin_rate(self, t, y, mode: _Mode) -> float:
        """d margin / dt within a mode."""
        speed = self.M * y[1] + (self.mass_m * y[3] if self.absorber else 0.0)
        d_anchor, _ = self.rates(t, y, mode)
        return (-GRAVITY * speed * self.cos - d_anchor * self.lever) / (
            self.mount_mass * GRAVITY * self.L_w
        )

    # --- events -----------------------------------------------------------------------
    def peak_events(self) -> list[_Event]:
        """Non-terminal surfaces where a tracked quantity may peak: the falling zeros of
        v_M, dF_AN/dt and dF_ct/dt, and every zero of the stroke rate."""
        events = [
            _Event(lambda t, y, mode: y[1] if not mode.stuck else -1.0, direction=-1.0),
            _Event(lambda t, y, mode: self.rates(t, y, mode)[0], direction=-1.0),
            _Event(lambda t, y, mode: self.rates(t, y, mode)[1], direction=-1.0),
            _Event(lambda t, y, mode: y[1] - y[3]),
        ]
        if self.envelope and not self.absorber:
            # Without an absorber F_ct = 0, and a stuck barrel's stroke rate is 0: a
            # surface that is zero everywhere is a root at every step (the paper's path
            # keeps its events as they were).
            # Likewise F_AN while stuck under an impulse load: constant.
            events[1] = _Event(
                lambda t, y, mode: -1.0 if self.constant(mode) else self.rates(t, y, mode)[0],
                direction=-1.0,
            )
            events[2] = _Event(lambda t, y, mode: -1.0, direction=-1.0)
            events[3] = _Event(lambda t, y, mode: y[1] - y[3] if not mode.stuck else 1.0)
        return events

    def low_events(self) -> list[_Event]:
        """Non-terminal surfaces where F_AN may be least (`peak_pull_force`): the rising
        zeros of dF_AN/dt (not where it is constant: a surface zero everywhere is a root
        at every step). Apart from `peak_events`, so that the peaks they locate are
        found at the same points as before."""
        if self.envelope and not self.absorber:
            return [
                _Event(
                    lambda t, y, mode: 1.0 if self.constant(mode) else self.rates(t, y, mode)[0],
                    direction=1.0,
                )
            ]
        return [_Event(lambda t, y, mode: self.rates(t, y, mode)[0], direction=1.0)]

    def constant(self, mode: _Mode) -> bool:
        """Nothing moves and no force changes: a stuck barrel without an absorber under
        an impulse load (between its rounds)."""
        return mode.stuck and not self.absorber and self.impulse

    def envelope_events(self) -> list[_Event]:
        """Non-terminal surfaces of the envelope's metrics: the barrel coming forward
        through `x_M = x_r + 1 mm` (the return), and the rising zeros of the stability
        margin's rate (its local minima), with a mount."""
        battery = self.x_r + BATTERY
        events = [
            _Event(
                lambda t, y, mode: y[0] - battery if not mode.stuck else 1.0,
                direction=-1.0,
                kind="return",
            )
        ]
        if self.mount:
            events.append(
                _Event(
                    lambda t, y, mode: 1.0 if self.constant(mode) else self.margin_rate(t, y, mode),
                    direction=1.0,
                    kind="margin",
                )
            )
        return events

    def switch_events(self, mode: _Mode) -> list[_Event]:
        """Terminal events that fire only when leaving the current mode's region, so a
        segment that starts on a switching surface cannot re-detect it."""
        if mode.stuck:
            return self.stuck_events(mode)
        events = [
            _Event(
                lambda t, y, mode: y[1],
                direction=-1.0 if mode.moving_out else 1.0,
                terminal=True,
                kind="velocity",
            )
        ]
        events += self.absorber_events(mode)
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
        if self.stop:
            events.append(
                _Event(
                    lambda t, y, mode: -y[0],
                    direction=-1.0 if mode.stop else 1.0,
                    terminal=True,
                    kind="stop",
                )
            )
            if mode.stop and self.lam_s > 0:
                events.append(
                    _Event(
                        lambda t, y, mode: 1.0 - self.lam_s * y[1],
                        direction=1.0 if mode.stop_clamped else -1.0,
                        terminal=True,
                        kind="stop clamp",
                    )
                )
        if self.counter_buffer:
            events.append(
                _Event(
                    lambda t, y, mode: y[0] - self.L_b,
                    direction=1.0 if mode.in_buffer else -1.0,
                    terminal=True,
                    kind="counter buffer",
                )
            )
        return events

    def absorber_events(self, mode: _Mode) -> list[_Event]:
        """The absorber's switches, held barrel or not: its contact with the barrel
        closing or opening, and within contact the Hunt–Crossley clamp."""
        if not self.absorber:
            return []
        events = [
            _Event(
                lambda t, y, mode: y[0] - y[2] - self.gap,
                direction=-1.0 if mode.contact else 1.0,
                terminal=True,
                kind="contact",
            )
        ]
        if mode.contact and self.lam > 0:
            events.append(
                _Event(
                    lambda t, y, mode: 1.0 + self.lam * (y[1] - y[3]),
                    direction=1.0 if mode.clamped else -1.0,
                    terminal=True,
                    kind="clamp",
                )
            )
        return events

    def stuck_events(self, mode: _Mode) -> list[_Event]:
        """A barrel held by friction: it slips when the net force on it reaches ±F_max;
        only the absorber moves (its contact and clamp switches)."""
        events = [
            _Event(
                lambda t, y, mode: self.net_force(t, y, mode) - self.band,
                direction=1.0,
                terminal=True,
                kind="slip out",
            ),
            _Event(
                lambda t, y, mode: self.net_force(t, y, mode) + self.band,
                direction=-1.0,
                terminal=True,
                kind="slip back",
            ),
        ]
        return events + self.absorber_events(mode)

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

    def classify(self, t, y, previous: _Mode | None = None) -> _Mode:
        """The mode of the state `y` at `t` with the envelope (at the start, and after a
        round's firing or a table point): each side from the state; on a surface, the
        side the motion goes to. At rest, the barrel sticks if the net force on it is
        within ±F_max, else it moves the way the net force pushes."""
        x, v = y[0], y[1]
        mode = self.initial_mode(y)
        stop = self.stop and (x < 0 or (x == 0 and v < 0))
        mode = dataclasses.replace(
            mode,
            moving_out=v > 0,
            stop=bool(stop),
            stop_clamped=bool(stop and 1.0 - self.lam_s * v < 0),
            in_buffer=bool(x < self.L_b or (x == self.L_b and v < 0)),
        )
        if v != 0:
            return mode
        net = self.net_force(t, y, mode)
        if self.friction and abs(net) <= self.band:
            return dataclasses.replace(mode, stuck=True, moving_out=net > 0)
        if net == 0 and previous is not None:
            return dataclasses.replace(mode, moving_out=previous.moving_out)
        # Moving off from rest: forward into the stop if it is at x = 0.
        stop = self.stop and (x < 0 or (x == 0 and net < 0))
        return dataclasses.replace(mode, moving_out=bool(net > 0), stop=bool(stop))

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

    def next_envelope_mode(self, t, mode: _Mode, fired: set[str], y) -> _Mode:
        """`next_mode` with the envelope's switches; sets `y[1] = 0` where the barrel
        sticks. At `v_M = 0` a barrel with friction sticks if the net force on it is
        within ±F_max, else it reverses; from a stick it slips the way N pushes."""
        base = self.next_mode(mode, fired - {"velocity"}, y)
        stop = (not mode.stop) if "stop" in fired else mode.stop
        stop_clamped = (not mode.stop_clamped) if "stop clamp" in fired else mode.stop_clamped
        if not stop:
            stop_clamped = False
        elif "stop" in fired:  # a new stop contact
            stop_clamped = 1.0 - self.lam_s * y[1] < 0.0
        in_buffer = (not mode.in_buffer) if "counter buffer" in fired else mode.in_buffer
        new = dataclasses.replace(
            base,
            moving_out=mode.moving_out,
            stuck=mode.stuck,
            stop=stop,
            stop_clamped=bool(stop_clamped),
            in_buffer=in_buffer,
        )
        if "slip out" in fired or "slip back" in fired:
            return dataclasses.replace(new, stuck=False, moving_out="slip out" in fired)
        if "velocity" in fired:
            if not self.friction:
                return dataclasses.replace(new, moving_out=not mode.moving_out)
            net = self.net_force(t, y, new)
            if abs(net) <= self.band:
                y[1] = 0.0
                return dataclasses.replace(new, stuck=True, stop_clamped=False)
            return dataclasses.replace(new, moving_out=bool(net > 0))
        return new

    def step_limit(self, start: float, end: float, mode: _Mode) -> dict[str, float]:
        """`solve_ivp` options for a segment: a barrel held by friction does not feel a
        pulse in its state, so the steps would pass over it and miss the slip; while a
        pulse acts (50 pulse times from its round's firing: 1e-20 of its peak is left)
        they are held to an eighth of the pulse time. (A table's points are segment ends,
        and it is linear between.) A free barrel's segment from a round's firing starts
        with a step of an eighth of the pulse time: at rest (as at its static rest, where
        no force acts at first) the step size the solver would pick from the vanishing
        rates leaps over the pulse to the gas column's end and back."""
        if self.impulse or self.table is not None:
            return {}
        if not mode.stuck:
            firing = np.any(self.firing_times() == start)
            return {"first_step": min(self.pulse_time / 8, end - start)} if firing else {}
        window = _PULSE_WINDOW * self.pulse_time  # its end is a segment end (`stops`)
        acting = [tj for tj in self.firing_times() if tj < end and start < tj + window]
        return {"max_step": self.pulse_time / 8} if acting else {}

    def stops(self, t1: float) -> np.ndarray:
        """Segment ends known in advance: later rounds, and every table point."""
        times = list(self.firing_times()[1:])
        if self.table is not None:
            times += [tj + ti for tj in self.firing_times() for ti in self.table[0]]
        if self.envelope and not self.impulse and self.table is None:
            times += list(self.firing_times() + _PULSE_WINDOW * self.pulse_time)
        return np.unique([s for s in times if 0.0 < s < t1])

    # --- energy -----------------------------------------------------------------------
    def stored_energy(self, y) -> float:
        """Kinetic energy and the springs' and contacts' potentials (J); gravity apart."""
        x_M, v_M, x_m, v_m = y[:4]
        energy = 0.5 * self.M * v_M**2 + 0.5 * self.k * x_M**2
        if self.absorber:
            energy += 0.5 * self.mass_m * v_m**2 + 0.5 * self.k_r * (x_M - x_m) ** 2
            delta = max(x_M - x_m - self.gap, 0.0)
            energy += self.k_c * delta ** (self.n_c + 1.0) / (self.n_c + 1.0)
        if self.recuperator:
            ratio = self.L_r / (self.L_r - x_M)
            if self.gamma == 1.0:
                column = self.L_r * math.log(ratio)
            else:
                column = self.L_r * (ratio ** (self.gamma - 1.0) - 1.0) / (self.gamma - 1.0)
            energy += self.F_r * (column - x_M) + self.P * column
        if self.stop:
            delta = max(-x_M, 0.0)
            energy += self.k_s * delta ** (self.n_s + 1.0) / (self.n_s + 1.0)
        return energy

    def powers(self, t, y, mode: _Mode) -> tuple[float, float]:
        """(power of the breech force, power dissipated) (W): the dampers, the orifice,
        friction, and the Hunt–Crossley parts of the two contacts (each its force less
        the elastic part, times the rate of penetration)."""
        x_M, v_M, x_m, v_m = y[:4]
        if mode.stuck:
            v_M = 0.0
        rest = np.array([x_M, v_M, x_m, v_m])
        breech = self.breech(t) * v_M
        lost = (
            self.damping(mode) * v_M**2
            + self.orifice(rest, mode) * v_M
            + self.counter_force(rest, mode) * v_M
            + self.friction_force(t, rest, mode) * v_M
        )
        if self.absorber:
            lost += self.c_r * (v_M - v_m) ** 2
            delta = max(x_M - x_m - self.gap, 0.0)
            elastic = self.k_c * delta**self.n_c
            lost += (self.contact_force(rest, mode) - elastic) * (v_M - v_m)
        if self.stop:
            delta = max(-x_M, 0.0)
            lost += (self.stop_force(rest, mode) - self.k_s * delta**self.n_s) * (-v_M)
        return breech, lost


class _RunningPeaks:
    """Running maxima (value, time) of x_M, F_AN and F_ct, the running minimum of F_AN,
    and the stroke's range."""

    def __init__(self):
        self.displacement = (-np.inf, 0.0)
        self.anchoring = (-np.inf, 0.0)
        self.low = (np.inf, 0.0)  # the least F_AN
        self.contact = (0.0, 0.0)
        self.min_stroke = np.inf  # the first state considered (t = 0) sets both
        self.max_stroke = -np.inf

    def consider(self, model: _HardModel, t, y, mode: _Mode) -> None:
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

    def consider_low(self, model: _HardModel, t, y, mode: _Mode) -> None:
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


class _Envelope:
    """The envelope's metrics as the solve goes: the barrel's forward crossings of
    `x_M = x_r + 1 mm` (time, speed), the stability margin's running minimum (with a mount),
    and the times the barrel sticks and slips."""

    def __init__(self, model: _HardModel):
        self.model = model
        self.returns: list[tuple[float, float]] = []
        self.margin = (np.inf, 0.0)
        self.sticks: list[float] = []
        self.slips: list[float] = []

    def consider(self, t, y, mode: _Mode) -> None:
        if self.model.mount:
            margin = self.model.margin(t, y, mode)
            if margin < self.margin[0]:
                self.margin = (margin, t)

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
    Also the firing envelope's metrics (`docs/model.md`, revision 2): `rest_position` (m,
    the static rest `x_r <= 0` the solve starts from, as `reference_rest`);
    `peak_displacement` is `max (x_M − x_r)`; `return_time` (s, from the last round's
    firing to the barrel's first forward crossing of `x_M = x_r + 1 mm` after it; None
    if it never comes back), `battery_speed` (m/s, `−v_M` at that crossing; None
    likewise), `returned` (bool), `residual_displacement` (m, `x_M − x_r` at the end),
    `peak_pull_force` (N, `max(0, −min F_AN)`) and `peak_pull_force_time` (s, where
    `F_AN` is least), `peak_mount_load` (N, `max |F_AN|`) and `peak_mount_load_time`,
    `stability_margin` (the least `(S − K d) / (m_g g L_w)`, `K = F_AN − (M + m) g sin θ`)
    and `stability_margin_time` (None without a mount), `end_time` (s, `t1` unless the
    solve stopped early) and `sticks`, `slips` (the times, s, at which friction held the
    barrel and let it go).

    **Raises:** `RuntimeError` if more than `max_segments` segments are needed (contact
    chatter when the system comes to rest on the contact boundary, at gap 0 after
    ~1.5 s: use a shorter `t1` for such designs), or if scipy fails.
    """
    model = _model_of(values, force_table)
    if t1 is None:
        t1 = 10.0 + (model.shots - 1) * model.interval
    done = _integrate(model, t1, rtol, atol, method, max_segments)
    return (
        done.running.metrics(model.x_r)
        | {"segments": done.segments, "status": done.status}
        | done.envelope.metrics(done.t, done.y)
    )


def reference_energy(
    values: Mapping[str, float] | None = None,
    t1: float | None = None,
    rtol: float = 1e-12,
    atol: float = 1e-14,
    method: str = "DOP853",
    max_segments: int = 20000,
    force_table=None,
) -> dict[str, float]:
    """The energy balance of the hard-switch model over `[0, t1]` (J), the work and the
    dissipation integrated as two more states of the same event-located solve:
    `breech_work` (the breech force's, impulses as their kinetic energy), `gravity_work`,
    `dissipated` (dampers, orifice, counter-recoil buffer, friction, and the contacts'
    Hunt–Crossley parts), `stored_change` (kinetic energy, springs, gas column and
    contacts' potentials: at the end less at rest in battery before the first round);
    they balance,
    `breech_work + gravity_work = dissipated + stored_change`. Arguments as
    `reference_peaks`."""
    model = _model_of(values, force_table)
    if t1 is None:
        t1 = 10.0 + (model.shots - 1) * model.interval
    done = _integrate(model, t1, rtol, atol, method, max_segments, audit=True)
    y0 = _initial_state(model)
    y0[1] = 0.0  # at rest in battery, before the first round's impulse (its work)
    y = done.y
    gravity = model.M * (y[0] - y0[0])
    if model.absorber:
        gravity += model.mass_m * (y[2] - y0[2])
    return {
        "breech_work": float(y[4]),
        "gravity_work": float(GRAVITY * model.sin * gravity),
        "dissipated": float(y[5]),
        "stored_change": float(model.stored_energy(y) - model.stored_energy(y0)),
        "end_time": float(done.t),
    }


def reference_rest(values: Mapping[str, float] | None = None) -> float:
    """The static rest `x_r` (m, `<= 0`) of the hard-switch model for flat parameter
    values (as `reference_peaks`): the root of `F_AN(x, v = 0) = (M + m) g sin θ` with
    friction left out, `k x + F_g + F_p − k_s (−x)^n_s`, with a battery stop
    (`stop_stiffness > 0`) and a preload above the axial weight; else 0."""
    return _model_of(values, None).x_r


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


def _initial_state(model: _HardModel) -> np.ndarray:
    """From the static rest in battery: `x_M = x_r`, `v_M = v0` under an impulse (else
    0), the absorber at rest at its sag on the barrel, `x_m = x_r + m g sin θ / k_r`."""
    return np.array([model.x_r, model.v0 if model.impulse else 0.0, model.x_m0, 0.0])


@dataclasses.dataclass
class _Done:
    """What `_integrate` ends with."""

    running: _RunningPeaks
    envelope: _Envelope
    segments: int
    status: str
    t: float
    y: np.ndarray


def _integrate(model, t1, rtol, atol, method, max_segments, ts=None, samples=None, audit=False):
    """The segment loop; with `ts`, `samples` filled in place; with `audit`, the state
    carries the breech force's work and the dissipated energy (`reference_energy`)."""
    import scipy.integrate  # when used: `import recoil_jax` stays quick

    peak_events = model.peak_events()
    low_events = model.low_events()
    envelope_events = model.envelope_events()
    running = _RunningPeaks()
    envelope = _Envelope(model)
    t = 0.0
    y = _initial_state(model)
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
            events=peak_events + low_events + envelope_events + switches,
            dense_output=ts is not None,
            **options,
        )
        if sol.status < 0:
            raise RuntimeError(f"reference solver failed: {sol.message}")
        assert sol.t_events is not None and sol.y_events is not None
        for index in range(len(peak_events)):
            for te, ye in zip(sol.t_events[index], sol.y_events[index], strict=True):
                running.consider(model, te, ye, mode)
        for index in range(len(peak_events), len(peak_events) + len(low_events)):
            for te, ye in zip(sol.t_events[index], sol.y_events[index], strict=True):
                running.consider_low(model, te, ye, mode)
        start = len(peak_events) + len(low_events)
        for index, event in enumerate(envelope_events, start=start):
            for te, ye in zip(sol.t_events[index], sol.y_events[index], strict=True):
                if event.kind == "return":
                    envelope.returns.append((float(te), float(ye[1])))
                envelope.consider(te, ye, mode)
        if ts is not None:
            _sample(model, sol, mode, t, sol.t[-1], ts, samples)
        empty = empty + 1 if sol.t[-1] == t else 0
        if empty > _MAX_EMPTY:
            raise RuntimeError(
                f"reference solver: {_MAX_EMPTY} switch events in a row at t = {t:.17g} s "
                f"without progress (mode {mode})"
            )
        t, y = sol.t[-1], sol.y[:, -1].copy()
        running.consider(model, t, y, mode)
        envelope.consider(t, y, mode)
        if sol.status == 1:
            first = len(peak_events) + len(low_events) + len(envelope_events)
            fired = {
                event.kind for i, event in enumerate(switches) if sol.t_events[first + i].size > 0
            }
            if "bottom" in fired:
                status = "bottomed_out"
            if model.envelope:
                was_stuck = mode.stuck
                mode = model.next_envelope_mode(t, mode, fired, y)
                if mode.stuck and not was_stuck:
                    envelope.sticks.append(t)
                elif was_stuck and not mode.stuck:
                    envelope.slips.append(t)
                # Friction, the counter-recoil buffer and the stop's clamp can make
                # F_AN jump at a switch: both sides count.
                running.consider(model, t, y, mode)
                envelope.consider(t, y, mode)
            else:
                mode = model.next_mode(mode, fired, y)
        elif t < t1:  # a stop: a round fires (a velocity jump for an impulse load)
            if model.impulse and np.any(
                np.isclose(t, model.firing_times()[1:], rtol=0, atol=1e-12)
            ):
                if audit:
                    y[4] += 0.5 * model.M * ((y[1] + model.v0) ** 2 - y[1] ** 2)
                y[1] += model.v0
            if model.envelope:
                was_stuck = mode.stuck
                new = model.classify(t, y, previous=mode)
                mode = new if not model.buffer else dataclasses.replace(new, piece=mode.piece)
                if mode.stuck and not was_stuck:
                    envelope.sticks.append(t)
                elif was_stuck and not mode.stuck:
                    envelope.slips.append(t)
            else:
                mode = (
                    model.initial_mode(y)
                    if not model.buffer
                    else dataclasses.replace(model.initial_mode(y), piece=mode.piece)
                )
            running.consider(model, t, y, mode)
            envelope.consider(t, y, mode)
            if ts is not None:  # a sample at the firing itself: after it, as at t = 0
                _sample_at(model, mode, t, y, ts, samples)
    return _Done(running, envelope, segments, status, t, y)


def _off_the_surface(event: _Event, start: float) -> _Event:
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


def _audited(model: _HardModel):
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
