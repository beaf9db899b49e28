"""Applications built on the recoil-jax engine, a folder each: the `recoil-jax` command
line (`_cli`, a module a command), the optimisation studies (`_studies`), the files the
commands read and write (`_files`), every figure (`_figures`), the explorer (`_explore`)
and the benchmarks (`_bench`).

They use the engine only through its public API (`import recoil_jax` and its lower-level
interfaces, `recoil_jax.extend`); the engine never imports them. The one exception is
named in `READS_INTERNALS`, with its reason. Each is loaded on first use, so that
`recoil-jax simulate` does not pay for matplotlib or scipy.
"""

import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # what the lazy loader below provides, for type checkers
    from ._bench.speed import run_bench as run_bench
    from ._bench.tuning import run_tuning_bench as run_tuning_bench
    from ._cli import main as main
    from ._cli.reproduce import reproduce as reproduce
    from ._explore.explorer import explorer as explorer
    from ._figures.designs import (
        plot_convergence as plot_convergence,
        plot_heatmap as plot_heatmap,
    )
    from ._figures.histories import plot_history as plot_history, plot_series as plot_series
    from ._figures.planning import (
        plot_plan_information as plot_plan_information,
        plot_plan_intervals as plot_plan_intervals,
    )
    from ._studies.study import run_study as run_study
    from ._studies.study_file import load_study as load_study, resolve_study as resolve_study

#: Applications that read the engine's private modules, and why: the benchmark's compiled
#: scalar loop takes the loop's step-size rule and the model's contact width from where
#: the engine keeps them, so that it cannot drift from them; the posterior's benchmark
#: gives emcee the posterior's own log density (priors, coordinates, likelihood) and
#: times NUTS's own transitions vmapped, so that neither comparison is of another model.
READS_INTERNALS = {"_bench/anchor.py", "_bench/posterior.py"}

__all__ = [
    "READS_INTERNALS",
    "explorer",
    "load_study",
    "main",
    "plot_convergence",
    "plot_heatmap",
    "plot_history",
    "plot_plan_information",
    "plot_plan_intervals",
    "plot_series",
    "reproduce",
    "resolve_study",
    "run_bench",
    "run_study",
    "run_tuning_bench",
]

_HOMES = {
    "main": "._cli",
    "explorer": "._explore.explorer",
    "load_study": "._studies.study_file",
    "resolve_study": "._studies.study_file",
    "run_study": "._studies.study",
    "run_bench": "._bench.speed",
    "run_tuning_bench": "._bench.tuning",
    "reproduce": "._cli.reproduce",
    "plot_convergence": "._figures.designs",
    "plot_heatmap": "._figures.designs",
    "plot_plan_information": "._figures.planning",
    "plot_plan_intervals": "._figures.planning",
    "plot_history": "._figures.histories",
    "plot_series": "._figures.histories",
}


def __getattr__(name: str):
    if name in _HOMES:
        return getattr(importlib.import_module(_HOMES[name], __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
