"""`recoil-jax plan`: a plan file (`_studies/plan_file`) run through `rj.plan_firings`;
result.json, summary.txt, the figures and a calibration.toml skeleton written, and with
`--check N` the simulated tests of the plan and of the hand-drawn ones."""

from __future__ import annotations

import math

import recoil_jax as rj
import recoil_jax.extend as rjx

from .._files.calibration_file import calibration_skeleton
from .._files.inputs import (
    check_not_input,
    design_warnings,
    output_folder,
    results_folder,
    values_taken,
    warn,
)
from .._files.json_writer import dumps as json_dumps, write as write_json, write_text
from .._files.options import Commands, add_json
from .._studies.plan_file import load_plan

__all__ = ["add_command", "ratio_range", "run_plan", "summary"]

_NAMES = {
    "plan": "planned",
    "baseline": "spread evenly",
    "first_candidate": "all at the first candidate",
}


def _firing_line(i: int, condition: dict, signals) -> str:
    values = ", ".join(f"{k} = {v:g}" for k, v in condition.items())
    return f"    firing {i}: {values}; record {', '.join(signals)}"


def _interval(report: rjx.PlanReport, name: str, guess: float) -> str:
    """`1.56 N*s/m (0.0098 %; 95 %: 15996.9 to 16003.1)`: the standard error in its unit,
    as a share of the guess, and the 95 % interval."""
    interval, stderr = report.ci95[name], report.stderr[name]
    if interval is None or stderr is None:
        return "not determined"
    unit = rj.PARAMETERS[name].unit if name in rj.PARAMETERS else "s"
    unit = f" {unit}" if unit else ""  # none for a coefficient
    share = f"{100 * stderr / abs(guess):.2g} %; " if guess else ""
    return f"{stderr:.4g}{unit} ({share}95 %: {interval[0]:.6g} to {interval[1]:.6g})"


def ratio_range(fits: int, level: float = 0.99) -> tuple[float, float]:
    """The range that `level` of the ratios of `fits` fits' spread (their sample standard
    deviation) to the true standard error fall in, for Gaussian fits:
    `sqrt(χ²_{n−1} / (n − 1))` at its two tails."""
    import scipy.stats  # when used: it takes 0.4 s to import

    dof = max(fits - 1, 1)
    tail = (1 - level) / 2
    low, high = scipy.stats.chi2.ppf([tail, 1 - tail], dof)
    return math.sqrt(low / dof), math.sqrt(high / dof)


def summary(plan: rj.FiringPlan, checks: dict | None = None) -> str:
    """The plan, each parameter's predicted standard error and 95 % interval beside the
    hand-drawn plans', what each leaves undetermined, and the checks."""
    problem = plan.problem
    criterion = problem.criterion
    lines = [f"plan: {problem.firings} firings of {len(plan.conditions)} candidates, "
             f"criterion {criterion}{f' over {problem.robust} draws' if problem.robust else ''}"
             f", {plan.seconds:.1f} s"]  # fmt: skip
    for i, (c, signals) in enumerate(plan.plan.firings, 1):
        lines.append(_firing_line(i, plan.conditions[c], signals))
    for key in ("baseline", "first_candidate"):  # the hand-drawn plans, compared below
        firings = "; ".join(
            ", ".join(f"{k} {v:g}" for k, v in plan.conditions[c].items())
            + f" ({', '.join(signals)})"
            for c, signals in getattr(plan, key).firings
        )
        lines.append(f"  {_NAMES[key]}: {firings}")
    lines.append("  criterion (higher is better): " + ", ".join(
        f"{label} {_value(getattr(plan, key).criterion)}" for key, label in _NAMES.items()
    ) + f", greedy selection {_value(plan.greedy)}")  # fmt: skip
    lines.append("  predicted standard error (its share of the guess; 95 % interval):")
    width = max(len(n) for n in problem.fit)
    guess = problem.guess
    for name in problem.fit:
        lines.append(f"    {name:<{width}}  " + "; ".join(
            f"{label} {_interval(getattr(plan, key), name, guess[name])}"
            for key, label in _NAMES.items()
        ))  # fmt: skip
    for key, label in _NAMES.items():
        for text in getattr(plan, key).undetermined:
            lines.append(f"  {label}: {text}")
    if checks:
        lines.append("  check (spread of fitted values / predicted standard error):")
        for key, check in checks.items():
            ratios = ", ".join(
                f"{n} {'undetermined' if r is None else f'{r:.2f}'}" for n, r in check.ratio.items()
            )
            low, high = ratio_range(check.converged)
            lines.append(f"    {_NAMES[key]}: {check.converged} of {check.tests} fits "
                         f"converged; {ratios} (for {check.converged} fits, 99 % of ratios "
                         f"fall in {low:.2f}-{high:.2f} where the prediction holds)")  # fmt: skip
    return "\n".join(lines)


def _value(value: float) -> str:
    return f"{value:.4g}" if math.isfinite(value) else "undetermined"


def run_plan(args) -> int:
    """The `plan` command."""
    if args.check is not None and not 2 <= args.check <= 10_000:
        raise rj.ParameterError(f"--check {args.check}: valid 2 to 10,000 simulated tests")
    if args.seed < 0:
        raise rj.ParameterError(f"--seed {args.seed}: valid an integer >= 0")
    problem, description = load_plan(args.source)
    if args.check:  # its traces, before the plan's work (every signal of every firing)
        rjx.check_tests_memory(problem, args.check)
    warn(design_warnings(values_taken(problem.design, problem.fit, problem.candidates)))
    out = output_folder(results_folder(args.out, "plan", args.source))
    check_not_input(out, ("result.json", "summary.txt", "calibration.toml"), args.source)
    plan = rj.plan_firings(problem, progress=True)
    checks = None
    if args.check:
        checks = rjx.check_plan(
            plan, args.check, seed=args.seed, which=("plan", "baseline"), progress=True
        )
    report = {"source": str(args.source), "description": description, **plan.to_json()}
    if checks:
        report["check"] = {key: check.to_json() for key, check in checks.items()}
    from .._figures.planning import planning_figures

    report["figures"] = [str(p) for p in planning_figures(plan, out)]
    write_text(out / "calibration.toml", calibration_skeleton(plan, description))
    text = summary(plan, checks)
    write_text(out / "summary.txt", text + "\n")
    write_json(out / "result.json", report)
    if args.json:
        print(json_dumps(report))
    else:
        print(text)
        print(f"  wrote {out / 'result.json'}, summary.txt, calibration.toml and "
              f"{len(report['figures'])} figures")  # fmt: skip
    return 0


def add_command(commands: Commands) -> None:
    """`recoil-jax plan`'s arguments."""
    plan = commands.add(
        "plan",
        run_plan,
        help="plan a firing test: which firings and signals determine the model best",
        description="Choose the firings (candidate conditions, repeats allowed) and each "
        "firing's signals, within a budget, that best determine the parameters a test "
        "must pin down (a TOML file: [design], [fit], [candidates], [signals], [sampling], "
        "[budget], [criterion]; or a shipped example's name: envelope_friction). The "
        "Fisher information comes from the exact sensitivities of the signals; the choice "
        "is Fedorov's exchange. Writes result.json (the plan, each parameter's predicted "
        "standard error and 95% interval, and the same for the firings spread evenly and "
        "for every round at the first candidate), summary.txt, intervals.png, "
        "information.png and a calibration.toml for the traces. Exit 0 done, 1 a solve "
        "failed, 2 bad input.",
    )
    plan.add_argument("source", help="a plan file (.toml) or a shipped example's name")
    plan.add_argument("--out", help="output folder (default results/plan/<example or file name>)")
    add_json(plan)
    plan.add_argument(
        "--check",
        type=int,
        default=None,
        metavar="N",
        help="simulate N noisy tests of the plan and of the evenly spread one at a truth "
        "drawn from the middle half of the [fit] box, fit each with the calibration and "
        "compare the spread of the fitted values with the predicted standard errors "
        "(about 1 s a test on 2 cores for the shipped example)",
    )
    plan.add_argument("--seed", type=int, default=0, help="the check's truth and noise (default 0)")
