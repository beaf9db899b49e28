"""The paper's figures, drawn from our model: Fig. 4, 7, 8 and 9 (`recoil-jax reproduce`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

import recoil_jax as rj

from .histories import plot_series

__all__ = ["paper_figures"]


def paper_figures(out: Path, log=None) -> list[Path]:
    """PNGs corresponding to the paper's Fig. 4, 7, 8 and 9."""
    figures = []
    simplified = rj.params_from_values(m=0.0)
    ts = np.linspace(0.0, 10.0, 20001)
    history = rj.simulate(simplified, ts=ts)
    best = rj.peaks(simplified)
    x_peak, t_peak = float(best.peak_displacement), float(best.peak_displacement_time)
    figures.append(
        plot_series(
            {"simplified model": (history.ts, history.x_M)},
            out / "fig4_simplified_displacement.png",
            xlabel="time (s)",
            ylabel="barrel displacement $x_M$ (m)",
            title="Fig. 4: simplified model, barrel displacement",
            mark=(t_peak, x_peak, f"{x_peak:.4f} m at {t_peak:.3f} s"),
        )
    )
    if log:
        log(f"  wrote {figures[-1]}")
    whole, first = {}, {}
    ts_first = np.linspace(0.0, 0.04, 20001)
    for m in (100.0, 500.0, 1000.0, 1500.0):
        params = rj.params_from_values(m=m, gap=0.0)
        h = rj.simulate(params, ts=ts)
        whole[f"m = {m:.0f} kg"] = (h.ts, h.contact_force)
        h = rj.simulate(params, ts=ts_first)
        first[f"m = {m:.0f} kg"] = (h.ts, h.contact_force)
    figures.append(
        plot_series(
            whole,
            out / "fig7_contact_force_gap0.png",
            xlabel="time (s)",
            ylabel="contact force $F_{ct}$ (kN)",
            yscale=1e-3,
            title="Fig. 7: contact force, gap = 0",
        )
    )
    figures.append(
        plot_series(
            first,
            out / "fig8_contact_force_gap0_first_impact.png",
            xlabel="time (ms)",
            ylabel="contact force $F_{ct}$ (kN)",
            xscale=1e3,
            yscale=1e-3,
            title="Fig. 8: contact force, gap = 0, first impact",
        )
    )
    proposed = rj.params_from_values(m=1500.0, gap=0.062)
    h_best = rj.simulate(proposed, ts=ts)
    figures.append(
        plot_series(
            {
                "simplified model": (history.ts, history.anchoring_force),
                "with absorber m = 1500 kg, gap = 62 mm": (h_best.ts, h_best.anchoring_force),
            },
            out / "fig9_anchoring_force.png",
            xlabel="time (s)",
            ylabel="anchoring force $F_{AN}$ (kN)",
            yscale=1e-3,
            title="Fig. 9: anchoring force",
            mark=(
                float(best.peak_anchoring_force_time),
                float(best.peak_anchoring_force),
                f"{float(best.peak_anchoring_force):.0f} N",
            ),
        )
    )
    if log:
        for path in figures[1:]:
            log(f"  wrote {path}")
    return figures
