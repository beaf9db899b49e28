"""A design and a model in words: the parameters a solve uses, a one-line description of a
design (figure titles), the model a calibration fitted."""

from __future__ import annotations

import recoil_jax as rj

__all__ = ["describe", "structure_line", "used_parameters"]


def used_parameters(params: rj.RecoilParams, table=None, source=None) -> dict:
    """The parameters a solve of `params` uses, by flat name (integers as integers); with a
    force `table` (read from `source`) the table's summary replaces `v0` and
    `pulse_time`, which it makes unused."""
    import numpy as np

    used: dict = {}
    for name, value in rj.params_to_values(params).items():
        if table is not None and name in ("v0", "pulse_time"):
            continue
        number = float(np.asarray(value))
        integer = name in rj.PARAMETERS and rj.PARAMETERS[name].integer
        used[name] = int(number) if integer else number
    if table is not None:
        t, F = np.asarray(table.t, dtype=float), np.asarray(table.F, dtype=float)
        used["force_table"] = {
            "file": str(source),
            "points": int(t.size),
            "duration_s": float(t[-1]),
            "impulse_N_s": float(np.sum(0.5 * (F[1:] + F[:-1]) * np.diff(t))),
        }
    return used


def describe(values: dict) -> str:
    """A one-line description of a design, for figure titles."""
    parts = []
    if values.get("m", 0.0) > 0:
        parts.append(f"absorber m={values['m']:g} kg, gap={1e3 * values['gap']:g} mm")
    else:
        parts.append("no absorber")
    if "shots" in values:
        shots = int(values["shots"])
        if "force_table" in values:
            load = "the force table"
        elif values.get("pulse_time"):
            load = f"a {values['pulse_time'] * 1e3:g} ms pulse"
        else:
            load = "an impulse"
        rounds = f"1 round of {load}" if shots == 1 else f"{shots} rounds of {load}"
        every = f" every {values['fire_interval']:g} s" if shots > 1 else ""
        parts.append(rounds + every)
    knots = sum(1 for name in values if name.startswith("orifice_") and name[8:].isdigit())
    if knots and values.get("piston_area", 0.0) > 0:
        parts.append(f"{knots}-knot orifice")
    if values.get("recuperator_force", 0.0) > 0:
        parts.append(f"recuperator {values['recuperator_force']:g} N")
    if values.get("recuperator_preload", 0.0) > 0:
        parts.append(f"preload {values['recuperator_preload'] / 1e3:g} kN")
    if "elevation" in values:
        parts.append(f"elevation {values['elevation']:g}°")
    return ", ".join(parts)


def structure_line(structure: dict) -> str:
    """The model a calibration fitted, in words (`CalibrationResult.structure`)."""
    if not structure:
        return "unknown"
    load = {"impulse": "an impulse (v0)", "pulse": "a pulse (pulse_time)",
            "force table": "a measured force table"}[structure["load"]]  # fmt: skip
    shots = structure["shots"]
    hardware = " and ".join(structure["hardware"]) or "no buffer or recuperator"
    absorber = "absorber" if structure["absorber"] else "no absorber (m = 0)"
    return f"{absorber}; {shots} round{'s' if shots > 1 else ''} of {load}; {hardware}"
