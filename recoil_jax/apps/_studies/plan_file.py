"""`recoil-jax plan`'s file: a firing test to plan (`rj.PlanProblem`), from a TOML file or
the name of a shipped example (`optimise/plans/`), checked before anything compiles.

```toml
description = "what the test must pin down"
robust = 0                # optional: average the criterion over N draws from [fit]
seed = 0
[design]                  # the best guess before the test (also the fixed values)
M = 1800.0
[fit]                     # what the test must determine: bounds [lower, upper]
c_out = [5e3, 5e4]
[candidates]              # each firing may take any combination of these values
elevation = [0, 15, 30, 45, 60, 70]
v0 = [8.0, 10.0]
[signals]                 # what can be recorded: its noise, and its cost per firing
x_M = { sigma = 3e-4, cost = 1.0 }
[sampling]
rate = 1000.0             # samples per second, from the firing
duration = 3.0            # seconds recorded
[budget]
firings = 3
cost = 4.0                # optional: the most a firing's signals may cost
[criterion]
name = "D"                # "D", "A", or a fitted parameter's name
```
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import recoil_jax as rj

from .._files.inputs import (
    check_keys,
    file_error as _error,
    file_integer,
    file_number as _number,
    read_toml,
    resolve_shipped,
)

__all__ = ["SHIPPED", "load_plan"]

#: The shipped examples.
SHIPPED = Path(__file__).resolve().parents[3] / "optimise" / "plans"

_SECTIONS = {"description", "robust", "seed", "design", "fit", "candidates", "signals",
             "sampling", "budget", "criterion"}  # fmt: skip


def _table(path, config: dict, section: str, required: bool = True) -> dict:
    if section not in config:
        if required:
            raise _error(path, f"missing [{section}]")
        return {}
    value = config[section]
    if not isinstance(value, dict):
        raise _error(path, f"[{section}] must be a table (a [{section}] section)")
    return value


def _fit(path, section: dict) -> dict[str, tuple[float, float]]:
    fit = {}
    for name, value in section.items():
        if not (isinstance(value, list) and len(value) == 2):
            raise _error(path, f"[fit] {name} = {value!r}: give bounds as [lower, upper]")
        fit[name] = tuple(_number(f"{path}: [fit] {name}", v) for v in value)
    return fit


def _candidates(path, section: dict) -> dict[str, list[float]]:
    candidates = {}
    for name, values in section.items():
        if not isinstance(values, list):
            raise _error(path, f"[candidates] {name} = {values!r}: give a list of values")
        candidates[name] = [_number(f"{path}: [candidates] {name}", v) for v in values]
    return candidates


def _signals(path, section: dict) -> dict[str, rj.Sensor]:
    signals = {}
    for name, value in section.items():
        where = f"{path}: [signals] {name}"
        if not isinstance(value, dict) or "sigma" not in value:
            raise _error(where, "give { sigma = noise, cost = per firing }")
        check_keys(where, "", value, ("sigma", "cost"))
        sigma = _number(f"{where}.sigma", value["sigma"])
        signals[name] = rj.Sensor(sigma, _number(f"{where}.cost", value.get("cost", 1.0)))
    return signals


def load_plan(source) -> tuple[rj.PlanProblem, str]:
    """A plan file (or a shipped example's name) as a checked `rj.PlanProblem`, and its
    description. Every refusal is one line naming the file and the entry."""
    path = resolve_shipped(source, SHIPPED, "plan", "plans")
    config = read_toml(path, "plan file")
    check_keys(path, "", config, _SECTIONS, kind="section")
    description = config.get("description", "")
    if not isinstance(description, str):
        raise _error(path, "description must be a string")
    design = {
        name: _number(f"{path}: [design] {name}", value)
        for name, value in _table(path, config, "design", required=False).items()
    }
    sampling = _table(path, config, "sampling")
    check_keys(path, "sampling", sampling, ("rate", "duration"))
    budget = _table(path, config, "budget")
    check_keys(path, "budget", budget, ("firings", "cost"))
    criterion = _table(path, config, "criterion", required=False)
    check_keys(path, "criterion", criterion, ("name",))
    for key in ("rate", "duration"):
        if key not in sampling:
            raise _error(path, f"[sampling] needs {key}")
    if "firings" not in budget:
        raise _error(path, "[budget] needs firings (how many rounds)")
    arguments: dict[str, Any] = {
        "design": design,
        "fit": _fit(path, _table(path, config, "fit")),
        "candidates": _candidates(path, _table(path, config, "candidates")),
        "signals": _signals(path, _table(path, config, "signals")),
        "rate": _number(f"{path}: [sampling] rate", sampling["rate"]),
        "duration": _number(f"{path}: [sampling] duration", sampling["duration"]),
        "firings": file_integer(path, "[budget] firings", budget["firings"], 1, 50),
        "cost": None if "cost" not in budget else _number(f"{path}: [budget] cost", budget["cost"]),
        "criterion": criterion.get("name", "D"),
        "robust": file_integer(path, "robust", config.get("robust", 0), 0, 256),
        "seed": file_integer(path, "seed", config.get("seed", 0), 0),
    }
    if not isinstance(arguments["criterion"], str):
        raise _error(path, f"[criterion] name = {arguments['criterion']!r}: give a string")
    try:
        problem = rj.PlanProblem(**arguments)
    except rj.ParameterError as error:
        raise _error(path, str(error)) from None
    return problem, description
