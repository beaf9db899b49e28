"""Figures (matplotlib, Agg backend: works without a display)."""

from __future__ import annotations

import functools
from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.cm
import matplotlib.colors
import matplotlib.pyplot as plt
import numpy as np

import recoil_jax as rj
import recoil_jax.extend as rjx

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


#: From this many lines on, a sweep's lines are told apart by a colour scale, not a legend.
LEGEND_LINES = 7

__all__ = [
    "LEGEND_LINES",
    "calibration_figures",
    "objective_label",
    "plot_calibration_fit",
    "plot_convergence",
    "plot_correlation",
    "plot_heatmap",
    "plot_history",
    "plot_morris",
    "plot_prediction",
    "plot_profiles",
    "plot_search_convergence",
    "plot_sensitivity_indices",
    "plot_sensitivity_scatter",
    "plot_series",
    "sensitivity_figures",
]


@_styled
def plot_history(history: rj.History, path, title: str = "") -> Path:
    """Time histories, stacked: the barrel's and absorber's displacements; the anchoring
    force with each element that carries it (recoil spring, damper, hydraulic buffer,
    gas recuperator); the breech force of each round and the contact force. Elements the
    design does not have are left out. Saved as PNG at `path`."""
    ts = np.asarray(history.ts)
    f = history.forces
    # Without an absorber (m = 0) its displacement and the contact force stay 0: not
    # drawn, and without a breech force either there is no third panel.
    absorber = bool(np.any(np.asarray(history.x_m) != 0))
    panels = 3 if absorber or f.breech is not None else 2
    fig, axes = plt.subplots(panels, 1, figsize=(9, 3 * panels), sharex=True)
    axes[0].plot(ts, 1e3 * np.asarray(history.x_M), label="barrel $x_M$")
    if absorber:
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
        xlabel += f": the first {shown:.2g} of {ts[-1]:g} s (later, each signal < 5 % of its peak)"
    axes[-1].set_xlabel(xlabel)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return _save(fig, path)


def _active_until(history: rj.History) -> float:
    """Where a history's time axis may end: a fifth past the last time any drawn signal
    (displacements, anchoring and contact force) is 5 % of its peak or more."""
    ts = np.asarray(history.ts)
    last = 0.0
    for signal in (history.x_M, history.x_m, history.anchoring_force, history.contact_force):
        size = np.abs(np.asarray(signal, dtype=float))
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
    return _save(fig, path)


@_styled
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
        _no_feasible_note(ax)
    ax.set_xlabel("wall time (s), compilation included")
    ax.set_ylabel(objective_label(result.problem))
    ax.legend(fontsize=8)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    return _save(fig, path)


@_styled
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
    return _save(fig, path)


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


@_styled
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
        _no_feasible_note(ax)
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
    return _save(fig, path)


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


@_styled
def plot_calibration_fit(result: rj.CalibrationResult, path) -> Path:
    """Measured against fitted for each experiment (columns) and signal (rows), each
    with its residual panel below (in the signal's unit)."""
    from ._calibration import structure_line

    signals = list(dict.fromkeys(s for m in result.measured for s in m))
    experiments = len(result.times)
    checks = {(c.experiment, c.signal): c for c in result.check.signals}
    fig, axes = plt.subplots(
        2 * len(signals),
        experiments,
        figsize=(4.8 * experiments + 1, 3.4 * len(signals)),
        squeeze=False,
        gridspec_kw={"height_ratios": [3, 1] * len(signals)},
        sharex="col",
        layout="constrained",
    )
    for e, (t, measured, model) in enumerate(
        zip(result.times, result.measured, result.model, strict=True)
    ):
        name = result.experiments[e]["name"]
        for s, signal in enumerate(signals):
            top, bottom = axes[2 * s, e], axes[2 * s + 1, e]
            unit = rjx.SIGNALS[signal][0]
            if signal not in measured:
                top.set_visible(False)
                bottom.set_visible(False)
                continue
            top.plot(t, measured[signal], ".", ms=2, color="0.55", label="measured")
            top.plot(t, model[signal], color="C0", lw=1.4, label="fitted")
            top.set_ylabel(f"{signal} ({unit})")
            top.set_title(f"{name}: {rjx.SIGNALS[signal][1]}")
            top.legend(loc="upper right")
            residual = measured[signal] - model[signal]
            bottom.plot(t, residual, ".", ms=2, color="C3")
            bottom.axhline(0.0, color="k", lw=0.8)
            bottom.set_ylabel(f"residual ({unit})")
            check = checks.get((name, signal))
            if check is not None:  # the noise the residuals are held to, and where they fail
                for y in (-2 * check.noise, 2 * check.noise):
                    bottom.axhline(y, color="k", lw=0.6, ls="--")
                for start, end in check.failing_spans():
                    for ax in (top, bottom):
                        ax.axvspan(start, end, color="C3", alpha=0.12, lw=0)
        axes[-1, e].set_xlabel("t (s)")
    fitted = ", ".join(f"{k} = {v:.4g}" for k, v in result.values.items())
    verdict = (
        "the model explains the traces\n(dashed: twice the noise)"
        if result.explains
        else "the model does NOT explain the traces\n(shaded: where it fails; dashed: twice "
        "the noise)"
    )
    fig.suptitle(
        f"calibration of: {structure_line(result.structure)}\nreduced chi2 "
        f"{result.reduced_chi2:.3g}; {fitted}\n{verdict}",
        fontsize=9,
        color="k" if result.explains else "C3",
    )
    return _save(fig, path)


@_styled
def plot_correlation(result: rj.CalibrationResult, path) -> Path:
    """The fitted values' correlation matrix (blank where a value is not determined)."""
    names = list(result.fitted)
    n = len(names)
    fig, ax = plt.subplots(figsize=(1.1 * n + 2.5, 1.0 * n + 1.8), layout="constrained")
    image = ax.imshow(result.correlation, vmin=-1, vmax=1, cmap="RdBu_r")
    ax.set_xticks(range(n), names, rotation=45, ha="right")
    ax.set_yticks(range(n), names)
    ax.grid(False)
    for i in range(n):
        for j in range(n):
            c = result.correlation[i, j]
            if np.isfinite(c):
                ax.text(j, i, f"{c:+.2f}", ha="center", va="center", fontsize=8)
    fig.colorbar(image, ax=ax, label="correlation")
    ax.set_title("correlation of the fitted values")
    return _save(fig, path)


@_styled
def plot_profiles(result: rj.CalibrationResult, path) -> Path:
    """Each fitted value's profile (the refitted cost's rise, in units of the reduced
    chi2) beside the linear approximation's parabola, with the 95 % threshold."""
    names = list(result.profiles)
    fig, axes = plt.subplots(1, len(names), figsize=(3.8 * len(names), 3.4), squeeze=False,
                             layout="constrained")  # fmt: skip
    threshold = 3.841
    for ax, name in zip(axes[0], names, strict=True):
        profile, fitted = result.profiles[name], result.fitted[name]
        ax.plot(profile["values"], profile["delta_chi2"], "o-", ms=3, label="profile")
        if fitted.stderr:
            x = np.linspace(profile["values"].min(), profile["values"].max(), 200)
            ax.plot(x, ((x - fitted.value) / fitted.stderr) ** 2, "--", color="C1",
                    label="linear (stderr)")  # fmt: skip
        ax.axhline(threshold, color="C3", lw=0.9, label="95 % threshold")
        ax.set_ylim(0, max(3 * threshold, 1.05 * min(profile["delta_chi2"].max(), 40)))
        ax.set_xlabel(name + ("" if fitted.identifiable else " (not determined)"))
        ax.ticklabel_format(axis="x", useOffset=False)
        ax.tick_params(axis="x", labelrotation=30)
        ax.set_ylabel("rise of chi2 / reduced chi2")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle("profile likelihoods (the others refitted at each point)", fontsize=10)
    return _save(fig, path)


def calibration_figures(result: rj.CalibrationResult, out) -> list[Path]:
    """The calibration's figures in the folder `out`: `fit.png`, `correlation.png` and,
    with profiles, `profiles.png`."""
    out = Path(out)
    figures = [
        plot_calibration_fit(result, out / "fit.png"),
        plot_correlation(result, out / "correlation.png"),
    ]
    if result.profiles:
        figures.append(plot_profiles(result, out / "profiles.png"))
    return figures


@_styled
def plot_prediction(prediction: rjx.Prediction, path) -> Path:
    """Each peak metric's sampled values under the fitted uncertainty (histogram), with
    the nominal value and both 95 % bands (sampled percentiles, linear propagation)."""
    shown = [n for n in ("peak_anchoring_force", "peak_displacement", "max_stroke")
             if np.ptp(prediction.samples[n]) > 0]  # fmt: skip
    fig, axes = plt.subplots(1, len(shown), figsize=(4.6 * len(shown), 3.6), squeeze=False,
                             layout="constrained")  # fmt: skip
    for ax, name in zip(axes[0], shown, strict=True):
        ax.hist(prediction.samples[name], bins=60, color="0.75")
        ax.axvline(prediction.nominal[name], color="k", lw=1.2, label="at the fitted values")
        for i, x in enumerate(prediction.sampled[name]["ci95"]):
            ax.axvline(x, color="C0", ls="--", label="95 %: samples" if i == 0 else None)
        for i, x in enumerate(prediction.linear[name]["ci95"]):
            ax.axvline(x, color="C3", ls=":", lw=1.6, label="95 %: linear" if i == 0 else None)
        ax.set_xlabel(rj.METRICS[name].label)
        ax.ticklabel_format(axis="x", useOffset=False)
        ax.tick_params(axis="x", labelrotation=30)
        ax.set_ylabel("samples")
        ax.legend(loc="upper left", fontsize=7)
    fig.suptitle(
        f"prediction from the calibration's uncertainty ({prediction.count} samples, "
        f"{prediction.failed} failed)",
        fontsize=10,
    )
    return _save(fig, path)


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


@_styled
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
    return _save(fig, path)


@_styled
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
    return _save(fig, path)


@_styled
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
    return _save(fig, path)


def sensitivity_figures(result: rj.SensitivityResult, out) -> list[Path]:
    """The analysis's figures in the folder `out`: `indices.png`, `scatter.png` and,
    for Morris (`mu_star` and `sigma`), `morris.png`."""
    out = Path(out)
    figures = [plot_sensitivity_indices(result, out / "indices.png")]
    if {"mu_star", "sigma"} <= set(result.keys):
        figures.append(plot_morris(result, out / "morris.png"))
    figures.append(plot_sensitivity_scatter(result, out / "scatter.png"))
    return figures
