"""What a calibration gives: each fitted value (`Fitted`) and the whole report
(`CalibrationResult`), with its JSON (`result.json`) and the fitted hardware parameters
for predictions (`hardware()`)."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from .._model.parameter_table import PARAMETERS
from .._model.settings import Smoothing
from .._model.status import OK_CODE
from .model_check import ModelCheck, finite
from .predict import FittedParameters

__all__ = ["AT_BOUND", "REACHED", "CalibrationResult", "Fitted"]

#: A value within this of a bound of its box (box coordinates, the bounds 0 and 1) ended
#: on that bound (`Fitted.at_bound`): the fit's bounded transform approaches a bound it
#: is pressed against to ~1e-6 of the box.
AT_BOUND = 1e-4

#: A start reached the best when its score (−2 log-likelihood) is within this of the
#: best: a tenth of a standard error in the worst direction.
REACHED = 0.01


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
      words (`"k_c, n_c: 0.71·k_c − 0.70·n_c (box coordinates)"`); `unresolved`: the
      samples the standard errors leave out, on an event their sampling does not
      resolve (`{"experiment", "signal", "t"}` each).
    - `chi2`, `reduced_chi2`, `samples` (N), `dof` (N − P); `aic`, `bic`: −2
      log-likelihood of the Gaussian noise model (`chi2 + Σ n log σ²`, SI units, up to
      N log 2π) plus 2, or ln N, per estimated value (the fitted ones and each estimated
      noise); `rms`: per signal, the RMS residual (its unit); `sigma`: per experiment and
      signal, the noise used (given or estimated).
    - `converged`: the best start's fit converged; `starts`, `starts_at_best`: how many
      starts were run (each again where the fallback path ran: `fallback`) and how many
      reached the best (−2 log-likelihood within
      `REACHED`, 0.01); `continuation`: the widths fitted before the calibration's own;
      `smoothing`: the calibration's own, where the result is.
      `verdict`: the check and the starts together (`"explains"`, `"wrong_model"`,
      `"local_minimum"`).
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
    #: The samples left out of the standard errors: on an event their sampling does not
    #: resolve (`report.unresolved_samples`), each `{"experiment", "signal", "t"}`.
    unresolved: list[dict[str, Any]]
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
    #: The continuation's widths before the calibration's own (`Continuation.to_json`; {}:
    #: none).
    continuation: dict[str, list[float]] = dataclasses.field(default_factory=dict)
    defaults: dict[str, float] = dataclasses.field(default_factory=dict)
    #: The smoothing widths the result is at, by name (`Calibration.smoothing`, those of
    #: parts the design lacks at the model's: `acting_smoothing`; None: the width its
    #: rule derives).
    smoothing: dict[str, float | None] = dataclasses.field(default_factory=dict)
    #: The model check failed at the best point of the continuation's path, so the fit
    #: ran its fallback path too (`Continuation.fallback`); the result is the best of both.
    fallback: bool = False

    @property
    def verdict(self) -> str:
        """What the fit says of the model: `"explains"` (the check passed),
        `"wrong_model"` (it failed at a best point reached from two starts or more: the
        fit's global work is done, and the model does not explain the traces) or
        `"local_minimum"` (it failed at a best point reached from one start only, or
        from the one start run: the fit may be stuck, not the model wrong)."""
        if self.explains:
            return "explains"
        return "wrong_model" if self.starts_at_best >= 2 else "local_minimum"

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
            Smoothing(**self.smoothing) if self.smoothing else Smoothing(),
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
            "unresolved": self.unresolved,
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
            "verdict": self.verdict,
            "continuation": self.continuation,
            "smoothing": self.smoothing,
            "fallback": self.fallback,
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
