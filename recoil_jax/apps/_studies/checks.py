"""What a study does with its best design once the optimiser has found it: its peaks and
history on the problem's own settings, the worst case over a scatter, the grid and local
scans around it, the hard-switch model, a Pareto front's points, a throttling design's
force over its stroke, a robust design against the nominal one."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import cast

import jax
import numpy as np

import recoil_jax as rj
import recoil_jax.extend as rjx

from .._files.json_writer import write_text
from .study_file import Study

__all__ = [
    "best_summary",
    "check_best",
    "condition_hazards",
    "condition_params",
    "condition_peaks",
    "per_condition",
    "percent",
    "problem_peaks",
    "run_front",
    "unit_of",
    "write_front",
]


def problem_peaks(problem: rj.DesignProblem, params, smoothing=None) -> rj.Peaks:
    """The peaks of `params` with the problem's solver options (and smoothing).

    **Raises:** `SolveError` with the solve's status where it fails: tested here, not by
    the program's runtime error, whose host callback keeps JAX from keeping the program
    in its compilation cache (compiled again in every process: 4.6 s of a warm
    `optimise envelope`)."""
    smoothing = problem.smoothing if smoothing is None else smoothing
    peaks = rj.peaks(params, smoothing, problem.options, throw=False)
    _raise_unless_ok(peaks.status, "the peaks")
    return peaks


def _raise_unless_ok(status, what: str) -> None:
    """`SolveError` naming `what` and the status where a solve failed."""
    if not bool(np.all(np.asarray(status == rj.Status.ok))):
        raise rj.SolveError(f"{what}: {rj.Status[status]}")


def _history(problem: rj.DesignProblem, params, time: float) -> rj.History:
    """The history of `params` with the problem's smoothing and solver options, on 3001
    points over `[0, time]` (s): one grid size, so that the histories of a structure
    are one compiled program. Its `peaks` are over the whole solve.

    **Raises:** `SolveError` with the solve's status where it fails (said once, not
    through the program's runtime error)."""
    history = rj.simulate(
        params, problem.smoothing, problem.options, ts=np.linspace(0.0, time, 3001), throw=False
    )
    _raise_unless_ok(history.peaks.status, f"the history over [0, {time:g}] s")
    return history


def _scattered(problem: rj.DesignProblem, params, offsets) -> list[rj.Peaks]:
    """The peaks at each scatter point, `offsets (S, k)` relative to `params`."""
    names, _ = problem.objective.scatter_points
    nominal = np.asarray(rj.values_of(params, names))
    return [
        problem_peaks(problem, rj.with_values(params, names, nominal * (1 + o))) for o in offsets
    ]


def condition_params(problem: rj.DesignProblem, params) -> dict[str, object]:
    """`params` at each of the problem's conditions by name (`{"": params}` without)."""
    if not problem.conditions:
        return {"": params}
    return {
        c.name: rj.with_values(params, c.names, np.asarray([v for _, v in c.values]))
        for c in problem.conditions
    }


def condition_peaks(problem: rj.DesignProblem, params) -> dict[str, rj.Peaks]:
    """The peaks of `params` at each condition by name (`condition_params`)."""
    return {k: problem_peaks(problem, p) for k, p in condition_params(problem, params).items()}


def per_condition(runs: list[rj.Peaks], names=tuple(rj.METRICS)) -> dict[str, np.ndarray]:
    """The metrics `names` of each run by name, `(K,)` each (`rj.constraint_report`'s
    form for a problem with conditions)."""
    return {name: np.asarray([float(getattr(r, name)) for r in runs]) for name in names}


def _solved(peaks: rj.Peaks) -> list[str]:
    """The metrics a design has (the firing envelope's only with the envelope, the
    margin only with a mount: NaN otherwise)."""
    return [name for name in rj.METRICS if not np.isnan(float(getattr(peaks, name)))]


def _worst_case(problem: rj.DesignProblem, runs: list[rj.Peaks]) -> tuple[dict, float]:
    """Worst-case metrics (each metric's own extreme, or the objective's quantile
    towards it) by JSON key, and the objective the same way, over the scattered solves
    `runs`: what the optimiser held."""
    objective = problem.objective
    worst = rjx.worst_case(per_condition(runs, _solved(runs[0])), quantile=objective.quantile)
    objectives = np.array([float(objective(r.metrics())) for r in runs])
    return (
        {rj.METRICS[name].key: float(v) for name, v in worst.items()},
        float(objective.over_scatter(objectives)),
    )


def condition_hazards(problem: rj.DesignProblem, params, at: dict[str, rj.Peaks]) -> dict:
    """The hazards of `params` at each condition by name (`rj.peaks_hazards`, from its
    peaks `at` each, `condition_peaks`), each with `limited`: whether a limit on the
    metric that measures it holds at that condition (`rjx.HAZARDS`); one that no limit
    covers is a warning of the study's summary."""
    limited: dict[str, set[str]] = {name: set() for name in at}
    names = list(at)
    for (metric, _, _), where in zip(
        problem.metric_constraints, problem.limit_conditions, strict=True
    ):
        for j in where if problem.conditions else [0]:
            limited[names[int(j)]].add(metric)
    return {
        name: [
            h | {"limited": rjx.HAZARDS[h["name"]].metric in limited[name]}
            for h in rj.peaks_hazards(p, at[name])
        ]
        for name, p in condition_params(problem, params).items()
    }


def best_summary(study: Study, result: rj.OptimiseResult, scenario: int) -> dict:
    problem = study.problem
    params = result.best_params(scenario)
    design = result.best_design(scenario)
    best = problem_peaks(problem, params)
    summary = {
        "best": design,
        "metrics": best.to_dict(),
        "objective": float(problem.objective(best.metrics())),
    }
    limits = result.scenario_limits[scenario]
    if problem.conditions:
        at = condition_peaks(problem, params)
        runs = list(at.values())
        worst, worst_objective = _worst_case(problem, runs)
        objectives = [float(problem.objective(r.metrics())) for r in runs]
        summary["objective"] = worst_objective
        summary["worst_condition"] = list(at)[int(np.argmax(objectives))]
        summary["metrics"] = runs[int(np.argmax(objectives))].to_dict()
        summary["worst_case_metrics"] = worst
        hazards = condition_hazards(problem, params, at)
        summary["conditions"] = {
            c.name: {
                "values": dict(c.values),
                "objective": objective,
                "metrics": r.to_dict(),
                "hazards": hazards[c.name],
            }
            for c, r, objective in zip(problem.conditions, runs, objectives, strict=True)
        }
        summary["constraints"] = rj.constraint_report(problem, design, per_condition(runs), limits)
    elif problem.objective.scatter is not None:
        worst, worst_objective = _worst_case(
            problem, _scattered(problem, params, problem.objective.scatter_points[1])
        )
        summary["objective"] = worst_objective
        summary["worst_case_metrics"] = worst
        by_name = {name: worst[m.key] for name, m in rj.METRICS.items() if m.key in worst}
        summary["constraints"] = rj.constraint_report(problem, design, by_name, limits)
    else:
        summary["constraints"] = rj.constraint_report(problem, design, best.metrics(), limits)
    if not problem.conditions:
        summary["hazards"] = condition_hazards(problem, params, {"": best})[""]
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
    }, int(objective.size) * problem.solves_per_design


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
    }, len(points) * problem.solves_per_design


def percent(fraction: float) -> str:
    percent = 100 * fraction
    return f"{percent:,.0f} %" if abs(percent) >= 100 else f"{percent:.3g} %"


def check_best(study: Study, result, report: dict, simulations: dict, kwargs, out: Path, phase):
    """The best design's history figure and the study's `[check]`s, into `report`."""
    from .._figures.histories import plot_history

    problem = study.problem
    worst = report.get("worst_condition")
    at = condition_params(problem, result.best_params(0))
    with phase("history", "the best design's history"):
        title = f"{study.name}: best design" + (f" at {worst}" if worst else "")
        params = cast(rj.RecoilParams, at[worst or ""])  # over the whole solve, as its peaks
        history = _history(problem, params, float(rjx.end_time(params, problem.options)))
        plot_history(history, out / "best_history.png", title=title)
    if problem.conditions:
        from .._figures.studies import plot_conditions

        plot_conditions(problem, report, out / "conditions.png", title=study.name)

    if _is_throttling(report["best"]):
        with phase("force_stroke", "force over the stroke, beside a tuned linear damper"):
            report["force_stroke"] = _force_stroke(
                problem, result.best_params(0), history.peaks, out
            )
    check = study.check
    if check.get("hard"):
        with phase("hard_check", "check: the hard-switch model"):
            hard = {k: problem_peaks(problem, p, rj.Smoothing.exact()) for k, p in at.items()}
            smooth = condition_peaks(problem, result.best_params(0))
        # At the nominal parameters (for a scatter study too; at each condition): a check
        # of the model.
        differences = {
            k: max(
                abs(float(getattr(hard[k], name)) - float(getattr(smooth[k], name)))
                / max(abs(float(getattr(smooth[k], name))), 1e-12)
                for name in _solved(smooth[k])
            )
            for k in at
        }
        key = worst or ""
        report["hard_model"] = {
            "metrics": hard[key].to_dict(),
            "objective_at_nominal": float(problem.objective(hard[key].metrics())),
            "max_relative_difference": max(differences.values()),
        }
        if problem.conditions:
            report["hard_model"]["at"] = worst
            report["hard_model"]["max_relative_difference_by_condition"] = differences
        simulations["hard_check"] = len(at)
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


def run_front(study: Study, front: dict, kwargs: dict) -> tuple[dict, int]:
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
        summary = best_summary(study, result, s)
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


def unit_of(name: str) -> str:
    """The unit of a parameter or a metric."""
    return rj.PARAMETERS[name].unit if name in rj.PARAMETERS else rj.METRICS[name].unit


def write_front(table: dict, out: Path) -> None:
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
    write_text(out / f"front_{vary}.csv", "\n".join(lines) + "\n")


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
