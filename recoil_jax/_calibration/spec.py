"""The calibration problem as given (`Calibration`): the experiments, the parameters fitted
with their bounds and starts, the known values and the loss, all checked when it is made.

The checks of the bounds and starts are here; those of the designs, the signals and the
time spans are the layout's (`layout`), run from here, so that a bad calibration is
refused before anything compiles.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from typing import Literal

from .._model.derivatives import GRADIENT_OPTIONS
from .._model.parameter_table import PARAMETERS
from .._model.params import ForceTable
from .._model.registry import ParameterError, check_value
from .._model.settings import Smoothing, SolverOptions
from .layout import Layout, check_fitted_designs, prepare
from .traces import T_SHIFT, Experiment

__all__ = [
    "LOSSES",
    "Calibration",
    "check_fitted",
    "validation_problem",
]

#: The robust losses: `linear` (plain least squares), `soft_l1` and `huber` (scipy's),
#: each applied to the residual in units of `f_scale` noise deviations.
LOSSES = ("linear", "soft_l1", "huber")


def _fit_limits(name: str):
    """The valid range of a fitted name (`T_SHIFT` for the trigger delay)."""
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
    - `smoothing`, `options`: as for any solve (default the model's widths, and
      `GRADIENT_OPTIONS`, rtol 1e-7).
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
            check_fitted(name, bounds, self.start.get(name))
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
        layout = Layout.of(self)  # checks the designs and signals
        check_fitted_designs(self, layout)  # and each as the fit will solve it
        prepare(self, self.experiments, layout)  # and the time spans
        for experiment in self.validation:  # the same checks, before the fit
            validation_problem(self, experiment)

    def shared_start(self) -> dict[str, float]:
        """The values the fit starts from for the parameters every experiment shares (those
        a prediction takes from it), by name (SI units): the given start, or the design's
        value inside the bounds, else the box's middle."""
        start = Layout.of(self).start_values()
        return {
            name: value for name, value in start.items() if name in self.fit and name != "t_shift"
        }

    def experiment_design(self, experiment: Experiment) -> dict[str, float]:
        """The known values of one experiment: the shared ones, then its own."""
        return {**self.design, **experiment.design}

    def experiment_table(self, experiment: Experiment) -> ForceTable | None:
        """The force table one experiment fires: its own, else the shared one."""
        return experiment.force_table if experiment.force_table is not None else self.force_table


def check_fitted(name: str, bounds, start) -> None:
    """Check one fitted name, its `bounds` `(lower, upper)` and its `start` (None: none).

    **Raises:** `ParameterError` for an unknown or integer parameter, bounds that are not
    two numbers, outside the valid range or reversed, or a start outside them.
    """
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


def validation_problem(calibration: Calibration, experiment: Experiment) -> Calibration:
    """A validation experiment as a calibration of its own, every fitted name shared (its
    `per_experiment` dropped): checked as the fitted experiments are."""
    alone = dataclasses.replace(experiment, per_experiment=())
    return dataclasses.replace(calibration, experiments=(alone,), validation=())
