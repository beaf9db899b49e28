"""`recoil-jax explore`: serve the design explorer (`_explore`) in the browser."""

from __future__ import annotations

from .._files.inputs import parse_assignments
from .._files.options import Commands

__all__ = ["add_command", "run_explore"]


def run_explore(args) -> int:
    """Run `recoil-jax explore` with the parsed `args`; its exit status."""
    from .._explore.explorer import main_explore

    return main_explore(args, parse_assignments(args.assignments))


def add_command(commands: Commands) -> None:
    """`recoil-jax explore`'s arguments."""
    explore = commands.add(
        "explore",
        run_explore,
        help="a live design explorer in the browser",
        description="Serve the design explorer: a number field for every parameter, "
        "the displacements and forces against time, the peaks against their limits and "
        "the gradient of the peak anchoring force, updated as you type. Optional "
        "name=value items set the starting design.",
    )
    explore.add_argument("assignments", nargs="*", metavar="name=value")
    explore.add_argument("--port", type=int, default=5006, help="port (default 5006)")
    explore.add_argument("--address", default="localhost", help="address (default localhost)")
    explore.add_argument("--no-browser", action="store_true", help="do not open a browser tab")
    explore.add_argument(
        "--trace", metavar="CSV", help="a measured trace to show over the histories (points)"
    )
