"""Calibration: fitting the model's parameters to measured firing traces (`calibrate`).

The fit is weighted least squares over every experiment, signal and sample,
`Σ ρ(((model − measured) / σ)²)`, solved by optimistix's Levenberg–Marquardt. Its
Jacobian is the library's forward sensitivities of the signals at the sample times (the
same error-controlled solve as the peaks' gradients; no finite differences), given to
optimistix through a `jax.custom_jvp`, so that one solve per step gives the residuals
and their Jacobian. The experiments, and the starts (`starts`) or noise draws, run
one after another inside one compiled program (on a CPU, lockstep lanes cost more than
they save: `docs/speed.md`).

The parameters move in the search space's coordinates (`SearchSpace`: linear between
the bounds, or logarithmic over three decades and more) through lmfit's bounded
transform `z = (sin u + 1) / 2`, so that no step leaves the bounds. Uncertainty is the
Gauss–Newton covariance at the optimum scaled by the reduced χ² (lmfit's default), with
a direction the data cannot confine within the bounds reported by name instead of an
interval (`docs/calibration.md`).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
import sys
import time
from collections.abc import Mapping, Sequence
from typing import Any, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .._calibration.model_check import ModelCheck, check_residuals, finite, trace_noise
from .._calibration.predict import FittedParameters
from .._calibration.traces import T_SHIFT, Experiment, known_values
from .._campaigns.progress import Progress
from .._campaigns.store import CalibrationStore, campaign_identity
from .._model.derivatives import (
    ABSORBER_SIGNALS,
    GRADIENT_OPTIONS,
    SIGNALS,
    signal_sensitivities,
)
from .._model.parameter_table import PARAMETERS
from .._model.params import (
    ForceTable,
    RecoilParams,
    params_from_values,
    params_to_values,
    with_values,
)
from .._model.programs import structure_jit
from .._model.registry import ParameterError, check_value
from .._model.settings import Smoothing, SolverOptions, end_time, with_default_tolerances
from .._model.status import OK_CODE
from .._sweeps.space import SearchSpace, log_coordinates
from .._sweeps.sweep import batch_params, with_table

__all__ = [
    "LOSSES",
    "Calibration",
    "CalibrationResult",
    "Fitted",
    "calibrate",
    "fit_many",
]

#: The robust losses: `linear` (plain least squares), `soft_l1` and `huber` (scipy's),
#: each applied to the residual in units of `f_scale` noise deviations.
LOSSES = ("linear", "soft_l1", "huber")

#: A value within this of a bound of its box (box coordinates, the bounds 0 and 1) ended
#: on that bound (`Fitted.at_bound`): the fit's bounded transform approaches a bound it
#: is pressed against to ~1e-6 of the box.
AT_BOUND = 1e-4

#: A start reached the best when its score (−2 log-likelihood) is within this of the
#: best: a tenth of a standard error in the worst direction.
REACHED = 0.01

#: The residual given to the fit where an experiment's solve failed (in noise
#: deviations): large and finite, so that the step is refused rather than NaN.
_FAILED_RESIDUAL = 1e6

#: Levenberg–Marquardt stops once a step changes `u` by less than this (relatively) and
#: every residual by less than this many noise deviations (optimistix's own test) ...
_LM_TOLERANCE = 1e-4
#: ... or once the Gauss–Newton step from its last accepted point would move the fit by
#: less than this many standard errors (the Mahalanobis length of that step, under the
#: covariance the report gives). The first test alone waited, at the optimum, for a
#: step whose predicted gain (10⁻¹⁰ in χ²) the solve's rounding hides, and refused up
#: to 20 of them one by one (measured on 20 noise draws of the bench's absorber test:
#: 16–37 steps a fit before, 6–7 after; the values the same within 0.001 standard
#: errors).
_LM_STANDARD_ERRORS = 1e-3
#: Marquardt's first damping, a fraction of the largest diagonal of `JᵀJ` at the start
#: (Madsen, Nielsen and Tingleff's τ for a start that may be far), instead of
#: optimistix's damping of 1 whatever the residuals' scale: in noise units `JᵀJ` is
#: 10⁴–10⁸, so a damping of 1 is a Gauss–Newton step from a far start, refused and
#: shrunk by 4 up to seven times before one is taken.
_LM_FIRST_DAMPING = 1e-3


def _fit_limits(name: str):
    return T_SHIFT if name == "t_shift" else PARAMETERS[name]


@dataclasses.dataclass(frozen=True)
class Calibration:
    """A calibration problem: experiments that share the fitted hardware parameters.

    - `experiments`: the `Experiment`s fitted together (at least one).
    - `fit`: the parameters to estimate, flat name → `(lower, upper)` bounds (SI units);
      any real design parameter, or `t_shift` (the traces' trigger delay).
    - `start`: a starting value by name (default: the design's value, or for `t_shift`
      its known value, moved into the bounds).
    - `design`: known values shared by every experiment (each experiment's own win).
    - `loss`: `"linear"`, `"soft_l1"` or `"huber"` (robust against outliers), turning at
      `f_scale` noise deviations.
    - `smoothing`, `options`: as for any solve (default `GRADIENT_OPTIONS`, rtol 1e-7).
    - `validation`: experiments scored with the fitted values but not fitted.
    - `force_table`: the breech force of one round for every experiment that does not
      give its own (`Experiment.force_table`).

    **Raises:** `ParameterError` (at construction, before anything compiles) for an empty
    experiment list, an unknown or integer parameter, bounds reversed or outside the valid
    range, a start outside its bounds, a signal the design does not have, a trace that
    ends after the solve's end time `t1`, or experiments of different structure.
    """

    experiments: Sequence[Experiment]
    fit: Mapping[str, tuple[float, float]]
    start: Mapping[str, float] = dataclasses.field(default_factory=dict)
    design: Mapping[str, float] = dataclasses.field(default_factory=dict)
    loss: Literal["linear", "soft_l1", "huber"] = "linear"
    f_scale: float = 3.0
    smoothing: Smoothing = Smoothing()  # noqa: RUF009 (immutable)
    options: SolverOptions = GRADIENT_OPTIONS
    validation: Sequence[Experiment] = ()
    force_table: ForceTable | None = None

    def __post_init__(self):
        object.__setattr__(self, "experiments", tuple(self.experiments))
        object.__setattr__(self, "validation", tuple(self.validation))
        if not self.experiments:
            raise ParameterError("calibration: no experiment to fit (give at least one trace)")
        if not self.fit:
            raise ParameterError("calibration: no parameter to fit ([fit] is empty)")
        if self.loss not in LOSSES:
            raise ParameterError(
                f"calibration: loss = {self.loss!r} is invalid: valid {', '.join(LOSSES)}"
            )
        if not (math.isfinite(self.f_scale) and self.f_scale > 0):
            raise ParameterError(f"calibration: f_scale = {self.f_scale!r}: valid > 0")
        for name, bounds in self.fit.items():
            _check_fitted(name, bounds, self.start.get(name))
        for name in self.start:
            if name not in self.fit:
                raise ParameterError(f"calibration: a start for {name}, which is not fitted")
        if not [n for n in self.fit if n != "t_shift"]:
            raise ParameterError("calibration: fit at least one model parameter besides t_shift")
        for experiment in (*self.experiments, *self.validation):
            for name in experiment.per_experiment:
                if name not in self.fit:
                    raise ParameterError(
                        f"{experiment.label}: per_experiment names {name}, which [fit] does not"
                    )
        # A validation experiment fires as the fitted ones do: a table, or none.
        tables = self.experiment_table(self.experiments[0]) is not None
        for experiment in self.validation:
            if (self.experiment_table(experiment) is not None) != tables:
                has, fitted = ("no force table", "do") if tables else ("a force table", "do not")
                raise ParameterError(
                    f"{experiment.label}: this validation experiment has {has} but the "
                    f"fitted ones {fitted}: every experiment fires a table, or none does"
                )
        layout = _Layout.of(self)  # checks the designs and signals
        _prepare(self, self.experiments, layout)  # and the time spans
        for experiment in self.validation:  # the same checks, before the fit
            _validation_problem(self, experiment)

    def experiment_design(self, experiment: Experiment) -> dict[str, float]:
        """The known values of one experiment: the shared ones, then its own."""
        return {**self.design, **experiment.design}

    def experiment_table(self, experiment: Experiment) -> ForceTable | None:
        """The force table one experiment fires: its own, else the shared one."""
        return experiment.force_table if experiment.force_table is not None else self.force_table


def _check_fitted(name: str, bounds, start) -> None:
    if name != "t_shift":
        if name not in PARAMETERS:
            raise PARAMETERS.unknown(name, also=("t_shift",))
        if PARAMETERS[name].integer:
            raise ParameterError(f"cannot fit {name}: it is an integer count")
    limits = _fit_limits(name)
    try:
        lower, upper = (float(b) for b in bounds)
    except (TypeError, ValueError):
        raise ParameterError(
            f"fit.{name} = {bounds!r}: give bounds as [lower, upper] ({limits.unit})"
        ) from None
    check_value("fit", name, lower, limits)
    check_value("fit", name, upper, limits)
    if not lower < upper:
        raise ParameterError(
            f"fit.{name} = [{lower:g}, {upper:g}]: the lower bound must be below the upper"
        )
    if start is not None:
        check_value("start", name, start, limits)
        if not lower <= float(start) <= upper:
            raise ParameterError(
                f"start.{name} = {float(start):g} is outside its bounds [{lower:g}, {upper:g}]"
            )


@dataclasses.dataclass(frozen=True)
class _Layout:
    """Where each fitted value goes: `labels` (P,) of the fitted values (`name` shared,
    `name[i]` experiment i's own), their bounds; `wrt` the model parameters fitted
    anywhere (then `t_shift`: the K columns of each experiment); `index (E, K)` the
    fitted value each column takes (−1: its known value, `known (E, K)`)."""

    labels: tuple[str, ...]
    parameters: tuple[str, ...]
    lower: np.ndarray
    upper: np.ndarray
    start: np.ndarray
    wrt: tuple[str, ...]
    signals: tuple[str, ...]
    index: np.ndarray
    known: np.ndarray

    @classmethod
    def of(cls, calibration: Calibration) -> _Layout:
        experiments = calibration.experiments
        labels, parameters, owners = [], [], []
        for name in calibration.fit:
            own = [i for i, e in enumerate(calibration.experiments, 1) if name in e.per_experiment]
            if len(own) < len(calibration.experiments):
                labels.append(name)
                parameters.append(name)
                owners.append(None)
            for i in own:
                labels.append(f"{name}[{i}]")
                parameters.append(name)
                owners.append(i)
        wrt = tuple(n for n in calibration.fit if n != "t_shift")
        columns = (*wrt, "t_shift")
        signals = tuple(s for s in SIGNALS if any(s in e.trace.signals for e in experiments))
        index = np.full((len(experiments), len(columns)), -1)
        known = np.zeros((len(experiments), len(columns)))
        for e, experiment in enumerate(experiments):
            number = next(
                (i for i, x in enumerate(calibration.experiments, 1) if x is experiment), None
            )
            design = _design_of(calibration, experiment)
            for k, name in enumerate(columns):
                known[e, k] = (
                    calibration.experiment_design(experiment).get("t_shift", 0.0)
                    if name == "t_shift"
                    else design[name]
                )
                for p, (param, owner) in enumerate(zip(parameters, owners, strict=True)):
                    if param == name and (owner is None or owner == number):
                        if owner == number or index[e, k] < 0:
                            index[e, k] = p
        lower = np.asarray([calibration.fit[n][0] for n in parameters], dtype=float)
        upper = np.asarray([calibration.fit[n][1] for n in parameters], dtype=float)
        start = np.empty(len(parameters))
        for p, name in enumerate(parameters):
            if name in calibration.start:
                start[p] = float(calibration.start[name])
            else:
                column = columns.index(name)
                used = index[:, column] == p
                guess = float(np.mean(known[used, column])) if used.any() else 0.0
                start[p] = guess if lower[p] <= guess <= upper[p] else np.nan
        return cls(
            tuple(labels),
            tuple(parameters),
            lower,
            upper,
            start,
            wrt,
            signals,
            index,
            known,
        )

    @property
    def space(self) -> SearchSpace:
        return SearchSpace(
            jnp.asarray(self.lower),
            jnp.asarray(self.upper),
            jnp.asarray(log_coordinates(self.lower, self.upper)),
        )


def _design_of(calibration: Calibration, experiment: Experiment) -> dict[str, float]:
    """Every model parameter's value in an experiment (defaults, then known values)."""
    known = known_values(calibration.experiment_design(experiment))
    try:
        params = params_from_values(known)
    except ParameterError as error:
        raise ParameterError(f"{experiment.label}: {error}") from None
    values = {k: float(np.asarray(v)) for k, v in params_to_values(params).items()}
    for name in calibration.fit:
        if name != "t_shift" and name not in values:
            raise ParameterError(
                f"{experiment.label}: cannot fit {name}: this design does not have its "
                f"{PARAMETERS[name].group} (give one of its parameters in [design])"
            )
    if params.absorber is None:
        absent = [s for s in experiment.trace.signals if s in ABSORBER_SIGNALS]
        if absent:
            raise ParameterError(
                f"{experiment.trace.source}: column {absent[0]} is a signal of the absorber, "
                "but this design has none (m = 0)"
            )
    return values


class _Data(eqx.Module):
    """The arrays of a fit: the experiments' designs (batched over E), sample times
    `(E, n)` (padded with the last time), `t1 (E,)`, the measured values `(E, S, n)` (0
    where absent), `present (E, S, n)`, the noise `sigma (E, S)` and which of it is
    given, `sigma_given (E, S)`, `index`, `known (E, K)` (`_Layout`), the bounds' space."""

    params: RecoilParams
    times: jax.Array
    t1: jax.Array
    measured: jax.Array
    present: jax.Array
    sigma: jax.Array
    sigma_given: jax.Array
    index: jax.Array
    known: jax.Array
    space: SearchSpace
    smoothing: Smoothing
    options: SolverOptions


class _Static(eqx.Module):
    """What shapes the fit's program: the model parameters fitted, the signals, the
    loss, the LM step limit, and whether any noise is estimated (a second pass)."""

    wrt: tuple[str, ...] = eqx.field(static=True)
    signals: tuple[str, ...] = eqx.field(static=True)
    loss: str = eqx.field(static=True)
    f_scale: float = eqx.field(static=True)
    max_steps: int = eqx.field(static=True)
    estimate_noise: bool = eqx.field(static=True, default=True)
    lanes: int = eqx.field(static=True, default=1)
    # Levenberg–Marquardt's stopping tests (fields, so that a program made with others
    # is another program, never a cached one).
    lm_tolerance: float = eqx.field(static=True, default=_LM_TOLERANCE)
    lm_standard_errors: float = eqx.field(static=True, default=_LM_STANDARD_ERRORS)


def _prepare(calibration: Calibration, experiments, layout: _Layout) -> _Data:
    """The arrays of `experiments` (checked: a trace must end within the solve)."""
    designs, traces = [], []
    for experiment in experiments:
        design = known_values(calibration.experiment_design(experiment))
        designs.append(design)
        traces.append(experiment.fitted_trace)
    names = sorted({"M", *(k for d in designs for k in d)})  # M: at least one column
    columns = {k: [d.get(k, PARAMETERS[k].default) for d in designs] for k in names}
    try:
        params, _ = batch_params(columns)
    except ParameterError as error:
        raise ParameterError(
            f"calibration: the experiments must share one structure (all with or all "
            f"without an absorber, one number of rounds): {error}"
        ) from None
    tables = [calibration.experiment_table(e) for e in experiments]
    if any(table is not None for table in tables):
        missing = [e.label for e, table in zip(experiments, tables, strict=True) if table is None]
        if missing:
            raise ParameterError(
                f"calibration: {missing[0]} has no force table but other experiments do: "
                "give every experiment one (or a shared force_table), or none"
            )
        params = with_table(params, ForceTable.stacked([t for t in tables if t is not None]))
    n = max(len(t.t) for t in traces)
    E, S = len(experiments), len(layout.signals)
    times = np.zeros((E, n))
    measured = np.zeros((E, S, n))
    present = np.zeros((E, S, n), dtype=bool)
    sigma = np.ones((E, S))
    given = np.zeros((E, S), dtype=bool)
    shift_column = layout.index[:, -1]
    t1 = np.zeros(E)
    for e, (experiment, trace) in enumerate(zip(experiments, traces, strict=True)):
        m = len(trace.t)
        times[e, :m], times[e, m:] = trace.t, trace.t[-1]
        for s, name in enumerate(layout.signals):
            if name in trace.signals:
                values = trace.signals[name]
                present[e, s, :m] = np.isfinite(values)
                measured[e, s, :m] = np.where(np.isfinite(values), values, 0.0)
                sigma[e, s] = experiment.sigma.get(name) or _noise_guess(values)
                given[e, s] = name in experiment.sigma
        # The solve runs to the trace's end at the earliest trigger the fit may try.
        p = shift_column[e]
        earliest = layout.lower[p] if p >= 0 else layout.known[e, -1]
        needed = trace.t[-1] - earliest
        t1_given = calibration.experiment_design(experiment).get("t1")
        if t1_given is not None:
            if trace.t[-1] - layout.known[e, -1] > t1_given and p < 0:
                row = int(np.argmax(trace.t - layout.known[e, -1] > t1_given))
                raise ParameterError(
                    f"{trace.source}: the trace runs to {trace.t[-1]:g} s, after the "
                    f"simulated window t1 = {t1_given:g} s (sample {row + 1}, t = "
                    f"{trace.t[row]:g} s): give a larger t1 or a window"
                )
            needed = max(needed, float(t1_given))
        t1[e] = max(needed, 1e-6)
    for e, experiment in enumerate(experiments):
        options = dataclasses.replace(calibration.options, t1=float(t1[e]))
        single = params_from_index(params, e)
        try:
            end_time(single, options)
        except ParameterError as error:
            raise ParameterError(f"{experiment.label}: {error}") from None
    options = with_default_tolerances(params, calibration.options)
    return _Data(
        params,
        jnp.asarray(times),
        jnp.asarray(t1),
        jnp.asarray(measured),
        jnp.asarray(present),
        jnp.asarray(sigma),
        jnp.asarray(given),
        jnp.asarray(layout.index),
        jnp.asarray(layout.known),
        layout.space,
        calibration.smoothing,
        dataclasses.replace(options, t1=None),
    )


def params_from_index(params: RecoilParams, i: int) -> RecoilParams:
    """Design `i` of a batched `RecoilParams`."""
    return jax.tree.map(lambda leaf: leaf[i], params)


def _estimates_noise(data: _Data) -> bool:
    """Whether any measured signal's noise is left to estimate."""
    measured = np.asarray(data.present).any(-1)
    return bool(np.any(measured & ~np.asarray(data.sigma_given)))


def _noise_guess(values) -> float:
    """A first guess of a signal's noise from its samples alone (`trace_noise`: robust,
    allowing for coloured noise; on a trace too short for it, the spread (MAD) of its
    successive differences over √2); at least 1e-9 of the signal's size."""
    present = values[np.isfinite(values)]
    size = float(np.max(np.abs(present))) if present.size else 1.0
    own = trace_noise(present).sigma
    if not math.isfinite(own):
        steps = np.diff(present)
        own = 1.4826 * float(np.median(np.abs(steps - np.median(steps)))) / math.sqrt(2)
        own = own if steps.size else 0.0
    return max(own, 1e-9 * size, 1e-300)


def _experiment_signals(theta_e, params, times, t1, data: _Data, static: _Static):
    """One experiment's signals at its sample times `(S, n)` and their Jacobian `(S, n,
    K)` with respect to its K columns (`wrt`, then `t_shift`), and its status code."""
    params = with_values(params, static.wrt, theta_e[:-1])
    model_times = times - theta_e[-1]
    before = model_times < 0  # before the firing the gun is at rest
    solved = signal_sensitivities(
        params,
        data.smoothing,
        dataclasses.replace(data.options, t1=t1),
        static.wrt,
        jnp.clip(model_times, 0.0, t1),
        t1,
        static.signals,
    )
    gradients = jnp.concatenate([solved.gradients, -solved.rates[..., None]], axis=-1)
    values = jnp.where(before, 0.0, solved.values)
    gradients = jnp.where(before[:, None], 0.0, gradients)
    (code,) = jax.tree.leaves(solved.status)
    return values, gradients, code


class _Evaluation(eqx.Module):
    """The fit's pieces at one point θ: the normalised residuals `(E, S, n)` (0 where
    no sample), their Jacobian with respect to θ `(E, S, n, P)`, the model's signals
    `(E, S, n)` and each experiment's status code `(E,)`."""

    residuals: jax.Array
    jacobian: jax.Array
    signals: jax.Array
    codes: jax.Array


def _evaluate(theta, data: _Data, static: _Static) -> _Evaluation:
    P = theta.shape[0]
    index = data.index
    columns = jnp.where(index >= 0, theta[jnp.maximum(index, 0)], data.known)
    # The experiments one after another (`lax.map`), not in lockstep: a vmapped solve
    # selects its whole carry, the saved signals included, at every step (measured, one
    # experiment of 5,001 samples: 13 ms vmapped, 3 ms alone).
    values, gradients, codes = jax.lax.map(
        lambda a: _experiment_signals(a[0], a[1], a[2], a[3], data, static),
        (columns, data.params, data.times, data.t1),
    )
    ok = (codes == OK_CODE)[:, None, None]
    select = jax.nn.one_hot(index, P) * (index >= 0)[..., None]  # (E, K, P)
    jacobian = jnp.einsum("esnk,ekp->esnp", gradients, select) / data.sigma[..., None, None]
    residuals = (values - data.measured) / data.sigma[..., None]
    residuals = jnp.where(
        data.present & ok, residuals, jnp.where(data.present, _FAILED_RESIDUAL, 0)
    )
    jacobian = jnp.where((data.present & ok)[..., None], jacobian, 0.0)
    return _Evaluation(residuals, jacobian, values, codes)


def _robust(r, loss: str, f_scale: float):
    """The residual whose square is the loss `ρ(r²)`: `r` (linear), or scipy's soft-L1
    and Huber of `r / f_scale`, times `f_scale` (smooth in r; the same near 0)."""
    if loss == "linear":
        return r
    x = r / f_scale
    if loss == "soft_l1":  # ρ(z) = 2(√(1+z) − 1) = 2z / (√(1+z) + 1)
        return r * jnp.sqrt(2.0 / (jnp.sqrt(1.0 + x * x) + 1.0))
    # Huber: ρ(z) = z for z <= 1, else 2√z − 1.
    big = jnp.abs(x) > 1.0
    safe = jnp.where(big, jnp.abs(x), 1.0)
    return jnp.where(big, r * jnp.sqrt((2.0 * safe - 1.0) / (safe * safe)), r)


def _theta_of_u(u, space: SearchSpace):
    """lmfit's bounded transform: `z = (sin u + 1) / 2`, `θ = space.theta(z)`."""
    return space.theta((jnp.sin(u) + 1.0) / 2.0)


def _u_of_z(z):
    return np.arcsin(np.clip(2.0 * np.asarray(z) - 1.0, -1.0, 1.0))


def _lm_function(static: _Static):
    """`(u, (data, held, held_theta)) → robust residuals (N,)`, whose Jacobian
    (`custom_jvp`) comes from the same forward-sensitivity solve as the residuals. The
    values `held (P,)` stay at `held_theta` (a profile's fixed parameter)."""

    def value_and_jacobian(u, args):
        data, held, held_theta = args
        theta, dtheta = jax.jvp(lambda u_: _theta_of_u(u_, data.space), (u,), (jnp.ones_like(u),))
        theta = jnp.where(held, held_theta, theta)
        dtheta = jnp.where(held, 0.0, dtheta)
        evaluation = _evaluate(theta, data, static)
        r = evaluation.residuals.reshape(-1)
        J = evaluation.jacobian.reshape(r.shape[0], -1) * dtheta
        robust, slope = jax.jvp(
            lambda x: _robust(x, static.loss, static.f_scale), (r,), (jnp.ones_like(r),)
        )
        return robust, J * slope[:, None]

    @jax.custom_jvp
    def residuals(u, data):
        return value_and_jacobian(u, data)[0]

    @residuals.defjvp
    def _(primals, tangents):
        u, data = primals
        du = tangents[0]
        r, J = value_and_jacobian(u, data)
        return r, J @ du

    return residuals


def _quiet(**_) -> None:
    """optimistix's `verbose` hook, silent."""


class _MarquardtTrustRegion(optx.ClassicalTrustRegion):
    """optimistix's trust region with Marquardt's first damping (`_LM_FIRST_DAMPING`)
    and Moré's cutoff for relaxing it: a step that gains three quarters of its predicted
    reduction, not 99 %, lets the next one be longer."""

    high_cutoff: float = 0.75  # pyright: ignore[reportIncompatibleVariableOverride]
    first_damping: float = _LM_FIRST_DAMPING

    def step(self, first_step, y, y_eval, f_info, f_eval_info, state):
        step_size, accept, result, state = super().step(
            first_step, y, y_eval, f_info, f_eval_info, state
        )
        diagonal = jnp.sum(f_eval_info.jac.as_matrix() ** 2, axis=0)  # pyright: ignore[reportAttributeAccessIssue]
        first = 1.0 / (self.first_damping * jnp.maximum(jnp.max(diagonal), 1e-300))
        # A Jacobian that is not finite at the start: optimistix's damping of 1, whose
        # step is then refused (not a NaN damping, whose zero steps it would accept).
        first = jnp.where(jnp.isfinite(first), first, 1.0)
        step_size = jnp.where(first_step, first, step_size)
        return step_size, accept, result, eqx.tree_at(lambda s: s.step_size, state, step_size)


class _LevenbergMarquardt(optx.AbstractGaussNewton):
    """Levenberg–Marquardt (optimistix's Gauss–Newton with a damped Newton descent)
    with `_MarquardtTrustRegion` and a second stopping test: the Gauss–Newton step from
    the last accepted point would move the fit by under `standard_errors`. Never at a
    point where an experiment's solve failed (a residual of at least `failed`)."""

    rtol: float
    atol: float
    standard_errors: float
    failed: float
    norm: Any = optx.max_norm
    # optimistix declares these abstract; its own LevenbergMarquardt narrows them so.
    descent: optx.DampedNewtonDescent = optx.DampedNewtonDescent()  # pyright: ignore[reportIncompatibleVariableOverride]
    search: _MarquardtTrustRegion = _MarquardtTrustRegion()  # pyright: ignore[reportIncompatibleVariableOverride]
    verbose: Any = _quiet

    def terminate(self, fn, y, args, options, state, tags):
        done, result = super().terminate(fn, y, args, options, state, tags)
        data, held, _ = args
        jacobian, residuals = state.f_info.jac.as_matrix(), state.f_info.residual
        step = jnp.linalg.lstsq(jacobian, residuals)[0]
        # The step's squared length in standard errors: ‖J δ‖² over the residual
        # variance (the covariance's scale: the samples present, the values free).
        length2 = jnp.sum((jacobian @ step) ** 2)
        freedom = jnp.maximum(data.present.sum() - jnp.sum(~held), 1)
        variance = jnp.sum(residuals**2) / freedom
        near = length2 <= self.standard_errors**2 * jnp.maximum(variance, 1e-300)
        near = near & jnp.all(jnp.abs(residuals) < self.failed) & ~state.first_step
        return done | near, result


def _solve_lm(u0, data: _Data, static: _Static, held=None, held_theta=None):
    with jax.ensure_compile_time_eval():  # half the failed residual, as the loss gives it
        failed = float(_robust(jnp.asarray(0.5 * _FAILED_RESIDUAL), static.loss, static.f_scale))
    solver = _LevenbergMarquardt(
        rtol=static.lm_tolerance,
        atol=static.lm_tolerance,
        standard_errors=static.lm_standard_errors,
        failed=failed,
    )
    held = jnp.zeros(u0.shape, dtype=bool) if held is None else held
    held_theta = jnp.zeros(u0.shape) if held_theta is None else held_theta
    solution = optx.least_squares(
        _lm_function(static),
        solver,
        u0,
        args=(data, held, held_theta),
        max_steps=static.max_steps,
        throw=False,
    )
    return solution.value, solution.result == optx.RESULTS.successful, solution.stats["num_steps"]


def _residual_scale(residuals, present, loss: str):
    """Each signal's noise in units of the assumed one, from the residuals `(E, S, n)`:
    the RMS, or with a robust loss the MAD's normal-consistent scale."""
    if loss == "linear":
        count = jnp.maximum(present.sum(-1), 1)
        return jnp.sqrt(jnp.sum(jnp.where(present, residuals**2, 0.0), -1) / count)
    absolute = jnp.where(present, jnp.abs(residuals), jnp.nan)
    return 1.4826 * jnp.nanmedian(absolute, axis=-1)


class _FitOutcome(eqx.Module):
    """One lane of a batched fit: the optimum `u`, whether the fit converged, its steps,
    the noise it settled on `(E, S)`, the cost there, and its `score`: −2 log-likelihood
    of the Gaussian noise model up to a constant (the cost plus `Σ n log σ²` over every
    experiment and signal), which ranks fits whose noise was estimated each on its own
    (their costs are all about N)."""

    u: jax.Array
    converged: jax.Array
    steps: jax.Array
    sigma: jax.Array
    cost: jax.Array
    score: jax.Array


def _log_likelihood_term(sigma, present):
    """`Σ n log σ²` over experiments and signals (`n` samples each), any array module."""
    xp = jnp if isinstance(sigma, jax.Array) else np
    return xp.sum(present.sum(-1) * xp.log(sigma**2))


def _fit_one(u0, measured, data: _Data, static: _Static) -> _FitOutcome:
    """Two passes: fit with the assumed noise; then (where it is estimated) with the
    noise the residuals show, from the first optimum."""
    data = eqx.tree_at(lambda d: d.measured, data, measured)
    u1, ok1, steps1 = _solve_lm(u0, data, static)
    if not static.estimate_noise:  # every noise given: one pass
        final = _evaluate(_theta_of_u(u1, data.space), data, static)
        cost = jnp.sum(_robust(final.residuals, static.loss, static.f_scale) ** 2)
        score = cost + _log_likelihood_term(data.sigma, data.present)
        return _FitOutcome(u1, ok1, steps1, data.sigma, cost, score)
    first = _evaluate(_theta_of_u(u1, data.space), data, static)
    scale = _residual_scale(first.residuals, data.present, static.loss)
    scale = jnp.where(jnp.isfinite(scale) & (scale > 0), scale, 1.0)
    sigma = jnp.where(data.sigma_given, data.sigma, data.sigma * scale)
    data = eqx.tree_at(lambda d: d.sigma, data, sigma)
    u2, ok2, steps2 = _solve_lm(u1, data, static)
    final = _evaluate(_theta_of_u(u2, data.space), data, static)
    cost = jnp.sum(_robust(final.residuals, static.loss, static.f_scale) ** 2)
    score = cost + _log_likelihood_term(sigma, data.present)
    return _FitOutcome(u2, ok1 & ok2, steps1 + steps2, sigma, cost, score)


@functools.partial(structure_jit, exported=lambda leaves: _FitOutcome(*leaves))
def _fit_program(u0, measured, data: _Data, static: _Static) -> _FitOutcome:
    """`_fit_one` over a batch, `u0 (B, P)`, `measured (B, E, S, n)`, in one program:
    `static.lanes` fits at a time in lockstep (`vmap`), the groups one after another
    (`lax.map`). On a CPU one lane is fastest: lanes in lockstep run until the slowest
    has converged, a vmapped loop selects its whole carry at every step, and a CPU gains
    nothing from solving lanes side by side (measured, 8 fits of 1,001 samples: 2.6 s in
    lockstep, 0.5 s as lanes of one, 0.28 s as a plain scan)."""
    # `batch_size=1` would still vmap (lanes of one, carrying selects); None does not.
    lanes = static.lanes if static.lanes > 1 else None
    return jax.lax.map(lambda a: _fit_one(a[0], a[1], data, static), (u0, measured),
                       batch_size=lanes)  # fmt: skip


@functools.partial(structure_jit, exported=lambda leaves: _Evaluation(*leaves))
def _evaluate_program(theta, data: _Data, static: _Static) -> _Evaluation:
    return _evaluate(theta, data, static)


@structure_jit
def _profile_program(u0, held, held_theta, data: _Data, static: _Static):
    """The least cost with the values `held (B, P)` fixed at `held_theta (B, P)`, the
    others refitted from `u0 (B, P)` (one lane per profile point): `(cost (B,),
    converged (B,))`."""

    def one(u, h, t):
        u_, ok, _ = _solve_lm(u, data, static, h, t)
        theta = jnp.where(h, t, _theta_of_u(u_, data.space))
        r = _robust(_evaluate(theta, data, static).residuals, static.loss, static.f_scale)
        return jnp.sum(r**2), ok

    return jax.lax.map(lambda a: one(*a), (u0, held, held_theta))


@dataclasses.dataclass(frozen=True)
class Fitted:
    """One fitted value: `value` (SI units), and where the data determine it
    (`identifiable`) its standard error `stderr` and 95 % interval `ci95`; None where
    they do not. `profile_ci95`: the profile-likelihood interval (`calibrate(...,
    profiles=True)`), a side None where the profile stays below the threshold up to the
    bound."""

    value: float
    stderr: float | None
    ci95: tuple[float, float] | None
    identifiable: bool
    profile_ci95: tuple[float | None, float | None] | None = None
    #: `"lower"` or `"upper"` where the value ended on that bound of its box (within
    #: `AT_BOUND` of the box): the best fit within the bounds, which the data may want
    #: beyond them. Its interval is then the curvature there, cut at the bound, not a
    #: confidence interval.
    at_bound: str | None = None
    #: The model does not explain the traces (`CalibrationResult.check`): `stderr` and
    #: `ci95` are withheld (None), since they assume it does.
    withheld: bool = False

    def to_json(self) -> dict[str, Any]:
        out = {
            "value": self.value,
            "stderr": self.stderr,
            "ci95": None if self.ci95 is None else list(self.ci95),
            "identifiable": self.identifiable,
            "at_bound": self.at_bound,
            "withheld": self.withheld,
        }
        if self.profile_ci95 is not None:
            out["profile_ci95"] = list(self.profile_ci95)
        return out


@dataclasses.dataclass(frozen=True)
class CalibrationResult:
    """What `calibrate` gives.

    - `fitted`: each fitted value by label (`name`, or `name[i]` for experiment i's own)
      as `Fitted`; `values`: the values alone.
    - `correlation (P, P)`: of the fitted values (NaN rows for unidentifiable ones);
      `covariance (P, P)` (SI units).
    - `unidentifiable`: the combinations the data cannot confine within the bounds, in
      words (`"k_c, n_c: 0.71·k_c − 0.70·n_c (box coordinates)"`).
    - `chi2`, `reduced_chi2`, `samples` (N), `dof` (N − P); `aic`, `bic`: −2
      log-likelihood of the Gaussian noise model (`chi2 + Σ n log σ²`, SI units, up to
      N log 2π) plus 2, or ln N, per estimated value (the fitted ones and each estimated
      noise); `rms`: per signal, the RMS residual (its unit); `sigma`: per experiment and
      signal, the noise used (given or estimated).
    - `converged`: the best start's fit converged; `starts`, `starts_at_best`: how many
      starts were run and how many reached the best (−2 log-likelihood within
      `REACHED`, 0.01).
    - `experiments`: per experiment, its name, trace, samples, skipped samples and RMS
      per signal; `validation`: the same for the validation experiments.
    - `times`, `measured`, `model`: per experiment (a list), the sample times `(n,)` and
      the measured and fitted signals by name (for figures).
    - `codes`: each experiment's status code at the optimum; `seconds`.
    - `profiles`: with `profiles=True`, each value's profile: `values (m,)` and
      `delta_chi2 (m,)` (the refitted cost's rise over the best, in units of the
      reduced χ²; 3.84 bounds the 95 % interval).
    - `check`: the test of the residuals against each trace's own noise
      (`ModelCheck`); `explains`: it passed. Where it did not, every `Fitted`'s interval
      is withheld.
    - `structure`: the model fitted (`absorber`, `load`: impulse, pulse or force table,
      `shots`, `hardware`: the optional groups present); `defaults`: the design values
      no experiment gave and the fit did not fit, taken from the defaults.
    - `bounds`: each fitted value's bounds; `design`: the known values the experiments
      shared. `hardware()`: the fitted hardware parameters with their covariance, for
      `predict` and robust studies.
    """

    fitted: dict[str, Fitted]
    values: dict[str, float]
    correlation: np.ndarray
    covariance: np.ndarray
    unidentifiable: list[str]
    chi2: float
    reduced_chi2: float
    aic: float
    bic: float
    samples: int
    dof: int
    rms: dict[str, float]
    sigma: list[dict[str, float]]
    converged: bool
    starts: int
    starts_at_best: int
    steps: int
    experiments: list[dict[str, Any]]
    validation: list[dict[str, Any]]
    times: list[np.ndarray]
    measured: list[dict[str, np.ndarray]]
    model: list[dict[str, np.ndarray]]
    codes: np.ndarray
    seconds: float
    bounds: dict[str, tuple[float, float]] = dataclasses.field(default_factory=dict)
    design: dict[str, float] = dataclasses.field(default_factory=dict)
    profiles: dict[str, dict[str, np.ndarray]] = dataclasses.field(default_factory=dict)
    check: ModelCheck = dataclasses.field(default_factory=lambda: ModelCheck(()))
    structure: dict[str, Any] = dataclasses.field(default_factory=dict)
    defaults: dict[str, float] = dataclasses.field(default_factory=dict)

    @property
    def explains(self) -> bool:
        """The model explains the traces: no signal's residuals are far above its noise
        or far from white (`check`)."""
        return self.check.explains

    def hardware(self) -> FittedParameters:
        """The fitted values shared by every experiment that are design parameters (not
        `t_shift`, not an experiment's own), with their covariance, bounds and the known
        shared values."""
        labels = list(self.fitted)
        names = [n for n in labels if n in PARAMETERS]
        index = [labels.index(n) for n in names]
        return FittedParameters(
            tuple(names),
            np.asarray([self.values[n] for n in names]),
            self.covariance[np.ix_(index, index)],
            np.asarray([self.bounds[n][0] for n in names]),
            np.asarray([self.bounds[n][1] for n in names]),
            np.asarray([self.fitted[n].identifiable for n in names], dtype=bool),
            dict(self.design),
            self.explains,
        )

    @property
    def solved(self) -> bool:
        """Every experiment's solve at the optimum succeeded."""
        return bool(np.all(self.codes == OK_CODE))

    def to_json(self) -> dict[str, Any]:
        """The report as JSON-ready values (`result.json`)."""
        names = list(self.fitted)
        return {
            "fitted": {k: f.to_json() for k, f in self.fitted.items()},
            "correlation": {
                a: {b: finite(self.correlation[i, j]) for j, b in enumerate(names)}
                for i, a in enumerate(names)
            },
            "unidentifiable": self.unidentifiable,
            "chi2": self.chi2,
            "reduced_chi2": self.reduced_chi2,
            "aic": self.aic,
            "bic": self.bic,
            "samples": self.samples,
            "dof": self.dof,
            "rms": self.rms,
            "sigma": self.sigma,
            "converged": self.converged,
            "solved": self.solved,
            "explains": self.explains,
            "model": {"structure": self.structure, "defaults": self.defaults},
            "model_check": self.check.to_json(),
            "starts": self.starts,
            "starts_at_best": self.starts_at_best,
            "steps": self.steps,
            "experiments": self.experiments,
            "validation": self.validation,
            "seconds": self.seconds,
            "profiles": {
                k: {"values": v["values"].tolist(), "delta_chi2": v["delta_chi2"].tolist()}
                for k, v in self.profiles.items()
            },
            "hardware": self.hardware().to_json()
            if any(n in PARAMETERS for n in self.fitted)
            else None,
        }


def _starts(layout: _Layout, starts: int, seed: int) -> np.ndarray:
    """`(starts, P)` points in box coordinates: the given start (or the box's middle where
    the design's value lies outside it), then scrambled Sobol points."""
    space = layout.space
    middle = np.full(len(layout.labels), 0.5)
    given = np.isfinite(layout.start)
    first = np.where(given, space.z(np.where(given, layout.start, layout.lower)), middle)
    if starts == 1:
        return first[None]
    import scipy.stats  # when used: it takes 0.4 s to import

    sobol = scipy.stats.qmc.Sobol(
        len(layout.labels), scramble=True, rng=np.random.default_rng(seed)
    )
    points = sobol.random_base2(max(0, math.ceil(math.log2(starts - 1))))
    return np.concatenate([first[None], points[: starts - 1]])


#: Starts are moved this far (box coordinates) inside the bounds: on a bound the bounded
#: transform's slope is 0, and the fit could never move the value.
_START_MARGIN = 1e-3


def _start_points(layout: _Layout, starts, seed: int) -> np.ndarray:
    """`starts` (a count, or `(N, P)` values) as points in box coordinates, a little
    inside the bounds (`_START_MARGIN`)."""
    return np.clip(_given_starts(layout, starts, seed), _START_MARGIN, 1 - _START_MARGIN)


def _given_starts(layout: _Layout, starts, seed: int) -> np.ndarray:
    if isinstance(starts, int) and not isinstance(starts, bool):
        if starts < 1:
            raise ParameterError(f"starts = {starts!r} is invalid: valid an integer >= 1")
        return _starts(layout, starts, seed)
    points = np.asarray(starts, dtype=float)
    if points.ndim != 2 or points.shape[1] != len(layout.labels) or len(points) == 0:
        raise ParameterError(
            f"starts: give a count, or one row of {len(layout.labels)} values per start "
            f"({', '.join(layout.labels)})"
        )
    outside = (points < layout.lower) | (points > layout.upper) | ~np.isfinite(points)
    if outside.any():
        row, column = np.argwhere(outside)[0]
        raise ParameterError(
            f"starts[{row}]: {layout.labels[column]} = {points[row, column]:g} is outside "
            f"its bounds [{layout.lower[column]:g}, {layout.upper[column]:g}]"
        )
    return layout.space.z(points)


def calibrate(
    calibration: Calibration,
    *,
    starts: int | np.ndarray = 1,
    seed: int = 0,
    max_steps: int = 200,
    profiles: bool = False,
    progress: bool | None = None,
    store: str | os.PathLike | None = None,
) -> CalibrationResult:
    """Fit the parameters `calibration.fit` to its experiments' traces.

    **Arguments:**

    - `calibration`: the `Calibration` (experiments, parameters and bounds, loss).
    - `starts`: how many starts (the given start, then Sobol points in the box), or the
      start points themselves, `(N, P)` values in SI units (in the order of the fitted
      labels, within the bounds); fitted as one batch, the best kept and the count
      reaching it reported.
    - `seed`: the Sobol points' scrambling; `max_steps`: Levenberg–Marquardt steps per
      pass; `progress`: a progress line on stderr (None: on a terminal).
    - `profiles`: also profile each value (refit the others with it held at 12 points
      around the optimum, or across the bounds where it is not determined; one batched
      program) for profile-likelihood intervals, as lmfit's `conf_interval`.
    - `store`: the path of an SQLite file that keeps each finished part (a chunk of
      `STARTS_PER_CHUNK` starts, the profiles), so that a killed calibration resumes: the
      same call with the same store reads the parts it has and fits the rest, to the
      same result bit for bit. A store made by another calibration is refused.

    **Returns:** a `CalibrationResult`: values, standard errors, 95 % intervals,
    correlation, identifiability, χ², AIC, BIC, RMS per signal, the fitted signals.

    **Raises:** `ParameterError` for `starts < 1` or start points outside the bounds
    (the calibration checked itself when built). A failed solve or a fit that did not
    converge is reported (`result.solved`, `result.converged`), not raised.
    """
    clock = time.perf_counter()
    layout = _Layout.of(calibration)
    z0 = _start_points(layout, starts, seed)
    starts = len(z0)
    data = _prepare(calibration, calibration.experiments, layout)
    static = _Static(layout.wrt, layout.signals, calibration.loss, calibration.f_scale,
                     max_steps, _estimates_noise(data))  # fmt: skip
    bar = Progress("calibrate", 4, "phases", progress, rates=False)
    store_ = None
    if store is not None:
        store_ = _open_store(store, calibration, layout, data, static, z0, profiles)
        if (done := store_.stored_fits()) and progress is not False:
            print(f"calibrate: resuming from {store}: {done} fits already done",
                  file=sys.stderr)  # fmt: skip
    try:  # the store (and its writer lock) closed whatever happens
        return _calibrate(
            calibration, layout, data, static, z0, profiles, bar, store_, clock
        )  # fmt: skip
    finally:
        if store_ is not None:
            store_.close()


#: Starts fitted per part of a calibration kept in a store (each part committed).
STARTS_PER_CHUNK = 8


def _open_store(path, calibration, layout, data, static, z0, profiles):
    """The calibration's store at `path` (made, or checked to be this calibration's)."""
    identity = campaign_identity("calibration", data, static, np.asarray(z0), bool(profiles))
    total = len(z0) + (_PROFILE_POINTS * len(layout.labels) if profiles else 0)
    description = {
        "fit": list(layout.labels),
        "starts": len(z0),
        "experiments": [e.label for e in calibration.experiments],
        "created": time.strftime("%Y-%m-%d %H:%M:%S"),
    }
    return CalibrationStore(path, identity=identity, total=total,
                            plan={"starts_per_chunk": STARTS_PER_CHUNK}, columns=(),
                            description=description)  # fmt: skip


def _stored_part(store_, part: str, fits: int, compute) -> dict[str, np.ndarray]:
    """A part of the calibration: read from the store, or computed (`compute()`, named
    arrays) and committed there; without a store, computed."""
    if store_ is not None and (arrays := store_.stored(part)) is not None:
        return arrays
    started = time.perf_counter()
    arrays = {name: np.asarray(value) for name, value in compute().items()}
    if store_ is not None:
        store_.commit(part, fits, arrays, time.perf_counter() - started)
    return arrays


def _fit_starts(u0: np.ndarray, data: _Data, static: _Static, store_) -> _FitOutcome:
    """Every start's fit: one program for them all, or with a store one part per
    `starts_per_chunk` of its plan (the last padded to it), each read or committed."""

    size = len(u0) if store_ is None else int(store_.plan["starts_per_chunk"])

    def fit(u):
        # A short last part is padded with its last start: one program for every part
        # (a fit costs less than a compilation); the padding's fits are dropped.
        padded = np.concatenate([u, np.repeat(u[-1:], size - len(u), axis=0)])
        measured = jnp.broadcast_to(data.measured, (size, *data.measured.shape))
        outcome = _fit_program(jnp.asarray(padded), measured, data, static)
        return {f.name: getattr(outcome, f.name)[: len(u)] for f in dataclasses.fields(outcome)}

    parts = []
    for begin in range(0, len(u0), size):
        chunk = np.asarray(u0[begin : begin + size])
        parts.append(_stored_part(store_, f"fit:{begin}", len(chunk), lambda u=chunk: fit(u)))
    return _FitOutcome(**{k: jnp.concatenate([p[k] for p in parts]) for k in parts[0]})


def _calibrate(calibration, layout, data, static, z0, profiles, bar, store_, clock):
    """`calibrate` once its inputs are checked and its store (if any) open."""
    starts = len(z0)
    where = "one program" if store_ is None else f"parts of {store_.plan['starts_per_chunk']}"
    bar.update(0, f"fitting from {starts} start{'s' if starts > 1 else ''} ({where})")
    outcome = _fit_starts(_u_of_z(z0), data, static, store_)
    score = np.asarray(outcome.score)
    score = np.where(np.isfinite(score), score, np.inf)
    best = int(np.argmin(score))
    at_best = int(np.sum(score <= score[best] + REACHED))
    bar.update(1, f"fitted in {int(outcome.steps[best])} steps; uncertainty")
    data = eqx.tree_at(lambda d: d.sigma, data, outcome.sigma[best])
    result = _lane_report(calibration, layout, data, static, outcome, best, (starts, at_best))
    if profiles:
        bar.update(2, f"profiles ({len(layout.labels)} values)")
        result = _with_profiles(result, layout, data, static, outcome.u[best], store_)
    bar.update(3, "validation")
    validation = [validate(calibration, result, e) for e in calibration.validation]
    bar.update(4, "done", final=True)
    return dataclasses.replace(result, validation=validation, seconds=time.perf_counter() - clock)


#: Where a profile is evaluated, in standard errors from the optimum (each side).
_PROFILE_STEPS = (1.0, 1.5, 2.0, 2.5, 3.0, 4.0)
#: The points of each value's profile (refits), on both sides.
_PROFILE_POINTS = 2 * len(_PROFILE_STEPS)
#: The 95 % threshold of a profile's Δχ² (one degree of freedom): `chi2.ppf(0.95, 1)`,
#: the square of the normal's 97.5 % point (a literal: importing scipy.stats takes 0.4 s
#: of the command line's start; a test checks it against scipy).
_PROFILE_THRESHOLD = 1.959963984540054**2


def _with_profiles(result, layout, data, static, u_best, store_=None):
    """`result` with every fitted value's profile and profile-likelihood interval: the
    value held at each profile point while the others are refitted (every point of
    every value one lane of one batched fit), under the fit's noise; one part of the
    store."""
    space = layout.space
    theta = np.asarray([result.values[label] for label in layout.labels])
    z = space.z(theta)
    P = len(theta)
    # The standard error in box coordinates, from the slope there (not by moving θ, which
    # the bounds would clip at a value on its bound).
    dtheta_dz = np.asarray(jax.jvp(space.theta, (jnp.asarray(z),), (jnp.ones(P),))[1])
    grids = []
    for i, label in enumerate(layout.labels):
        f = result.fitted[label]
        if f.identifiable and f.stderr:
            sd_z = max(f.stderr / max(abs(dtheta_dz[i]), 1e-300), 1e-12)
            steps = np.asarray(_PROFILE_STEPS)
            points = np.concatenate([z[i] - sd_z * steps[::-1], z[i] + sd_z * steps])
        else:  # not determined: across the bounds
            points = np.linspace(0.0, 1.0, _PROFILE_POINTS)
        grids.append(np.clip(points, 0.0, 1.0))
    m = len(grids[0])
    held = np.zeros((P * m, P), dtype=bool)
    held_z = np.tile(z, (P * m, 1))
    for i, points in enumerate(grids):
        held[i * m : (i + 1) * m, i] = True
        held_z[i * m : (i + 1) * m, i] = points
    held_theta = np.asarray(jax.vmap(space.theta)(jnp.asarray(held_z)))
    u0 = jnp.broadcast_to(u_best, held.shape)

    def refit():
        cost, converged = _profile_program(
            u0, jnp.asarray(held), jnp.asarray(held_theta), data, static
        )
        return {"cost": cost, "converged": converged}

    part = _stored_part(store_, "profiles", len(held), refit)
    cost, converged = part["cost"], part["converged"]
    # A point whose refit did not converge is left out (NaN); a rise below 0 (a better
    # optimum than the fit's) is kept, and shows in the profile.
    delta = np.where(
        np.asarray(converged), (np.asarray(cost) - result.chi2) / result.reduced_chi2, np.nan
    )
    profiles, fitted = {}, dict(result.fitted)
    for i, label in enumerate(layout.labels):
        values = np.concatenate([held_theta[i * m : (i + 1) * m, i], [theta[i]]])
        rise = np.concatenate([delta[i * m : (i + 1) * m], [0.0]])
        order = np.argsort(values, kind="stable")
        values, rise = values[order], rise[order]
        profiles[label] = {"values": values, "delta_chi2": rise}
        if not fitted[label].withheld:  # the profile's interval assumes the model too
            fitted[label] = dataclasses.replace(
                fitted[label], profile_ci95=_crossings(values, rise, theta[i])
            )
    return dataclasses.replace(result, fitted=fitted, profiles=profiles)


def _crossings(values, rise, best) -> tuple[float | None, float | None]:
    """Where the profile `rise` first reaches the 95 % threshold on each side of `best`
    (linear between points), or None where it stays below it to the last point."""
    sides = []
    for lower in (True, False):
        side = values < best if lower else values > best
        side &= np.isfinite(rise)
        xs, ys = values[side], rise[side]
        if lower:  # nearest first
            xs, ys = xs[::-1], ys[::-1]
        x0, y0, found = best, 0.0, None
        for x, y in zip(xs, ys, strict=True):
            if y >= _PROFILE_THRESHOLD:
                found = x0 + (x - x0) * (_PROFILE_THRESHOLD - y0) / max(y - y0, 1e-300)
                break
            x0, y0 = x, y
        sides.append(None if found is None else float(found))
    return sides[0], sides[1]


def _lane_report(calibration, layout, data, static, outcome: _FitOutcome, lane: int, starts):
    """The report of one lane of a batched fit, on `data` (with that lane's noise)."""
    theta = _theta_of_u(outcome.u[lane], data.space)
    evaluation = _evaluate_program(theta, data, static)
    return _report(
        calibration,
        layout,
        data,
        evaluation,
        np.asarray(theta),
        converged=bool(outcome.converged[lane]),
        starts=starts,
        steps=int(outcome.steps[lane]),
    )


def _report(calibration, layout, data, evaluation, theta, *, converged, starts, steps):
    r = np.asarray(evaluation.residuals)
    present = np.asarray(data.present)
    codes = np.asarray(evaluation.codes)
    robust, slope = (
        np.asarray(a)
        for a in jax.jvp(
            lambda x: _robust(x, calibration.loss, calibration.f_scale),
            (jnp.asarray(r[present]),),
            (jnp.ones(int(present.sum())),),
        )
    )
    # The Jacobian of the residuals the fit minimised (a robust loss down-weights outliers
    # there too), `(N, P)`.
    J = np.asarray(evaluation.jacobian)[present] * slope[:, None]
    N, P = J.shape[0], len(theta)
    if N == 0:
        raise ParameterError("calibration: no usable sample within the experiments' windows")
    dof = max(N - P, 1)
    chi2 = float(np.sum(robust**2))
    reduced = chi2 / dof
    # Box coordinates (each bound range [0, 1]; logarithmic where the space is).
    space = layout.space
    z = space.z(theta)
    dtheta_dz = np.asarray(jax.jvp(space.theta, (jnp.asarray(z),), (jnp.ones(P),))[1])
    Jz = J * dtheta_dz
    H = Jz.T @ Jz
    eigenvalues, vectors = np.linalg.eigh(H)
    largest = max(float(eigenvalues[-1]), 1e-300)
    # A direction is unconfined when its 95 % interval is wider than the box (or JᵀJ is
    # singular to rounding there).
    flat = [
        j
        for j, lam in enumerate(eigenvalues)
        if lam <= 1e-12 * largest or 1.96 * math.sqrt(reduced / max(lam, 1e-300)) > 0.5
    ]
    covariance_z = reduced * np.linalg.pinv(H, rcond=1e-12, hermitian=True)
    sd_z = np.sqrt(np.maximum(np.diag(covariance_z), 0.0))
    involved = set()
    unidentifiable = []
    for j in flat:
        v = vectors[:, j]
        names = [i for i in np.argsort(-np.abs(v)) if abs(v[i]) >= 0.2 * np.max(np.abs(v))]
        involved.update(names)
        terms = " ".join(
            f"{'−' if v[i] < 0 else '+'} {abs(v[i]):.2f}·{layout.labels[i]}" for i in names
        ).lstrip("+ ")
        unidentifiable.append(
            f"{', '.join(layout.labels[i] for i in names)}: {terms} (box coordinates) is not "
            "determined by the data"
        )
    identifiable = np.asarray(
        [i not in involved and 2 * 1.96 * sd_z[i] < 1.0 for i in range(P)], dtype=bool
    )
    covariance = covariance_z * np.outer(dtheta_dz, dtheta_dz)
    sd = np.sqrt(np.maximum(np.diag(covariance), 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        correlation = covariance / np.outer(sd, sd)
    correlation[~identifiable, :] = np.nan
    correlation[:, ~identifiable] = np.nan
    sigma = np.asarray(data.sigma)
    residual_si = r * sigma[..., None]
    experiments, times, measured, model = [], [], [], []
    signals_model = np.asarray(evaluation.signals)
    for e, experiment in enumerate(calibration.experiments):
        summary, t, m, fit = _experiment_summary(
            experiment, e, layout, present, residual_si, np.asarray(data.measured), signals_model
        )
        summary["sigma"] = {
            name: float(sigma[e, s])
            for s, name in enumerate(layout.signals)
            if name in experiment.trace.signals
        }
        summary["status"] = int(codes[e])
        experiments.append(summary)
        times.append(t)
        measured.append(m)
        model.append(fit)
    check = check_residuals(
        [(x.label, t, m, fit, x.sigma)
         for x, t, m, fit in zip(calibration.experiments, times, measured, model, strict=True)],
        {name: SIGNALS[name][0] for name in layout.signals},
        robust=calibration.loss != "linear",
    )  # fmt: skip
    fitted = {}
    for i, label in enumerate(layout.labels):
        zi = float(z[i])
        side = "lower" if zi <= AT_BOUND else "upper" if zi >= 1.0 - AT_BOUND else None
        if not check.explains:  # an interval would assume the model the data refute
            fitted[label] = Fitted(float(theta[i]), None, None, bool(identifiable[i]),
                                   at_bound=side, withheld=True)  # fmt: skip
        elif identifiable[i]:
            low, high = theta[i] - 1.96 * sd[i], theta[i] + 1.96 * sd[i]
            if side is not None:  # nothing beyond the bound is a fit
                low, high = max(low, layout.lower[i]), min(high, layout.upper[i])
            fitted[label] = Fitted(
                float(theta[i]), float(sd[i]), (float(low), float(high)), True, at_bound=side
            )
        else:
            fitted[label] = Fitted(float(theta[i]), None, None, False, at_bound=side)
    rms = {
        name: float(np.sqrt(np.mean(residual_si[:, s][present[:, s]] ** 2)))
        for s, name in enumerate(layout.signals)
        if present[:, s].any()
    }
    # −2 log-likelihood of the Gaussian noise model (up to N log 2π), and how many values
    # were estimated: the fitted ones and every estimated noise.
    minus_two_log_likelihood = chi2 + float(_log_likelihood_term(sigma, present))
    estimated = P + int(np.sum(present.any(-1) & ~np.asarray(data.sigma_given)))
    return CalibrationResult(
        fitted=fitted,
        values={label: float(theta[i]) for i, label in enumerate(layout.labels)},
        correlation=correlation,
        covariance=covariance,
        unidentifiable=unidentifiable,
        chi2=chi2,
        reduced_chi2=reduced,
        aic=minus_two_log_likelihood + 2 * estimated,
        bic=minus_two_log_likelihood + math.log(N) * estimated,
        samples=N,
        dof=dof,
        rms=rms,
        sigma=[e["sigma"] for e in experiments],
        converged=converged,
        starts=starts[0],
        starts_at_best=starts[1],
        steps=steps,
        experiments=experiments,
        validation=[],
        times=times,
        measured=measured,
        model=model,
        codes=codes,
        seconds=0.0,
        bounds={
            label: (float(layout.lower[i]), float(layout.upper[i]))
            for i, label in enumerate(layout.labels)
        },
        design={k: float(v) for k, v in calibration.design.items() if k != "t1"},
        check=check,
        **_structure(calibration),
    )


def _structure(calibration: Calibration) -> dict[str, Any]:
    """The model a calibration fits (`CalibrationResult.structure`), from its first
    experiment (they share one structure), and the values that experiment took from the
    defaults (those that act: not the contact's without an absorber)."""
    experiment = calibration.experiments[0]
    values = _design_of(calibration, experiment)
    groups = {PARAMETERS[name].group for name in values}
    if calibration.experiment_table(experiment) is not None:
        load = "force table"
    else:
        load = "pulse" if values.get("pulse_time", 0.0) > 0 else "impulse"
    given = {*calibration.fit, *experiment.design, *calibration.design}
    if values.get("m", 0.0) == 0:  # no absorber: its contact's values have no effect
        given |= {name for name in values if PARAMETERS[name].group == "contact"}
    structure = {
        "absorber": values.get("m", 0.0) > 0,
        "load": load,
        "shots": int(values.get("shots", 1)),
        "hardware": sorted(groups - {"barrel", "absorber", "contact", "load"}),
    }
    defaults = {k: v for k, v in values.items() if k not in given}
    return {"structure": structure, "defaults": defaults}


def _experiment_summary(experiment, e, layout, present, residual_si, measured, model):
    trace = experiment.fitted_trace
    n = len(trace.t)
    signals = [s for s in layout.signals if s in trace.signals]
    rows = {name: layout.signals.index(name) for name in signals}
    summary = {
        "name": experiment.label,
        "trace": trace.source,
        "samples": int(sum(present[e, s].sum() for s in rows.values())),
        "skipped": dict(trace.skipped),
        "rms": {
            name: float(np.sqrt(np.mean(residual_si[e, s][present[e, s]] ** 2)))
            for name, s in rows.items()
            if present[e, s].any()
        },
    }
    measured_signals = {
        name: np.where(present[e, s, :n], measured[e, s, :n], np.nan) for name, s in rows.items()
    }
    model_signals = {name: model[e, s, :n] for name, s in rows.items()}
    return summary, trace.t, measured_signals, model_signals


def _validation_problem(calibration: Calibration, experiment: Experiment) -> Calibration:
    """A validation experiment as a calibration of its own, every fitted name shared (its
    `per_experiment` dropped): checked as the fitted experiments are."""
    alone = dataclasses.replace(experiment, per_experiment=())
    return dataclasses.replace(calibration, experiments=(alone,), validation=())


def validate(
    calibration: Calibration, result: CalibrationResult, experiment: Experiment
) -> dict[str, Any]:
    """Score the fitted model on an experiment the fit did not see: its RMS residual per
    signal, its reduced χ² under the noise it was given, else the fit's (the first
    fitted experiment that measured the signal), else its own first guess, and its
    `model_check` against its own noise (`ModelCheck.to_json`: does the fitted model
    explain this trace too?).

    Each fitted name takes the experiment's own known value where it gives one (its
    `v0`, its `t_shift`), else the fitted shared value, else the mean of the fitted
    experiments' own values."""
    validating = _validation_problem(calibration, experiment)
    layout = _Layout.of(validating)
    values = []
    for label in layout.labels:
        if label in experiment.design:
            values.append(float(experiment.design[label]))
        elif label in result.values:
            values.append(result.values[label])
        else:
            own = [v for k, v in result.values.items() if k.startswith(label + "[")]
            values.append(float(np.mean(own)))
    data = _prepare(validating, validating.experiments, layout)
    sigma = np.array(data.sigma)
    for s, name in enumerate(layout.signals):
        if name in experiment.sigma:
            continue
        fitted = [e[name] for e in result.sigma if name in e]
        if fitted:
            sigma[0, s] = fitted[0]
    data = eqx.tree_at(lambda d: d.sigma, data, jnp.asarray(sigma))
    static = _Static(layout.wrt, layout.signals, calibration.loss, calibration.f_scale, 1)
    evaluation = _evaluate_program(jnp.asarray(values), data, static)
    r = np.asarray(evaluation.residuals)
    present = np.asarray(data.present)
    residual_si = r * sigma[..., None]
    summary, t, measured, model = _experiment_summary(
        experiment,
        0,
        layout,
        present,
        residual_si,
        np.asarray(data.measured),
        np.asarray(evaluation.signals),
    )
    summary["reduced_chi2"] = float(np.sum(r[present] ** 2) / max(int(present.sum()), 1))
    # Held to its own noise as the fitted traces are (its own `sigma` where given).
    summary["model_check"] = check_residuals(
        [(experiment.label, t, measured, model, experiment.sigma)],
        {name: SIGNALS[name][0] for name in layout.signals},
        robust=calibration.loss != "linear",
    ).to_json()
    summary["status"] = int(np.asarray(evaluation.codes)[0])
    return summary


def fit_many(
    calibration: Calibration, measured: Sequence[Sequence[Mapping[str, np.ndarray]]]
) -> list[dict[str, Any]]:
    """Fit many data sets of the same experiments at once (one batched program): e.g.
    noise draws of a synthetic test. `measured[b][e]`: the signals of experiment `e` in
    data set `b`, on that experiment's sample times. Returns each set's fitted values
    by label with their standard errors (`"<label>.stderr"`; NaN where withheld), a
    `"converged"` flag, whether the model `"explains"` the set, the `"failing"` signals
    (`"x_M in firing.csv"`) and the whole `"check"` (`ModelCheck`)."""
    layout = _Layout.of(calibration)
    data = _prepare(calibration, calibration.experiments, layout)
    static = _Static(layout.wrt, layout.signals, calibration.loss, calibration.f_scale, 200,
                     _estimates_noise(data))  # fmt: skip
    batch = np.zeros((len(measured), *data.measured.shape))
    for b, sets in enumerate(measured):
        for e, signals in enumerate(sets):
            for s, name in enumerate(layout.signals):
                if name in signals:
                    values = np.asarray(signals[name], dtype=float)
                    batch[b, e, s, : values.size] = values
    z0 = np.tile(_start_points(layout, 1, 0), (len(measured), 1))
    outcome = _fit_program(jnp.asarray(_u_of_z(z0)), jnp.asarray(batch), data, static)
    rows = []
    for b in range(len(measured)):
        data_b = eqx.tree_at(
            lambda d: (d.measured, d.sigma), data, (jnp.asarray(batch[b]), outcome.sigma[b])
        )
        report = _lane_report(calibration, layout, data_b, static, outcome, b, (1, 1))
        row: dict[str, Any] = {label: f.value for label, f in report.fitted.items()}
        row |= {
            f"{label}.stderr": (f.stderr if f.stderr is not None else math.nan)
            for label, f in report.fitted.items()
        }
        row["converged"] = report.converged
        row["explains"] = report.explains
        row["failing"] = [f"{c.signal} in {c.experiment}" for c in report.check.failing]
        row["check"] = report.check
        rows.append(row)
    return rows
