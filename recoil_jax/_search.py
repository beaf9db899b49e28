"""Global search plus gradient polish: space-filling samples through the batched
solver, then a local method with exact gradients from the best few of them.

- `minimise`: the method on any box-bounded problem with inequality constraints, given
  a batched evaluator (the global phase) and a value-and-Jacobian function (the local
  phase). Works in normalised coordinates `z ∈ [0, 1]^P`. The local method is an object
  the caller passes in (`SLSQP`, `EpigraphMinimax`, `TrustRegionLP`, see `_local.py`);
  `BasinHopping` spends what is left of a budget near the best point found.
- `search`: `minimise` on a `DesignProblem`. The global phase runs plain solves
  through `sweep`; the local phase differentiates `evaluate_design` through its custom
  JVP (one sensitivity solve per gradient, whatever the number of outputs). A peak that
  jumps between local maxima over time is minimised as a minimax of the signal at a
  thousand times, so that competing maxima are levelled together. The tuned parameters
  move in the problem's `SearchSpace` (log coordinates where the bounds span three
  decades or more: orifice areas).

Why SLSQP by default: it handles bounds and metric limits natively (no penalty to tune)
and converges superlinearly near a smooth optimum; each iteration costs one gradient
solve. Measured against the optax Adam loop of `optimise` in `optimise/README.md`.
"""

from __future__ import annotations

import os
import sys
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._cache import structure_jit
from ._gradients import MetricSeries, series_name
from ._local import (
    SLSQP,
    EpigraphMinimax,
    LocalEvaluation,
    LocalMethod,
    TrustRegionLP,
    run_local,
)
from ._metrics import METRICS
from ._params import (
    ParameterError,
    end_time,
    params_to_values,
    values_of,
)
from ._problem import DesignProblem, evaluate_design, feasible, metric_violations
from ._progress import Progress
from ._result import OptimiseResult
from ._space import SearchSpace
from ._status import Status, status_codes, status_messages
from ._store import StudyStore, fingerprint
from ._sweep import default_workers, sweep

__all__ = [
    "BasinHopping",
    "SobolStarts",
    "default_local",
    "minimax_metric",
    "minimise",
    "search",
]

#: Default continuation of the smooth-maximum temperatures: factors of the objective's.
TEMPERATURE_SCHEDULE = (1.0, 1 / 3, 1 / 9, 1 / 30)

#: Every other local run starts at least this far (max-norm, normalised coordinates)
#: from the others: the best samples crowd into the widest basin (measured on
#: `tuned_absorber` without a start, 8 starts all spaced so: 0.1 found the global
#: optimum in 8 of 10 seeds, 0.25 and 0.4 in 10 of 10).
SPACING = 0.25


class BasinHopping(eqx.Module):
    """Monotonic basin hopping after the starts: rounds of `workers` local runs at once,
    each from the best point found so far (the least violating while none is feasible)
    moved by a uniform random step of at most `step` per normalised coordinate, until
    `hops` runs are done or the time budget is spent. Each round starts from the best
    at its start, so a seeded run hops the same way whatever the threads' timing.

    The best basins of a narrow, rugged objective are found near the best one found so
    far more often than from another sample (measured on `burst_recuperator`: see
    `optimise/README.md`)."""

    hops: int = 32
    step: float = 0.05

    def __check_init__(self):
        if not self.hops >= 0 or not 0.0 < self.step <= 1.0:
            raise ParameterError(
                f"BasinHopping: need hops >= 0 and 0 < step <= 1 (got {self.hops}, {self.step})"
            )

    def run(self, record, local_run, pool, workers: int, seed: int, out_of_time) -> list[dict]:
        rng = np.random.default_rng([seed, 1])
        runs: list[dict] = []
        done = 0
        while done < self.hops and not out_of_time():
            centre = record.best_z if record.best_z is not None else record.closest_z
            if centre is None:
                break
            count = min(workers, self.hops - done)
            moves = rng.uniform(-self.step, self.step, (count, np.size(centre)))
            starts = [np.clip(centre + move, 0.0, 1.0) for move in moves]
            for run in pool.map(local_run, starts):
                runs.append(run | {"phase": "hop"})
            done += count
        return runs


class SobolStarts(eqx.Module):
    """The global phase of `minimise` and `search`: a scrambled Sobol sample of
    `samples` points of the box (rounded up to a power of 2; 0: none), solved in one
    batch, then `starts` local runs from the best distinct ones, ranked feasible first
    by objective, then the others by violation: alternately the best not within
    `spacing` (max-norm, normalised coordinates) of any chosen (spread over basins) and
    the best not within `spacing / 10` (the best basin's neighbours), so that both a
    crowded best basin and a narrow one elsewhere are tried early. Starts within
    `spacing` of one another count as one region in `OptimiseResult.agreement`."""

    samples: int = 1024
    starts: int = 8
    spacing: float = SPACING

    def __check_init__(self):
        if not (self.samples >= 0 and self.starts >= 0 and 0.0 < self.spacing <= 1.0):
            raise ParameterError(
                f"SobolStarts: need samples >= 0, starts >= 0 and 0 < spacing <= 1 (got "
                f"{self.samples}, {self.starts}, {self.spacing})"
            )

    @property
    def points(self) -> int:
        """How many points are sampled: `samples` rounded up to a power of 2."""
        return 0 if self.samples == 0 else int(2 ** np.ceil(np.log2(self.samples)))

    def sample(self, dimension: int, seed: int) -> np.ndarray:
        """`(points, dimension)`: the scrambled Sobol points of the unit box."""
        import scipy.stats

        sobol = scipy.stats.qmc.Sobol(dimension, scramble=True, rng=np.random.default_rng(seed))
        return sobol.random(self.points)

    def choose(self, sampled: dict[str, np.ndarray]) -> list[np.ndarray]:
        """The start points (up to `starts`) from the evaluated samples (`z`,
        `objective`, `violation`, `ok`)."""
        if self.starts == 0 or not len(sampled["z"]):
            return []
        ok = sampled["ok"].astype(bool) & np.isfinite(sampled["objective"])
        held = feasible(ok, sampled["objective"], sampled["violation"][:, None])
        key = np.where(held, 0, np.where(ok, 1, 2))
        order = np.lexsort((np.where(held, sampled["objective"], sampled["violation"]), key))
        order = order[key[order] < 2]
        chosen: list[np.ndarray] = []
        for spacing in [self.spacing, self.spacing / 10] * self.starts:
            for i in order:
                z = sampled["z"][i]
                if all(np.max(np.abs(z - c)) > spacing for c in chosen):
                    chosen.append(z)
                    break
            if len(chosen) == self.starts:
                break
        return chosen


class _Minimum(NamedTuple):
    """What `_minimise` found, in normalised coordinates: the best feasible point
    (`best_z`, NaN if none), the least violating one, every evaluation (`trace`), the
    global phase (`samples`) and each local run (`run_local`'s dicts with `phase`,
    `evaluations`, `best_feasible`, `best_z`)."""

    best_z: np.ndarray
    best_objective: float
    closest_z: np.ndarray
    closest_violation: float
    trace: dict[str, np.ndarray]
    samples: dict[str, np.ndarray]
    runs: list[dict]
    solves: int
    gradient_solves: int
    seconds: float
    spacing: float  # the global phase's: starts this close are one region


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
        self.closest_z, self.closest = None, np.inf  # the least worst violation
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
            held = bool(feasible(good, f, [v]))
            for key, value in zip(self.rows, (now, float(f), held, gradient, phase), strict=True):
                self.rows[key].append(value)
            if held and f < self.best:
                self.best, self.best_z = float(f), np.array(zi, dtype=float)
            if bool(good) and np.isfinite(f) and v < self.closest:
                self.closest, self.closest_z = float(v), np.array(zi, dtype=float)
        self.count += int(np.size(objective))
        best = f"{self.best:.7g}" if np.isfinite(self.best) else "none feasible yet"
        self.bar.update(min(self.count, self.bar.total - 1), f"best feasible objective {best}")


def minimise(
    evaluate_batch: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]],
    value_and_jacobian: Callable[[np.ndarray, float], Any],
    dimension: int,
    *,
    local: LocalMethod | None = None,
    global_phase: SobolStarts | None = None,
    initial: Sequence[np.ndarray] = (),
    hopping: BasinHopping | None = None,
    seed: int = 0,
    max_seconds: float | None = None,
    workers: int = 1,
    progress: bool | None = None,
    label: str = "search",
    run_evaluator: Callable[[], Callable[[np.ndarray, float], Any]] | None = None,
    spent: Callable[[], float] | None = None,
) -> OptimiseResult:
    """Minimise `f(z)` subject to `g(z) <= 0` over the unit box `z ∈ [0, 1]^P`: a scrambled
    Sobol sample of the box, then a local method from the best few distinct points.

    **Arguments:**

    - `evaluate_batch(z)`: `z (n, P)` → `(objective (n,), violations (n, C), ok (n,))`:
      the exact objective, the normalised constraint values (`<= 0` when held) and whether
      the evaluation succeeded.
    - `value_and_jacobian(z, level)`: `z (P,)` → a `LocalEvaluation` (or the same
      6-tuple; with `run_evaluator`, only the warm-up's): the smoothed objective the
      local method minimises at continuation `level` (one of `local.levels`), its
      constraints, their Jacobians, the exact objective at `z`, and whether the
      evaluation succeeded. At level 0 (a minimax method) `f` is a vector `(K,)` with
      `df (K, P)`: the objective is its maximum.
    - `dimension`: `P`.
    - `local`: the local method, a `LocalMethod` with its own settings (default
      `SLSQP()`): `SLSQP`, `EpigraphMinimax`, `TrustRegionLP`, or one of your own.
    - `global_phase`: the samples and the starts chosen from them, an object with its
      own settings (default `SobolStarts()`: 1024 Sobol points, 8 starts); `initial`
      points (e.g. a given design) start local runs first.
    - `hopping`: after the starts, more local runs from the best point so far,
      perturbed (`BasinHopping`); None: none.
    - `max_seconds`: a wall-time budget: once spent, no further gradient solve starts
      and the best point so far is returned.
    - `workers`: local runs at the same time, each from its own thread (the given
      starts run while the global phase samples).
    - `progress`: a progress line with the best feasible objective (default: on a
      terminal).
    - `run_evaluator()`: called at the start of each local run, returns that run's own
      `value_and_jacobian`, with state of its own (`search`'s minimax adds the signal's
      local maxima at the run's previous point). Default: `value_and_jacobian` for
      every run.
    - `spent()`: the seconds of the `max_seconds` budget spent so far (default: since
      this call; a resumed study adds the earlier runs').

    **Returns:** `OptimiseResult` (`method` `"minimise"`, one scenario, `θ = z`).
    """
    minimum = _minimise(
        evaluate_batch, value_and_jacobian, dimension, local=local, global_phase=global_phase,
        initial=initial, hopping=hopping, seed=seed, max_seconds=max_seconds, workers=workers,
        progress=progress, label=label, run_evaluator=run_evaluator, spent=spent,
    )  # fmt: skip
    return _result(minimum, "minimise", None, lambda z: np.asarray(z, dtype=float))


def _minimise(
    evaluate_batch, value_and_jacobian, dimension: int, *, local, global_phase, initial,
    hopping, seed, max_seconds, workers, progress, label, run_evaluator, spent,
) -> _Minimum:  # fmt: skip
    """`minimise`, in normalised coordinates."""
    local = SLSQP() if local is None else local
    global_phase = SobolStarts() if global_phase is None else global_phase
    if not isinstance(local, LocalMethod):
        raise ParameterError(f"minimise: local must be a LocalMethod, got {local!r}")
    if not isinstance(global_phase, SobolStarts):
        raise ParameterError(f"minimise: global_phase must be a SobolStarts, got {global_phase!r}")
    if dimension < 1:
        raise ParameterError(f"minimise: need dimension >= 1 (got {dimension})")
    initial = [np.clip(np.asarray(z, dtype=float), 0.0, 1.0) for z in initial]
    n_samples = global_phase.points
    levels = local.levels
    runs = global_phase.starts + len(initial) + (0 if hopping is None else hopping.hops)
    budget = n_samples + len(initial) + runs * len(levels) * local.maxiter
    bar = Progress(label, budget, "solves", progress)
    record = _Recorder(bar)

    def out_of_time() -> bool:
        used = spent() if spent is not None else time.perf_counter() - record.start
        return max_seconds is not None and used > max_seconds

    def clock() -> float:
        return time.perf_counter() - record.start

    def record_local(z, objective, violation, ok):
        record.add(z, objective, violation, ok, True, "local")

    def warm_up():
        centre = np.full(dimension, 0.5)
        _, g, _, _, exact, ok = value_and_jacobian(centre, levels[0])
        record.add(centre, exact, _worst(np.asarray(g)[None], 1), ok, True, "local")

    def local_run(z0):
        evaluate = value_and_jacobian if run_evaluator is None else run_evaluator()
        seen = {"evaluations": 0, "best_feasible": np.inf, "best_z": None}  # this run's

        def record_run(z, objective, violation, ok):
            record_local(z, objective, violation, ok)
            seen["evaluations"] += 1
            if feasible(ok, objective, [violation]) and objective < seen["best_feasible"]:
                seen["best_feasible"], seen["best_z"] = float(objective), np.array(z)

        run = run_local(local, evaluate, z0, record_run, out_of_time, clock)
        return run | {"phase": "start"} | seen

    # Given starts first (a design known to be good is polished at once), then the
    # global phase: one batch through the batched solver, and the best distinct samples.
    with ThreadPoolExecutor(max(1, workers)) as pool:
        given = [pool.submit(local_run, z0) for z0 in initial]
        if not given and global_phase.starts:
            # Compile the gradient program while the global phase samples: one
            # gradient solve at the centre of the box, recorded like the others.
            given_warmup = pool.submit(warm_up)
        else:
            given_warmup = None
        if n_samples and not out_of_time():
            z = global_phase.sample(dimension, seed)
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
        sampled_runs = pool.map(local_run, global_phase.choose(sampled))
        runs = [future.result() for future in given] + list(sampled_runs)
        if given_warmup is not None:
            given_warmup.result()
        if hopping is not None:
            runs += hopping.run(record, local_run, pool, max(1, workers), seed, out_of_time)
    bar.update(bar.total, _best_note(record.best), final=True)
    trace = {k: np.asarray(v) for k, v in record.rows.items()}
    nowhere = np.full(dimension, np.nan)
    return _Minimum(
        best_z=nowhere if record.best_z is None else np.asarray(record.best_z),
        best_objective=record.best if record.best_z is not None else np.nan,
        closest_z=nowhere if record.closest_z is None else np.asarray(record.closest_z),
        closest_violation=float(record.closest) if record.closest_z is not None else np.nan,
        trace=trace,
        samples=sampled,
        runs=runs,
        solves=n_samples,
        gradient_solves=record.gradient_solves,
        seconds=time.perf_counter() - record.start,
        spacing=global_phase.spacing,
    )


def _regions(runs: list[dict], spacing: float) -> list[int | None]:
    """The start region of each run: a start that evaluated a point joins the first
    region whose first start is within `spacing` (max-norm) of its own, or begins a
    new one; basin hopping's runs and those that evaluated nothing have none."""
    firsts: list[np.ndarray] = []
    regions: list[int | None] = []
    for run in runs:
        if run["phase"] != "start" or run["evaluations"] == 0:
            regions.append(None)
            continue
        near = [k for k, first in enumerate(firsts) if np.max(np.abs(run["z0"] - first)) <= spacing]
        if not near:
            firsts.append(run["z0"])
        regions.append(near[0] if near else len(firsts) - 1)
    return regions


def _result(
    minimum: _Minimum,
    method: str,
    problem: DesignProblem | None,
    theta: Callable[[np.ndarray], np.ndarray],
    *,
    extra_gradient_solves: int = 0,
    compilations: int = 0,
    replayed: int = 0,
) -> OptimiseResult:
    """The `OptimiseResult` of a `_minimise` run, its points mapped to parameter values by
    `theta` (NaN stays NaN)."""

    def to_theta(z) -> np.ndarray:
        z = np.asarray(z, dtype=float)
        return np.asarray(theta(z)) if np.all(np.isfinite(z)) else np.full(z.shape, np.nan)

    runs = []
    for run, region in zip(minimum.runs, _regions(minimum.runs, minimum.spacing), strict=True):
        best_z = run["z0"] * np.nan if run["best_z"] is None else run["best_z"]
        runs.append(
            {
                "scenario": 0,
                "region": region,
                "phase": run["phase"],
                "theta0": to_theta(run["z0"]),
                "theta": to_theta(run["z"]),
                "objective": float(run["objective"]),
                "best_objective": float(run["best_feasible"]),
                "best_theta": to_theta(best_z),
                "evaluations": run["evaluations"],
                "iterations": run["iterations"],
                "converged": run["converged"],
                "message": run["message"],
                "seconds": run["seconds"],
            }
        )
    trace = minimum.trace | {"scenario": np.zeros(len(minimum.trace["seconds"]), dtype=int)}
    limits = [] if problem is None else [limit for _, _, limit in problem.metric_constraints]
    return OptimiseResult(
        method=method,
        problem=problem,
        best_theta=to_theta(minimum.best_z)[None],
        best_objective=np.array([minimum.best_objective]),
        closest_theta=to_theta(minimum.closest_z)[None],
        closest_violation=np.array([minimum.closest_violation]),
        runs=tuple(runs),
        trace=trace,
        solves=minimum.solves,
        gradient_solves=minimum.gradient_solves + extra_gradient_solves,
        seconds=minimum.seconds,
        compilations=compilations,
        scenario_params=(
            None if problem is None else jax.tree.map(lambda x: np.asarray(x)[None], problem.params)
        ),
        scenario_limits=np.asarray([limits], dtype=float).reshape(1, len(limits)),
        samples=minimum.samples,
        replayed=replayed,
    )


def _best_note(best: float) -> str:
    return f"best feasible objective {best:.7g}" if np.isfinite(best) else "nothing feasible"


def _worst(violations, n: int) -> np.ndarray:
    violations = np.asarray(violations, dtype=float).reshape(n, -1)
    return np.max(violations, axis=1) if violations.shape[1] else np.full(n, -np.inf)


_TRACES = [0]  # how many times the gradient program was traced (compiled)


class _GradientSolve(NamedTuple):
    """`_gradient_program`'s outputs: `LocalEvaluation`'s, with the solve's integer
    `Status` code in place of `ok`."""

    f: Any
    g: Any
    df: Any
    dg: Any
    objective: Any
    status_code: Any


@structure_jit
def _gradient_program(problem: DesignProblem, box: SearchSpace, z, temperature, series_ts=None):
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
            evaluation = evaluate_design(
                problem, box.theta(z), series=MetricSeries((name,), series_ts)
            )
            metrics = evaluation.metrics
            peaks = weight * jnp.concatenate([metrics[name][None], metrics[series_name(name)]])
            values = jnp.concatenate([peaks, evaluation.violations])
            return values, (values, evaluation)

        jacobian, (values, evaluation) = jax.jacfwd(minimax_outputs, has_aux=True)(z)
        n = series_ts.shape[0] + 1
        f, df = values[:n], jacobian[:n]
    else:

        def outputs(z):
            evaluation = evaluate_design(problem, box.theta(z), temperature_scale=temperature)
            values = jnp.concatenate([evaluation.smooth_objective[None], evaluation.violations])
            return values, (values, evaluation)

        jacobian, (values, evaluation) = jax.jacrev(outputs, has_aux=True)(z)
        n = 1
        f, df = values[0], jacobian[0]
    (code,) = jax.tree.leaves(evaluation.status)
    return _GradientSolve(f, values[n:], df, jacobian[n:], evaluation.objective, code)


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


def default_local(problem: DesignProblem, minimax: bool | None = None) -> LocalMethod:
    """The local method `search` uses for `problem` when none is given.

    - `minimax` (default: when the objective's one peak over time has a temperature, the
      study's sign that it jumps between local maxima): with a temperature
      `EpigraphMinimax()`, without one `TrustRegionLP()`;
    - otherwise `SLSQP` through the continuation `TEMPERATURE_SCHEDULE` of the
      objective's temperatures (a single level on the peaks when it has none).
    """
    name = minimax_metric(problem)
    if minimax is None:
        minimax = name in problem.objective.temperatures
    if minimax:
        # Smoothed first where the objective has a temperature: from a far start the
        # smooth maximum finds the basin, where the minimax (level 0) then levels the peaks.
        return EpigraphMinimax() if problem.objective.temperatures else TrustRegionLP()
    return SLSQP(schedule=TEMPERATURE_SCHEDULE if problem.objective.temperatures else (1.0,))


def search(
    problem: DesignProblem,
    *,
    local: LocalMethod | None = None,
    minimax: bool | None = None,
    global_phase: SobolStarts | None = None,
    use_design: bool = True,
    hopping: BasinHopping | None = None,
    seed: int = 0,
    max_seconds: float | None = None,
    workers: int | None = None,
    progress: bool | None = None,
    store: str | os.PathLike | None = None,
    client: Any = None,
) -> OptimiseResult:
    """Minimise `problem.objective` subject to `problem.constraints` by global search
    plus gradient polish (`minimise`): the global phase's Sobol designs over the bounds
    through the batched sweep, then a local method with exact gradients (forward
    sensitivities, error controlled) from its best distinct ones.

    **Arguments:**

    - `problem`: the `DesignProblem`; its objective's temperatures (if any) are the
      smooth maxima's at continuation level 1.
    - `local`: the local method (default `default_local(problem, minimax)`): `SLSQP`
      (the smoothed objective through a continuation of temperatures),
      `EpigraphMinimax` or `TrustRegionLP` (the minimax below), or your own
      `LocalMethod`.
    - `minimax`: which default to take, when `local` is not given.
    - `global_phase`, `hopping`, `seed`, `max_seconds`, `progress`: as `minimise`
      (default `SobolStarts()`: 1024 designs, 8 starts).
    - `workers`: local runs at the same time (default `default_workers`: one per core
      on CPU, where one solve keeps about one core busy).
    - `use_design`: start one local run at the problem's base design (clipped to the
      bounds) besides the sampled ones.
    - `store`: the path of an SQLite file that keeps every evaluation as it is made
      (`docs/campaigns.md`). Running the same search with the same store resumes a
      stopped one: stored evaluations are read back bit for bit, not solved, so a
      seeded search retraces its path and ends at the same best design. A store made by
      another search is refused with `ParameterError`. `max_seconds` counts the time of
      the earlier runs; `workers` is the store's (it sets how basin hopping proceeds).
    - `client`: a `dask.distributed.Client`: the global phase's sweep runs its chunks
      on the cluster (`sweep`'s `client`).

    A minimax (level 0 of `EpigraphMinimax` and `TrustRegionLP`) needs an objective that
    is one peak over time (`minimax_metric`, e.g. the peak anchoring force): the local
    phase levels the signal at `SERIES_POINTS` times over the run (the run's length
    found at the first gradient solve) and at its located peak, each a smooth piece
    `F(t_k)` with its exact gradient from the one sensitivity solve, and for
    `EpigraphMinimax` at the `peak_times` highest local maxima of the signal at the
    run's previous point.

    Parameters whose bounds are positive and at least a factor 1000 apart are searched
    in log coordinates (`SearchSpace`).

    **Returns:** `OptimiseResult` (`method` `"search"`, one scenario). Its objectives are
    exact (true peaks).

    **Raises:** `ParameterError` for bad arguments, before compiling.
    """
    if problem.objective.scatter is not None:
        raise ParameterError(
            "search does not take a scatter objective yet; use optimise for robust designs"
        )
    if local is not None and minimax is not None and bool(minimax) != local.minimax:
        raise ParameterError(
            f"search: minimax = {minimax} contradicts local = {type(local).__name__}"
        )
    local = default_local(problem, minimax) if local is None else local
    if not isinstance(local, LocalMethod):
        raise ParameterError(f"search: local must be a LocalMethod, got {local!r}")
    global_phase = SobolStarts() if global_phase is None else global_phase
    if not isinstance(global_phase, SobolStarts):
        raise ParameterError(f"search: global_phase must be a SobolStarts, got {global_phase!r}")
    if local.minimax and minimax_metric(problem) is None:
        raise ParameterError(
            "search: minimax needs an objective that is one peak over time "
            "(peak_anchoring_force or peak_displacement, positive weight, no scatter)"
        )
    box = SearchSpace.of(problem)
    base = params_to_values(problem.params)
    ok_code = int(status_codes(Status.ok))
    workers = default_workers(jax.local_devices()) if workers is None else workers
    study = None
    if store is not None:
        study = _open_study_store(
            store, problem, local, hopping, global_phase, use_design, seed, workers, progress
        )
        workers = int(study.plan["workers"])
    began = time.perf_counter()

    def spent() -> float:
        """Seconds of the time budget spent, the earlier runs' included."""
        return (study.prior_seconds if study else 0.0) + time.perf_counter() - began

    def solve_batch(z):
        theta = np.asarray(jax.vmap(box.theta)(jnp.asarray(z)))
        designs = {k: np.full(len(z), float(v)) for k, v in base.items()}
        designs |= {name: theta[:, j] for j, name in enumerate(problem.tune)}
        result = sweep(
            designs,
            smoothing=problem.smoothing,
            options=problem.options,
            progress=False,
            client=client,
        )
        metrics = result.peaks
        objective = np.asarray(problem.objective(metrics), dtype=float)
        violations = np.asarray(metric_violations(problem, metrics), dtype=float)
        return theta, objective, violations.reshape(len(z), -1), status_codes(result.status)

    def evaluate_batch(z):
        if study is None:
            _, objective, violations, codes = solve_batch(z)
            return objective, violations, codes == ok_code
        keys = [fingerprint("sample", row) for row in z]
        stored = [study.stored(key) for key in keys]
        todo = np.asarray([i for i, out in enumerate(stored) if out is None], dtype=int)
        objective = np.zeros(len(z))
        violations = np.zeros((len(z), len(problem.metric_constraints)))
        codes = np.zeros(len(z), dtype=np.int32)
        for i, out in enumerate(stored):
            if out is not None:
                objective[i], violations[i], codes[i] = (
                    out["objective"],
                    out["violations"],
                    out["code"],
                )
        if todo.size:
            theta, objective[todo], violations[todo], codes[todo] = solve_batch(z[todo])
            held = feasible(codes[todo] == ok_code, objective[todo], violations[todo])
            messages = status_messages(codes[todo])
            study.commit(
                [
                    {
                        "seconds": spent(), "phase": "sample", "theta": theta[j],
                        "objective": objective[i], "violations": violations[i],
                        "feasible": held[j], "status": messages[j], "status_code": codes[i],
                        "key": keys[i],
                        "outputs": {
                            "objective": objective[i], "violations": violations[i],
                            "code": codes[i],
                        },
                    }
                    for j, i in enumerate(todo.tolist())
                ]
            )  # fmt: skip
        return objective, violations, codes == ok_code

    traces = _TRACES[0]

    window: list[np.ndarray] = []  # the minimax's save times, set at the first call
    window_lock = threading.Lock()

    def gradient_solve(z, level, series_ts=None):
        if study is None:
            solve = _gradient_program(
                problem, box, jnp.asarray(z), jnp.asarray(level, dtype=float), series_ts
            )
            ok = int(solve.status_code) == ok_code
            return LocalEvaluation(solve.f, solve.g, solve.df, solve.dg, float(solve.objective), ok)
        z = np.asarray(z, dtype=float)
        times = () if series_ts is None else np.asarray(series_ts)
        key = fingerprint("gradient", z, np.asarray(level, dtype=float), times)
        out = study.stored(key)
        if out is None:
            solve = _gradient_program(
                problem, box, jnp.asarray(z), jnp.asarray(level, dtype=float), series_ts
            )
            # The store's names for the outputs (stores written before keep resuming).
            names = ("f", "g", "df", "dg", "exact", "code")
            out = dict(zip(names, map(np.asarray, solve), strict=True))
            code = int(out["code"])
            study.commit(
                [
                    {
                        "seconds": spent(), "phase": "local",
                        "theta": np.asarray(box.theta(jnp.asarray(z))),
                        "objective": out["exact"], "violations": out["g"],
                        "feasible": feasible(code == ok_code, out["exact"], out["g"]),
                        "status": status_messages(np.asarray([code]))[0],
                        "status_code": code, "key": key, "outputs": out,
                    }
                ]
            )  # fmt: skip
        f, g, df, dg = out["f"], out["g"], out["df"], out["dg"]
        return LocalEvaluation(f, g, df, dg, float(out["exact"]), int(out["code"]) == ok_code)

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

    # The peaks' own save times, as many as the local method asks for (EpigraphMinimax:
    # the study says the peaks are narrow, it gave them a temperature).
    peak_times = local.peak_times

    def run_evaluator():
        """One local run's `value_and_jacobian`: at level 0 the minimax's pieces are the
        signal on the grid and at the local maxima of the run's previous point."""
        previous_maxima: list[np.ndarray] = []  # this run's, at its last good solve

        def value_and_jacobian(z, level):
            if level > 0:
                return gradient_solve(z, level)
            grid = series_ts(z)
            extra = previous_maxima[-1] if previous_maxima else np.full(peak_times, grid[-1])
            times = np.concatenate([grid, extra])
            # Saved in time order; returned in this order, so that each value keeps its
            # place (one constraint of SLSQP's each) from one point to the next.
            order = np.argsort(times, kind="stable")
            f, g, df, dg, exact, ok = gradient_solve(z, level, jnp.asarray(times[order]))
            f, df = np.array(f), np.array(df)
            f[1 + order], df[1 + order] = f[1:].copy(), df[1:].copy()
            if bool(ok) and peak_times:
                previous_maxima[:] = [_local_maxima(times, f[1:], peak_times, grid[-1])]
            # Save times after the solve's end (its peaks certain) are no constraint.
            after = ~np.isfinite(f)
            if np.any(np.isfinite(f)):
                f[after], df[after] = np.nanmin(f), 0.0
            return LocalEvaluation(f, g, df, dg, exact, ok)

        return value_and_jacobian

    initial = []
    if use_design:
        initial.append(box.z(np.asarray(values_of(problem.params, problem.tune))))
    try:
        minimum = _minimise(
            evaluate_batch,
            run_evaluator(),  # the warm-up's
            len(problem.tune),
            local=local,
            global_phase=global_phase,
            initial=initial,
            hopping=hopping,
            seed=seed,
            max_seconds=max_seconds,
            workers=workers,
            progress=progress,
            label="search",
            run_evaluator=run_evaluator,
            spent=spent,
        )
    finally:
        if study is not None:
            study.close()
    return _result(
        minimum,
        "search",
        problem,
        lambda z: np.asarray(box.theta(jnp.asarray(z))),
        extra_gradient_solves=len(window),  # the window's solve
        compilations=_TRACES[0] - traces,
        replayed=0 if study is None else study.replayed,
    )


def _open_study_store(
    path, problem, local, hopping, global_phase, use_design, seed, workers, progress
) -> StudyStore:
    """The store at `path` for this search (created, or checked to be this search's);
    its plan's `workers` replaces `workers`."""
    from . import __version__

    identity = fingerprint(
        "search", __version__, problem, local, hopping, global_phase.samples,
        global_phase.starts, use_design, seed,
        # (the spacing only when it is not the default: stores made before it was a
        # setting keep resuming)
        *([] if global_phase.spacing == SPACING else [global_phase.spacing]),
    )  # fmt: skip
    runs = global_phase.starts + int(use_design) + (0 if hopping is None else hopping.hops)
    n_samples = global_phase.points
    study = StudyStore(
        path,
        identity=identity,
        total=n_samples + runs * len(local.levels) * local.maxiter,
        plan={"workers": int(workers)},
        tune=problem.tune,
        limits=[(name, kind) for name, kind, _ in problem.metric_constraints],
        description={
            "study": "search",
            "tune": list(problem.tune),
            "local": type(local).__name__,
            "seed": seed,
            "created": time.strftime("%Y-%m-%d %H:%M:%S"),
        },
    )
    if progress is not False:
        if study.stored_count:
            print(
                f"search: resuming from {path}: {study.stored_count} evaluations stored "
                f"(read back, not solved), {study.prior_seconds:.1f} s of the budget spent",
                file=sys.stderr,
            )
        if study.plan["workers"] != workers:
            print(
                f"search: {study.plan['workers']} local runs at once, as in the run that "
                f"made {path} (not {workers}): basin hopping proceeds the same way",
                file=sys.stderr,
            )
    return study
