"""Calibration: fitting the model's parameters to measured firing traces (`calibrate`),
scoring the fit on experiments it did not see (`validate`), and fitting many data sets
of the same experiments at once (`fit_many`).

The fit is weighted least squares over every experiment, signal and sample, solved by
Levenberg–Marquardt on the model's exact forward sensitivities (`least_squares`), from
one start or many (`starts`), each start's fit in one compiled program; its uncertainty
is the Gauss–Newton covariance at the optimum scaled by the reduced χ² (lmfit's
default), with a direction the data cannot confine within the bounds reported by name
instead of an interval (`report`, `docs/calibration.md`), and optionally profile
likelihood intervals (`profiles`). A calibration kept in a store resumes (`campaign`).
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._campaigns.progress import Progress
from .._campaigns.store import CalibrationStore
from .._model.derivatives import SIGNALS
from .campaign import STARTS_PER_CHUNK, open_store, stored_part
from .continuation import DEFAULT_CONTINUATION, Continuation
from .layout import CalibrationData, Layout, estimates_noise, prepare
from .least_squares import (
    FitOutcome,
    FitSettings,
    evaluate_program,
    fit_program,
    jumps_at,
    u_of_z,
)
from .model_check import check_residuals
from .profiles import profile_grid, refit_profiles, with_profiles
from .report import experiment_summary, lane_report
from .result import REACHED, CalibrationResult
from .spec import Calibration, validation_problem
from .starts import start_points
from .traces import Experiment

__all__ = ["DEFAULT_STARTS", "calibrate", "fit_many", "validate"]

#: The starts a calibration fits from unless told: the given start and one Sobol point.
DEFAULT_STARTS = 2
#: Two starts ended a continuation's stage at the same point when their χ² there is
#: within `REACHED` and every value within this of each other, in box coordinates (the
#: bounds 0 and 1): the next stages fit that point once (`_same_points`).
SAME_POINT = 1e-3


def calibrate(
    calibration: Calibration,
    *,
    starts: int | np.ndarray = DEFAULT_STARTS,
    seed: int = 0,
    max_steps: int = 200,
    continuation: Continuation | None = DEFAULT_CONTINUATION,
    profiles: bool = False,
    progress: bool | None = None,
    store: str | os.PathLike | None = None,
) -> CalibrationResult:
    """Fit the parameters `calibration.fit` to its experiments' traces.

    **Arguments:**

    - `calibration`: the `Calibration` (experiments, parameters and bounds, loss).
    - `starts`: how many starts (the given start, then Sobol points in the box), or the
      start points themselves, `(N, P)` values in SI units (in the order of the fitted
      labels, within the bounds); the best kept and the count reaching it reported.
      Default 2: the given start and one Sobol point, so that a best point reached
      from both is known not to be a start's local minimum (`CalibrationResult.verdict`).
    - `continuation`: the smoothing widths the fit starts from (`Continuation`), each
      stage's optimum the next one's start, the last stage at the calibration's own
      widths (`Calibration.smoothing`); None: at those widths only. Only the widths
      whose switch the design has. Where the model check fails at the best point, the
      starts are fitted again through its `fallback` path (the default has one), and
      the best of both is the result (`CalibrationResult.fallback`).
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
    layout = Layout.of(calibration)
    z0 = start_points(layout, starts, seed)
    data = prepare(calibration, calibration.experiments, layout)
    static = FitSettings(layout.wrt, layout.signals, calibration.loss, calibration.f_scale,
                         max_steps, estimates_noise(data))  # fmt: skip
    stages = None if continuation is None else continuation.for_design(data.params, data.smoothing)
    fits = len(z0) * (1 + (0 if stages is None else stages.stages))
    bar = Progress("calibrate", fits + 3, "fits and phases", progress, rates=False)
    bar.update(0, f"fitting from {len(z0)} start{'s' if len(z0) > 1 else ''}")
    # The store (and its writer lock) closed whatever happens.
    with open_store(store, calibration, layout, data, static, z0, profiles, progress,
                    stages, starts=starts, seed=seed) as store_:  # fmt: skip
        return _calibrate(calibration, layout, data, static, z0, profiles, bar, store_, clock,
                          stages)  # fmt: skip


def _fit_starts(
    u0: np.ndarray,
    data: CalibrationData,
    static: FitSettings,
    store: CalibrationStore | None,
    continuation: Continuation | None,
    bar: Progress,
    measured: np.ndarray | None = None,
    chunk: int | None = None,
    fallback: bool = False,
) -> FitOutcome:
    """Every start's fit, from `u0 (N, P)` (the fit's coordinates): at each stage of the
    `continuation` (one Levenberg–Marquardt pass from the last stage's optimum, under the
    noise given or guessed), then at the calibration's own widths (`_fit_one`: its passes).
    Each stage runs `chunk` starts a call of one compiled program, the same for every
    stage (the widths are leaves of `data`): one start a call (lanes of `static.lanes`),
    or with a store one part per `starts_per_chunk` of its plan (the last padded to it),
    each read or committed. Starts that end a stage at one point (`_same_points`) are
    fitted once from it in every later stage, its outcome theirs too (not where each
    start has its own data set). The progress line says each stage's starts as they end.
    `measured (N, E, S, n)`: each start's own data set (`fit_many`; default: the
    calibration's, for every start); `chunk`: the starts a call without a store;
    `fallback`: this is the continuation's fallback path (its parts stored under their
    own names, its fits counted as phases, its progress after the first path's)."""
    if store is not None:
        size = int(store.plan["starts_per_chunk"])
    else:
        size = max(static.lanes, 1) if chunk is None else chunk
    stages = 0 if continuation is None else continuation.stages
    warm = dataclasses.replace(static, estimate_noise=False)

    # Starts that ended a stage at the same point are fitted once from it in the next
    # (`_same_points`), the one's outcome copied to the others: only where every start
    # fits the same data.
    merge = measured is None
    if measured is None:
        measured = np.broadcast_to(np.asarray(data.measured), (len(u0), *data.measured.shape))

    # Each stage: its data (the widths are leaves of it), settings and words.
    plan = [
        (eqx.tree_at(lambda d: d.smoothing, data, continuation.smoothing(data.smoothing, k)),
         warm, continuation.describe(k))
        for k in range(stages)
    ] if continuation is not None else []  # fmt: skip
    plan.append((data, static, "the calibration's widths"))
    u, steps = np.asarray(u0), np.zeros(len(u0), dtype=np.int64)
    outcome: dict[str, np.ndarray] = {}
    first = bar.done if fallback else 0  # the progress line's count where this path starts
    same = np.arange(len(u))  # each start's representative: the start fitted for it
    for stage, (data_, static_, what) in enumerate(plan):
        last = stage == stages
        fitted = np.unique(same)  # the starts this stage fits
        merged = (f" (at {len(fitted)} point{'s' if len(fitted) > 1 else ''}, each fitted "
                  "once)" if len(fitted) < len(u) else "")  # fmt: skip
        words = (f"{'fallback: ' if fallback else ''}stage {stage + 1} of {stages + 1} "
                 f"({what})")  # fmt: skip

        def report(done, part, best, last=last, stage=stage, merged=merged, words=words):
            bar.update(first + stage * len(u0) + done,
                       f"{words}: {done} of {len(u0)} starts{merged}, "
                       f"{int(np.max(part['steps']))} steps, best "
                       f"{'score' if last else 'χ²'} {best:.6g}")  # fmt: skip

        name = "fit:{}" if last else f"stage{stage}:{{}}"
        stage_ = _Stage(data_, static_, last, f"fallback:{name}" if fallback else name, size)
        outcome = _fit_stage(stage_, store, u, measured, same, fallback, report)
        steps = steps + outcome["steps"]
        u = outcome["u"]
        if merge and not last:
            same = _same_points(u, outcome["cost"], same)
    outcome["steps"] = steps
    return FitOutcome(**{k: jnp.asarray(v) for k, v in outcome.items()})


class _Stage(NamedTuple):
    """One stage of `_fit_starts`: its data and settings, whether it is the last (at the
    calibration's own widths), its parts' names (`name.format(first start)`) and the
    starts a part."""

    data: CalibrationData
    static: FitSettings
    last: bool
    name: str
    size: int


def _fit_stage(stage: _Stage, store, u, measured, same, fallback: bool, report) -> dict:
    """One stage's fits of the starts `np.unique(same)` from `u (N, P)` on their data sets
    `measured`, a part of `stage.size` at a time, each read from `store` or committed;
    `report(done, part, best)` after each. Returns the outcome by field, for every
    start (a follower gets its representative's)."""
    fitted = np.unique(same)
    parts, best, done = [], np.inf, 0
    for begin in range(0, len(fitted), stage.size):
        starts = fitted[begin : begin + stage.size]
        represented = int(np.isin(same, starts).sum())
        # A warm-up stage's parts hold no fit, nor does the fallback's.
        fits = represented if stage.last and not fallback else 0

        def compute(u_=np.asarray(u[starts]), m=np.asarray(measured[starts])):
            return _fit_padded(u_, m, stage.data, stage.static, stage.size)

        part = stored_part(store, stage.name.format(begin), fits, compute)
        parts.append(part)
        score = np.asarray(part["score"] if stage.last else part["cost"], dtype=float)
        best = min(best, float(np.min(np.where(np.isfinite(score), score, np.inf))))
        done += represented
        report(done, part, best)
    outcome = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    return {k: v[np.searchsorted(fitted, same)] for k, v in outcome.items()}


def _fit_padded(u, sets, data: CalibrationData, static: FitSettings, size: int) -> dict:
    """The fits of the starts `u` on their data `sets` in one call of the fit program.
    A short last part is padded with its last start: one program for every part (a fit
    costs less than a compilation); the padding's fits are dropped."""

    def pad(a):
        return np.concatenate([a, np.repeat(a[-1:], size - len(a), axis=0)])

    outcome = fit_program(jnp.asarray(pad(u)), jnp.asarray(pad(sets)), data, static)
    return {f.name: getattr(outcome, f.name)[: len(u)] for f in dataclasses.fields(outcome)}


def _same_points(u: np.ndarray, cost: np.ndarray, same: np.ndarray) -> np.ndarray:
    """Each start's representative after a stage, `(N,)`, from `same`, the one it had
    before: a start fitted in the stage follows the first such start whose cost there
    is within `REACHED` of its own and every value within `SAME_POINT` of its own (box
    coordinates), its followers with it. Such starts reached one optimum; the next
    stage from it is deterministic, and fitting it once for each would spend the same
    steps to the same point."""
    z = (np.sin(u) + 1.0) / 2.0
    out, kept = same.copy(), []
    for i in np.unique(same):  # in order: an earlier start is kept before a later one
        j = next((j for j in kept if np.isfinite(cost[i]) and abs(cost[i] - cost[j]) <= REACHED
                  and np.max(np.abs(z[i] - z[j])) <= SAME_POINT), None)  # fmt: skip
        if j is None:
            kept.append(i)
        else:
            out[out == i] = j  # i's own followers with it
    return out


def _calibrate(calibration, layout, data, static, z0, profiles, bar, store_, clock, continuation):
    """`calibrate` once its inputs are checked and its store (if any) open."""
    fitted = bar.total - 3  # the fits' share of the progress line
    outcome = _fit_starts(u_of_z(z0), data, static, store_, continuation, bar)
    report = _best_of(outcome, calibration, layout, data, static, bar, fitted)
    path = None if continuation is None else continuation.fallback
    if path is not None and not report.result.explains:
        # Before saying the model does not explain the traces, the other path: the best
        # of both paths' fits is the result (`Continuation.fallback`).
        added = len(z0) * (1 + path.stages)
        bar.total, fitted = bar.total + added, fitted + added
        bar.update(bar.done, "the model check failed there: the fallback path")
        second = _fit_starts(u_of_z(z0), data, static, store_, path, bar, fallback=True)
        outcome = jax.tree.map(lambda a, b: jnp.concatenate([a, b]), outcome, second)
        report = _best_of(outcome, calibration, layout, data, static, bar, fitted)
    result, best, data = report
    if profiles:
        bar.update(fitted + 1, f"profiles ({len(layout.labels)} values)")
        grid = profile_grid(result, layout)
        u_best = outcome.u[best]
        refits = stored_part(
            store_, "profiles", len(grid.held), lambda: refit_profiles(grid, data, static, u_best)
        )
        result = with_profiles(result, layout, grid, refits)
    bar.update(fitted + 2, "validation")
    validation = [validate(calibration, result, e) for e in calibration.validation]
    bar.update(fitted + 3, "done", final=True)
    stages = {} if continuation is None else continuation.to_json()
    widths = {f.name: getattr(data.smoothing, f.name) for f in dataclasses.fields(data.smoothing)}
    return dataclasses.replace(
        result, validation=validation, continuation=stages, seconds=time.perf_counter() - clock,
        smoothing={n: None if w is None else float(w) for n, w in widths.items()},
        fallback=len(outcome.score) > len(z0),
    )  # fmt: skip


class _Best(NamedTuple):
    """The report at the best of a batch of fits, which fit it is, and the data with
    that fit's noise."""

    result: CalibrationResult
    best: int
    data: CalibrationData


def _best_of(outcome, calibration, layout, data, static, bar, fitted) -> _Best:
    """The report at the best (lowest score) of `outcome`'s fits, with how many reached
    it (within `REACHED`) of all of them."""
    score = np.asarray(outcome.score)
    score = np.where(np.isfinite(score), score, np.inf)
    best = int(np.argmin(score))
    at_best = int(np.sum(score <= score[best] + REACHED))
    bar.update(fitted, f"fitted in {int(outcome.steps[best])} steps; uncertainty")
    data = eqx.tree_at(lambda d: d.sigma, data, outcome.sigma[best])
    result = lane_report(calibration, layout, data, static, outcome, best, starts=len(score),
                         at_best=at_best)  # fmt: skip
    return _Best(result, best, data)


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
    validating = validation_problem(calibration, experiment)
    layout = Layout.of(validating)
    values = []
    for label in layout.labels:
        if label in experiment.design:
            values.append(float(experiment.design[label]))
        elif label in result.values:
            values.append(result.values[label])
        else:
            own = [v for k, v in result.values.items() if k.startswith(label + "[")]
            values.append(float(np.mean(own)))
    data = prepare(validating, validating.experiments, layout)
    sigma = np.array(data.sigma)
    for s, name in enumerate(layout.signals):
        if name in experiment.sigma:
            continue
        fitted = [e[name] for e in result.sigma if name in e]
        if fitted:
            sigma[0, s] = fitted[0]
    data = eqx.tree_at(lambda d: d.sigma, data, jnp.asarray(sigma))
    static = FitSettings(layout.wrt, layout.signals, calibration.loss, calibration.f_scale, 1)
    evaluation = evaluate_program(jnp.asarray(values), data, static)
    r = np.asarray(evaluation.residuals)
    # Off the jumps in the model's signal, as the fit (`jumps_at`).
    counted = np.asarray(data.present) & ~np.asarray(jumps_at(evaluation, data))
    residual_si = r * sigma[..., None]
    fit = experiment_summary(
        experiment,
        0,
        layout,
        np.asarray(data.present),
        residual_si,
        np.asarray(data.measured),
        np.asarray(evaluation.signals),
        counted,
    )
    summary = fit.summary
    summary["reduced_chi2"] = float(np.sum(r[counted] ** 2) / max(int(counted.sum()), 1))
    # Held to its own noise as the fitted traces are (its own `sigma` where given).
    summary["model_check"] = check_residuals(
        [(experiment.label, fit.times, fit.counted, fit.model, experiment.sigma)],
        {name: SIGNALS[name][0] for name in layout.signals},
        robust=calibration.loss != "linear",
    ).to_json()
    summary["status"] = int(np.asarray(evaluation.codes)[0])
    return summary


def fit_many(
    calibration: Calibration,
    measured: Sequence[Sequence[Mapping[str, np.ndarray]]],
    continuation: Continuation | None = DEFAULT_CONTINUATION,
    progress: bool | None = False,
    stream=None,
    chunk: int = STARTS_PER_CHUNK,
) -> list[dict[str, Any]]:
    """Fit many data sets of the same experiments (one compiled program): e.g. noise
    draws of a synthetic test, each from the calibration's start through the
    `continuation`'s stages as `calibrate` fits (its first path: no fallback).
    `measured[b][e]`: the signals of experiment `e` in data set `b`, on that
    experiment's sample times; `progress`: a
    progress line (on `stream`, default stderr) as each `chunk` of sets is fitted (one
    program for every chunk, the last padded). Returns each set's fitted values
    by label with their standard errors (`"<label>.stderr"`; NaN where withheld), a
    `"converged"` flag, whether the model `"explains"` the set, the `"failing"` signals
    (`"x_M in firing.csv"`) and the whole `"check"` (`ModelCheck`)."""
    layout = Layout.of(calibration)
    data = prepare(calibration, calibration.experiments, layout)
    static = FitSettings(layout.wrt, layout.signals, calibration.loss, calibration.f_scale, 200,
                     estimates_noise(data))  # fmt: skip
    batch = np.zeros((len(measured), *data.measured.shape))
    for b, sets in enumerate(measured):
        for e, signals in enumerate(sets):
            for s, name in enumerate(layout.signals):
                if name in signals:
                    values = np.asarray(signals[name], dtype=float)
                    batch[b, e, s, : values.size] = values
    z0 = np.tile(start_points(layout, 1, 0), (len(measured), 1))
    stages = None if continuation is None else continuation.for_design(data.params, data.smoothing)
    fits = len(z0) * (1 + (0 if stages is None else stages.stages))
    bar = Progress("fit_many", fits, "fits", progress, stream=stream, rates=False)
    outcome = _fit_starts(u_of_z(z0), data, static, None, stages, bar, measured=batch,
                          chunk=min(chunk, len(z0)))  # fmt: skip
    rows = []
    for b in range(len(measured)):
        data_b = eqx.tree_at(
            lambda d: (d.measured, d.sigma), data, (jnp.asarray(batch[b]), outcome.sigma[b])
        )
        report = lane_report(calibration, layout, data_b, static, outcome, b, starts=1, at_best=1)
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
