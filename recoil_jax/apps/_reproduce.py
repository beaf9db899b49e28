"""`recoil-jax reproduce`: the paper's numbers beside ours, and the paper's figures."""

from __future__ import annotations

import csv
import sys
from pathlib import Path

import numpy as np

import recoil_jax as rj
import recoil_jax.extend as rjx

from ._figures import plot_series

__all__ = ["comparison_rows", "format_table", "reproduce", "write_figures"]

_COLUMNS = ["case", "quantity", "paper", "reference", "ours", "ours_vs_paper", "ours_vs_reference"]


def _relative(ours: float, other: float | None) -> float | None:
    if other is None:
        return None
    if other == 0:
        return 0.0 if ours == 0 else None
    return (ours - other) / abs(other)


def comparison_rows(log=None) -> list[dict]:
    """One row per (case, quantity): paper value (or None), reference value, ours
    (default smoothed model) and the relative differences. Quantities are the JSON keys
    (`PEAK_FIELDS`) the reference gives."""
    rows = []
    for case in rj.paper_cases():
        ours = rj.peaks(rj.case_params(case)).to_dict()
        if log:
            log(f"  {case['case']}: peak F_AN {ours['peak_anchoring_force_N']:.1f} N")
        quantities = [key for key in rjx.PEAK_FIELDS.values() if key in case["reference"]]
        for quantity in quantities:
            paper = case["paper"].get(quantity)
            reference = case["reference"].get(quantity)
            rows.append(
                {
                    "case": case["case"],
                    "quantity": quantity,
                    "paper": paper,
                    "reference": reference,
                    "ours": ours[quantity],
                    "ours_vs_paper": _relative(ours[quantity], paper),
                    "ours_vs_reference": _relative(ours[quantity], reference),
                }
            )
    return rows


def format_table(rows: list[dict]) -> str:
    def num(x, style="g"):
        if x is None:
            return "-"
        return {"g": f"{x:.6g}", "pct": f"{100 * x:+.3f} %", "e": f"{x:+.1e}"}[style]

    header = (
        f"{'case':24s} {'quantity':28s} {'paper':>10s} {'reference':>12s} {'ours':>12s}"
        f" {'vs paper':>10s} {'vs reference':>13s}"
    )
    lines = [header, "-" * len(header)]
    for r in rows:
        lines.append(
            f"{r['case']:24s} {r['quantity']:28s} {num(r['paper']):>10s} "
            f"{num(r['reference']):>12s} {num(r['ours']):>12s} "
            f"{num(r['ours_vs_paper'], 'pct'):>10s} {num(r['ours_vs_reference'], 'e'):>13s}"
        )
    return "\n".join(lines)


def write_figures(out: Path, log=None) -> list[Path]:
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


def reproduce(out, log=None) -> list[dict]:
    """Compute the comparison, write `out/reproduce.csv` and the figures; return rows."""
    log = log or (lambda msg: print(msg, file=sys.stderr, flush=True))
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    log(f"reproducing {len(rj.paper_cases())} paper cases (default smoothed model)")
    rows = comparison_rows(log)
    with open(out / "reproduce.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=_COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    log(f"  wrote {out / 'reproduce.csv'}")
    log("figures")
    write_figures(out, log)
    return rows
