"""Where each fitted value goes (`Layout`) and the arrays a fit runs on (`CalibrationData`,
made by `prepare`): the experiments' designs batched, their samples padded to one
length, the noise assumed or given, and the end time of each solve.

`_Data` keeps its name and fields: a calibration's store is identified by a digest of
these arrays whose structure names the class (`campaign_identity`), so a store made
before a change of either would be refused. Other modules use its alias
`CalibrationData`.
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._model.derivatives import ABSORBER_SIGNALS, SIGNALS
from .._model.parameter_table import PARAMETERS
from .._model.params import ForceTable, RecoilParams, params_from_values, params_to_values
from .._model.registry import ParameterError
from .._model.settings import (
    T1_LIMITS,
    Smoothing,
    SolverOptions,
    end_time,
    with_default_tolerances,
)
from .._sweeps.batches import batch_params, with_table
from .._sweeps.space import SearchSpace, log_coordinates
from .continuation import acting_smoothing
from .model_check import trace_noise
from .traces import Experiment, known_values

__all__ = [
    "CalibrationData",
    "Layout",
    "check_fitted_designs",
    "design_of",
    "estimates_noise",
    "prepare",
]


@dataclasses.dataclass(frozen=True)
class Layout:
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
    def of(cls, calibration) -> Layout:
        """The layout of a `Calibration`: its fitted values' labels, bounds and starts (a
        start NaN where the design's value lies outside the bounds), and where each goes
        in each experiment.

        **Raises:** `ParameterError` from `design_of`: a design that does not hold a
        fitted parameter, or a signal of the absorber without one.
        """
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
            design = design_of(calibration, experiment)
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

    def start_z(self) -> np.ndarray:
        """The fit's first start `(P,)` in box coordinates: the given start, or the
        design's value where it lies inside the bounds, else the box's middle."""
        given = np.isfinite(self.start)
        return np.where(given, self.space.z(np.where(given, self.start, self.lower)), 0.5)

    def start_values(self) -> dict[str, float]:
        """The fit's first start by label (SI units; `start_z`)."""
        theta = np.asarray(self.space.theta(jnp.asarray(self.start_z())))
        return dict(zip(self.labels, map(float, theta), strict=True))

    @property
    def space(self) -> SearchSpace:
        """The fitted values' box as a search space: linear between the bounds, or
        logarithmic over three decades and more (`log_coordinates`)."""
        return SearchSpace(
            jnp.asarray(self.lower),
            jnp.asarray(self.upper),
            jnp.asarray(log_coordinates(self.lower, self.upper)),
        )


def check_fitted_designs(calibration, layout: Layout) -> None:
    """Each experiment's design as the fit will solve it, checked whole before the fit:
    at the fit's first start, and with each fitted value at its upper bound in turn (a
    fitted preload needs a battery stop; a mount must outweigh the gun it carries).

    **Raises:** `ParameterError` naming the experiment and the fitted values."""
    start = layout.start_values()
    fitted = list(calibration.experiments)
    for experiment in (*calibration.experiments, *calibration.validation):
        number = next((i for i, x in enumerate(fitted, 1) if x is experiment), None)
        at_start = {}
        for label, name in zip(layout.labels, layout.parameters, strict=True):
            owner = int(label[label.index("[") + 1 : -1]) if "[" in label else None
            if name != "t_shift" and ((owner is None and name not in at_start) or owner == number):
                at_start[name] = start[label]
        known = known_values(calibration.experiment_design(experiment))
        trials = [("at the fit's start", at_start)]
        trials += [
            (f"with {name} at its upper bound {calibration.fit[name][1]:g}, where the fit may go",
             at_start | {name: calibration.fit[name][1]})
            for name in at_start
        ]  # fmt: skip
        for where, values in trials:
            try:
                params_from_values(known | values)
            except ParameterError as error:
                shown = ", ".join(f"{n} = {v:g}" for n, v in values.items())
                raise ParameterError(f"{experiment.label}: {where} ({shown}): {error}") from None


def design_of(calibration, experiment: Experiment) -> dict[str, float]:
    """Every model parameter's value in an experiment of a `Calibration` (defaults,
    then known values).

    **Raises:** `ParameterError` for a design `params_from_values` refuses, a fitted
    parameter the design does not have, or a signal of the absorber without one.
    """
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
    given, `sigma_given (E, S)`, `index`, `known (E, K)` (`Layout`), the bounds' space."""

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


#: The name other modules use for `_Data`, whose own name stays (it is in the identity of
#: every calibration store).
CalibrationData = _Data


def prepare(calibration, experiments, layout: Layout) -> _Data:
    """The arrays of `experiments` (a `Calibration`'s, or one validation experiment in
    its own calibration) under `layout`.

    **Raises:** `ParameterError` for experiments of different structure, a force table
    given to some experiments and not others, or a trace that ends after its solve's end
    time `t1` (`_end_times`, `_check_end_times`).
    """
    designs, traces = [], []
    for experiment in experiments:
        design = known_values(calibration.experiment_design(experiment))
        designs.append(design)
        traces.append(experiment.fitted_trace)
    params = _batched_params(calibration, experiments, designs)
    samples = _samples(experiments, traces, layout)
    t1 = _end_times(calibration, experiments, traces, layout)
    _check_end_times(calibration, experiments, params, t1)
    options = with_default_tolerances(params, calibration.options)
    return _Data(
        params,
        jnp.asarray(samples.times),
        jnp.asarray(t1),
        jnp.asarray(samples.measured),
        jnp.asarray(samples.present),
        jnp.asarray(samples.sigma),
        jnp.asarray(samples.given),
        jnp.asarray(layout.index),
        jnp.asarray(layout.known),
        layout.space,
        acting_smoothing(params, calibration.smoothing),
        dataclasses.replace(options, t1=None),
    )


def _batched_params(calibration, experiments, designs) -> RecoilParams:
    """The experiments' designs `designs` (their known model values) as one batched
    `RecoilParams` (E,), each with its force table where they fire one.

    **Raises:** `ParameterError` for designs of different structure, or a force table for
    some experiments and not others.
    """
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
    return params


@dataclasses.dataclass(frozen=True)
class _Samples:
    """The traces' samples on one padded grid: `times (E, n)` (padded with the last
    time), `measured (E, S, n)` (0 where absent), `present (E, S, n)`, the noise
    `sigma (E, S)` (given, else a first guess) and which of it is `given (E, S)`."""

    times: np.ndarray
    measured: np.ndarray
    present: np.ndarray
    sigma: np.ndarray
    given: np.ndarray


def _samples(experiments, traces, layout: Layout) -> _Samples:
    """The samples of `traces` (each experiment's, within its window) by the layout's
    signals (`_Samples`)."""
    n = max(len(t.t) for t in traces)
    E, S = len(experiments), len(layout.signals)
    times = np.zeros((E, n))
    measured = np.zeros((E, S, n))
    present = np.zeros((E, S, n), dtype=bool)
    sigma = np.ones((E, S))
    given = np.zeros((E, S), dtype=bool)
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
    return _Samples(times, measured, present, sigma, given)


def _end_times(calibration, experiments, traces, layout: Layout) -> np.ndarray:
    """Each experiment's solve end time `t1 (E,)` (s): its trace's end at the earliest
    trigger the fit may try (the lower bound of its fitted `t_shift`, else its known
    one), or the `t1` it gives where that is later; at least 1e-6 s.

    **Raises:** `ParameterError` for a trace that runs past the `t1` it gives, its
    trigger delay known.
    """
    shift_column = layout.index[:, -1]
    t1 = np.zeros(len(experiments))
    for e, (experiment, trace) in enumerate(zip(experiments, traces, strict=True)):
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
        if needed > T1_LIMITS.ceiling:
            raise ParameterError(
                f"{trace.source} runs to t = {trace.t[-1]:g} s, past the longest solve "
                f"({T1_LIMITS.ceiling:g} s): are its times epoch seconds? The model's t = 0 "
                "is the firing: give times from it"
            )
        t1[e] = max(needed, 1e-6)
    return t1


def _check_end_times(calibration, experiments, params: RecoilParams, t1: np.ndarray) -> None:
    """Check that each experiment's solve may run to its end time `t1[e]` (`end_time`).

    **Raises:** `ParameterError`, naming the experiment, where it may not.
    """
    for e, experiment in enumerate(experiments):
        options = dataclasses.replace(calibration.options, t1=float(t1[e]))
        single = params_from_index(params, e)
        try:
            end_time(single, options)
        except ParameterError as error:
            raise ParameterError(f"{experiment.label}: {error}") from None


def params_from_index(params: RecoilParams, i: int) -> RecoilParams:
    """Design `i` of a batched `RecoilParams`."""
    return jax.tree.map(lambda leaf: leaf[i], params)


def estimates_noise(data: _Data) -> bool:
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
