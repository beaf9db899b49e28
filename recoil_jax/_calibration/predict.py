"""From a calibration to designs: the fitted hardware parameters with their uncertainty
(`FittedParameters`) and any design's peaks with a 95 % band from it (`predict`)."""

from __future__ import annotations

import dataclasses
import json
import math
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from .._model.derivatives import GRADIENT_OPTIONS, peak_jacobian
from .._model.metrics import METRICS
from .._model.parameter_table import PARAMETERS
from .._model.params import params_from_values
from .._model.registry import ParameterError, check_integer
from .._model.settings import Smoothing, SolverOptions
from .._model.solve import peaks
from .._model.text_files import read_text
from .._sweeps.sweep import sweep

__all__ = ["FittedParameters", "Prediction", "predict"]


#: Smoothing widths a `result.json` may hold from before model revision 3 (the rails'
#: friction, smoothed then; a mode of the solve now), read past.
_RETIRED_WIDTHS = ("friction_width", "slip_width", "stick_time")


@dataclasses.dataclass(frozen=True)
class FittedParameters:
    """The hardware parameters a calibration fitted (shared by its experiments; not the
    trigger delays or per-experiment values), with their uncertainty.

    - `names (k,)`, `values (k,)` (SI units), `covariance (k, k)`, the fit's bounds
      `lower`, `upper (k,)`, and `identifiable (k,)`;
    - `design`: the known values the calibration shared (`[design]`), which a prediction
      starts from;
    - `smoothing`: the widths the fit was at (`CalibrationResult.smoothing`), which a
      prediction solves at;
    - `draws (N, k)`: the posterior's draws of the values (`Posterior.hardware`), which
      `sample` then gives instead of the normal's samples; None from a fit alone.
    """

    names: tuple[str, ...]
    values: np.ndarray
    covariance: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    identifiable: np.ndarray
    design: dict[str, float]
    #: The calibration's model explained its traces (`CalibrationResult.explains`).
    explains: bool = True
    smoothing: Smoothing = dataclasses.field(default_factory=Smoothing)
    draws: np.ndarray | None = None

    def __post_init__(self):
        if not self.names:
            raise ParameterError("the calibration fitted no shared hardware parameter")

    def check_determined(self) -> None:
        """Raise `ParameterError` if a fitted value is not determined by the data: a band
        around it would not mean anything, or if the model did not explain the traces."""
        if not self.explains:
            raise ParameterError(
                "the calibration's model does not explain its traces (model_check in its "
                "result.json): its uncertainty would mean nothing; fit the right model first"
            )
        loose = [n for n, ok in zip(self.names, self.identifiable, strict=True) if not ok]
        if loose:
            raise ParameterError(
                f"{', '.join(loose)} not determined by the calibration's data: a band from "
                "its uncertainty would mean nothing; fit again with more data, or fix "
                "it as a known value"
            )

    def sample(self, count: int, seed: int = 0) -> tuple[np.ndarray, int]:
        """`count` draws `(count, k)` from the normal of the fit (seeded), clipped to the
        fit's bounds, and how many were clipped. With the posterior's `draws`: `count` of
        them, evenly spread over every chain (each once; where `count` is more, each
        about `count / N` times), none clipped (they lie within the bounds) and `seed`
        unused."""
        rng = np.random.default_rng(seed)
        if self.draws is not None:
            # Each draw ⌊count/N⌋ or ⌈count/N⌉ times, in order (so over every chain).
            index = np.arange(count) * len(self.draws) // count
            return self.draws[index], 0
        draws = rng.multivariate_normal(self.values, self.covariance, size=count, method="eigh")
        clipped = np.any((draws < self.lower) | (draws > self.upper), axis=1)
        return np.clip(draws, self.lower, self.upper), int(clipped.sum())

    def sigma_points(self) -> np.ndarray:
        """`(2k + 1, k)`: the fitted values, and each ± √k times a column of the
        covariance's square root (the unscented transform's points, equal weights on
        the sides): a fixed set whose spread is the fit's. Clipped to the bounds."""
        k = len(self.names)
        root = np.linalg.cholesky(self.covariance + 1e-300 * np.eye(k))
        offsets = math.sqrt(k) * root.T
        points = np.concatenate([self.values[None], self.values + offsets, self.values - offsets])
        return np.clip(points, self.lower, self.upper)

    @property
    def fitted_design(self) -> dict[str, float]:
        """The calibration's known values with the fitted values: the design it found."""
        return {**self.design, **dict(zip(self.names, self.values.tolist(), strict=True))}

    def box(self, sigmas: float = 2.0) -> dict[str, tuple[float, float]]:
        """Each fitted value ± `sigmas` standard errors, within the fit's bounds: ranges
        for `sensitivity` (uniform over the box; the correlations are not kept)."""
        if not (math.isfinite(sigmas) and sigmas > 0):
            raise ParameterError(f"sigmas = {sigmas!r}: give a number > 0")
        self.check_determined()
        variance = np.diag(self.covariance)
        for name, v in zip(self.names, variance, strict=True):
            if not (math.isfinite(v) and v > 0):
                raise ParameterError(
                    f"{name}: its variance in the calibration's covariance is {v:g}, not a "
                    "positive number: the fit gives it no uncertainty to range over; fit "
                    "again, or give its range yourself"
                )
        stderr = np.sqrt(variance) * sigmas
        lower = np.maximum(self.values - stderr, self.lower)
        upper = np.minimum(self.values + stderr, self.upper)
        return {
            n: (float(lo), float(hi)) for n, lo, hi in zip(self.names, lower, upper, strict=True)
        }

    def to_json(self) -> dict[str, Any]:
        return {
            "names": list(self.names),
            "values": self.values.tolist(),
            "covariance": self.covariance.tolist(),
            "lower": self.lower.tolist(),
            "upper": self.upper.tolist(),
            "identifiable": self.identifiable.tolist(),
            "design": self.design,
            "explains": self.explains,
        }

    @classmethod
    def from_json(cls, path) -> FittedParameters:
        """Read the `hardware` entry of a calibration's `result.json`."""
        text = read_text(Path(path), "calibration result")
        try:
            report = json.loads(text)
            entry = report["hardware"]
            # Results written before a calibration had widths of its own: the model's. The
            # friction's widths are gone since the stick became a mode (model revision 3):
            # a result that has them was fitted at a smoothed stick, its values still
            # the hardware's.
            widths = {k: v for k, v in (report.get("smoothing") or {}).items()
                      if k not in _RETIRED_WIDTHS}  # fmt: skip
            fitted = cls(
                tuple(entry["names"]),
                np.asarray(entry["values"], dtype=float),
                np.asarray(entry["covariance"], dtype=float),
                np.asarray(entry["lower"], dtype=float),
                np.asarray(entry["upper"], dtype=float),
                np.asarray(entry["identifiable"], dtype=bool),
                {k: float(v) for k, v in entry["design"].items()},
                bool(entry.get("explains", True)),  # results written before the check
                Smoothing(**widths),
            )
        except (json.JSONDecodeError, KeyError, TypeError, ValueError, ParameterError):
            raise ParameterError(
                f"{path} is not a calibration result (recoil-jax calibrate's result.json)"
            ) from None
        k = len(fitted.names)
        shapes = [fitted.values.shape, fitted.lower.shape, fitted.upper.shape]
        if any(s != (k,) for s in shapes) or fitted.covariance.shape != (k, k):
            raise ParameterError(f"{path}: its hardware entry's sizes do not agree")
        for name in fitted.names:
            if name not in PARAMETERS:
                raise PARAMETERS.unknown(name)
        return fitted


@dataclasses.dataclass(frozen=True)
class Prediction:
    """A design's peaks under the fitted uncertainty (`predict`).

    - `design`: every value given (the calibration's known ones, yours, the fitted ones);
      `given`: yours, the design it predicts (empty: the calibration's own design).
    - `nominal`: each metric (`METRICS`) at the fitted values.
    - `sampled`: per metric, `mean`, `std` and `ci95` (2.5 and 97.5 percentiles) over the
      covariance samples; `linear`: per metric, `std` and `ci95` (± 1.96 std) from the
      exact gradient and the covariance (`g Σ gᵀ`).
    - `samples`: per metric, the sampled values `(n,)`; `count`, `clipped` (draws moved
      to the fit's bounds), `failed` (solves that failed, left out and counted),
      `seconds`.
    """

    design: dict[str, float]
    given: dict[str, float]
    nominal: dict[str, float]
    sampled: dict[str, dict[str, Any]]
    linear: dict[str, dict[str, Any]]
    samples: dict[str, np.ndarray]
    count: int
    clipped: int
    failed: int
    seconds: float

    def to_json(self) -> dict[str, Any]:
        return {
            "design": self.design,
            "given": self.given,
            "nominal": self.nominal,
            "sampled": self.sampled,
            "linear": self.linear,
            "count": self.count,
            "clipped": self.clipped,
            "failed": self.failed,
            "seconds": self.seconds,
        }


def predict(
    fitted: FittedParameters,
    design: Mapping[str, float] | None = None,
    *,
    samples: int = 10_000,
    seed: int = 0,
    smoothing: Smoothing | None = None,
    options: SolverOptions = SolverOptions(),
    progress: bool | None = None,
) -> Prediction:
    """Any design's peak metrics with a 95 % band from a calibration's uncertainty, two
    ways: `samples` draws from the fitted normal (or, from `Posterior.hardware()`, the
    posterior's draws, `seed` then unused) through one batched sweep, and linear
    propagation of the covariance through the exact gradients at the fitted values.

    **Arguments:**

    - `fitted`: `CalibrationResult.hardware()` or `FittedParameters.from_json(path)`.
    - `design`: the design's values by flat name (the calibration's known values fill
      in; the fitted parameters take their fitted values and may not be given).
    - `samples`, `seed`: the draws; `smoothing`, `options`: the solves' (`smoothing`
      by default the fit's own, `fitted.smoothing`: its values belong to those widths).

    **Raises:** `ParameterError` for a fitted parameter given in `design`, a fitted value
    the data did not determine, or `samples < 2`.
    """
    design = _checked_design(fitted, design, samples)
    smoothing = fitted.smoothing if smoothing is None else smoothing
    clock = time.perf_counter()
    values = {
        **fitted.design,
        **design,
        **dict(zip(fitted.names, fitted.values.tolist(), strict=True)),
    }
    params = params_from_values(values)
    nominal_peaks = peaks(params, smoothing, options)
    draws, clipped = fitted.sample(samples, seed)
    columns = {name: np.full(samples, float(v)) for name, v in values.items()}
    columns |= {name: draws[:, j] for j, name in enumerate(fitted.names)}
    result = sweep(columns, smoothing=smoothing, options=options, progress=progress)
    ok = result.ok
    if ok.sum() < 2:
        raise ParameterError(
            f"predict: {int((~ok).sum())} of {samples} solves failed "
            f"({result.failures()[0][1]}): no band to give; check the design"
        )
    _, gradients = peak_jacobian(params, smoothing, GRADIENT_OPTIONS, fitted.names)
    bands = _bands(nominal_peaks, result, gradients, fitted.covariance)
    return Prediction(
        design={k: float(v) for k, v in values.items()},
        given={k: float(v) for k, v in design.items()},
        nominal=bands.nominal,
        sampled=bands.sampled,
        linear=bands.linear,
        samples=bands.samples,
        count=samples,
        clipped=clipped,
        failed=int((~ok).sum()),
        seconds=time.perf_counter() - clock,
    )


def _checked_design(
    fitted: FittedParameters, design: Mapping[str, float] | None, samples: int
) -> dict[str, float]:
    """The design a prediction is asked for, as a dict, once `samples` and `fitted` are
    checked.

    **Raises:** `ParameterError` for `samples < 2` (or not an integer), a fitted value
    the data did not determine (`FittedParameters.check_determined`), or a fitted
    parameter given in `design`.
    """
    samples = check_integer("samples", samples, 2)
    fitted.check_determined()
    design = dict(design or {})
    for name in design:
        if name in fitted.names:
            raise ParameterError(
                f"{name} is fitted: its value comes from the calibration "
                f"({fitted.values[fitted.names.index(name)]:g}); leave it out of the design"
            )
    return design


@dataclasses.dataclass(frozen=True)
class _Bands:
    """Each metric's band (`Prediction`'s fields of the same names): `nominal` at the
    fitted values, `sampled` (mean, std, ci95) over the draws that solved, `linear` (std,
    ci95) from the gradient and the covariance, and the draws' values, `samples`."""

    nominal: dict[str, float]
    sampled: dict[str, dict[str, Any]]
    linear: dict[str, dict[str, Any]]
    samples: dict[str, np.ndarray]


def _bands(nominal_peaks, result, gradients, covariance: np.ndarray) -> _Bands:
    """Each metric's band (`_Bands`) from the peaks at the fitted values
    `nominal_peaks`, the sweep of the draws `result` (its solves that failed left out),
    and the metrics' `gradients` with respect to the fitted values, whose `covariance
    (k, k)` they propagate (`g Σ gᵀ`)."""
    ok = result.ok
    nominal, sampled, linear, kept = {}, {}, {}, {}
    for name in METRICS:
        nominal[name] = float(getattr(nominal_peaks, name))
        values_ = result.peaks[name][ok]
        kept[name] = values_
        low, high = np.percentile(values_, [2.5, 97.5])
        sampled[name] = {
            "mean": float(np.mean(values_)),
            "std": float(np.std(values_, ddof=1)),
            "ci95": [float(low), float(high)],
        }
        g = np.asarray(getattr(gradients, name), dtype=float)
        std = float(math.sqrt(max(g @ covariance @ g, 0.0)))
        linear[name] = {
            "std": std,
            "ci95": [nominal[name] - 1.96 * std, nominal[name] + 1.96 * std],
        }
    return _Bands(nominal, sampled, linear, kept)
