"""A fit's report (`CalibrationResult`) at its optimum: the misfit (χ², the samples and
degrees of freedom), the uncertainty (the Gauss–Newton covariance scaled by the reduced
χ², lmfit's default, and the directions the data cannot confine within the bounds, by
name), each experiment's fit and the model check, and each fitted value (`Fitted`).

Each piece is a function of its own with a named result: `_misfit` (`_Misfit`),
`_uncertainty` (`_Uncertainty`), `_experiment_fits` (`_ExperimentFits`), `_fitted`;
`_report` puts them together.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._model.derivatives import SIGNALS
from .._model.parameter_table import PARAMETERS
from .._model.registry import PAPER_GROUPS, ParameterError
from .layout import CalibrationData, Layout, design_of
from .least_squares import (
    Evaluation,
    FitOutcome,
    FitSettings,
    evaluate_program,
    jumps_at,
    log_likelihood_term,
    robust,
    theta_of_u,
)
from .model_check import ModelCheck, check_residuals
from .result import AT_BOUND, CalibrationResult, Fitted
from .spec import Calibration
from .traces import Experiment

__all__ = [
    "BoxCovariance",
    "ExperimentFit",
    "box_covariance",
    "experiment_summary",
    "lane_report",
    "unresolved_samples",
]

#: A sample at which the model's signal moves, over the sample's own spacing, more than
#: this many times its step to either neighbour (and more than the noise) lies on an
#: event its sampling does not resolve: the counter-recoil buffer's engagement, an impact
#: shorter than a sample. Its Jacobian is the slope of the model's smoothed switch there, which
#: grows as 1 / the switch's width: the smoothing's information, not the data's, so the
#: standard errors leave it out (a sine sampled 3 times a period moves 2.4 times its step
#: at most; a ramp 30 µs wide sampled each ms, ~30 times).
UNRESOLVED_RATIO = 3.0


def lane_report(
    calibration: Calibration,
    layout: Layout,
    data: CalibrationData,
    static: FitSettings,
    outcome: FitOutcome,
    lane: int,
    *,
    starts: int,
    at_best: int,
) -> CalibrationResult:
    """The report of one lane of a batched fit, on `data` (with that lane's noise), of
    `starts` starts of which `at_best` reached the best.

    **Raises:** `ParameterError` where no sample lies within the experiments' windows.
    """
    theta = theta_of_u(outcome.u[lane], data.space)
    evaluation = evaluate_program(theta, data, static)
    return _report(
        calibration,
        layout,
        data,
        evaluation,
        np.asarray(theta),
        converged=bool(outcome.converged[lane]),
        starts=starts,
        at_best=at_best,
        steps=int(outcome.steps[lane]),
    )


def _report(
    calibration: Calibration,
    layout: Layout,
    data: CalibrationData,
    evaluation: Evaluation,
    theta: np.ndarray,
    *,
    converged: bool,
    starts: int,
    at_best: int,
    steps: int,
) -> CalibrationResult:
    """The report at the fitted values `theta (P,)` (SI units), from `evaluation` there:
    the pieces (`_misfit`, `_uncertainty`, `_experiment_fits`, `_fitted`), the RMS per
    signal, AIC and BIC.

    **Raises:** `ParameterError` where no sample lies within the experiments' windows.
    """
    misfit = _misfit(calibration, data, evaluation, len(theta))
    uncertainty = _uncertainty(layout, theta, misfit)
    unresolved = [
        {"experiment": calibration.experiments[e].label, "signal": layout.signals[s],
         "t": float(np.asarray(data.times)[e, i])}
        for e, s, i in np.argwhere(misfit.unresolved)
    ]  # fmt: skip
    fits = _experiment_fits(calibration, layout, data, evaluation, misfit)
    fitted = _fitted(layout, theta, uncertainty, fits.check.explains)
    present, residual_si = misfit.present, misfit.residual_si
    rms = {
        name: float(np.sqrt(np.mean(residual_si[:, s][present[:, s]] ** 2)))
        for s, name in enumerate(layout.signals)
        if present[:, s].any()
    }
    # −2 log-likelihood of the Gaussian noise model (up to N log 2π) over every sample of
    # the traces (each left out beside a jump at the χ² it expects, 1, as the fit ranks
    # its starts), and how many values were estimated: the fitted ones and every
    # estimated noise.
    minus_two_log_likelihood = (
        misfit.chi2 + misfit.left_out
        + float(log_likelihood_term(misfit.sigma, np.asarray(data.present)))
    )  # fmt: skip
    estimated = len(theta) + int(np.sum(present.any(-1) & ~np.asarray(data.sigma_given)))
    return CalibrationResult(
        fitted=fitted,
        values={label: float(theta[i]) for i, label in enumerate(layout.labels)},
        correlation=uncertainty.correlation,
        covariance=uncertainty.covariance,
        unidentifiable=uncertainty.unidentifiable,
        unresolved=unresolved,
        chi2=misfit.chi2,
        reduced_chi2=misfit.reduced_chi2,
        aic=minus_two_log_likelihood + 2 * estimated,
        bic=minus_two_log_likelihood + math.log(misfit.samples) * estimated,
        samples=misfit.samples,
        dof=misfit.dof,
        rms=rms,
        sigma=[e["sigma"] for e in fits.summaries],
        converged=converged,
        starts=starts,
        starts_at_best=at_best,
        steps=steps,
        experiments=fits.summaries,
        validation=[],
        times=fits.times,
        measured=fits.measured,
        model=fits.model,
        codes=misfit.codes,
        seconds=0.0,
        bounds={
            label: (float(layout.lower[i]), float(layout.upper[i]))
            for i, label in enumerate(layout.labels)
        },
        design={k: float(v) for k, v in calibration.design.items() if k != "t1"},
        check=fits.check,
        **_structure(calibration),
    )


@dataclasses.dataclass(frozen=True)
class _Misfit:
    """The misfit at the fitted values: the normalised residuals `residuals (E, S, n)`,
    which samples are `present (E, S, n)` (off the model's jumps: `jump_samples`), the
    noise `sigma (E, S)` and the residuals in the signals' units `residual_si (E, S,
    n)`, each experiment's status `codes (E,)`;
    the Jacobian of the residuals the fit minimised `jacobian (N, P)` (a robust loss
    down-weights outliers there too), the samples on an event their sampling does not
    resolve `unresolved (E, S, n)` (`unresolved_samples`), the `samples` N, `dof` (N −
    P, at least 1), `chi2` (the robust cost), `reduced_chi2`, and how many samples of
    the traces are `left_out` beside a jump."""

    residuals: np.ndarray
    present: np.ndarray
    sigma: np.ndarray
    residual_si: np.ndarray
    codes: np.ndarray
    jacobian: np.ndarray
    unresolved: np.ndarray
    samples: int
    dof: int
    chi2: float
    reduced_chi2: float
    left_out: int


def _misfit(
    calibration: Calibration, data: CalibrationData, evaluation: Evaluation, P: int
) -> _Misfit:
    """The misfit of `evaluation` (`_Misfit`), `P` values fitted.

    **Raises:** `ParameterError` where no sample lies within the experiments' windows.
    """
    r = np.asarray(evaluation.residuals)
    # Off the jumps in the model's signal, as the fit (`jumps_at`).
    present = np.asarray(data.present) & ~np.asarray(jumps_at(evaluation, data))
    codes = np.asarray(evaluation.codes)
    robust_r, slope = (
        np.asarray(a)
        for a in jax.jvp(
            lambda x: robust(x, calibration.loss, calibration.f_scale),
            (jnp.asarray(r[present]),),
            (jnp.ones(int(present.sum())),),
        )
    )
    # The Jacobian of the residuals the fit minimised (a robust loss down-weights outliers
    # there too), `(N, P)`.
    J = np.asarray(evaluation.jacobian)[present] * slope[:, None]
    N = J.shape[0]
    if N == 0:
        raise ParameterError("calibration: no usable sample within the experiments' windows")
    dof = max(N - P, 1)
    chi2 = float(np.sum(robust_r**2))
    sigma = np.asarray(data.sigma)
    residual_si = r * sigma[..., None]
    unresolved = unresolved_samples(
        np.asarray(data.times), np.asarray(evaluation.signals), np.asarray(evaluation.rates),
        np.asarray(data.present), sigma,
    ) & present  # fmt: skip
    left_out = int(np.asarray(data.present).sum() - present.sum())
    return _Misfit(r, present, sigma, residual_si, codes, J, unresolved, N, dof, chi2, chi2 / dof,
                   left_out)  # fmt: skip


def unresolved_samples(times, signals, rates, present, sigma) -> np.ndarray:
    """Which samples `(E, S, n)` lie on an event their sampling does not resolve: where
    the model's signal `signals (E, S, n)` moves at its rate `rates (E, S, n)` over the
    sample's spacing (half the span to its neighbours; `times (E, n)`) by more than
    `UNRESOLVED_RATIO` times its step to either present neighbour, plus the signal's
    noise `sigma (E, S)`."""
    unresolved = np.zeros(present.shape, dtype=bool)
    for e, s in np.ndindex(present.shape[:2]):
        (index,) = np.nonzero(present[e, s])
        if index.size < 3:
            continue
        steps = np.abs(np.diff(signals[e, s, index]))
        neighbour = np.maximum(np.r_[steps[0], steps], np.r_[steps, steps[-1]])
        moved = np.abs(rates[e, s, index]) * np.gradient(times[e, index])
        unresolved[e, s, index] = moved > UNRESOLVED_RATIO * neighbour + sigma[e, s]
    return unresolved


@dataclasses.dataclass(frozen=True)
class _Uncertainty:
    """The fitted values' uncertainty: their box coordinates `z (P,)`, `covariance (P,
    P)` and standard errors `sd (P,)` (SI units), `correlation (P, P)` (NaN rows and
    columns for the unidentifiable), which are `identifiable (P,)`, and the combinations
    the data cannot confine, in words (`unidentifiable`)."""

    z: np.ndarray
    covariance: np.ndarray
    sd: np.ndarray
    correlation: np.ndarray
    identifiable: np.ndarray
    unidentifiable: list[str]


@dataclasses.dataclass(frozen=True)
class BoxCovariance:
    """What an information matrix determines, in box coordinates (each bound range [0,
    1]): the `covariance (P, P)`, the directions it cannot confine to the box, in words
    (`unidentifiable`), and which values are `identifiable (P,)` (in none of them, and a
    95 % interval narrower than the box)."""

    covariance: np.ndarray
    identifiable: np.ndarray
    unidentifiable: list[str]


def box_covariance(information: np.ndarray, labels, scale: float = 1.0) -> BoxCovariance:
    """The covariance `scale · H⁻¹` of an information matrix `H (P, P)` in box
    coordinates (`JᵀJ`, or `JᵀJ/σ²` with `scale` 1), and what it leaves undetermined: a
    direction whose 95 % interval is wider than the box, or where `H` is singular to
    rounding, is unconfined, and every value it involves (by `labels`) unidentifiable.
    Shared by the calibration's report and the test plan's prediction."""
    H = 0.5 * (information + information.T)
    P = H.shape[0]
    eigenvalues, vectors = np.linalg.eigh(H)
    largest = max(float(eigenvalues[-1]), 1e-300)
    flat = [
        j
        for j, lam in enumerate(eigenvalues)
        if lam <= 1e-12 * largest or 1.96 * math.sqrt(scale / max(lam, 1e-300)) > 0.5
    ]
    covariance = scale * np.linalg.pinv(H, rcond=1e-12, hermitian=True)
    sd = np.sqrt(np.maximum(np.diag(covariance), 0.0))
    involved = set()
    unidentifiable = []
    for j in flat:
        v = vectors[:, j]
        names = [i for i in np.argsort(-np.abs(v)) if abs(v[i]) >= 0.2 * np.max(np.abs(v))]
        involved.update(names)
        terms = " ".join(
            f"{'−' if v[i] < 0 else '+'} {abs(v[i]):.2f}·{labels[i]}" for i in names
        ).lstrip("+ ")
        unidentifiable.append(
            f"{', '.join(labels[i] for i in names)}: {terms} (box coordinates) is not "
            "determined by the data"
        )
    identifiable = np.asarray(
        [i not in involved and 2 * 1.96 * sd[i] < 1.0 for i in range(P)], dtype=bool
    )
    return BoxCovariance(covariance, identifiable, unidentifiable)


def _uncertainty(layout: Layout, theta: np.ndarray, misfit: _Misfit) -> _Uncertainty:
    """The Gauss–Newton covariance of `theta (P,)` scaled by the reduced χ², from the
    samples their sampling resolves (`unresolved_samples`), worked in box coordinates
    (each bound range [0, 1]; logarithmic where the space is), with what the data leave
    undetermined (`box_covariance`)."""
    P = len(theta)
    space = layout.space
    z = space.z(theta)
    dtheta_dz = np.asarray(jax.jvp(space.theta, (jnp.asarray(z),), (jnp.ones(P),))[1])
    resolved = ~misfit.unresolved[misfit.present]
    Jz = misfit.jacobian[resolved] * dtheta_dz
    box = box_covariance(Jz.T @ Jz, layout.labels, misfit.reduced_chi2)
    identifiable = box.identifiable
    covariance = box.covariance * np.outer(dtheta_dz, dtheta_dz)
    sd = np.sqrt(np.maximum(np.diag(covariance), 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        correlation = covariance / np.outer(sd, sd)
    correlation[~identifiable, :] = np.nan
    correlation[:, ~identifiable] = np.nan
    return _Uncertainty(z, covariance, sd, correlation, identifiable, box.unidentifiable)


@dataclasses.dataclass(frozen=True)
class _ExperimentFits:
    """Every fitted experiment at the fitted values: its `summaries` (name, trace,
    samples, skipped, RMS, noise and status), and per experiment the sample times
    `(n,)` and the measured and model signals by name (`times`, `measured`, `model`);
    the model `check` of them all."""

    summaries: list[dict[str, Any]]
    times: list[np.ndarray]
    measured: list[dict[str, np.ndarray]]
    model: list[dict[str, np.ndarray]]
    check: ModelCheck


def _experiment_fits(
    calibration: Calibration,
    layout: Layout,
    data: CalibrationData,
    evaluation: Evaluation,
    misfit: _Misfit,
) -> _ExperimentFits:
    """Each fitted experiment's summary and signals (`experiment_summary`, with its noise
    and status), and the test of the residuals against each trace's own noise
    (`check_residuals`)."""
    sigma = misfit.sigma
    experiments, times, measured, model, counted = [], [], [], [], []
    signals_model = np.asarray(evaluation.signals)
    for e, experiment in enumerate(calibration.experiments):
        fit = experiment_summary(experiment, e, layout, np.asarray(data.present),
                                 misfit.residual_si, np.asarray(data.measured), signals_model,
                                 misfit.present)  # fmt: skip
        summary = fit.summary
        summary["sigma"] = {
            name: float(sigma[e, s])
            for s, name in enumerate(layout.signals)
            if name in experiment.trace.signals
        }
        summary["status"] = int(misfit.codes[e])
        experiments.append(summary)
        times.append(fit.times)
        measured.append(fit.measured)
        model.append(fit.model)
        counted.append(fit.counted)
    check = check_residuals(
        [(x.label, t, m, fit, x.sigma)
         for x, t, m, fit in zip(calibration.experiments, times, counted, model, strict=True)],
        {name: SIGNALS[name][0] for name in layout.signals},
        robust=calibration.loss != "linear",
    )  # fmt: skip
    return _ExperimentFits(experiments, times, measured, model, check)


def _fitted(
    layout: Layout, theta: np.ndarray, uncertainty: _Uncertainty, explains: bool
) -> dict[str, Fitted]:
    """Each fitted value by label (`Fitted`): its standard error and 95 % interval where
    the data determine it (cut at a bound it ended on, `AT_BOUND`), withheld where the
    model does not `explain` the traces."""
    z, sd, identifiable = uncertainty.z, uncertainty.sd, uncertainty.identifiable
    fitted = {}
    for i, label in enumerate(layout.labels):
        zi = float(z[i])
        side = "lower" if zi <= AT_BOUND else "upper" if zi >= 1.0 - AT_BOUND else None
        if not explains:  # an interval would assume the model the data refute
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
    return fitted


def _structure(calibration: Calibration) -> dict[str, Any]:
    """The model a calibration fits (`CalibrationResult.structure`), from its first
    experiment (they share one structure), and the values that experiment took from the
    defaults (those that act: not the contact's without an absorber)."""
    experiment = calibration.experiments[0]
    values = design_of(calibration, experiment)
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
        "hardware": sorted(groups - {*PAPER_GROUPS, "load"}),  # (the load: above)
    }
    defaults = {k: v for k, v in values.items() if k not in given}
    return {"structure": structure, "defaults": defaults}


@dataclasses.dataclass(frozen=True)
class ExperimentFit:
    """One experiment at the fitted values: its `summary` (name, trace, samples,
    skipped samples, samples left out beside a jump and RMS residual per signal), its
    sample times `times (n,)` (s), its `measured` (NaN where absent) and `model`
    signals by name, `(n,)` each, and the measured ones the fit counts, `counted` (NaN
    also beside a jump in the model's signal: what the model check tests)."""

    summary: dict[str, Any]
    times: np.ndarray
    measured: dict[str, np.ndarray]
    model: dict[str, np.ndarray]
    counted: dict[str, np.ndarray]


def experiment_summary(
    experiment: Experiment,
    e: int,
    layout: Layout,
    present: np.ndarray,
    residual_si: np.ndarray,
    measured: np.ndarray,
    model: np.ndarray,
    counted: np.ndarray,
) -> ExperimentFit:
    """Experiment `e` of the arrays `present` (the trace's samples), `residual_si`
    (signal units), `measured` and `model`, and `counted` (the samples the fit counts:
    those present off the model's jumps, `jump_samples`), each `(E, S, n)`, by the
    signals its trace measures (`ExperimentFit`)."""
    trace = experiment.fitted_trace
    n = len(trace.t)
    signals = [s for s in layout.signals if s in trace.signals]
    rows = {name: layout.signals.index(name) for name in signals}
    summary = {
        "name": experiment.label,
        "trace": trace.source,
        "samples": int(sum(counted[e, s].sum() for s in rows.values())),
        "skipped": dict(trace.skipped),
        "left_out": int(sum((present[e, s] & ~counted[e, s]).sum() for s in rows.values())),
        "rms": {
            name: float(np.sqrt(np.mean(residual_si[e, s][counted[e, s]] ** 2)))
            for name, s in rows.items()
            if counted[e, s].any()
        },
    }

    def where(mask):
        return {name: np.where(mask[e, s, :n], measured[e, s, :n], np.nan)
                for name, s in rows.items()}  # fmt: skip

    model_signals = {name: model[e, s, :n] for name, s in rows.items()}
    return ExperimentFit(summary, trace.t, where(present), model_signals, where(counted))
