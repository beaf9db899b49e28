"""`recoil-jax sensitivity`: global sensitivity of the peaks over a tolerance box, from a
file (TOML) or the name of a shipped example (`sensitivity/`); `result.json`,
`samples.csv` and the figures.

The file, in the style of the study files:

```toml
description = "..."
[design]            # the base design: every value not ranged (paper values elsewhere)
m = 1500.0
[ranges]            # parameter = [low, high] (SI units), or { relative = 0.05 }
k = [25000.0, 30000.0]
v0 = { relative = 0.03 }
[metrics]
names = ["peak_anchoring_force", "peak_displacement"]
objective = { peak_anchoring_force = 1.0 }   # optional: also "objective", their sum
study = "tuned_absorber"                      # optional: its objective and limited metrics
[method]
name = "sobol"      # or "morris", "dgsm"; then that method's settings:
samples = 1024      # sobol: samples, second_order, resamples, seed
                    # morris: trajectories, levels, resamples, seed
                    # dgsm: samples, resamples, seed
[calibration]       # optional: ranges from a fit's uncertainty
from = "result.json"  # a calibration's result (relative to this file)
sigmas = 2.0          # each fitted value +- 2 standard errors
```
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import recoil_jax as rj
import recoil_jax.extend as rjx

from .._files.inputs import (
    check_keys,
    file_error as _error,
    file_number as _number,
    read_calibration_section,
    read_toml,
    resolve_shipped,
)

__all__ = ["SHIPPED", "load_sensitivity", "resolve_sensitivity"]


#: The shipped examples.
SHIPPED = Path(__file__).resolve().parents[3] / "sensitivity"


_SECTIONS = {"description", "design", "ranges", "metrics", "method", "calibration"}


def resolve_sensitivity(source: str | Path) -> Path:
    """The file `source` names: an existing path, or a shipped example's name."""
    return resolve_shipped(source, SHIPPED, "sensitivity", "examples")


def _table(path, config: dict, section: str) -> dict:
    value = config.get(section, {})
    if not isinstance(value, dict):
        raise _error(path, f"[{section}] must be a table (a [{section}] section)")
    return value


def _ranges(path, section: dict) -> dict[str, Any]:
    ranges: dict[str, Any] = {}
    for name, value in section.items():
        where = f"{path}: [ranges] {name}"
        if isinstance(value, dict):
            if set(value) != {"relative"}:
                raise rj.ParameterError(f"{where}: give [low, high] or {{ relative = r }}")
            ranges[name] = _number(f"{where}.relative", value["relative"])
        elif isinstance(value, list) and len(value) == 2:
            ranges[name] = tuple(_number(where, v) for v in value)
        else:
            raise rj.ParameterError(f"{where} = {value!r}: give [low, high] or {{ relative = r }}")
    return ranges


def _metrics(path, section: dict) -> tuple[list[str], rj.Objective | None]:
    check_keys(path, "metrics", section, ("names", "objective", "study"))
    names = section.get("names", [])
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise _error(path, f"[metrics] names = {names!r}: give a list of metric names")
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise _error(path, f"[metrics] names: {twice[0]} is given twice")
    for name in names:
        if name not in rj.METRICS:
            known = ", ".join(rj.METRICS)
            raise _error(path, f"[metrics] unknown metric {name!r}; known: {known} "
                         "(objective = {...} for a weighted sum)")  # fmt: skip
    if "objective" in section and "study" in section:
        raise _error(path, "[metrics] give objective or study, not both")
    objective = None
    if "study" in section:
        from .study_file import load_study

        study = section["study"]
        if not isinstance(study, str):
            raise _error(path, f"[metrics] study = {study!r}: give a study's name or file")
        try:
            problem = load_study(study).problem
        except rj.ParameterError as error:
            raise _error(path, f"[metrics] study: {error}") from None
        names = names + [m for m, _, _ in problem.metric_constraints if m not in names]
        objective = problem.objective
        if objective.scatter is not None:
            raise _error(path, f"[metrics] study {study}'s objective is a worst case over a "
                         "scatter, not a function of one design: range the scattered "
                         "parameters instead")  # fmt: skip
    elif "objective" in section:
        weights = section["objective"]
        if not isinstance(weights, dict) or not weights:
            raise _error(path, "[metrics] objective = { metric = weight, ... }")
        where = f"{path}: [metrics] objective"
        weights = {k: _number(f"{where}.{k}", v) for k, v in weights.items()}
        try:
            objective = rj.Objective(weights=weights)
        except rj.ParameterError as error:
            raise _error(where, str(error)) from None
    return names, objective


def _method(path, section: dict) -> rjx.SensitivityMethod:
    name = section.get("name")
    methods = rjx.SENSITIVITY_METHODS
    if not isinstance(name, str) or name not in methods:
        choices = ", ".join(f'"{n}"' for n in methods)
        raise _error(path, f"[method] name = {name!r}: give one of {choices}")
    cls = methods[name]
    keys = {f.name for f in dataclasses.fields(cls)}
    settings = {k: v for k, v in section.items() if k != "name"}
    unknown = set(settings) - keys
    if unknown:
        raise _error(path, f"[method] {sorted(unknown)[0]!r} is not a setting of "
                     f"{name}; its settings: {', '.join(sorted(keys))}")  # fmt: skip
    try:
        return cls(**settings)
    except rj.ParameterError as error:
        raise _error(path, f"[method] {error}") from None


def load_sensitivity(source) -> tuple[dict[str, Any], str]:
    """A sensitivity file (or a shipped example's name) as `rj.sensitivity`'s arguments
    (design, ranges, metrics, method, objective), checked, and its description."""
    path = resolve_sensitivity(source)
    config = read_toml(path, "sensitivity file")
    check_keys(path, "", config, _SECTIONS, kind="section")
    for section in ("metrics", "method"):
        if section not in config:
            raise _error(path, f"missing [{section}]")
    if "ranges" not in config and "calibration" not in config:
        raise _error(path, "missing [ranges] (or a [calibration] to take them from)")
    description = config.get("description", "")
    if not isinstance(description, str):
        raise _error(path, "description must be a string")
    design = {
        name: _number(f"{path}: [design] {name}", value)
        for name, value in _table(path, config, "design").items()
    }
    for name in design:
        if name not in rj.PARAMETERS and name != "t1":
            raise _error(path, f"[design] {rj.PARAMETERS.unknown(name, also=('t1',))}")
    ranges = _ranges(path, _table(path, config, "ranges"))
    if "calibration" in config:
        section = config["calibration"]
        taken = {name: "[design]" for name in design} | {name: "[ranges]" for name in ranges}
        fitted = read_calibration_section(path, section, ("from", "sigmas"), taken)
        sigmas = _number(f"{path}: [calibration] sigmas", section.get("sigmas", 2.0))
        try:
            box = fitted.box(sigmas)
        except rj.ParameterError as error:
            raise _error(path, f"[calibration] {error}") from None
        design = fitted.fitted_design | design
        ranges = box | ranges
    if not ranges:
        raise _error(path, "[ranges] is empty: range at least one parameter")
    names, objective = _metrics(path, _table(path, config, "metrics"))
    method = _method(path, _table(path, config, "method"))
    try:  # the ranges around the design, and the size of the sample, before anything runs
        rjx.sensitivity_box(design, ranges)
    except rj.ParameterError as error:
        raise _error(path, str(error)) from None
    arguments = {"design": design, "ranges": ranges, "metrics": names, "method": method,
                 "objective": objective}  # fmt: skip
    return arguments, description
