"""The search space and its evaluators: the one place where a point of the search space
becomes solves.

An optimiser moves in normalised coordinates `z ∈ [0, 1]^P` (`SearchSpace`: the tuned
parameters' box, linear per parameter or logarithmic where the bounds span three decades
or more); these objects turn `z` into what it needs, and every solve of `search` (and
of the tuning benchmark's batched methods and the studies' checks) goes through them:

- `BatchEvaluator`: `z (n, P)` → designs → one `sweep` → objective and violations (the
  global phase of `search`, the tuning benchmark's batched methods).
- `GradientEvaluator`: `z (P,)` → one sensitivity solve → a `LocalEvaluation` (the
  smoothed objective at a continuation level, or a minimax's pieces at save times).
- `StoredEvaluator`: either of them through a study's store: an evaluation already
  stored is read back bit for bit, any other is solved and committed.
- `MinimaxWindow` and `MinimaxEvaluator`: the minimax over time of one peak: the save
  times, found once from the first design, and one local run's pieces (the signal on
  the window's grid and at its previous point's local maxima).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._campaigns.store import StudyStore, evaluation_row, fingerprint
from .._design.local import LocalEvaluation
from .._design.problem import DesignProblem, evaluate_design, metric_violations
from .._model.metrics import METRICS
from .._model.params import params_to_values
from .._model.programs import program_builds, structure_jit
from .._model.settings import end_time
from .._model.smooth_max import MetricSeries, series_name
from .._model.status import OK_CODE
from .._sweeps.settings import CHUNK_SIZE
from .._sweeps.space import SearchSpace
from .._sweeps.sweep import sweep

__all__ = [
    "SERIES_POINTS",
    "BatchEvaluation",
    "BatchEvaluator",
    "GradientEvaluator",
    "MinimaxEvaluator",
    "MinimaxWindow",
    "StoredEvaluator",
    "gradient_traces",
    "minimax_metric",
]

#: Save times of the minimax's series: the signal's maximum is levelled on this grid.
SERIES_POINTS = 1024


class BatchEvaluation(NamedTuple):
    """What `BatchEvaluator` gives for `n` points: `theta (n, P)` (the tuned values),
    `objective (n,)` (exact: true peaks), `violations (n, C)` (normalised, `<= 0` where
    held), `status_code (n,)` (integer `Status` codes)."""

    theta: np.ndarray
    objective: np.ndarray
    violations: np.ndarray
    status_code: np.ndarray

    @property
    def ok(self) -> np.ndarray:
        """`(n,)`: whether each solve succeeded."""
        return self.status_code == OK_CODE


class BatchEvaluator:
    """`z (n, P)` → the designs of `problem` at `space.theta(z)` (the untuned values the
    base design's) → one `sweep` → a `BatchEvaluation`; or any designs by flat name
    through the same sweep (`evaluate`).

    - `client`: a `dask.distributed.Client`: the sweep's chunks run on the cluster;
    - `chunk_size`, `progress`: the sweep's (default its own chunks, no progress line).
    """

    def __init__(
        self,
        problem: DesignProblem,
        space: SearchSpace | None = None,
        client=None,
        *,
        chunk_size: int = CHUNK_SIZE,
        progress: bool | None = False,
    ):
        self.problem, self.client = problem, client
        self.space = SearchSpace.of(problem) if space is None else space
        self.chunk_size, self.progress = chunk_size, progress
        self._base = params_to_values(problem.params)

    def theta(self, z: np.ndarray) -> np.ndarray:
        """`(n, P)`: the tuned values of the points `z (n, P)`."""
        return np.asarray(jax.vmap(self.space.theta)(jnp.asarray(z)))

    def designs(self, z: np.ndarray) -> dict[str, np.ndarray]:
        """Every parameter of each design by flat name, `(n,)` each."""
        theta = self.theta(z)
        designs = {k: np.full(len(z), float(v)) for k, v in self._base.items()}
        return designs | {name: theta[:, j] for j, name in enumerate(self.problem.tune)}

    def __call__(self, z: np.ndarray) -> BatchEvaluation:
        return self.evaluate(self.designs(z))

    def evaluate(self, designs: dict[str, np.ndarray]) -> BatchEvaluation:
        """The designs given by flat name (`(n,)` columns, the tuned ones among them;
        names not given take the paper's values), swept with `problem`'s smoothing and
        options; with conditions, each design at each (`n·K` points in the one sweep),
        its objective and violations the worst over them (`metric_violations`)."""
        problem = self.problem
        n = len(next(iter(designs.values())))
        conditions = problem.conditions
        if conditions:
            # Row i·K + k: design i at condition k.
            at = {name: v.ravel() for name, v in problem.condition_values(designs).items()}
            designs = {name: np.repeat(np.asarray(v, dtype=float), len(conditions)) for
                       name, v in designs.items()} | at  # fmt: skip
        result = sweep(
            designs,
            smoothing=problem.smoothing,
            options=problem.options,
            progress=self.progress,
            client=self.client,
            chunk_size=self.chunk_size,
        )
        codes, peaks = result.codes, result.peaks
        objective = np.asarray(problem.objective(peaks), dtype=float)
        theta = np.stack([np.asarray(designs[name], dtype=float) for name in problem.tune], 1)
        if conditions:
            shape = (n, len(conditions))
            peaks = {name: np.asarray(v).reshape(shape) for name, v in peaks.items()}
            objective = np.max(objective.reshape(shape), axis=1)
            codes = np.max(codes.reshape(shape), axis=1)
            theta = theta[:: len(conditions)]
        violations = np.asarray(metric_violations(problem, peaks), dtype=float)
        return BatchEvaluation(theta, objective, violations.reshape(n, -1), codes)


class GradientEvaluator:
    """`z (P,)` at continuation `level` → one sensitivity solve of `problem` →
    `outputs`: the smoothed objective `f` (or, with `series_ts`, the minimax's pieces),
    the violations `g`, their Jacobians `df` and `dg`, the exact objective `exact` and the
    status `code`, as NumPy arrays by name (a study's store keeps them by these names).
    Calling it gives the same as a `LocalEvaluation`."""

    def __init__(self, problem: DesignProblem, space: SearchSpace | None = None):
        self.problem = problem
        self.space = SearchSpace.of(problem) if space is None else space

    def outputs(self, z, level, series_ts=None) -> dict[str, np.ndarray]:
        solve = _gradient_program(
            self.problem, self.space, jnp.asarray(z), jnp.asarray(level, dtype=float), series_ts
        )
        return {name: np.asarray(solve[name]) for name in GRADIENT_OUTPUTS}

    def __call__(self, z, level, series_ts=None) -> LocalEvaluation:
        return local_evaluation(self.outputs(z, level, series_ts), level, series_ts is not None)


def local_evaluation(out: dict[str, np.ndarray], level, series: bool = False) -> LocalEvaluation:
    """A gradient solve's named outputs at continuation `level` as the local phase's
    `LocalEvaluation` (`series`: a minimax's solve over time, whose pieces it keeps). A
    problem with conditions gives the objective at each: at level 0 (a minimax) they are
    its pieces; above it, the greatest is the objective (its row of the Jacobian, a
    subgradient of the maximum)."""
    ok = int(out["code"]) == OK_CODE
    f, df = out["f"], out["df"]
    if np.ndim(f) == 1 and float(level) > 0 and not series:
        worst = int(np.argmax(np.where(np.isnan(f), np.inf, f)))
        f, df = f[worst], df[worst]
    return LocalEvaluation(f, out["g"], df, out["dg"], float(out["exact"]), ok)


class StoredEvaluator:
    """The evaluators through a study's `store`: each evaluation is named by a
    `fingerprint` of what was evaluated; one already stored is read back bit for bit,
    any other solved and committed with the seconds of the study's budget so far
    (`StudyStore.spent`). The one place where "replay or solve" is decided."""

    def __init__(self, store: StudyStore, batch: BatchEvaluator, gradient: GradientEvaluator):
        self.store, self._batch, self._gradient = store, batch, gradient

    def batch(self, z: np.ndarray) -> BatchEvaluation:
        """`BatchEvaluator`'s evaluation, the stored points read back."""
        keys = [fingerprint("sample", row) for row in z]
        stored = [self.store.stored(key) for key in keys]
        todo = np.asarray([i for i, out in enumerate(stored) if out is None], dtype=int)
        n, constraints = len(z), len(self._batch.problem.metric_constraints)
        out = BatchEvaluation(
            self._batch.theta(z),
            np.zeros(n),
            np.zeros((n, constraints)),
            np.zeros(n, dtype=np.int32),
        )
        for i, row in enumerate(stored):
            if row is not None:
                out.objective[i], out.violations[i], out.status_code[i] = (
                    row["objective"], row["violations"], row["code"]
                )  # fmt: skip
        if todo.size:
            solved = self._batch(z[todo])
            out.objective[todo] = solved.objective
            out.violations[todo], out.status_code[todo] = solved.violations, solved.status_code
            self.store.commit(
                [
                    self._row(
                        "sample", solved.theta[j], keys[i], out.objective[i], out.violations[i],
                        {"objective": out.objective[i], "violations": out.violations[i],
                         "code": out.status_code[i]},
                    )
                    for j, i in enumerate(todo.tolist())
                ]
            )  # fmt: skip
        return out

    def gradient(self, z, level, series_ts=None) -> LocalEvaluation:
        """`GradientEvaluator`'s evaluation, read back if stored."""
        z = np.asarray(z, dtype=float)
        times = () if series_ts is None else np.asarray(series_ts)
        key = fingerprint("gradient", z, np.asarray(level, dtype=float), times)
        out = self.store.stored(key)
        if out is None:
            out = self._gradient.outputs(z, level, series_ts)
            theta = np.asarray(self._gradient.space.theta(jnp.asarray(z)))
            self.store.commit([self._row("local", theta, key, out["exact"], out["g"], out)])
        return local_evaluation(out, level, series_ts is not None)

    def _row(self, phase: str, theta, key: str, objective, violations, out: dict) -> dict:
        """The store's row of one evaluation, its outputs kept for the resume."""
        return evaluation_row(
            self.store.spent(),
            phase,
            theta,
            objective,
            violations,
            out["code"],
            key=key,
            outputs=out,
        )


class MinimaxWindow:
    """The save times of a minimax over time (`SERIES_POINTS` of them): from 0 to where
    the first design's peaks were certain, plus a quarter (a later design's maximum
    outside them still counts, through its located peak). Found by one gradient solve
    at the first design that asks (`times`), then shared by every local run."""

    def __init__(self, problem: DesignProblem, peak_times: int):
        self.problem, self.peak_times = problem, peak_times
        self._times: np.ndarray | None = None
        self._lock = threading.Lock()  # the local runs ask from their threads

    @property
    def solves(self) -> int:
        """The gradient solves spent finding the window (0 or 1)."""
        return int(self._times is not None)

    def times(self, z, solve: Callable[..., LocalEvaluation]) -> np.ndarray:
        """The window's save times `(SERIES_POINTS,)`, found at `z` with `solve(z,
        level, series_ts)` if not yet."""
        with self._lock:
            if self._times is None:
                problem = self.problem
                t1 = float(np.max(np.asarray(end_time(problem.params, problem.options))))
                whole = np.linspace(0.0, t1, SERIES_POINTS)
                padded = np.concatenate([whole, np.full(self.peak_times, t1)])
                f = np.asarray(solve(z, 1.0, jnp.asarray(padded))[0])[1:]
                f = f[:SERIES_POINTS]
                written = np.nonzero(np.isfinite(f))[0]
                end = whole[written[-1]] if written.size else t1
                self._times = np.linspace(0.0, min(t1, 1.25 * end), SERIES_POINTS)
            return self._times


class MinimaxEvaluator:
    """One local run's `value_and_jacobian(z, level)`: at a level above 0 the smoothed
    objective (`solve(z, level)`); at level 0 the minimax's pieces: the signal on the
    `window`'s grid and at the `peak_times` highest local maxima of this run's previous
    good point (each refined to its parabola's vertex)."""

    def __init__(self, solve: Callable[..., LocalEvaluation], window: MinimaxWindow):
        self.solve, self.window = solve, window
        self.previous_maxima: np.ndarray | None = None  # at this run's last good solve

    def __call__(self, z, level) -> LocalEvaluation:
        if level > 0:
            return self.solve(z, level)
        peak_times = self.window.peak_times
        grid = self.window.times(z, self.solve)
        extra = self.previous_maxima
        times = np.concatenate([grid, np.full(peak_times, grid[-1]) if extra is None else extra])
        # Saved in time order; returned in this order, so that each value keeps its
        # place (one constraint of SLSQP's each) from one point to the next.
        order = np.argsort(times, kind="stable")
        f, g, df, dg, exact, ok = self.solve(z, level, jnp.asarray(times[order]))
        f, df = np.array(f), np.array(df)
        f[1 + order], df[1 + order] = f[1:].copy(), df[1:].copy()
        if bool(ok) and peak_times:
            self.previous_maxima = _local_maxima(times, f[1:], peak_times, grid[-1])
        # Save times after the solve's end (its peaks certain) are no constraint.
        after = ~np.isfinite(f)
        if np.any(np.isfinite(f)):
            f[after], df[after] = np.nanmin(f), 0.0
        return LocalEvaluation(f, g, df, dg, exact, ok)


def minimax_metric(problem: DesignProblem) -> str | None:
    """The metric when `problem`'s objective is a positive multiple of one maximum over
    time (a metric with a `SmoothMax`), with no scatter and no conditions: `search` then
    treats it as a minimax over time. Else None (with conditions, the minimax is over
    them)."""
    objective = problem.objective
    if objective.scatter is not None or problem.conditions or len(objective.weights) != 1:
        return None
    ((name, weight),) = objective.weights.items()
    return name if weight > 0 and METRICS[name].smoothable else None


#: A gradient solve's outputs by name (a study's store keeps them by these names).
GRADIENT_OUTPUTS = ("f", "g", "df", "dg", "exact", "code")


def _gradient_solve(problem: DesignProblem, box: SearchSpace, z, temperature, series_ts=None):
    """The smooth objective, the violations, their Jacobians, the exact objective and
    the status code at `z` (`GRADIENT_OUTPUTS`): one sensitivity solve, reverse mode
    through the custom JVP (the Jacobian of all outputs from the one solve). One
    compilation per problem structure: re-running a study, or another seed, reuses it.

    With `series_ts` (`(n,)` save times), the objective comes as a minimax instead:
    `(1 + n,)` values, its peak then the weighted signal at each save time (NaN after
    the solve's end), with their Jacobian `(1 + n, P)` (forward mode: P columns).

    With conditions (`K`), the objective at each condition `(K,)` and its Jacobian
    `(K, P)`: smoothed at a level above 0, with the peaks at level 0, the minimax's
    pieces (`local_evaluation` takes the greatest above level 0)."""
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
    elif problem.conditions:
        # Level 0 is the minimax over the conditions (no smoothing); the scale keeps the
        # smoothed branch finite there, so that `where` passes no NaN to the gradient.
        smoothed = temperature > 0
        scale = jnp.where(smoothed, temperature, 1.0)

        def condition_outputs(z):
            evaluation = evaluate_design(problem, box.theta(z), temperature_scale=scale)
            per_condition = evaluation.conditions
            assert per_condition is not None
            pieces = jnp.where(
                smoothed,
                problem.objective(per_condition, smooth=bool(problem.objective.temperatures)),
                problem.objective(per_condition),
            )
            values = jnp.concatenate([pieces, evaluation.violations])
            return values, (values, evaluation)

        jacobian, (values, evaluation) = jax.jacrev(condition_outputs, has_aux=True)(z)
        n = len(problem.conditions)
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
    solved = (f, values[n:], df, jacobian[n:], evaluation.objective, code)
    return dict(zip(GRADIENT_OUTPUTS, solved, strict=True))


_GRADIENT_TREE = jax.tree.structure(dict.fromkeys(GRADIENT_OUTPUTS, 0))

# Exported to the compilation cache's folder: a study run again (the same problem's
# structure) loads it instead of tracing it (6.4 s of a warm `optimise envelope`'s 21.7 s).
_gradient_program = structure_jit(
    _gradient_solve, exported=lambda leaves: jax.tree.unflatten(_GRADIENT_TREE, leaves)
)


def gradient_traces() -> int:
    """How many gradient programs this process has built (traced and compiled, or
    loaded exported from the compilation cache's folder)."""
    return program_builds(_gradient_solve)


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
