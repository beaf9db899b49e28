"""Optimisation studies: a TOML file → `optimise` → `result.json` and figures.

```toml
description = "what this study asks"
[design]                      # the base design (simulate names); the rest: paper values
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
[optimiser]                   # starts, steps, learning_rate, seed, anneal, patience
starts = 8
[[front]]                     # optional, repeatable: one optimisation per value (vmapped)
vary = "m"                    #   a parameter, or a constrained metric (ε-constraint)
values = [250, 500, 1000]
[check]                       # optional checks of the best design
grid = {gap = [0.0, 0.12, 241]}   # cartesian grid (lo, hi, count) around it
local = 0.02                  # 1-D scans ± this fraction of each bound's width
hard = true                   # the hard-switch model
nominal = true                # (scatter) the nominal optimum under the same scatter
```
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import jax
import numpy as np

from ._optimise import _JSON_KEYS as _METRIC_KEYS, constraint_report
from ._params import PARAMETER_NAMES, ParameterError, Smoothing, params_from_values
from ._solve import peaks, simulate

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

_SECTIONS = {"description", "design", "tune", "objective", "constraints", "optimiser",
             "front", "check"}
_OPTIMISER_KEYS = {"starts", "steps", "learning_rate", "seed", "anneal", "patience",
                   "update_every", "penalty"}
_CHECK_KEYS = {"grid", "local", "hard", "nominal"}


@dataclass
class Study:
    """A parsed study file."""

    name: str
    description: str
    problem: Any  # DesignProblem
    optimiser: dict = field(default_factory=dict)
    fronts: list[dict] = field(default_factory=list)
    check: dict = field(default_factory=dict)


def _error(path, message: str) -> ParameterError:
    return ParameterError(f"{path}: {message}")


def load_study(path) -> Study:
    """Parse and validate a study file (errors name the file and the key)."""
    from ._optimise import Constraint, DesignProblem, Objective

    path = Path(path)
    try:
        config = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise ParameterError(f"study file {path} not found") from None
    except tomllib.TOMLDecodeError as error:
        raise _error(path, f"not valid TOML: {error}") from None
    unknown = set(config) - _SECTIONS
    if unknown:
        raise _error(path, f"unknown section(s) {', '.join(sorted(unknown))}; known: "
                     f"{', '.join(sorted(_SECTIONS))}")
    for section in ("tune", "objective"):
        if section not in config:
            raise _error(path, f"missing [{section}]")
    design = dict(config.get("design", {}))
    tune, bounds = [], {}
    for name, bound in config["tune"].items():
        if name not in PARAMETER_NAMES:
            raise _error(path, f"[tune] unknown parameter {name!r}")
        if not (isinstance(bound, list) and len(bound) == 2):
            raise _error(path, f"[tune] {name} = [lo, hi] expected, got {bound!r}")
        tune.append(name)
        bounds[name] = (float(bound[0]), float(bound[1]))
    objective_config = dict(config["objective"])
    temperatures = objective_config.pop("temperatures", {})
    scatter = objective_config.pop("scatter", None)
    if scatter is not None:
        if len(scatter) != 1:
            raise _error(path, "[objective.scatter] takes one parameter = [offsets]")
        (scatter_name, offsets), = scatter.items()
        scatter = (scatter_name, tuple(float(o) for o in offsets))
    objective = Objective(
        weights={k: float(v) for k, v in objective_config.items()},
        temperatures={k: float(v) for k, v in temperatures.items()},
        scatter=scatter,
    )
    constraints = []
    for name, limits in config.get("constraints", {}).items():
        if not isinstance(limits, dict) or set(limits) - {"max", "min"}:
            raise _error(path, f"[constraints] {name} = {{max = .., min = ..}} expected")
        constraints.append(Constraint(name, upper=limits.get("max"), lower=limits.get("min")))
    # The base design starts inside the (constraint-tightened) bounds.
    params = params_from_values(design)
    problem = DesignProblem(params=params, objective=objective, tune=tuple(tune),
                            bounds=bounds, constraints=tuple(constraints))
    optimiser = dict(config.get("optimiser", {}))
    if set(optimiser) - _OPTIMISER_KEYS:
        raise _error(path, f"[optimiser] unknown key(s) "
                     f"{', '.join(sorted(set(optimiser) - _OPTIMISER_KEYS))}; known: "
                     f"{', '.join(sorted(_OPTIMISER_KEYS))}")
    fronts = config.get("front", [])
    fronts = [fronts] if isinstance(fronts, dict) else list(fronts)
    constrained = [name for name, _, _ in problem.metric_constraints]
    for front in fronts:
        vary = front.get("vary")
        if vary not in PARAMETER_NAMES and vary not in constrained:
            raise _error(path, f"[[front]] vary = {vary!r}: give a parameter or a "
                         f"constrained metric ({', '.join(constrained) or 'none'})")
        if vary in tune:
            raise _error(path, f"[[front]] vary = {vary!r} is tuned; fix it to vary it")
        if not front.get("values"):
            raise _error(path, "[[front]] needs values = [...]")
    check = dict(config.get("check", {}))
    if set(check) - _CHECK_KEYS:
        raise _error(path, f"[check] unknown key(s) {', '.join(sorted(set(check) - _CHECK_KEYS))}")
    return Study(name=path.stem, description=config.get("description", ""), problem=problem,
                 optimiser=optimiser, fronts=fronts, check=check)


def _optimise_kwargs(study: Study, progress: bool | None) -> dict:
    from ._optimise import default_optimiser

    o = study.optimiser
    steps = int(o.get("steps", 200))
    kwargs = dict(starts=int(o.get("starts", 8)), steps=steps, seed=int(o.get("seed", 0)),
                  optimiser=default_optimiser(float(o.get("learning_rate", 0.1)), steps),
                  progress=progress)
    for key in ("anneal", "penalty"):
        if key in o:
            kwargs[key] = float(o[key])
    for key in ("patience", "update_every"):
        if key in o:
            kwargs[key] = int(o[key])
    return kwargs


def _metrics_json(params, smoothing=None) -> dict:
    return peaks(params, smoothing or Smoothing()).to_dict()


def _scatter_worst(problem, params, offsets) -> tuple[dict, float]:
    """Worst-case metrics (max; min for min_stroke) and objective over `offsets`."""
    from ._design import values_of, with_values

    name, _ = problem.objective.scatter
    nominal = float(values_of(params, (name,))[0])
    rows = [_metrics_json(with_values(params, (name,), [nominal * (1 + o)]))
            for o in offsets]
    worst = {k: (min if k == "min_stroke_m" else max)(r[k] for r in rows)
             for k in rows[0] if k.endswith(("_m", "_N"))}
    return worst, max(problem.objective.of_json(r) for r in rows)


def _best_summary(study: Study, result, scenario: int) -> dict:
    problem = study.problem
    params = result.best_params(scenario)
    design = result.best_design(scenario)
    metrics = _metrics_json(params)
    summary = {"best": design, "metrics": metrics,
               "objective": problem.objective.of_json(metrics)}
    limits = result.scenario_limits[scenario]
    if problem.objective.scatter is not None:
        worst, worst_objective = _scatter_worst(problem, params, problem.objective.scatter[1])
        summary["objective"] = worst_objective
        summary["worst_case_metrics"] = worst
        summary["constraints"] = constraint_report(problem, design, worst, limits)
    else:
        summary["constraints"] = constraint_report(problem, design, metrics, limits)
    return summary


def _feasible_objective(problem, sweep_result) -> tuple[np.ndarray, np.ndarray]:
    """The objective (with peaks) of each swept design, inf where a solve failed or a
    metric limit is broken; and the feasibility mask."""
    feasible = sweep_result.ok.copy()
    for name, kind, limit in problem.metric_constraints:
        values = sweep_result.peaks[_METRIC_KEYS[name]]
        feasible &= values <= limit if kind == "max" else values >= limit
    objective = problem.objective(
        {n: sweep_result.peaks[_METRIC_KEYS[n]] for n in problem.objective.weights})
    return np.where(feasible, objective, np.inf), feasible


def _grid_check(study: Study, result, axes: dict) -> tuple[dict, int]:
    """The best feasible point of a cartesian grid around the best design (others fixed
    at it), for the objective with peaks."""
    from ._sweep import sweep_grid

    problem = study.problem
    design = result.best_design(0)
    grid_axes = {}
    for name, spec in axes.items():
        lo, hi, count = spec
        grid_axes[name] = np.linspace(float(lo), float(hi), int(count))
    fixed = {k: v for k, v in design.items() if k not in grid_axes}
    sweep_result = sweep_grid(grid_axes, fixed=fixed, progress=False)
    objective, feasible = _feasible_objective(problem, sweep_result)
    i = int(np.argmin(objective))
    spacing = {n: float(a[1] - a[0]) if len(a) > 1 else 0.0 for n, a in grid_axes.items()}
    return {
        "axes": {n: [float(a[0]), float(a[-1]), len(a)] for n, a in grid_axes.items()},
        "points": int(objective.size),
        "feasible_points": int(feasible.sum()),
        "grid_best_objective": float(objective[i]),
        "grid_best_design": {n: float(sweep_result.values[n][i]) for n in grid_axes},
        "grid_spacing": spacing,
    }, int(objective.size)


def _local_check(study: Study, result, fraction: float) -> tuple[dict, int]:
    """1-D scans of ± `fraction` of each bound's width through the best design."""
    from ._sweep import sweep

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
    sweep_result = sweep(points, progress=False)
    objective, _ = _feasible_objective(problem, sweep_result)
    return {"fraction_of_bounds": fraction, "points": len(points),
            "best_scan_objective": float(np.min(objective)),
            "per_parameter": {n: float(np.min(objective[np.asarray(labels) == n]))
                              for n in problem.tune}}, len(points)


def run_study(path, out: str | Path | None = None, progress: bool | None = None) -> dict:
    """Run a study file: optimise, check, write `result.json` and figures to `out`
    (default `results/<study name>`). Returns the result dict."""
    from ._optimise import optimise
    from ._plot import plot_convergence, plot_history, plot_series

    study = load_study(path)
    out = Path(out) if out is not None else Path("results") / study.name
    out.mkdir(parents=True, exist_ok=True)
    problem = study.problem
    kwargs = _optimise_kwargs(study, progress)
    started = time.perf_counter()
    if progress is not False:
        print(f"study {study.name}: {study.description}", file=sys.stderr)

    result = optimise(problem, **kwargs)
    report: dict[str, Any] = {"study": study.name, "description": study.description}
    report |= _best_summary(study, result, 0)
    simulations = {"optimiser": int(result.simulations)}
    report["tuned"] = list(problem.tune)
    report["optimiser"] = {
        "starts": result.starts, "steps": result.steps, "compilations": result.compilations,
        "seconds": round(result.seconds, 2),
        "converged_runs": int(result.converged.sum()),
        "where_starts_ended": result.clusters(0),
    }
    plot_convergence(result, out / "convergence.png", title=study.name)
    history = simulate(result.best_params(0), ts=np.linspace(0.0, 3.0, 3001))
    plot_history(history, out / "best_history.png", title=f"{study.name}: best design")

    check = study.check
    if check.get("hard"):
        hard = _metrics_json(result.best_params(0), Smoothing.exact())
        smooth = report["metrics"]
        # At the nominal parameters (for a scatter study too): a check of the model.
        report["hard_model"] = {
            "metrics": hard,
            "objective_at_nominal": problem.objective.of_json(hard),
            "max_relative_difference": max(
                abs(hard[k] - smooth[k]) / max(abs(smooth[k]), 1e-12)
                for k in smooth if k.endswith("_N") or k.endswith("_m")),
        }
        simulations["hard_check"] = 1
    if "grid" in check:
        report["grid_check"], n = _grid_check(study, result, check["grid"])
        report["grid_check"]["optimiser_minus_grid"] = (
            report["objective"] - report["grid_check"]["grid_best_objective"])
        simulations["grid_check"] = n
    if "local" in check:
        report["local_check"], n = _local_check(study, result, float(check["local"]))
        report["local_check"]["optimiser_minus_best_scan"] = (
            report["objective"] - report["local_check"]["best_scan_objective"])
        simulations["local_check"] = n
    if check.get("nominal") and problem.objective.scatter is not None:
        report["nominal_comparison"], n = _nominal_comparison(study, result, kwargs, out)
        simulations["nominal"] = n
    fronts = []
    for front in study.fronts:
        table, n = _run_front(study, front, kwargs)
        fronts.append(table)
        simulations[f"front_{front['vary']}"] = n
        _plot_front(table, out, plot_series)
    if fronts:
        report["fronts"] = fronts
    report["simulations"] = int(sum(simulations.values()))
    report["simulations_by_part"] = simulations
    report["seconds"] = round(time.perf_counter() - started, 2)
    (out / "result.json").write_text(json.dumps(report, indent=2) + "\n")
    return report


def _run_front(study: Study, front: dict, kwargs: dict) -> tuple[dict, int]:
    from ._design import with_values
    from ._optimise import optimise

    problem = study.problem
    vary, values = front["vary"], [float(v) for v in front["values"]]
    if vary in PARAMETER_NAMES:
        scenarios = jax.vmap(lambda v: with_values(problem.params, (vary,), v[None]))(
            np.asarray(values))
        result = optimise(problem, scenarios=scenarios, **kwargs)
    else:
        result = optimise(problem, scenario_limits={vary: values}, **kwargs)
    rows = []
    for s, value in enumerate(values):
        if not np.isfinite(result.best_objective[s]):
            rows.append({vary: value, "feasible": False})
            continue
        summary = _best_summary(study, result, s)
        rows.append({vary: value, "feasible": True, "objective": summary["objective"],
                     "best": summary["best"], "metrics": summary["metrics"],
                     "constraints": summary["constraints"]})
    return {"vary": vary, "points": rows}, int(result.simulations)


def _plot_front(table: dict, out: Path, plot_series) -> None:
    vary = table["vary"]
    rows = [r for r in table["points"] if r["feasible"]]
    if not rows:
        return
    x = [r[vary] for r in rows]
    force = [r["metrics"]["peak_anchoring_force_N"] for r in rows]
    displacement = [r["metrics"]["peak_displacement_m"] for r in rows]
    unit = "kg" if vary == "m" else ("m" if vary in PARAMETER_NAMES else "")
    plot_series({"best design": (x, force)}, out / f"front_{vary}.png",
                xlabel=f"{vary} ({unit})" if unit else vary, ylabel="peak anchoring force (N)",
                title=f"Pareto front: peak anchoring force vs {vary}")
    plot_series({"best design": (displacement, force)},
                out / f"front_{vary}_force_vs_displacement.png",
                xlabel="peak barrel displacement (mm)", ylabel="peak anchoring force (N)",
                xscale=1e3, title="peak anchoring force vs peak displacement")
    lines = [f"{vary},peak_anchoring_force_N,peak_displacement_m,max_stroke_m,"
             + ",".join(rows[0]["best"])]
    for r in rows:
        lines.append(",".join(f"{v:.9g}" for v in [
            r[vary], r["metrics"]["peak_anchoring_force_N"], r["metrics"]["peak_displacement_m"],
            r["metrics"]["max_stroke_m"], *r["best"].values()]))
    (out / f"front_{vary}.csv").write_text("\n".join(lines) + "\n")


def _nominal_comparison(study: Study, result, kwargs: dict, out: Path) -> tuple[dict, int]:
    """Optimise the nominal problem (no scatter) and compare both designs over a fine
    scatter of the same range."""
    from ._design import values_of, with_values
    from ._optimise import optimise
    from ._plot import plot_series

    problem = study.problem
    name, offsets = problem.objective.scatter
    nominal_problem = dataclasses.replace(
        problem, objective=dataclasses.replace(problem.objective, scatter=None))
    nominal = optimise(nominal_problem, **kwargs)
    fine = np.linspace(min(offsets), max(offsets), 21)
    curves, report = {}, {}
    for label, params in (("robust", result.best_params(0)),
                          ("nominal", nominal.best_params(0))):
        base = float(values_of(params, (name,))[0])
        objectives = [problem.objective.of_json(_metrics_json(
            with_values(params, (name,), [base * (1 + o)]))) for o in fine]
        curves[f"{label} design"] = (100 * fine, objectives)
        report[label] = {"best": {k: v for k, v in
                                  zip(problem.tune, (float(x) for x in values_of(
                                      params, problem.tune)), strict=True)},
                         "objective_nominal": objectives[len(fine) // 2],
                         "objective_worst": max(objectives)}
    plot_series(curves, out / "robust_vs_nominal.png", xlabel=f"{name} offset (%)",
                ylabel="objective", title="objective under scatter")
    return report, int(nominal.simulations) + 2 * len(fine)
