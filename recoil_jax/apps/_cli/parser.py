"""The `recoil-jax` parser, built from the commands (each adds its own subparser beside
its code, in `COMMANDS`' order), and `main`: parse, run inside the fault boundary, and
remove the folders a failed command made."""

from __future__ import annotations

import argparse
import os
import sys

import recoil_jax as rj

from .._bench import (
    calibration as calibration_bench,
    sensitivity as sensitivity_bench,
    speed as speed_bench,
    store as store_bench,
    tuning as tuning_bench,
)
from .._files.inputs import MADE_FOLDERS, remove_unused_folders
from .._files.options import Commands
from . import (
    calibrate,
    explore,
    optimise,
    plan,
    progress,
    reproduce,
    sensitivity,
    simulate,
    sweep,
)
from .boundary import INTERRUPTED, run_command
from .optimise import INFEASIBLE

#: The commands, in the order `recoil-jax --help` lists them: each module adds its own
#: parser (`add_command`) and holds the code it runs.
COMMANDS = (simulate, sweep, progress, speed_bench, store_bench, optimise, tuning_bench,
            calibrate, sensitivity, plan, calibration_bench, sensitivity_bench, explore,
            reproduce)  # fmt: skip

__all__ = ["COMMANDS", "INFEASIBLE", "INTERRUPTED", "build_parser", "main"]


class _Parser(argparse.ArgumentParser):
    """argparse's parser, whose errors (an unknown option, `--starts x`) are one line like
    every other refusal: `recoil-jax: error: ...`, status 2 (its subcommands' parsers are
    of this class too)."""

    def error(self, message: str):  # pyright: ignore[reportIncompatibleMethodOverride]
        command = self.prog.removeprefix("recoil-jax").strip()
        where = f"{command}: " if command else ""
        self.exit(2, f"recoil-jax: error: {where}{message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="recoil-jax",
        description="Differentiable recoil-system models: gun barrel with an impact absorber.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {rj.__version__}")
    # Every command takes --no-cache.
    common = _Parser(add_help=False)
    common.add_argument(
        "--no-cache",
        action="store_true",
        help="do not keep compiled programs on disk (default: kept in "
        "$RECOIL_JAX_CACHE or ~/.cache/recoil-jax/jax, so a repeated command does not "
        "compile again; RECOIL_JAX_CACHE=off also turns it off; the benchmarks never use "
        "it)",
    )
    commands = Commands(parser.add_subparsers(dest="command", required=True), common)
    for command in COMMANDS:
        command.add_command(commands)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command line with `argv` (default `sys.argv[1:]`); returns the exit code:
    0 done, 1 a solve failed (or the disk, the pipe or a store failed the run), 2 bad
    input, 3 (`optimise`) no design met every limit, 4 (`calibrate`) the fit did not
    converge, 5 (`calibrate`) the model does not explain the traces, 130 interrupted
    (Ctrl-C). An output folder the command made and left
    empty is removed when it does not succeed."""
    rj.use_avx2_codegen()  # before any computation: the flag is read as the backend starts
    parser = build_parser()
    # name=value items may come after the flags (`simulate m=500 --hard t1=2`).
    args, extra = parser.parse_known_args(argv)
    if extra:
        if args.command not in ("simulate", "sweep", "explore", "calibrate") or any(
            item.startswith("-") for item in extra
        ):
            parser.error(f"unrecognized arguments: {' '.join(extra)}")
        args.assignments = list(args.assignments) + extra
    # The benchmarks measure compilation among other things: they never load from disk.
    if not args.no_cache and not args.command.startswith("bench"):
        try:
            rj.enable_compilation_cache()
        except OSError as error:  # RECOIL_JAX_CACHE naming a file, or under /proc
            folder = error.filename or os.environ.get("RECOIL_JAX_CACHE", "")
            print(f"recoil-jax: warning: the compilation cache {folder} cannot be used "
                  f"({error.strerror}); running without it", file=sys.stderr)  # fmt: skip
    MADE_FOLDERS.clear()  # this command's folders only (main may run many times)
    status = 1
    try:
        status = run_command(args)
    finally:
        if status != 0:
            remove_unused_folders()
    return status


if __name__ == "__main__":
    sys.exit(main())
