"""`recoil-jax progress`: where a campaign stands, read from its store."""

from __future__ import annotations

import json

import recoil_jax as rj

from .._files.options import Commands, add_json

__all__ = ["add_command", "run_progress"]


def run_progress(args) -> int:
    """Run `recoil-jax progress` with the parsed `args`; its exit status."""
    progress = rj.campaign_progress(args.store)
    if args.json:  # unknown figures (NaN) as null
        known = {k: None if v != v else v for k, v in progress._asdict().items()}
        print(json.dumps(known))
    else:
        print(f"{args.store}: {progress.line()}")
    return 0


def add_command(commands: Commands) -> None:
    """`recoil-jax progress`'s arguments."""
    prog = commands.add(
        "progress",
        run_progress,
        help="where a campaign stands, from its store",
        description="Read a store (sweep --store) while its campaign runs or after it "
        "stopped: designs done of the total, runs, the rate of the latest run and the time "
        "left.",
    )
    prog.add_argument("store", metavar="FILE.sqlite", help="the store")
    add_json(prog, "one JSON object")
