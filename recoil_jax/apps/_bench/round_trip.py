"""`recoil-jax bench-calibration --round-trip`: the firing test's round trip from the
defaults. The shipped plan's firings (`optimise/plans/envelope_friction.toml`, planned
here), their traces drawn by the independent hard-switch solver with the plan's noise at
truths drawn from the box's middle half, and each fitted by `calibrate` as a user runs
it: no option, the plan's guess as its start. Beside it, on the first draws of each
truth, one start and 16 starts without continuation. Figures printed, never asserted
(`docs/calibration.md`).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

import recoil_jax as rj
import recoil_jax.extend as rjx

__all__ = [
    "ROUND_TRIP_PLAN",
    "format_round_trip",
    "plan_file",
    "planned_calibration",
    "round_trip",
    "shipped_plan",
    "truth_of",
]

#: The shipped plan the round trip fires (relative to the repository's root).
ROUND_TRIP_PLAN = Path("optimise/plans/envelope_friction.toml")
#: A fitted value is on the truth when within this many of its standard errors.
WITHIN_STDERR = 3.0
#: The ways of fitting compared: name → `calibrate`'s options.
WAYS = {
    "default": {},
    "1 start, no continuation": {"starts": 1, "continuation": None},
    "16 starts, no continuation": {"starts": 16, "continuation": None},
}


def truth_of(problem, index: int) -> dict[str, float]:
    """Truth `index`: each fitted value uniform over the middle half of its box (seeded)."""
    rng = np.random.default_rng(1000 + index)
    return {n: lo + (hi - lo) * (0.25 + 0.5 * rng.random()) for n, (lo, hi) in problem.fit.items()}


def planned_traces(plan, report, truth: dict[str, float], seed: int) -> list[rjx.Trace]:
    """One trace per planned firing: the reference solver's signals at the plan's rate
    over its duration, at the firing's condition and `truth`, with the plan's noise."""
    problem = plan.problem
    rng = np.random.default_rng(seed)
    ts = np.arange(0.0, problem.duration + 1e-12, 1.0 / problem.rate)
    traces = []
    for c, signals in report.firings:
        design = {**problem.guess, **plan.conditions[c], **truth}
        history = rjx.reference_history(design, ts)
        noisy = {s: history[s] + problem.signals[s].sigma * rng.standard_normal(ts.size)
                 for s in signals}  # fmt: skip
        traces.append(rjx.Trace.of(ts, source=f"firing at {plan.conditions[c]}", **noisy))
    return traces


def plan_file(plan_path) -> Path:
    """`plan_path` (relative to the working directory), or a `ParameterError` where it is
    not a file."""
    path = Path(plan_path)
    if not path.is_file():
        raise rj.ParameterError(
            f"{path}: the shipped plan is not here; run from the repository's root"
        )
    return path


def shipped_plan(plan_path=ROUND_TRIP_PLAN):
    """The plan file at `plan_path` (`plan_file`), loaded and planned:
    `(problem, plan, report)`."""
    from .._studies.plan_file import load_plan

    problem, _ = load_plan(plan_file(plan_path))
    plan = rj.plan_firings(problem)
    return problem, plan, plan.plan


def planned_calibration(plan, report, truth: dict[str, float], seed: int):
    """The calibration of the planned firings' traces at `truth` (`planned_traces`)."""
    return rjx.plan_calibration(plan, report, planned_traces(plan, report, truth, seed))


def _fit(calibration, truth, options) -> dict:
    started = time.perf_counter()
    result = rj.calibrate(calibration, progress=False, **options)
    seconds = time.perf_counter() - started
    apart = {}
    for name, value in truth.items():
        fitted = result.fitted[name]
        stderr = fitted.stderr if fitted.stderr else np.nan
        apart[name] = abs(fitted.value - value) / stderr
    worst = max(apart.values())
    return {
        "seconds": seconds,
        "converged": result.converged,
        "verdict": result.verdict,
        "starts_at_best": result.starts_at_best,
        "fallback": result.fallback,
        "unresolved": len(result.unresolved),
        "within": bool(result.converged and result.explains and worst <= WITHIN_STDERR),
        "apart_stderr": apart,
        "values": dict(result.values),
    }


def round_trip(
    draws: int = 20, truths: int = 2, compare: int = 1, plan_path=ROUND_TRIP_PLAN, log=None
) -> dict:
    """The round trip's figures: per truth and way, each draw's fit (`_fit`)."""
    log = log or (lambda msg: print(msg, file=sys.stderr, flush=True))
    problem, plan, report = shipped_plan(plan_path)
    log(f"round trip: {len(report.firings)} planned firings of {plan_path}")
    rows = []
    for t in range(truths):
        truth = truth_of(problem, t)
        log(f"truth {t}: " + ", ".join(f"{n} {v:.6g}" for n, v in truth.items()))
        for d in range(draws):
            calibration = planned_calibration(plan, report, truth, seed=100 * t + d)
            for way, options in WAYS.items():
                if way != "default" and d >= compare:
                    continue
                fit = _fit(calibration, truth, options)
                rows.append({"truth": t, "draw": d, "way": way, **fit})
                where = "on the truth" if fit["within"] else "OFF the truth"
                worst = max(fit["apart_stderr"].values())
                log(f"  truth {t} draw {d} {way}: {fit['seconds']:.1f} s, {where} (worst "
                    f"{worst:.2f} stderr), {fit['verdict']}"
                    + (", through the fallback path too" if fit["fallback"] else ""))  # fmt: skip
    return {
        "plan": str(plan_path),
        "firings": [plan.conditions[c] | {"signals": list(s)} for c, s in report.firings],
        "truths": [truth_of(problem, t) for t in range(truths)],
        "within_stderr": WITHIN_STDERR,
        "rows": rows,
    }


def format_round_trip(result: dict) -> str:
    """Per way and truth: on the truth in how many draws, and the seconds a fit."""
    lines = [f"round trip of {result['plan']} (reference traces, the plan's noise):"]
    for way in WAYS:
        for t in range(len(result["truths"])):
            rows = [r for r in result["rows"] if r["way"] == way and r["truth"] == t]
            if not rows:
                continue
            seconds = [r["seconds"] for r in rows]
            on = sum(r["within"] for r in rows)
            verdicts = {v: sum(r["verdict"] == v for r in rows) for v in
                        ("explains", "local_minimum", "wrong_model")}  # fmt: skip
            fallbacks = sum(r.get("fallback", False) for r in rows)
            lines.append(
                f"  {way}, truth {t}: on the truth (within {result['within_stderr']:g} "
                f"stderr) in {on} of {len(rows)} draws; {np.median(seconds):.1f} s a fit "
                f"(median; {min(seconds):.1f}-{max(seconds):.1f}); verdicts "
                + ", ".join(f"{k} {v}" for k, v in verdicts.items())
                + f"; the fallback path in {fallbacks}"
            )
    return "\n".join(lines)
