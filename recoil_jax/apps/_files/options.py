"""What every command's parser shares: the commands' subparsers (`Commands`: each command
adds its own, beside its code) and the options several take."""

from __future__ import annotations

import argparse
from collections.abc import Callable

import recoil_jax as rj

__all__ = ["Commands", "add_cluster", "add_force_table", "add_json", "add_max_steps", "add_store"]


class Commands:
    """The subparsers of `recoil-jax`: `add` makes one command's parser, taking the options
    every command takes (`common`: `--no-cache`), and runs `run(args)` for it."""

    def __init__(self, subparsers, common: argparse.ArgumentParser):
        self.subparsers = subparsers
        self.common = common

    def add(self, name: str, run: Callable[[argparse.Namespace], int], **kwargs):
        """The parser of the command `name`, which runs `run` (its exit status)."""
        parser = self.subparsers.add_parser(name, parents=[self.common], **kwargs)
        parser.set_defaults(func=run)
        return parser


def add_max_steps(parser: argparse.ArgumentParser) -> None:
    """`--max-steps N`: the most solver steps per design."""
    parser.add_argument(
        "--max-steps",
        type=int,
        default=rj.SolverOptions().max_steps,
        metavar="N",
        help="most solver steps per design (default %(default)s); a solve that needs more "
        "fails with status max_steps",
    )


def add_force_table(parser: argparse.ArgumentParser) -> None:
    """`--force-table FILE.csv`: the breech force of one round, measured."""
    parser.add_argument(
        "--force-table", metavar="FILE.csv", help="breech force of one round (header t_s,F_N)"
    )


def add_json(parser: argparse.ArgumentParser, prints: str = "result.json") -> None:
    """`--json`: print what the command made as JSON (`prints` says what) on stdout."""
    parser.add_argument("--json", action="store_true", help=f"print {prints}")


def add_store(parser: argparse.ArgumentParser, keeps: str, campaign: str) -> None:
    """`--store FILE.sqlite`: keep each finished part (`keeps`) of a `campaign` in an
    SQLite file that the same command resumes from."""
    parser.add_argument(
        "--store",
        metavar="FILE.sqlite",
        help=f"{keeps} to this SQLite file; the same command with the same store resumes a "
        f"stopped {campaign} (docs/campaigns.md)",
    )


def add_cluster(parser: argparse.ArgumentParser, runs: str) -> None:
    """`--workers N` and `--scheduler ADDRESS`: run `runs` on a Dask cluster, local or
    running."""
    parser.add_argument(
        "--workers", type=int, metavar="N",
        help=f"run {runs} on a local Dask cluster of N worker processes",
    )  # fmt: skip
    parser.add_argument(
        "--scheduler", metavar="ADDRESS",
        help=f"run {runs} on the running Dask cluster at ADDRESS (tcp://host:8786)",
    )  # fmt: skip
