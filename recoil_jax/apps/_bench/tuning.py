"""`recoil-jax bench-tuning`: our optimiser (`rj.search`: global samples through the
batched sweep, then SLSQP with exact gradients) against the tools a user would pick
instead, on the same problems, the same solver and the same wall-time budget:

- `nelder_mead`: scipy's Nelder–Mead (bounded, adaptive) from one Sobol point after
  another, each design solved on its own (`rj.peaks`, jitted) — its natural form;
- `differential_evolution`: scipy's, `vectorized=True` with deferred updating, each
  generation solved as one batch through `rj.sweep` — its strongest honest form;
- `cma_es`: CMA-ES from the maintained `cmaes` package (restarts with a doubled
  population, IPOP), each generation one batch through `rj.sweep`.

Every method works in the same normalised coordinates as ours (log coordinates for
parameters whose bounds span three decades), sees the exact objective with true peaks,
and the derivative-free ones a static penalty for broken limits. JAX's compiled code is
dropped before each method, so each pays for its own compilation. Reported per problem
and method: the best feasible objective, wall seconds, plain and gradient solves, and
the wall seconds until a feasible design came within 0.1 % of the best known value
(the best any method found in the run).
"""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import jax
import numpy as np

import recoil_jax as rj
import recoil_jax.extend as rjx

from .._files.cluster import dask_client
from .._files.options import Commands, add_cluster, add_json
from .._studies.study_file import load_study, search_kwargs

__all__ = [
    "DEFAULT_PROBLEMS",
    "add_command",
    "format_report",
    "main_tuning_bench",
    "over_seeds",
    "run_tuning_bench",
    "speedup",
]

#: Problem (shipped study) → wall-time budget per method (s) on 2 CPU cores.
DEFAULT_PROBLEMS = {
    "tuned_absorber": 20.0,
    "tuned_absorber_global": 20.0,
    "throttling": 60.0,
    "burst": 60.0,
    "burst_recuperator": 90.0,
}
METHODS = ("recoil-jax", "nelder_mead", "differential_evolution", "cma_es")
#: Within this fraction of the best known value counts as reaching it.
TOLERANCE = 1e-3
#: The penalty factor of the derivative-free methods: objective · (1 + PENALTY · excess).
PENALTY = 100.0


class _Budget(Exception):
    """The method's wall-time budget is spent."""


class _Evaluator:
    """Plain solves of a problem in normalised coordinates, single or batched, with
    every evaluation recorded (time, exact objective, feasibility)."""

    def __init__(self, problem: rj.DesignProblem, budget: float, client=None):
        self.problem, self.budget = problem, budget
        self.space = rjx.SearchSpace.of(problem)  # the coordinates `rj.search` moves in
        self.evaluator = rjx.BatchEvaluator(problem, self.space, client)
        self.start = time.perf_counter()
        self.times: list[float] = []
        self.values: list[float] = []
        self.feasible: list[bool] = []

    def theta(self, z: np.ndarray) -> np.ndarray:
        return np.asarray(self.space.theta(np.clip(np.asarray(z, float), 0.0, 1.0)))

    def _score(self, objective: np.ndarray, violations: np.ndarray, ok: np.ndarray):
        excess = np.sum(np.maximum(violations, 0.0), axis=-1)
        ok = ok & np.isfinite(objective)
        now = time.perf_counter() - self.start
        self.times += [now] * len(objective)
        self.values += [float(f) for f in objective]
        self.feasible += list(rj.feasible(ok, objective, violations))
        if now > self.budget:
            raise _Budget
        return np.where(ok, objective * (1.0 + PENALTY * excess), 1e12)

    def batch(self, z: np.ndarray) -> np.ndarray:
        """Penalised objectives of `z (n, P)`, through the batched sweep (the evaluator
        of `rj.search`'s global phase)."""
        evaluation = self.evaluator(np.clip(np.asarray(z, float), 0.0, 1.0))
        return self._score(evaluation.objective, evaluation.violations, evaluation.ok)

    def single(self, z: np.ndarray) -> float:
        """The penalised objective of one design `z (P,)`, through `rj.peaks`."""
        params = rj.with_values(self.problem.params, self.problem.tune, self.theta(z))
        peaks = rj.peaks(params, self.problem.smoothing, self.problem.options, throw=False)
        metrics = {name: np.atleast_1d(float(getattr(peaks, name))) for name in rj.METRICS}
        objective = np.asarray(self.problem.objective(metrics), dtype=float)
        violations = rj.metric_violations(self.problem, metrics)
        ok = np.atleast_1d(bool(peaks.status == rj.Status.ok))
        return float(self._score(objective, violations, ok)[0])

    def trace(self) -> dict[str, np.ndarray]:
        return {
            "seconds": np.asarray(self.times),
            "objective": np.asarray(self.values),
            "feasible": np.asarray(self.feasible, dtype=bool),
        }


def _run_nelder_mead(evaluator: _Evaluator, dimension: int, seed: int) -> None:
    from scipy.optimize import minimize  # here: the command line loads this module
    from scipy.stats import qmc

    starts = qmc.Sobol(dimension, scramble=True, rng=np.random.default_rng(seed))
    while True:
        minimize(
            evaluator.single,
            starts.random(1)[0],
            method="Nelder-Mead",
            bounds=[(0.0, 1.0)] * dimension,
            options={"maxfev": 200 * dimension, "xatol": 1e-6, "fatol": 1e-6, "adaptive": True},
        )


def _run_differential_evolution(evaluator: _Evaluator, dimension: int, seed: int) -> None:
    from scipy.optimize import differential_evolution  # here: the command line loads this

    while True:  # restarts with a new seed if it converges before the budget
        differential_evolution(
            lambda x: evaluator.batch(np.asarray(x).T),
            [(0.0, 1.0)] * dimension,
            vectorized=True,
            updating="deferred",
            polish=False,
            maxiter=100000,
            tol=1e-8,
            rng=np.random.default_rng(seed),
        )
        seed += 1000


def _run_cma_es(evaluator: _Evaluator, dimension: int, seed: int) -> None:
    from cmaes import CMA

    population = None
    rng = np.random.default_rng(seed)
    while True:  # IPOP: restart with a doubled population
        optimizer = CMA(
            mean=rng.random(dimension),
            sigma=0.3,
            bounds=np.tile([0.0, 1.0], (dimension, 1)),
            seed=int(rng.integers(2**31)),
            population_size=population,
        )
        while not optimizer.should_stop():
            z = np.stack([optimizer.ask() for _ in range(optimizer.population_size)])
            values = evaluator.batch(z)
            optimizer.tell(list(zip(z, values, strict=True)))
        population = 2 * optimizer.population_size


_DERIVATIVE_FREE: dict[str, Callable[[_Evaluator, int, int], None]] = {
    "nelder_mead": _run_nelder_mead,
    "differential_evolution": _run_differential_evolution,
    "cma_es": _run_cma_es,
}


def _summary(trace: dict, wall: float, solves: int, gradient_solves: int) -> dict:
    values = np.where(trace["feasible"], trace["objective"], np.inf)
    best = float(np.min(values)) if values.size else np.inf
    return {
        "best": best if np.isfinite(best) else None,
        "wall_s": round(wall, 2),
        "solves": int(solves),
        "gradient_solves": int(gradient_solves),
        "trace": trace,
    }


def _run_ours(study, budget: float, seed: int, client=None) -> dict:
    kwargs = search_kwargs(study, progress=False) | {"seed": seed, "max_seconds": budget}
    kwargs["client"] = client
    start = time.perf_counter()
    result = rj.search(study.problem, **kwargs)
    wall = time.perf_counter() - start
    # Held to the same budget: what came after it does not count.
    within = result.trace["seconds"] <= budget
    trace = {k: result.trace[k][within] for k in ("seconds", "objective", "feasible")}
    gradient = result.trace["gradient"][within].astype(bool)
    return _summary(trace, min(wall, budget), int((~gradient).sum()), int(gradient.sum()))


def _run_derivative_free(method: str, study, budget: float, seed: int, client=None) -> dict:
    evaluator = _Evaluator(study.problem, budget, client)
    try:
        _DERIVATIVE_FREE[method](evaluator, len(study.problem.tune), seed)
    except _Budget:
        pass
    wall = time.perf_counter() - evaluator.start
    trace = evaluator.trace()
    return _summary(trace, min(wall, budget), len(trace["objective"]), 0)


def run_tuning_bench(
    problems: dict[str, float] | None = None,
    *,
    seeds: Sequence[int] = (0,),
    budget_scale: float = 1.0,
    methods: tuple[str, ...] = METHODS,
    out: str | Path | None = None,
    log=None,
    client=None,
) -> dict:
    """Run every method on every problem (study name → budget in s, times
    `budget_scale`) from every seed of `seeds`, cold then warm. Returns `{"problems":
    {name: {"dimension", "best_known", "target", "budget_s", "speedup", "methods":
    {method: {"best", "wall_s", "solves", "gradient_solves", "to_target_s", "cold",
    "over_seeds"}}}}}`: the run of the first seed, and `over_seeds` (`over_seeds`) of all
    of them (`speedup`: see `speedup`, of the medians over the seeds); with `out`, a
    convergence figure per problem there (the first seed's runs). With `client` (a
    `dask.distributed.Client`), every batch of plain solves (our global phase, each
    generation of differential evolution and CMA-ES) runs its chunks on the cluster
    (a cold run then drops this process's compiled programs, not the workers')."""
    log = log or (lambda msg: print(msg, file=sys.stderr, flush=True))
    problems = dict(DEFAULT_PROBLEMS if problems is None else problems)
    seeds = _checked_bench(methods, seeds)
    report: dict = {"problems": {}, "seeds": seeds}
    for name, budget in problems.items():
        study = load_study(name)
        budget = float(budget) * budget_scale
        runs, cold = _run_methods(study, budget, seeds, methods, client, log)
        every = [r["best"] for m in methods for r in [*runs[m], *cold[m]]]
        bests = [b for b in every if b is not None]
        best_known = min(bests) if bests else None
        target = None if best_known is None else best_known * (1.0 + TOLERANCE)
        if out is not None:
            _plot(study.name, {m: r[0] for m, r in runs.items()}, target, Path(out))
        entry = {
            "dimension": len(study.problem.tune),
            "best_known": best_known,
            "target": target,
            "budget_s": budget,
            "methods": {m: _method_report(runs[m], cold[m], target) for m in methods},
        }
        report["problems"][study.name] = entry | {"speedup": speedup(entry)}
    return report


def _checked_bench(methods, seeds) -> list[int]:
    """The seeds as integers, the methods and seeds checked (cmaes installed if asked)."""
    unknown = set(methods) - set(METHODS)
    if unknown:
        raise rj.ParameterError(f"unknown method(s) {sorted(unknown)}; known: {list(METHODS)}")
    seeds = [int(s) for s in seeds]
    if not seeds or any(s < 0 for s in seeds):
        raise rj.ParameterError(f"seeds = {seeds}: valid one or more integers >= 0")
    if "cma_es" in methods:
        import cmaes  # noqa: F401 (the `apps` extra: missing, say so before anything runs)
    return seeds


def _run_methods(study, budget: float, seeds, methods, client, log):
    """Every method from every seed, cold then warm: `runs[method][i]` the warm run
    from `seeds[i]`, `cold[method][i]` its cold one."""
    runs: dict[str, list] = {m: [] for m in methods}
    cold: dict[str, list] = {m: [] for m in methods}
    for seed in seeds:
        for method in methods:
            # Twice: cold (JAX's compiled code dropped first, so each method pays for
            # its own compilation), then warm (the same run again, its programs
            # compiled: a design session's second study, a re-run notebook cell).
            for label, into in (("cold", cold), ("warm", runs)):
                log(f"{study.name}: {method} ({label}, seed {seed}), budget {budget:g} s ...")
                if label == "cold":
                    jax.clear_caches()
                if method == "recoil-jax":
                    run = _run_ours(study, budget, seed, client)
                else:
                    run = _run_derivative_free(method, study, budget, seed, client)
                into[method].append(run)
                log(f"  best {run['best']}, {run['wall_s']} s")
    return runs, cold


def _method_report(runs: list[dict], cold: list[dict], target) -> dict:
    """One method's entry: its first seed's warm run, cold run, and all seeds'."""
    first, first_cold = runs[0], cold[0]
    return {k: v for k, v in first.items() if k != "trace"} | {
        "to_target_s": _seconds_to(first["trace"], target),
        "cold": {
            "best": first_cold["best"],
            "to_target_s": _seconds_to(first_cold["trace"], target),
            "solves": first_cold["solves"],
            "gradient_solves": first_cold["gradient_solves"],
        },
        "over_seeds": over_seeds(
            [_seconds_to(r["trace"], target) for r in runs],
            [_seconds_to(r["trace"], target) for r in cold],
            [r["best"] for r in runs],
        ),
    }


def over_seeds(warm: list, cold: list, bests: list) -> dict:
    """Per method, over its seeds: `seeds`, `successes` (warm runs within 0.1 % of the
    best known), the median and worst seconds to target, warm and cold (None where it
    is never: a median whose half of the runs never reached it, a worst where one run
    never did), and the spread of the best objectives (`best_min`, `best_max`)."""

    def stats(times: list) -> dict:
        values = np.asarray([np.inf if t is None else t for t in times] or [np.inf])
        median, worst = float(np.median(values)), float(np.max(values))
        return {
            "successes": int(np.isfinite(values).sum()),
            "median_to_target_s": round(median, 2) if np.isfinite(median) else None,
            "worst_to_target_s": round(worst, 2) if np.isfinite(worst) else None,
        }

    found = [b for b in bests if b is not None]
    return (
        {"seeds": len(warm)}
        | stats(warm)
        | {"cold": stats(cold)}
        | {
            "best_min": min(found) if found else None,
            "best_max": max(found) if len(found) == len(bests) and found else None,
        }
    )


def _seconds_to(trace: dict, target) -> float | None:
    """Wall seconds until a feasible objective <= `target` (None if never)."""
    if target is None:
        return None
    reached = trace["feasible"] & (trace["objective"] <= target)
    return round(float(trace["seconds"][np.argmax(reached)]), 2) if reached.any() else None


def _plot(name: str, runs: dict, target, out: Path) -> None:
    from .._figures.histories import plot_series

    series = {}
    for method, run in runs.items():
        trace = run["trace"]
        best = np.minimum.accumulate(np.where(trace["feasible"], trace["objective"], np.inf))
        finite = np.isfinite(best)
        if finite.any():
            series[method] = (trace["seconds"][finite], best[finite])
    if series:
        out.mkdir(parents=True, exist_ok=True)
        low = min(float(np.min(y)) for _, y in series.values())
        plot_series(
            series,
            out / f"bench_tuning_{name}.png",
            xlabel="wall time (s), compilation included",
            ylabel="best feasible objective",
            title=f"{name}: best feasible objective so far"
            + ("" if target is None else f" (target {target:.6g})"),
            ylim=(low * 0.998, low * 1.05),
        )


def _median_to_target(run: dict):
    over = run.get("over_seeds")
    return run["to_target_s"] if over is None else over["median_to_target_s"]


def speedup(problem: dict) -> dict | None:
    """How many times sooner recoil-jax reached the target than the best other method,
    by the median over the seeds (with one seed: its time): `{"factor": F, "at_least":
    bool}`. When no other method's median reached it within the budget, `F = budget /
    ours` is a lower bound (`at_least`); None when ours did not reach it or no other
    method ran."""
    ours = _median_to_target(problem["methods"].get("recoil-jax", {"to_target_s": None}))
    others = [_median_to_target(r) for m, r in problem["methods"].items() if m != "recoil-jax"]
    if ours is None or not others:
        return None
    reached = [t for t in others if t is not None]
    seconds = min(reached) if reached else problem["budget_s"]
    return {"factor": round(seconds / max(ours, 1e-9), 2), "at_least": not reached}


def _speedups(problem: dict) -> str:
    ratio = problem["speedup"]
    if _median_to_target(problem["methods"].get("recoil-jax", {"to_target_s": None})) is None:
        return "recoil-jax did not reach the target"
    if ratio is None:
        return "no other method ran"
    if ratio["at_least"]:
        return (
            f"no other method reached the target in {problem['budget_s']:g} s: recoil-jax "
            f">= {ratio['factor']:.1f}x sooner"
        )
    return f"recoil-jax {ratio['factor']:.1f}x sooner than the best other method"


def format_report(report: dict) -> str:
    lines = []
    for name, problem in report["problems"].items():
        target = problem["target"]
        lines.append(
            f"{name} ({problem['dimension']} parameters, budget {problem['budget_s']:g} s): "
            f"best known {problem['best_known']:.7g}, target {target:.7g}; " + _speedups(problem)
            if target is not None
            else f"{name}: no method found a feasible design"
        )
        for method, r in problem["methods"].items():
            best = "none feasible" if r["best"] is None else f"{r['best']:.7g}"

            def seconds(x):
                return "never" if x is None else f"{x} s"

            lines.append(
                f"  {method:<24} best {best:<14} to target {seconds(r['to_target_s']):<9} "
                f"(cold {seconds(r['cold']['to_target_s'])}); {r['solves']} solves + "
                f"{r['gradient_solves']} gradient solves in {r['wall_s']} s"
            )
            over = r["over_seeds"]
            if over["seeds"] > 1:
                lines.append(
                    f"  {'':<24} over {over['seeds']} seeds: {over['successes']} reach the "
                    f"target, median {seconds(over['median_to_target_s'])}, worst "
                    f"{seconds(over['worst_to_target_s'])} (cold: {over['cold']['successes']}, "
                    f"median {seconds(over['cold']['median_to_target_s'])}, worst "
                    f"{seconds(over['cold']['worst_to_target_s'])}); best "
                    f"{over['best_min']} to {over['best_max']}"
                )
    return "\n".join(lines)


def main_tuning_bench(args) -> int:
    problems = None
    if args.problems:
        problems = {p: DEFAULT_PROBLEMS.get(p, 60.0) for p in args.problems}
    if args.seeds is not None and args.seeds < 1:
        raise rj.ParameterError(f"--seeds {args.seeds}: valid >= 1")
    with dask_client(args.workers, args.scheduler) as client:
        report = run_tuning_bench(
            problems,
            seeds=[args.seed] if args.seeds is None else range(args.seeds),
            budget_scale=args.budget_scale,
            methods=tuple(args.methods or METHODS),
            out=args.out,
            client=client,
        )
    print(json.dumps(report) if args.json else format_report(report))
    return 0


def add_command(commands: Commands) -> None:
    """`recoil-jax bench-tuning`'s arguments."""
    tuning = commands.add(
        "bench-tuning",
        main_tuning_bench,
        help="our optimiser against Nelder-Mead, differential evolution and CMA-ES",
        description="On each problem (shipped studies; default tuned_absorber, "
        "tuned_absorber_global, throttling, burst, burst_recuperator), run recoil-jax's "
        "search and, with the same solver and wall-time budget, scipy's Nelder-Mead "
        "(multistart), scipy's differential_evolution (vectorized, batches through the "
        "sweep) and CMA-ES (cmaes, batches through the sweep). Reports the best feasible "
        "objective, solves, and wall seconds to within 0.1 % of the best known value.",
    )
    tuning.add_argument(
        "problems", nargs="*", help="shipped study names (default: all five problems)"
    )
    add_json(tuning, "one JSON object")
    tuning.add_argument("--seed", type=int, default=0, help="seed of every method (default 0)")
    tuning.add_argument(
        "--seeds",
        type=int,
        metavar="K",
        help="run every method from seeds 0..K-1 (replaces --seed) and report, per "
        "method, how many reach the target and the median and worst time to it, cold and "
        "warm; the speedup is of the medians",
    )
    tuning.add_argument(
        "--budget-scale",
        type=float,
        default=1.0,
        help="multiply every problem's wall-time budget (default 1)",
    )
    tuning.add_argument(
        "--methods",
        nargs="+",
        metavar="METHOD",
        help="the methods to run: recoil-jax, nelder_mead, differential_evolution, "
        "cma_es (default: all four)",
    )
    tuning.add_argument("--out", help="folder for the convergence figures (default: none)")
    add_cluster(tuning, "every batch of plain solves")
