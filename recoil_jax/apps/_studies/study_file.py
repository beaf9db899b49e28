"""Optimisation studies: a TOML file → `optimise` → `result.json` and figures.

```toml
description = "what this study asks"
[design]                      # the base design (flat names); the rest: paper values
m = 1500
[tune]                        # tuned parameters and their bounds
gap = [0.0, 0.12]
[objective]                   # metric = weight (minimised)
peak_anchoring_force = 1.0
[objective.temperatures]      # optional: smooth max over time, temperature (metric unit)
peak_anchoring_force = 20.0
[objective.scatter]           # optional: worst case over relative offsets of a parameter
v0 = [-0.05, 0.0, 0.05]
[constraints]                 # name = {max = .., min = ..}: metrics or parameters
max_stroke = {max = 0.15}     #   (a metric's: at every condition)
[[condition]]                 # optional, repeatable: firing conditions (values of untuned
name = "70 deg"               #   parameters); the objective is the worst over them, each
elevation = 70.0              #   solved in one batched program; a condition's own limits:
constraints = {peak_displacement = {max = 0.8}}
[optimiser]                   # method = "search" (global + a local method): samples, starts,
starts = 8                    #   maxiter, seed, max_seconds, and local = "slsqp",
                              #   "epigraph_minimax", "trust_region_lp" or "optax_adam"
                              #   (or minimax = true / false to choose the default),
                              #   hops and hop_step (basin hopping after the starts);
                              #   "adam" (default; fronts,
                              #   scatter): starts, steps, learning_rate, seed, anneal,
                              #   patience

[[front]]                     # optional, repeatable: one optimisation per value (vmapped)
vary = "m"                    #   a parameter, or a constrained metric (ε-constraint)
values = [250, 500, 1000]
[calibration]                 # optional: design on a calibration's fitted hardware
from = "fit/result.json"      #   (recoil-jax calibrate): its values enter the design and
points = "sigma"              #   the objective and limits hold at its 2k + 1 sigma points
                              #   (worst case), or "sample" (samples = N, seed, and
                              #   quantile = q to hold them at that quantile, not the worst)
[check]                       # optional checks of the best design
grid = {gap = [0.0, 0.12, 241]}   # cartesian grid (lo, hi, count) around it
local = 0.02                  # 1-D scans ± this fraction of each bound's width
hard = true                   # the hard-switch model
nominal = true                # (scatter) the nominal optimum under the same scatter
```

`[design]` may also give `t1`, the end time of every solve (s; default 10 s after the
last round). A condition fires at the design's values of what it does not set; a
parameter that every condition sets need not be in `[design]`, one that only some set
must be.

A `[design]` that gives a tuned parameter is a start (`search` starts one local run
there); one that sets only fixed hardware is not. Tuned parameters it does not give take
the middle of their bounds (geometric for log coordinates), which only sets the design's
shape (e.g. the number of orifice knots).

A study is named by its path, or by the name of a study shipped in the repository's
`optimise/` folder (`resolve_study`), so that neither depends on the working directory.
Every metric of a study's result is solved with the problem's own smoothing and solver
options.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

import recoil_jax as rj
import recoil_jax.extend as rjx

from .._files.inputs import (
    check_keys,
    file_error as _error,
    file_integer,
    read_calibration_section,
    read_toml,
    resolve_shipped,
    values_taken,
)

__all__ = [
    "LOCAL_METHODS",
    "MAX_CONDITIONS",
    "MAX_GRID_CHECK",
    "SHIPPED",
    "Study",
    "load_study",
    "local_method",
    "optimise_kwargs",
    "resolve_study",
    "search_kwargs",
    "study_values",
]


_SECTIONS = {
    "calibration",
    "condition",
    "description",
    "design",
    "tune",
    "objective",
    "constraints",
    "optimiser",
    "front",
    "check",
}


_OPTIMISER_KEYS = {
    "method",
    "local",
    "hops",
    "hop_step",
    "samples",
    "maxiter",
    "max_seconds",
    "minimax",
    "starts",
    "steps",
    "learning_rate",
    "seed",
    "anneal",
    "patience",
    "update_every",
    "penalty",
}


_SEARCH_KEYS = {
    "method",
    "local",
    "samples",
    "starts",
    "maxiter",
    "seed",
    "max_seconds",
    "minimax",
    "hops",
    "hop_step",
}


#: The local methods of `method = "search"`, by the name a study gives in `local`.
LOCAL_METHODS = {
    "slsqp": rj.SLSQP,
    "epigraph_minimax": rj.EpigraphMinimax,
    "trust_region_lp": rj.TrustRegionLP,
    "optax_adam": rj.OptaxLocal,
}


_CHECK_KEYS = {"grid", "local", "hard", "nominal"}


#: The `[optimiser]` settings that are counts, with their least value (`adam` needs
#: `starts` >= 1, `optimise_kwargs`), and those that must be positive.
_INTEGER_KEYS = {
    "hops": 0,
    "samples": 0,
    "starts": 0,
    "steps": 1,
    "maxiter": 1,
    "seed": 0,
    "patience": 1,
    "update_every": 1,
}


_POSITIVE_KEYS = {"hop_step", "max_seconds", "learning_rate", "anneal", "penalty"}


#: Where the shipped studies live: `optimise/` beside the package, in a checkout or an
#: editable install.
SHIPPED = Path(__file__).resolve().parents[3] / "optimise"


@dataclass
class Study:
    """A parsed study file."""

    name: str
    description: str
    problem: rj.DesignProblem
    optimiser: dict = field(default_factory=dict)
    fronts: list[dict] = field(default_factory=list)
    check: dict = field(default_factory=dict)
    has_start: bool = True  # whether [design] gives a tuned parameter (a start)
    calibration: dict | None = None  # [calibration]: where from, which parameters, points


def study_values(problem: rj.DesignProblem) -> dict[str, np.ndarray]:
    """Every value each parameter takes in a study (`values_taken`): its design, its
    tuned bounds and its conditions' values, for `design_warnings`."""
    return values_taken(
        rj.params_to_values(problem.params),
        {name: problem.bounds[name] for name in problem.tune if name in problem.bounds},
        *(dict(condition.values) for condition in problem.conditions),
    )


def resolve_study(study: str | Path) -> Path:
    """The study file `study` names: an existing path, or the name of a shipped study
    (`tuned_absorber` or `tuned_absorber.toml`, found in `optimise/` whatever the working
    directory)."""
    return resolve_shipped(study, SHIPPED, "study", "studies")


def _front_values(path, front: dict, constrained: list[str]) -> list[float]:
    vary, values = front.get("vary"), front.get("values")
    if vary not in rj.PARAMETERS and vary not in constrained:
        raise _error(
            path,
            f"[[front]] vary = {vary!r}: give a parameter or a constrained "
            f"metric ({', '.join(constrained) or 'none'})",
        )
    if not isinstance(values, list) or not values:
        raise _error(path, f"[[front]] vary = {vary!r} needs values = [...]")
    if not all(isinstance(v, int | float) and not isinstance(v, bool) for v in values):
        raise _error(path, f"[[front]] vary = {vary!r}: values must be numbers, got {values!r}")
    values = [float(v) for v in values]
    if vary in rj.PARAMETERS:
        try:
            rj.params_from_values({str(vary): np.asarray(values)})
        except rj.ParameterError as error:
            raise _error(path, f"[[front]] {error}") from None
    elif not np.all(np.isfinite(values)):
        raise _error(path, f"[[front]] vary = {vary!r}: values must be finite")
    return values


def load_study(path) -> Study:
    """Parse and validate a study file or shipped study name, section by section (errors
    name the file and the key); the optimiser's parts are built here too, so that a bad
    setting is refused before anything runs."""
    path = resolve_study(path)
    config = _read_config(path)
    tune, bounds = _parse_tune(path, config["tune"])
    objective = _parse_objective(path, config["objective"])
    constraints = _parse_constraints(path, config.get("constraints", {}))
    conditions, condition_limits = _parse_conditions(path, config.get("condition", []), tune)
    constraints = constraints + condition_limits
    design = dict(config.get("design", {}))
    t1 = _parse_t1(path, design)
    for name in dict.fromkeys(n for c in conditions for n in c.names):
        # A condition that does not set a parameter fires at the design's value of it.
        unset = [c.name for c in conditions if name not in c.names]
        if name not in design and unset:
            raise _error(
                path, f"[[condition]] {unset[0]!r} does not set {name}, which another condition "
                f"sets: give {name} in [design] (its value there) or at every condition",
            )  # fmt: skip
        design.setdefault(name, dict(next(c for c in conditions if name in c.names).values)[name])
    calibration = None
    if "calibration" in config:
        design, objective = _parse_calibration(path, config["calibration"], design, tune, objective)
        names, offsets = objective.scatter_points
        calibration = {
            "from": str(config["calibration"]["from"]),
            "parameters": list(names),
            "points": len(offsets),
            "solves_per_evaluation": len(offsets),
            "held_at": "worst case"
            if objective.quantile is None
            else f"quantile {objective.quantile:g}",
        }
    params, has_start = _parse_design(path, design, tune, bounds)
    options = rj.GRADIENT_OPTIONS if t1 is None else dataclasses.replace(rj.GRADIENT_OPTIONS, t1=t1)
    try:
        problem = rj.DesignProblem(
            params=params, objective=objective, tune=tuple(tune), bounds=bounds,
            constraints=constraints, conditions=conditions, options=options,
        )  # fmt: skip
    except rj.ParameterError as error:
        raise _error(path, str(error)) from None
    optimiser = _parse_optimiser(path, dict(config.get("optimiser", {})))
    fronts = _parse_fronts(path, config.get("front", []), problem)
    for front in fronts:
        if any(front["vary"] in c.names for c in conditions):
            raise _error(path, f"[[front]] vary = {front['vary']!r} is set by the conditions")
    if optimiser["method"] == "search" and (fronts or objective.scatter is not None):
        raise _error(
            path, 'method = "search" takes neither [[front]] nor a scatter; use "adam" for those'
        )
    study = Study(
        name=path.stem,
        description=config.get("description", ""),
        problem=problem,
        optimiser=optimiser,
        fronts=fronts,
        check=_parse_check(path, dict(config.get("check", {}))),
        has_start=has_start,
        calibration=calibration,
    )
    try:
        (search_kwargs if optimiser["method"] == "search" else optimise_kwargs)(study, False)
    except rj.ParameterError as error:
        raise _error(path, f"[optimiser] {error}") from None
    return study


def _read_config(path: Path) -> dict:
    """The study file's TOML, its sections checked (known, and the required ones there)."""
    config = read_toml(path, "study file")
    check_keys(path, "", config, _SECTIONS, kind="section")
    for section in ("tune", "objective"):
        if section not in config:
            raise _error(path, f"missing [{section}]")
    return config


def _is_number(value) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _parse_tune(path, section: dict) -> tuple[list[str], dict[str, tuple[float, float]]]:
    """`[tune]`: the tuned parameters, in order, and their bounds."""
    tune, bounds = [], {}
    for name, bound in section.items():
        if name not in rj.PARAMETERS:
            raise _error(path, f"[tune] unknown parameter {name!r}")
        if not (isinstance(bound, list) and len(bound) == 2 and all(map(_is_number, bound))):
            raise _error(path, f"[tune] {name} = [lo, hi] (numbers) expected, got {bound!r}")
        if not bound[0] < bound[1]:
            raise _error(path, f"[tune] {name} = {bound!r}: need lo < hi")
        tune.append(name)
        bounds[name] = (float(bound[0]), float(bound[1]))
    return tune, bounds


_CALIBRATION_KEYS = {"from", "points", "samples", "seed", "quantile"}


def _parse_calibration(path, section, design: dict, tune, objective: rj.Objective):
    """`[calibration]`: the fitted hardware of a calibration's `result.json` (`from`,
    relative to the study) enters the design at its fitted values, and the objective and
    limits hold over its uncertainty: the worst case over a fixed set of points drawn
    from the fit, `points = "sigma"` (2k + 1 sigma points, default) or `"sample"`
    (`samples`, `seed`), or with `quantile = q` (sampled points only) the q-quantile
    towards the worst."""
    if objective.scatter is not None:
        raise _error(path, "[calibration] and [objective.scatter] cannot both scatter the design")
    taken = {name: "[design]" for name in design} | {name: "[tune]" for name in tune}
    fitted = read_calibration_section(path, section, _CALIBRATION_KEYS, taken)
    kind = section.get("points", "sigma")
    if kind == "sigma":
        points = fitted.sigma_points()
    elif kind == "sample":
        samples, seed = section.get("samples", 16), section.get("seed", 0)
        for key, value, least in (("samples", samples, 2), ("seed", seed, 0)):
            file_integer(path, f"[calibration] {key}", value, least)
        draws, _ = fitted.sample(samples - 1, seed)
        points = np.concatenate([fitted.values[None], draws])
    else:
        raise _error(path, f'[calibration] points = {kind!r}: "sigma" or "sample"')
    quantile = section.get("quantile")
    if quantile is not None:
        if kind != "sample":
            raise _error(path, '[calibration] quantile needs points = "sample": a quantile of '
                         "the 2k + 1 sigma points does not estimate one of the fit")  # fmt: skip
        if isinstance(quantile, bool) or not _is_number(quantile) or not 0 < quantile <= 1:
            raise _error(path, f"[calibration] quantile = {quantile!r}: a number in (0, 1] "
                         "(1: the worst case)")  # fmt: skip
        quantile = float(quantile)
    zero = [n for n, v in zip(fitted.names, fitted.values, strict=True) if v == 0.0]
    if zero:
        raise _error(path, f"[calibration] {zero[0]} was fitted as 0: the scatter is relative "
                     "to the fitted values; fix it as a known value instead")  # fmt: skip
    # A point clipped to a lower bound of 0 sits just above it (offsets must be > -1).
    offsets = np.maximum(points / fitted.values - 1.0, -1.0 + 1e-9)
    known = fitted.fitted_design
    scatter = (fitted.names, tuple(tuple(float(o) for o in row) for row in offsets))
    return known | design, dataclasses.replace(objective, scatter=scatter, quantile=quantile)


def _parse_objective(path, section: dict) -> rj.Objective:
    """`[objective]` with its optional `temperatures` and `scatter` tables."""
    weights = dict(section)
    temperatures = weights.pop("temperatures", {})
    scatter = weights.pop("scatter", None)
    if not isinstance(temperatures, dict):
        raise _error(path, f"[objective.temperatures] = {temperatures!r}: give metric = number")
    if scatter is not None:
        shape = "[objective.scatter] takes one parameter = [offsets], e.g. v0 = [-0.05, 0.05]"
        if not isinstance(scatter, dict) or len(scatter) != 1:
            raise _error(path, shape)
        ((scatter_name, offsets),) = scatter.items()
        if not isinstance(offsets, list) or not offsets or not all(map(_is_number, offsets)):
            raise _error(path, f"{shape}; got {scatter_name} = {offsets!r}")
        scatter = (scatter_name, tuple(float(o) for o in offsets))
    for table, values in (("objective", weights), ("objective.temperatures", temperatures)):
        for name, value in values.items():
            if not _is_number(value):
                raise _error(path, f"[{table}] {name} = {value!r}: valid a number")
    try:
        return rj.Objective(
            weights={k: float(v) for k, v in weights.items()},
            temperatures={k: float(v) for k, v in temperatures.items()},
            scatter=scatter,
        )
    except rj.ParameterError as error:
        raise _error(path, f"[objective] {error}") from None


def _parse_constraints(path, section: dict, where="[constraints]") -> tuple[rj.Constraint, ...]:
    """`[constraints]`: `name = {max = .., min = ..}` for metrics and parameters."""
    constraints = []
    for name, limits in section.items():
        if not isinstance(limits, dict) or set(limits) - {"max", "min"}:
            raise _error(path, f"{where} {name} = {{max = .., min = ..}} expected")
        if not all(_is_number(v) for v in limits.values()):
            raise _error(path, f"{where} {name} = {limits!r}: limits must be numbers")
        try:
            constraints.append(
                rj.Constraint(name, upper=limits.get("max"), lower=limits.get("min"))
            )
        except rj.ParameterError as error:
            raise _error(path, f"{where} {error}") from None
    return tuple(constraints)


_CONDITION_KEYS = {"name", "constraints"}
#: The most `[[condition]]`s a study takes.
MAX_CONDITIONS = 100


def _parse_conditions(
    path, tables, tune: list[str]
) -> tuple[tuple[rj.Condition, ...], tuple[rj.Constraint, ...]]:
    """`[[condition]]`: each a `name` (default its values, `"elevation=70"`), values of
    untuned parameters, and its own limits (`constraints = {metric = {max = ..}}`)."""
    tables = [tables] if isinstance(tables, dict) else list(tables)
    if len(tables) > MAX_CONDITIONS:
        raise _error(path, f"{len(tables):,} [[condition]]s: valid at most {MAX_CONDITIONS} (each "
                     "is a lane of every solve and a piece of the worst case): split the "
                     "study, or sweep the design over the conditions")  # fmt: skip
    conditions, limits = [], []
    for i, table in enumerate(tables):
        if not isinstance(table, dict):
            raise _error(path, "[[condition]] must be tables: name = .., parameter = value")
        values = {k: v for k, v in table.items() if k not in _CONDITION_KEYS}
        where = f"[[condition]] {i + 1}"
        for name, value in values.items():
            if name not in rj.PARAMETERS:
                raise _error(path, f"{where}: {rj.PARAMETERS.unknown(name)}")
            if not _is_number(value):
                raise _error(path, f"{where}: {name} = {value!r}: valid a number")
            if name in tune:
                raise _error(path, f"{where} sets {name}, which is tuned: a condition sets "
                             "untuned parameters only")  # fmt: skip
        default = ", ".join(f"{k}={v:g}" for k, v in values.items())
        name = table.get("name", default)
        if not isinstance(name, str) or not name.strip():
            raise _error(path, f"{where}: name = {name!r}: valid a non-empty string")
        try:
            conditions.append(rj.Condition(name, values))
        except rj.ParameterError as error:
            raise _error(path, f"{where}: {error}") from None
        own = table.get("constraints", {})
        if not isinstance(own, dict):
            raise _error(path, f"{where}: constraints = {{metric = {{max = .., min = ..}}}}")
        for constraint in _parse_constraints(path, own, f"[[condition]] {name!r} constraints"):
            if not constraint.is_metric:
                raise _error(path, f"{where}: constraints may limit metrics only, not the "
                             f"parameter {constraint.name}")  # fmt: skip
            limits.append(dataclasses.replace(constraint, conditions=(name,)))
    return tuple(conditions), tuple(limits)


def _parse_t1(path, design: dict) -> float | None:
    """`[design] t1` (removed from `design`): the solves' end time, s."""
    if "t1" not in design:
        return None
    t1 = design.pop("t1")
    limits = rjx.T1_LIMITS
    if not _is_number(t1) or not limits.lower < t1 <= limits.ceiling:
        raise _error(path, f"[design] t1 = {t1!r}: valid {limits.describe()}")
    return float(t1)


def _parse_design(path, design: dict, tune: list[str], bounds: dict) -> tuple[Any, bool]:
    """`[design]` as the base design, and whether it is a start (it gives a tuned
    parameter). A tuned parameter it does not give takes the middle of its bounds
    (geometric in log coordinates); the box's corners must be designs too."""
    for name in design:
        if name not in rj.PARAMETERS:
            raise _error(
                path, f"[design] unknown parameter {name!r}; known: {', '.join(rj.PARAMETERS)}"
            )
    for name, value in design.items():
        # each given value by itself first: a bad one is [design]'s, whatever the bounds
        if not _is_number(value):
            raise _error(path, f"[design] {name} = {value!r}: valid a number")
        if name not in tune:
            try:
                rj.PARAMETERS[name].check(value)
            except rj.ParameterError as error:
                raise _error(path, f"[design] {error}") from None
    has_start = any(name in design for name in tune)
    for name in tune:
        if name not in design:
            lo, hi = bounds[name]
            log = bool(rjx.log_coordinates(np.asarray([lo]), np.asarray([hi]))[0])
            design[name] = float(np.sqrt(lo * hi)) if log else 0.5 * (lo + hi)
    for side, end in (("lower", 0), ("upper", 1)):
        try:
            rj.params_from_values(design | {name: bounds[name][end] for name in tune})
        except rj.ParameterError as error:
            raise _error(path, f"[tune] at the {side} bounds: {error}") from None
    try:
        return rj.params_from_values(design), has_start
    except rj.ParameterError as error:
        raise _error(path, f"[design] {error}") from None


def _parse_optimiser(path, optimiser: dict) -> dict:
    """`[optimiser]`: its method (default `"adam"`) and the settings that apply to it,
    each a value of the right kind."""
    check_keys(path, "optimiser", optimiser, _OPTIMISER_KEYS)
    method = optimiser.setdefault("method", "adam")
    if method not in ("adam", "search"):
        raise _error(path, f'[optimiser] method = {method!r}: valid "adam" or "search"')
    search_only = {"local", "samples", "maxiter", "max_seconds", "minimax", "hops", "hop_step"}
    allowed = _SEARCH_KEYS if method == "search" else _OPTIMISER_KEYS - search_only
    if set(optimiser) - allowed:
        raise _error(
            path,
            f"[optimiser] key(s) {', '.join(sorted(set(optimiser) - allowed))} do not apply "
            f"to method = {method!r}; it takes {', '.join(sorted(allowed))}",
        )
    for key, value in optimiser.items():
        if key not in ("method", "local", "minimax"):
            _check_setting(path, key, value)
    if not isinstance(optimiser.get("minimax", False), bool):
        raise _error(path, f"[optimiser] minimax = {optimiser['minimax']!r}: valid true or false")
    if "local" in optimiser:
        if optimiser["local"] not in LOCAL_METHODS:
            raise _error(
                path,
                f"[optimiser] local = {optimiser['local']!r}: valid "
                + ", ".join(f'"{name}"' for name in LOCAL_METHODS),
            )
        if "minimax" in optimiser:
            raise _error(path, "[optimiser] give local or minimax, not both")
    if method == "search":  # its counts against the free memory, now
        try:
            _part(rj.SobolStarts, optimiser, samples="samples", starts="starts")
        except rj.ParameterError as error:
            raise _error(path, f"[optimiser] {error}") from None
    return optimiser


def _check_setting(path, key: str, value) -> None:
    """A numeric `[optimiser]` setting: finite; a count an integer at least its least
    value; a positive setting positive."""
    if not _is_number(value) or not np.isfinite(value):
        raise _error(path, f"[optimiser] {key} = {value!r}: valid a finite number")
    if key in _INTEGER_KEYS:
        file_integer(path, f"[optimiser] {key}", value, _INTEGER_KEYS[key])
    if key in _POSITIVE_KEYS and not value > 0:
        raise _error(path, f"[optimiser] {key} = {value!r}: valid a number > 0")


def _parse_fronts(path, fronts, problem: rj.DesignProblem) -> list[dict]:
    """`[[front]]`: each a parameter or a constrained metric to vary, and its values."""
    fronts = [fronts] if isinstance(fronts, dict) else list(fronts)
    constrained = [name for name, _, _ in problem.metric_constraints]
    for front in fronts:
        front["values"] = _front_values(path, front, constrained)
        if front["vary"] in problem.tune:
            raise _error(path, f"[[front]] vary = {front['vary']!r} is tuned; fix it to vary it")
        if constrained.count(front["vary"]) > 1:
            raise _error(
                path,
                f"[[front]] vary = {front['vary']!r} has several limits (at different "
                "conditions, or a max and a min): a front varies one",
            )
    return fronts


#: The most points a study's `[check] grid` may have (about 10 s of solves).
MAX_GRID_CHECK = 100_000


def _parse_check(path, check: dict) -> dict:
    """`[check]`: which checks of the best design to run, each setting checked here (a
    check runs after the optimiser: a bad one would lose the run)."""
    check_keys(path, "check", check, _CHECK_KEYS)
    for key in ("hard", "nominal"):
        if key in check and not isinstance(check[key], bool):
            raise _error(path, f"[check] {key} = {check[key]!r}: give true or false")
    if "local" in check:
        fraction = check["local"]
        if not _is_number(fraction) or not 0.0 < fraction <= 1.0:
            raise _error(path, f"[check] local = {fraction!r}: a fraction of each bound's "
                         "width, in (0, 1]")  # fmt: skip
    if "grid" in check:
        grid = check["grid"]
        if not isinstance(grid, dict) or not grid:
            raise _error(path, "[check] grid = { name = [lo, hi, count], ... }")
        points = 1
        for name, spec in grid.items():
            where = f"[check] grid.{name}"
            if name not in rj.PARAMETERS:
                raise _error(path, f"{where}: {rj.PARAMETERS.unknown(name)}")
            if not (isinstance(spec, list) and len(spec) == 3 and all(map(_is_number, spec))):
                raise _error(path, f"{where} = {spec!r}: give [lo, hi, count]")
            lo, hi, count = spec
            if not (isinstance(count, int) and count >= 1) or not lo <= hi:
                raise _error(path, f"{where} = {spec!r}: need lo <= hi and an integer count "
                             ">= 1")  # fmt: skip
            points *= count
        if points > MAX_GRID_CHECK:
            raise _error(path, f"[check] grid has {points:,} points, more than "
                         f"{MAX_GRID_CHECK:,}: give fewer")  # fmt: skip
    return check


def local_method(study: Study) -> rjx.LocalMethod:
    """The local method of a `search` study: `local` by name (`LOCAL_METHODS`), else
    `rjx.default_local` (which `minimax` chooses), with the study's `maxiter`."""
    o = study.optimiser
    if "local" in o:
        method = LOCAL_METHODS[o["local"]]()
    else:
        method = rjx.default_local(study.problem, o.get("minimax"))
    if "maxiter" in o:
        method = dataclasses.replace(method, maxiter=int(o["maxiter"]))
    return method


def search_kwargs(study: Study, progress: bool | None) -> dict:
    """The keyword arguments of `rj.search` that the study's `[optimiser]` sets."""
    o = study.optimiser
    kwargs: dict[str, Any] = dict(
        use_design=study.has_start, progress=progress, local=local_method(study)
    )
    if "seed" in o:
        kwargs["seed"] = int(o["seed"])
    if (global_phase := _part(rj.SobolStarts, o, samples="samples", starts="starts")) is not None:
        kwargs["global_phase"] = global_phase
    if "max_seconds" in o:
        kwargs["max_seconds"] = float(o["max_seconds"])
    if (hopping := _part(rj.BasinHopping, o, hops="hops", step="hop_step")) is not None:
        kwargs["hopping"] = hopping
    return kwargs


def _part(cls, o: dict, **keys: str):
    """`cls()` with the `[optimiser]` settings `keys` (field = key) the study gives, each
    of its default's type; None when it gives none of them."""
    given = {field: o[key] for field, key in keys.items() if key in o}
    defaults = cls()
    kinds = {field: type(getattr(defaults, field)) for field in given}
    return cls(**{f: kinds[f](value) for f, value in given.items()}) if given else None


def optimise_kwargs(study: Study, progress: bool | None) -> dict:
    """The keyword arguments of `rj.optimise` that the study's `[optimiser]` sets."""
    o = study.optimiser
    file_integer(None, "starts", o.get("starts", 8), 1)  # adam needs one start
    steps = int(o.get("steps", 200))
    kwargs: dict[str, Any] = dict(
        starts=int(o.get("starts", 8)),
        steps=steps,
        seed=int(o.get("seed", 0)),
        optimiser=rj.default_optimiser(float(o.get("learning_rate", 0.1)), steps),
        progress=progress,
    )
    if "anneal" in o:
        kwargs["anneal"] = float(o["anneal"])
    lagrangian = _part(rj.AugmentedLagrangian, o, penalty="penalty", update_every="update_every")
    if lagrangian is not None:
        kwargs["lagrangian"] = lagrangian
    if (stopping := _part(rj.Stopping, o, patience="patience")) is not None:
        kwargs["stopping"] = stopping
    return kwargs
