"""Calibration figures: the fit over the traces, the correlation, the profiles, a
prediction's bands, the posterior (corner plot) and its predictive bands."""

from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

import recoil_jax as rj
import recoil_jax.extend as rjx

from .style import save, styled

__all__ = [
    "calibration_figures",
    "plot_calibration_fit",
    "plot_correlation",
    "plot_posterior",
    "plot_posterior_predictive",
    "plot_prediction",
    "plot_profiles",
]


def _signal_grid(measured: list[dict], heights: tuple[int, int]):
    """The signals measured in any experiment (in order), and a figure of two panels
    each (a trace over its residuals, of `heights`) per signal (rows) and experiment
    (columns)."""
    signals = list(dict.fromkeys(s for m in measured for s in m))
    fig, axes = plt.subplots(
        2 * len(signals),
        len(measured),
        figsize=(4.8 * len(measured) + 1, 3.4 * len(signals)),
        squeeze=False,
        gridspec_kw={"height_ratios": list(heights) * len(signals)},
        sharex="col",
        layout="constrained",
    )
    return signals, fig, axes


@styled
def plot_calibration_fit(result: rj.CalibrationResult, path) -> Path:
    """Measured against fitted for each experiment (columns) and signal (rows), each
    with its residual panel below (in the signal's unit)."""
    from .._files.describe import structure_line

    signals, fig, axes = _signal_grid(result.measured, (3, 1))
    checks = {(c.experiment, c.signal): c for c in result.check.signals}
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
    return save(fig, path)


@styled
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
    return save(fig, path)


@styled
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
    return save(fig, path)


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


@styled
def plot_prediction(
    prediction: rjx.Prediction, path, source: str = "the calibration's uncertainty"
) -> Path:
    """Each peak metric's sampled values under the fitted uncertainty (histogram; drawn
    from `source`), with the nominal value and both 95 % bands (sampled percentiles,
    linear propagation)."""
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
        f"prediction from {source} ({prediction.count} samples, {prediction.failed} failed)",
        fontsize=10,
    )
    return save(fig, path)


def plot_posterior(posterior: rjx.Posterior, path) -> Path:
    """The posterior's corner plot: each value's marginal (histogram of every draw) with
    the least-squares Laplace normal over it, and each pair's draws (up to 2,000) with the
    Laplace 95 % ellipse; where the two differ, the draws are the posterior."""
    labels = posterior.labels
    P = len(labels)
    flat = posterior.draws.reshape(-1, P)
    fit = posterior.fit
    value = np.array([fit.values[k] for k in labels])
    covariance = np.asarray(fit.covariance, dtype=float)
    shown = flat[np.linspace(0, len(flat) - 1, min(len(flat), 2000)).astype(int)]
    size = max(2.2, min(3.2, 9.0 / P))
    fig, axes = plt.subplots(P, P, figsize=(size * P, size * P), squeeze=False,
                             layout="constrained")  # fmt: skip
    for i in range(P):
        for j in range(P):
            ax = axes[i, j]
            if j > i:
                ax.set_visible(False)
                continue
            if i == j:
                ax.hist(flat[:, i], bins=50, density=True, color="0.7")
                sd = np.sqrt(covariance[i, i])
                if np.isfinite(sd) and sd > 0:
                    xs = np.linspace(flat[:, i].min(), flat[:, i].max(), 200)
                    density = np.exp(-0.5 * ((xs - value[i]) / sd) ** 2) / (sd * np.sqrt(2 * np.pi))
                    ax.plot(xs, density, color="C3", lw=1.2, label="Laplace")
                ax.set_yticks([])
                if i == 0:
                    ax.legend(fontsize=7, loc="upper right")
            else:
                ax.plot(shown[:, j], shown[:, i], ".", ms=1.5, color="C0", alpha=0.4)
                block = covariance[np.ix_([j, i], [j, i])]
                if np.all(np.isfinite(block)):
                    # The 95 % ellipse of two jointly normal values: χ²₂ = 5.99.
                    w, v = np.linalg.eigh(block)
                    t = np.linspace(0, 2 * np.pi, 200)
                    ring = (v * np.sqrt(np.maximum(w, 0) * 5.991)) @ np.stack(
                        [np.cos(t), np.sin(t)]
                    )
                    ax.plot(value[j] + ring[0], value[i] + ring[1], color="C3", lw=1.0)
            if i == P - 1:
                ax.set_xlabel(labels[j])
                ax.tick_params(axis="x", labelrotation=30, labelsize=7)
            else:
                ax.set_xticklabels([])
            if j == 0 and i > 0:
                ax.set_ylabel(labels[i])
                ax.tick_params(axis="y", labelsize=7)
            elif j > 0:
                ax.set_yticklabels([])
    chains, draws = posterior.draws.shape[:2]
    verdict = "converged" if posterior.converged else "NOT converged"
    fig.suptitle(f"posterior: {chains} chains × {draws} draws, {verdict}; red: the "
                 "least-squares Laplace approximation", fontsize=9)  # fmt: skip
    return save(fig, path)


@styled
def plot_posterior_predictive(predictive: rjx.PosteriorPredictive, path) -> Path:
    """The traces under the posterior, each experiment (columns) and signal (rows): the
    measured samples over the model's median, and below, everything less that median
    (in the signal's unit), where the bands show: the model's 95 % band over the draws
    (dark) and a repeated firing's (light: the model with the likelihood's noise)."""
    signals, fig, axes = _signal_grid(predictive.measured, (2, 2))
    for e, t in enumerate(predictive.times):
        for s, signal in enumerate(signals):
            top, bottom = axes[2 * s, e], axes[2 * s + 1, e]
            unit = rjx.SIGNALS[signal][0]
            if signal not in predictive.measured[e]:
                top.set_visible(False)
                bottom.set_visible(False)
                continue
            measured = predictive.measured[e][signal]
            low, median, high = predictive.model[e][signal]
            observed = predictive.observed[e][signal]
            top.plot(t, measured, ".", ms=2, color="0.55", label="measured")
            top.plot(t, median, color="C0", lw=1.2, label="posterior median")
            top.set_ylabel(f"{signal} ({unit})")
            top.set_title(f"{predictive.experiments[e]}: {rjx.SIGNALS[signal][1]}")
            top.legend(loc="upper right", fontsize=7)
            bottom.fill_between(t, observed[0] - median, observed[1] - median, color="C0",
                                alpha=0.18, lw=0, label="95 %: a repeated firing")  # fmt: skip
            bottom.fill_between(t, low - median, high - median, color="C0", alpha=0.6, lw=0,
                                label="95 %: the model")  # fmt: skip
            bottom.plot(t, measured - median, ".", ms=1.5, color="C3", label="measured")
            bottom.axhline(0.0, color="k", lw=0.6)
            bottom.set_ylabel(f"less the median ({unit})")
            bottom.set_title(
                f"{predictive.coverage[e][signal]:.1%} of the samples inside the light band",
                fontsize=8,
            )
            bottom.legend(loc="upper right", fontsize=7)
        axes[-1, e].set_xlabel("t (s)")
    failed = f", {predictive.failed} failed" if predictive.failed else ""
    fig.suptitle(f"posterior predictive: the model at {predictive.draws} posterior draws"
                 f"{failed}", fontsize=9)  # fmt: skip
    return save(fig, path)
