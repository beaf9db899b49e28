"""A study's own figures beside its convergence (`designs`): a Pareto front, a throttling
design's force over its stroke, a robust design against the nominal one under scatter."""

from __future__ import annotations

from pathlib import Path

import recoil_jax as rj

from .histories import plot_series

__all__ = ["plot_force_stroke", "plot_front", "plot_robust"]


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
