"""Figures (matplotlib, Agg backend: works without a display)."""

from __future__ import annotations

import functools
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

import recoil_jax as rj

#: One look for every figure the command line writes (reproduce, sweep, optimise,
#: benchmarks): light grid, no top and right frame, legible sizes. Applied per figure
#: (`_styled`), so a notebook that imports these keeps its own defaults.
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


def _styled(plot):
    @functools.wraps(plot)
    def styled(*args, **kwargs):
        with plt.style.context(STYLE):
            return plot(*args, **kwargs)

    return styled


__all__ = [
    "plot_convergence",
    "plot_heatmap",
    "plot_history",
    "plot_search_convergence",
    "plot_series",
]


@_styled
def plot_history(history: rj.History, path, title: str = "") -> Path:
    """Time histories, stacked: the barrel's and absorber's displacements; the anchoring
    force with each element that carries it (recoil spring, damper, hydraulic buffer,
    gas recuperator); the breech force of each round and the contact force. Elements the
    design does not have are left out. Saved as PNG at `path`."""
    ts = np.asarray(history.ts)
    f = history.forces
    fig, axes = plt.subplots(3, 1, figsize=(9, 9), sharex=True)
    axes[0].plot(ts, 1e3 * np.asarray(history.x_M), label="barrel $x_M$")
    axes[0].plot(ts, 1e3 * np.asarray(history.x_m), label="absorber $x_m$")
    axes[0].set_ylabel("displacement (mm)")
    axes[0].legend(loc="upper right")
    parts = {
        "anchoring $F_{AN}$": history.anchoring_force,
        "spring $k x_M$": f.recoil_spring,
        "damper $c(v)v$": f.recoil_damper,
        "orifice $F_h$": f.buffer,
        "recuperator $F_g$": f.recuperator,
    }
    for i, (label, force) in enumerate(parts.items()):
        if force is not None:
            axes[1].plot(
                ts,
                1e-3 * np.asarray(force),
                label=label,
                lw=2 if i == 0 else 1,
                color="k" if i == 0 else None,
            )
    axes[1].set_ylabel("force into the mounting (kN)")
    axes[1].legend(loc="upper right", fontsize=8)
    if f.breech is not None:
        axes[2].plot(ts, 1e-3 * np.asarray(f.breech), label="breech $F_b$", color="C4")
    axes[2].plot(ts, 1e-3 * np.asarray(history.contact_force), label="contact $F_{ct}$", color="C3")
    axes[2].set_ylabel("force (kN)")
    axes[2].legend(loc="upper right", fontsize=8)
    axes[2].set_xlabel("time (s)")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return _save(fig, path)


@_styled
def plot_series(
    series,
    path,
    *,
    xlabel: str,
    ylabel: str,
    title: str = "",
    xscale: float = 1.0,
    yscale: float = 1.0,
    mark=None,
    ylim=None,
    markers: bool = False,
    minima: str | None = None,
) -> Path:
    """Line plot of labelled `(x, y)` series; `mark` = `(x, y, text)` annotates a point;
    `ylim` = `(low, high)` in the series' units; `markers` draws each point (a front's
    designs); `minima` (a unit, e.g. `"N"`) marks each series' lowest point and gives
    it in the legend, in the series' units."""
    fig, ax = plt.subplots(figsize=(8, 4.5))
    if ylim is not None:
        ax.set_ylim(yscale * ylim[0], yscale * ylim[1])
    for label, (x, y) in series.items():
        x, y = xscale * np.asarray(x, float), yscale * np.asarray(y, float)
        if minima is not None and np.any(np.isfinite(y)):
            i = int(np.nanargmin(y))
            value = y[i] / yscale
            label = f"{label}: min {value:.4g} {minima} at {x[i]:.4g}"
        (line,) = ax.plot(x, y, marker="o" if markers else None, ms=4, label=label)
        if minima is not None and np.any(np.isfinite(y)):
            ax.plot([x[i]], [y[i]], "v", color=line.get_color(), ms=8)  # pyright: ignore
    if mark is not None:
        x, y, text = mark
        ax.plot([xscale * x], [yscale * y], "ko")
        ax.annotate(text, (xscale * x, yscale * y), textcoords="offset points", xytext=(8, 6))
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if len(series) > 1 or minima is not None:
        ax.legend()
    if title:
        ax.set_title(title)
    fig.tight_layout()
    return _save(fig, path)


@_styled
def plot_search_convergence(result: rj.MinimiseResult, path, title: str = "") -> Path:
    """Convergence of `rj.search`: each evaluated design's objective (sampled designs and
    gradient solves, infeasible ones faint) and the best feasible objective so far,
    against wall time."""
    trace = result.trace
    seconds, objective = trace["seconds"], trace["objective"]
    feasible, gradient = trace["feasible"].astype(bool), trace["gradient"].astype(bool)
    best = result.best_so_far()
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for mask, label, style in (
        (~gradient & feasible, "sampled design (plain solve)", dict(color="C0", s=6)),
        (gradient & feasible, "local phase (gradient solve)", dict(color="C1", s=8)),
        (~feasible, "infeasible", dict(color="0.7", s=4)),
    ):
        if mask.any():
            ax.scatter(seconds[mask], objective[mask], label=label, **style)  # pyright: ignore
    ax.step(seconds, np.where(np.isfinite(best), best, np.nan), "k", where="post", lw=2,
            label="best feasible so far")  # fmt: skip
    finite = best[np.isfinite(best)]
    if finite.size:
        low, high = float(np.min(finite)), float(np.max(finite))
        ax.set_ylim(low - 0.02 * (high - low + abs(low) * 1e-3), high + 0.3 * (high - low))
    else:
        _no_feasible_note(ax)
    ax.set_xlabel("wall time (s), compilation included")
    ax.set_ylabel("objective")
    ax.legend(fontsize=8)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    return _save(fig, path)


@_styled
def plot_heatmap(
    x, y, values, path, *, xlabel: str, ylabel: str, label: str, diverging: bool = False
) -> Path:
    """`values[i, j]` at `(x[j], y[i])` as a colour map (NaN: failed points, blank); on
    a map of a peak (not `diverging`) a star marks the lowest point."""
    fig, ax = plt.subplots(figsize=(7, 5))
    ax.grid(False)
    values = np.asarray(values, dtype=float)
    kwargs = {}
    if diverging:
        # Clip at the 98th percentile: grazing impacts at the plateau's edge are steep.
        limit = float(np.nanpercentile(np.abs(values), 98)) or 1.0
        kwargs = {"cmap": "RdBu_r", "vmin": -limit, "vmax": limit}
    mesh = ax.pcolormesh(np.asarray(x), np.asarray(y), values, shading="nearest", **kwargs)
    fig.colorbar(mesh, ax=ax, label=label)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    title = label
    if not diverging and np.any(np.isfinite(values)):
        i, j = np.unravel_index(np.nanargmin(values), values.shape)
        x_min, y_min = (
            np.asarray(a)[(i, j) if np.ndim(a) == 2 else k] for a, k in ((x, j), (y, i))
        )
        ax.plot([x_min], [y_min], "*", color="w", mec="k", ms=14)
        title += f"\n★ lowest: {values[i, j]:.4g} at {xlabel} = {x_min:.4g}, {ylabel} = {y_min:.4g}"
    ax.set_title(title)
    fig.tight_layout()
    return _save(fig, path)


@_styled
def plot_convergence(result, path, title: str = "") -> Path:
    """Convergence of an `OptimiseResult`: per run, the best feasible objective so far
    and the worst normalised constraint violation, against the step."""
    history = result.history
    ok = history["status"] == int(rj.status_codes(rj.Status.ok))
    held = rj.feasible(ok, history["objective"], history["violations"])
    objective = np.where(held, history["objective"], np.inf)
    best_so_far = np.minimum.accumulate(objective, axis=0)
    steps = np.arange(1, objective.shape[0] + 1)
    has_limits = history["violations"].shape[-1] > 0
    fig, axes = plt.subplots(
        2 if has_limits else 1, 1, figsize=(8, 7 if has_limits else 4.5), sharex=True, squeeze=False
    )
    ax = axes[0, 0]
    for r in range(objective.shape[1]):
        ax.plot(
            steps,
            np.where(np.isfinite(best_so_far[:, r]), best_so_far[:, r], np.nan),
            lw=0.8,
            alpha=0.6,
        )
    overall = np.min(best_so_far, axis=1)
    ax.plot(
        steps, np.where(np.isfinite(overall), overall, np.nan), "k", lw=2, label="best of all runs"
    )
    finite = best_so_far[np.isfinite(best_so_far)]
    if finite.size:
        low = float(np.min(finite))
        high = float(np.percentile(finite, 90))
        ax.set_ylim(low - 0.02 * (high - low + abs(low) * 1e-3), high)
    else:
        _no_feasible_note(ax)
    ax.set_ylabel("best feasible objective")
    ax.legend()
    ax.grid(alpha=0.3)
    if has_limits:
        ax = axes[1, 0]
        worst = np.max(history["violations"], axis=-1)
        for r in range(worst.shape[1]):
            ax.plot(steps, np.maximum(worst[:, r], 1e-7), lw=0.8, alpha=0.6)
        ax.set_yscale("log")
        ax.set_ylabel("worst limit violation (relative)")
        ax.grid(alpha=0.3)
    axes[-1, 0].set_xlabel("step")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return _save(fig, path)


def _no_feasible_note(ax) -> None:
    """Says on a convergence plot that no evaluated design met every limit."""
    ax.text(
        0.5, 0.5, "no design met every limit\n(result.json: the closest, and what it misses)",
        transform=ax.transAxes, ha="center", va="center", color="C3", fontsize=11,
    )  # fmt: skip


def _save(fig, path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
