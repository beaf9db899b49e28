"""Gradient-based absorber tuning with optax.

The pieces, each small:

- `Objective`: a weighted sum of peak metrics, optionally with a smooth maximum over time
  (log-sum-exp, `SmoothMax`) in place of a peak, and optionally the worst case over a
  scatter of one parameter (e.g. v0 ± 5 %).
- `Constraint`: an upper or lower limit on a metric or a parameter. Limits on tuned
  parameters tighten their bounds (held exactly by the reparametrisation); limits on
  metrics go through an augmented Lagrangian (PHR), whose multipliers are updated every
  `update_every` steps while the penalty grows as long as a limit is violated.
- `DesignProblem`: the base design, the tuned parameters with their bounds, the objective
  and the constraints. Bounds are held by a smooth reparametrisation,
  `θ = lo + (hi − lo) · sigmoid(u)`, so no clipping ever zeroes a gradient.
- `optimise`: many starts at once (`vmap`), one optax optimiser, one compiled step for the
  whole run, a history of every step, stopping rules per start, and the best feasible
  design over every evaluated point.
"""

from __future__ import annotations

import dataclasses
import sys
import time
from collections.abc import Callable, Mapping, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from ._design import METRICS, _metrics as _design_metrics, values_of, with_values
from ._gradients import GRADIENT_OPTIONS, SmoothMax, _check_wrt
from ._params import (
    PARAMETER_NAMES,
    ParameterError,
    RecoilParams,
    Smoothing,
    SolverOptions,
    _check_value,
    parameter_limits,
    params_to_values,
)
from ._solve import PEAK_KEYS, Status

#: `Peaks` field → `simulate --json` key.
_JSON_KEYS = {field: key for key, field in PEAK_KEYS.items()}


class Objective(eqx.Module):
    """`Σ_k weights[k] · metric_k`, to be minimised (metric units, e.g. N and m).

    - `weights`: metric name (`METRICS`) → weight.
    - `temperatures`: metric name → temperature (metric unit). Those metrics enter the
      objective the optimiser sees as their smooth maximum over time
      (`T·log((1/t1)∫exp(g/T)dt)`, see `SmoothMax`) instead of their peak: smooth where the
      peak jumps from one local maximum to another. Only `peak_displacement` and
      `peak_anchoring_force` have one. The *reported* objective always uses the peaks.
    - `scatter`: `(name, relative offsets)`: evaluate the design at `value·(1 + offset)`
      of that parameter for each offset (vmapped) and take the worst case, for the
      objective and the metric constraints alike (robust design).
    """

    weights: dict[str, float]
    temperatures: dict[str, float] = eqx.field(default_factory=dict)
    scatter: tuple[str, tuple[float, ...]] | None = eqx.field(default=None, static=True)

    def __check_init__(self):
        if not self.weights:
            raise ParameterError("Objective.weights is empty: weight at least one metric")
        for name in self.weights:
            if name not in METRICS:
                raise ParameterError(f"Objective: unknown metric {name!r}; choose from "
                                     f"{', '.join(METRICS)}")
        for name in self.temperatures:
            if name not in self.weights:
                raise ParameterError(f"Objective.temperatures names {name!r}, which the "
                                     "objective does not weight")
        SmoothMax(tuple(self.temperatures), list(self.temperatures.values()))
        if self.scatter is not None:
            name, offsets = self.scatter
            if name not in PARAMETER_NAMES:
                raise ParameterError(f"Objective.scatter: unknown parameter {name!r}")
            if not offsets or any(not -1.0 < o < 10.0 for o in offsets):
                raise ParameterError(
                    "Objective.scatter offsets must be relative offsets > -1, e.g. "
                    "(-0.05, 0, 0.05)")

    def smooth_max(self, temperature_scale=1.0) -> SmoothMax | None:
        """The `SmoothMax` of the objective's temperatures times `temperature_scale`."""
        if not self.temperatures:
            return None
        temperatures = jnp.asarray(list(self.temperatures.values())) * temperature_scale
        return SmoothMax(tuple(self.temperatures), temperatures)

    def of_json(self, metrics: Mapping[str, float]) -> float:
        """The objective (with peaks) of metrics keyed as `simulate --json`."""
        return float(self({name: metrics[_JSON_KEYS[name]] for name in self.weights}))

    def __call__(self, metrics: Mapping[str, jax.Array], smooth: bool = False) -> jax.Array:
        """The objective of `metrics` (a dict of scalars, or arrays of equal shape).
        `smooth=True` takes `smooth_<metric>` where the objective has a temperature."""
        total = 0.0
        for name, weight in self.weights.items():
            key = "smooth_" + name if smooth and name in self.temperatures else name
            total = total + weight * metrics[key]
        return total


class Constraint(eqx.Module):
    """`lower <= value <= upper` for a metric (`METRICS`) or a parameter (flat
    name), in its SI unit. Give one or both limits."""

    name: str = eqx.field(static=True)
    upper: float | None = eqx.field(default=None, static=True)
    lower: float | None = eqx.field(default=None, static=True)

    def __check_init__(self):
        if self.name not in METRICS and self.name not in PARAMETER_NAMES:
            raise ParameterError(
                f"Constraint on unknown quantity {self.name!r}; metrics: "
                f"{', '.join(METRICS)}; parameters: {', '.join(PARAMETER_NAMES)}")
        if self.upper is None and self.lower is None:
            raise ParameterError(f"Constraint on {self.name} has neither upper nor lower")
        if self.upper is not None and self.lower is not None and self.lower > self.upper:
            raise ParameterError(f"Constraint on {self.name}: lower {self.lower} > upper "
                                 f"{self.upper}")

    @property
    def is_metric(self) -> bool:
        return self.name in METRICS

    def limits(self) -> list[tuple[str, float]]:
        """`[(kind, limit)]` with kind `"max"` or `"min"`."""
        out = []
        if self.upper is not None:
            out.append(("max", float(self.upper)))
        if self.lower is not None:
            out.append(("min", float(self.lower)))
        return out


class DesignProblem(eqx.Module):
    """What to tune, within which bounds, for which objective, under which limits.

    - `params`: the base design. Parameters not tuned keep its values; the first start of
      each run begins at it.
    - `tune`: flat names of the tuned parameters (default gap, m, k_r, c_r).
    - `bounds`: name → `(lo, hi)`; default the documented range. Parameter constraints on
      tuned parameters tighten these.
    - `objective`, `constraints`, `smoothing`, `options` (default `GRADIENT_OPTIONS`).
    """

    params: RecoilParams
    objective: Objective
    tune: tuple[str, ...] = eqx.field(default=("gap", "m", "k_r", "c_r"), static=True)
    bounds: dict[str, tuple[float, float]] = eqx.field(default_factory=dict, static=True)
    constraints: tuple[Constraint, ...] = eqx.field(default=(), static=True)
    smoothing: Smoothing = Smoothing()
    options: SolverOptions = GRADIENT_OPTIONS

    def __check_init__(self):
        _check_wrt(self.params, self.tune)
        for name, bound in self.bounds.items():
            if name not in self.tune:
                raise ParameterError(f"bounds given for {name!r}, which is not tuned")
            lo, hi = bound
            if not lo < hi:
                raise ParameterError(f"bounds for {name}: need lo < hi, got ({lo}, {hi})")
            _check_value("bounds", name, lo, parameter_limits(name))
            _check_value("bounds", name, hi, parameter_limits(name))
        lower, upper = self.box()
        for name, lo, hi in zip(self.tune, lower, upper, strict=True):
            if not lo < hi:
                raise ParameterError(
                    f"the constraints leave no room for {name}: bounds ({lo:g}, {hi:g})")

    def box(self) -> tuple[np.ndarray, np.ndarray]:
        """The bounds of the tuned parameters, tightened by their constraints."""
        lower, upper = [], []
        for name in self.tune:
            lo, hi = self.bounds.get(name, parameter_limits(name).documented)
            for c in self.constraints:
                if c.name == name:
                    lo = lo if c.lower is None else max(lo, c.lower)
                    hi = hi if c.upper is None else min(hi, c.upper)
            lower.append(lo)
            upper.append(hi)
        return np.asarray(lower, dtype=float), np.asarray(upper, dtype=float)

    @property
    def metric_constraints(self) -> list[tuple[str, str, float]]:
        """`[(metric, kind, limit)]` handled by the augmented Lagrangian."""
        return [(c.name, kind, limit) for c in self.constraints if c.is_metric
                for kind, limit in c.limits()]


def _to_theta(u, lower, upper):
    return lower + (upper - lower) * jax.nn.sigmoid(u)


def _to_u(theta, lower, upper):
    fraction = np.clip((np.asarray(theta) - lower) / (upper - lower), 1e-4, 1 - 1e-4)
    return np.log(fraction) - np.log1p(-fraction)


def evaluate_design(problem: DesignProblem, theta, params=None, temperature_scale=1.0,
                    limits=None):
    """Metrics of the tuned values `theta` (worst case over the objective's scatter),
    their `status`, the smooth and exact objectives, and the normalised violations of the
    metric constraints (`<= 0` when satisfied). Differentiable in `theta`; unjitted.
    `temperature_scale` multiplies the objective's smooth-max temperatures; `limits`
    (shape `(C,)`) replaces the limits of `problem.metric_constraints`."""
    params = problem.params if params is None else params
    if limits is None:
        limits = jnp.asarray([limit for _, _, limit in problem.metric_constraints])
    objective = problem.objective
    smooth_max = objective.smooth_max(temperature_scale)

    def metrics_at(p):
        return _design_metrics(theta, params=p, wrt=problem.tune, smoothing=problem.smoothing,
                               options=problem.options, smooth_max=smooth_max)

    if objective.scatter is None:
        metrics, status = metrics_at(params)
    else:
        name, offsets = objective.scatter
        nominal = values_of(params, (name,))
        scattered = jax.vmap(lambda o: with_values(params, (name,), nominal * (1.0 + o)))(
            jnp.asarray(offsets))
        per_sample, statuses = jax.vmap(metrics_at)(scattered)
        # Worst case over the scatter: of the objective, and of each limited metric.
        smooth_values = objective(per_sample, smooth=True)
        exact_values = objective(per_sample)
        metrics = {k: jnp.max(v) for k, v in per_sample.items()}
        metrics["min_stroke"] = jnp.min(per_sample["min_stroke"])
        status = jnp.max(statuses)
        return (metrics, status, jnp.max(smooth_values), jnp.max(exact_values),
                _violations(problem, metrics, limits))
    return (metrics, status, objective(metrics, smooth=True), objective(metrics),
            _violations(problem, metrics, limits))


def _violations(problem: DesignProblem, metrics, limits) -> jax.Array:
    out = []
    for j, (name, kind, _) in enumerate(problem.metric_constraints):
        limit = limits[j]
        scale = jnp.where(limit != 0, jnp.abs(limit), 1.0)
        value = metrics[name]
        out.append((value - limit) / scale if kind == "max" else (limit - value) / scale)
    return jnp.stack(out) if out else jnp.zeros((0,))


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
    status: jax.Array
    smooth_objective: jax.Array
    objective: jax.Array
    violations: jax.Array


def _make_step(problem: DesignProblem, optimiser: optax.GradientTransformation, steps: int,
               anneal: float, update_every: int, penalty_growth: float, max_penalty: float,
               trace_counter):
    lower, upper = (jnp.asarray(b) for b in problem.box())

    def one(state: _State, params, limits, active):
        trace_counter.append(1)  # counts traces (tests check there is exactly one)

        def loss(u):
            theta = _to_theta(u, lower, upper)
            # Anneal the smooth-max temperatures geometrically to `anneal` of their start.
            progress = state.step / max(steps - 1, 1)
            metrics, status, smooth, exact, violations = evaluate_design(
                problem, theta, params, anneal**progress, limits)
            scale = jnp.where(state.step == 0, jax.lax.stop_gradient(jnp.abs(smooth)),
                              state.scale)
            scale = jnp.where(scale > 0, scale, 1.0)
            lam, rho = state.multipliers, state.penalty
            augmented = jnp.sum(jnp.maximum(lam + rho * violations, 0.0) ** 2 - lam**2) / (
                2.0 * rho)
            record = _StepRecord(theta, metrics, status, smooth, exact, violations)
            return smooth / scale + augmented, (record, scale)

        (value, (record, scale)), grad = jax.value_and_grad(loss, has_aux=True)(state.u)
        ok = (record.status == Status.OK) & jnp.isfinite(value) & jnp.all(jnp.isfinite(grad))
        move = active & ok
        updates, opt_state = optimiser.update(grad, state.opt_state, state.u)
        u = jnp.where(move, optax.apply_updates(state.u, updates), state.u)
        opt_state = jax.tree.map(lambda new, old: jnp.where(move, new, old), opt_state,
                                 state.opt_state)
        # Augmented Lagrangian (PHR): first-order multiplier update every `update_every`
        # steps; the penalty grows while any limit is still violated.
        at_update = move & ((state.step + 1) % update_every == 0)
        multipliers = jnp.where(
            at_update, jnp.maximum(state.multipliers + state.penalty * record.violations, 0.0),
            state.multipliers)
        violated = jnp.any(record.violations > 0)
        penalty = jnp.where(at_update & violated,
                            jnp.minimum(state.penalty * penalty_growth, max_penalty),
                            state.penalty)
        new = _State(u, opt_state, multipliers, penalty, scale, state.step + move)
        return new, record

    return eqx.filter_jit(jax.vmap(one))


@dataclasses.dataclass
class OptimiseResult:
    """Outcome of `optimise` (host NumPy arrays; `R` runs = scenarios × starts, `N`
    steps taken).

    - `best_theta`, `best_objective`, `best_run`, `best_step`: the best feasible point
      found over every evaluated point of every run (NaN objective if none was feasible),
      per scenario (`(S, P)`, `(S,)`...).
    - `history`: per step, arrays of shape `(N, R, ...)`: `theta`, `objective` (exact,
      with peaks), `smooth_objective`, `violations`, `status`, and each metric.
    - `converged`: per run, whether its stopping rule fired (`(R,)`); `converged_step`.
    - `simulations`: solves used (each with sensitivities; times the scatter samples).
    - `compilations`: how many times the step was traced (1).
    """

    problem: DesignProblem
    scenarios: int
    starts: int
    history: dict[str, np.ndarray]
    converged: np.ndarray
    converged_step: np.ndarray
    best_theta: np.ndarray
    best_objective: np.ndarray
    best_run: np.ndarray
    best_step: np.ndarray
    run_best_objective: np.ndarray
    run_best_theta: np.ndarray
    simulations: int
    steps: int
    seconds: float
    compilations: int
    scenario_params: RecoilParams  # the base design of each scenario, leading axis S
    scenario_limits: np.ndarray  # (S, C) the metric limits of each scenario

    @property
    def tune(self) -> tuple[str, ...]:
        return self.problem.tune

    def best_design(self, scenario: int = 0) -> dict[str, float]:
        """Every parameter of the best design of `scenario`, by the `simulate` names."""
        params = self.best_params(scenario)
        return {k: float(np.asarray(v)) for k, v in params_to_values(params).items()}

    def best_params(self, scenario: int = 0) -> RecoilParams:
        base = jax.tree.map(lambda x: x[scenario], self.scenario_params)
        return with_values(base, self.tune, self.best_theta[scenario])

    def clusters(self, scenario: int = 0, rtol: float = 1e-3) -> list[dict]:
        """Where the starts of `scenario` ended: groups of runs whose best objectives agree
        within `rtol`, best first, with their count, how many converged, the group's best
        design, and how many of its runs ended with no impact at all (on the plateau
        where the gap gradient is exactly zero)."""
        runs = np.arange(scenario * self.starts, (scenario + 1) * self.starts)
        values = self.run_best_objective[runs]
        order = runs[np.argsort(np.where(np.isfinite(values), values, np.inf))]
        groups: list[dict] = []
        for r in order:
            value = self.run_best_objective[r]
            if not np.isfinite(value):
                groups.append({"objective": None, "count": 1, "runs": [int(r)],
                               "design": None, "converged": int(self.converged[r]),
                               "no_impact": int(self._no_impact(r))})
                continue
            for g in groups:
                if g["objective"] is not None and abs(value - g["objective"]) <= rtol * abs(
                        g["objective"]):
                    g["count"] += 1
                    g["runs"].append(int(r))
                    g["converged"] += int(self.converged[r])
                    g["no_impact"] += int(self._no_impact(r))
                    break
            else:
                groups.append({"objective": float(value), "count": 1, "runs": [int(r)],
                               "design": dict(zip(self.tune, map(float,
                                                                 self.run_best_theta[r]),
                                                  strict=True)),
                               "converged": int(self.converged[r]),
                               "no_impact": int(self._no_impact(r))})
        return groups

    def _no_impact(self, run: int) -> bool:
        contact = self.history["peak_contact_force"][:, run]
        return bool(contact[-1] == 0.0)


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
    worst = np.max(violations, axis=(0, 2)) if violations.shape[-1] else np.zeros_like(spread)
    return flat & (worst <= vtol)


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
) -> OptimiseResult:
    """Minimise `problem.objective` subject to `problem.constraints` from `starts` starting
    points at once (vmapped), with `optimiser` (default Adam with a cosine-decayed step of
    0.1 → 0.001 in the sigmoid coordinates).

    - `anneal`: the smooth-max temperatures fall geometrically to this fraction of the
      objective's over the `steps` (a continuation: smooth early, close to the peak late).
    - `scenarios`: optionally a batched `RecoilParams` (leading axis `S`): the problem is
      solved for each (e.g. one absorber mass per point of a Pareto front), `starts` each;
      `scenario_limits`: metric name → one limit per scenario (an ε-constraint front).
    - Stopping: a run stops once, over the last `patience` steps (after `min_steps`),
      its objective has moved by at most `ftol` (relative) and its metric limits have
      held within `vtol` (relative); a run whose solve fails stops too. The optimisation
      stops when every run has stopped, or after `steps`. The best design is the best
      *feasible* point (every limit strictly held) over all steps of all runs.
    - `progress`: a progress line on stderr (default: when stderr is a terminal).
    - `callback(step, record)`: called after each step with the host-side record.
    """
    if starts < 1 or steps < 1:
        raise ParameterError(f"starts and steps must be >= 1 (got {starts}, {steps})")
    if optimiser is None:
        optimiser = default_optimiser(0.1, steps)
    constraints = problem.metric_constraints
    limits = np.asarray([[limit for _, _, limit in constraints]], dtype=float).reshape(1, -1)
    sizes = set()
    if scenarios is not None:
        # Leaves with a leading axis vary per scenario; scalars are shared.
        sizes |= {int(np.shape(x)[0]) for x in jax.tree.leaves(scenarios) if np.ndim(x)}
        if not sizes:
            raise ParameterError("scenarios: no parameter has a leading scenario axis")
    if scenario_limits:
        names = [name for name, _, _ in constraints]
        for name, values in scenario_limits.items():
            if name not in names:
                raise ParameterError(f"scenario_limits names {name!r}, which has no metric "
                                     f"constraint; constrained: {', '.join(names) or 'none'}")
            sizes.add(len(values))
    if len(sizes) > 1:
        raise ParameterError(f"scenarios of different lengths: {sorted(sizes)}")
    n_scenarios = sizes.pop() if sizes else 1
    # Every parameter is a scalar per design: shared values broadcast over the scenarios.
    params = jax.tree.map(lambda x: jnp.broadcast_to(jnp.asarray(x, dtype=float),
                                                     (n_scenarios,)),
                          problem.params if scenarios is None else scenarios)
    limits = np.repeat(limits, n_scenarios, axis=0)
    for name, values in (scenario_limits or {}).items():
        limits[:, [c[0] for c in constraints].index(name)] = np.asarray(values, dtype=float)
    runs = n_scenarios * starts
    run_params = jax.tree.map(lambda x: jnp.repeat(jnp.asarray(x), starts, axis=0), params)
    run_limits = jnp.asarray(np.repeat(limits, starts, axis=0))

    lower, upper = problem.box()
    theta0 = _start_points(problem, params, n_scenarios, starts, seed)
    u0 = jnp.asarray(_to_u(theta0, lower, upper))
    n_limits = len(problem.metric_constraints)
    state = _State(
        u=u0,
        opt_state=jax.vmap(optimiser.init)(u0),
        multipliers=jnp.zeros((runs, n_limits)),
        penalty=jnp.full((runs,), float(penalty)),
        scale=jnp.ones((runs,)),
        step=jnp.zeros((runs,), dtype=int),
    )
    traces: list[int] = []
    step_fn = _make_step(problem, optimiser, steps, anneal, update_every, penalty_growth,
                         max_penalty, traces)
    samples = 1 if problem.objective.scatter is None else len(problem.objective.scatter[1])

    show = sys.stderr.isatty() if progress is None else progress
    active = np.ones(runs, dtype=bool)
    converged_step = np.full(runs, -1)
    records: list[_StepRecord] = []
    simulations = 0
    best_so_far = np.inf
    start_time = time.perf_counter()
    for k in range(steps):
        state, record = step_fn(state, run_params, run_limits, jnp.asarray(active))
        record = jax.tree.map(np.asarray, record)
        records.append(record)
        simulations += runs * samples
        failed = record.status != Status.OK
        stop = active & (failed | ((k + 1 >= min_steps) & _stationary(records, patience, ftol,
                                                                     vtol)))
        converged_step = np.where(stop & ~failed, k, converged_step)
        active &= ~stop
        if callback is not None:
            callback(k, {"objective": record.objective, "active": active.copy()})
        feasible = np.all(record.violations <= 0, axis=-1) & (record.status == Status.OK)
        best_so_far = min(best_so_far, float(np.min(np.where(feasible, record.objective,
                                                              np.inf))))
        tty = sys.stderr.isatty()
        last = k + 1 == steps or not active.any()
        if show and (tty or last or (k + 1) % max(1, steps // 10) == 0):
            print(f"optimise: step {k + 1}/{steps}, {int(active.sum())}/{runs} runs active, "
                  f"best feasible objective {best_so_far:.6g}, "
                  f"{time.perf_counter() - start_time:.1f} s",
                  end="\r" if tty and not last else "\n", file=sys.stderr, flush=True)
        if not active.any():
            break

    history = {
        "theta": np.stack([r.theta for r in records]),
        "objective": np.stack([r.objective for r in records]),
        "smooth_objective": np.stack([r.smooth_objective for r in records]),
        "violations": np.stack([r.violations for r in records]),
        "status": np.stack([r.status for r in records]),
    } | {name: np.stack([r.metrics[name] for r in records]) for name in records[0].metrics}
    feasible = np.all(history["violations"] <= 0, axis=-1) & (history["status"] == Status.OK)
    values = np.where(feasible, history["objective"], np.inf)  # (N, R)
    run_best_step = np.argmin(values, axis=0)
    run_best_objective = values[run_best_step, np.arange(runs)]
    run_best_objective = np.where(np.isfinite(run_best_objective), run_best_objective, np.nan)
    run_best_theta = history["theta"][run_best_step, np.arange(runs)]

    best_theta, best_objective, best_run, best_step = [], [], [], []
    for s in range(n_scenarios):
        rs = np.arange(s * starts, (s + 1) * starts)
        scores = np.where(np.isnan(run_best_objective[rs]), np.inf, run_best_objective[rs])
        r = int(rs[np.argmin(scores)])
        best_run.append(r)
        best_step.append(int(run_best_step[r]))
        best_objective.append(run_best_objective[r])
        best_theta.append(run_best_theta[r])
    return OptimiseResult(
        problem=problem,
        scenarios=n_scenarios,
        starts=starts,
        history=history,
        converged=converged_step >= 0,
        converged_step=converged_step,
        best_theta=np.asarray(best_theta),
        best_objective=np.asarray(best_objective),
        best_run=np.asarray(best_run),
        best_step=np.asarray(best_step),
        run_best_objective=run_best_objective,
        run_best_theta=run_best_theta,
        simulations=simulations,
        steps=len(records),
        seconds=time.perf_counter() - start_time,
        compilations=len(traces),
        scenario_params=params,
        scenario_limits=limits,
    )


def constraint_report(problem: DesignProblem, design: Mapping[str, float],
                      metrics: Mapping[str, float], limits=None) -> dict[str, dict]:
    """`{"<name> (max|min)": {value, limit, satisfied}}` for every constraint of `problem`.

    `design`: flat parameter values; `metrics`: the peaks with `simulate --json` keys
    (`Peaks.to_dict()`); `limits`: optional per-scenario limits of the metric
    constraints (in the order of `problem.metric_constraints`)."""
    metric_limits = iter([] if limits is None else [float(x) for x in limits])
    report = {}
    for c in problem.constraints:
        for kind, limit in c.limits():
            if c.is_metric:
                limit = next(metric_limits) if limits is not None else limit
                value = float(metrics[_JSON_KEYS[c.name]])
            else:
                value = float(design[c.name])
            ok = value <= limit if kind == "max" else value >= limit
            report[f"{c.name} ({kind})"] = {"value": value, "limit": float(limit),
                                           "satisfied": bool(ok)}
    return report


def default_optimiser(learning_rate: float, steps: int) -> optax.GradientTransformation:
    """Adam on the sigmoid coordinates, its step cosine-decayed to 1 % over `steps`."""
    return optax.adam(optax.cosine_decay_schedule(learning_rate, steps, alpha=0.01))

