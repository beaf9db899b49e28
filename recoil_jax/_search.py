"""Global search plus gradient polish: space-filling samples through the batched
solver, then a bounded, constrained quasi-Newton method (SLSQP) with exact gradients
from the best few of them.

- `minimise`: the method on any box-bounded problem with inequality constraints, given
  a batched evaluator (the global phase) and a value-and-Jacobian function (the local
  phase). Works in normalised coordinates `z ∈ [0, 1]^P`.
- `search`: `minimise` on a `DesignProblem`. The global phase runs plain solves
  through `sweep`; the local phase differentiates `evaluate_design` in reverse mode
  through its custom JVP (one sensitivity solve per gradient, whatever the number of
  outputs), with a continuation on the objective's smooth-maximum temperatures.
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

from ._params import ParameterError, RecoilParams, params_to_values, values_of, with_values
from ._problem import DesignProblem, evaluate_design
from ._progress import Progress
from ._status import Status, status_codes
from ._sweep import default_workers, sweep

__all__ = ["MinimiseResult", "log_coordinates", "minimise", "search"]

#: Default continuation of the smooth-maximum temperatures: factors of the objective's.
TEMPERATURE_SCHEDULE = (1.0, 1 / 3, 1 / 9, 1 / 30)

#: SLSQP's tolerance at every continuation level but the last: a level's optimum only
#: starts the next one, so polishing it further is wasted.
LEVEL_FTOL = 1e-6

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
    - `starts`: per local run: `z0`, `z`, `objective`, `iterations`, `message`.
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
            feasible = bool(good) and bool(v <= -TOLERANCE) and bool(np.isfinite(f))
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
      the exact objective at `z`, and whether the evaluation succeeded.
    - `dimension`: `P`.
    - `samples`: Sobol points of the global phase (rounded up to a power of 2; 0: none).
    - `starts`: local runs, from the best distinct points (feasible first, then the least
      violating); `initial` points (e.g. a given design) come first.
    - `schedule`: the continuation levels, run in turn from each start.
    - `maxiter`, `ftol`: SLSQP's iteration limit per level and its tolerance at the last
      level (earlier levels stop at `max(ftol, LEVEL_FTOL)`).
    - `max_seconds`: a wall-time budget: once spent, no further gradient solve starts
      and the best point so far is returned.
    - `workers`: local runs at the same time, each from its own thread (the given
      starts run while the global phase samples).
    - `progress`: a progress line with the best feasible objective (default: on a
      terminal).

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
    if not schedule or any(not s > 0 for s in schedule):
        raise ParameterError(f"minimise: schedule must be positive factors, got {schedule}")
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
        z, message, iterations, final = z0, "", 0, np.nan
        cache: dict[Any, tuple] = {}
        failures = 0
        fallback: tuple | None = None  # what a failed trial point reports

        def evaluate(x, level):
            nonlocal failures
            key = (x.tobytes(), level)
            if key not in cache:
                if out_of_time():
                    raise _OutOfTime
                cache.clear()
                f, g, df, dg, exact, ok = value_and_jacobian(x, level)
                f, g, df, dg = (np.asarray(a, dtype=float) for a in (f, g, df, dg))
                record.add(x, exact, _worst(g[None], 1), ok, True, "local")
                finite = all(np.all(np.isfinite(a)) for a in (f, g, df, dg))
                if bool(ok) and finite:
                    cache[key] = (float(f), g, df, dg)
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
                scale = abs(f0) if f0 != 0 else 1.0
                fallback = (f0 + 10.0 * scale, np.abs(g0) + 1.0, df0, dg0)
                result = scipy.optimize.minimize(
                    lambda x, lv=level, s=scale: (evaluate(x, lv)[0] / s, evaluate(x, lv)[2] / s),
                    z,
                    jac=True,
                    method="SLSQP",
                    bounds=[(0.0, 1.0)] * dimension,
                    constraints=[
                        {
                            "type": "ineq",
                            "fun": lambda x, lv=level: -evaluate(x, lv)[1] - MARGIN,
                            "jac": lambda x, lv=level: -evaluate(x, lv)[3],
                        }
                    ],
                    options={
                        "maxiter": maxiter,
                        "ftol": ftol if level == schedule[-1] else max(ftol, LEVEL_FTOL),
                    },
                )
                z, message = np.clip(result.x, 0.0, 1.0), str(result.message)
                iterations += int(result.nit)
                final = evaluate(z, level)[0]
        except _SolveFailed:
            message = f"solves failed ({failures}): this start ended there"
        except _OutOfTime:
            message = "the time budget ran out"
        return {"z0": z0, "z": z, "objective": final, "iterations": iterations, "message": message}

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
def _gradient_program(problem: DesignProblem, box: _Box, z, temperature):
    """The smooth objective, the violations, their Jacobians, the exact objective and
    the status code at `z`: one sensitivity solve, reverse mode through the custom JVP
    (the Jacobian of all outputs from the one solve). One compilation per problem
    structure: re-running a study, or another seed, reuses it."""
    _TRACES[0] += 1

    def outputs(z):
        _, status, smooth, exact, violations = evaluate_design(
            problem, box.theta(z), temperature_scale=temperature
        )
        (code,) = jax.tree.leaves(status)
        values = jnp.concatenate([smooth[None], violations])
        return values, (values, exact, code)

    jacobian, (values, exact, code) = jax.jacrev(outputs, has_aux=True)(z)
    return values[0], values[1:], jacobian[0], jacobian[1:], exact, code


def search(
    problem: DesignProblem,
    *,
    samples: int = 1024,
    starts: int = 8,
    use_design: bool = True,
    schedule: Sequence[float] | None = None,
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
    - `schedule`: the factors of the objective's temperatures, one SLSQP run each in
      turn (default `(1, 1/3, 1/9, 1/30)` when the objective has temperatures, else a
      single run on the peaks).

    **Returns:** `MinimiseResult` with `best_theta` and the `OptimiseResult` methods that
    studies use (`best_design`, `best_params`). Its objectives are exact (true peaks).

    **Raises:** `ParameterError` for bad arguments, before compiling.
    """
    if problem.objective.scatter is not None:
        raise ParameterError(
            "search does not take a scatter objective yet; use optimise for robust designs"
        )
    if schedule is None:
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

    def value_and_jacobian(z, level):
        f, g, df, dg, exact, code = _gradient_program(
            problem, box, jnp.asarray(z), jnp.asarray(level, dtype=float)
        )
        return f, g, df, dg, float(exact), int(code) == ok_code

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
    )
    result.problem = problem
    result.compilations = _TRACES[0] - traces
    if result.feasible:
        result.best_theta = np.asarray(box.theta(jnp.asarray(result.best_z)))
    return result
