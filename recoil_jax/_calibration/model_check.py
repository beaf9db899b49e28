"""Does the model explain the traces? A test of a fit's residuals that does not trust the
noise the fit estimated from them.

With its noise estimated from the residuals, a fit's reduced χ² is 1 by construction,
whatever the model: a wrong model is fitted "well" to noise it made up. This test
measures each signal's noise from its trace alone instead, and asks two questions of
the residuals, window by window:

- **Size.** Is their RMS far above the trace's own noise (or the noise the user gave)?
- **Whiteness.** Are they far more correlated from one sample to the next than the
  trace's own noise is? A model error is smooth; noise is not.

**The trace's own noise** comes from its high-pass: the samples less a least-squares
cubic through each 21 (Savitzky–Golay). On a densely sampled smooth signal that holds
the noise and almost none of the signal, and the few samples where the signal kinks
(the firing, an impact), beyond 4 robust deviations, are left out. A data logger's
filter colours the noise; the estimate allows for it as AR(1) noise,
`n_t = φ n_{t−1} + e_t`: the high-pass of such noise has a lag-1 correlation and a
variance that are known functions of φ (from the filter's own autocorrelation), so φ is
read from the one and the noise's variance from the other. (Second differences hold
less of the signal but read φ poorly: over 200 draws with φ = 0.5 their noise was off by
up to 138 %, this one's by up to 20 %.)

The limits (`RATIO_LIMIT`, `CORRELATION_LIMIT`, `CORRELATION_MARGIN`) were set from
noise draws of right and wrong fits (`docs/calibration.md`): over 200 right fits, with
white or AR(1) noise up to φ = 0.5, no window was over 1.19 times the noise or 0.21 above
its noise's correlation; the four wrong models' worst windows were 36 to 92 times.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any

import numpy as np

__all__ = [
    "CORRELATION_LIMIT",
    "CORRELATION_MARGIN",
    "RATIO_LIMIT",
    "ModelCheck",
    "NoiseEstimate",
    "SignalCheck",
    "Window",
    "check_residuals",
    "finite",
    "trace_noise",
]

#: A window fails when its residual RMS is more than this many times the noise.
RATIO_LIMIT = 2.0
#: ... or when its residuals' lag-1 autocorrelation is above this, and above the trace's
#: own noise's by `CORRELATION_MARGIN`, while their RMS is above `WHITENESS_RATIO`
#: times the noise (a correlated residual far under the noise is not a misfit).
CORRELATION_LIMIT = 0.8
CORRELATION_MARGIN = 0.3
WHITENESS_RATIO = 1.25
#: Windows hold at least this many samples (a lag-1 autocorrelation of AR(1) noise with
#: φ = 0.5 is then within ±0.06, one standard deviation), and a signal has at most
#: `MAX_WINDOWS` of them.
WINDOW_SAMPLES = 200
MAX_WINDOWS = 10
#: Fewer samples than this: the noise cannot be estimated, the signal is not tested (the
#: command line's report says 20).
MIN_SAMPLES = 20
#: The noise a signal is tested against is at least this fraction of its range (peak to
#: peak): a noise-free trace is not held to rounding.
NOISE_FLOOR = 1e-4
#: High-pass samples beyond this many robust deviations are kinks of the signal (an
#: impact, the firing), not noise.
_TRIM = 4.0
#: The largest noise correlation read from a trace: noise more coloured than this
#: cannot be told from a slow signal by its high-pass.
_PHI_MAX = 0.9
#: The high-pass's width (samples): a cubic over 21 samples follows the paper's designs
#: at 1 kHz to 1e-6 of a 0.3 mm or 40 N noise away from their kinks, and leaves a band
#: wide enough to read the noise's colour (over 50 draws of 1,001 samples: σ within 13 %
#: and φ within 0.11, for φ up to 0.5; wider, the absorber's impacts leak in).
_WIDTH = 21


@dataclasses.dataclass(frozen=True)
class NoiseEstimate:
    """A signal's noise from its samples alone (`trace_noise`): `sigma` (its unit) and
    `correlation` φ (lag-1, AR(1)); NaN for both with fewer than `MIN_SAMPLES` samples."""

    sigma: float
    correlation: float


def trace_noise(values) -> NoiseEstimate:
    """The noise of one measured signal `(n,)` (NaN where missing) from its high-pass
    (the samples less a local cubic fit): robust to a few kinks, allowing for AR(1)
    colour (module doc)."""
    y = np.asarray(values, dtype=float)
    y = y[np.isfinite(y)]
    if y.size < MIN_SAMPLES:
        return NoiseEstimate(math.nan, math.nan)
    width = min(_WIDTH, 2 * (y.size // 6) + 1)
    power_of, correlation_of = _high_pass_tables(width)
    size = float(np.max(np.abs(y)))
    if size == 0.0:
        return NoiseEstimate(0.0, 0.0)
    e = np.convolve(y / size, _high_pass(width), mode="valid")  # in units of its size:
    # squares of a signal near the largest float64 would overflow
    centre = float(np.median(e))
    scale = 1.4826 * float(np.median(np.abs(e - centre)))
    if scale == 0.0:  # constant, or quantised coarser than its noise: then the rounding,
        # a step over √12, is the noise (a logger's smallest step is its quantum)
        steps = np.abs(np.diff(y))
        steps = steps[steps > 0]
        return NoiseEstimate(float(np.min(steps)) / math.sqrt(12.0) if steps.size else 0.0, 0.0)
    keep = np.abs(e - centre) <= _TRIM * scale
    pairs = keep[1:] & keep[:-1]
    power = float(np.mean(e[keep] ** 2))
    rho = float(np.sum(e[1:][pairs] * e[:-1][pairs])) / max(
        float(np.sum(e[:-1][pairs] ** 2)), 1e-300
    )
    # ρ(φ) rises with φ: the φ whose high-pass has this lag-1 correlation.
    i = int(np.clip(np.searchsorted(correlation_of, rho), 0, _PHIS.size - 1))
    return NoiseEstimate(size * math.sqrt(power / power_of[i]), float(_PHIS[i]))


#: The correlations φ the tables hold (`trace_noise` reads φ to 0.001).
_PHIS = np.linspace(-0.5, _PHI_MAX, 1401)


@functools.cache
def _high_pass(width: int) -> np.ndarray:
    """The samples less their least-squares cubic over `width` samples (Savitzky–Golay):
    the filter `(width,)` that leaves the noise and removes a smooth signal."""
    x = np.arange(width) - width // 2
    smooth = np.linalg.pinv(np.vander(x, 4, increasing=True))[0]
    return np.eye(width)[width // 2] - smooth


@functools.cache
def _high_pass_tables(width: int) -> tuple[np.ndarray, np.ndarray]:
    """For AR(1) noise of unit variance and each φ in `_PHIS`: the high-pass's variance,
    and its lag-1 correlation (increasing in φ)."""
    h = _high_pass(width)
    autocorrelation = np.convolve(h, h[::-1])  # of the filter, lags −(w−1) .. w−1
    lags = np.arange(-(width - 1), width)
    power = np.array([np.sum(autocorrelation * phi ** np.abs(lags)) for phi in _PHIS])
    lagged = np.array([np.sum(autocorrelation * phi ** np.abs(lags + 1)) for phi in _PHIS])
    return power, lagged / power


@dataclasses.dataclass(frozen=True)
class Window:
    """A stretch of one signal's samples: `start`, `end` (s, the trace's time), its
    residual `rms` (the signal's unit), `ratio` (rms over the noise), lag-1
    `correlation`, and whether it `fails`."""

    start: float
    end: float
    rms: float
    ratio: float
    correlation: float
    fails: bool


@dataclasses.dataclass(frozen=True)
class SignalCheck:
    """The test of one experiment's signal.

    - `noise`: what the residuals are held to (its unit): the `sigma` given
      (`noise_given`), else the trace's own noise (at least `NOISE_FLOOR` of its range);
      `trace_noise`, `trace_correlation`: the trace's own noise and its φ.
    - `rms`, `ratio`, `correlation`: the residuals over the whole trace (`rms`: with a
      robust loss, their robust scale).
    - `windows`: the same per stretch; `fails`: some window fails.
    """

    experiment: str
    signal: str
    unit: str
    noise: float
    noise_given: bool
    trace_noise: float
    trace_correlation: float
    rms: float
    ratio: float
    correlation: float
    windows: tuple[Window, ...]

    @property
    def fails(self) -> bool:
        return any(w.fails for w in self.windows)

    @property
    def failing(self) -> tuple[Window, ...]:
        return tuple(w for w in self.windows if w.fails)

    def failing_spans(self) -> list[tuple[float, float]]:
        """The failing windows as spans of time `(start, end)` (s), neighbours joined."""
        return _spans(self.windows)

    def reason(self) -> str:
        """What fails, in a line: the signal, its residuals against the noise, where."""
        held = "the given noise" if self.noise_given else "the trace's own noise"
        failing = self.failing
        spans = ", ".join(f"{a:.3g}–{b:.3g} s" for a, b in self.failing_spans())
        white = (
            f"not white (lag-1 autocorrelation {self.correlation:.2f}; the trace's noise "
            f"{self.trace_correlation:.2f})"
            if self.correlation > _correlation_limit(self.trace_correlation)
            else f"lag-1 autocorrelation {self.correlation:.2f}"
        )
        return (
            f"{self.signal} in {self.experiment}: residual RMS {self.rms:.3g} {self.unit} is "
            f"{self.ratio:.3g}× {held} ({self.noise:.3g} {self.unit}), {white}; fails over "
            f"{spans} ({len(failing)} of {len(self.windows)} windows)"
        )

    def to_json(self) -> dict[str, Any]:
        out = {k: v for k, v in dataclasses.asdict(self).items() if k != "windows"}
        out["fails"] = self.fails
        out["windows"] = [
            {k: finite(v) for k, v in dataclasses.asdict(w).items()} for w in self.windows
        ]
        return {k: finite(v) for k, v in out.items()}


def finite(value):
    """A number as a float, None (JSON's null) where it is not finite; anything else as
    it is."""
    if isinstance(value, float | np.floating):
        return float(value) if math.isfinite(value) else None
    return value


def _spans(windows: tuple[Window, ...]) -> list[tuple[float, float]]:
    spans: list[tuple[float, float]] = []
    previous = False
    for w in windows:
        if w.fails and previous:
            spans[-1] = (spans[-1][0], w.end)
        elif w.fails:
            spans.append((w.start, w.end))
        previous = w.fails
    return spans


@dataclasses.dataclass(frozen=True)
class ModelCheck:
    """The test of every fitted experiment's signals (`CalibrationResult.check`):
    `signals` (`SignalCheck`s; a signal with fewer than `MIN_SAMPLES` samples is not
    tested), `explains` (no signal fails), `failing`."""

    signals: tuple[SignalCheck, ...]

    @property
    def explains(self) -> bool:
        return not self.failing

    @property
    def tested(self) -> bool:
        """Some signal had the `MIN_SAMPLES` a test needs."""
        return bool(self.signals)

    @property
    def failing(self) -> tuple[SignalCheck, ...]:
        return tuple(s for s in self.signals if s.fails)

    def to_json(self) -> dict[str, Any]:
        return {
            "explains": self.explains,
            "tested": self.tested,
            "limits": {
                "ratio": RATIO_LIMIT,
                "correlation": CORRELATION_LIMIT,
                "correlation_margin": CORRELATION_MARGIN,
                "whiteness_ratio": WHITENESS_RATIO,
            },
            "failing": [s.reason() for s in self.failing],
            "signals": [s.to_json() for s in self.signals],
        }


def _correlation_limit(trace_correlation: float) -> float:
    """The lag-1 autocorrelation over which residuals are far from white, for a trace
    whose own noise has `trace_correlation` (NaN: unknown)."""
    own = trace_correlation if math.isfinite(trace_correlation) else 0.0
    return max(CORRELATION_LIMIT, own + CORRELATION_MARGIN)


def _window(t, r, noise: float, trace_correlation: float, robust: bool) -> Window:
    # A fit with a robust loss is judged as it fitted: by a scale a few outliers do not
    # move (a model error moves it: it shifts most residuals of a window).
    rms = 1.4826 * float(np.median(np.abs(r))) if robust else float(np.sqrt(np.mean(r * r)))
    power = float(np.sum(r * r))
    correlation = float(np.sum(r[1:] * r[:-1]) / power) if power > 0 else 0.0
    ratio = rms / noise
    limit = _correlation_limit(trace_correlation)
    fails = ratio > RATIO_LIMIT or (correlation > limit and ratio > WHITENESS_RATIO)
    fails = fails or not math.isfinite(rms)  # a failed solve explains nothing
    return Window(float(t[0]), float(t[-1]), rms, ratio, correlation, bool(fails))


def check_signal(
    experiment: str, signal: str, unit: str, t, measured, model, given: float | None,
    robust: bool = False,
) -> SignalCheck | None:  # fmt: skip
    """The test of one signal: sample times `t (n,)`, `measured (n,)` (NaN where
    missing), the fitted `model (n,)`, the noise `given` (None: the trace's own);
    `robust`: the residuals' size is their robust scale, `1.4826 median |r|`, not their
    RMS (the fit's loss was robust to outliers)."""
    present = np.isfinite(measured)
    if present.sum() < MIN_SAMPLES:
        return None
    t, y, r = t[present], measured[present], (measured - model)[present]
    own = trace_noise(y)
    floor = NOISE_FLOOR * float(np.ptp(y))
    noise = float(given) if given is not None else max(own.sigma, floor, 1e-300)
    count = int(np.clip(len(r) // WINDOW_SAMPLES, 1, MAX_WINDOWS))
    windows = tuple(
        _window(t[i], r[i], noise, own.correlation, robust)
        for i in np.array_split(np.arange(len(r)), count)
    )
    whole = _window(t, r, noise, own.correlation, robust)
    return SignalCheck(experiment, signal, unit, noise, given is not None, own.sigma,
                       own.correlation, whole.rms, whole.ratio, whole.correlation,
                       windows)  # fmt: skip


def check_residuals(experiments, units: dict[str, str], robust: bool = False) -> ModelCheck:
    """The test of a fit: `experiments`, one `(name, t (n,), measured {signal: (n,)},
    model {signal: (n,)}, given {signal: noise})` each; `robust` as `check_signal`."""
    checks = []
    for name, t, measured, model, given in experiments:
        for signal, values in measured.items():
            check = check_signal(name, signal, units[signal], np.asarray(t),
                                 np.asarray(values), np.asarray(model[signal]),
                                 given.get(signal), robust)  # fmt: skip
            if check is not None:
                checks.append(check)
    return ModelCheck(tuple(checks))
