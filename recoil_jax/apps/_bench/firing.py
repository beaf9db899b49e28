"""The firing test the calibration benchmarks share (`bench-calibration`, and its
`--posterior`): the absorber model, 5 fitted values, x_M and F_AN measured, traces by the
independent reference solver with Gaussian noise."""

from __future__ import annotations

import numpy as np

import recoil_jax as rj
import recoil_jax.extend as rjx

__all__ = ["BOX", "NOISE", "TRUTH", "calibration_of", "firing_test"]

#: The firing test: the absorber model, 5 fitted parameters, x_M and F_AN measured.
TRUTH = {"k": 28000.0, "c_out": 6000.0, "c_ret": 14000.0, "gap": 0.02, "m": 1000.0}
BOX = {"k": (1e4, 1e5), "c_out": (1e3, 3e4), "c_ret": (1e3, 4e4), "gap": (0.0, 0.1),
       "m": (200.0, 3000.0)}  # fmt: skip
NOISE = {"x_M": 2e-4, "F_AN": 300.0}


def firing_test(known: dict, samples: int, end: float, seed: int):
    """`(t, {signal: measured})`: the reference solver's history with Gaussian noise."""
    ts = np.linspace(0.0, end, samples)
    history = rjx.reference_history(known | TRUTH, ts)
    rng = np.random.default_rng(seed)
    return ts, {s: history[s] + NOISE[s] * rng.standard_normal(samples) for s in NOISE}


def calibration_of(known: dict, ts, measured: dict) -> rj.Calibration:
    """The firing test as recoil-jax's calibration: the 5 values in `BOX`, the noise
    given."""
    experiment = rjx.Experiment(rjx.Trace.of(ts, **measured), design=known, sigma=NOISE)
    return rj.Calibration([experiment], fit=BOX)
