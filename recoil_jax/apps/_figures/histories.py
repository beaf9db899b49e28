"""Histories and series: a design's displacements and forces against time, and any
family of curves (a sweep's lines, the paper's figures)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib.cm
import matplotlib.colors
import matplotlib.pyplot as plt
import numpy as np

import recoil_jax as rj

from .style import save, styled

__all__ = ["LEGEND_LINES", "plot_history", "plot_series"]


#: From this many lines on, a sweep's lines are told apart by a colour scale, not a legend.
LEGEND_LINES = 7


#: The label of each share of `F_AN` (`rjx.Forces.names`); a force added outside the
#: package is labelled by its share's name.
_SHARE_LABELS = {
    "recoil_spring": "spring $k x_M$",
    "recoil_damper": "damper $c(v)v$",
    "buffer": "orifice $F_h$",
    "recuperator": "recuperator gas $F_g$",
    "preload": "recuperator preload $F_p$",
    "counter_recoil": "counter-recoil buffer $F_{cb}$",
    "friction": "rail friction $F_f$",
    "stop": "battery stop $-F_s$",
}


@styled
def plot_history(history: rj.History, path, title: str = "") -> Path:
    """Time histories, stacked: the barrel's and absorber's displacements; the anchoring
    force with each element that carries it (recoil spring, damper, hydraulic buffer,
    gas recuperator and its preload, counter-recoil buffer, rail friction, battery stop,
    any force added outside the package, by its name) and gravity along the rails; the
    breech force of each round and the contact force. Elements the design does not have
    are left out. Saved as PNG at `path`."""
    ts = np.asarray(history.ts)
    f = history.forces
    # Without an absorber (m = 0) its displacement and the contact force stay 0: not
    # drawn, and without a breech force either there is no third panel.
    # (x_m alone does not tell: without an absorber it rests with the barrel, not at 0.)
    absorber = not all(_all_zero(g) for g in (f.coupling_spring, f.coupling_damper, f.contact))
    panels = 3 if absorber or f.breech is not None else 2
    fig, axes = plt.subplots(panels, 1, figsize=(9, 3 * panels), sharex=True)
    axes[0].plot(ts, 1e3 * np.asarray(history.x_M), label="barrel $x_M$")
    if absorber:
        axes[0].plot(ts, 1e3 * np.asarray(history.x_m), label="absorber $x_m$")
    axes[0].set_ylabel("displacement (mm)")
    axes[0].legend(loc="upper right")
    # Every part of F_AN the design has (`Forces.anchoring`: the stop enters with its
    # minus sign), then gravity along the rails, which acts on the barrel, not the mount.
    parts: dict[str, Any] = {"anchoring $F_{AN}$": history.anchoring_force}
    for name, share in zip(f.names, f.shares, strict=True):
        if name == "stop":
            share = -np.asarray(share)
        elif name in ("recoil_spring", "recuperator") and _all_zero(share):
            continue  # (k = 0, or F_r = 0: a part present by its group, carrying nothing)
        parts[_SHARE_LABELS.get(name, name.replace("_", " "))] = share
    for i, (label, force) in enumerate(parts.items()):
        if force is not None:
            axes[1].plot(
                ts,
                1e-3 * np.asarray(force),
                label=label,
                lw=2 if i == 0 else 1,
                color="k" if i == 0 else None,
            )
    if f.gravity is not None and not _all_zero(f.gravity):
        axes[1].plot(ts, 1e-3 * np.asarray(f.gravity), ls="--", lw=1, color="0.5",
                     label=r"gravity on the barrel $M g \sin\theta$ (not in $F_{AN}$)")  # fmt: skip
    axes[1].set_ylabel("force into the mounting (kN)")
    # Many parts: the legend beside the panel, not over its curves.
    many = sum(v is not None for v in parts.values()) > 4
    axes[1].legend(
        loc="upper left" if many else "upper right", fontsize=8,
        bbox_to_anchor=(1.01, 1.0) if many else None,
    )  # fmt: skip
    if panels == 3:
        if f.breech is not None:
            axes[2].plot(ts, 1e-3 * np.asarray(f.breech), label="breech $F_b$", color="C4")
        if absorber:
            contact = 1e-3 * np.asarray(history.contact_force)
            axes[2].plot(ts, contact, label="contact $F_{ct}$", color="C3")
        axes[2].set_ylabel("force (kN)")
        axes[2].legend(loc="upper right", fontsize=8)
    _mark_peaks(axes, history)
    shown = _active_until(history)
    xlabel = "time (s)"
    if shown < ts[-1]:
        axes[-1].set_xlim(0.0, shown)
        xlabel += (f": the first {shown:.2g} of {ts[-1]:g} s (later, each signal stays within "
                   "5 % of its peak of its final value)")  # fmt: skip
    axes[-1].set_xlabel(xlabel)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return save(fig, path)


def _all_zero(force) -> bool:
    """A force the design carries as identically 0 (`k = 0`: no recoil spring)."""
    return force is None or not np.any(np.asarray(force) != 0)


def _active_until(history: rj.History) -> float:
    """Where a history's time axis may end: a fifth past the last time any drawn signal
    (displacements, anchoring and contact force) is 5 % of its peak or more away from
    where it ends (a gun at rest on elevated rails carries a static load to the end)."""
    ts = np.asarray(history.ts)
    last = 0.0
    for signal in (history.x_M, history.x_m, history.anchoring_force, history.contact_force):
        values = np.asarray(signal, dtype=float)
        size = np.abs(values - values[-1]) if values.size else values
        peak = np.nanmax(size) if size.size else 0.0
        if peak > 0:
            last = max(last, float(ts[np.nonzero(size >= 0.05 * peak)[0][-1]]))
    return float(min(ts[-1], 1.2 * last)) if last > 0 else float(ts[-1])


def _mark_peaks(axes, history: rj.History) -> None:
    """The solve's peaks (located between steps, not on the save grid) on the history:
    barrel displacement, anchoring force and, with an impact, the contact force, the
    last also in an inset around it (a few milliseconds)."""
    p = history.peaks
    marks = [
        (axes[0], "peak_displacement", 1e3, "mm", "peak $x_M$"),
        (axes[1], "peak_anchoring_force", 1e-3, "kN", "peak $F_{AN}$"),
        (axes[-1], "peak_contact_force", 1e-3, "kN", "peak $F_{ct}$"),
    ]
    for ax, name, scale, unit, text in marks:
        value = float(np.asarray(getattr(p, name)))
        when = float(np.asarray(getattr(p, name + "_time")))
        if value <= 0 or not np.isfinite(value):
            continue
        ax.plot([when], [scale * value], "o", color="k", ms=5, zorder=5)
        ax.annotate(
            f"{text} {scale * value:.4g} {unit} at {when:.3f} s",
            (when, scale * value),
            textcoords="offset points",
            xytext=(8, -4),
            fontsize=8,
        )
    contact, when = (
        float(np.asarray(p.peak_contact_force)),
        float(np.asarray(p.peak_contact_force_time)),
    )
    if contact > 0:
        # The impact that holds the peak: where its force is above 1 % of the peak.
        ts, force = np.asarray(history.ts), 1e-3 * np.asarray(history.contact_force)
        above = force >= 1e-5 * contact
        k = int(np.argmin(np.abs(ts - when)))
        start, end = k, k
        while start > 0 and above[start - 1]:
            start -= 1
        while end < ts.size - 1 and above[end + 1]:
            end += 1
        width = ts[end] - ts[start]
        near = (ts >= ts[start] - 0.3 * width) & (ts <= ts[end] + 0.3 * width)
        if np.count_nonzero(near) >= 5:
            inset = axes[2].inset_axes((0.5, 0.35, 0.28, 0.55))
            inset.plot(1e3 * ts[near], force[near], color="C3")
            inset.plot([1e3 * when], [1e-3 * contact], "o", color="k", ms=4)
            inset.set_title(f"the impact: {1e3 * width:.3g} ms (time in ms)", fontsize=8)
            inset.tick_params(labelsize=7)


@styled
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
    colour_by: tuple[str, Sequence[float]] | None = None,
) -> Path:
    """Line plot of labelled `(x, y)` series; `mark` = `(x, y, text)` annotates a point;
    `ylim` = `(low, high)` in the series' units; `markers` draws each point (a front's
    designs); `minima` (a unit, e.g. `"N"`) marks each series' lowest point and gives
    it in the legend, in the series' units. `colour_by = (label, values)`, one value per
    series: lines coloured on a scale with a colour bar instead of a legend (used from
    `LEGEND_LINES` lines on, which a legend cannot tell apart; the minima are then
    marked only)."""
    fig, ax = plt.subplots(figsize=(8, 4.5))
    if ylim is not None:
        ax.set_ylim(yscale * ylim[0], yscale * ylim[1])
    colours, mapper = None, None
    if colour_by is not None:
        norm = matplotlib.colors.Normalize(min(colour_by[1]), max(colour_by[1]))
        mapper = matplotlib.cm.ScalarMappable(norm=norm, cmap="viridis")
        colours = list(mapper.to_rgba(np.asarray(colour_by[1], dtype=float)))
    for k, (label, (x, y)) in enumerate(series.items()):
        x, y = xscale * np.asarray(x, float), yscale * np.asarray(y, float)
        if minima is not None and np.any(np.isfinite(y)):
            i = int(np.nanargmin(y))
            value = y[i] / yscale
            label = f"{label}: min {value:.4g} {minima} at {x[i]:.4g}"
        colour = None if colours is None else colours[k]
        (line,) = ax.plot(x, y, marker="o" if markers else None, ms=4, label=label, color=colour)
        if minima is not None and np.any(np.isfinite(y)):
            # Edged in black: in the line's own colour it vanishes into the line.
            ax.plot([x[i]], [y[i]], "v", color=line.get_color(), mec="k", mew=0.8, ms=7)  # pyright: ignore
    if mark is not None:
        x, y, text = mark
        ax.plot([xscale * x], [yscale * y], "ko")
        ax.annotate(text, (xscale * x, yscale * y), textcoords="offset points", xytext=(8, 6))
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if colour_by is not None and mapper is not None:
        fig.colorbar(mapper, ax=ax, label=colour_by[0])
    elif len(series) > 1 or minima is not None:
        ax.legend()
    if title:
        ax.set_title(title)
    fig.tight_layout()
    return save(fig, path)
