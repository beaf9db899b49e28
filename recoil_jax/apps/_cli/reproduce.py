"""`recoil-jax reproduce`: the paper's numbers beside ours, and the paper's figures."""

from __future__ import annotations

import csv
import sys
from pathlib import Path

import recoil_jax as rj
import recoil_jax.extend as rjx

from .._files.inputs import output_folder
from .._files.options import Commands

__all__ = [
    "add_command",
    "comparison_rows",
    "format_table",
    "reproduce",
    "run_reproduce",
]

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


def reproduce(out, log=None) -> list[dict]:
    """Compute the comparison, write `out/reproduce.csv` and the figures; return rows."""
    log = log or (lambda msg: print(msg, file=sys.stderr, flush=True))
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    log(f"reproducing {len(rj.paper_cases())} paper cases (default smoothed model)")
    rows = comparison_rows(log)
    with rjx.written(out / "reproduce.csv") as temporary, open(temporary, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=_COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    log(f"  wrote {out / 'reproduce.csv'}")
    log("figures")
    from .._figures.paper import paper_figures  # matplotlib: only when drawing

    paper_figures(out, log)
    return rows


def run_reproduce(args) -> int:
    """Run `recoil-jax reproduce` with the parsed `args`; its exit status."""
    print(format_table(reproduce(output_folder(args.out))))
    return 0


def add_command(commands: Commands) -> None:
    """`recoil-jax reproduce`'s arguments."""
    rep = commands.add(
        "reproduce",
        run_reproduce,
        help="the paper's numbers beside ours, and its figures",
        description="Compare with the paper's Table 2 and text and the hard-switch "
        "reference; write reproduce.csv and Fig. 4, 7, 8, 9 as PNG.",
    )
    rep.add_argument("--out", default="results/reproduce", help="output folder")
