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
max_stroke = {max = 0.15}
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

import contextlib
import dataclasses
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import jax
import numpy as np

import recoil_jax as rj
import recoil_jax.extend as rjx

from .._files.cluster import check_cluster, dask_client
from .._files.inputs import (
    check_keys,
    file_error as _error,
    file_integer,
    output_folder,
    read_calibration_section,
    read_toml,
    resolve_shipped,
)
from .._files.json_writer import write as write_json

__all__ = [
    "LOCAL_METHODS",
    "SHIPPED",
    "Study",
    "agreement_line",
    "load_study",
    "local_method",
    "optimise_kwargs",
    "resolve_study",
    "run_study",
    "search_kwargs",
    "study_summary",
]


_SECTIONS = {
    "calibration",
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
    design = dict(config.get("design", {}))
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
    problem = rj.DesignProblem(
        params=params, objective=objective, tune=tuple(tune), bounds=bounds,
        constraints=constraints,
    )  # fmt: skip
    optimiser = _parse_optimiser(path, dict(config.get("optimiser", {})))
    fronts = _parse_fronts(path, config.get("front", []), problem)
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
    if scatter is not None:
        if len(scatter) != 1:
            raise _error(path, "[objective.scatter] takes one parameter = [offsets]")
        ((scatter_name, offsets),) = scatter.items()
        scatter = (scatter_name, tuple(float(o) for o in offsets))
    for table, values in (("objective", weights), ("objective.temperatures", temperatures)):
        for name, value in values.items():
            if not _is_number(value):
                raise _error(path, f"[{table}] {name} = {value!r}: valid a number")
    return rj.Objective(
        weights={k: float(v) for k, v in weights.items()},
        temperatures={k: float(v) for k, v in temperatures.items()},
        scatter=scatter,
    )


def _parse_constraints(path, section: dict) -> tuple[rj.Constraint, ...]:
    """`[constraints]`: `name = {max = .., min = ..}` for metrics and parameters."""
    constraints = []
    for name, limits in section.items():
        if not isinstance(limits, dict) or set(limits) - {"max", "min"}:
            raise _error(path, f"[constraints] {name} = {{max = .., min = ..}} expected")
        constraints.append(rj.Constraint(name, upper=limits.get("max"), lower=limits.get("min")))
    return tuple(constraints)


def _parse_design(path, design: dict, tune: list[str], bounds: dict) -> tuple[Any, bool]:
    """`[design]` as the base design, and whether it is a start (it gives a tuned
    parameter). A tuned parameter it does not give takes the middle of its bounds
    (geometric in log coordinates); the box's corners must be designs too."""
    for name in design:
        if name not in rj.PARAMETERS:
            raise _error(
                path, f"[design] unknown parameter {name!r}; known: {', '.join(rj.PARAMETERS)}"
            )
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
    return rj.params_from_values(design), has_start


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


def agreement_line(report: dict) -> str | None:
    """The summary's line on how firmly a feasible study found its best design
    (`rj.Agreement.line`, from result.json's `optimiser.agreement`); None for an
    infeasible study."""
    agreement = report.get("optimiser", {}).get("agreement")
    if not report.get("feasible") or agreement is None:
        return None
    return rj.Agreement(**agreement).line()


def study_summary(report: dict) -> str:
    """The command's summary of a feasible study's `result.json`: the objective and every
    limit with their units, the best values, and how firmly it was found."""
    lines = [
        f"study {report['study']}: objective {report['objective']:.6g} "
        f"{report['objective_unit']}, {report['simulations']} simulations, "
        f"{report['seconds']:.1f} s",
        "  best: " + ", ".join(f"{k}={report['best'][k]:.6g}" for k in report["tuned"]),
    ]
    for name, c in report["constraints"].items():
        unit = _unit(name.rsplit(" (", 1)[0])
        state = "ok" if c["satisfied"] else "VIOLATED"
        lines.append(f"  {name}: {c['value']:.6g} {unit} (limit {c['limit']:g} {unit}) {state}")
    if line := agreement_line(report):
        lines.append(f"  {line}")
    return "\n".join(lines)


def _search_summary(result: rj.OptimiseResult, local: rjx.LocalMethod) -> dict:
    """What `result.json` says of a `search` run."""
    samples = result.samples
    assert samples is not None  # search's global phase
    feasible = rj.feasible(samples["ok"], samples["objective"], samples["violation"][:, None])
    return {
        "method": "search",
        "local": type(local).__name__,
        "samples": len(samples["z"]),
        "feasible_samples": int(feasible.sum()),
        "local_runs": [
            {
                "phase": run.phase,
                # None: a run the time budget stopped before its first evaluation.
                "objective_at_end": (float(run.objective) if np.isfinite(run.objective) else None),
                "iterations": run.iterations,
                "message": run.message,
            }
            for run in result.runs
        ],
        "agreement": result.agreement()._asdict(),
        "where_starts_ended": result.clusters(),
        "solves": result.solves,
        "gradient_solves": result.gradient_solves,
        "compilations": result.compilations,
        "replayed": result.replayed,
        "seconds": round(result.seconds, 2),
    }


def _peaks(problem: rj.DesignProblem, params, smoothing=None) -> rj.Peaks:
    """The peaks of `params` with the problem's solver options (and smoothing)."""
    return rj.peaks(params, problem.smoothing if smoothing is None else smoothing, problem.options)


def _history(problem: rj.DesignProblem, params, time: float) -> rj.History:
    """The history of `params` with the problem's smoothing and solver options, on 3001
    points over `[0, time]` (s): one grid size, so that the histories of a structure
    are one compiled program. Its `peaks` are over the whole solve."""
    return rj.simulate(params, problem.smoothing, problem.options, ts=np.linspace(0.0, time, 3001))


def _scattered(problem: rj.DesignProblem, params, offsets) -> list[rj.Peaks]:
    """The peaks at each scatter point, `offsets (S, k)` relative to `params`."""
    names, _ = problem.objective.scatter_points
    nominal = np.asarray(rj.values_of(params, names))
    return [_peaks(problem, rj.with_values(params, names, nominal * (1 + o))) for o in offsets]


def _worst_case(problem: rj.DesignProblem, runs: list[rj.Peaks]) -> tuple[dict, float]:
    """Worst-case metrics (each metric's own extreme, or the objective's quantile
    towards it) by JSON key, and the objective the same way, over the scattered solves
    `runs`: what the optimiser held."""
    objective = problem.objective
    values = {name: [float(getattr(r, name)) for r in runs] for name in rj.METRICS}
    worst = rjx.worst_case(values, quantile=objective.quantile)
    objectives = np.array([float(objective(r.metrics())) for r in runs])
    return (
        {rj.METRICS[name].key: float(v) for name, v in worst.items()},
        float(objective.over_scatter(objectives)),
    )


def _best_summary(study: Study, result: rj.OptimiseResult, scenario: int) -> dict:
    problem = study.problem
    params = result.best_params(scenario)
    design = result.best_design(scenario)
    best = _peaks(problem, params)
    summary = {
        "best": design,
        "metrics": best.to_dict(),
        "objective": float(problem.objective(best.metrics())),
    }
    limits = result.scenario_limits[scenario]
    if problem.objective.scatter is not None:
        worst, worst_objective = _worst_case(
            problem, _scattered(problem, params, problem.objective.scatter_points[1])
        )
        summary["objective"] = worst_objective
        summary["worst_case_metrics"] = worst
        by_name = {name: worst[m.key] for name, m in rj.METRICS.items()}
        summary["constraints"] = rj.constraint_report(problem, design, by_name, limits)
    else:
        summary["constraints"] = rj.constraint_report(problem, design, best.metrics(), limits)
    return summary


def _feasible_objective(problem, designs: dict, progress) -> tuple[np.ndarray, np.ndarray]:
    """The objective (with peaks) of each design (flat name → `(n,)`), inf where it is
    not feasible (`rj.feasible`); and the feasibility mask. Chunks of 1024, the size
    `rj.sweep` gives up to 1024 designs (the search's samples): every check runs the
    program the search compiled."""
    evaluator = rjx.BatchEvaluator(problem, chunk_size=1024, progress=progress)
    evaluation = evaluator.evaluate(designs)
    feasible = rj.feasible(evaluation.ok, evaluation.objective, evaluation.violations)
    return np.where(feasible, evaluation.objective, np.inf), feasible


def _grid_check(study: Study, result, axes: dict, progress: bool) -> tuple[dict, int]:
    """The best feasible point of a cartesian grid around the best design (others fixed
    at it), for the objective with peaks."""
    problem = study.problem
    design = result.best_design(0)
    grid_axes = {}
    for name, spec in axes.items():
        lo, hi, count = spec
        grid_axes[name] = np.linspace(float(lo), float(hi), int(count))
    fixed = {k: v for k, v in design.items() if k not in grid_axes}
    columns, _ = rj.grid(grid_axes, fixed)
    objective, feasible = _feasible_objective(problem, columns, progress)
    i = int(np.argmin(objective))
    spacing = {n: float(a[1] - a[0]) if len(a) > 1 else 0.0 for n, a in grid_axes.items()}
    return {
        "axes": {n: [float(a[0]), float(a[-1]), len(a)] for n, a in grid_axes.items()},
        "points": int(objective.size),
        "feasible_points": int(feasible.sum()),
        "grid_best_objective": float(objective[i]),
        "grid_best_design": {n: float(columns[n][i]) for n in grid_axes},
        "grid_spacing": spacing,
    }, int(objective.size)


def _local_check(study: Study, result, fraction: float, progress: bool) -> tuple[dict, int]:
    """1-D scans of ± `fraction` of each bound's width through the best design."""
    problem = study.problem
    design = result.best_design(0)
    lower, upper = problem.box()
    points, labels = [], []
    for j, name in enumerate(problem.tune):
        width = fraction * (upper[j] - lower[j])
        for x in np.linspace(-width, width, 11):
            value = float(np.clip(design[name] + x, lower[j], upper[j]))
            points.append({**design, name: value})
            labels.append(name)
    columns = {name: np.asarray([p[name] for p in points]) for name in points[0]}
    objective, _ = _feasible_objective(problem, columns, progress)
    return {
        "fraction_of_bounds": fraction,
        "points": len(points),
        "best_scan_objective": float(np.min(objective)),
        "per_parameter": {
            n: float(np.min(objective[np.asarray(labels) == n])) for n in problem.tune
        },
    }, len(points)


class _Phases:
    """Says on stderr what a study is doing, phase by phase, and times each phase (for
    `result.json`'s `seconds_by_part`): a first run's seconds are mostly compilation."""

    def __init__(self, name: str, enabled: bool | None):
        self.name, self.enabled = name, enabled is not False
        self.seconds: dict[str, float] = {}

    @contextlib.contextmanager
    def __call__(self, part: str, what: str):
        if self.enabled:
            print(f"study {self.name}: {what} ...", file=sys.stderr, flush=True)
        began = time.perf_counter()
        yield
        self.seconds[part] = round(self.seconds.get(part, 0.0) + time.perf_counter() - began, 2)
        if self.enabled:
            print(
                f"study {self.name}: {what}: done in {self.seconds[part]:.1f} s",
                file=sys.stderr,
                flush=True,
            )


def run_study(
    path,
    out: str | Path | None = None,
    progress: bool | None = None,
    seed: int | None = None,
    store: str | Path | None = None,
    workers: int | None = None,
    scheduler: str | None = None,
) -> dict:
    """Run a study: optimise, check, write `result.json` and figures.

    **Arguments:**

    - `path`: a study file, or the name of a shipped study (`resolve_study`).
    - `out`: the output folder (default `results/<study name>`).
    - `progress`: progress lines on stderr, for every phase (default: on a terminal).
    - `seed`: replaces the study's `[optimiser] seed`.
    - `store`: an SQLite file that keeps every evaluation of the optimiser (`rj.search`'s
      or `rj.optimise`'s `store`): the same study with the same store resumes where it
      stopped and ends at the same best design. The checks and fronts run again.
    - `workers`, `scheduler`: the global phase of `method = "search"` on a local Dask
      cluster of `workers` processes, or on the running one at `scheduler`.

    **Returns:** the dict written to `result.json`. Its `feasible` says whether a design
    met every limit. When none did, `best` and `objective` are None and `closest` gives
    the least violating design found, with each limit it misses and by how much
    (`message` says it in one line); the checks are skipped.
    """
    study = _prepared(path, seed, workers, scheduler)
    out = output_folder(out if out is not None else Path("results") / study.name)
    kwargs = optimise_kwargs(study, progress)
    started = time.perf_counter()
    phase = _Phases(study.name, progress)
    if progress is not False:
        print(f"study {study.name}: {study.description}", file=sys.stderr)
    report: dict[str, Any] = {
        "study": study.name,
        "description": study.description,
        "objective_unit": study.problem.objective.unit,
    }
    if study.optimiser["method"] == "search":
        result, simulations, report["optimiser"] = _run_search(
            study, out, phase, progress, store, workers, scheduler
        )
    else:
        result, simulations, report["optimiser"] = _run_adam(study, out, phase, kwargs, store)
    report |= _outcome(study, result, phase)
    if report["feasible"]:
        _checks(study, result, report, simulations, kwargs, out, phase)
    fronts = []
    for front in study.fronts:
        with phase(f"front_{front['vary']}", f"front over {front['vary']}"):
            table, n = _run_front(study, front, kwargs)
        fronts.append(table)
        simulations[f"front_{front['vary']}"] = n
        _write_front(table, out)
    if fronts:
        report["fronts"] = fronts
    report["simulations"] = int(sum(simulations.values()))
    report["simulations_by_part"] = simulations
    report["seconds"] = round(time.perf_counter() - started, 2)
    report["seconds_by_part"] = phase.seconds
    write_json(out / "result.json", report)
    return report


def _prepared(path, seed: int | None, workers, scheduler) -> Study:
    """The study to run: loaded, its seed replaced by `seed`, the cluster options
    checked against its method."""
    study = load_study(path)
    check_cluster(workers, scheduler)  # before the study's first line is printed
    if (workers is not None or scheduler is not None) and study.optimiser["method"] != "search":
        raise rj.ParameterError(
            f"{study.name}: --workers and --scheduler spread the global phase of "
            'method = "search"; this study uses method = "adam", which has none'
        )
    if seed is not None:
        study.optimiser["seed"] = file_integer(None, "seed", seed, 0)
    return study


def _run_search(study: Study, out: Path, phase, progress, store, workers, scheduler):
    """The `search` of a study: its result, simulations and `result.json`'s summary;
    the convergence figure."""
    from .._figures.designs import plot_search_convergence

    search = search_kwargs(study, progress)
    with (
        phase("optimiser", f"global search, then {type(search['local']).__name__}"),
        dask_client(workers, scheduler) as client,
    ):
        result = rj.search(study.problem, store=store, client=client, **search)
    simulations = {"optimiser": result.solves, "optimiser_gradients": result.gradient_solves}
    summary = _search_summary(result, search["local"])
    summary["seed"] = int(study.optimiser.get("seed", 0))
    plot_search_convergence(result, out / "convergence.png", title=study.name)
    return result, simulations, summary


def _run_adam(study: Study, out: Path, phase, kwargs: dict, store):
    """The `optimise` of a study: its result, simulations and `result.json`'s summary;
    the convergence figure."""
    from .._figures.designs import plot_convergence

    with phase("optimiser", f"optax from {kwargs['starts']} starts"):
        result = rj.optimise(study.problem, store=store, **kwargs)
    summary = {
        "method": "adam",
        "seed": kwargs["seed"],
        "starts": kwargs["starts"],
        "steps": len(result.history["objective"]) if result.history else 0,
        "compilations": result.compilations,
        "seconds": round(result.seconds, 2),
        "converged_runs": sum(run.converged for run in result.runs),
        "agreement": result.agreement()._asdict(),
        "where_starts_ended": result.clusters(),
    }
    plot_convergence(result, out / "convergence.png", title=study.name)
    return result, {"optimiser": int(result.simulations)}, summary


def _outcome(study: Study, result: rj.OptimiseResult, phase) -> dict:
    """`result.json`'s `feasible`, the best design's summary (or the closest one's,
    when none was feasible) and the tuned parameters."""
    feasible = bool(result.feasible[0])
    report: dict[str, Any] = {"feasible": feasible}
    if feasible:
        report |= _best_summary(study, result, 0)
    else:
        closest = result.closest_params(0) if np.isfinite(result.closest_violation[0]) else None
        with phase("closest", "no design met every limit: the closest design's peaks"):
            report |= _infeasible_summary(study, closest)
    report |= {"tuned": list(study.problem.tune)}
    if study.calibration is not None:
        report["calibration"] = study.calibration
    return report


def _infeasible_summary(study: Study, closest) -> dict:
    """What `result.json` says when no design met every limit: `best` and `objective`
    None, the least violating design (`closest`, re-solved) with each limit it misses,
    and a one-line `message`."""
    problem = study.problem
    summary: dict[str, Any] = {"best": None, "objective": None}
    if closest is None:
        summary["closest"] = None
        summary["message"] = "no design met every limit, and no solve succeeded"
        return summary
    peaks = _peaks(problem, closest)
    metrics = peaks.metrics()
    missed = rj.closest_miss(problem, rj.metric_violations(problem, metrics))
    design = {k: float(np.asarray(v)) for k, v in rj.params_to_values(closest).items()}
    summary["closest"] = {
        "design": design,
        "metrics": peaks.to_dict(),
        "objective": float(problem.objective(metrics)),
        "missed": missed,
    }
    units = {
        f"{name} ({kind})": rj.METRICS[name].unit for name, kind, _ in problem.metric_constraints
    }
    misses = "; ".join(
        f"{name} {m['value']:.6g} {units[name]} against the limit {m['limit']:.6g} "
        f"{units[name]} (misses by {m['missed_by']:.3g} {units[name]}, "
        f"{_percent(m['missed_by_relative'])})"
        for name, m in missed.items()
    )
    summary["message"] = f"no design met every limit; the closest: {misses}"
    return summary


def _percent(fraction: float) -> str:
    percent = 100 * fraction
    return f"{percent:,.0f} %" if abs(percent) >= 100 else f"{percent:.3g} %"


def _checks(study: Study, result, report: dict, simulations: dict, kwargs, out: Path, phase):
    """The best design's history figure and the study's `[check]`s, into `report`."""
    from .._figures.histories import plot_history

    problem = study.problem
    with phase("history", "the best design's history"):
        history = _history(problem, result.best_params(0), 3.0)
        plot_history(history, out / "best_history.png", title=f"{study.name}: best design")

    if _is_throttling(report["best"]):
        with phase("force_stroke", "force over the stroke, beside a tuned linear damper"):
            report["force_stroke"] = _force_stroke(
                problem, result.best_params(0), history.peaks, out
            )
    check = study.check
    if check.get("hard"):
        with phase("hard_check", "check: the hard-switch model"):
            hard = _peaks(problem, result.best_params(0), rj.Smoothing.exact())
            smooth = _peaks(problem, result.best_params(0))
        # At the nominal parameters (for a scatter study too): a check of the model.
        report["hard_model"] = {
            "metrics": hard.to_dict(),
            "objective_at_nominal": float(problem.objective(hard.metrics())),
            "max_relative_difference": max(
                abs(float(getattr(hard, name)) - float(getattr(smooth, name)))
                / max(abs(float(getattr(smooth, name))), 1e-12)
                for name in rj.METRICS
            ),
        }
        simulations["hard_check"] = 1
    if "grid" in check:
        with phase("grid_check", "check: a grid around the best design"):
            report["grid_check"], n = _grid_check(study, result, check["grid"], phase.enabled)
        report["grid_check"]["optimiser_minus_grid"] = (
            report["objective"] - report["grid_check"]["grid_best_objective"]
        )
        simulations["grid_check"] = n
    if "local" in check:
        with phase("local_check", "check: 1-D scans through the best design"):
            report["local_check"], n = _local_check(
                study, result, float(check["local"]), phase.enabled
            )
        report["local_check"]["optimiser_minus_best_scan"] = (
            report["objective"] - report["local_check"]["best_scan_objective"]
        )
        simulations["local_check"] = n
    if check.get("nominal") and problem.objective.scatter is not None:
        with phase("nominal", "check: the nominal optimum under the same scatter"):
            report["nominal_comparison"], n = _nominal_comparison(study, result, kwargs, out)
        simulations["nominal"] = n


def _run_front(study: Study, front: dict, kwargs: dict) -> tuple[dict, int]:
    problem = study.problem
    vary, values = front["vary"], front["values"]
    if vary in rj.PARAMETERS:
        scenarios = jax.vmap(lambda v: rj.with_values(problem.params, (vary,), v[None]))(
            np.asarray(values)
        )
        result = rj.optimise(problem, scenarios=scenarios, **kwargs)
    else:
        result = rj.optimise(problem, scenario_limits={vary: values}, **kwargs)
    rows = []
    for s, value in enumerate(values):
        if not np.isfinite(result.best_objective[s]):
            rows.append({vary: value, "feasible": False})
            continue
        summary = _best_summary(study, result, s)
        rows.append(
            {
                vary: value,
                "feasible": True,
                "objective": summary["objective"],
                "best": summary["best"],
                "metrics": summary["metrics"],
                "constraints": summary["constraints"],
            }
        )
    return {"vary": vary, "points": rows}, int(result.simulations)


_BUFFER = ("piston_area", "oil_density", "discharge_coefficient", "orifice_length")


def _is_throttling(design: dict) -> bool:
    """A single round on the simplified model with a throttling orifice."""
    return (
        design.get("piston_area", 0.0) > 0
        and design.get("m", 0.0) == 0
        and (design.get("shots", 1) == 1)
    )


def _force_stroke(problem: rj.DesignProblem, params, best: rj.Peaks, out: Path) -> dict:
    """The anchoring force over the recoil stroke of a throttling design, beside the
    constant-force ideal `E0/L` (the least peak force that stops the impulse's energy
    `E0 = M v0²/2` within the stroke `L`) and the paper's linear damper without the
    buffer, its `c_out` tuned (Brent) to the same stroke. `best`: the design's peaks (its
    history's). Writes `force_stroke.png`."""
    from scipy.optimize import brentq

    from .._figures.studies import plot_force_stroke

    # Every solve here is a history on `_history`'s grid: the tuned design's runs the
    # program of the best design's history, and the damper's one program of its own.
    design = {k: v for k, v in rj.params_to_values(params).items()}
    stroke = float(best.peak_displacement)
    energy = 0.5 * design["M"] * design["v0"] ** 2
    ideal = energy / stroke
    plain = {k: v for k, v in design.items() if k not in _BUFFER and not k.startswith("orifice_")}

    def overshoot(c_out):
        params = rj.params_from_values({**plain, "c_out": c_out})
        return float(_history(problem, params, 3.0).peaks.peak_displacement) - stroke

    lo, hi = rj.PARAMETERS["c_out"].documented or (0.0, 1e6)
    c_out, _ = brentq(overshoot, lo, hi, xtol=1e-6 * hi, full_output=True)
    damper = rj.params_from_values({**plain, "c_out": c_out})
    damper_peaks = _history(problem, damper, 3.0).peaks

    def recoil(params, time):
        history = _history(problem, params, time)
        return np.asarray(history.x_M), np.asarray(history.anchoring_force)

    curves = {
        "tuned orifice": recoil(params, float(best.peak_displacement_time)),
        f"linear damper, c_out = {c_out:.0f} N·s/m": recoil(
            damper, float(damper_peaks.peak_displacement_time)
        ),
        f"constant-force ideal E0/L = {ideal:.1f} N": ([0.0, stroke], [ideal, ideal]),
    }
    plot_force_stroke(curves, out)
    damper_peak = float(damper_peaks.peak_anchoring_force)
    return {
        "ideal_force_N": ideal,
        "stroke_m": stroke,
        "above_ideal": float(best.peak_anchoring_force) / ideal - 1.0,
        "linear_damper": {"c_out": c_out, "peak_anchoring_force_N": damper_peak},
    }


def _label(name: str) -> str:
    """An axis label with its unit, for a parameter or a metric."""
    return rj.PARAMETERS[name].label if name in rj.PARAMETERS else rj.METRICS[name].label


def _unit(name: str) -> str:
    """The unit of a parameter or a metric."""
    return rj.PARAMETERS[name].unit if name in rj.PARAMETERS else rj.METRICS[name].unit


def _write_front(table: dict, out: Path) -> None:
    """A front's feasible points: its figures, and `front_<vary>.csv`."""
    from .._figures.studies import plot_front

    vary = table["vary"]
    rows = [r for r in table["points"] if r["feasible"]]
    if not rows:
        return
    force_key = rj.METRICS["peak_anchoring_force"].key
    displacement_key = rj.METRICS["peak_displacement"].key
    x = [r[vary] for r in rows]
    force = [r["metrics"][force_key] for r in rows]
    displacement = [r["metrics"][displacement_key] for r in rows]
    plot_front(vary, _label(vary), x, force, displacement, out)
    stroke_key = rj.METRICS["max_stroke"].key
    lines = [f"{vary},{force_key},{displacement_key},{stroke_key}," + ",".join(rows[0]["best"])]
    for r in rows:
        lines.append(
            ",".join(
                f"{v:.9g}"
                for v in [
                    r[vary],
                    r["metrics"][force_key],
                    r["metrics"][displacement_key],
                    r["metrics"][stroke_key],
                    *r["best"].values(),
                ]
            )
        )
    (out / f"front_{vary}.csv").write_text("\n".join(lines) + "\n")


def _nominal_comparison(study: Study, result, kwargs: dict, out: Path) -> tuple[dict, int]:
    """Optimise the nominal problem (no scatter) and compare both designs over a fine
    scatter of the same range."""
    from .._figures.studies import plot_robust

    problem = study.problem
    names, offsets = problem.objective.scatter_points
    nominal_problem = dataclasses.replace(
        problem, objective=dataclasses.replace(problem.objective, scatter=None)
    )
    nominal = rj.optimise(nominal_problem, **kwargs)
    # One parameter: a fine line over its range; several: the scatter's own points,
    # the first of which is the nominal (a calibration's sigma points).
    line = len(names) == 1
    fine = np.linspace(offsets.min(), offsets.max(), 21)[:, None] if line else offsets
    at = len(fine) // 2 if line else int(np.argmin(np.abs(offsets).sum(1)))
    curves, report = {}, {}
    for label, params in (("robust", result.best_params(0)), ("nominal", nominal.best_params(0))):
        objectives = [
            float(problem.objective(r.metrics())) for r in _scattered(problem, params, fine)
        ]
        x = 100 * fine[:, 0] if line else np.arange(len(fine))
        curves[f"{label} design"] = (x, objectives)
        report[label] = {
            "best": dict(
                zip(
                    problem.tune,
                    (float(x) for x in rj.values_of(params, problem.tune)),
                    strict=True,
                )
            ),
            "objective_nominal": objectives[at],
            "objective_worst": max(objectives),
        }
    xlabel = f"{names[0]} offset (%)" if line else "scatter point (0: the fitted values)"
    plot_robust(curves, xlabel, out)
    return report, int(nominal.simulations) + 2 * len(fine)
