"""`recoil-jax optimise`: run an optimisation study (`_studies`) and say how it ended."""

from __future__ import annotations

import sys

from .._files.json_writer import dumps as json_dumps
from .._files.options import Commands, add_cluster, add_json, add_store

__all__ = ["INFEASIBLE", "add_command", "run_optimise"]

#: The exit status of `optimise` when no design met every limit (0 done, 1 a solve
#: failed, 2 bad input).
INFEASIBLE = 3


def run_optimise(args) -> int:
    """Run `recoil-jax optimise` with the parsed `args`; its exit status."""
    from .._studies.study import hazard_lines, run_study, study_summary

    report = run_study(
        args.study,
        args.out,
        progress=True,
        seed=args.seed,
        store=args.store,
        workers=args.workers,
        scheduler=args.scheduler,
    )
    if args.json:
        print(json_dumps(report))
    if not report["feasible"]:
        print(f"recoil-jax: infeasible: {report['message']}", file=sys.stderr)
        for line in hazard_lines(report):  # the closest design's
            print(f"recoil-jax: {line.strip()}", file=sys.stderr)
        return INFEASIBLE
    if not args.json:
        print(study_summary(report))
    return 0


def add_command(commands: Commands) -> None:
    """`recoil-jax optimise`'s arguments."""
    opt = commands.add(
        "optimise",
        run_optimise,
        help="run an optimisation study (optimise/<study>.toml)",
        description='Tune design parameters as the study file says (method "search": '
        "global samples, then a local method with exact gradients: SLSQP, or for a worst "
        "case (several conditions, or a peak over time with a temperature) the minimax by "
        'trust-region linear programming; "adam": optax from many '
        "starts); write result.json, convergence.png, best_history.png (and front/robust "
        "figures). STUDY is a path, or the name of a study shipped in optimise/ (e.g. "
        "paper_gap). Exit status: 0 done, 1 a solve failed, 2 bad input, 3 no design met "
        "every limit (result.json then has feasible: false, best: null and the closest "
        "design with the limits it misses).",
    )
    opt.add_argument("study", help="study file or name, e.g. optimise/paper_gap.toml")
    opt.add_argument("--out", help="output folder (default results/<study name>)")
    add_json(opt, "result.json to stdout")
    opt.add_argument(
        "--seed",
        type=int,
        metavar="N",
        help="seed of the optimiser's samples and starts (default: the study's, else 0)",
    )
    add_store(opt, "commit every evaluation of the optimiser", "study")
    add_cluster(opt, 'the global phase (method "search")')
