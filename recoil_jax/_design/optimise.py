"""Gradient-based design tuning with optax: many starts at once, bounds by
reparametrisation, metric limits by an augmented Lagrangian.

- Bounds hold through a smooth reparametrisation, `θ = space.theta(sigmoid(u))` in the
  problem's `SearchSpace` (linear, or log where the bounds span three decades), so no
  clipping ever zeroes a gradient.
- Limits on metrics go through an `AugmentedLagrangian` (PHR): the multipliers are
  updated every `update_every` steps, and the penalty grows while a limit is violated.
- Every start (and every scenario of a front) runs in one vmapped step, compiled once
  per run; the host loop (`_Runs`) keeps the history, applies the `Stopping` rules and
  selects the best feasible design.
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from .._campaigns.opener import open_study
from .._campaigns.progress import Progress
from .._campaigns.store import StudyStore, campaign_identity, evaluation_row
from .._design.lagrangian import AugmentedLagrangian, LagrangianState, cosine_decayed
from .._design.problem import (
    DesignProblem,
    evaluate_design,
)
from .._design.result import Found, OptimiseResult, RunRecord, build_result
from .._model.feasibility import (
    best_feasible_note,
    closest_index,
    feasible,
    largest_violation,
)
from .._model.metrics import METRICS
from .._model.params import RecoilParams, values_of
from .._model.registry import ParameterError
from .._model.status import OK_CODE
from .._sweeps.memory import check_memory
from .._sweeps.space import SearchSpace

__all__ = ["Stopping", "default_optimiser", "optimise"]


class Stopping(eqx.Module):
    """When a run of `optimise` stops: once, over the last `patience` steps (after
    `min_steps`), its exact objective has moved by at most `ftol` (relative) and no limit
    was violated by more than `vtol` (relative); or at once when its solve fails."""

    patience: int = 20
    ftol: float = 1e-4
    vtol: float = 1e-3
    min_steps: int = 40

    def __check_init__(self):
        if not (self.patience >= 1 and self.min_steps >= 0 and self.ftol >= 0 and self.vtol >= 0):
            raise ParameterError(
                f"Stopping: need patience >= 1, min_steps >= 0, ftol >= 0, vtol >= 0 (got "
                f"{self.patience}, {self.min_steps}, {self.ftol}, {self.vtol})"
            )

    def stationary(self, records) -> np.ndarray:
        """Per run: whether the last `patience` records are stationary (see above)."""
        if len(records) < self.patience:
            return np.zeros(records[-1].objective.shape, dtype=bool)
        window = np.stack([r.objective for r in records[-self.patience :]])
        spread = np.max(window, axis=0) - np.min(window, axis=0)
        flat = spread <= self.ftol * np.abs(window[-1])
        violations = np.stack([r.violations for r in records[-self.patience :]])
        worst = np.max(largest_violation(violations), axis=0)
        return flat & (worst <= self.vtol)

    def stops(self, records, step: int, failed: np.ndarray) -> np.ndarray:
        """Per run: whether it stops after step `step` (from 0)."""
        return failed | ((step + 1 >= self.min_steps) & self.stationary(records))


def _to_theta(space: SearchSpace, u):
    """The tuned values of unconstrained coordinates `u`: `space.theta(sigmoid(u))`."""
    return space.theta(jax.nn.sigmoid(u))


def _to_u(space: SearchSpace, theta) -> np.ndarray:
    fraction = np.clip(space.z(theta), 1e-4, 1 - 1e-4)
    return np.log(fraction) - np.log1p(-fraction)


class _State(eqx.Module):
    u: jax.Array  # (P,) unconstrained coordinates
    opt_state: optax.OptState
    limits: LagrangianState  # (C,) multipliers and () penalty
    scale: jax.Array  # () |objective| at the start: normalises the objective
    step: jax.Array  # () int


class _StepRecord(eqx.Module):
    theta: jax.Array
    metrics: dict
    status: jax.Array  # integer `Status` codes
    smooth_objective: jax.Array
    objective: jax.Array
    violations: jax.Array


def _make_step(
    problem: DesignProblem,
    optimiser: optax.GradientTransformation,
    lagrangian: AugmentedLagrangian,
    steps: int,
    anneal: float,
):
    """The vmapped, jitted step of every run, and the function whose traces count the
    compilations (`eqx.debug.get_num_traces`)."""
    space = SearchSpace.of(problem)

    def loss(u, state: _State, params, limits):
        theta = _to_theta(space, u)
        # Anneal the smooth-max temperatures geometrically to `anneal` of their start.
        progress = state.step / max(steps - 1, 1)
        evaluation = evaluate_design(problem, theta, params, anneal**progress, limits)
        smooth, violations = evaluation.smooth_objective, evaluation.violations
        scale = jnp.where(state.step == 0, jax.lax.stop_gradient(jnp.abs(smooth)), state.scale)
        scale = jnp.where(scale > 0, scale, 1.0)
        (code,) = jax.tree.leaves(evaluation.status)
        record = _StepRecord(
            theta, evaluation.metrics, code, smooth, evaluation.objective, violations
        )
        return smooth / scale + lagrangian.value(state.limits, violations), (record, scale)

    @eqx.debug.assert_max_traces(max_traces=1)
    def one(state: _State, params, limits, active):
        (value, (record, scale)), grad = jax.value_and_grad(loss, has_aux=True)(
            state.u, state, params, limits
        )
        solved = (record.status == OK_CODE) & jnp.isfinite(value) & jnp.all(jnp.isfinite(grad))
        move = active & solved
        updates, opt_state = optimiser.update(grad, state.opt_state, state.u)

        def where_moving(new: Any, old: Any) -> Any:
            return jnp.where(move, new, old)

        u = where_moving(optax.apply_updates(state.u, updates), state.u)
        opt_state = jax.tree.map(where_moving, opt_state, state.opt_state)
        limits = lagrangian.update(state.limits, record.violations, state.step, moved=move)
        return _State(u, opt_state, limits, scale, state.step + move), record

    return eqx.filter_jit(jax.vmap(one)), one


def _start_points(problem: DesignProblem, params, scenarios: int, starts: int, seed: int):
    """`(scenarios·starts, P)`: per scenario, the base design first, then points of a
    randomised Latin hypercube over the bounds."""
    lower, upper = problem.box()
    rng = np.random.default_rng(seed)
    base = np.asarray(jax.vmap(lambda p: values_of(p, problem.tune))(params))
    points = []
    for s in range(scenarios):
        p = len(problem.tune)
        cells = np.stack([rng.permutation(starts - 1) for _ in range(p)], axis=1)
        fractions = (cells + rng.random(cells.shape)) / max(starts - 1, 1)
        points.append(np.clip(base[s], lower, upper)[None])
        points.append(lower + (upper - lower) * fractions)
    return np.concatenate(points)[: scenarios * starts]


def _scenarios(
    problem: DesignProblem,
    scenarios: RecoilParams | None,
    scenario_limits: Mapping[str, Sequence[float]] | None,
):
    """The base design `(S, ...)` and metric limits `(S, C)` of each scenario."""
    constraints = problem.metric_constraints
    limits = np.asarray([[limit for _, _, limit in constraints]], dtype=float).reshape(1, -1)
    sizes = set()
    source = problem.params if scenarios is None else scenarios

    def batched(leaf, base) -> bool:
        # A leaf varies per scenario when it has one axis more than the design's (a
        # scalar parameter, or the orifice's knots); otherwise it is shared.
        return np.ndim(leaf) == np.ndim(base) + 1

    if scenarios is not None:
        if jax.tree.structure(scenarios) != jax.tree.structure(problem.params):
            raise ParameterError("scenarios must have the structure of problem.params")
        sizes |= {
            int(np.shape(x)[0])
            for x, b in zip(
                jax.tree.leaves(scenarios), jax.tree.leaves(problem.params), strict=True
            )
            if batched(x, b)
        }
        if not sizes:
            raise ParameterError("scenarios: no parameter has a leading scenario axis")
    names = [name for name, _, _ in constraints]
    for name, values in (scenario_limits or {}).items():
        if name not in names:
            raise ParameterError(
                f"scenario_limits names {name!r}, which has no metric "
                f"constraint; constrained: {', '.join(names) or 'none'}"
            )
        if names.count(name) > 1:
            raise ParameterError(
                f"scenario_limits names {name!r}, which has {names.count(name)} limits (at "
                "different conditions, or a max and a min): a front varies a metric with one"
            )
        if not np.all(np.isfinite(np.asarray(values, dtype=float))):
            raise ParameterError(f"scenario_limits for {name} must be finite numbers")
        sizes.add(len(values))
    if len(sizes) > 1:
        raise ParameterError(f"scenarios of different lengths: {sorted(sizes)}")
    count = sizes.pop() if sizes else 1
    # Shared values broadcast over the scenarios.
    params = jax.tree.map(
        lambda x, b: (
            jnp.asarray(x, dtype=float)
            if batched(x, b)
            else jnp.broadcast_to(jnp.asarray(x, dtype=float), (count, *np.shape(x)))
        ),
        source,
        problem.params,
    )
    limits = np.repeat(limits, count, axis=0)
    for name, values in (scenario_limits or {}).items():
        limits[:, names.index(name)] = np.asarray(values, dtype=float)
    return params, limits


def _select_best(history: dict[str, np.ndarray], held: np.ndarray, scenarios: int, starts: int):
    """The best feasible point of each run (inf where none), and of each scenario (NaN
    where none); and the least violating point of each scenario. `held (N, R)`: which
    evaluations held every limit."""
    ok = history["status"] == OK_CODE
    runs = scenarios * starts
    values = np.where(held, history["objective"], np.inf)  # (N, R)
    run_best_step = np.argmin(values, axis=0)
    run_best_objective = values[run_best_step, np.arange(runs)]
    run_best_theta = history["theta"][run_best_step, np.arange(runs)]
    best = {"theta": [], "objective": []}
    worst = largest_violation(history["violations"])  # (N, R)
    best["closest_theta"], best["closest_violation"] = [], []
    for s in range(scenarios):
        rs = np.arange(s * starts, (s + 1) * starts)
        objective, violation = history["objective"][:, rs], worst[:, rs]
        i = closest_index(ok[:, rs].ravel(), objective.ravel(), violation.ravel())
        if i is None:  # no solve succeeded: no closest design
            best["closest_theta"].append(np.full(history["theta"].shape[-1], np.nan))
            best["closest_violation"].append(np.nan)
        else:
            step, run = np.unravel_index(i, violation.shape)
            best["closest_theta"].append(history["theta"][step, rs[run]])
            best["closest_violation"].append(violation[step, run])
        r = int(rs[np.argmin(run_best_objective[rs])])
        found = np.isfinite(run_best_objective[r])
        best["objective"].append(run_best_objective[r] if found else np.nan)
        best["theta"].append(run_best_theta[r])
    return ({k: np.asarray(v) for k, v in best.items()}, run_best_objective, run_best_theta)


def optimise(
    problem: DesignProblem,
    *,
    optimiser: optax.GradientTransformation | None = None,
    starts: int = 8,
    steps: int = 200,
    scenarios: RecoilParams | None = None,
    scenario_limits: Mapping[str, Sequence[float]] | None = None,
    seed: int = 0,
    anneal: float = 0.05,
    lagrangian: AugmentedLagrangian | None = None,
    stopping: Stopping | None = None,
    progress: bool | None = None,
    callback: Callable[[int, dict], None] | None = None,
    store: str | os.PathLike | None = None,
) -> OptimiseResult:
    """Minimise `problem.objective` subject to `problem.constraints` from many starts at
    once (vmapped), with an optax optimiser, in one compiled step.

    **Arguments:**

    - `problem`: the `DesignProblem`.
    - `optimiser`: any optax transformation, applied to the unconstrained coordinates
      `u` (`θ = SearchSpace.theta(sigmoid(u))`); default
      Adam with a step cosine-decayed from 0.1 to 0.001 (`default_optimiser`).
    - `starts`: starts per scenario: the base design, then a Latin hypercube (`seed`).
    - `steps`: the most steps taken.
    - `scenarios`: optionally a batched `RecoilParams` (leading axis `S`): the problem is
      solved for each (e.g. one absorber mass per point of a Pareto front), `starts` each.
    - `scenario_limits`: metric name → one limit per scenario (an ε-constraint front).
    - `anneal`: the smooth-max temperatures fall geometrically to this fraction of the
      objective's over the `steps` (a continuation: smooth early, close to the peak late).
    - `lagrangian`: how the metric limits are held (default `AugmentedLagrangian()`:
      its multiplier period and penalty schedule).
    - `stopping`: when a run stops (default `Stopping()`: stationary over 20 steps
      after 40, or a failed solve).
    - `progress`: a progress line on stderr (default: when stderr is a terminal).
    - `callback(step, record)`: called after each step with the host-side record.
    - `store`: the path of an SQLite file that keeps every step as it is taken: each
      run's evaluation (design, objective, limits, status) and the state to go on from
      (`docs/campaigns.md`). Running the same optimisation with the same store resumes
      a stopped one from its last step, with the bits of an uninterrupted run; steps
      read back are not passed to `callback`. A store made by another optimisation is
      refused with `ParameterError`. (The optax transformation is told apart by its
      updates on a fixed probe of gradients.)

    **Returns:** `OptimiseResult`: the best *feasible* point (every limit strictly held)
    over all steps of all runs, per scenario, with the whole history.

    **Raises:** `ParameterError` for bad arguments (before compiling).
    """
    if starts < 1 or steps < 1:
        raise ParameterError(f"starts and steps must be >= 1 (got {starts}, {steps})")
    lagrangian = AugmentedLagrangian() if lagrangian is None else lagrangian
    stopping = Stopping() if stopping is None else stopping
    optimiser = default_optimiser(0.1, steps) if optimiser is None else optimiser
    params, limits = _scenarios(problem, scenarios, scenario_limits)
    # Each run keeps its history, every step's point, metrics and multipliers.
    check_memory(
        limits.shape[0] * starts, 8 * steps * (2 * len(problem.tune) + len(METRICS) + 8),
        "optax runs", "give fewer starts (or steps)", unit="runs",
    )  # fmt: skip
    space = SearchSpace.of(problem)
    u0 = jnp.asarray(_to_u(space, _start_points(problem, params, limits.shape[0], starts, seed)))
    state = _initial_state(optimiser, lagrangian, u0, limits.shape[1])
    step_fn, traced = _make_step(problem, optimiser, lagrangian, steps, anneal)
    runs = _Runs(len(u0), steps, problem)
    settings = (starts, steps, params, limits, seed, anneal, lagrangian, stopping)
    with _open_store(store, problem, optimiser, u0, settings, progress) as study:
        state = runs.resume(study, state)
        bar = Progress("optimise", steps, "steps", progress, already=len(runs.records))
        run_params = jax.tree.map(lambda x: jnp.repeat(jnp.asarray(x), starts, axis=0), params)
        run_limits = jnp.asarray(np.repeat(limits, starts, axis=0))
        runs.take_steps(step_fn, (run_params, run_limits), state, stopping, study, bar, callback)
    return build_result(
        "optax", problem, runs.found(space, u0, starts, limits.shape[0], bar.elapsed),
        compilations=eqx.debug.get_num_traces(traced), scenario_params=params,
        scenario_limits=limits,
    )  # fmt: skip


def _initial_state(optimiser, lagrangian: AugmentedLagrangian, u0, constraints: int) -> _State:
    """Every run's state before its first step (leading axis: the runs)."""
    runs = len(u0)
    return _State(
        u=u0,
        opt_state=jax.vmap(optimiser.init)(u0),
        limits=LagrangianState(
            jnp.zeros((runs, constraints)), jnp.full((runs,), float(lagrangian.penalty))
        ),
        scale=jnp.ones((runs,)),
        step=jnp.zeros((runs,), dtype=int),
    )


class _Runs:
    """The host's view of `optimise`'s vmapped runs, step by step: which are `active`,
    the step each converged at (-1: not), every step's record, which runs took it and
    when it ended (seconds of the budget, earlier runs' included), the best feasible
    objective so far; saved to a study's store after each step and restored from it."""

    def __init__(self, count: int, steps: int, problem: DesignProblem):
        self.steps = steps
        self.samples = problem.solves_per_design  # solves in a run's step
        self.active = np.ones(count, dtype=bool)
        self.converged_step = np.full(count, -1)
        self.records: list[_StepRecord] = []
        self.took: list[np.ndarray] = []  # which runs took each step
        self.seconds: list[float] = []  # when each step ended
        self.best = np.inf

    def resume(self, study: StudyStore | None, state: _State) -> _State:
        """The state after the steps stored in `study` (read back), or `state`."""
        treedef = jax.tree.structure(state)
        for saved in [] if study is None else study.checkpoints():
            self.took.append(self.active.copy())
            leaves = [jnp.asarray(saved[f"state:{i}"]) for i in range(treedef.num_leaves)]
            state = jax.tree.unflatten(treedef, leaves)
            metrics = {k.split(":", 1)[1]: v for k, v in saved.items() if k.startswith("metric:")}
            arrays: Any = saved  # host arrays in the record's fields, as after a step
            self.records.append(
                _StepRecord(
                    arrays["theta"], metrics, arrays["status"], arrays["smooth_objective"],
                    arrays["objective"], arrays["violations"],
                )
            )  # fmt: skip
            self.active = saved["active"].copy()
            self.converged_step = saved["converged_step"].copy()
            self.best = float(saved["best_so_far"])
            self.seconds.append(float(saved.get("seconds", 0.0)))  # 0 in early stores
        return state

    def take_steps(self, step, inputs, state: _State, stopping, study, bar, callback) -> None:
        """Step every active run (`step(state, *inputs, active)`) until none is or the
        steps are spent."""
        began = time.perf_counter()
        # Seconds of the budget: a study's own clock (the earlier runs' included).
        clock = (lambda: time.perf_counter() - began) if study is None else study.spent
        for k in range(len(self.records), self.steps if self.active.any() else 0):
            state, record = step(state, *inputs, jnp.asarray(self.active))
            record = jax.tree.map(np.asarray, record)
            self.records.append(record)
            failed = record.status != OK_CODE
            stop = self.active & stopping.stops(self.records, k, failed)
            self.converged_step = np.where(stop & ~failed, k, self.converged_step)
            self.took.append(self.active.copy())
            self.active &= ~stop
            self.seconds.append(clock())
            if callback is not None:
                callback(k, {"objective": record.objective, "active": self.active.copy()})
            held = feasible(~failed, record.objective, record.violations)
            self.best = min(self.best, float(np.min(np.where(held, record.objective, np.inf))))
            if study is not None:
                study.checkpoint(k, self._saved(state, record), self._rows(record))
            note = f"{int(self.active.sum())}/{len(self.active)} runs active, "
            note += best_feasible_note(self.best)
            bar.update(k + 1, note, final=not self.active.any())
            if not self.active.any():
                break

    def _saved(self, state: _State, record: _StepRecord) -> dict:
        """What a step's checkpoint holds, by name (`resume` reads it back)."""
        saved = {f"state:{i}": leaf for i, leaf in enumerate(jax.tree.leaves(state))}
        saved |= {
            "theta": record.theta, "status": record.status,
            "smooth_objective": record.smooth_objective, "objective": record.objective,
            "violations": record.violations, "active": self.active,
            "converged_step": self.converged_step, "best_so_far": self.best,
            "seconds": self.seconds[-1],
        }  # fmt: skip
        return saved | {f"metric:{name}": value for name, value in record.metrics.items()}

    def _rows(self, record: _StepRecord) -> list[dict]:
        """A step's evaluations as store rows, one per run that took the step."""
        return [
            evaluation_row(
                self.seconds[-1], "step", record.theta[r], record.objective[r],
                record.violations[r], record.status[r], start=r,
            )
            for r in np.nonzero(self.took[-1])[0].tolist()
        ]  # fmt: skip

    def history(self) -> dict[str, np.ndarray]:
        """Per step, `(steps, runs, ...)` arrays by name: `theta`, `objective`,
        `smooth_objective`, `violations`, `status`, and each metric."""
        records = self.records
        names = ("theta", "objective", "smooth_objective", "violations")
        history = {name: np.stack([getattr(r, name) for r in records]) for name in names}
        history["status"] = np.stack([r.status for r in records])
        return history | {
            name: np.stack([r.metrics[name] for r in records]) for name in records[0].metrics
        }

    def found(self, space, u0, starts: int, scenarios: int, seconds: float) -> Found:
        """What the runs found (for `build_result`)."""
        history = self.history()
        held = feasible(history["status"] == OK_CODE, history["objective"], history["violations"])
        best, run_best_objective, run_best_theta = _select_best(history, held, scenarios, starts)
        took = np.stack(self.took)  # (N, R): which runs took each step
        step_seconds = np.asarray(self.seconds)
        theta0 = np.asarray(_to_theta(space, u0))
        runs = tuple(
            self._record(r, starts, history, theta0, run_best_objective, run_best_theta, took)
            for r in range(len(theta0))
        )
        # Every evaluation, step by step: the vmapped step solves every run, a stopped one
        # at where it stopped ("stopped"), so its last move is judged like the others.
        steps_of, runs_of = np.indices(took.shape).reshape(2, -1)
        return Found(
            best_theta=best["theta"], best_objective=best["objective"],
            closest_theta=best["closest_theta"], closest_violation=best["closest_violation"],
            runs=list(runs),
            trace={
                "seconds": step_seconds[steps_of],
                "scenario": runs_of // starts,
                "objective": history["objective"][steps_of, runs_of],
                "feasible": held[steps_of, runs_of],
                "gradient": np.ones(len(steps_of), dtype=bool),
                "phase": np.where(took[steps_of, runs_of], "step", "stopped"),
            },
            solves=0, gradient_solves=len(self.records) * len(theta0) * self.samples,
            seconds=seconds, history=history,
        )  # fmt: skip

    def _record(self, r, starts, history, theta0, run_best_objective, run_best_theta, took):
        """Run `r`'s `RunRecord`."""
        taken = int(took[:, r].sum())
        failed = bool(np.any(took[:, r] & (history["status"][:, r] != OK_CODE)))
        found = np.isfinite(run_best_objective[r])
        message = (
            "converged" if self.converged_step[r] >= 0
            else "a solve failed: this start ended there" if failed
            else f"step limit ({self.steps}) reached"
        )  # fmt: skip
        return RunRecord(
            phase="start",
            theta0=theta0[r],
            # Where it ended: a stopped run stays at the point its last step moved to,
            # evaluated at every later step of the others.
            theta=history["theta"][-1, r],
            objective=float(history["objective"][-1, r]),
            best_objective=float(run_best_objective[r]),
            best_theta=run_best_theta[r] if found else np.full(theta0.shape[1], np.nan),
            evaluations=len(self.records),
            iterations=taken,
            converged=bool(self.converged_step[r] >= 0),
            message=message,
            seconds=(0.0, float(self.seconds[taken - 1])),
            scenario=r // starts,
            region=r % starts,  # each start its own region
            no_impact=bool(history["peak_contact_force"][-1, r] == 0.0),
        )


def _open_store(
    path, problem, optimiser, u0, settings: tuple, progress
) -> contextlib.AbstractContextManager[StudyStore | None]:
    """The store at `path` of this optimisation (`open_study`: made, or checked to be
    its own; None where `path` is None)."""
    starts, steps, params, limits, seed, anneal, lagrangian, stopping = settings

    def identity() -> str:
        # The settings flat, in the order stores were named by before they were objects.
        return _identity(
            problem, optimiser, u0, starts, steps, params, limits, seed, anneal,
            lagrangian.update_every, lagrangian.penalty, lagrangian.penalty_growth,
            lagrangian.max_penalty, stopping.patience, stopping.ftol, stopping.vtol,
            stopping.min_steps,
        )  # fmt: skip

    return open_study(
        path, label="optimise", problem=problem, identity=identity, total=len(u0) * steps,
        plan={}, description={"runs": len(u0)}, progress=progress,
    )  # fmt: skip


def _identity(problem, optimiser: optax.GradientTransformation, u0, *settings) -> str:
    """A `fingerprint` of everything an optimisation's steps depend on. The optax
    transformation (functions, not data) is told apart by its updates over a fixed
    probe: eight steps from `u0` with gradients of fixed, varied signs and sizes."""
    u: Any = jnp.asarray(u0)
    opt_state = jax.vmap(optimiser.init)(u)
    probe = []
    for k in range(8):
        grad = jnp.cos(jnp.arange(u.size, dtype=u.dtype).reshape(u.shape) * (k + 1.7)) * 10.0**-k
        updates, opt_state = jax.vmap(optimiser.update)(grad, opt_state, u)
        u = optax.apply_updates(u, updates)
        probe.append(np.asarray(updates))
    return campaign_identity("optimise", problem, np.asarray(u0), probe, settings)


def default_optimiser(learning_rate: float, steps: int) -> optax.GradientTransformation:
    """Adam on the sigmoid coordinates, its step cosine-decayed to 1 % over `steps`."""
    return cosine_decayed("adam", learning_rate, steps, 0.01)
