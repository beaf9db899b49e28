"""Global search plus gradient polish: space-filling samples through the batched
solver, then a bounded, constrained quasi-Newton method (SLSQP) with exact gradients
from the best few of them.

- `minimise`: the method on any box-bounded problem with inequality constraints, given
  a batched evaluator (the global phase) and a value-and-Jacobian function (the local
  phase). Works in normalised coordinates `z ∈ [0, 1]^P`.
- `search`: `minimise` on a `DesignProblem`. The global phase runs plain solves
  through `sweep`; the local phase differentiates `evaluate_design` through its custom
  JVP (one sensitivity solve per gradient, whatever the number of outputs). A peak that
  jumps between local maxima over time is minimised as a minimax of the signal at a
  thousand times, so that competing maxima are levelled together: from the samples by
  trust-region linear programming, or after a short smoothed level by SLSQP on the
  epigraph, with the signal also at its local maxima (narrow peaks).
  Parameters whose bounds are positive and span three decades or more are searched in
  log coordinates (orifice areas, stiffnesses, masses).

Why SLSQP: it handles bounds and metric limits natively (no penalty to tune) and
converges superlinearly near a smooth optimum; each iteration costs one gradient
solve. Measured against the optax Adam loop of `optimise` in `optimise/README.md`.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._gradients import MetricSeries, series_name
from ._metrics import METRICS
from ._params import (
    ParameterError,
    RecoilParams,
    end_time,
    params_to_values,
    values_of,
    with_values,
)
from ._problem import DesignProblem, evaluate_design
from ._progress import Progress
from ._status import Status, status_codes
from ._sweep import default_workers, sweep

__all__ = ["MinimiseResult", "log_coordinates", "minimax_metric", "minimise", "search"]

#: Default continuation of the smooth-maximum temperatures: factors of the objective's.
TEMPERATURE_SCHEDULE = (1.0, 1 / 3, 1 / 9, 1 / 30)

#: SLSQP's tolerance at every continuation level but the last: a level's optimum only
#: starts the next one, so polishing it further is wasted.
LEVEL_FTOL = 1e-6

#: Before a minimax, a smoothed level finds the basin: SLSQP stops there after this many
#: iterations or at this tolerance (on `throttling`, warm, to within 0.1 %: 2.6 s with 8,
#: 4.0 s with 15, slower with 30; with none, the minimax stalled far off from the samples).
BASIN_MAXITER = 8
BASIN_FTOL = 1e-4

#: The minimax from the samples (trust-region linear programming): the first trust
#: radius (max-norm, normalised coordinates), the fraction of the predicted fall in the
#: merit a step must achieve to be taken, the radius at which a run ends, and the
#: penalty per unit of normalised limit violation in the merit.
MINIMAX_RADIUS = 0.03
ACCEPT = 0.01
MIN_RADIUS = 1e-9
LIMIT_PENALTY = 100.0

#: A minimax run ends once its best feasible objective has not improved by this
#: fraction in this many gradient solves.
STALL_RTOL = 1e-6
STALL_SOLVES = 20

#: Every other local run starts at least this far (max-norm, normalised coordinates)
#: from the others: the best samples crowd into the widest basin (measured on
#: `tuned_absorber` without a start, 8 starts all spaced so: 0.1 found the global
#: optimum in 8 of 10 seeds, 0.25 and 0.4 in 10 of 10).
SPACING = 0.25

#: A point is feasible when every normalised violation is <= -TOLERANCE, and the local
#: phase aims at -MARGIN: the limits then hold on any re-solve of the design (a plain
#: solve and a sensitivity solve of the same design differ by ~5e-7 in a stroke).
TOLERANCE = 1e-6
MARGIN = 1e-5

#: Failed solves at trial points a local run steps back from before it ends.
MAX_FAILURES = 20


@dataclasses.dataclass
class MinimiseResult:
    """Outcome of `minimise` / `search` (host NumPy values).

    - `best_z`: the best feasible point in normalised coordinates `(P,)`, `best_theta`
      in SI units (`search`), `best_objective` (NaN and `feasible = False` when no
      evaluated point held every limit: the problem is reported infeasible).
    - `trace`: every evaluation in order: `seconds` since the start, `objective` (exact),
      `feasible`, `gradient` (whether it was a gradient solve), `phase` (`"sample"`,
      `"start"` or `"local"`).
    - `samples`: the global phase: `z (N, P)`, `objective (N,)`, `violation (N,)` (the
      largest normalised violation), `ok (N,)`.
    - `starts`: per local run: `z0`, `z`, `objective`, `iterations`, `message`,
      `seconds` (its start and end since the start of the search).
    - `solves`, `gradient_solves`: plain solves and sensitivity solves; `seconds`;
      `compilations` of the gradient program.
    """

    best_z: np.ndarray
    best_objective: float
    feasible: bool
    trace: dict[str, np.ndarray]
    samples: dict[str, np.ndarray]
    starts: list[dict]
    solves: int
    gradient_solves: int
    seconds: float
    compilations: int
    problem: DesignProblem | None = None
    best_theta: np.ndarray | None = None

    def best_so_far(self) -> np.ndarray:
        """The best feasible objective after each evaluation of `trace` (inf before)."""
        values = np.where(self.trace["feasible"], self.trace["objective"], np.inf)
        return np.minimum.accumulate(values)

    def seconds_to(self, target: float) -> float | None:
        """Wall seconds until a feasible objective ≤ `target` was found (None if never)."""
        hits = np.nonzero(self.best_so_far() <= target)[0]
        return float(self.trace["seconds"][hits[0]]) if hits.size else None

    # The interface of `OptimiseResult` that studies read (one scenario).
    @property
    def tune(self) -> tuple[str, ...]:
        assert self.problem is not None
        return self.problem.tune

    @property
    def scenario_limits(self) -> np.ndarray:
        assert self.problem is not None
        return np.asarray([[limit for _, _, limit in self.problem.metric_constraints]])

    def best_params(self, scenario: int = 0) -> RecoilParams:
        if not self.feasible:
            raise ParameterError("no feasible design was found: there is no best design")
        assert self.problem is not None and self.best_theta is not None and scenario == 0
        return with_values(self.problem.params, self.problem.tune, self.best_theta)

    def best_design(self, scenario: int = 0) -> dict[str, float]:
        """Every parameter of the best design, by flat name."""
        params = self.best_params(scenario)
        return {k: float(np.asarray(v)) for k, v in params_to_values(params).items()}


class _Recorder:
    """Every evaluation, in order, with the best feasible point so far."""

    def __init__(self, bar: Progress):
        self.bar, self.start = bar, time.perf_counter()
        self.lock = threading.Lock()
        self.gradient_solves = 0
        self.rows: dict[str, list] = {
            k: [] for k in ("seconds", "objective", "feasible", "gradient", "phase")
        }
        self.best_z, self.best = None, np.inf
        self.count = 0

    def add(self, z, objective, violation, ok, gradient: bool, phase: str):
        with self.lock:
            self._add(z, objective, violation, ok, gradient, phase)

    def _add(self, z, objective, violation, ok, gradient: bool, phase: str):
        now = time.perf_counter() - self.start
        self.gradient_solves += int(gradient)
        for zi, f, v, good in zip(
            np.atleast_2d(z), np.atleast_1d(objective), np.atleast_1d(violation),
            np.atleast_1d(ok), strict=True
        ):  # fmt: skip
            feasible = _feasible(good, v, f)
            for key, value in zip(
                self.rows, (now, float(f), feasible, gradient, phase), strict=True
            ):
                self.rows[key].append(value)
            if feasible and f < self.best:
                self.best, self.best_z = float(f), np.array(zi, dtype=float)
        self.count += int(np.size(objective))
        best = f"{self.best:.7g}" if np.isfinite(self.best) else "none feasible yet"
        self.bar.update(min(self.count, self.bar.total - 1), f"best feasible objective {best}")


class _SolveFailed(Exception):
    pass


class _OutOfTime(Exception):
    pass


class _Stalled(Exception):
    pass


def minimise(
    evaluate_batch: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]],
    value_and_jacobian: Callable[[np.ndarray, float], tuple],
    dimension: int,
    *,
    samples: int = 1024,
    starts: int = 8,
    initial: Sequence[np.ndarray] = (),
    schedule: Sequence[float] = (1.0,),
    maxiter: int = 100,
    ftol: float = 1e-10,
    seed: int = 0,
    max_seconds: float | None = None,
    workers: int = 1,
    progress: bool | None = None,
    label: str = "search",
    new_run: Callable[[], None] | None = None,
) -> MinimiseResult:
    """Minimise `f(z)` subject to `g(z) <= 0` over the unit box `z ∈ [0, 1]^P`: a scrambled
    Sobol sample of the box, then SLSQP from the best few distinct points.

    **Arguments:**

    - `evaluate_batch(z)`: `z (n, P)` → `(objective (n,), violations (n, C), ok (n,))`:
      the exact objective, the normalised constraint values (`<= 0` when held) and whether
      the evaluation succeeded.
    - `value_and_jacobian(z, temperature)`: `z (P,)` → `(f, g, df (P,), dg (C, P),
      objective, ok)`: the smoothed objective the local phase minimises at continuation
      level `temperature` (a factor from `schedule`), its constraints, their Jacobians,
      the exact objective at `z`, and whether the evaluation succeeded. At level 0 `f`
      may instead be a vector `(K,)` with `df (K, P)`: the objective is then its
      maximum, a minimax: with `schedule=(0.0,)` solved by trust-region linear
      programming (Madsen's method), after smoothed levels by SLSQP on the epigraph
      `min s, f_k(z) <= s`.
    - `dimension`: `P`.
    - `samples`: Sobol points of the global phase (rounded up to a power of 2; 0: none).
    - `starts`: local runs, from the best distinct points (feasible first, then the least
      violating); `initial` points (e.g. a given design) come first.
    - `schedule`: the continuation levels (factors >= 0), run in turn from each start;
      before a last level 0 (the minimax), the smoothed levels only find the basin
      (`BASIN_MAXITER`).
    - `maxiter`, `ftol`: the iteration limit per level (SLSQP's, or the LP's) and the
      tolerance at the last level (earlier levels stop at `max(ftol, LEVEL_FTOL)`).
    - `max_seconds`: a wall-time budget: once spent, no further gradient solve starts
      and the best point so far is returned.
    - `workers`: local runs at the same time, each from its own thread (the given
      starts run while the global phase samples).
    - `progress`: a progress line with the best feasible objective (default: on a
      terminal).
    - `new_run`: called at the start of each local run, from its thread (`search`
      forgets there what it adapted to the previous run's points).

    **Returns:** `MinimiseResult`.
    """
    # scipy is imported when used: `import recoil_jax` stays quick for the command line.
    import scipy.optimize
    import scipy.stats

    if dimension < 1 or starts < 0 or samples < 0 or maxiter < 1:
        raise ParameterError(
            f"minimise: need dimension >= 1, starts >= 0, samples >= 0, maxiter >= 1 "
            f"(got {dimension}, {starts}, {samples}, {maxiter})"
        )
    if not schedule or any(not s >= 0 for s in schedule):
        raise ParameterError(f"minimise: schedule must be factors >= 0, got {schedule}")
    initial = [np.clip(np.asarray(z, dtype=float), 0.0, 1.0) for z in initial]
    n_samples = 0 if samples == 0 else int(2 ** np.ceil(np.log2(samples)))
    budget = n_samples + len(initial) + (starts + len(initial)) * len(schedule) * maxiter
    bar = Progress(label, budget, "solves", progress)
    record = _Recorder(bar)

    def out_of_time() -> bool:
        return max_seconds is not None and time.perf_counter() - record.start > max_seconds

    def warm_up():
        centre = np.full(dimension, 0.5)
        _, g, _, _, exact, ok = value_and_jacobian(centre, schedule[0])
        record.add(centre, exact, _worst(np.asarray(g)[None], 1), ok, True, "local")

    # Local phase: SLSQP from a point, through the continuation levels.

    def local_run(z0):
        began = time.perf_counter() - record.start
        if new_run is not None:
            new_run()
        z, message, final = z0, "", np.nan
        state = {"iterations": 0}
        cache: dict[Any, tuple] = {}
        failures = 0
        fallback: tuple | None = None  # what a failed trial point reports
        # The minimax's best feasible point of this run, and gradient solves since it.
        progress: dict[str, Any] = {"best": np.inf, "z": None, "since": 0}

        def watch(x, exact, violation, ok, level):
            """End a minimax that has stalled: SLSQP's own test on the change of `s`
            rarely fires, since the signal's values carry the solver's tolerance."""
            if level != 0:
                return
            gain = exact < progress["best"] * (1.0 - STALL_RTOL)
            if _feasible(ok, violation, exact) and gain:
                progress.update(best=float(exact), z=np.array(x), since=0)
            else:
                progress["since"] += 1
                if progress["since"] >= STALL_SOLVES and progress["z"] is not None:
                    raise _Stalled

        def limits(level):
            """The metric limits as SLSQP's inequality (aimed `MARGIN` inside)."""
            return {
                "type": "ineq",
                "fun": lambda x: -evaluate(x[:dimension], level)[1] - MARGIN,
                "jac": lambda x: _padded(-evaluate(x[:dimension], level)[3], x.size),
            }

        def evaluate(x, level):
            nonlocal failures
            key = (x.tobytes(), level)
            if key not in cache:
                if out_of_time():
                    raise _OutOfTime
                cache.clear()
                f, g, df, dg, exact, ok = value_and_jacobian(x, level)
                f, g, df, dg = (np.asarray(a, dtype=float) for a in (f, g, df, dg))
                violation = _worst(g[None], 1)
                record.add(x, exact, violation, ok, True, "local")
                watch(x, exact, violation[0], ok, level)
                finite = all(np.all(np.isfinite(a)) for a in (f, g, df, dg))
                if bool(ok) and finite:
                    cache[key] = (f if f.ndim else float(f), g, df, dg)
                else:
                    # A trial point whose solve failed looks much worse than the start
                    # of the level, so that the line search steps back from it.
                    failures += 1
                    if fallback is None or failures > MAX_FAILURES:
                        raise _SolveFailed
                    cache[key] = fallback
            return cache[key]

        try:
            for level in schedule:
                fallback = None
                f0, g0, df0, dg0 = evaluate(z, level)
                scale = float(np.max(np.abs(f0))) or 1.0
                fallback = (f0 + 10.0 * scale, np.abs(g0) + 1.0, df0, dg0)
                ftol_level = ftol if level == schedule[-1] else max(ftol, LEVEL_FTOL)
                iters = maxiter
                if level > 0 and schedule[-1] == 0:
                    # Only the basin for the minimax that follows: a few iterations.
                    iters, ftol_level = min(maxiter, BASIN_MAXITER), max(ftol, BASIN_FTOL)
                if np.ndim(f0) == 0:
                    result = scipy.optimize.minimize(
                        lambda x, lv=level, s=scale: (
                            evaluate(x, lv)[0] / s,
                            evaluate(x, lv)[2] / s,
                        ),
                        z,
                        jac=True,
                        method="SLSQP",
                        bounds=[(0.0, 1.0)] * dimension,
                        constraints=[limits(level)],
                        options={"maxiter": iters, "ftol": ftol_level},
                    )
                    z, message = np.clip(result.x, 0.0, 1.0), str(result.message)
                    state["iterations"] += int(result.nit)
                elif len(schedule) == 1:
                    z, message = _trust_region_lp(
                        evaluate, z, level, scale, maxiter, ftol_level, state
                    )
                else:
                    z, message = _epigraph_slsqp(
                        evaluate, limits, z, level, scale, maxiter, ftol_level, state
                    )
                final = float(np.max(evaluate(z, level)[0]))
        except _SolveFailed:
            message = f"solves failed ({failures}): this start ended there"
        except _OutOfTime:
            message = "the time budget ran out"
        except _Stalled:
            z, final = progress["z"], progress["best"]
            message = f"stalled: no gain of {STALL_RTOL:g} in {STALL_SOLVES} gradient solves"
        return {
            "z0": z0,
            "z": z,
            "objective": final,
            "iterations": state["iterations"],
            "message": message,
            "seconds": (began, time.perf_counter() - record.start),
        }

    # Given starts first (a design known to be good is polished at once), then the
    # global phase: one batch through the batched solver, and the best distinct samples.
    with ThreadPoolExecutor(max(1, workers)) as pool:
        given = [pool.submit(local_run, z0) for z0 in initial]
        if not given and starts:
            # Compile the gradient program while the global phase samples: one
            # gradient solve at the centre of the box, recorded like the others.
            given_warmup = pool.submit(warm_up)
        else:
            given_warmup = None
        if n_samples and not out_of_time():
            z = scipy.stats.qmc.Sobol(
                dimension, scramble=True, rng=np.random.default_rng(seed)
            ).random(n_samples)
            objective, violations, ok = (np.asarray(a) for a in evaluate_batch(z))
            violation = _worst(violations, len(z))
            record.add(z, objective, violation, ok, False, "sample")
            sampled = {"z": z, "objective": objective, "violation": violation, "ok": ok}
        else:
            sampled = {
                "z": np.zeros((0, dimension)),
                "objective": np.zeros(0),
                "violation": np.zeros(0),
                "ok": np.zeros(0, bool),
            }
        sampled_runs = pool.map(local_run, _distinct_best(sampled, starts))
        runs = [future.result() for future in given] + list(sampled_runs)
        if given_warmup is not None:
            given_warmup.result()
    bar.update(bar.total, _best_note(record.best), final=True)
    trace = {k: np.asarray(v) for k, v in record.rows.items()}
    feasible = record.best_z is not None
    return MinimiseResult(
        best_z=np.asarray(record.best_z) if feasible else np.full(dimension, np.nan),
        best_objective=record.best if feasible else np.nan,
        feasible=feasible,
        trace=trace,
        samples=sampled,
        starts=runs,
        solves=n_samples,
        gradient_solves=record.gradient_solves,
        seconds=time.perf_counter() - record.start,
        compilations=0,
    )


def _padded(jacobian: np.ndarray, columns: int) -> np.ndarray:
    """A Jacobian `(m, P)` with zero columns appended up to `columns` (the epigraph's
    extra variable)."""
    return np.pad(jacobian, ((0, 0), (0, columns - jacobian.shape[1])))


def _epigraph_slsqp(evaluate, limits, z, level, scale, maxiter, ftol, state):
    """SLSQP on the epigraph of a minimax: `min s` over `(z, s)` subject to every value
    `f_k(z) <= s` (here the objective's signal at many times and its located peak) and
    the limits. Each local maximum becomes its own smooth constraint, so SLSQP levels
    competing peaks at once instead of chasing the one that is highest. After a
    smoothed level: SLSQP's curvature model carries it over kinks of peaks narrower
    than the grid, where `_trust_region_lp` stops (see `minimise`)."""
    import scipy.optimize

    dimension = z.size
    top = np.zeros(dimension + 1)
    top[-1] = 1.0

    def peaks_below(x):
        return x[-1] - evaluate(x[:dimension], level)[0] / scale

    def peaks_jacobian(x):
        df = evaluate(x[:dimension], level)[2] / scale
        return np.hstack([-df, np.ones((df.shape[0], 1))])

    start = np.append(z, np.max(evaluate(z, level)[0]) / scale)
    result = scipy.optimize.minimize(
        lambda x: (x[-1], top),
        start,
        jac=True,
        method="SLSQP",
        bounds=[(0.0, 1.0)] * dimension + [(None, None)],
        constraints=[{"type": "ineq", "fun": peaks_below, "jac": peaks_jacobian}, limits(level)],
        options={"maxiter": maxiter, "ftol": ftol},
    )
    state["iterations"] += int(result.nit)
    return np.clip(result.x[:dimension], 0.0, 1.0), str(result.message)


def _trust_region_lp(evaluate, z, level, scale, maxiter, ftol, state):
    """Trust-region linear programming on a minimax (Madsen's method): from `z`, each
    iteration solves `min_d max_k f_k + ∇f_k·d` (here the objective's signal at many
    times and its located peak), the limits linearised, `|d| <= radius` and the unit
    box, as an LP (HiGHS), then accepts the step if the exact merit fell by at least
    `ACCEPT` of the predicted fall, and grows or shrinks the radius by their ratio.
    Every local maximum is its own linear piece, so competing peaks are levelled at
    once; near a levelled optimum (more active peaks than parameters) it converges
    quadratically. A limit enters the merit as an exact penalty (`LIMIT_PENALTY` per
    unit of normalised violation), so a step may trade a little violation for a lower
    peak only while it leads back inside.

    `state["iterations"]` counts the iterations as they go (one gradient solve each).
    **Returns:** `(z, message)`."""
    import scipy.optimize

    dimension = z.size

    def merit(f, g):
        return np.max(f) / scale + LIMIT_PENALTY * max(0.0, np.max(g + MARGIN, initial=-np.inf))

    f, g, df, dg = evaluate(z, level)
    value = merit(f, g)
    radius = MINIMAX_RADIUS
    # Variables `(d (P), peak, excess)`: minimise `peak + LIMIT_PENALTY * excess`.
    cost = np.zeros(dimension + 2)
    cost[dimension:] = 1.0, LIMIT_PENALTY
    for _ in range(maxiter):
        rows = np.vstack(
            [
                np.hstack([df / scale, -np.ones((f.size, 1)), np.zeros((f.size, 1))]),
                np.hstack([dg, np.zeros((g.size, 1)), -np.ones((g.size, 1))]),
            ]
        )
        step_bounds = [(max(-radius, -zi), min(radius, 1.0 - zi)) for zi in z]
        lp = scipy.optimize.linprog(
            cost,
            A_ub=rows,
            b_ub=np.concatenate([-f / scale, -(g + MARGIN)]),
            bounds=[*step_bounds, (None, None), (0.0, None)],
            method="highs",
        )
        if lp.status != 0:
            return z, f"the linear program failed: {lp.message}"
        step = lp.x[:dimension]
        predicted = value - cost @ lp.x
        if predicted <= ftol * max(1.0, abs(value)):
            return z, "converged: the predicted decrease is below ftol"
        trial = np.clip(z + step, 0.0, 1.0)
        f_trial, g_trial, df_trial, dg_trial = evaluate(trial, level)
        state["iterations"] += 1
        trial_value = merit(f_trial, g_trial)
        ratio = (value - trial_value) / predicted
        if ratio > ACCEPT:
            z, f, g, df, dg, value = trial, f_trial, g_trial, df_trial, dg_trial, trial_value
        length = float(np.max(np.abs(step)))
        if ratio > 0.75:
            radius = min(1.0, max(radius, 2.5 * length))
        elif ratio < 0.25:
            radius = length / 2
        if radius < MIN_RADIUS:
            return z, f"converged: the trust radius is below {MIN_RADIUS:g}"
    return z, "iteration limit reached"


def _feasible(ok, violation, objective) -> bool:
    """Whether an evaluation counts as feasible: it succeeded, its objective is finite and
    its largest normalised violation is at most `-TOLERANCE`."""
    return bool(ok) and bool(violation <= -TOLERANCE) and bool(np.isfinite(objective))


def _best_note(best: float) -> str:
    return f"best feasible objective {best:.7g}" if np.isfinite(best) else "nothing feasible"


def _worst(violations, n: int) -> np.ndarray:
    violations = np.asarray(violations, dtype=float).reshape(n, -1)
    return np.max(violations, axis=1) if violations.shape[1] else np.full(n, -np.inf)


def _distinct_best(sampled: dict, count: int) -> list[np.ndarray]:
    """`count` start points from the samples, ranked feasible first by objective, then
    the others by violation: alternately the best not within `SPACING` of any chosen
    (spread over basins) and the best not within `SPACING / 10` (the best basin's
    neighbours), so that both a crowded best basin and a narrow one elsewhere are
    tried early."""
    if count == 0 or not len(sampled["z"]):
        return []
    ok = sampled["ok"].astype(bool) & np.isfinite(sampled["objective"])
    feasible = ok & (sampled["violation"] <= 0)
    key = np.where(feasible, 0, np.where(ok, 1, 2))
    order = np.lexsort((np.where(feasible, sampled["objective"], sampled["violation"]), key))
    order = order[key[order] < 2]
    chosen: list[np.ndarray] = []
    for spacing in [SPACING, SPACING / 10] * count:
        for i in order:
            z = sampled["z"][i]
            if all(np.max(np.abs(z - c)) > spacing for c in chosen):
                chosen.append(z)
                break
        if len(chosen) == count:
            break
    return chosen


def log_coordinates(lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Which parameters `search` moves in log coordinates: bounds positive and at
    least two decades apart."""
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    return (lower > 0) & (upper >= 1000 * np.where(lower > 0, lower, 1.0))


class _Box(eqx.Module):
    """`θ(z)` of normalised coordinates: linear or logarithmic per parameter."""

    lower: jax.Array
    upper: jax.Array
    log: jax.Array

    def theta(self, z):
        lo = jnp.where(self.log, jnp.log(jnp.where(self.log, self.lower, 1.0)), self.lower)
        hi = jnp.where(self.log, jnp.log(jnp.where(self.log, self.upper, 1.0)), self.upper)
        x = lo + (hi - lo) * z
        return jnp.where(self.log, jnp.exp(jnp.where(self.log, x, 0.0)), x)

    def z(self, theta) -> np.ndarray:
        lower, upper, log = (np.asarray(a) for a in (self.lower, self.upper, self.log))
        theta = np.clip(np.asarray(theta, float), lower, upper)
        safe = np.where(log, 1.0, upper - lower)
        linear = (theta - lower) / safe
        logged = np.log(np.where(log, theta, 1.0) / np.where(log, lower, 1.0)) / np.log(
            np.where(log, upper / np.where(log, lower, 1.0), np.e)
        )
        return np.clip(np.where(log, logged, linear), 0.0, 1.0)


_TRACES = [0]  # how many times the gradient program was traced (compiled)


@eqx.filter_jit
def _gradient_program(problem: DesignProblem, box: _Box, z, temperature, series_ts=None):
    """The smooth objective, the violations, their Jacobians, the exact objective and
    the status code at `z`: one sensitivity solve, reverse mode through the custom JVP
    (the Jacobian of all outputs from the one solve). One compilation per problem
    structure: re-running a study, or another seed, reuses it.

    With `series_ts` (`(n,)` save times), the objective comes as a minimax instead:
    `(1 + n,)` values, its peak then the weighted signal at each save time (NaN after
    the solve's end), with their Jacobian `(1 + n, P)` (forward mode: P columns)."""
    _TRACES[0] += 1
    if series_ts is not None:
        name = minimax_metric(problem)
        assert name is not None
        weight = problem.objective.weights[name]

        def minimax_outputs(z):
            metrics, status, _, exact, violations = evaluate_design(
                problem, box.theta(z), series=MetricSeries((name,), series_ts)
            )
            (code,) = jax.tree.leaves(status)
            peaks = weight * jnp.concatenate([metrics[name][None], metrics[series_name(name)]])
            values = jnp.concatenate([peaks, violations])
            return values, (values, exact, code)

        jacobian, (values, exact, code) = jax.jacfwd(minimax_outputs, has_aux=True)(z)
        n = series_ts.shape[0] + 1
        return values[:n], values[n:], jacobian[:n], jacobian[n:], exact, code

    def outputs(z):
        _, status, smooth, exact, violations = evaluate_design(
            problem, box.theta(z), temperature_scale=temperature
        )
        (code,) = jax.tree.leaves(status)
        values = jnp.concatenate([smooth[None], violations])
        return values, (values, exact, code)

    jacobian, (values, exact, code) = jax.jacrev(outputs, has_aux=True)(z)
    return values[0], values[1:], jacobian[0], jacobian[1:], exact, code


def minimax_metric(problem: DesignProblem) -> str | None:
    """The metric when `problem`'s objective is a positive multiple of one maximum over
    time (a metric with a `SmoothMax`), with no scatter: `search` then treats it as a
    minimax over time. Else None."""
    objective = problem.objective
    if objective.scatter is not None or len(objective.weights) != 1:
        return None
    ((name, weight),) = objective.weights.items()
    return name if weight > 0 and METRICS[name].smoothable else None


#: Save times of the minimax's series: the signal's maximum is levelled on this grid.
SERIES_POINTS = 1024

#: For SLSQP on the epigraph, the series is also saved at the times of the highest
#: local maxima of the signal at the run's previous point, each refined to the vertex
#: of the parabola through its samples. Near the optimum they sit on the peaks, so that
#: each competing maximum is its own smooth piece (at a maximum, the value and gradient
#: at a fixed time are the peak's own, by the envelope theorem), also for a peak
#: narrower than the grid, which the grid would see only through the located peak.
PEAK_TIMES = 64


def _local_maxima(ts: np.ndarray, values: np.ndarray, count: int, fill: float) -> np.ndarray:
    """The times `(count,)` of the `count` highest interior local maxima of a sampled
    signal (`ts` in any order, NaN values ignored), each refined to the vertex of the
    parabola through it and its neighbours; `fill` where there are fewer."""
    keep = np.isfinite(values)
    t, first = np.unique(ts[keep], return_index=True)  # sorted, each time once
    v = values[keep][first]
    out = np.full(count, fill)
    if t.size < 3:
        return out
    interior = np.nonzero((v[1:-1] >= v[:-2]) & (v[1:-1] > v[2:]))[0] + 1
    # The highest `count`, in time order (a slot keeps its peak while they persist).
    interior = np.sort(interior[np.argsort(-v[interior], kind="stable")][:count])
    t0, t1, t2 = t[interior - 1], t[interior], t[interior + 1]
    v0, v1, v2 = v[interior - 1], v[interior], v[interior + 1]
    # Vertex of the parabola through three points (unequal spacing).
    num = (t1 - t0) ** 2 * (v1 - v2) - (t1 - t2) ** 2 * (v1 - v0)
    den = (t1 - t0) * (v1 - v2) - (t1 - t2) * (v1 - v0)
    safe = np.abs(den) > 0
    vertex = t1 - 0.5 * num / np.where(safe, den, 1.0)
    vertex = np.where(safe & (vertex > t0) & (vertex < t2), vertex, t1)
    out[: vertex.size] = vertex
    return out


def search(
    problem: DesignProblem,
    *,
    samples: int = 1024,
    starts: int = 8,
    use_design: bool = True,
    schedule: Sequence[float] | None = None,
    minimax: bool | None = None,
    maxiter: int = 100,
    ftol: float = 1e-10,
    seed: int = 0,
    max_seconds: float | None = None,
    workers: int | None = None,
    progress: bool | None = None,
) -> MinimiseResult:
    """Minimise `problem.objective` subject to `problem.constraints` by global search
    plus gradient polish (`minimise`): `samples` Sobol designs over the bounds through
    the batched sweep, then SLSQP with exact gradients (forward sensitivities, error
    controlled) from the `starts` best distinct ones.

    **Arguments:**

    - `problem`: the `DesignProblem`; its objective's temperatures (if any) start the
      smooth-maximum continuation.
    - `samples`, `starts`, `maxiter`, `ftol`, `seed`, `max_seconds`, `progress`: as
      `minimise`.
    - `workers`: local runs at the same time (default `default_workers`: one per core
      on CPU, where one solve keeps about one core busy).
    - `use_design`: start one local run at the problem's base design (clipped to the
      bounds) besides the sampled ones.
    - `minimax`: when the objective is one peak over time (`minimax_metric`, e.g. the
      peak anchoring force), minimise it as a minimax (default: when that peak has a
      temperature, the study's sign that it jumps between local maxima): the
      local phase levels the signal at `SERIES_POINTS` times over the run (the run's
      length found at the first gradient solve) and at its located peak, each a smooth
      piece `F(t_k)` with its exact gradient from the one sensitivity solve. Without a
      temperature, trust-region linear programming from the samples (fast where the
      grid resolves every competing maximum); with one, a short smoothed level
      (`BASIN_MAXITER`) first finds the basin, then SLSQP on the epigraph
      `min s, F(t_k) <= s` (its curvature model passes over the kinks of peaks
      narrower than the grid), with `PEAK_TIMES` more pieces at the local maxima of
      the signal at the run's previous point; no further continuation.
    - `schedule`: without the minimax, the factors of the objective's temperatures, one
      SLSQP run each in turn (default `(1, 1/3, 1/9, 1/30)` when the objective has
      temperatures, else a single run on the peaks).

    **Returns:** `MinimiseResult` with `best_theta` and the `OptimiseResult` methods that
    studies use (`best_design`, `best_params`). Its objectives are exact (true peaks).

    **Raises:** `ParameterError` for bad arguments, before compiling.
    """
    if problem.objective.scatter is not None:
        raise ParameterError(
            "search does not take a scatter objective yet; use optimise for robust designs"
        )
    minimax_name = minimax_metric(problem)
    if minimax and minimax_name is None:
        raise ParameterError(
            "search: minimax needs an objective that is one peak over time "
            "(peak_anchoring_force or peak_displacement, positive weight, no scatter)"
        )
    if minimax is None:
        # By default where the study says the peak jumps between local maxima: it gave
        # the peak a temperature.
        minimax = minimax_name in problem.objective.temperatures
    minimax = bool(minimax)
    if minimax:
        # Smoothed first where the objective has a temperature: from a far start the
        # smooth maximum finds the basin, where the minimax (level 0) then levels the peaks.
        schedule = (1.0, 0.0) if problem.objective.temperatures else (0.0,)
    elif schedule is None:
        schedule = TEMPERATURE_SCHEDULE if problem.objective.temperatures else (1.0,)
    lower, upper = problem.box()
    box = _Box(jnp.asarray(lower), jnp.asarray(upper), jnp.asarray(log_coordinates(lower, upper)))
    base = params_to_values(problem.params)
    constraints = problem.metric_constraints
    ok_code = int(status_codes(Status.ok))

    def evaluate_batch(z):
        theta = np.asarray(jax.vmap(box.theta)(jnp.asarray(z)))
        designs = {k: np.full(len(z), float(v)) for k, v in base.items()}
        designs |= {name: theta[:, j] for j, name in enumerate(problem.tune)}
        result = sweep(
            designs, smoothing=problem.smoothing, options=problem.options, progress=False
        )
        metrics = result.peaks
        violations = np.stack(
            [
                (metrics[name] - limit if kind == "max" else limit - metrics[name])
                / (abs(limit) or 1.0)
                for name, kind, limit in constraints
            ]
            or [np.zeros(len(z))],
            axis=1,
        )[:, : len(constraints)]
        objective = np.asarray(problem.objective(metrics), dtype=float)
        return objective, violations, result.ok

    traces = _TRACES[0]

    window: list[np.ndarray] = []  # the minimax's save times, set at the first call
    window_lock = threading.Lock()

    def gradient_solve(z, level, series_ts=None):
        f, g, df, dg, exact, code = _gradient_program(
            problem, box, jnp.asarray(z), jnp.asarray(level, dtype=float), series_ts
        )
        return f, g, df, dg, float(exact), int(code) == ok_code

    def series_ts(z) -> np.ndarray:
        """Save times over the first design's run (from 0 to where its peaks were
        certain, plus a quarter): a later design's maximum outside them still counts,
        through the located peak."""
        with window_lock:
            if not window:
                t1 = float(np.max(np.asarray(end_time(problem.params, problem.options))))
                whole = np.linspace(0.0, t1, SERIES_POINTS)
                padded = np.concatenate([whole, np.full(peak_times, t1)])
                f = np.asarray(gradient_solve(z, 1.0, jnp.asarray(padded))[0])[1:]
                f = f[:SERIES_POINTS]
                written = np.nonzero(np.isfinite(f))[0]
                end = whole[written[-1]] if written.size else t1
                window.append(np.linspace(0.0, min(t1, 1.25 * end), SERIES_POINTS))
            return window[0]

    # The peaks' own save times, for SLSQP on the epigraph (where the study says the
    # peaks are narrow: it gave them a temperature); the trust-region LP keeps the grid.
    peak_times = PEAK_TIMES if len(schedule) > 1 else 0
    peaks_seen = threading.local()  # per local run (one per thread at a time)

    def new_run():
        peaks_seen.ts = None

    def value_and_jacobian(z, level):
        if level > 0:
            return gradient_solve(z, level)
        grid = series_ts(z)
        extra = getattr(peaks_seen, "ts", None)
        if extra is None:
            extra = np.full(peak_times, grid[-1])
        times = np.concatenate([grid, extra])
        # Saved in time order; returned in this order, so that each value keeps its
        # place (one constraint of SLSQP's each) from one point to the next.
        order = np.argsort(times, kind="stable")
        f, g, df, dg, exact, ok = gradient_solve(z, level, jnp.asarray(times[order]))
        f, df = np.array(f), np.array(df)
        f[1 + order], df[1 + order] = f[1:].copy(), df[1:].copy()
        if bool(ok) and peak_times:
            peaks_seen.ts = _local_maxima(times, f[1:], peak_times, grid[-1])
        # Save times after the solve's end (its peaks certain) are no constraint.
        after = ~np.isfinite(f)
        if np.any(np.isfinite(f)):
            f[after], df[after] = np.nanmin(f), 0.0
        return f, g, df, dg, exact, ok

    initial = []
    if use_design:
        initial.append(box.z(np.asarray(values_of(problem.params, problem.tune))))
    result = minimise(
        evaluate_batch,
        value_and_jacobian,
        len(problem.tune),
        samples=samples,
        starts=starts,
        initial=initial,
        schedule=tuple(schedule),
        maxiter=maxiter,
        ftol=ftol,
        seed=seed,
        max_seconds=max_seconds,
        workers=default_workers(jax.local_devices()) if workers is None else workers,
        progress=progress,
        new_run=new_run,
    )
    result.problem = problem
    result.gradient_solves += len(window)  # the solve that set the series' window
    result.compilations = _TRACES[0] - traces
    if result.feasible:
        result.best_theta = np.asarray(box.theta(jnp.asarray(result.best_z)))
    return result
