"""An independent reference solver: scipy `solve_ivp`, hard switches, event-located.

Shares no code with the JAX model: the equations are written out again here in NumPy.
Each switch (contact onset `δ = 0`, damping sign `v_M = 0`, the no-pull clamp
`1 + λ_c δ̇ = 0`) ends an integration segment at an exactly located event, so every
segment is smooth and the integrator keeps its full order. Peaks are located as events of
their time derivatives (and checked at every segment end), not read off a grid.

Used by the tests as ground truth across the documented ranges, and as the serial
baseline of the benchmarks.
"""

from __future__ import annotations

import numpy as np
from scipy.integrate import solve_ivp

from ._params import PARAMETER_NAMES, params_from_values, params_to_values


class _Mode:
    def __init__(self, moving_out: bool, contact: bool, clamped: bool):
        self.moving_out = moving_out  # v_M > 0: damping c_out
        self.contact = contact  # δ > 0
        self.clamped = clamped  # 1 + λ δ̇ < 0 while in contact: F_ct = 0


def reference_peaks(
    values: dict | None = None,
    t1: float = 10.0,
    rtol: float = 1e-12,
    atol: float = 1e-14,
    method: str = "DOP853",
    max_segments: int = 20000,
) -> dict:
    """Peaks of the hard-switch model for flat parameter `values` (names as
    `params_from_values`, defaults filled in). Returns a dict with the `simulate --json`
    keys plus `min_stroke_m`, `max_stroke_m` and `segments`.

    Raises `RuntimeError` if more than `max_segments` switch events occur (contact
    chatter when the system comes to rest on the contact boundary, at gap 0 after
    ~1.5 s): use a shorter `t1` for such designs.
    """
    p = params_to_values(params_from_values(values or {}))
    p = {name: float(np.asarray(v)) for name, v in p.items() if name in PARAMETER_NAMES}
    M, k, c_out, c_ret, v0 = p["M"], p["k"], p["c_out"], p["c_ret"], p["v0"]
    absorber = p["m"] > 0
    m = p["m"] if absorber else 1.0
    gap = p.get("gap", 0.0)
    k_r = p.get("k_r", 0.0) if absorber else 0.0
    c_r = p.get("c_r", 0.0) if absorber else 0.0
    k_c, n_c, lam = p["k_c"], p["n_c"], p["lambda_c"]

    def contact_force(y, mode):
        if not absorber or not mode.contact or mode.clamped:
            return 0.0
        delta = max(y[0] - y[2] - gap, 0.0)
        return k_c * delta**n_c * (1.0 + lam * (y[1] - y[3]))

    def rhs(t, y, mode):
        x_M, v_M, x_m, v_m = y
        c = c_out if mode.moving_out else c_ret
        coupling = k_r * (x_M - x_m) + c_r * (v_M - v_m) if absorber else 0.0
        f_ct = contact_force(y, mode)
        a_M = (-c * v_M - k * x_M - coupling - f_ct) / M
        a_m = (coupling + f_ct) / m if absorber else 0.0
        return np.array([v_M, a_M, v_m, a_m])

    def anchoring(y, mode):
        return k * y[0] + (c_out if mode.moving_out else c_ret) * y[1]

    def rates(y, mode):
        """Time derivatives of F_AN and F_ct within a mode."""
        a = rhs(0.0, y, mode)
        c = c_out if mode.moving_out else c_ret
        d_anchor = k * y[1] + c * a[1]
        d_contact = 0.0
        if absorber and mode.contact and not mode.clamped:
            delta = max(y[0] - y[2] - gap, 0.0)
            rate = y[1] - y[3]
            accel = a[1] - a[3]
            d_contact = k_c * (
                n_c * delta ** (n_c - 1.0) * rate * (1.0 + lam * rate) + delta**n_c * lam * accel
            )
        return d_anchor, d_contact

    # Peak surfaces (non-terminal): falling zero of each quantity's rate.
    def ev_velocity_peak(t, y, mode):
        return y[1]

    def ev_anchor_peak(t, y, mode):
        return rates(y, mode)[0]

    def ev_contact_peak(t, y, mode):
        return rates(y, mode)[1]

    def ev_stroke_turn(t, y, mode):
        return y[1] - y[3]

    for ev in (ev_velocity_peak, ev_anchor_peak, ev_contact_peak):
        ev.direction = -1.0
    peak_events = [ev_velocity_peak, ev_anchor_peak, ev_contact_peak, ev_stroke_turn]

    def switch_events(mode):
        """Terminal events that fire only when leaving the current mode's region, so a
        segment that starts on a switching surface cannot re-detect it."""

        def velocity(t, y, mode):
            return y[1]

        velocity.direction = -1.0 if mode.moving_out else 1.0
        events = [velocity]
        if absorber:

            def contact(t, y, mode):
                return y[0] - y[2] - gap

            contact.direction = -1.0 if mode.contact else 1.0
            events.append(contact)
            if mode.contact and lam > 0:

                def clamp(t, y, mode):
                    return 1.0 + lam * (y[1] - y[3])

                clamp.direction = 1.0 if mode.clamped else -1.0
                events.append(clamp)
        for ev in events:
            ev.terminal = True
        return events

    def make_mode(y):
        delta = y[0] - y[2] - gap
        contact = absorber and (delta > 0 or (delta == 0 and y[1] - y[3] > 0))
        clamped = contact and lam * (y[1] - y[3]) < -1.0
        return _Mode(moving_out=y[1] > 0, contact=contact, clamped=clamped)

    # Running maxima (value, time); the initial state is considered below.
    best = {"x": (-np.inf, 0.0), "F": (-np.inf, 0.0), "Fc": (0.0, 0.0), "smin": 0.0,
            "smax": 0.0}

    def consider(t, y, mode):
        if y[0] > best["x"][0]:
            best["x"] = (y[0], t)
        fan = anchoring(y, mode)
        if fan > best["F"][0]:
            best["F"] = (fan, t)
        fct = contact_force(y, mode)
        if fct > best["Fc"][0]:
            best["Fc"] = (fct, t)
        stroke = y[2] - y[0]
        best["smin"] = min(best["smin"], stroke)
        best["smax"] = max(best["smax"], stroke)

    t, y = 0.0, np.array([0.0, v0, 0.0, 0.0])
    mode = make_mode(y)
    consider(t, y, mode)
    segments = 0
    while t < t1:
        segments += 1
        if segments > max_segments:
            raise RuntimeError(
                f"reference solver: more than {max_segments} switch events before t1 = {t1} "
                f"(stopped at t = {t:.6g} s); use a shorter t1"
            )
        switches = switch_events(mode)
        sol = solve_ivp(
            rhs, (t, t1), y, method=method, rtol=rtol, atol=atol, args=(mode,),
            events=peak_events + switches,
        )
        if sol.status < 0:
            raise RuntimeError(f"reference solver failed: {sol.message}")
        for index in range(len(peak_events)):
            for te, ye in zip(sol.t_events[index], sol.y_events[index], strict=True):
                consider(te, ye, mode)
        t, y = sol.t[-1], sol.y[:, -1].copy()
        consider(t, y, mode)
        if sol.status == 1:
            fired = [ev for i, ev in enumerate(switches)
                     if sol.t_events[len(peak_events) + i].size]
            mode = _Mode(
                moving_out=(not mode.moving_out) if switches[0] in fired else mode.moving_out,
                contact=(not mode.contact) if (len(switches) > 1 and switches[1] in fired)
                else mode.contact,
                clamped=mode.clamped,
            )
            if len(switches) > 2 and switches[2] in fired:
                mode.clamped = not mode.clamped
            if not mode.contact:
                mode.clamped = False
            elif len(switches) > 1 and switches[1] in fired:  # new contact
                mode.clamped = lam * (y[1] - y[3]) < -1.0
    return {
        "peak_displacement_m": best["x"][0],
        "peak_displacement_time_s": best["x"][1],
        "peak_anchoring_force_N": best["F"][0],
        "peak_anchoring_force_time_s": best["F"][1],
        "peak_contact_force_N": best["Fc"][0],
        "peak_contact_force_time_s": best["Fc"][1],
        "min_stroke_m": best["smin"],
        "max_stroke_m": best["smax"],
        "segments": segments,
    }

