"""The local phase of `minimise`: each method is a class that carries its own settings and
is passed in by the caller (as diffrax's solvers are), and each run of it gets a
`LocalRun`, the per-run state (evaluations, failures, the stall watch).

- `SLSQP`: SLSQP on the smoothed objective, through a continuation of temperatures.
- `EpigraphMinimax`: a short smoothed level (the basin), then SLSQP on the epigraph of
  the minimax `min s, f_k(z) <= s`.
- `TrustRegionLP`: the minimax by trust-region linear programming (Madsen's method).
- `OptaxLocal`: an optax optimiser, projected onto the box, the limits by an augmented
  Lagrangian.

A new method subclasses `LocalMethod` and writes `run(local_run, z0)`; it evaluates
through `local_run.evaluate(z, level)` and needs nothing else from the library.
"""

from __future__ import annotations

import abc
import dataclasses
import functools
from collections.abc import Callable
from typing import Any, NamedTuple, final

import equinox as eqx
import numpy as np

from .._design.lagrangian import AugmentedLagrangian, cosine_decayed
from .._design.result import RunRecord
from .._model.feasibility import (
    feasible,
    largest_violation,
)
from .._model.registry import ParameterError

__all__ = [
    "SLSQP",
    "EpigraphMinimax",
    "LocalEvaluation",
    "LocalMethod",
    "LocalRun",
    "MinimaxMethod",
    "OptaxLocal",
    "TrustRegionLP",
    "run_local",
    "store_form",
]


class LocalEvaluation(NamedTuple):
    """What the local phase's `value_and_jacobian(z, level)` gives at one point `z (P,)`.

    - `f`: the objective the method minimises at continuation `level` (a scalar), or at
      level 0 of a minimax a vector `(K,)` whose maximum is the objective;
    - `g (C,)`: the normalised limit violations (`<= 0` where held);
    - `df (P,)` or `(K, P)`, `dg (C, P)`: their Jacobians;
    - `objective`: the exact objective at `z` (what is recorded and reported);
    - `ok`: whether the evaluation succeeded.
    """

    f: Any
    g: Any
    df: Any
    dg: Any
    objective: float
    ok: bool


class SolveFailed(Exception):
    """A local run met more failed solves than it steps back from."""


class OutOfTime(Exception):
    """The wall-time budget is spent."""


class Stalled(Exception):
    """A minimax run stopped improving (`MinimaxMethod.stall_solves`)."""


_LAGRANGIAN = AugmentedLagrangian()

#: How a local method's message starts when its own test of convergence ended the run
#: (`OptimiseResult.runs`' `converged`); a stall of a minimax counts. Anything else (an
#: iteration limit, a failed line search or LP, the time budget, failed solves) does not.
CONVERGED = ("converged", "stalled", "Optimization terminated successfully")


class LocalMethod(eqx.Module):
    """A local method of `minimise` (abstract): its settings, and `run`, which each
    method writes. The methods here are final: a new one subclasses `LocalMethod`,
    declares its own `maxiter` (iterations per level) and writes `run`.

    - `levels`: the continuation levels it evaluates at, in order (factors of the
      objective's temperatures; 0: the minimax, where `f` is a vector).
    - `ftol`: the tolerance at the last level.
    - `margin`: every normalised limit is aimed at `-margin`, inside the feasibility
      tolerance (`FEASIBILITY_TOLERANCE`), so the limits hold on a re-solve.
    - `max_failures`: failed trial solves a run steps back from before it ends.

    A method that solves a minimax over time subclasses `MinimaxMethod`.
    """

    maxiter: eqx.AbstractVar[int]
    ftol: float = 1e-10
    margin: float = 1e-5
    max_failures: int = 20

    def __check_init__(self):
        if not self.maxiter >= 1:
            raise ParameterError(f"{type(self).__name__}: maxiter = {self.maxiter}: valid >= 1")
        if any(not level >= 0 for level in self.levels):
            raise ParameterError(
                f"{type(self).__name__}: levels must be factors >= 0, got {self.levels}"
            )

    @property
    def levels(self) -> tuple[float, ...]:
        return (1.0,)

    @property
    def minimax(self) -> bool:
        """Whether the method solves a minimax (a last level 0)."""
        return self.levels[-1] == 0

    @abc.abstractmethod
    def run(self, local: LocalRun, z0: np.ndarray) -> tuple[np.ndarray, str]:
        """Minimise from `z0`, evaluating through `local.evaluate(z, level)`; returns the
        end point and a message (starting with `"converged"` when the method's own test
        ended it: `CONVERGED`)."""


class MinimaxMethod(LocalMethod):
    """A local method whose last level is the minimax (abstract), with the stall watch
    every minimax has: at level 0, a run ends once its best feasible objective has not
    improved by `stall_rtol` in `stall_solves` gradient solves (None: never). A method
    may also declare `peak_times`: how many of the signal's local maxima at the run's
    previous point `search` adds to the minimax's pieces (each refined to the vertex of
    the parabola through its samples): near the optimum they sit on the peaks, so each
    competing maximum is its own smooth piece (at a maximum, the value and gradient at a
    fixed time are the peak's own, by the envelope theorem), also for a peak narrower
    than the grid. None are added where it does not."""

    stall_rtol: float = 1e-6
    stall_solves: int | None = 20


class LocalRun:
    """The state of one local run: its evaluations (cached at the last point and level,
    recorded, failed ones replaced by a fallback that makes a line search step back),
    the iterations, and the stall watch of a minimax.

    `evaluate(x, level)` → `(f, g, df, dg)` as NumPy arrays; `start_level(z, level)`
    evaluates a level's start and sets the fallback from it; `limits(level)` is the
    metric limits as SLSQP's inequality constraint (aimed `margin` inside).
    """

    def __init__(
        self,
        method: LocalMethod,
        value_and_jacobian: Callable[[np.ndarray, float], Any],
        dimension: int,
        record: Callable[[np.ndarray, float, float, bool], None],
        out_of_time: Callable[[], bool],
    ):
        self.method, self.dimension = method, dimension
        self._value_and_jacobian, self._record, self._out_of_time = (
            value_and_jacobian,
            record,
            out_of_time,
        )
        self.iterations = 0
        self.failures = 0
        # Every evaluation of this run, and the best feasible one.
        self.evaluations, self.best_feasible, self.best_z = 0, np.inf, None
        # Where the last completed level ended, and its objective: what a run that is cut
        # short (out of time, failed solves) reports.
        self.z: np.ndarray | None = None
        self.final = np.nan
        self._cache: dict[Any, tuple] = {}
        self._fallback: tuple | None = None
        # The minimax's best feasible point, and gradient solves since it.
        self.stall_best, self.stall_z, self._since = np.inf, None, 0

    def _watch(self, x, exact, held: bool, level):
        """End a minimax that has stalled: SLSQP's own test on the change of `s` rarely
        fires, since the signal's values carry the solver's tolerance."""
        method = self.method
        if level != 0 or not isinstance(method, MinimaxMethod) or method.stall_solves is None:
            return
        gain = exact < self.stall_best * (1.0 - method.stall_rtol)
        if held and gain:
            self.stall_best, self.stall_z, self._since = float(exact), np.array(x), 0
        else:
            self._since += 1
            if self._since >= method.stall_solves and self.stall_z is not None:
                raise Stalled

    def _count(self, x, exact, held: bool) -> None:
        self.evaluations += 1
        if held and exact < self.best_feasible:
            self.best_feasible, self.best_z = float(exact), np.array(x)

    def evaluate(self, x: np.ndarray, level: float) -> tuple:
        key = (x.tobytes(), level)
        if key not in self._cache:
            if self._out_of_time():
                raise OutOfTime
            self._cache.clear()
            f, g, df, dg, exact, ok = self._value_and_jacobian(x, level)
            f, g, df, dg = (np.asarray(a, dtype=float) for a in (f, g, df, dg))
            violation = float(largest_violation(g))
            self._record(x, exact, violation, ok)
            held = bool(feasible(ok, exact, [violation]))  # the one feasibility test
            self._count(x, exact, held)
            self._watch(x, exact, held, level)
            finite = all(np.all(np.isfinite(a)) for a in (f, g, df, dg))
            if bool(ok) and finite:
                self._cache[key] = (f if f.ndim else float(f), g, df, dg)
            else:
                # A trial point whose solve failed looks much worse than the start of the
                # level, so that the line search steps back from it.
                self.failures += 1
                if self._fallback is None or self.failures > self.method.max_failures:
                    raise SolveFailed
                self._cache[key] = self._fallback
        return self._cache[key]

    def start_level(self, z: np.ndarray, level: float) -> float:
        """Evaluate the start of a level; returns the scale of its objective."""
        self._fallback = None
        f0, g0, df0, dg0 = self.evaluate(z, level)
        scale = float(np.max(np.abs(f0))) or 1.0
        self._fallback = (f0 + 10.0 * scale, np.abs(g0) + 1.0, df0, dg0)
        return scale

    def limits(self, level: float) -> dict:
        """The metric limits as SLSQP's inequality (aimed `margin` inside); `x` may carry
        extra variables after the design's (the epigraph's `s`)."""
        d, margin = self.dimension, self.method.margin
        return {
            "type": "ineq",
            "fun": lambda x: -self.evaluate(x[:d], level)[1] - margin,
            "jac": lambda x: _padded(-self.evaluate(x[:d], level)[3], x.size),
        }

    def slsqp(self, z: np.ndarray, level: float, scale: float, maxiter: int, ftol: float):
        """SLSQP on the scalar objective at `level` from `z`, within the unit box and
        the limits; returns `(z, message)`."""
        import scipy.optimize

        result = scipy.optimize.minimize(
            lambda x: (self.evaluate(x, level)[0] / scale, self.evaluate(x, level)[2] / scale),
            z,
            jac=True,
            method="SLSQP",
            bounds=[(0.0, 1.0)] * self.dimension,
            constraints=[self.limits(level)],
            options={"maxiter": maxiter, "ftol": ftol},
        )
        self.iterations += int(result.nit)
        return np.clip(result.x, 0.0, 1.0), str(result.message)

    def level_done(self, z: np.ndarray, level: float) -> None:
        """A level ended at `z`: its objective there is the run's so far."""
        final = float(np.max(self.evaluate(z, level)[0]))
        self.z, self.final = z, final


def run_local(
    method: LocalMethod,
    value_and_jacobian,
    z0: np.ndarray,
    record,
    out_of_time,
    clock: Callable[[], float],
) -> RunRecord:
    """One local run of `method` from `z0`, in normalised coordinates: its `RunRecord`
    (phase `"start"`; `search` maps its points to parameter values)."""
    began = clock()
    local = LocalRun(method, value_and_jacobian, z0.size, record, out_of_time)
    message, stopped = "", False
    try:
        z, message = method.run(local, z0)
        local.level_done(z, method.levels[-1])
    except SolveFailed:
        message, stopped = f"solves failed ({local.failures}): this start ended there", True
    except OutOfTime:
        message, stopped = "the time budget ran out", True
    except Stalled:  # (only a MinimaxMethod's run stalls)
        assert isinstance(method, MinimaxMethod)
        local.z, local.final = local.stall_z, local.stall_best
        message = (
            f"stalled: no gain of {method.stall_rtol:g} in {method.stall_solves} gradient solves"
        )
    return RunRecord(
        phase="start",
        theta0=z0,
        theta=z0 if local.z is None else local.z,
        objective=float(local.final),
        best_objective=float(local.best_feasible),
        best_theta=np.full(z0.shape, np.nan) if local.best_z is None else local.best_z,
        evaluations=local.evaluations,
        iterations=local.iterations,
        converged=not stopped and message.startswith(CONVERGED),
        message=message,
        seconds=(began, clock()),
    )


@final
class SLSQP(LocalMethod):
    """SLSQP with exact gradients on the smoothed objective, one run per continuation
    level in turn (factors of the objective's temperatures); every level but the last
    stops at `level_ftol` (a level's optimum only starts the next)."""

    maxiter: int = 100
    schedule: tuple[float, ...] = (1.0,)
    level_ftol: float = 1e-6

    @property
    def levels(self) -> tuple[float, ...]:
        return tuple(self.schedule)

    def __check_init__(self):
        _check_smoothed_schedule(self)

    def run(self, local: LocalRun, z0: np.ndarray) -> tuple[np.ndarray, str]:
        z, message = z0, ""
        for level in self.schedule:
            scale = local.start_level(z, level)
            last = level == self.schedule[-1]
            ftol = self.ftol if last else max(self.ftol, self.level_ftol)
            z, message = local.slsqp(z, level, scale, self.maxiter, ftol)
            local.level_done(z, level)
        return z, message


@final
class EpigraphMinimax(MinimaxMethod):
    """A smoothed level at `basin_level` first finds the basin (SLSQP, at most
    `basin_maxiter` iterations, `basin_ftol`), then SLSQP on the epigraph of the minimax:
    `min s` over `(z, s)` subject to every piece `f_k(z) <= s` and the limits. Each local
    maximum is its own smooth constraint, so SLSQP levels competing peaks at once, and
    its curvature model carries it over kinks of peaks narrower than the grid, where
    `TrustRegionLP` stops. The caller adds the signal at `peak_times` local maxima."""

    basin_level: float = 1.0
    basin_maxiter: int = 8
    basin_ftol: float = 1e-4
    maxiter: int = 100
    peak_times: int = 64

    @property
    def levels(self) -> tuple[float, ...]:
        return (self.basin_level, 0.0)

    def run(self, local: LocalRun, z0: np.ndarray) -> tuple[np.ndarray, str]:
        import scipy.optimize

        scale = local.start_level(z0, self.basin_level)
        z, _ = local.slsqp(
            z0,
            self.basin_level,
            scale,
            min(self.maxiter, self.basin_maxiter),
            max(self.ftol, self.basin_ftol),
        )
        local.level_done(z, self.basin_level)
        scale = local.start_level(z, 0.0)
        d = local.dimension
        top = np.zeros(d + 1)
        top[-1] = 1.0

        def peaks_below(x):
            return x[-1] - local.evaluate(x[:d], 0.0)[0] / scale

        def peaks_jacobian(x):
            df = local.evaluate(x[:d], 0.0)[2] / scale
            return np.hstack([-df, np.ones((df.shape[0], 1))])

        start = np.append(z, np.max(local.evaluate(z, 0.0)[0]) / scale)
        result = scipy.optimize.minimize(
            lambda x: (x[-1], top),
            start,
            jac=True,
            method="SLSQP",
            bounds=[(0.0, 1.0)] * d + [(None, None)],
            constraints=[
                {"type": "ineq", "fun": peaks_below, "jac": peaks_jacobian},
                local.limits(0.0),
            ],
            options={"maxiter": self.maxiter, "ftol": self.ftol},
        )
        local.iterations += int(result.nit)
        return np.clip(result.x[:d], 0.0, 1.0), str(result.message)


@final
class TrustRegionLP(MinimaxMethod):
    """Trust-region linear programming on a minimax (Madsen's method): from `z`, each
    iteration solves `min_d max_k f_k + ∇f_k·d`, the limits linearised, `|d| <= radius`
    (max-norm, normalised coordinates) and the unit box, as an LP (HiGHS), then accepts
    the step if the exact merit fell by at least `accept` of the predicted fall, and
    grows or shrinks the radius by their ratio; a run ends below `min_radius`. Every
    local maximum is its own linear piece, so competing peaks are levelled at once; near
    a levelled optimum (more active peaks than parameters) it converges quadratically.
    A limit enters the merit as an exact penalty (`limit_penalty` per unit of normalised
    violation), so a step may trade a little violation for a lower peak only while it
    leads back inside. Fast where the samples' grid resolves every competing maximum."""

    radius: float = 0.03
    accept: float = 0.01
    min_radius: float = 1e-9
    limit_penalty: float = 100.0
    maxiter: int = 100

    @property
    def levels(self) -> tuple[float, ...]:
        return (0.0,)

    def run(self, local: LocalRun, z0: np.ndarray) -> tuple[np.ndarray, str]:
        import scipy.optimize

        z, d, margin = z0, local.dimension, self.margin
        scale = local.start_level(z, 0.0)

        def merit(f, g):
            return np.max(f) / scale + self.limit_penalty * max(
                0.0, np.max(g + margin, initial=-np.inf)
            )

        f, g, df, dg = local.evaluate(z, 0.0)
        value = merit(f, g)
        radius = self.radius
        # Variables `(d (P), peak, excess)`: minimise `peak + limit_penalty * excess`.
        cost = np.zeros(d + 2)
        cost[d:] = 1.0, self.limit_penalty
        for _ in range(self.maxiter):
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
                b_ub=np.concatenate([-f / scale, -(g + margin)]),
                bounds=[*step_bounds, (None, None), (0.0, None)],
                method="highs",
            )
            if lp.status != 0:
                return z, f"the linear program failed: {lp.message}"
            step = lp.x[:d]
            predicted = value - cost @ lp.x
            if predicted <= self.ftol * max(1.0, abs(value)):
                return z, "converged: the predicted decrease is below ftol"
            trial = np.clip(z + step, 0.0, 1.0)
            f_trial, g_trial, df_trial, dg_trial = local.evaluate(trial, 0.0)
            local.iterations += 1
            trial_value = merit(f_trial, g_trial)
            ratio = (value - trial_value) / predicted
            if ratio > self.accept:
                z, f, g, df, dg, value = trial, f_trial, g_trial, df_trial, dg_trial, trial_value
            length = float(np.max(np.abs(step)))
            if ratio > 0.75:
                radius = min(1.0, max(radius, 2.5 * length))
            elif ratio < 0.25:
                radius = length / 2
            if radius < self.min_radius:
                return z, f"converged: the trust radius is below {self.min_radius:g}"
        return z, "iteration limit reached"


@final
class OptaxLocal(LocalMethod):
    """An optax optimiser as a local method: `optax.<optimiser>` (by name: `"adam"`,
    `"sgd"`, `"lion"`...) with its step cosine-decayed from `learning_rate` to
    `final_fraction` of it over `maxiter` steps, on the smoothed objective of each level
    of `schedule` in turn (scaled by its size at the level's start), projected onto the
    unit box after every step, the limits by an augmented Lagrangian (PHR: multipliers
    updated every `update_every` steps, the `penalty` multiplied by `penalty_growth`
    while a limit is violated, up to `max_penalty`). One gradient solve a step; a level
    ends after `maxiter` steps or once a step moves no coordinate by more than `xtol`.
    A point whose solve fails is stepped back from: the run returns to the last good
    point and halves its steps from there. The best feasible point of every evaluation
    is the run's, as for every method.

    First-order steps need more gradient solves than SLSQP's quasi-Newton ones (the
    tests: a few hundred against a few tens), so `search` defaults to SLSQP; this is the
    way to drive `search`'s starts with optax, as `optimise` drives its vmapped ones."""

    optimiser: str = "adam"
    learning_rate: float = 0.05
    final_fraction: float = 1e-3
    schedule: tuple[float, ...] = (1.0,)
    maxiter: int = 300
    # The augmented Lagrangian's settings (`lagrangian`), its defaults; flat here, as
    # stores name a search by its method's fields.
    penalty: float = _LAGRANGIAN.penalty
    penalty_growth: float = _LAGRANGIAN.penalty_growth
    max_penalty: float = _LAGRANGIAN.max_penalty
    update_every: int = _LAGRANGIAN.update_every
    xtol: float = 1e-9

    @property
    def levels(self) -> tuple[float, ...]:
        return tuple(self.schedule)

    def __check_init__(self):
        if not (self.learning_rate > 0 and 0 < self.final_fraction <= 1):
            raise ParameterError(
                f"OptaxLocal: need learning_rate > 0 and 0 < final_fraction <= 1 (got "
                f"{self.learning_rate}, {self.final_fraction})"
            )
        _ = self.lagrangian  # checks its settings
        _check_smoothed_schedule(self)
        try:  # one update of a 2-vector: the name is an optimiser that takes a gradient
            probe = self._transformation()
            probe.update(np.ones(2), probe.init(np.zeros(2)), np.zeros(2))
        except Exception as error:
            raise ParameterError(
                f"OptaxLocal: optimiser = {self.optimiser!r} is not an optax optimiser that "
                f"steps on a gradient alone (valid: the name of one, e.g. 'adam', 'sgd', "
                f"'lion'): {type(error).__name__}: {error}"
            ) from None

    @property
    def lagrangian(self) -> AugmentedLagrangian:
        """The augmented Lagrangian of the limits, from this method's settings."""
        return AugmentedLagrangian(
            self.penalty, self.penalty_growth, self.max_penalty, self.update_every
        )

    def _transformation(self):
        return cosine_decayed(self.optimiser, self.learning_rate, self.maxiter, self.final_fraction)

    def run(self, local: LocalRun, z0: np.ndarray) -> tuple[np.ndarray, str]:
        z, message = np.asarray(z0, dtype=float), ""
        for level in self.schedule:
            scale = local.start_level(z, level)
            optimiser, lagrangian = self._transformation(), self.lagrangian
            state, limits = optimiser.init(z), None
            # The last point whose solve succeeded, and a factor on the steps that halves
            # at each failed one: the run steps back from where the model fails.
            last, shrink = None, 1.0
            message = f"iteration limit reached: {self.maxiter} steps"
            for k in range(self.maxiter):
                failures = local.failures
                _, g, df, dg = local.evaluate(z, level)
                if local.failures > failures and last is not None:
                    (z, g, df, dg), shrink = last, shrink / 2
                else:
                    last = (z, g, df, dg)
                limits = lagrangian.init(g) if limits is None else limits
                gradient = df / scale + lagrangian.weights(limits, g, self.margin) @ dg
                updates, state = optimiser.update(gradient, state, z)
                moved = np.clip(z + shrink * np.asarray(updates), 0.0, 1.0)
                local.iterations += 1
                limits = lagrangian.update(limits, g, k, self.margin)
                if np.max(np.abs(moved - z)) <= self.xtol:
                    z, message = moved, f"converged: no step above xtol = {self.xtol:g}"
                    break
                z = moved
            local.level_done(z, level)
        return z, message


#: The settings every method carried when stores were first named (the minimax's among
#: them): a study's store names its search by a fingerprint of its local method laid out
#: as then (`store_form`), so that every store written before still resumes.
_STORE_FIELDS = (
    "maxiter", "ftol", "margin", "stall_rtol", "stall_solves", "max_failures", "peak_times",
)  # fmt: skip
#: Their values in a method that has no such setting (what every method had then).
_STORE_DEFAULTS = {"stall_rtol": 1e-6, "stall_solves": None, "peak_times": 0}


def store_form(method: LocalMethod) -> Any:
    """`method` as a study's store names it: one of the library's methods laid out as
    `_STORE_FIELDS`, then its own settings in order; a method of one's own as it is."""
    if type(method) not in (SLSQP, EpigraphMinimax, TrustRegionLP, OptaxLocal):
        return method
    own = tuple(f.name for f in dataclasses.fields(method) if f.name not in _STORE_FIELDS)
    names = _STORE_FIELDS + own
    values = (getattr(method, n, _STORE_DEFAULTS.get(n)) for n in names)
    return _layout(type(method).__name__, names)(*values)


@functools.cache
def _layout(name: str, names: tuple[str, ...]) -> type:
    """A module named `name` with the fields `names`, in order (a pytree's layout)."""
    return type(name, (eqx.Module,), {"__annotations__": dict.fromkeys(names, Any)})


def _check_smoothed_schedule(method) -> None:
    """A method on the smoothed objective only: its `schedule` of temperature factors
    is not empty and has no 0 (the minimax's level)."""
    if not method.schedule or 0.0 in method.schedule:
        raise ParameterError(
            f"{type(method).__name__}: schedule must be factors > 0 (0 is the minimax: "
            f"EpigraphMinimax or TrustRegionLP), got {method.schedule}"
        )


def _padded(jacobian: np.ndarray, columns: int) -> np.ndarray:
    """A Jacobian `(m, P)` with zero columns appended up to `columns` (the epigraph's
    extra variable)."""
    return np.pad(jacobian, ((0, 0), (0, columns - jacobian.shape[1])))
