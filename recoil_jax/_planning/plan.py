"""Planning a firing test (`plan_firings` → `FiringPlan`): the information of every
candidate firing and signal from the exact sensitivities, the firings and signals chosen
by Fedorov's exchange for the criterion, and what the plan, a plan drawn by hand (the
firings spread evenly over the candidates) and the test most rigs fire (every round at
the first candidate) each predict: standard errors and 95 % intervals, or which values
they leave undetermined, in the calibration's words (`box_covariance`)."""

from __future__ import annotations

import dataclasses
import itertools
import math
import sys
import time
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._calibration.report import BoxCovariance, box_covariance
from .._model.params import values_of
from .._model.status import OK_CODE, SolveError, status_item, status_messages
from .._sweeps.space import SearchSpace, log_coordinates
from .choose import Options, exchange, greedy, options, plan_value
from .information import candidate_information
from .problem import PlanProblem

__all__ = [
    "FiringPlan",
    "PlanReport",
    "plan_firings",
    "plan_space",
    "predicted_stderr",
    "progress_logger",
]


@dataclasses.dataclass(frozen=True)
class PlanReport:
    """What one plan predicts.

    - `firings`: each firing's candidate (an index into `FiringPlan.conditions`) and
      the signals it records (names).
    - `criterion`: the criterion's value (higher better; −inf where the information is
      singular to rounding where the criterion needs it), averaged over the robust
      draws where there are some. A value may be named in `undetermined` (its interval
      wider than the box) with a finite criterion.
    - `stderr`, `ci95`: each fitted parameter's predicted standard error and 95 %
      interval around the guess (SI units), None where it is not determined.
    - `undetermined`: the combinations the plan cannot confine to the box, in words.
    - `information (P, P)`: the plan's information at the guess, in box coordinates.
    """

    firings: tuple[tuple[int, tuple[str, ...]], ...]
    criterion: float
    stderr: dict[str, float | None]
    ci95: dict[str, tuple[float, float] | None]
    undetermined: list[str]
    information: np.ndarray

    def to_json(self, conditions: list[dict[str, float]]) -> dict[str, Any]:
        return {
            "plan": [{**conditions[c], "signals": list(signals)} for c, signals in self.firings],
            "predicted": {
                name: {"stderr": self.stderr[name], "ci95": self.ci95[name]} for name in self.stderr
            },
            "undetermined": self.undetermined,
        }


@dataclasses.dataclass(frozen=True)
class FiringPlan:
    """A planned firing test (`plan_firings`).

    - `problem`: the `PlanProblem`; `conditions`: every candidate's values `(C,)`.
    - `plan`, `baseline` (spread evenly), `first_candidate` (every round at the first
      candidate): each a `PlanReport`.
    - `greedy`: the criterion of greedy selection, for comparison.
    - `information (C, S, P, P)`: each candidate's and signal's information at the
      guess, in box coordinates; `signals`: their names `(S,)`.
    - `truths (R, P)`: the fitted values the information was computed at (the guess,
      then the robust draws); `seconds`: the whole planning's time.
    """

    problem: PlanProblem
    conditions: list[dict[str, float]]
    signals: tuple[str, ...]
    plan: PlanReport
    baseline: PlanReport
    first_candidate: PlanReport
    greedy: float
    information: np.ndarray
    truths: np.ndarray
    seconds: float

    def firing_options(self) -> Options:
        """Every way one firing may be made at the guess (`Options`: a candidate and an
        affordable signal set, with its information `(O, 1, P, P)`)."""
        costs = [self.problem.signals[s].cost for s in self.signals]
        return options(self.information, costs, self.problem.cost)

    def to_json(self) -> dict[str, Any]:
        """`result.json`'s body: `plan`, `predicted`, `undetermined`, `baseline` and
        `first_candidate` (each `{"plan", "predicted", "undetermined"}`), `criterion`
        (its name and each plan's value, and greedy's) and the candidates."""
        name = self.problem.criterion
        plan = self.plan.to_json(self.conditions)
        return {
            **plan,
            "baseline": self.baseline.to_json(self.conditions),
            "first_candidate": self.first_candidate.to_json(self.conditions),
            "criterion": {
                "name": name,
                "meaning": _MEANING.get(name, f"minus the variance of {name} (box coordinates)"),
                "plan": _finite(self.plan.criterion),
                "baseline": _finite(self.baseline.criterion),
                "first_candidate": _finite(self.first_candidate.criterion),
                "greedy": _finite(self.greedy),
                "robust_draws": self.problem.robust,
                "method": "Fedorov exchange from the greedy plan and 7 random ones",
            },
            "candidates": self.conditions,
            "signals": {
                s: {"sigma": self.problem.signals[s].sigma, "cost": self.problem.signals[s].cost}
                for s in self.signals
            },
            "seconds": self.seconds,
        }


_MEANING = {
    "D": "log det of the information (box coordinates): higher is better",
    "A": "minus the sum of the variances (box coordinates): higher is better",
}


def _finite(value: float) -> float | None:
    """A criterion for JSON: None where the plan leaves it undetermined (−inf)."""
    return float(value) if math.isfinite(value) else None


def plan_space(problem: PlanProblem) -> SearchSpace:
    """The `fit` box as the calibration's coordinates: linear between the bounds, or
    logarithmic over three decades and more."""
    lower, upper = (np.asarray([b[i] for b in problem.fit.values()]) for i in (0, 1))
    return SearchSpace(
        jnp.asarray(lower), jnp.asarray(upper), jnp.asarray(log_coordinates(lower, upper))
    )


def plan_firings(problem: PlanProblem, progress: bool | Callable[[str], Any] = False) -> FiringPlan:
    """Plan the firing test `problem`: which firings (repeats allowed) and which signals
    each records, within the budget, for the best criterion.

    The information `JᵀJ/σ²` of every candidate and signal comes from the exact
    sensitivities, all candidates in one program (at the guess, and at `robust` draws
    from the box). The choice is Fedorov's exchange over every (candidate, affordable
    signal set), started from the greedy plan and seven random ones.

    `progress`: True prints each phase to stderr (or a callable takes the lines).

    **Raises:** `SolveError` naming the candidate where a solve fails.
    """
    log = progress_logger(progress)
    clock = time.perf_counter()
    fit = tuple(problem.fit)
    params = problem.params
    space = plan_space(problem)
    conditions = problem.conditions
    signals = tuple(problem.signals)
    guess = np.asarray(values_of(params, fit))
    truths = guess[None]
    if problem.robust:
        rng = np.random.default_rng(problem.seed)
        draws = np.asarray(space.theta(jnp.asarray(rng.uniform(size=(problem.robust, len(fit))))))
        truths = np.concatenate([truths, draws])
    columns = {name: np.asarray([c[name] for c in conditions]) for name in problem.candidates}
    log(f"plan: the information of {len(conditions)} candidate firings × {len(signals)} "
        f"signals × {len(fit)} parameters at {len(truths)} truth(s), {problem.samples:,} "
        "samples a signal")  # fmt: skip
    information, codes = candidate_information(
        params, fit, space, columns, signals,
        [problem.signals[s].sigma for s in signals], problem.times,
        problem.smoothing, problem.options, truths,
    )  # fmt: skip
    _check_solves(codes, conditions, truths, fit)
    log(f"plan: computed in {time.perf_counter() - clock:.1f} s; choosing {problem.firings} "
        "firings by exchange")  # fmt: skip
    costs = [problem.signals[s].cost for s in signals]
    chosen_rows = information[1:] if problem.robust else information[:1]
    opts = options(chosen_rows, costs, problem.cost)
    criterion = _criterion_index(problem)
    found = exchange(opts, problem.firings, criterion)
    by_greedy = greedy(opts, problem.firings, criterion).value

    def report(firings) -> PlanReport:
        return _report(problem, chosen_rows, firings, information[0], space, guess, signals)

    plan = report([(int(opts.candidate[o]), opts.signals[o]) for o in found.chosen])
    baseline = report(_even_spread(problem, signals))
    first = report([(0, _affordable_signals(problem, signals))] * problem.firings)
    seconds = time.perf_counter() - clock
    log(f"plan: done in {seconds:.1f} s")
    return FiringPlan(problem, conditions, signals, plan, baseline, first, by_greedy,
                      information[0], truths, seconds)  # fmt: skip


def progress_logger(progress) -> Callable[[str], Any]:
    """Where progress lines go: a callable as given, True: stderr, False: nowhere."""
    if callable(progress):
        return progress
    if progress:
        return lambda line: print(line, file=sys.stderr, flush=True)
    return lambda line: None


def _check_solves(codes, conditions, truths, fit) -> None:
    failed = np.argwhere(codes != OK_CODE)
    if failed.size:
        r, c = (int(i) for i in failed[0])
        where = ", ".join(f"{k}={v:g}" for k, v in conditions[c].items())
        at = "the guess" if r == 0 else f"robust draw {r} ({_values(fit, truths[r])})"
        (message,) = status_messages(status_item(np.int32(codes[r, c])))
        raise SolveError(
            f"plan: the solve of candidate {where} at {at} failed ({len(failed)} of "
            f"{codes.size} failed): {message}"
        )


def _values(names, values) -> str:
    return ", ".join(f"{n}={v:.4g}" for n, v in zip(names, values, strict=True))


def _criterion_index(problem: PlanProblem) -> str | int:
    c = problem.criterion
    return c if c in ("D", "A") else list(problem.fit).index(c)


def _affordable_signals(problem: PlanProblem, signals) -> tuple[int, ...]:
    """What a person records without the tool: as many signals as the cost allows,
    then the set that spends most of it, then the first in the file's order."""
    costs = [problem.signals[name].cost for name in signals]
    sets = [
        subset
        for size in range(1, len(signals) + 1)
        for subset in itertools.combinations(range(len(signals)), size)
        if problem.cost is None or sum(costs[i] for i in subset) <= problem.cost * (1 + 1e-12)
    ]
    return max(sets, key=lambda subset: (len(subset), sum(costs[i] for i in subset)))


def _even_spread(problem: PlanProblem, signals) -> list[tuple[int, tuple[int, ...]]]:
    """The plan a person draws without the tool: firing `i` of `n` at the value of
    each condition a fraction `i/(n−1)` along its sorted values (nearest, halves up),
    each recording every signal the cost allows."""
    n = problem.firings
    names = list(problem.candidates)
    firings = []
    for i in range(n):
        values = {}
        for name in names:
            ordered = sorted(problem.candidates[name])
            at = 0 if n == 1 else math.floor(i * (len(ordered) - 1) / (n - 1) + 0.5)
            values[name] = ordered[at]
        index = next(c for c, cond in enumerate(problem.conditions) if cond == values)
        firings.append((index, _affordable_signals(problem, signals)))
    return firings


def _report(problem, scored, firings, information, space, guess, signals) -> PlanReport:
    """A plan's prediction at the guess (`information (C, S, P, P)` there), and its
    criterion on the information the choice scored (`scored (R, C, S, P, P)`: the
    guess, or the robust draws)."""
    plan_rows = sum(scored[:, c, list(s)].sum(axis=1) for c, s in firings)
    value = plan_value(np.asarray(plan_rows), _criterion_index(problem))
    matrix = sum(information[c, list(s)].sum(axis=0) for c, s in firings)
    fit = list(problem.fit)
    stderr, box = predicted_stderr(matrix, fit, space, guess)
    # The interval in box coordinates, mapped back: guess ± 1.96 sd where the box is
    # linear, a factor either side where it is logarithmic.
    z = np.asarray(space.z(guess))
    sd_z = np.sqrt(np.maximum(np.diag(box.covariance), 0.0))
    ci95 = {}
    for j, (name, sd) in enumerate(stderr.items()):
        ends = [z.copy(), z.copy()]
        ends[0][j] -= 1.96 * sd_z[j]
        ends[1][j] += 1.96 * sd_z[j]
        lo, hi = (float(np.asarray(space.theta(jnp.asarray(e)))[j]) for e in ends)
        ci95[name] = None if sd is None else (lo, hi)
    named = tuple((c, tuple(signals[i] for i in s)) for c, s in firings)
    return PlanReport(named, value, stderr, ci95, box.unidentifiable, np.asarray(matrix))


def predicted_stderr(
    information, fit, space: SearchSpace, theta
) -> tuple[dict[str, float | None], BoxCovariance]:
    """Each fitted value's standard error (SI units; None where undetermined) from an
    information matrix `(P, P)` in box coordinates at the values `theta (P,)`, with
    what it leaves undetermined (`box_covariance`)."""
    z = jnp.asarray(space.z(np.asarray(theta)))
    dtheta_dz = np.asarray(jax.jvp(space.theta, (z,), (jnp.ones_like(z),))[1])
    box = box_covariance(np.asarray(information), list(fit))
    sd = np.sqrt(np.maximum(np.diag(box.covariance), 0.0)) * np.abs(dtheta_dz)
    return {p: (float(sd[j]) if box.identifiable[j] else None) for j, p in enumerate(fit)}, box
