"""Global search plus gradient polish: space-filling samples through the batched
solver, then a local method with exact gradients from the best few of them.

- `minimise`: the method on any box-bounded problem with inequality constraints, given
  a batched evaluator (the global phase) and a value-and-Jacobian function (the local
  phase). Works in normalised coordinates `z ∈ [0, 1]^P`. The local method is an object
  the caller passes in (`SLSQP`, `EpigraphMinimax`, `TrustRegionLP`, see `local.py`);
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

import abc
import contextlib
import dataclasses
import itertools
import os
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING, Any, NamedTuple, final

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._campaigns.opener import open_study
from .._campaigns.progress import Progress
from .._campaigns.store import StudyStore, campaign_identity
from .._design.evaluators import (
    BatchEvaluation,
    BatchEvaluator,
    GradientEvaluator,
    MinimaxEvaluator,
    MinimaxWindow,
    StoredEvaluator,
    gradient_traces,
    minimax_metric,
)
from .._design.local import (
    SLSQP,
    EpigraphMinimax,
    LocalMethod,
    TrustRegionLP,
    run_local,
    store_form,
)
from .._design.problem import DesignProblem
from .._design.result import Found, OptimiseResult, RunRecord, build_result
from .._model.feasibility import (
    best_feasible_note,
    closest_index,
    feasible,
    largest_violation,
)
from .._model.params import values_of
from .._model.registry import ParameterError
from .._sweeps.memory import check_memory, default_workers
from .._sweeps.space import SearchSpace

__all__ = [
    "BasinHopping",
    "GlobalPhase",
    "SobolStarts",
    "default_local",
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

    def run(self, record, local_run, pool, workers: int, seed: int, out_of_time) -> list[RunRecord]:
        rng = np.random.default_rng([seed, 1])
        runs: list[RunRecord] = []
        done = 0
        while done < self.hops and not out_of_time():
            centre = record.best_z if record.best_z is not None else record.closest_z
            if centre is None:
                break
            count = min(workers, self.hops - done)
            moves = rng.uniform(-self.step, self.step, (count, np.size(centre)))
            starts = [np.clip(centre + move, 0.0, 1.0) for move in moves]
            for run in pool.map(local_run, starts):
                runs.append(dataclasses.replace(run, phase="hop"))
            done += count
        return runs


class GlobalPhase(eqx.Module):
    """The global phase of `minimise` and `search` (abstract): the points of the unit box
    evaluated in one batch, then the starts of the local runs chosen from them.

    - `sample(dimension, seed)`: `(points, dimension)` points of `[0, 1]^dimension`;
    - `choose(sampled)`: the start points (at most `starts`) from the evaluated samples
      (`z`, `objective`, `violation` (largest), `ok`);
    - `points`, and the fields `starts` and `spacing` every phase has: how many points
      and starts (the progress line's budget), and the distance (max-norm) within which
      starts count as one region in `OptimiseResult.agreement`.
    """

    if TYPE_CHECKING:  # every phase's fields (not declared here: they keep their order)
        starts: int
        spacing: float

    @property
    @abc.abstractmethod
    def points(self) -> int: ...

    @abc.abstractmethod
    def sample(self, dimension: int, seed: int) -> np.ndarray: ...

    @abc.abstractmethod
    def choose(self, sampled: dict[str, np.ndarray]) -> list[np.ndarray]: ...


@final
class SobolStarts(GlobalPhase):
    """The default global phase of `minimise` and `search`: a scrambled Sobol sample of
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
        # Each sample's point, its solve's results and its evaluation's record (up to 40
        # tuned values and 64 outputs, a few copies, and the record's Python objects).
        check_memory(
            self.points, 8 * 3 * (40 + 64) + 1024, "a global phase", "give fewer samples",
            unit="samples",
        )  # fmt: skip

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
        # (At most one start a sample: the alternation is no longer than that.)
        tries = 2 * min(self.starts, len(order))
        for spacing in itertools.islice(itertools.cycle((self.spacing, self.spacing / 10)), tries):
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
    global phase (`samples`) and each local run (`RunRecord`s in normalised
    coordinates)."""

    best_z: np.ndarray
    best_objective: float
    closest_z: np.ndarray
    closest_violation: float
    trace: dict[str, np.ndarray]
    samples: dict[str, np.ndarray]
    runs: list[RunRecord]
    solves: int
    gradient_solves: int
    seconds: float
    spacing: float  # the global phase's: starts this close are one region


class _Recorder:
    """Every evaluation, in order, with the best feasible point and the least violating
    one so far (`add` is called from the local runs' threads)."""

    def __init__(self, bar: Progress, budget_clock: Callable[[], float] | None = None):
        self.bar, self.start = bar, time.perf_counter()
        self._budget_clock = budget_clock
        self.lock = threading.Lock()
        self.gradient_solves = 0
        self.rows: dict[str, list] = {
            k: [] for k in ("seconds", "objective", "feasible", "gradient", "phase")
        }
        self.best_z, self.best = None, np.inf
        self.closest_z, self.closest = None, np.inf  # the least worst violation
        self.count = 0

    def clock(self) -> float:
        """Seconds of the time budget: since this run began, or `budget_clock()` (a
        resumed study's, the earlier runs' included). The trace's and runs' seconds."""
        if self._budget_clock is not None:
            return self._budget_clock()
        return time.perf_counter() - self.start

    def add(self, z, objective, violation, ok, gradient: bool, phase: str):
        """Record evaluations: `z (n, P)` or `(P,)`, with their exact objectives, largest
        violations and whether their solves succeeded."""
        z = np.atleast_2d(np.asarray(z, dtype=float))
        objective, violation = np.atleast_1d(objective), np.atleast_1d(violation)
        if not objective.size:  # a global phase that sampled nothing
            return
        held = feasible(np.atleast_1d(ok), objective, violation[:, None])
        with self.lock:
            now = self.clock()
            self.gradient_solves += int(gradient)
            n = len(objective)
            for key, values in zip(
                self.rows, ([now] * n, objective.tolist(), held.tolist(), [gradient] * n,
                            [phase] * n), strict=True
            ):  # fmt: skip
                self.rows[key].extend(values)
            best = np.where(held, objective, np.inf)
            if np.min(best) < self.best:
                i = int(np.argmin(best))
                self.best, self.best_z = float(objective[i]), z[i].copy()
            i = closest_index(np.atleast_1d(ok), objective, violation)
            if i is not None and violation[i] < self.closest:
                self.closest, self.closest_z = float(violation[i]), z[i].copy()
            self.count += n
            self.bar.update(min(self.count, self.bar.total - 1), best_feasible_note(self.best))

    def minimum(self, samples, runs, solves: int, spacing: float) -> _Minimum:
        """What the run found (`_Minimum`), once every phase has ended."""
        self.bar.update(self.bar.total, best_feasible_note(self.best), final=True)
        nowhere = np.full(samples["z"].shape[1], np.nan)
        return _Minimum(
            best_z=nowhere if self.best_z is None else self.best_z,
            best_objective=self.best if self.best_z is not None else np.nan,
            closest_z=nowhere if self.closest_z is None else self.closest_z,
            closest_violation=float(self.closest) if self.closest_z is not None else np.nan,
            trace={k: np.asarray(v) for k, v in self.rows.items()},
            samples=samples,
            runs=runs,
            solves=solves,
            gradient_solves=self.gradient_solves,
            seconds=time.perf_counter() - self.start,
            spacing=spacing,
        )


class _LocalRunner:
    """Runs one local run of `method` from a start (`__call__(z0)`: its `RunRecord`, in
    normalised coordinates), each with its own evaluator from `evaluator()`, recording
    every evaluation."""

    def __init__(self, method: LocalMethod, evaluator, record: _Recorder, out_of_time):
        self.method, self.evaluator, self.record = method, evaluator, record
        self.out_of_time = out_of_time

    def _record_local(self, z, objective, violation, ok) -> None:
        self.record.add(z, objective, violation, ok, True, "local")

    def __call__(self, z0: np.ndarray) -> RunRecord:
        return run_local(
            self.method, self.evaluator(), z0, self._record_local, self.out_of_time,
            self.record.clock,
        )  # fmt: skip

    def warm_up(self, dimension: int, evaluate) -> None:
        """One gradient solve at the centre of the box with `evaluate`, recorded like
        the others: the gradient program compiles while the global phase samples."""
        centre = np.full(dimension, 0.5)
        _, g, _, _, exact, ok = evaluate(centre, self.method.levels[0])
        self.record.add(centre, exact, largest_violation(np.asarray(g)[None]), ok, True, "local")


def _sample(global_phase: GlobalPhase, evaluate_batch, dimension: int, seed: int, record):
    """The global phase's samples, evaluated in one batch and recorded: `z (N, P)`,
    `objective`, `violation` (largest), `ok`."""
    z = global_phase.sample(dimension, seed)
    evaluation = evaluate_batch(z)
    if isinstance(evaluation, BatchEvaluation):
        evaluation = (evaluation.objective, evaluation.violations, evaluation.ok)
    objective, violations, ok = (np.asarray(a) for a in evaluation)
    violation = largest_violation(np.asarray(violations, dtype=float).reshape(len(z), -1))
    record.add(z, objective, violation, ok, False, "sample")
    return {"z": z, "objective": objective, "violation": violation, "ok": ok}


def _no_samples(dimension: int) -> dict[str, np.ndarray]:
    return {
        "z": np.zeros((0, dimension)),
        "objective": np.zeros(0),
        "violation": np.zeros(0),
        "ok": np.zeros(0, bool),
    }


def _checked_methods(local, global_phase, dimension: int, caller: str):
    """`local` and `global_phase` (defaults `SLSQP()` and `SobolStarts()`), checked."""
    local = SLSQP() if local is None else local
    global_phase = SobolStarts() if global_phase is None else global_phase
    if not isinstance(local, LocalMethod):
        raise ParameterError(f"{caller}: local must be a LocalMethod, got {local!r}")
    if not isinstance(global_phase, GlobalPhase):
        raise ParameterError(
            f"{caller}: global_phase must be a GlobalPhase (e.g. SobolStarts), got {global_phase!r}"
        )
    if dimension < 1:
        raise ParameterError(f"{caller}: need dimension >= 1 (got {dimension})")
    return local, global_phase


def minimise(
    evaluate_batch: Callable[[np.ndarray], Any],
    value_and_jacobian: Callable[[np.ndarray, float], Any],
    dimension: int,
    *,
    local: LocalMethod | None = None,
    global_phase: GlobalPhase | None = None,
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

    - `evaluate_batch(z)`: `z (n, P)` → a `BatchEvaluation`, or `(objective (n,),
      violations (n, C), ok (n,))`: the exact objective, the normalised constraint values
      (`<= 0` when held) and whether the evaluation succeeded.
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
    - `spent()`: the seconds of the `max_seconds` budget spent so far, and the clock of
      the trace's and the runs' seconds (default: since this call; a resumed study's
      counts the earlier runs').

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
    """`minimise`, in normalised coordinates: the given starts and the global phase at
    once, then the local runs from the best samples, then basin hopping."""
    local, global_phase = _checked_methods(local, global_phase, dimension, "minimise")
    initial = [np.clip(np.asarray(z, dtype=float), 0.0, 1.0) for z in initial]
    runs = global_phase.starts + len(initial) + (0 if hopping is None else hopping.hops)
    budget = global_phase.points + len(initial) + runs * len(local.levels) * local.maxiter
    record = _Recorder(Progress(label, budget, "solves", progress), spent)

    def out_of_time() -> bool:
        return max_seconds is not None and record.clock() > max_seconds

    evaluator = run_evaluator if run_evaluator is not None else lambda: value_and_jacobian
    runner = _LocalRunner(local, evaluator, record, out_of_time)
    # Given starts first (a design known to be good is polished at once), then the
    # global phase: one batch through the batched solver, and the best distinct samples.
    with ThreadPoolExecutor(max(1, workers)) as pool:
        given = [pool.submit(runner, z0) for z0 in initial]
        warm_up = None
        if not given and global_phase.starts:
            warm_up = pool.submit(runner.warm_up, dimension, value_and_jacobian)
        if global_phase.points and not out_of_time():
            sampled = _sample(global_phase, evaluate_batch, dimension, seed, record)
        else:
            sampled = _no_samples(dimension)
        sampled_runs = pool.map(runner, global_phase.choose(sampled))
        done = [future.result() for future in given] + list(sampled_runs)
        if warm_up is not None:
            warm_up.result()
        if hopping is not None:
            done += hopping.run(record, runner, pool, max(1, workers), seed, out_of_time)
    return record.minimum(sampled, done, len(sampled["z"]), global_phase.spacing)


def _regions(runs: list[RunRecord], spacing: float) -> list[int | None]:
    """The start region of each run: a start that evaluated a point joins the first
    region whose first start is within `spacing` (max-norm) of its own, or begins a
    new one; basin hopping's runs and those that evaluated nothing have none."""
    firsts: list[np.ndarray] = []
    regions: list[int | None] = []
    for run in runs:
        if run.phase != "start" or run.evaluations == 0:
            regions.append(None)
            continue
        near = [
            k for k, first in enumerate(firsts) if np.max(np.abs(run.theta0 - first)) <= spacing
        ]
        if not near:
            firsts.append(run.theta0)
        regions.append(near[0] if near else len(firsts) - 1)
    return regions


def _result(
    minimum: _Minimum,
    method: str,
    problem: DesignProblem | None,
    theta: Callable[[np.ndarray], np.ndarray],
    extra_gradient_solves: int = 0,
    compilations: int = 0,
    replayed: int = 0,
) -> OptimiseResult:
    """The `OptimiseResult` of a `_minimise` run, its points mapped to parameter values by
    `theta`, each start given its region."""
    regions = _regions(minimum.runs, minimum.spacing)
    # An evaluation solves the design at each of its firing conditions.
    per_design = 1 if problem is None else problem.solves_per_design
    found = Found(
        best_theta=minimum.best_z[None],
        best_objective=np.array([minimum.best_objective]),
        closest_theta=minimum.closest_z[None],
        closest_violation=np.array([minimum.closest_violation]),
        runs=[
            dataclasses.replace(run, region=r) for run, r in zip(minimum.runs, regions, strict=True)
        ],
        trace=minimum.trace,
        solves=minimum.solves * per_design,
        gradient_solves=(minimum.gradient_solves + extra_gradient_solves) * per_design,
        seconds=minimum.seconds,
        samples=minimum.samples,
    )
    return build_result(
        method, problem, found, compilations=compilations, replayed=replayed, to_theta=theta
    )


def default_local(problem: DesignProblem, minimax: bool | None = None) -> LocalMethod:
    """The local method `search` uses for `problem` when none is given.

    - `minimax` (default: when the objective's one peak over time has a temperature, the
      study's sign that it jumps between local maxima, or when there are several firing
      conditions, whose worst case is the objective): with a temperature
      `EpigraphMinimax()`, without one `TrustRegionLP()`;
    - otherwise `SLSQP` through the continuation `TEMPERATURE_SCHEDULE` of the
      objective's temperatures (a single level on the peaks when it has none).
    """
    name = minimax_metric(problem)
    if minimax is None:
        minimax = name in problem.objective.temperatures or len(problem.conditions) > 1
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
    global_phase: GlobalPhase | None = None,
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
    plus gradient polish: `minimise` on the problem's evaluators (`recoil_jax.extend`):
    the global phase's designs through one batched sweep (`BatchEvaluator`), then a local
    method with exact gradients (`GradientEvaluator`: forward sensitivities, error
    controlled) from its best distinct ones, in the problem's `SearchSpace` (log
    coordinates where the bounds span three decades).

    **Arguments:**

    - `problem`: the `DesignProblem`; its objective's temperatures (if any) are the
      smooth maxima's at continuation level 1.
    - `local`: the local method (default `default_local(problem, minimax)`): `SLSQP`
      (the smoothed objective through a continuation of temperatures),
      `EpigraphMinimax` or `TrustRegionLP` (a minimax over time of one peak:
      `MinimaxEvaluator`), or your own `LocalMethod`.
    - `minimax`: which default to take, when `local` is not given.
    - `global_phase`, `hopping`, `seed`, `max_seconds`, `progress`: as `minimise`
      (default `SobolStarts()`: 1024 designs, 8 starts).
    - `workers`: local runs at the same time (default one per core on CPU).
    - `use_design`: start one local run at the problem's base design (clipped to the
      bounds) besides the sampled ones.
    - `store`: an SQLite file that keeps every evaluation as it is made
      (`docs/campaigns.md`, `StoredEvaluator`): the same search with the same store
      resumes a stopped one, stored evaluations read back bit for bit, and ends at the
      same best design; another search's store is refused. `max_seconds` counts the
      earlier runs' time; `workers` is the store's (it sets how basin hopping proceeds).
    - `client`: a `dask.distributed.Client` for the global phase's sweep.

    **Returns:** `OptimiseResult` (`method` `"search"`, one scenario; exact objectives).

    **Raises:** `ParameterError` for bad arguments, before compiling.
    """
    local, global_phase = _search_methods(problem, local, minimax, global_phase)
    space = SearchSpace.of(problem)
    workers = default_workers(jax.local_devices()) if workers is None else workers
    batch, gradient = BatchEvaluator(problem, space, client), GradientEvaluator(problem, space)
    window = MinimaxWindow(problem, getattr(local, "peak_times", 0))
    initial = [space.z(np.asarray(values_of(problem.params, problem.tune)))] if use_design else []
    with _open_search_store(
        store, problem, local, hopping, global_phase, use_design, seed, workers, progress
    ) as study:
        if study is not None:
            workers = int(study.plan["workers"])
            stored = StoredEvaluator(study, batch, gradient)
            batch, gradient = stored.batch, stored.gradient
        traces = gradient_traces()

        def run_evaluator():
            # With conditions the minimax's pieces are the conditions' objectives, each
            # solve's own; else the signal over time (`MinimaxEvaluator`).
            return gradient if problem.conditions else MinimaxEvaluator(gradient, window)

        minimum = _minimise(
            batch, run_evaluator(), len(problem.tune), local=local,
            global_phase=global_phase, initial=initial, hopping=hopping, seed=seed,
            max_seconds=max_seconds, workers=workers, progress=progress, label="search",
            run_evaluator=run_evaluator, spent=None if study is None else study.spent,
        )  # fmt: skip
    theta = lambda z: np.asarray(space.theta(jnp.asarray(z)))  # noqa: E731
    replayed = 0 if study is None else study.replayed
    compilations = gradient_traces() - traces
    return _result(minimum, "search", problem, theta, window.solves, compilations, replayed)


def _search_methods(problem: DesignProblem, local, minimax, global_phase):
    """`search`'s local method (default `default_local`) and global phase, checked
    against the problem."""
    if problem.objective.scatter is not None:
        raise ParameterError(
            "search does not take a scatter objective yet; use optimise for robust designs"
        )
    if local is not None and minimax is not None and bool(minimax) != local.minimax:
        raise ParameterError(
            f"search: minimax = {minimax} contradicts local = {type(local).__name__}"
        )
    local = default_local(problem, minimax) if local is None else local
    local, global_phase = _checked_methods(local, global_phase, len(problem.tune), "search")
    if local.minimax and minimax_metric(problem) is None and not problem.conditions:
        raise ParameterError(
            "search: minimax needs an objective that is one peak over time "
            "(peak_anchoring_force or peak_displacement, positive weight, no scatter), "
            "or firing conditions"
        )
    return local, global_phase


@contextlib.contextmanager
def _open_search_store(
    path, problem, local, hopping, global_phase, use_design, seed, workers, progress
) -> Iterator[StudyStore | None]:
    """The store at `path` for this search (`open_study`: None where `path` is None),
    whose plan's `workers` the search takes instead of `workers`."""

    def identity() -> str:
        if isinstance(global_phase, SobolStarts):  # as before it was a class of its own:
            # (the spacing only when it is not the default: stores made before it was a
            # setting keep resuming)
            spacing = [] if global_phase.spacing == SPACING else [global_phase.spacing]
            phase = [global_phase.samples, global_phase.starts]
        else:
            phase, spacing = [global_phase], []
        return campaign_identity(
            "search", problem, store_form(local), hopping, *phase, use_design, seed,
            *spacing,
        )  # fmt: skip

    runs = global_phase.starts + int(use_design) + (0 if hopping is None else hopping.hops)
    with open_study(
        path,
        label="search",
        problem=problem,
        identity=identity,
        total=global_phase.points + runs * len(local.levels) * local.maxiter,
        plan={"workers": int(workers)},
        description={"local": type(local).__name__, "seed": seed},
        progress=progress,
    ) as study:
        if study is not None and progress is not False and study.plan["workers"] != workers:
            print(
                f"search: {study.plan['workers']} local runs at once, as in the run that "
                f"made {path} (not {workers}): basin hopping proceeds the same way",
                file=sys.stderr,
            )
        yield study
