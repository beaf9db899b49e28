"""The reference's switches: the events that end a segment or locate a peak, and the mode
the state is in on each side of them (contact, clamps, damping sign, orifice pieces,
the battery stop, the counter-recoil buffer, and exact stick–slip friction)."""

from __future__ import annotations

import dataclasses

import numpy as np

from ..._model.reference.physics import BATTERY, BOTTOM, PULSE_WINDOW, Event, HardPhysics, Mode

__all__ = ["HardModel"]


class HardModel(HardPhysics):
    """The model with hard switches (`HardPhysics`) and its switches: the events of each
    mode, and the mode after each event."""

    def peak_events(self) -> list[Event]:
        """Non-terminal surfaces where a tracked quantity may peak: the falling zeros of
        v_M, dF_AN/dt and dF_ct/dt, and every zero of the stroke rate."""
        events = [
            Event(lambda t, y, mode: y[1] if not mode.stuck else -1.0, direction=-1.0),
            Event(lambda t, y, mode: self.rates(t, y, mode)[0], direction=-1.0),
            Event(lambda t, y, mode: self.rates(t, y, mode)[1], direction=-1.0),
            Event(lambda t, y, mode: y[1] - y[3]),
        ]
        if self.envelope and not self.absorber:
            # Without an absorber F_ct = 0, and a stuck barrel's stroke rate is 0: a
            # surface that is zero everywhere is a root at every step (the paper's path
            # keeps its events as they were).
            # Likewise F_AN while stuck under an impulse load: constant.
            events[1] = Event(
                lambda t, y, mode: -1.0 if self.constant(mode) else self.rates(t, y, mode)[0],
                direction=-1.0,
            )
            events[2] = Event(lambda t, y, mode: -1.0, direction=-1.0)
            events[3] = Event(lambda t, y, mode: y[1] - y[3] if not mode.stuck else 1.0)
        return events

    def low_events(self) -> list[Event]:
        """Non-terminal surfaces where F_AN may be least (`peak_pull_force`): the rising
        zeros of dF_AN/dt (not where it is constant: a surface zero everywhere is a root
        at every step). Apart from `peak_events`, so that the peaks they locate are
        found at the same points as before."""
        if self.envelope and not self.absorber:
            return [
                Event(
                    lambda t, y, mode: 1.0 if self.constant(mode) else self.rates(t, y, mode)[0],
                    direction=1.0,
                )
            ]
        return [Event(lambda t, y, mode: self.rates(t, y, mode)[0], direction=1.0)]

    def constant(self, mode: Mode) -> bool:
        """Nothing moves and no force changes: a stuck barrel without an absorber under
        an impulse load (between its rounds)."""
        return mode.stuck and not self.absorber and self.impulse

    def envelope_events(self) -> list[Event]:
        """Non-terminal surfaces of the envelope's metrics: the barrel coming forward
        through `x_M = x_r + 1 mm` (the return), and the rising zeros of the stability
        margin's rate (its local minima), with a mount."""
        battery = self.x_r + BATTERY
        events = [
            Event(
                lambda t, y, mode: y[0] - battery if not mode.stuck else 1.0,
                direction=-1.0,
                kind="return",
            )
        ]
        if self.mount:
            events.append(
                Event(
                    lambda t, y, mode: 1.0 if self.constant(mode) else self.margin_rate(t, y, mode),
                    direction=1.0,
                    kind="margin",
                )
            )
        return events

    def switch_events(self, mode: Mode) -> list[Event]:
        """Terminal events that fire only when leaving the current mode's region, so a
        segment that starts on a switching surface cannot re-detect it."""
        if mode.stuck:
            return self.stuck_events(mode)
        events = [
            Event(
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
                events.append(Event(lambda t, y, mode, b=low: y[0] - b, -1.0, True, "piece down"))
            if mode.piece <= K - 2:
                high = self.knot_x[mode.piece + 1]
                events.append(Event(lambda t, y, mode, b=high: y[0] - b, 1.0, True, "piece up"))
        if self.recuperator:
            bottom = BOTTOM * self.L_r
            events.append(Event(lambda t, y, mode: y[0] - bottom, 1.0, True, "bottom"))
        if self.stop:
            events.append(
                Event(
                    lambda t, y, mode: -y[0],
                    direction=-1.0 if mode.stop else 1.0,
                    terminal=True,
                    kind="stop",
                )
            )
            if mode.stop and self.lam_s > 0:
                events.append(
                    Event(
                        lambda t, y, mode: 1.0 - self.lam_s * y[1],
                        direction=1.0 if mode.stop_clamped else -1.0,
                        terminal=True,
                        kind="stop clamp",
                    )
                )
        if self.counter_buffer:
            events.append(
                Event(
                    lambda t, y, mode: y[0] - self.L_b,
                    direction=1.0 if mode.in_buffer else -1.0,
                    terminal=True,
                    kind="counter buffer",
                )
            )
        return events

    def absorber_events(self, mode: Mode) -> list[Event]:
        """The absorber's switches, held barrel or not: its contact with the barrel
        closing or opening, and within contact the Hunt–Crossley clamp."""
        if not self.absorber:
            return []
        events = [
            Event(
                lambda t, y, mode: y[0] - y[2] - self.gap,
                direction=-1.0 if mode.contact else 1.0,
                terminal=True,
                kind="contact",
            )
        ]
        if mode.contact and self.lam > 0:
            events.append(
                Event(
                    lambda t, y, mode: 1.0 + self.lam * (y[1] - y[3]),
                    direction=1.0 if mode.clamped else -1.0,
                    terminal=True,
                    kind="clamp",
                )
            )
        return events

    def stuck_events(self, mode: Mode) -> list[Event]:
        """A barrel held by friction: it slips when the net force on it reaches ±F_max;
        only the absorber moves (its contact and clamp switches)."""
        events = [
            Event(
                lambda t, y, mode: self.net_force(t, y, mode) - self.band,
                direction=1.0,
                terminal=True,
                kind="slip out",
            ),
            Event(
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

    def initial_mode(self, y) -> Mode:
        delta = y[0] - y[2] - self.gap
        contact = self.absorber and (delta > 0 or (delta == 0 and y[1] - y[3] > 0))
        clamped = contact and self.lam * (y[1] - y[3]) < -1.0
        moving_out = y[1] > 0 or (y[1] == 0 and self.breech(0.0) > 0)
        return Mode(
            moving_out=bool(moving_out),
            contact=bool(contact),
            clamped=bool(clamped),
            piece=self.piece(y[0], y[1]),
        )

    def classify(self, t, y, previous: Mode | None = None) -> Mode:
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

    def next_mode(self, mode: Mode, fired: set[str], y) -> Mode:
        """The mode after the switch events of the kinds in `fired`."""
        moving_out = (not mode.moving_out) if "velocity" in fired else mode.moving_out
        in_contact = (not mode.contact) if "contact" in fired else mode.contact
        clamped = (not mode.clamped) if "clamp" in fired else mode.clamped
        if not in_contact:
            clamped = False
        elif "contact" in fired:  # a new contact
            clamped = self.lam * (y[1] - y[3]) < -1.0
        piece = mode.piece + ("piece up" in fired) - ("piece down" in fired)
        return Mode(moving_out=moving_out, contact=in_contact, clamped=bool(clamped), piece=piece)

    def next_envelope_mode(self, t, mode: Mode, fired: set[str], y) -> Mode:
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

    def step_limit(self, start: float, end: float, mode: Mode) -> dict[str, float]:
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
        window = PULSE_WINDOW * self.pulse_time  # its end is a segment end (`stops`)
        acting = [tj for tj in self.firing_times() if tj < end and start < tj + window]
        return {"max_step": self.pulse_time / 8} if acting else {}
