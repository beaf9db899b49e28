"""Test-plan figures: each parameter's predicted interval for the plan against the
hand-drawn plans, and which candidate firings carry the information."""

from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

import recoil_jax as rj

from .style import save, styled

__all__ = ["planning_figures", "plot_plan_information", "plot_plan_intervals"]

#: The plans a figure compares, with their legends.
_PLANS = (
    ("plan", "planned"),
    ("baseline", "spread evenly"),
    ("first_candidate", "every round at the first candidate"),
)


def _condition_label(condition: dict) -> str:
    """`elevation 30°, v0 8 m/s`: each value with its unit."""

    def unit(name: str) -> str:
        if name == "elevation":
            return "°"
        text = rj.PARAMETERS[name].unit if name in rj.PARAMETERS else ""
        return f" {text}" if text else ""

    return ", ".join(f"{k} {v:g}{unit(k)}" for k, v in condition.items())


@styled
def plot_plan_intervals(plan: rj.FiringPlan, path) -> Path:
    """Each fitted parameter's 95 % interval half-width as a share of its `[fit]` range,
    for the plan and the hand-drawn ones (log scale; "not determined" written where a
    bar would be, outside the scale, where a plan leaves the value undetermined)."""
    fit = list(plan.problem.fit)
    fig, ax = plt.subplots(figsize=(7.5, 2.0 + 0.6 * len(fit)))
    widths = {
        key: [
            None if getattr(plan, key).stderr[p] is None
            else 1.96 * getattr(plan, key).stderr[p] / np.ptp(plan.problem.fit[p])
            for p in fit
        ]
        for key, _ in _PLANS
    }  # fmt: skip
    y = np.arange(len(fit))
    for k, (key, label) in enumerate(_PLANS):
        offset = (k - 1) * 0.22
        values = widths[key]
        known = [i for i, w in enumerate(values) if w is not None]
        unknown = [i for i, w in enumerate(values) if w is None]
        lengths = [float(values[i] or 0.0) for i in known]
        ax.barh(y[known] + offset, lengths, height=0.2, color=f"C{k}", label=label)
        for i in unknown:  # words, not a mark at some width: there is no width
            ax.annotate(f"{label}: not determined", xy=(0.01, y[i] + offset),
                        xycoords=("axes fraction", "data"), va="center", fontsize=7,
                        color=f"C{k}", fontstyle="italic")  # fmt: skip
    ax.set_xscale("log")
    ax.set_yticks(y, fit)
    ax.invert_yaxis()
    ax.set_xlabel("95 % interval half-width / [fit] range (smaller is better)")
    ax.set_title(f"Predicted intervals: {plan.problem.firings} firings")
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.18), ncol=2, fontsize=8)
    fig.tight_layout()
    return save(fig, path)


@styled
def plot_plan_information(plan: rj.FiringPlan, path) -> Path:
    """Which candidates carry the information. Left: per candidate firing (rows) and
    fitted parameter (columns), the standard error one firing there alone would give
    the parameter if the others were known (`1/√F_jj` with every signal the cost
    allows, as a share of the [fit] range; darker is more informative). Right: what one
    more firing there would add to the plan, `tr(M⁻¹ F_c)` with `M` the plan's
    information and `F_c` the candidate's best affordable signals (the variance
    function of optimal design: for a D-optimal plan it peaks at the planned
    candidates). The planned firings are marked ▶ with how many times each is fired."""
    fit = list(plan.problem.fit)
    problem = plan.problem
    affordable = [plan.signals.index(s) for s in plan.baseline.firings[0][1]]
    diagonal = np.einsum("cspp->cp", plan.information[:, affordable])  # (C, P)
    alone = 1.0 / np.sqrt(np.maximum(diagonal, 1e-300))
    shade = np.log10(np.minimum(alone, 1e6))
    opts = plan.firing_options()
    inverse = np.linalg.pinv(plan.plan.information, hermitian=True)
    added = np.zeros(len(plan.conditions))
    for c, block in zip(opts.candidate, opts.information[:, 0], strict=True):
        added[c] = max(added[c], float(np.trace(inverse @ block)))
    fig, (ax, bars) = plt.subplots(
        1, 2, figsize=(4.5 + 1.3 * len(fit), 1.4 + 0.32 * len(plan.conditions)),
        gridspec_kw={"width_ratios": [len(fit), 2.2]}, sharey=True,
    )  # fmt: skip
    image = ax.imshow(shade, aspect="auto", cmap="viridis_r")
    fig.colorbar(
        image, ax=ax, label="log10 standard error of one firing alone\n(share of [fit] range)"
    )
    labels = [_condition_label(c) for c in plan.conditions]
    counts: dict[int, list[str]] = {}
    for c, signals in plan.plan.firings:
        counts.setdefault(c, []).append("+".join(signals))
    for c, records in counts.items():
        labels[c] = f"▶ {labels[c]}  ×{len(records)} ({'; '.join(sorted(set(records)))})"
    ax.set_yticks(range(len(labels)), labels, fontsize=8)
    ax.set_xticks(range(len(fit)), fit, rotation=30, ha="right")
    ax.grid(False)
    ax.set_title("Information per candidate firing")
    colours = ["C1" if c in counts else "C0" for c in range(len(plan.conditions))]
    bars.barh(range(len(added)), added, color=colours)
    bars.axvline(len(fit) / problem.firings, color="0.3", ls="--", lw=1,
                 label=f"P/n = {len(fit)}/{problem.firings}: "
                 "a D-optimal plan's firings")  # fmt: skip
    bars.set_xlabel("information added, tr(M⁻¹F)\n(M: the plan's, F: this firing's)")
    bars.set_title("One more firing there")
    # Below the panel, not over a bar; P/n is where a D-optimal plan's firings sit.
    bars.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.28))
    fig.tight_layout()
    return save(fig, path)


def planning_figures(plan: rj.FiringPlan, folder) -> list[Path]:
    """`intervals.png` and `information.png` in `folder`."""
    folder = Path(folder)
    return [plot_plan_intervals(plan, folder / "intervals.png"),
            plot_plan_information(plan, folder / "information.png")]  # fmt: skip
