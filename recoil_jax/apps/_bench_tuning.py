"""`recoil-jax bench-tuning`: gradient-based tuning (optax, multi-start, forward
sensitivities) against a gradient-free method (scipy's Nelder–Mead) on a study (default
`tuned_absorber`): how many simulations each needs to come within 0.1 % of the best
objective either finds, with every limit held."""

from __future__ import annotations

import json
import sys
import time

import numpy as np
from scipy.optimize import minimize

import recoil_jax as rj

from ._studies import load_study, optimise_kwargs

__all__ = ["DEFAULT_STUDY", "format_report", "main_tuning_bench", "run_tuning_bench"]

#: The study the benchmark runs by default (a shipped study, found from anywhere).
DEFAULT_STUDY = "tuned_absorber"


def _first_within(values: np.ndarray, target: float) -> int | None:
    hits = np.nonzero(values <= target)[0]
    return int(hits[0]) if hits.size else None


def run_tuning_bench(
    study_path=None, nelder_mead_evaluations: int = 4000, tolerance: float = 1e-3, log=None
) -> dict:
    log = log or (lambda msg: print(msg, file=sys.stderr, flush=True))
    study = load_study(study_path or DEFAULT_STUDY)
    problem = study.problem
    lower, upper = problem.box()

    log("gradient-based: optax Adam, multi-start, forward sensitivities ...")
    kwargs = optimise_kwargs(study, progress=False)
    start = time.perf_counter()
    result = rj.optimise(problem, **kwargs)
    gradient_seconds = time.perf_counter() - start
    history = result.history
    ok = int(rj.status_codes(rj.Status.ok))
    feasible = np.all(history["violations"] <= 0, axis=-1) & (history["status"] == ok)
    values = np.where(feasible, history["objective"], np.inf)  # (steps, runs)

    log("gradient-free: scipy Nelder-Mead from the same first start ...")
    smoothing, options = problem.smoothing, problem.options
    evaluations: list[tuple[float, bool]] = []

    def penalised(x):
        theta = lower + (upper - lower) * np.clip(x, 0.0, 1.0)
        peaks = rj.peaks(
            rj.with_values(problem.params, problem.tune, theta), smoothing, options, throw=False
        )
        solved = bool(peaks.status == rj.Status.ok)
        value = float(problem.objective(peaks.metrics()))
        # The sum of the normalised violations of the metric limits.
        violation = 0.0
        for name, kind, limit in problem.metric_constraints:
            excess = float(getattr(peaks, name)) - limit
            excess = excess if kind == "max" else -excess
            violation += max(0.0, excess / (abs(limit) or 1.0))
        evaluations.append((value, solved and violation == 0.0))
        return value * (1.0 + 100.0 * violation) if solved else 1e9

    def nelder_mead(x0, evaluations_cap):
        minimize(
            penalised,
            x0,
            method="Nelder-Mead",
            bounds=[(0.0, 1.0)] * len(x0),
            options={"maxfev": evaluations_cap, "xatol": 1e-7, "fatol": 1e-4, "adaptive": True},
        )

    starts = (result.history["theta"][0] - lower) / (upper - lower)  # (runs, P)
    penalised(starts[0])  # compile outside the timing
    evaluations.clear()
    start = time.perf_counter()
    nelder_mead(starts[0], nelder_mead_evaluations)
    nelder_mead_seconds = time.perf_counter() - start
    nm_values = np.asarray([f if ok else np.inf for f, ok in evaluations])

    log(f"gradient-free: Nelder-Mead from each of the {len(starts)} starts in turn ...")
    per_start = []
    for x0 in starts:
        evaluations.clear()
        nelder_mead(x0, nelder_mead_evaluations // 4)
        per_start.append(np.asarray([f if ok else np.inf for f, ok in evaluations]))

    best = min(
        float(np.min(values)), float(np.min(nm_values)), min(float(np.min(v)) for v in per_start)
    )
    target = best * (1.0 + tolerance)
    runs = values.shape[1]
    best_so_far = np.min(values, axis=1)
    step = _first_within(best_so_far, target)
    single = _first_within(values[:, 0], target)
    nm_hit = _first_within(np.minimum.accumulate(nm_values), target)
    # Multi-start Nelder-Mead, run one start after the other: simulations until one hits.
    used, multi_hit, reached = 0, None, 0
    for v in per_start:
        hit = _first_within(np.minimum.accumulate(v), target)
        reached += hit is not None
        if multi_hit is None and hit is not None:
            multi_hit = used + hit + 1
        used += len(v)
    report = {
        "study": study.name,
        "target_objective": target,
        "best_objective": best,
        "gradient": {
            "best_objective": float(np.min(values)),
            "starts": runs,
            "simulations_to_target": None if step is None else (step + 1) * runs,
            "single_start_simulations_to_target": None if single is None else single + 1,
            "simulations_total": int(result.simulations),
            "seconds_total": round(gradient_seconds, 2),
            "note": "each simulation integrates the 4 forward sensitivities too",
        },
        "nelder_mead": {
            "best_objective": float(np.min(nm_values)),
            "simulations_to_target": None if nm_hit is None else nm_hit + 1,
            "simulations_total": len(evaluations),
            "seconds_total": round(nelder_mead_seconds, 2),
        },
        "nelder_mead_multistart": {
            "starts": len(per_start),
            "starts_reaching_target": int(reached),
            "gradient_starts_reaching_target": int(np.sum(np.min(values, axis=0) <= target)),
            "simulations_to_target": multi_hit,
            "simulations_total": int(used),
            "best_objective": min(float(np.min(v)) for v in per_start),
        },
    }
    return report


def format_report(report: dict) -> str:
    g, nm = report["gradient"], report["nelder_mead"]

    def fmt(x):
        return "not reached" if x is None else f"{x}"

    return "\n".join(
        [
            f"tuning benchmark on {report['study']}: target objective "
            f"{report['target_objective']:.6g} (within 0.1 % of the best found, "
            f"{report['best_objective']:.6g})",
            f"  gradient (optax, {g['starts']} starts): best {g['best_objective']:.6g}; "
            f"simulations to target {fmt(g['simulations_to_target'])} (all starts), "
            f"{fmt(g['single_start_simulations_to_target'])} (the first start alone); "
            f"{g['simulations_total']} in {g['seconds_total']} s in all",
            f"  Nelder-Mead (scipy, 1 start): best {nm['best_objective']:.6g}; simulations to "
            f"target {fmt(nm['simulations_to_target'])}; {nm['simulations_total']} in "
            f"{nm['seconds_total']} s in all",
            f"  Nelder-Mead from each of the same {report['nelder_mead_multistart']['starts']} "
            f"starts in turn: {report['nelder_mead_multistart']['starts_reaching_target']} reach "
            f"the target (gradient: "
            f"{report['nelder_mead_multistart']['gradient_starts_reaching_target']}); "
            f"simulations to target "
            f"{fmt(report['nelder_mead_multistart']['simulations_to_target'])}",
        ]
    )


def main_tuning_bench(args) -> int:
    report = run_tuning_bench(args.study)
    print(json.dumps(report) if args.json else format_report(report))
    return 0
