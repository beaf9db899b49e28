"""The one look of every figure (matplotlib's Agg backend, set by this folder: works
without a display), and
what the figure modules share: saving, notes."""

from __future__ import annotations

import functools
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

import recoil_jax.extend as rjx

__all__ = ["STYLE", "no_feasible_note", "save", "styled"]


#: One look for every figure the command line writes (reproduce, sweep, optimise,
#: benchmarks): light grid, no top and right frame, legible sizes. Applied per figure
#: (`styled`), so a notebook that imports these keeps its own defaults.
STYLE = {
    "axes.grid": True,
    "grid.alpha": 0.3,
    "axes.spines.top": False,
    "axes.spines.right": False,
    "axes.titlesize": 11,
    "axes.labelsize": 10,
    "legend.fontsize": 9,
    "legend.framealpha": 0.8,
}


def styled(plot):
    """`plot`, drawn in the one look (`STYLE`)."""

    @functools.wraps(plot)
    def styled(*args, **kwargs):
        with plt.style.context(STYLE):
            return plot(*args, **kwargs)

    return styled


def no_feasible_note(ax) -> None:
    """Says on a convergence plot that no evaluated design met every limit."""
    ax.text(
        0.5, 0.5, "no design met every limit\n(result.json: the closest, and what it misses)",
        transform=ax.transAxes, ha="center", va="center", color="C3", fontsize=11,
    )  # fmt: skip


def save(fig, path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:  # whole or not at all: a full disk leaves no empty figure
        with rjx.written(path) as temporary:
            fig.savefig(temporary, dpi=110, format=path.suffix.lstrip(".") or "png")
    finally:
        plt.close(fig)
    return path
