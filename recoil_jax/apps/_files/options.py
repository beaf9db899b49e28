"""What every command's parser shares: the commands' subparsers (`Commands`: each command
adds its own, beside its code) and the options several take."""

from __future__ import annotations

import argparse
from collections.abc import Callable

import recoil_jax as rj

__all__ = ["Commands", "add_force_table", "add_max_steps"]


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
