"""Hazards, named unasked (`docs/model.md`, revision 2): what a design at a condition would
do in the field that a forgotten limit could hide.

`HAZARDS` is the one registry: each hazard's name, its rule and the sentence that reports
it with its value. Every report of a design (`simulate`, a study's summary and
`result.json`, a sweep's rows, the explorer) takes them from `design_hazards` (one
design) or `hazard_flags` (a batch, as arrays).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from .._model.forces.rails import GRAVITY
from .._model.parameter_table import PARAMETERS
from .._model.params import params_to_values

__all__ = ["HAZARDS", "Hazard", "design_hazards", "hazard_flags", "hazard_names", "peaks_hazards"]

#: A barrel further than this from its rest at `t1` is out of battery (m).
OUT_OF_BATTERY = 1e-3
#: An absorber whose contact force never reaches this has not touched its wall (N): the
#: smoothed contact's onset gives a few newtons at most to an absorber that only grazes.
IDLE_CONTACT = 1.0


def _value(metrics: Mapping[str, Any], name: str):
    """A metric as a float array; NaN where a design has none (None)."""
    value = metrics.get(name)
    if value is None:
        return np.float64(np.nan)
    return np.asarray(value, dtype=float)


def _returned(metrics: Mapping[str, Any]):
    """`returned` as 1.0 or 0.0, NaN where a design has no return (no envelope: its
    residual is NaN or None)."""
    returned = metrics.get("returned")
    if returned is None:
        return np.float64(np.nan)
    known = np.isfinite(_value(metrics, "residual_displacement"))
    return np.where(known, np.asarray(returned, dtype=float), np.nan)


def _statics(values: Mapping[str, Any]) -> dict[str, Any]:
    """The rest's forces from flat parameter values (arrays or floats; defaults as the
    registry's): the axial weight `W = (M + m) g sin θ`, the friction's hold `F_max` and
    the preload `P` (N), and the absorber's mass `m` (kg)."""

    def given(name):
        return np.asarray(values.get(name, PARAMETERS[name].default), dtype=float)

    M, m = given("M"), given("m")
    theta = np.radians(given("elevation"))
    mass = M + m
    weight = mass * GRAVITY * np.sin(theta)
    hold = given("friction_force") + given("friction_coefficient") * mass * GRAVITY * np.cos(theta)
    preload = given("recuperator_preload")
    return {"weight": weight, "hold": hold, "preload": preload, "m": m}


@dataclasses.dataclass(frozen=True)
class Hazard:
    """One hazard: its `name`, the rule (`when`, as `docs/model.md` tables it), `test`
    (flags from the metrics by name and the statics, arrays), `sentence` (the report of
    one flagged design, with its value) and `metric`, the metric whose limit covers it
    (None: no limit can; a study names a hazard that no limit covers as a warning)."""

    name: str
    when: str
    test: Callable[[Mapping[str, Any], Mapping[str, Any]], Any]
    sentence: Callable[[Mapping[str, Any], Mapping[str, Any]], str]
    metric: str | None


def _kn(force) -> str:
    return f"{float(force) / 1e3:,.1f} kN"


#: The hazards by name, in the order they are reported.
HAZARDS: dict[str, Hazard] = {
    h.name: h
    for h in (
        Hazard(
            "lifts",
            "stability_margin < 0: the wheels leave the ground (a mount is given)",
            lambda k, s: _value(k, "stability_margin") < 0,
            lambda k, s: (
                "the wheels leave the ground: the stability margin falls to "
                f"{float(_value(k, 'stability_margin')):.3g}"
            ),
            "stability_margin",
        ),
        Hazard(
            "slams",
            "peak_pull_force > peak_anchoring_force: the return loads the mount more than "
            "the recoil",
            lambda k, s: _value(k, "peak_pull_force") > _value(k, "peak_anchoring_force"),
            lambda k, s: (
                "the return loads the mount more than the recoil: it pulls "
                f"{_kn(_value(k, 'peak_pull_force'))} against a "
                f"{_kn(_value(k, 'peak_anchoring_force'))} push"
            ),
            "peak_pull_force",
        ),
        Hazard(
            "no_return",
            "no return to battery before t1 (of a barrel that left it: an unfired gun has "
            "none to make)",
            lambda k, s: (_returned(k) == 0.0) & (_value(k, "peak_displacement") > OUT_OF_BATTERY),
            lambda k, s: "the barrel does not come back into battery before t1",
            "return_time",
        ),
        Hazard(
            "out_of_battery",
            f"residual_displacement > {OUT_OF_BATTERY * 1e3:g} mm",
            lambda k, s: _value(k, "residual_displacement") > OUT_OF_BATTERY,
            lambda k, s: (
                "the barrel stays "
                f"{float(_value(k, 'residual_displacement')) * 1e3:.1f} mm out of battery at t1"
            ),
            "residual_displacement",
        ),
        Hazard(
            "sags",
            "at rest the barrel is not held in battery: no stop rest exists and the axial "
            "weight exceeds the friction's hold, (M + m) g sin θ > F_max + F_AN(0, 0)",
            lambda k, s: s["weight"] > s["hold"] + s["preload"],
            lambda k, s: (
                "nothing holds the barrel in battery before the shot: its axial "
                f"weight {_kn(s['weight'])} exceeds the friction's hold {_kn(s['hold'])} and "
                f"the preload {_kn(s['preload'])}"
            ),
            None,
        ),
        Hazard(
            "absorber_idle",
            f"an absorber is fitted (m > 0) and never touches its wall (peak contact force "
            f"< {IDLE_CONTACT:g} N)",
            lambda k, s: (s["m"] > 0) & (_value(k, "peak_contact_force") < IDLE_CONTACT),
            lambda k, s: f"the {float(s['m']):g} kg absorber never touches its wall",
            "peak_contact_force",
        ),
    )
}


def hazard_names() -> tuple[str, ...]:
    """The hazards' names, in the order they are reported."""
    return tuple(HAZARDS)


def hazard_flags(values: Mapping[str, Any], metrics: Mapping[str, Any]) -> dict[str, Any]:
    """Which designs have each hazard, by name (bool arrays, broadcast over the batch):
    `values` are flat parameter values (arrays or floats; absent ones at their defaults,
    as `params_to_values` gives them), `metrics` the metrics by name (arrays, NaN or None
    where a design has none) and `returned`. A metric a design has not got (NaN) flags
    nothing."""
    statics = _statics(values)
    return {name: np.asarray(h.test(metrics, statics), dtype=bool) for name, h in HAZARDS.items()}


def design_hazards(values: Mapping[str, Any], metrics: Mapping[str, Any]) -> list[dict[str, str]]:
    """The hazards of one design at one condition, as `[{"name", "sentence"}]` in the
    registry's order (`hazard_flags`'s arguments, scalars)."""
    statics = _statics(values)
    flags = hazard_flags(values, metrics)
    return [
        {"name": name, "sentence": HAZARDS[name].sentence(metrics, statics)}
        for name, flagged in flags.items()
        if bool(flagged)
    ]


def peaks_hazards(params, peaks) -> list[dict[str, str]]:
    """`design_hazards` of one solved design: `params` (`RecoilParams`) and its `Peaks`."""
    return design_hazards(params_to_values(params), peaks.metrics() | {"returned": peaks.returned})
