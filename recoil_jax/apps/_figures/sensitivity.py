"""Global sensitivity figures: the indices, Morris's plane, the scatter of the samples."""

from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

import recoil_jax as rj

from .style import save, styled

__all__ = [
    "plot_morris",
    "plot_sensitivity_indices",
    "plot_sensitivity_scatter",
    "sensitivity_figures",
]


def _metric_label(name: str) -> str:
    return rj.METRICS[name].label if name in rj.METRICS else "objective"


#: The bars of the methods the library ships: (key, interval key, legend) per bar, and
#: the axis label. Another method's bars are its main index.
_SENSITIVITY_BARS = {
    "sobol": ((("ST", "ST_conf", "total ST"), ("S1", "S1_conf", "first-order S1")),
              "Sobol index (share of the variance)"),
    "morris": ((("mu_star", "mu_star_conf", "μ*"),), "μ*: mean |effect| over the range"),
    "dgsm": ((("dgsm", "dgsm_conf", "DGSM bound on ST"),), "upper bound on the total index"),
}  # fmt: skip


@styled
def plot_sensitivity_indices(result: rj.SensitivityResult, path) -> Path:
    """A tornado of the method's indices per metric (most important on top), each bar
    with its 95 % interval."""
    main = ((result.main, f"{result.main}_conf", result.main),)
    bars, xlabel = _SENSITIVITY_BARS.get(result.method, (main, result.main))
    n, d = len(result.metrics), len(result.parameters)
    fig, axes = plt.subplots(1, n, figsize=(4.4 * n, 0.32 * d * len(bars) + 1.8),
                             squeeze=False, layout="constrained")  # fmt: skip
    height = 0.8 / len(bars)
    for ax, metric in zip(axes[0], result.metrics, strict=True):
        order = result.ranking(metric)[::-1]
        for b, (key, conf, label) in enumerate(bars):
            values = [result.indices[metric][p][key] for p in order]
            errors = [result.indices[metric][p][conf] for p in order]
            y = np.arange(d) + (b - (len(bars) - 1) / 2) * height
            ax.barh(y, values, height=height, xerr=errors, color=f"C{b}", label=label,
                    error_kw={"elinewidth": 0.8, "capsize": 2})  # fmt: skip
        ax.set_yticks(range(d), order)
        ax.locator_params(axis="x", nbins=4)  # metric units: long tick labels
        ax.axvline(0.0, color="k", lw=0.6)
        ax.set_xlabel(xlabel if result.method != "morris" else f"μ* ({_metric_label(metric)})")
        note = " (constant)" if metric in result.constant else ""
        ax.set_title(_metric_label(metric) + note)
    if len(bars) > 1:
        axes[0, 0].legend(loc="lower right")
    fig.suptitle(
        f"{result.method}: {result.used:,} of {len(result.ok):,} designs used", fontsize=10
    )
    return save(fig, path)


@styled
def plot_morris(result: rj.SensitivityResult, path) -> Path:
    """Morris μ* against σ per metric: far right matters, high up interacts or bends (the
    six most important named)."""
    n = len(result.metrics)
    fig, axes = plt.subplots(1, n, figsize=(4.4 * n, 3.8), squeeze=False, layout="constrained")
    for ax, metric in zip(axes[0], result.metrics, strict=True):
        by = result.indices[metric]
        mu_star = np.asarray([by[p]["mu_star"] for p in result.parameters])
        sigma = np.asarray([by[p]["sigma"] for p in result.parameters])
        ax.scatter(mu_star, sigma, s=18)
        named = set(result.ranking(metric)[:6])  # the rest crowd near the origin
        for p, x, y in zip(result.parameters, mu_star, sigma, strict=True):
            if p in named:
                ax.annotate(p, (x, y), fontsize=8, xytext=(3, 3), textcoords="offset points")
        top = max(mu_star.max(), sigma.max(), 1e-300) * 1.1
        ax.plot([0, top], [0, top], ":", color="0.5", lw=0.8, label="σ = μ*")
        ax.set_xlim(0, top)
        ax.set_ylim(0, top)
        ax.set_xlabel("μ* (mean |effect|)")
        ax.set_ylabel("σ (spread of the effects)")
        ax.set_title(_metric_label(metric))
    axes[0, 0].legend(loc="upper left")
    return save(fig, path)


@styled
def plot_sensitivity_scatter(result: rj.SensitivityResult, path, top: int = 3) -> Path:
    """Each metric against its `top` most important parameters (up to 3,000 of the
    designs that solved)."""
    cols, lines = min(top, len(result.parameters)), len(result.metrics)
    fig, axes = plt.subplots(lines, cols, figsize=(3.6 * cols, 2.9 * lines), squeeze=False,
                             layout="constrained")  # fmt: skip
    rows = np.flatnonzero(result.ok)
    rows = np.random.default_rng(0).permutation(rows)[:3000]
    for r, metric in enumerate(result.metrics):
        for c, name in enumerate(result.ranking(metric)[:cols]):
            ax = axes[r, c]
            i = result.parameters.index(name)
            ax.scatter(result.samples[rows, i], result.outputs[metric][rows], s=2, alpha=0.35)
            ax.set_xlabel(rj.PARAMETERS[name].label)
            if c == 0:
                ax.set_ylabel(_metric_label(metric))
            ax.ticklabel_format(axis="x", useOffset=False)
    return save(fig, path)


def sensitivity_figures(result: rj.SensitivityResult, out) -> list[Path]:
    """The analysis's figures in the folder `out`: `indices.png`, `scatter.png` and,
    for Morris (`mu_star` and `sigma`), `morris.png`."""
    out = Path(out)
    figures = [plot_sensitivity_indices(result, out / "indices.png")]
    if {"mu_star", "sigma"} <= set(result.keys):
        figures.append(plot_morris(result, out / "morris.png"))
    figures.append(plot_sensitivity_scatter(result, out / "scatter.png"))
    return figures
