"""Gradient-based design tuning with optax: many starts at once, bounds by
reparametrisation, metric limits by an augmented Lagrangian.

- Bounds hold through a smooth reparametrisation, `θ = space.theta(sigmoid(u))` in the
  problem's `SearchSpace` (linear, or log where the bounds span three decades), so no
  clipping ever zeroes a gradient.
- Limits on metrics go through an augmented Lagrangian (PHR): the multipliers are updated
  every `update_every` steps, and the penalty grows while a limit is violated.
- Every start (and every scenario of a front) runs in one vmapped step, compiled once
  per run; the host loop keeps the history, applies the stopping rules and selects the
  best feasible design.
"""

from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from ._params import ParameterError, RecoilParams, values_of
from ._problem import (
    DesignProblem,
    best_feasible_note,
    closest_index,
    evaluate_design,
    feasible,
    largest_violation,
)
from ._progress import Progress
from ._result import OptimiseResult
from ._space import SearchSpace
from ._status import Status, status_codes
from ._store import evaluation_row, fingerprint, open_study

__all__ = ["default_optimiser", "optimise"]


def _to_theta(space: SearchSpace, u):
    """The tuned values of unconstrained coordinates `u`: `space.theta(sigmoid(u))`."""
    return space.theta(jax.nn.sigmoid(u))


def _to_u(space: SearchSpace, theta) -> np.ndarray:
    fraction = np.clip(space.z(theta), 1e-4, 1 - 1e-4)
    return np.log(fraction) - np.log1p(-fraction)


class _State(eqx.Module):
    u: jax.Array  # (P,) unconstrained coordinates
    opt_state: optax.OptState
    multipliers: jax.Array  # (C,) augmented-Lagrangian multipliers
    penalty: jax.Array  # () penalty parameter
    scale: jax.Array  # () |objective| at the start: normalises the objective
    step: jax.Array  # () int


class _StepRecord(eqx.Module):
    theta: jax.Array
    metrics: dict
    status: jax.Array  # integer `Status` codes
    smooth_objective: jax.Array
    objective: jax.Array
    violations: jax.Array


@dataclasses.dataclass(frozen=True)
class _Settings:
    steps: int
    anneal: float
    update_every: int
    penalty_growth: float
    max_penalty: float


def _make_step(
    problem: DesignProblem, optimiser: optax.GradientTransformation, settings: _Settings
):
    """The vmapped, jitted step of every run, and the function whose traces count the
    compilations (`eqx.debug.get_num_traces`)."""
    space = SearchSpace.of(problem)
    steps = settings.steps
    ok = int(status_codes(Status.ok))

    def loss(u, state: _State, params, limits):
        theta = _to_theta(space, u)
        # Anneal the smooth-max temperatures geometrically to `anneal` of their start.
        progress = state.step / max(steps - 1, 1)
        evaluation = evaluate_design(problem, theta, params, settings.anneal**progress, limits)
        smooth, violations = evaluation.smooth_objective, evaluation.violations
        scale = jnp.where(state.step == 0, jax.lax.stop_gradient(jnp.abs(smooth)), state.scale)
        scale = jnp.where(scale > 0, scale, 1.0)
        lam, rho = state.multipliers, state.penalty
        augmented = jnp.sum(jnp.maximum(lam + rho * violations, 0.0) ** 2 - lam**2) / (2.0 * rho)
        (code,) = jax.tree.leaves(evaluation.status)
        record = _StepRecord(
            theta, evaluation.metrics, code, smooth, evaluation.objective, violations
        )
        return smooth / scale + augmented, (record, scale)

    @eqx.debug.assert_max_traces(max_traces=1)
    def one(state: _State, params, limits, active):
        (value, (record, scale)), grad = jax.value_and_grad(loss, has_aux=True)(
            state.u, state, params, limits
        )
        solved = (record.status == ok) & jnp.isfinite(value) & jnp.all(jnp.isfinite(grad))
        move = active & solved
        updates, opt_state = optimiser.update(grad, state.opt_state, state.u)

        def where_moving(new: Any, old: Any) -> Any:
            return jnp.where(move, new, old)

        u = where_moving(optax.apply_updates(state.u, updates), state.u)
        opt_state = jax.tree.map(where_moving, opt_state, state.opt_state)
        # Augmented Lagrangian (PHR): first-order multiplier update every `update_every`
        # steps; the penalty grows while any limit is still violated.
        at_update = move & ((state.step + 1) % settings.update_every == 0)
        multipliers = jnp.where(
            at_update,
            jnp.maximum(state.multipliers + state.penalty * record.violations, 0.0),
            state.multipliers,
        )
        violated = jnp.any(record.violations > 0)
        penalty = jnp.where(
            at_update & violated,
            jnp.minimum(state.penalty * settings.penalty_growth, settings.max_penalty),
            state.penalty,
        )
        new = _State(u, opt_state, multipliers, penalty, scale, state.step + move)
        return new, record

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


def _stationary(records, patience: int, ftol: float, vtol: float) -> np.ndarray:
    """Per run: over the last `patience` steps the exact objective moved by at most
    `ftol` (relative) and no metric limit was violated by more than `vtol` (relative)."""
    if len(records) < patience:
        return np.zeros(records[-1].objective.shape, dtype=bool)
    window = np.stack([r.objective for r in records[-patience:]])
    spread = np.max(window, axis=0) - np.min(window, axis=0)
    flat = spread <= ftol * np.abs(window[-1])
    violations = np.stack([r.violations for r in records[-patience:]])
    worst = np.max(largest_violation(violations), axis=0)
    return flat & (worst <= vtol)


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
    ok = history["status"] == int(status_codes(Status.ok))
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
    update_every: int = 20,
    penalty: float = 10.0,
    penalty_growth: float = 2.0,
    max_penalty: float = 1e4,
    patience: int = 20,
    ftol: float = 1e-4,
    vtol: float = 1e-3,
    min_steps: int = 40,
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
    - `update_every`, `penalty`, `penalty_growth`, `max_penalty`: the augmented
      Lagrangian's multiplier period and penalty schedule.
    - `patience`, `ftol`, `vtol`, `min_steps`: a run stops once, over the last `patience`
      steps (after `min_steps`), its objective has moved by at most `ftol` (relative) and
      its limits have held within `vtol` (relative); a run whose solve fails stops too.
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
    if optimiser is None:
        optimiser = default_optimiser(0.1, steps)
    params, limits = _scenarios(problem, scenarios, scenario_limits)
    n_scenarios = limits.shape[0]
    runs = n_scenarios * starts
    run_params = jax.tree.map(lambda x: jnp.repeat(jnp.asarray(x), starts, axis=0), params)
    run_limits = jnp.asarray(np.repeat(limits, starts, axis=0))

    space = SearchSpace.of(problem)
    u0 = jnp.asarray(_to_u(space, _start_points(problem, params, n_scenarios, starts, seed)))
    state = _State(
        u=u0,
        opt_state=jax.vmap(optimiser.init)(u0),
        multipliers=jnp.zeros((runs, limits.shape[1])),
        penalty=jnp.full((runs,), float(penalty)),
        scale=jnp.ones((runs,)),
        step=jnp.zeros((runs,), dtype=int),
    )
    step_fn, traced = _make_step(
        problem, optimiser, _Settings(steps, anneal, update_every, penalty_growth, max_penalty)
    )
    samples = 1 if problem.objective.scatter is None else len(problem.objective.scatter[1])

    active = np.ones(runs, dtype=bool)
    converged_step = np.full(runs, -1)
    records: list[_StepRecord] = []
    stepped_masks: list[np.ndarray] = []  # which runs took each step
    step_seconds: list[float] = []  # when each step ended, the earlier runs' included
    best_so_far = np.inf
    ok = int(status_codes(Status.ok))
    study = None
    if store is not None:
        identity = _identity(
            problem, optimiser, u0, starts, steps, params, limits, seed, anneal, update_every,
            penalty, penalty_growth, max_penalty, patience, ftol, vtol, min_steps,
        )  # fmt: skip
        study = open_study(
            store, label="optimise", problem=problem, identity=identity, total=runs * steps,
            plan={}, description={"runs": runs}, progress=progress,
        )  # fmt: skip
        checkpoints = study.checkpoints()
        for saved in checkpoints:
            stepped_masks.append(active.copy())
            state, record, active, converged_step, best_so_far, seconds = _restore(state, saved)
            records.append(record)
            step_seconds.append(seconds)
    bar = Progress("optimise", steps, "steps", progress, already=len(records))
    began = time.perf_counter()
    prior = 0.0 if study is None else study.prior_seconds
    try:
        for k in range(len(records), steps if active.any() else 0):
            state, record = step_fn(state, run_params, run_limits, jnp.asarray(active))
            record = jax.tree.map(np.asarray, record)
            records.append(record)
            failed = record.status != ok
            stop = active & (
                failed | ((k + 1 >= min_steps) & _stationary(records, patience, ftol, vtol))
            )
            converged_step = np.where(stop & ~failed, k, converged_step)
            stepped = active.copy()
            active &= ~stop
            stepped_masks.append(stepped)
            step_seconds.append(prior + time.perf_counter() - began)
            if callback is not None:
                callback(k, {"objective": record.objective, "active": active.copy()})
            held = feasible(~failed, record.objective, record.violations)
            best_so_far = min(best_so_far, float(np.min(np.where(held, record.objective, np.inf))))
            if study is not None:
                study.checkpoint(
                    k,
                    _saved(state, record, active, converged_step, best_so_far, step_seconds[-1]),
                    _step_rows(record, stepped, step_seconds[-1]),
                )
            bar.update(
                k + 1,
                f"{int(active.sum())}/{runs} runs active, {best_feasible_note(best_so_far)}",
                final=not active.any(),
            )
            if not active.any():
                break
    finally:
        if study is not None:
            study.close()

    history = {
        "theta": np.stack([r.theta for r in records]),
        "objective": np.stack([r.objective for r in records]),
        "smooth_objective": np.stack([r.smooth_objective for r in records]),
        "violations": np.stack([r.violations for r in records]),
        "status": np.stack([r.status for r in records]),
    } | {name: np.stack([r.metrics[name] for r in records]) for name in records[0].metrics}
    held = feasible(history["status"] == ok, history["objective"], history["violations"])
    best, run_best_objective, run_best_theta = _select_best(history, held, n_scenarios, starts)
    took = np.stack(stepped_masks)  # (N, R): which runs took each step
    seconds = np.asarray(step_seconds)
    theta0 = np.asarray(_to_theta(space, u0))
    runs_taken = took.sum(axis=0)
    out = []
    for r in range(runs):
        failed = bool(np.any(took[:, r] & (history["status"][:, r] != ok)))
        found = np.isfinite(run_best_objective[r])
        message = (
            "converged" if converged_step[r] >= 0
            else "a solve failed: this start ended there" if failed
            else f"step limit ({steps}) reached"
        )  # fmt: skip
        out.append(
            {
                "scenario": r // starts,
                "region": r % starts,  # each start its own region
                "phase": "start",
                "theta0": theta0[r],
                # Where it ended: a stopped run stays at the point its last step
                # moved to, evaluated at every later step of the others.
                "theta": history["theta"][-1, r],
                "objective": float(history["objective"][-1, r]),
                "best_objective": float(run_best_objective[r]),
                "best_theta": run_best_theta[r] if found else np.full(len(problem.tune), np.nan),
                "evaluations": len(records),
                "iterations": int(runs_taken[r]),
                "converged": bool(converged_step[r] >= 0),
                "message": message,
                "seconds": (0.0, float(seconds[runs_taken[r] - 1])),
                "no_impact": bool(history["peak_contact_force"][-1, r] == 0.0),
            }
        )
    # Every evaluation, step by step: the vmapped step solves every run, a stopped one
    # at where it stopped ("stopped"), so its last move is judged like the others.
    steps_of, runs_of = np.indices(took.shape).reshape(2, -1)
    return OptimiseResult(
        method="optax",
        problem=problem,
        best_theta=best["theta"],
        best_objective=best["objective"],
        closest_theta=best["closest_theta"],
        closest_violation=best["closest_violation"],
        runs=tuple(out),
        trace={
            "seconds": seconds[steps_of],
            "scenario": runs_of // starts,
            "objective": history["objective"][steps_of, runs_of],
            "feasible": held[steps_of, runs_of],
            "gradient": np.ones(len(steps_of), dtype=bool),
            "phase": np.where(took[steps_of, runs_of], "step", "stopped"),
        },
        solves=0,
        gradient_solves=len(records) * runs * samples,
        seconds=bar.elapsed,
        compilations=eqx.debug.get_num_traces(traced),
        scenario_params=params,
        scenario_limits=limits,
        history=history,
    )


def _identity(problem, optimiser: optax.GradientTransformation, u0, *settings) -> str:
    """A `fingerprint` of everything an optimisation's steps depend on. The optax
    transformation (functions, not data) is told apart by its updates over a fixed
    probe: eight steps from `u0` with gradients of fixed, varied signs and sizes."""
    from . import __version__

    u: Any = jnp.asarray(u0)
    opt_state = jax.vmap(optimiser.init)(u)
    probe = []
    for k in range(8):
        grad = jnp.cos(jnp.arange(u.size, dtype=u.dtype).reshape(u.shape) * (k + 1.7)) * 10.0**-k
        updates, opt_state = jax.vmap(optimiser.update)(grad, opt_state, u)
        u = optax.apply_updates(u, updates)
        probe.append(np.asarray(updates))
    return fingerprint("optimise", __version__, problem, np.asarray(u0), probe, settings)


def _saved(
    state: _State, record: _StepRecord, active, converged_step, best, seconds: float
) -> dict:
    """What a step's checkpoint holds, by name (`_restore` reads it back)."""
    saved = {f"state:{i}": leaf for i, leaf in enumerate(jax.tree.leaves(state))}
    saved |= {
        "theta": record.theta,
        "status": record.status,
        "smooth_objective": record.smooth_objective,
        "objective": record.objective,
        "violations": record.violations,
        "active": active,
        "converged_step": converged_step,
        "best_so_far": best,
        "seconds": seconds,
    }
    return saved | {f"metric:{name}": value for name, value in record.metrics.items()}


def _restore(state: _State, saved: dict[str, np.ndarray]):
    """The state after a stored step (`state` gives the structure), its record, which
    runs were active, their converged steps, the best feasible objective so far and when
    the step ended (0 in a store written before that was kept)."""
    treedef = jax.tree.structure(state)
    leaves = [jnp.asarray(saved[f"state:{i}"]) for i in range(treedef.num_leaves)]
    metrics = {k.split(":", 1)[1]: v for k, v in saved.items() if k.startswith("metric:")}
    arrays: Any = saved  # host arrays in the record's fields, as after a step
    record = _StepRecord(
        arrays["theta"],
        metrics,
        arrays["status"],
        arrays["smooth_objective"],
        arrays["objective"],
        arrays["violations"],
    )
    return (
        jax.tree.unflatten(treedef, leaves),
        record,
        saved["active"].copy(),
        saved["converged_step"].copy(),
        float(saved["best_so_far"]),
        float(saved.get("seconds", 0.0)),
    )


def _step_rows(record: _StepRecord, stepped, seconds: float) -> list[dict]:
    """A step's evaluations as store rows, one per run that took the step."""
    return [
        evaluation_row(
            seconds, "step", record.theta[r], record.objective[r], record.violations[r],
            record.status[r], start=r,
        )
        for r in np.nonzero(stepped)[0].tolist()
    ]  # fmt: skip


def default_optimiser(learning_rate: float, steps: int) -> optax.GradientTransformation:
    """Adam on the sigmoid coordinates, its step cosine-decayed to 1 % over `steps`."""
    return optax.adam(optax.cosine_decay_schedule(learning_rate, steps, alpha=0.01))
