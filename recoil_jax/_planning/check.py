"""The check that a plan's prediction holds (`check_plan`): simulated noisy tests of a
plan at a truth drawn from the box, each fitted by the calibration (`fit_many`, one
batched program), and the spread of the fitted values against the standard errors the
information predicts at that truth."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import jax.numpy as jnp
import numpy as np

from .._calibration.calibrate import fit_many
from .._calibration.spec import Calibration
from .._calibration.traces import Experiment, Trace
from .._model.derivatives import SIGNAL_ALIASES
from .._model.params import params_from_values, values_of, with_values
from .._model.reference import reference_history
from .._model.settings import Smoothing
from .._model.solve import simulate
from .._sweeps.memory import check_memory
from .information import candidate_information
from .plan import FiringPlan, PlanReport, plan_space, predicted_stderr, progress_logger

__all__ = ["PlanCheck", "check_plan", "check_tests_memory", "plan_calibration"]

#: `History`'s field of each signal.
_FIELDS = {signal: field for field, signal in SIGNAL_ALIASES.items()}


@dataclasses.dataclass(frozen=True)
class PlanCheck:
    """One plan's check: the `truth` (fitted name → value), how many `tests` were
    simulated and how many fits `converged`; per fitted name its `predicted` standard
    error at the truth (None where the plan leaves it undetermined), the `spread` (the
    standard deviation of the converged fits), their `ratio` and the fits' `bias` (mean
    minus truth); `fitted`, each converged fit's values by name `(n,)` (not in
    `to_json`)."""

    truth: dict[str, float]
    tests: int
    converged: int
    predicted: dict[str, float | None]
    spread: dict[str, float]
    ratio: dict[str, float | None]
    bias: dict[str, float]
    seconds: float
    fitted: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {k: v for k, v in dataclasses.asdict(self).items() if k != "fitted"}


def plan_calibration(
    plan: FiringPlan,
    report: PlanReport,
    traces: Sequence[Trace],
    start: Mapping[str, float] | None = None,
) -> Calibration:
    """The calibration of a plan's firings (`report`) from their `traces` (one per
    firing, in order): each experiment with its condition values, the sampled duration
    as `t1` and its signals' noise; the known values and bounds of the plan's problem,
    starting from `start` (default the guess), at the model's widths."""
    problem = plan.problem
    guess = problem.guess
    experiments = [
        Experiment(
            trace=trace,
            design={**plan.conditions[c], "t1": problem.duration},
            sigma={s: problem.signals[s].sigma for s in signals},
            name=f"firing {i}",
        )
        for i, ((c, signals), trace) in enumerate(zip(report.firings, traces, strict=True), 1)
    ]
    known = {k: v for k, v in guess.items() if k not in problem.fit}
    start = {n: guess[n] for n in problem.fit} if start is None else dict(start)
    return Calibration(
        experiments, dict(problem.fit), start=start, design=known,
        options=problem.options,
    )  # fmt: skip


def _SILENT(line: str) -> None:
    """No progress."""


class _LineStream:
    """A stream whose lines go to a progress logger (`fit_many`'s progress line)."""

    def __init__(self, log: Callable[[str], Any]):
        self.log = log

    def write(self, text: str) -> None:
        if text.strip():
            self.log(text.strip())

    def flush(self) -> None:
        pass


def check_tests_memory(problem, tests: int, report: PlanReport | None = None) -> None:
    """Refuse (`ParameterError`) `tests` simulated tests whose noisy traces, held for
    their batched fit with its copies (4 values a sample), would take over half the free
    memory: the `report`'s firings and signals, or before a plan is made, `problem`'s
    firings each recording every signal (the most a plan can hold)."""
    if report is None:
        signals = problem.firings * len(problem.signals)
    else:
        signals = sum(len(recorded) for _, recorded in report.firings)
    check_memory(
        tests, 8 * 4 * signals * len(problem.times), "a check", "give fewer simulated tests",
        unit="simulated tests",
    )  # fmt: skip


def check_plan(
    plan: FiringPlan,
    tests: int = 100,
    seed: int = 0,
    which: Sequence[str] = ("plan", "baseline", "first_candidate"),
    progress: bool | Callable[[str], Any] = False,
    truth: Mapping[str, float] | None = None,
    reference: bool = False,
) -> dict[str, PlanCheck]:
    """Simulate `tests` noisy firing tests of each plan in `which` (`FiringPlan`'s
    `plan`, `baseline`, `first_candidate`) at one truth drawn from the central half of
    the `fit` box (`seed`), fit each with the calibration, and compare the spread of the
    fitted values with the standard errors predicted at the truth. The fits start at
    the truth: the check measures the spread the noise causes, which the prediction
    describes, not whether a fit from afar finds the optimum (the calibration's
    starts).

    `truth`: the fitted values to simulate at instead (by name); `reference`: draw the
    traces with the independent hard-switch solver (`reference_history`) rather than
    the model itself.

    **Returns:** `{name: PlanCheck}`.
    """
    log = progress_logger(progress) if progress else _SILENT
    problem = plan.problem
    check_tests_memory(problem, tests, plan.plan)
    fit = tuple(problem.fit)
    space = plan_space(problem)
    rng = np.random.default_rng(seed)
    z = rng.uniform(0.25, 0.75, size=len(fit))
    if truth is None:
        theta = np.asarray(space.theta(jnp.asarray(z)))
    else:
        theta = np.asarray([float(truth[name]) for name in fit])
    truth_values = dict(zip(fit, map(float, theta), strict=True))
    params = params_from_values(problem.guess | truth_values)
    # The information at the truth: the predicted errors the spread should match.
    columns = {n: np.asarray([c[n] for c in plan.conditions]) for n in problem.candidates}
    information, _ = candidate_information(
        params, fit, space, columns, plan.signals,
        [problem.signals[s].sigma for s in plan.signals], problem.times,
        Smoothing(), problem.options, theta[None],
    )  # fmt: skip
    results = {}
    for name in which:
        clock = time.perf_counter()
        report: PlanReport = getattr(plan, name)
        index = {s: i for i, s in enumerate(plan.signals)}
        matrix = sum(information[0, c, [index[s] for s in signals]].sum(axis=0)
                     for c, signals in report.firings)  # fmt: skip
        predicted, _ = predicted_stderr(matrix, fit, space, theta)
        clean = [_signals_at(params, plan.conditions[c], signals, problem, reference)
                 for c, signals in report.firings]  # fmt: skip
        traces = [Trace.of(problem.times, source=f"firing {i}", **values)
                  for i, values in enumerate(clean, 1)]  # fmt: skip
        calibration = plan_calibration(plan, report, traces, start=truth_values)
        measured = [
            [
                {s: v + rng.normal(size=v.shape) * problem.signals[s].sigma for s, v in c.items()}
                for c in clean
            ]
            for _ in range(tests)
        ]
        log(f"check: {tests} simulated tests of the {name.replace('_', ' ')}, fitted in one batch")
        # From the truth, at the calibration's widths: the spread the noise causes, not the
        # way from a far start (a continuation's wide first stage would leave the truth).
        rows = fit_many(calibration, measured, continuation=None, progress=log is not _SILENT,
                        stream=_LineStream(log))  # fmt: skip
        ok = [r for r in rows if r["converged"]]
        spread, bias, ratio, fitted = _spread(ok, fit, theta, predicted)
        seconds = time.perf_counter() - clock
        log(f"check: {name.replace('_', ' ')}: {len(ok)} of {tests} fits converged, "
            f"{seconds:.1f} s")  # fmt: skip
        results[name] = PlanCheck(truth_values, tests, len(ok), predicted, spread, ratio, bias,
                                  seconds, fitted)  # fmt: skip
    return results


def _spread(ok: list[dict], fit: tuple[str, ...], theta, predicted: dict):
    """`(spread, bias, ratio, fitted)` by fitted name over the converged fits `ok`: the
    values' standard deviation, their mean's offset from the truth `theta`, the spread
    over the `predicted` standard error (None without one), and the values."""
    spread, bias, ratio, fitted = {}, {}, {}, {}
    for j, p in enumerate(fit):
        values = fitted[p] = np.asarray([r[p] for r in ok])
        spread[p] = float(np.std(values, ddof=1)) if len(values) > 1 else float("nan")
        bias[p] = float(np.mean(values) - theta[j]) if len(values) else float("nan")
        ratio[p] = None if predicted[p] is None else spread[p] / predicted[p]
    return spread, bias, ratio, fitted


def _signals_at(params, condition, signals, problem, reference) -> dict[str, np.ndarray]:
    """The signals of one firing at `condition`, without noise, at the sample times (by
    the model at the calibration's widths, which fit them, or by the `reference` solver)."""
    if reference:
        values = (
            problem.guess
            | dict(zip(problem.fit, values_of(params, tuple(problem.fit)).tolist(), strict=True))
            | condition
        )
        history = reference_history(values, problem.times)
        return {s: np.asarray(history[s]) for s in signals}
    p = with_values(params, tuple(condition), jnp.asarray(list(condition.values())))
    # To the last sample, as the calibration solves it: not the model's default 10 s.
    options = dataclasses.replace(problem.options, t1=float(problem.times[-1]))
    history = simulate(p, Smoothing(), options, ts=jnp.asarray(problem.times))
    return {s: np.asarray(getattr(history, str(_FIELDS.get(s) or s))) for s in signals}
