"""What a design study asks: objectives, constraints and the design problem, and the
evaluation of one design as a differentiable function of its tuned values.

- `Objective`: a weighted sum of peak metrics, optionally with a smooth maximum over time
  (log-sum-exp, `SmoothMax`) in place of a peak, and optionally the worst case over a
  scatter of one parameter (e.g. v0 ± 5 %).
- `Constraint`: an upper or lower limit on a metric or a parameter, at every firing
  condition or at some.
- `Condition`: a firing condition (e.g. an elevation, a charge's `v0`): values of
  untuned parameters the design must also be good at.
- `DesignProblem`: the base design, the tuned parameters with their bounds, the objective,
  the constraints and the firing conditions (the objective their worst case).
- `evaluate_design`: metrics, objectives and normalised limit violations of tuned values,
  differentiable through the forward sensitivities (`design_metrics`).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._model.derivatives import GRADIENT_OPTIONS, check_wrt
from .._model.differentiable import design_metrics
from .._model.feasibility import FEASIBILITY_TOLERANCE
from .._model.forces.system import check_envelope_metrics
from .._model.metrics import METRICS, metric, worst_case
from .._model.parameter_table import PARAMETERS, parameter
from .._model.params import (
    RecoilParams,
    check_present,
    params_from_values,
    params_to_values,
    values_of,
    with_values,
)
from .._model.registry import ParameterError, check_value, is_concrete
from .._model.settings import Smoothing, SolverOptions, end_time
from .._model.smooth_max import MetricSeries, SmoothMax, smooth_name
from .._model.solve import last_firing
from .._model.status import status_item

__all__ = [
    "Agreement",
    "Condition",
    "Constraint",
    "DesignEvaluation",
    "DesignProblem",
    "Objective",
    "closest_miss",
    "constraint_report",
    "evaluate_design",
    "metric_violations",
]


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
      objective and the metric constraints alike (robust design). Several parameters
      move together as `((name, ...), ((offset, ...), ...))`: one tuple of relative
      offsets per point (e.g. a calibration's sigma points).
    - `quantile`: with a scatter, hold the objective and the limits at this quantile
      towards the worst (`0 < q <= 1`; e.g. 0.9: nine tenths of the scatter points are no
      worse) instead of the worst case (`worst_case`). For a sampled scatter, where the
      worst of many draws is an outlier's.
    """

    weights: dict[str, float]
    temperatures: dict[str, float] = eqx.field(default_factory=dict)
    scatter: tuple[Any, tuple[Any, ...]] | None = eqx.field(default=None, static=True)
    quantile: float | None = eqx.field(default=None, static=True)

    def __check_init__(self):
        if not self.weights:
            raise ParameterError("Objective.weights is empty: weight at least one metric")
        for name, weight in self.weights.items():
            metric(name)
            if not _finite_number(weight):
                raise ParameterError(
                    f"Objective.weights[{name!r}] = {weight!r} is not a finite number"
                )
        for name in self.temperatures:
            if name not in self.weights:
                raise ParameterError(
                    f"Objective.temperatures names {name!r}, which the objective does not weight"
                )
        SmoothMax(tuple(self.temperatures), list(self.temperatures.values()))
        if self.scatter is not None:
            names, offsets = self.scatter_points
            for name in names:
                parameter(name)
            if offsets.size == 0 or offsets.shape[1] != len(names):
                raise ParameterError(
                    "Objective.scatter needs offsets: one per point for one parameter, or one "
                    "tuple per point with an offset for each parameter"
                )
            if not np.all((offsets > -1.0) & (offsets < 10.0)):
                raise ParameterError(
                    "Objective.scatter offsets must be relative offsets > -1, e.g. (-0.05, 0, 0.05)"
                )
        if self.quantile is not None:
            q = self.quantile
            if isinstance(q, bool) or not isinstance(q, (int, float)) or not 0.0 < q <= 1.0:
                raise ParameterError(
                    f"Objective.quantile = {q!r} is invalid: valid 0 < quantile <= 1 (1: the "
                    "worst case)"
                )
            if self.scatter is None:
                raise ParameterError(
                    "Objective.quantile needs a scatter: it is taken over the scatter's points"
                )

    @property
    def unit(self) -> str:
        """The objective's unit: its metrics' (`METRICS`) when they share one (the weights
        taken as pure numbers), else theirs as a weighted sum (`"N + m (weighted)"`)."""
        units = list(dict.fromkeys(METRICS[name].unit for name in self.weights))
        return units[0] if len(units) == 1 else " + ".join(units) + " (weighted)"

    def over_scatter(self, values: Any, xp: Any = np) -> Any:
        """The objective over the scatter from its value at each point `(S,)`: the
        greatest, or the `quantile`."""
        return xp.max(values) if self.quantile is None else xp.quantile(values, self.quantile)

    @property
    def scatter_points(self) -> tuple[tuple[str, ...], np.ndarray]:
        """The scatter as `(names (k,), relative offsets (S, k))` (either form)."""
        assert self.scatter is not None
        names, offsets = self.scatter
        if isinstance(names, str):
            return (names,), np.asarray(offsets, dtype=float).reshape(-1, 1)
        return tuple(names), np.asarray(offsets, dtype=float).reshape(len(offsets), -1)

    def smooth_max(self, temperature_scale=1.0) -> SmoothMax | None:
        """The `SmoothMax` of the objective's temperatures times `temperature_scale`."""
        if not self.temperatures:
            return None
        temperatures = jnp.asarray(list(self.temperatures.values())) * temperature_scale
        return SmoothMax(tuple(self.temperatures), temperatures)

    def __call__(self, metrics: Mapping[str, Any], smooth: bool = False) -> Any:
        """The objective of `metrics` (metric name → scalar, or arrays of equal shape).
        `smooth=True` takes the smooth maximum where the objective has a temperature."""
        total = 0.0
        for name, weight in self.weights.items():
            key = smooth_name(name) if smooth and name in self.temperatures else name
            total = total + weight * metrics[key]
        return total


def _finite_number(value: Any) -> bool:
    """A real number (not a bool), finite: a limit's or a weight's value (a tracer
    passes: it is checked where it is concrete)."""
    if isinstance(value, bool) or not is_concrete(value):
        return not isinstance(value, bool)
    try:
        array = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        return False
    return array.ndim == 0 and bool(np.isfinite(array))


def _condition_names(names: Any) -> Any:
    """A list of condition names as a tuple (a static field must hash); anything else
    as given, for `Constraint`'s check."""
    return tuple(names) if isinstance(names, list) else names


class Constraint(eqx.Module):
    """`lower <= value <= upper` for a metric (`METRICS`) or a parameter (flat
    name), in its SI unit. Give one or both limits."""

    name: str = eqx.field(static=True)
    upper: float | None = eqx.field(default=None, static=True)
    lower: float | None = eqx.field(default=None, static=True)
    conditions: tuple[str, ...] | None = eqx.field(
        default=None, static=True, converter=_condition_names
    )

    def __check_init__(self):
        if self.conditions is not None:
            if isinstance(self.conditions, str) or not self.conditions:
                raise ParameterError(
                    f"Constraint on {self.name}: conditions must be a non-empty tuple of "
                    "condition names (None: every condition)"
                )
            if self.name not in METRICS:
                raise ParameterError(
                    f"Constraint on {self.name}: only a metric's limit can name conditions "
                    "(a parameter's value is the design's, the same at every condition)"
                )
        if self.name not in METRICS and self.name not in PARAMETERS:
            raise ParameterError(
                f"Constraint on unknown quantity {self.name!r}; metrics: "
                f"{', '.join(METRICS)}; parameters: {', '.join(PARAMETERS)}"
            )
        if self.upper is None and self.lower is None:
            raise ParameterError(f"Constraint on {self.name} has neither upper nor lower")
        for kind, limit in (("max", self.upper), ("min", self.lower)):
            if limit is not None and not _finite_number(limit):
                raise ParameterError(
                    f"Constraint on {self.name}: {kind} = {limit!r} is not a finite number "
                    "(leave a side out for no limit there)"
                )
        if self.upper is not None and self.lower is not None and self.lower > self.upper:
            raise ParameterError(
                f"Constraint on {self.name}: lower {self.lower} > upper {self.upper}"
            )

    @property
    def is_metric(self) -> bool:
        return self.name in METRICS

    def label(self, kind: str) -> str:
        """How reports name its limit of `kind` ("max" or "min"): `"return_time (max)"`,
        with `" at 0°, 35°"` when it holds at some conditions only."""
        where = "" if self.conditions is None else " at " + ", ".join(self.conditions)
        return f"{self.name} ({kind}){where}"

    def limits(self) -> list[tuple[str, float]]:
        """`[(kind, limit)]` with kind `"max"` or `"min"`."""
        out = []
        if self.upper is not None:
            out.append(("max", float(self.upper)))
        if self.lower is not None:
            out.append(("min", float(self.lower)))
        return out


def _condition_values(values: Any) -> tuple[tuple[str, float], ...]:
    pairs = values.items() if isinstance(values, Mapping) else values
    return tuple((str(name), float(value)) for name, value in pairs)


class Condition(eqx.Module):
    """A firing condition: the values `(flat name → SI value)` of untuned parameters
    that the design must also be good at, e.g. `Condition("70°", {"elevation": 70.0})`
    or a charge, `Condition("charge 2", {"v0": 8.0})`. A `DesignProblem` with conditions
    solves every design at each (in one batched program), and its objective is their
    worst case."""

    name: str = eqx.field(static=True)
    values: tuple[tuple[str, float], ...] = eqx.field(static=True, converter=_condition_values)

    def __check_init__(self):
        if not isinstance(self.name, str) or not self.name.strip():
            raise ParameterError("Condition.name must be a non-empty string")
        if not self.values:
            raise ParameterError(f"condition {self.name!r} sets no parameter")
        names = [name for name, _ in self.values]
        if len(set(names)) != len(names):
            raise ParameterError(f"condition {self.name!r} sets a parameter twice: {names}")
        for name, value in self.values:
            check_value(f"condition {self.name!r}", name, value, parameter(name))

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(name for name, _ in self.values)


class DesignProblem(eqx.Module):
    """What to tune, within which bounds, for which objective, under which limits.

    - `params`: the base design. Parameters not tuned keep its values; the first start of
      each run begins at it.
    - `tune`: flat names of the tuned parameters (default gap, m, k_r, c_r).
    - `bounds`: name → `(lo, hi)`; default the documented range. Parameter constraints on
      tuned parameters tighten these.
    - `objective`, `constraints`, `smoothing`, `options` (default `GRADIENT_OPTIONS`).
    - `conditions`: firing conditions (`Condition`s): each design is solved at each,
      the objective is the worst over them and each metric limit the worst over the
      conditions it names (`Constraint.conditions`, default all). Their parameters must
      be in the base design and not tuned. Not with the objective's scatter.
    """

    params: RecoilParams
    objective: Objective
    tune: tuple[str, ...] = eqx.field(default=("gap", "m", "k_r", "c_r"), static=True)
    bounds: dict[str, tuple[float, float]] = eqx.field(default_factory=dict, static=True)
    constraints: tuple[Constraint, ...] = eqx.field(default=(), static=True)
    smoothing: Smoothing = Smoothing()
    options: SolverOptions = GRADIENT_OPTIONS
    conditions: tuple[Condition, ...] = eqx.field(default=(), static=True)

    def __check_init__(self):
        check_wrt(self.params, self.tune)
        self._check_conditions()
        asked = [*self.objective.weights, *(c.name for c in self.constraints if c.is_metric)]
        check_envelope_metrics(self.params, asked, "study")
        self._check_return_limits()
        for name, bound in self.bounds.items():
            if name not in self.tune:
                raise ParameterError(f"bounds given for {name!r}, which is not tuned")
            lo, hi = bound
            if not lo < hi:
                raise ParameterError(f"bounds for {name}: need lo < hi, got ({lo}, {hi})")
            check_value("bounds", name, lo, PARAMETERS[name])
            check_value("bounds", name, hi, PARAMETERS[name])
        lower, upper = self.box()
        for name, lo, hi in zip(self.tune, lower, upper, strict=True):
            if not lo < hi:
                raise ParameterError(
                    f"the constraints leave no room for {name}: bounds ({lo:g}, {hi:g})"
                )

    def _check_conditions(self) -> None:
        names = [c.name for c in self.conditions]
        if len(set(names)) != len(names):
            raise ParameterError(f"study: two conditions share a name: {names}")
        if self.conditions and self.objective.scatter is not None:
            raise ParameterError(
                "study: conditions and the objective's scatter cannot both be given (each "
                "is a worst case over designs); list the scatter's values as conditions"
            )
        for condition in self.conditions:
            for name in condition.names:
                if name in self.tune:
                    raise ParameterError(
                        f"condition {condition.name!r} sets {name}, which is tuned: a "
                        "condition sets untuned parameters only"
                    )
                try:
                    check_present(self.params, parameter(name))
                except ParameterError as error:
                    raise ParameterError(
                        f"condition {condition.name!r}: {error}; give {name} in the design too"
                    ) from None
            self._check_condition_design(condition)
        for c in self.constraints:
            for name in c.conditions or ():
                if name not in names:
                    known = ", ".join(names) if names else "none"
                    raise ParameterError(
                        f"the limit on {c.name} names condition {name!r}; conditions: {known}"
                    )

    def _check_condition_design(self, condition: Condition) -> None:
        """The whole design `condition` makes, checked as a design is (its values
        together: a mount heavier than the gun on it) and for the metrics asked of it
        there (a stability limit needs a mount), before anything compiles."""
        if not is_concrete(self.params):
            return
        asked = [*self.objective.weights]
        asked += [
            c.name
            for c in self.constraints
            if c.is_metric and (c.conditions is None or condition.name in c.conditions)
        ]
        try:
            design = params_from_values(params_to_values(self.params) | dict(condition.values))
            check_envelope_metrics(design, asked, f"condition {condition.name!r}")
        except ParameterError as error:
            message = str(error)
            if not message.startswith(f"condition {condition.name!r}"):
                message = f"condition {condition.name!r}: {message}"
            raise ParameterError(message) from None

    def _check_return_limits(self) -> None:
        """A design that has not come back by `t1` is reported with the time it was seen
        away, `t1 − t_last` (`Peaks`), which fails every upper limit on `return_time`
        below that: refuse a limit at or above it, which such a design would pass."""
        for c in self.constraints:
            if c.name != "return_time" or c.upper is None:
                continue
            seen = np.asarray(end_time(self.params, self.options) - last_firing(self.params))
            if is_concrete(seen) and c.upper >= (least := float(np.min(seen))):
                raise ParameterError(
                    f"study: return_time <= {c.upper:g} s is not below the {least:g} s "
                    "the solve sees after the last round, so a barrel that never comes back "
                    "would meet it: lower the limit or raise t1"
                )

    def box(self) -> tuple[np.ndarray, np.ndarray]:
        """The bounds of the tuned parameters, tightened by their constraints."""
        lower, upper = [], []
        for name in self.tune:
            documented = PARAMETERS[name].documented
            lo, hi = self.bounds.get(name, documented or (np.nan, np.nan))
            for c in self.constraints:
                if c.name == name:
                    lo = lo if c.lower is None else max(lo, c.lower)
                    hi = hi if c.upper is None else min(hi, c.upper)
            lower.append(lo)
            upper.append(hi)
        return np.asarray(lower, dtype=float), np.asarray(upper, dtype=float)

    @property
    def condition_names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.conditions)

    def condition_values(self, own: Mapping[str, Any], xp: Any = np) -> dict[str, Any]:
        """Each parameter a condition sets, at every condition, by name: `(..., K)`, the
        condition's value, or `own[name]` (`(...)`, the design's) where it sets none.
        `xp`: `numpy` or `jax.numpy`."""
        out = {}
        for name in dict.fromkeys(n for c in self.conditions for n in c.names):
            value = xp.asarray(own[name], dtype=float)
            set_by = [dict(c.values).get(name) for c in self.conditions]
            columns = [value if v is None else xp.full_like(value, v) for v in set_by]
            out[name] = xp.stack(columns, axis=-1)
        return out

    def at_conditions(self, params: RecoilParams) -> RecoilParams:
        """`params` at each condition, stacked along a leading axis `(K, ...)`
        (`condition_values`). The structure must have conditions."""
        names = tuple(dict.fromkeys(n for c in self.conditions for n in c.names))
        own = dict(zip(names, values_of(params, names), strict=True))
        values = self.condition_values(own, jnp)
        stacked = jnp.stack([values[name] for name in names], axis=1)  # (K, names)
        return jax.vmap(lambda v: with_values(params, names, v))(stacked)

    @property
    def solves_per_design(self) -> int:
        """The solves one evaluation of a design takes: one per scatter point or
        condition."""
        scatter = self.objective.scatter
        return max(1, len(self.conditions)) * (1 if scatter is None else len(scatter[1]))

    @property
    def limit_labels(self) -> list[str]:
        """The name of each metric limit in reports, in `metric_constraints`' order
        (`Constraint.label`)."""
        return [c.label(kind) for c in self.constraints if c.is_metric for kind, _ in c.limits()]

    @property
    def limit_conditions(self) -> list[np.ndarray]:
        """For each metric limit (`metric_constraints`' order), the indices of the
        conditions it holds at (all of them where it names none)."""
        names = self.condition_names
        every = np.arange(len(names))
        return [
            every if c.conditions is None else np.asarray([names.index(n) for n in c.conditions])
            for c in self.constraints
            if c.is_metric
            for _ in c.limits()
        ]

    @property
    def metric_constraints(self) -> list[tuple[str, str, float]]:
        """`[(metric, kind, limit)]`: the limits on metrics (`kind` "max" or "min"), which
        the optimisers hold through the solve (`metric_violations`); parameter bounds are
        the search space's."""
        return [
            (c.name, kind, limit)
            for c in self.constraints
            if c.is_metric
            for kind, limit in c.limits()
        ]


class Agreement(NamedTuple):
    """How firmly an optimiser run found its best design (`OptimiseResult.agreement`).

    - `starts`: local runs from the starts (the given design and the sampled points;
      not basin hopping's, which start beside the best) that evaluated a point;
    - `regions`: those starts grouped by where they began (`search` places every other
      start beside an earlier one: a start within `SobolStarts.spacing`, max-norm in normalised
      coordinates, of a region's first joins it; `optimise`'s starts are each their
      own);
    - `reached`: the regions with a run that evaluated a feasible design within `rtol`
      (relative, default 1e-3: 0.1 %) of the best objective.
    """

    reached: int
    regions: int
    starts: int
    rtol: float = 1e-3

    @property
    def found_once(self) -> bool:
        """Whether at most one of several regions reached the best, or none did (a sample
        or basin hopping found it): a rerun with another seed may end in another
        basin."""
        return self.starts > 0 and (self.reached == 0 or (self.regions >= 2 and self.reached == 1))

    def line(self) -> str | None:
        """The summary line, `best design reached from 2 of 5 start regions (8 starts,
        within 0.1 %)` (`k of n starts` where each start is its own region; the
        percentage is `rtol`'s), with a caution when `found_once`; None when no start
        ran."""
        if self.starts == 0:
            return None
        within = f"within {100 * self.rtol:g} %"
        if self.regions == self.starts:
            plural = "s" if self.starts != 1 else ""
            counted = f"{self.reached} of {self.starts} start{plural} ({within})"
        else:
            counted = (
                f"{self.reached} of {self.regions} start regions ({self.starts} starts, {within})"
            )
        line = f"best design reached from {counted}"
        if self.found_once:
            line += ": compare a few --seed values before relying on it"
        return line


class DesignEvaluation(NamedTuple):
    """What `evaluate_design` gives at one point (arrays; traced inside a `jit`).

    - `metrics`: metric name → value (worst case over the objective's scatter);
    - `status`: the solve's `Status`;
    - `smooth_objective`: the objective the optimiser sees (smooth maxima where the
      objective has temperatures);
    - `objective`: the objective with the true peaks;
    - `violations (C,)`: the normalised violations of the metric constraints (`<= 0`
      where held);
    - `conditions`: with firing conditions, the metrics at each, name → `(K,)` (the
      `metrics` are their worst case); else None.
    """

    metrics: dict[str, Any]
    status: Any
    smooth_objective: Any
    objective: Any
    violations: Any
    conditions: dict[str, Any] | None = None


def evaluate_design(
    problem: DesignProblem,
    theta,
    params=None,
    temperature_scale: Any = 1.0,
    limits=None,
    series: MetricSeries | None = None,
):
    """Evaluate the tuned values `theta` (shape `(len(problem.tune),)`) of `problem`.

    Differentiable in `theta` (through the forward sensitivities); unjitted.

    **Arguments:**

    - `params`: the base design (default `problem.params`).
    - `temperature_scale`: multiplies the objective's smooth-max temperatures.
    - `limits`: shape `(C,)`, replaces the limits of `problem.metric_constraints`.
    - `series`: a `MetricSeries`: its signals join the metrics (`series_<metric>`), and
      the objective is not smoothed (the smooth objective is the exact one).

    **Returns:** a `DesignEvaluation`: the metrics by name (worst case over the
    objective's scatter or the conditions), the solve's `Status`, the objective the
    optimiser sees and the one with true peaks, and the normalised violations of the
    metric constraints (`<= 0` when satisfied). With conditions (`DesignProblem.conditions`)
    every condition is solved in one vmapped program: the objectives are the worst over
    them, each limit's violation the worst over its conditions, and `conditions` holds
    the metrics at each.
    """
    params = problem.params if params is None else params
    if limits is None:
        limits = jnp.asarray([limit for _, _, limit in problem.metric_constraints])
    objective = problem.objective
    smooth_max = None if series is not None else objective.smooth_max(temperature_scale)

    def metrics_at(p):
        metrics, code = design_metrics(
            theta,
            params=p,
            wrt=problem.tune,
            smoothing=problem.smoothing,
            options=problem.options,
            smooth_max=smooth_max,
            series=series,
        )
        return metrics, status_item(code)

    if series is not None and (objective.scatter is not None or problem.conditions):
        raise ParameterError(
            "evaluate_design: a MetricSeries takes neither a scatter objective nor conditions"
        )
    if objective.scatter is None and not problem.conditions:
        metrics, status = metrics_at(params)
    else:
        per_point, statuses = jax.vmap(metrics_at)(_points(problem, params))
        # Worst case (or quantile) over the scatter or the conditions: of the objective,
        # and of each limited metric (with conditions, over those each limit names).
        smooth_values = objective(per_point, smooth=True)
        exact_values = objective(per_point)
        metrics = worst_case(per_point, xp=jnp, quantile=objective.quantile)
        at_conditions = per_point if problem.conditions else None
        return DesignEvaluation(
            metrics=metrics,
            status=jax.tree.map(jnp.max, statuses),
            smooth_objective=objective.over_scatter(smooth_values, jnp),
            objective=objective.over_scatter(exact_values, jnp),
            violations=_violations(problem, per_point if problem.conditions else metrics, limits),
            conditions=at_conditions,
        )
    return DesignEvaluation(
        metrics=metrics,
        status=status,
        smooth_objective=objective(metrics, smooth=smooth_max is not None),
        objective=objective(metrics),
        violations=_violations(problem, metrics, limits),
    )


def _points(problem: DesignProblem, params):
    """The designs the objective is the worst over, stacked: `params` at each of the
    problem's conditions, or at each point of its objective's scatter."""
    if problem.conditions:
        return problem.at_conditions(params)
    names, offsets = problem.objective.scatter_points
    nominal = values_of(params, names)
    return jax.vmap(lambda o: with_values(params, names, nominal * (1.0 + o)))(jnp.asarray(offsets))


def _violations(problem: DesignProblem, metrics, limits) -> jax.Array:
    return metric_violations(problem, metrics, limits, xp=jnp)


def metric_violations(problem: DesignProblem, metrics: Mapping[str, Any], limits=None, xp=np):
    """The normalised violations of `problem`'s metric limits, `(value − limit)/|limit|`
    for a `max` and `(limit − value)/|limit|` for a `min` (`|limit|` → 1 for a zero limit):
    `<= 0` where a limit holds.

    **Arguments:** `metrics`: metric name → values of one shape `(...)`, or `(..., K)`
    for a problem with `K` conditions (the metrics at each; a limit's violation is then
    the worst over its conditions); `limits`: `(C,)` in the order of
    `problem.metric_constraints` (default theirs); `xp`: `numpy` or `jax.numpy`.

    **Returns:** `(..., C)`.
    """
    constraints = problem.metric_constraints
    if limits is None:
        limits = [limit for _, _, limit in constraints]
    at = problem.limit_conditions
    out = []
    for j, (name, kind, _) in enumerate(constraints):
        limit = limits[j]
        scale = xp.where(limit != 0, xp.abs(limit), 1.0)
        value = xp.asarray(metrics[name])
        violation = (value - limit) / scale if kind == "max" else (limit - value) / scale
        if problem.conditions:
            violation = xp.max(violation[..., at[j]], axis=-1)
        out.append(violation)
    if out:
        return xp.stack(out, axis=-1)
    shape = xp.shape(metrics[next(iter(metrics))]) if metrics else ()
    if problem.conditions:
        shape = shape[:-1]
    return xp.zeros((*shape, 0))


def closest_miss(problem: DesignProblem, violations) -> dict[str, dict]:
    """How the least violating design misses each metric limit it breaks.

    **Arguments:** `violations (C,)`: its normalised violations (`metric_violations`).

    **Returns:** `{"<metric> (max|min)": {"limit", "value", "missed_by", "missed_by_relative"}}`
    for every limit it misses (value and miss in the metric's SI unit).
    """
    missed = {}
    for (_, kind, limit), label, v in zip(
        problem.metric_constraints,
        problem.limit_labels,
        np.asarray(violations, dtype=float),
        strict=True,
    ):
        if v > -FEASIBILITY_TOLERANCE:
            scale = abs(limit) or 1.0
            value = limit + v * scale if kind == "max" else limit - v * scale
            missed[label] = {
                "limit": float(limit),
                "value": float(value),
                "missed_by": float(v * scale),
                "missed_by_relative": float(v),
            }
    return missed


def constraint_report(
    problem: DesignProblem, design: Mapping[str, float], metrics: Mapping[str, Any], limits=None
) -> dict[str, dict]:
    """Whether each limit of `problem` holds.

    **Arguments:**

    - `design`: flat parameter values (`params_to_values`, `OptimiseResult.best_design`).
    - `metrics`: the metrics by name (`Peaks.metrics()`); for a problem with `K`
      conditions, `(K,)` each, the metrics at each condition (a limit's value is the
      worst over its conditions).
    - `limits`: optional per-scenario limits of the metric constraints (in the order of
      `problem.metric_constraints`).

    **Returns:** `{label: {"value", "limit", "satisfied"}}`, labels as
    `"<name> (max|min)"` (`Constraint.label`: `" at <conditions>"` after a limit held
    at some conditions only).
    """
    metric_limits = iter([] if limits is None else [float(x) for x in limits])
    limit_conditions = iter(problem.limit_conditions)
    report = {}
    for c in problem.constraints:
        for kind, limit in c.limits():
            if c.is_metric:
                limit = next(metric_limits) if limits is not None else limit
                values = np.asarray(metrics[c.name], dtype=float)
                at = next(limit_conditions)
                if problem.conditions:
                    values = values[at]
                value = float(np.max(values) if kind == "max" else np.min(values))
            else:
                value = float(design[c.name])
            ok = value <= limit if kind == "max" else value >= limit
            report[c.label(kind)] = {
                "value": value,
                "limit": float(limit),
                "satisfied": bool(ok),
            }
    return report
