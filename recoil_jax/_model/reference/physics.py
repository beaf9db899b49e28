"""The reference's model with hard switches: its parameters, its static rest, and its
forces, rates, energy and powers in each mode (`Mode`), written out in NumPy apart from
the JAX model (`docs/model.md`)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping

import numpy as np

__all__ = [
    "BAND",
    "BATTERY",
    "BOTTOM",
    "GRAVITY",
    "MAX_EMPTY",
    "PULSE_WINDOW",
    "Event",
    "HardPhysics",
    "Mode",
]

BOTTOM = 0.95  # the recuperator's gas column may be compressed to this fraction
#: Standard gravity (m/s²), as `docs/model.md` fixes it.
GRAVITY = 9.80665
#: In battery to within this (m): the return is the barrel coming forward through it.
BATTERY = 1e-3
#: Pulse times from a round's firing over which a stuck barrel's steps are held short.
PULSE_WINDOW = 50.0
#: The friction band's relative margin for rounding (`HardModel.band`).
BAND = 1e-9
#: Segments in a row that may end where they started (a state exactly on a switching
#: surface crosses it in a zero-length segment) before the solve is declared stuck.
MAX_EMPTY = 50


@dataclasses.dataclass(frozen=True)
class Mode:
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
class Event:
    """A `solve_ivp` event: the zeros of `surface(t, y, mode)` crossed in `direction`
    (0: either way); `terminal` ends the segment there, `kind` says which switch."""

    surface: Callable[[float, np.ndarray, Mode], float]
    direction: float = 0.0
    terminal: bool = False
    kind: str = ""

    def __call__(self, t, y, mode) -> float:
        return self.surface(t, y, mode)


class HardPhysics:
    """The model with hard switches, for flat parameter values and an optional force
    table `(t, F)` of one round: its parameters, its static rest, and its forces and
    rates in each mode (`HardModel` adds the switches between the modes)."""

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
        self.band = self.F_max * (1.0 + BAND)
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

    def area(self, x, mode: Mode) -> tuple[float, float]:
        """The orifice area and its slope dA/dx on the mode's piece."""
        K = len(self.knots)
        if mode.piece < 0:
            return self.knots[0], 0.0
        if mode.piece >= K - 1:
            return self.knots[-1], 0.0
        i = mode.piece
        slope = (self.knots[i + 1] - self.knots[i]) / (self.knot_x[i + 1] - self.knot_x[i])
        return self.knots[i] + slope * (x - self.knot_x[i]), slope

    def orifice(self, y, mode: Mode) -> float:
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

    def damping(self, mode: Mode) -> float:
        return self.c_out if mode.moving_out else self.c_ret

    def contact_force(self, y, mode: Mode) -> float:
        if not self.absorber or not mode.contact or mode.clamped:
            return 0.0
        delta = max(y[0] - y[2] - self.gap, 0.0)
        return self.k_c * delta**self.n_c * (1.0 + self.lam * (y[1] - y[3]))

    def stop_force(self, y, mode: Mode) -> float:
        """F_s = k_s δ^n_s (1 + λ_s δ̇), δ = −x_M, in the stop and unclamped."""
        if not self.stop or not mode.stop or mode.stop_clamped:
            return 0.0
        delta = max(-y[0], 0.0)
        return self.k_s * delta**self.n_s * (1.0 - self.lam_s * y[1])

    def counter_force(self, y, mode: Mode) -> float:
        """F_cb = c_b v_M while v_M < 0 and x_M < L_b."""
        if not self.counter_buffer or not mode.in_buffer or mode.moving_out or mode.stuck:
            return 0.0
        return self.c_b * y[1]

    def coupling(self, y) -> float:
        if not self.absorber:
            return 0.0
        return self.k_r * (y[0] - y[2]) + self.c_r * (y[1] - y[3])

    def held(self, y, mode: Mode) -> float:
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

    def net_force(self, t, y, mode: Mode) -> float:
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

    def friction_force(self, t, y, mode: Mode) -> float:
        """F_f: ±F_max sliding; held at rest, the net force N."""
        if not self.friction:
            return 0.0
        if mode.stuck:
            return self.net_force(t, y, mode)
        return self.F_max if mode.moving_out else -self.F_max

    def anchoring(self, y, mode: Mode, t: float = 0.0) -> float:
        if not self.envelope:
            return (
                self.k * y[0] + self.damping(mode) * y[1] + self.orifice(y, mode) + self.gas(y[0])
            )
        return self.held(y, mode) + self.friction_force(t, y, mode)

    def rhs(self, t, y, mode: Mode):
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

    def rates(self, t, y, mode: Mode) -> tuple[float, float]:
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

    def margin(self, t, y, mode: Mode) -> float:
        """(S − O) / (m_g g L_w): the share of the stabilising moment left (with a mount).
        `O = K d`, `K = F_AN − (M + m) g sin θ` (the resistance net of the axial weight),
        and `S = g (m_g L_w − (M (x_M − x_M(0)) + m (x_m − x_m(0))) cos θ)`."""
        moved = self.M * (y[0] - self.x_r)
        if self.absorber:
            moved += self.mass_m * (y[2] - self.x_m0)
        stabilising = GRAVITY * (self.mount_mass * self.L_w - moved * self.cos)
        overturning = (self.anchoring(y, mode, t) - self.weight) * self.lever
        return (stabilising - overturning) / (self.mount_mass * GRAVITY * self.L_w)

    def margin_rate(self, t, y, mode: Mode) -> float:
        """d margin / dt within a mode."""
        speed = self.M * y[1] + (self.mass_m * y[3] if self.absorber else 0.0)
        d_anchor, _ = self.rates(t, y, mode)
        return (-GRAVITY * speed * self.cos - d_anchor * self.lever) / (
            self.mount_mass * GRAVITY * self.L_w
        )

    def stops(self, t1: float) -> np.ndarray:
        """Segment ends known in advance: later rounds, and every table point."""
        times = list(self.firing_times()[1:])
        if self.table is not None:
            times += [tj + ti for tj in self.firing_times() for ti in self.table[0]]
        if self.envelope and not self.impulse and self.table is None:
            times += list(self.firing_times() + PULSE_WINDOW * self.pulse_time)
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

    def powers(self, t, y, mode: Mode) -> tuple[float, float]:
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
