"""A study run: its file loaded (`study_file`), the optimiser run through `rj.search` or
`rj.optimise` in phases with a progress line, the best design checked (`checks`), and
`result.json` and the figures written; the summary printed."""

from __future__ import annotations

import contextlib
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

import recoil_jax as rj
import recoil_jax.extend as rjx

from .._files.cluster import check_cluster, dask_client
from .._files.inputs import (
    check_not_input,
    design_warnings,
    file_integer,
    output_folder,
    warn,
)
from .._files.json_writer import write as write_json
from .checks import (
    best_summary,
    check_best,
    condition_hazards,
    condition_peaks,
    per_condition,
    percent,
    run_front,
    unit_of,
    write_front,
)
from .study_file import Study, load_study, optimise_kwargs, search_kwargs, study_values

__all__ = ["agreement_line", "hazard_lines", "run_study", "study_summary"]


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
    for name, c in report.get("conditions", {}).items():
        metrics = ", ".join(
            f"{key} {c['metrics'][key]:.6g}" if c["metrics"][key] is not None else f"{key} -"
            for key in _condition_keys(report)
        )
        worst = " (worst)" if name == report.get("worst_condition") else ""
        lines.append(f"  at {name}{worst}: {metrics}")
    for name, c in report["constraints"].items():
        unit = unit_of(name.split(" (", 1)[0])
        state = "ok" if c["satisfied"] else "VIOLATED"
        u = f" {unit}" if unit else ""  # a margin has no unit: no space before the bracket
        lines.append(f"  {name}: {c['value']:.6g}{u} (limit {c['limit']:g}{u}) {state}")
    if line := agreement_line(report):
        lines.append(f"  {line}")
    lines.extend(hazard_lines(report))
    return "\n".join(lines)


def hazard_lines(report: dict) -> list[str]:
    """The summary's warning lines: each hazard of the best design (or the closest) at
    each condition that no limit covers (`condition_hazards`)."""
    design = report.get("closest") if report.get("best") is None else report
    if not design:
        return []
    at = {k: c.get("hazards", []) for k, c in design.get("conditions", {}).items()}
    if not at:
        at = {"": design.get("hazards", [])}
    return [
        f"  warning: {h['name']}{' at ' + name if name else ''}: {h['sentence']} "
        "(no limit covers it)"
        for name, hazards in at.items()
        for h in hazards
        if not h["limited"]
    ]


def _condition_keys(report: dict) -> list[str]:
    """The JSON keys the summary shows at each condition: the objective's metrics and
    the limited ones."""
    names = [
        *report.get("objective_metrics", []),
        *(n.split(" (", 1)[0] for n in report["constraints"]),
    ]
    return [rj.METRICS[n].key for n in dict.fromkeys(names) if n in rj.METRICS]


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


class _Phases:
    """Says on stderr what a study is doing, phase by phase, and times each phase (for
    `result.json`'s `seconds_by_part`): a first run's seconds are mostly compilation."""

    def __init__(self, name: str, enabled: bool | None):
        self.name, self.enabled = name, enabled is not False
        self.seconds: dict[str, float] = {}
        self.current = ""  # the part under way (or last begun): what a failure was in

    @contextlib.contextmanager
    def __call__(self, part: str, what: str):
        self.current = part
        if self.enabled:
            print(f"study {self.name}: {what} ...", file=sys.stderr, flush=True)
        began = time.perf_counter()
        yield
        self.current = ""  # done: a failure after it is not this part's
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
    warn(design_warnings(study_values(study.problem)))
    out = output_folder(out if out is not None else Path("results") / study.name)
    check_not_input(out, ("result.json",), path)
    kwargs = optimise_kwargs(study, progress)
    started = time.perf_counter()
    phase = _Phases(study.name, progress)
    if progress is not False:
        print(f"study {study.name}: {study.description}", file=sys.stderr)
    report: dict[str, Any] = {
        "study": study.name,
        "description": study.description,
        "objective_unit": study.problem.objective.unit,
        "objective_metrics": list(study.problem.objective.weights),
    }
    if study.optimiser["method"] == "search":
        result, simulations, report["optimiser"] = _run_search(
            study, out, phase, progress, store, workers, scheduler
        )
    else:
        result, simulations, report["optimiser"] = _run_adam(study, out, phase, kwargs, store)
    report |= _outcome(study, result, phase)
    write_json(out / "result.json", report)  # the search's result, whatever follows
    try:
        if report["feasible"]:
            check_best(study, result, report, simulations, kwargs, out, phase)
        fronts = []
        for front in study.fronts:
            with phase(f"front_{front['vary']}", f"front over {front['vary']}"):
                table, n = run_front(study, front, kwargs)
            fronts.append(table)
            simulations[f"front_{front['vary']}"] = n
            write_front(table, out)
        if fronts:
            report["fronts"] = fronts
    except Exception as error:  # the after-steps' failure beside the result, then raised
        report["failed_after"] = {
            "step": phase.current or "between the steps after the search",
            "error": rj.failure_message(error)
            if isinstance(error, rj.SolveError)
            else f"{type(error).__name__}: {error}",
        }
        report["seconds"] = round(time.perf_counter() - started, 2)
        write_json(out / "result.json", report)
        raise
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
        report |= best_summary(study, result, 0)
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
    at = condition_peaks(problem, closest)
    runs = list(at.values())
    metrics = per_condition(runs) if problem.conditions else runs[0].metrics()
    missed = rj.closest_miss(problem, rj.metric_violations(problem, metrics))
    design = {k: float(np.asarray(v)) for k, v in rj.params_to_values(closest).items()}
    objectives = [float(problem.objective(r.metrics())) for r in runs]
    hazards = condition_hazards(problem, closest, at)
    summary["closest"] = {
        "design": design,
        "metrics": runs[int(np.argmax(objectives))].to_dict(),
        "objective": max(objectives),
        "missed": missed,
    }
    if problem.conditions:
        summary["closest"]["conditions"] = {
            k: r.to_dict() | {"hazards": hazards[k]} for k, r in zip(at, runs, strict=True)
        }
    else:
        summary["closest"]["hazards"] = hazards[""]
    units = {
        label: rj.METRICS[name].unit
        for (name, _, _), label in zip(
            problem.metric_constraints, problem.limit_labels, strict=True
        )
    }
    misses = "; ".join(
        f"{name} {m['value']:.6g} {units[name]} against the limit {m['limit']:.6g} "
        f"{units[name]} (misses by {m['missed_by']:.3g} {units[name]}, "
        f"{percent(m['missed_by_relative'])})"
        for name, m in missed.items()
    )
    summary["message"] = f"no design met every limit; the closest: {misses}"
    return summary
