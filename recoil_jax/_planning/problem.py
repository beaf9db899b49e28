"""A firing test to plan (`PlanProblem`), checked when it is made: the best guess, what
the test must determine, the candidate conditions, the signals that can be recorded with
their noise and cost, the sampling, the budget and the criterion."""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Mapping, Sequence
from typing import NamedTuple

import numpy as np

from .._calibration.spec import check_fitted
from .._model.derivatives import ABSORBER_SIGNALS, GRADIENT_OPTIONS, SIGNALS
from .._model.parameter_table import PARAMETERS
from .._model.params import RecoilParams, params_from_values
from .._model.registry import ParameterError, check_integer, check_value
from .._model.settings import Smoothing, SolverOptions
from .._sweeps.memory import check_memory

__all__ = ["CRITERIA", "PlanProblem", "Sensor"]

#: The criteria besides one parameter's name: `D` (log det of the information, the
#: volume of the confidence ellipsoid) and `A` (the sum of the variances).
CRITERIA = ("D", "A")
#: The most samples one firing's signals may have (a guard against a unit slip in
#: `rate` or `duration`).
MAX_SAMPLES = 100_000
#: The most candidate firings (combinations of the conditions' values).
MAX_CANDIDATES = 1000


#: A signal's noise, SI units: below a picometre (piconewton) the information `J/σ²`
#: loses its digits (at 1e-160 it overflows), above 1e12 no test measures anything.
MIN_SIGMA, MAX_SIGMA = 1e-12, 1e12


def _real(where: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float | np.floating | np.integer):
        raise ParameterError(f"{where} = {value!r}: give a number")
    return float(value)


def _sensors(signals: Mapping) -> dict[str, Sensor]:
    sensors = {}
    for name, sensor in signals.items():
        if isinstance(sensor, Mapping):
            sensor = Sensor(**sensor)
        elif not isinstance(sensor, tuple | list) or not 1 <= len(sensor) <= 2:
            raise ParameterError(f"signals.{name} = {sensor!r}: give Sensor(sigma, cost)")
        sensor = Sensor(*sensor)
        sensors[name] = Sensor(_real(f"signals.{name}.sigma", sensor.sigma),
                               _real(f"signals.{name}.cost", sensor.cost))  # fmt: skip
    return sensors


def _candidates(candidates: Mapping) -> dict[str, tuple[float, ...]]:
    out = {}
    for name, values in candidates.items():
        if isinstance(values, str | bytes) or not isinstance(values, Sequence | np.ndarray):
            raise ParameterError(f"candidates.{name} = {values!r}: give a list of values")
        out[name] = tuple(_real(f"candidates.{name}", v) for v in values)
    return out


class Sensor(NamedTuple):
    """A signal that can be recorded: its noise `sigma` (standard deviation, the
    signal's unit) and its `cost` per firing (any unit the budget uses)."""

    sigma: float
    cost: float = 1.0


@dataclasses.dataclass(frozen=True)
class PlanProblem:
    """A firing test to plan.

    - `design`: the best guess before the test, by flat name: the fitted parameters'
      values (the truth the plan is made for; default their `PARAMETERS` default,
      which must lie within the bounds) and every known value.
    - `fit`: the parameters the test must determine, flat name → `(lower, upper)`.
    - `candidates`: condition parameter → the values a firing may take (e.g.
      `{"elevation": [0, 30, 70], "v0": [8, 10]}`): each firing takes any combination.
    - `signals`: signal name (`x_M`, `F_AN`, …) → `Sensor(sigma, cost)`.
    - `rate` (samples/s) and `duration` (s, from the firing): the sampling.
    - `firings`: how many rounds; `cost`: the most one firing's signals may cost (None:
      every signal).
    - `criterion`: `"D"`, `"A"` or a fitted parameter's name (its own variance).
    - `robust`: 0 plans at the guess; N averages the criterion over N draws from the
      `fit` box (`seed`).

    **Raises:** `ParameterError`, before anything compiles, naming the entry: an unknown
    or integer parameter, bounds or values outside their valid range, a guess outside
    its bounds, a candidate that is fitted, an unknown signal (or one of the absorber
    without one), a noise that is not positive, a budget no firing fits, a criterion not
    among `D`, `A` and the fitted names, or a sampling with no sample or too many.
    """

    design: Mapping[str, float]
    fit: Mapping[str, tuple[float, float]]
    candidates: Mapping[str, Sequence[float]]
    signals: Mapping[str, Sensor]
    rate: float = 1000.0
    duration: float = 1.0
    firings: int = 3
    cost: float | None = None
    criterion: str = "D"
    robust: int = 0
    seed: int = 0
    smoothing: Smoothing = Smoothing()  # noqa: RUF009 (immutable)
    options: SolverOptions = GRADIENT_OPTIONS

    def __post_init__(self):
        object.__setattr__(self, "signals", _sensors(self.signals))
        candidates = _candidates(self.candidates)
        object.__setattr__(self, "candidates", candidates)
        fit = {}
        for name, bounds in self.fit.items():
            try:
                fit[name] = tuple(float(b) for b in bounds)
            except (TypeError, ValueError):
                raise ParameterError(f"fit.{name} = {bounds!r}: give [lower, upper]") from None
        object.__setattr__(self, "fit", fit)
        for key in ("rate", "duration"):
            _real(f"sampling.{key}", getattr(self, key))
        if self.cost is not None:
            _real("budget.cost", self.cost)
        if not self.fit:
            raise ParameterError("plan: no parameter to determine ([fit] is empty)")
        for name, bounds in self.fit.items():
            if name == "t_shift":
                raise ParameterError("plan: fit.t_shift: a trigger delay is not planned for")
            if name not in PARAMETERS:
                raise ParameterError(f"fit: {PARAMETERS.unknown(name)}")
            check_fitted(name, bounds, None)
        for name, value in self.design.items():
            if name not in PARAMETERS:
                raise ParameterError(f"design: {PARAMETERS.unknown(name)}")
            if not (name == "m" and value == 0):  # m = 0: the model without an absorber
                check_value("design", name, value, PARAMETERS[name])
        for name, (lower, upper) in self.fit.items():
            guess = self.guess[name]
            if not lower <= guess <= upper:
                raise ParameterError(
                    f"plan: the guess {name} = {guess:g} is outside fit.{name} = [{lower:g}, "
                    f"{upper:g}]: give its best guess in [design]"
                )
        if not candidates:
            raise ParameterError("plan: no candidate condition ([candidates] is empty)")
        count = math.prod(len(values) for values in candidates.values())
        if count > MAX_CANDIDATES:  # before each value is checked (a million take 20 s)
            raise ParameterError(
                f"candidates: {count:,} combinations; valid at most {MAX_CANDIDATES:,} (fewer "
                "values, or fewer conditions)"
            )
        _check_candidate_values(candidates, self.fit)
        self._check_signals()
        if not (math.isfinite(self.rate) and 0 < self.rate <= 1e6):
            raise ParameterError(f"sampling.rate = {self.rate!r}: valid > 0 to 1e6 samples/s")
        if not (math.isfinite(self.duration) and 0.01 <= self.duration <= 60):
            raise ParameterError(f"sampling.duration = {self.duration!r}: valid 0.01 to 60 s")
        if not 1 <= self.samples <= MAX_SAMPLES:
            raise ParameterError(
                f"sampling: rate × duration = {self.samples:,} samples a signal: valid 1 to "
                f"{MAX_SAMPLES:,}"
            )
        object.__setattr__(self, "firings", check_integer("budget.firings", self.firings, 1, 50))
        if self.criterion not in (*CRITERIA, *self.fit):
            raise ParameterError(
                f"criterion = {self.criterion!r}: valid {', '.join(CRITERIA)} or a fitted "
                f"parameter ({', '.join(self.fit)})"
            )
        object.__setattr__(self, "robust", check_integer("robust", self.robust, 0, 256))
        object.__setattr__(self, "seed", check_integer("seed", self.seed, 0))
        self._check_size()
        # The design as a whole at every candidate (e.g. a mount lighter than the gun).
        for condition in self.conditions:
            try:
                params_from_values(self.guess | condition)
            except ParameterError as error:
                where = ", ".join(f"{k} = {v:g}" for k, v in condition.items())
                raise ParameterError(f"candidate {where}: {error}") from None

    def _check_size(self) -> None:
        """The sensitivities a plan holds at once, bounded by the free memory before it
        starts: per truth (the guess and each robust draw), 4 values a candidate, signal,
        sample and parameter (the value's too) in one array (measured), and a copy."""
        per_truth = (
            8 * 2 * 4 * len(self.conditions) * len(self.signals) * (len(self.fit) + 1)
            * self.samples
        )  # fmt: skip
        check_memory(
            1 + self.robust, per_truth, "a plan",
            "give fewer robust draws, candidates or samples (rate × duration)", unit="truths",
        )  # fmt: skip

    def _check_signals(self) -> None:
        if not self.signals:
            raise ParameterError("plan: no signal to record ([signals] is empty)")
        absorber = float(self.guess.get("m", PARAMETERS["m"].default)) > 0
        for name, sensor in self.signals.items():
            if name not in SIGNALS:
                raise ParameterError(
                    f"signals.{name}: no such signal; the model records {', '.join(SIGNALS)}"
                )
            if name in ABSORBER_SIGNALS and not absorber:
                raise ParameterError(f"signals.{name}: a signal of the absorber, and m = 0")
            if not (math.isfinite(sensor.sigma) and MIN_SIGMA <= sensor.sigma <= MAX_SIGMA):
                raise ParameterError(
                    f"signals.{name}.sigma = {sensor.sigma!r}: valid {MIN_SIGMA:g} to "
                    f"{MAX_SIGMA:g} (the signal's SI unit; the information goes as 1/sigma²)"
                )
            if not (math.isfinite(sensor.cost) and sensor.cost >= 0):
                raise ParameterError(f"signals.{name}.cost = {sensor.cost!r}: valid >= 0")
        if self.cost is not None:
            cheapest = min(s.cost for s in self.signals.values())
            if not (math.isfinite(self.cost) and self.cost >= cheapest):
                raise ParameterError(
                    f"budget.cost = {self.cost!r}: no firing fits (the cheapest signal costs "
                    f"{cheapest:g})"
                )

    @property
    def guess(self) -> dict[str, float]:
        """Every value given, and each fitted parameter's guess (its default if not)."""
        fitted = {name: float(PARAMETERS[name].default) for name in self.fit}
        return fitted | {name: float(v) for name, v in self.design.items()}

    @property
    def params(self) -> RecoilParams:
        """The guess as parameters, at the first candidate (so that every group a
        condition sets is there for the others to be set in)."""
        return params_from_values(self.guess | self.conditions[0])

    @property
    def samples(self) -> int:
        """Samples a signal per firing."""
        return math.floor(self.rate * self.duration + 1e-9)

    @property
    def times(self) -> np.ndarray:
        """The sample times `(n,)` (s): `1/rate, 2/rate, …` up to `duration`."""
        return np.arange(1, self.samples + 1) / self.rate

    @property
    def conditions(self) -> list[dict[str, float]]:
        """Every candidate firing's condition values, `{name: value}`, the first
        condition varying slowest."""
        names = tuple(self.candidates)
        return [
            dict(zip(names, row, strict=True))
            for row in itertools.product(*self.candidates.values())
        ]


def _check_candidate_values(candidates: dict[str, tuple[float, ...]], fit) -> None:
    """Each candidate condition is a parameter that is not fitted, not an integer count,
    with at least one value, each valid and none twice (`ParameterError`)."""
    for name, values in candidates.items():
        if name in fit:
            raise ParameterError(
                f"candidates.{name}: {name} is fitted; a firing's condition must be known"
            )
        if name not in PARAMETERS:
            raise ParameterError(f"candidates: {PARAMETERS.unknown(name)}")
        if PARAMETERS[name].integer:
            raise ParameterError(f"candidates.{name}: an integer count cannot be a condition")
        if not values:
            raise ParameterError(f"candidates.{name}: give at least one value")
        for value in values:
            check_value("candidates", name, value, PARAMETERS[name])
        if len(set(values)) != len(values):
            raise ParameterError(f"candidates.{name}: a value is given twice")
