"""Design figures: sweep maps, optimisation convergence."""

from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

import recoil_jax as rj
import recoil_jax.extend as rjx

from .style import no_feasible_note, save, styled

__all__ = ["objective_label", "plot_convergence", "plot_heatmap", "plot_search_convergence"]


@styled
def plot_search_convergence(result: rj.OptimiseResult, path, title: str = "") -> Path:
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
        no_feasible_note(ax)
    ax.set_xlabel("wall time (s), compilation included")
    ax.set_ylabel(objective_label(result.problem))
    ax.legend(fontsize=8)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    return save(fig, path)


@styled
def plot_heatmap(
    x, y, values, path, *, xlabel: str, ylabel: str, label: str, diverging: bool = False
) -> Path:
    """`values[i, j]` at `(x[j], y[i])` (1-D swept values) as a colour map (NaN: failed
    points, blank); on a map of a peak (not `diverging`) a star marks the lowest point.

    Each cell is one swept design: on an evenly spaced axis centred on its value (the
    axis ends at the first and last value swept); on an unevenly spaced one (m = 100,
    500, 1000, 1500) the cells are equal and the ticks are the values swept."""
    fig, ax = plt.subplots(figsize=(7, 5))
    ax.grid(False)
    values = np.asarray(values, dtype=float)
    kwargs = {}
    if diverging:
        # Clip at the 98th percentile: grazing impacts at the plateau's edge are steep.
        limit = float(np.nanpercentile(np.abs(values), 98)) or 1.0
        kwargs = {"cmap": "RdBu_r", "vmin": -limit, "vmax": limit}
    x_cells, y_cells = _Cells(x), _Cells(y)
    mesh = ax.pcolormesh(x_cells.edges, y_cells.edges, values, shading="flat", **kwargs)
    x_cells.draw(ax.xaxis, ax.set_xlim)
    y_cells.draw(ax.yaxis, ax.set_ylim)
    fig.colorbar(mesh, ax=ax, label=label)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    title = label
    if not diverging and np.any(np.isfinite(values)):
        i, j = np.unravel_index(np.nanargmin(values), values.shape)
        x_min, y_min = x_cells.values[j], y_cells.values[i]
        ax.plot([x_cells.at[j]], [y_cells.at[i]], "*", color="w", mec="k", ms=14, clip_on=False)
        title += f"\n★ lowest: {values[i, j]:.4g} at {xlabel} = {x_min:.4g}, {ylabel} = {y_min:.4g}"
    ax.set_title(title)
    fig.tight_layout()
    return save(fig, path)


class _Cells:
    """The cells of one heatmap axis over swept `values` `(n,)`: `at` (where each is
    drawn), `edges` `(n + 1,)`, and how the axis is labelled (`draw`)."""

    def __init__(self, values):
        self.values = np.asarray(values, dtype=float).reshape(-1)
        steps = np.diff(self.values)
        n = self.values.size
        self.even = n > 1 and bool(np.allclose(steps, steps[0], rtol=1e-6, atol=0.0))
        if self.even or n == 1:
            half = 0.5 * (steps[0] if n > 1 else 1.0)
            self.at = self.values
            self.edges = np.concatenate([self.values - half, self.values[-1:] + half])
        else:
            self.at = np.arange(n, dtype=float)
            self.edges = np.arange(n + 1, dtype=float) - 0.5

    def draw(self, axis, set_limits) -> None:
        if self.even:
            set_limits(self.values[0], self.values[-1])
            return
        every = max(1, int(np.ceil(self.values.size / 12)))
        axis.set_ticks(self.at[::every], [f"{v:g}" for v in self.values[::every]])


@styled
def plot_convergence(result, path, title: str = "") -> Path:
    """Convergence of an `OptimiseResult`: per run, the best feasible objective so far
    and the worst normalised constraint violation, against the step."""
    history = result.history
    ok = history["status"] == rjx.OK_CODE
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
        # Zoomed on the end (the first steps are far above), but every run's final
        # value inside: a run stuck on a plateau shows where it stayed.
        ends = best_so_far[-1][np.isfinite(best_so_far[-1])]
        low = float(np.min(finite))
        high = max(float(np.percentile(finite, 90)), float(np.max(ends, initial=low)))
        span = high - low + abs(low) * 1e-3
        ax.set_ylim(low - 0.02 * span, high + 0.05 * span)
    else:
        no_feasible_note(ax)
    ax.set_ylabel("best feasible: " + objective_label(result.problem))
    ax.legend()
    ax.grid(alpha=0.3)
    if has_limits:
        ax = axes[1, 0]
        worst = np.max(history["violations"], axis=-1)
        for r in range(worst.shape[1]):
            ax.plot(steps, np.maximum(worst[:, r], 1e-7), lw=0.8, alpha=0.6)
        ax.set_yscale("log")
        ax.set_ylabel("worst limit violation (relative;\nheld: drawn at 1e-7)")
        ax.grid(alpha=0.3)
    axes[-1, 0].set_xlabel("step")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return save(fig, path)


def objective_label(problem: rj.DesignProblem | None) -> str:
    """An axis label for a problem's objective, with its unit: the metric's label for
    one metric of weight 1 (`peak anchoring force (N)`), else the weighted sum."""
    if problem is None:
        return "objective"
    weights = problem.objective.weights
    worst = ""
    if problem.objective.scatter is not None:
        q = problem.objective.quantile
        worst = (
            " (worst case of the scatter)" if q is None else f" ({q:.0%} quantile of the scatter)"
        )
    if len(weights) == 1:
        ((name, weight),) = weights.items()
        label = rj.METRICS[name].label
        return (label if weight == 1 else f"{weight:g} × {label}") + worst
    terms = " + ".join(f"{w:g} × {rj.METRICS[n].label}" for n, w in weights.items())
    return f"objective = {terms}{worst}"
