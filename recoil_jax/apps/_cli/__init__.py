"""The `recoil-jax` command line: one module a command, each adding its own subparser
beside its code (`add_command`), the parser that collects them (`parser`), and the fault
boundary every command runs inside (`boundary`). `python -m recoil_jax.apps._cli` runs it.

May import: `_files`, `_figures`, `_studies`, `_explore`, `_bench` (the parser collects
every command, the benchmarks' too)."""

import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # what the lazy loader below provides, for type checkers
    from .boundary import INTERRUPTED as INTERRUPTED
    from .parser import INFEASIBLE as INFEASIBLE, build_parser as build_parser, main as main

__all__ = ["INFEASIBLE", "INTERRUPTED", "build_parser", "main"]

_HOMES = {"INFEASIBLE": ".parser", "build_parser": ".parser", "main": ".parser",
          "INTERRUPTED": ".boundary"}  # fmt: skip


def __getattr__(name: str):
    # Lazy, so that a module of this folder (`boundary`) loads without the whole parser.
    if name in _HOMES:
        return getattr(importlib.import_module(_HOMES[name], __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
