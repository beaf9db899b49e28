"""A study's own figures beside its convergence (`designs`): a Pareto front, a throttling
design's force over its stroke, a robust design against the nominal one under scatter,
the best design's metrics at each firing condition."""

from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

import recoil_jax as rj

from .histories import plot_series
from .style import save, styled

__all__ = ["plot_conditions", "plot_force_stroke", "plot_front", "plot_robust"]


@styled
def plot_conditions(problem: rj.DesignProblem, report: dict, path, title: str = "") -> Path:
    """The best design's metrics at each firing condition side by side (`report`: a
    study's `result.json` with its `conditions`): a panel per metric of the objective
    and the limits, a bar per condition (red where it breaks a limit there, hatched
    where the condition is the objective's worst), each limit a dashed line over the
    conditions it holds at. Saved as PNG at `path`."""
    conditions = report["conditions"]
    names = list(conditions)
    metrics = list(dict.fromkeys([*problem.objective.weights,
                                  *(n for n, _, _ in problem.metric_constraints)]))  # fmt: skip
    columns = min(3, len(metrics))
    rows = -(-len(metrics) // columns)
    fig, axes = plt.subplots(rows, columns, figsize=(4.2 * columns, 3.2 * rows), squeeze=False)
    x = np.arange(len(names))
    at = list(zip(problem.metric_constraints, problem.limit_conditions, strict=True))
    for ax, name in zip(axes.flat, metrics, strict=False):
        metric = rj.METRICS[name]
        values = np.asarray(
            [np.nan if (v := conditions[c]["metrics"][metric.key]) is None else v for c in names],
            dtype=float,
        )
        broken = np.zeros(len(names), dtype=bool)
        for (limited, kind, limit), where in at:
            if limited != name:
                continue
            broken[where] |= values[where] > limit if kind == "max" else values[where] < limit
            for k in where:
                ax.hlines(limit, k - 0.45, k + 0.45, colors="k", linestyles="--", lw=1.2)
        colours = np.where(broken, "tab:red", "tab:blue")
        bars = ax.bar(x, np.nan_to_num(values), color=colours, width=0.6)
        if name in problem.objective.weights:
            bars[names.index(report["worst_condition"])].set_hatch("//")
        for k, v in enumerate(values):
            text = "not back" if np.isnan(v) else f"{v:,.0f}" if abs(v) >= 1e4 else f"{v:.4g}"
            ax.annotate(text, (k, 0 if np.isnan(v) else v), ha="center",
                        va="bottom" if not v < 0 else "top", fontsize=8)  # fmt: skip
        ax.set_xticks(x, names)
        ax.set_title(metric.label + _MEANING.get(name, ""), fontsize=9)
        ax.axhline(0.0, color="k", lw=0.5)
    for ax in list(axes.flat)[len(metrics) :]:
        ax.set_visible(False)
    fig.suptitle(
        f"{title}: the best design at each condition (dashed: limits; hatched: the "
        "objective's worst; red: a limit broken)",
        fontsize=10,
    )
    fig.tight_layout(rect=(0.0, 0.0, 1.0, 0.95))  # the panels below the title, not under it
    return save(fig, path)


#: What a dimensionless metric means, under its panel's title.
_MEANING = {
    "stability_margin": "\n(stabilising − overturning moment) / weight's moment:\n"
    "1 at rest, 0 on the point of tipping, < 0 lifted",
}


def plot_front(vary: str, xlabel: str, x, force, displacement, out: Path) -> list[Path]:
    """A front's best designs: the peak anchoring force against the varied value `x`
    (`front_<vary>.png`), and against the peak displacement
    (`front_<vary>_force_vs_displacement.png`)."""
    force_label = rj.METRICS["peak_anchoring_force"].label
    return [
        plot_series(
            {"best design": (x, force)},
            out / f"front_{vary}.png",
            xlabel=xlabel,
            ylabel=force_label,
            title=f"Pareto front: peak anchoring force vs {vary}",
            markers=True,
        ),
        plot_series(
            {"best design": (displacement, force)},
            out / f"front_{vary}_force_vs_displacement.png",
            xlabel="peak barrel displacement (mm)",
            ylabel=force_label,
            xscale=1e3,
            title="peak anchoring force vs peak displacement",
            markers=True,
        ),
    ]


def plot_force_stroke(curves: dict, out: Path) -> Path:
    """The anchoring force over the recoil stroke, a curve per design (`{label: (x_M,
    F_AN)}`, SI units): `force_stroke.png`."""
    return plot_series(
        curves,
        out / "force_stroke.png",
        xlabel="barrel travel x_M (mm)",
        ylabel="anchoring force F_AN (kN)",
        xscale=1e3,
        yscale=1e-3,
        title="anchoring force over the recoil stroke",
    )


def plot_robust(curves: dict, xlabel: str, out: Path) -> Path:
    """The objective of each design over the scatter (`{label: (offset, objective)}`):
    `robust_vs_nominal.png`."""
    return plot_series(
        curves, out / "robust_vs_nominal.png", xlabel=xlabel, ylabel="objective",
        title="objective under scatter",
    )  # fmt: skip
