"""`recoil-jax simulate`: one design's peaks, its histories as a figure or a trace."""

from __future__ import annotations

import json
import sys

import recoil_jax as rj
import recoil_jax.extend as rjx

from .._files.describe import describe, used_parameters
from .._files.inputs import (
    check_figure_path,
    check_output_file,
    design_warnings,
    names,
    parse_assignments,
    warn,
)
from .._files.options import Commands, add_force_table, add_max_steps

__all__ = ["add_command", "run_simulate"]


def run_simulate(args) -> int:
    """Run `recoil-jax simulate` with the parsed `args`; its exit status."""
    import numpy as np

    values = parse_assignments(args.assignments)
    plot = check_figure_path(args.plot) if args.plot else None  # before the solve
    trace = check_output_file(args.csv, "--csv") if args.csv else None
    options = rj.SolverOptions(t1=values.pop("t1", None), max_steps=args.max_steps)
    params = rj.params_from_values(values)
    table = rj.ForceTable.from_csv(args.force_table) if args.force_table else None
    if table is not None:
        params = rj.with_table(params, table)
    t1 = float(rjx.end_time(params, options))  # refuses a load that does not fit
    warn(design_warnings(values | {"t1": options.t1}, table))
    smoothing = rj.Smoothing.exact() if args.hard else rj.Smoothing()
    # Checked here, not inside the program: a program that can raise holds a host
    # callback, and JAX does not keep those in the compilation cache.
    from .._files.exported import exported_peaks

    peaks = exported_peaks(params, smoothing, options)
    if not bool(np.all(peaks.status == rj.Status.ok)):
        print(f"recoil-jax: solver failed: {rjx.status_messages(peaks.status)[0]}", file=sys.stderr)
        return 1
    result = peaks.to_dict()
    hazards = rj.peaks_hazards(params, peaks)
    used = used_parameters(params, table, args.force_table)
    used["t1"] = t1
    if args.json:
        print(
            json.dumps(
                result
                | {
                    "hazards": hazards,
                    "model": "hard" if args.hard else "smoothed",
                    "parameters": used,
                }
            )
        )
    else:
        model = "simplified (no absorber)" if params.absorber is None else "with absorber"
        print(f"recoil-jax: {model}, {'hard' if args.hard else 'smoothed'} switches")
        numbers = {k: v for k, v in used.items() if k != "force_table"}
        print("  parameters: " + ", ".join(f"{k}={v:g}" for k, v in numbers.items()))
        if table is not None:
            t = used["force_table"]
            print(
                f"  force table: {t['file']}, {t['points']} points over {t['duration_s']:g} s, "
                f"impulse {t['impulse_N_s']:g} N s per round"
            )
        metrics = rj.METRICS
        rows = []
        # Without an absorber there is no contact and no stroke to print (zeros).
        absorber = params.absorber is not None
        shown = ("peak_displacement", "peak_anchoring_force")
        for name in shown + (("peak_contact_force",) if absorber else ()):
            m = metrics[name]
            digits = 6 if m.unit == "m" else 2
            rows.append(
                (
                    m.meaning,
                    f"{result[m.key]:.{digits}f} {m.unit}",
                    f"at {result[m.time_key]:.4f} s",
                )
            )
        low, high = metrics["min_stroke"], metrics["max_stroke"]
        if absorber:
            stroke = f"{result[low.key]:+.4f} .. {result[high.key]:+.4f} m"
            rows.append(("absorber stroke x_m - x_M", stroke, ""))
        rows.extend(_envelope_rows(result))
        rows.append(("solver steps", f"{result['num_steps']}", ""))
        for name, value, when in rows:
            print(f"  {name:28s} {value:>22s}  {when}")
        for hazard in hazards:
            print(f"  hazard {hazard['name']}: {hazard['sentence']}")
    if plot is None and trace is None:
        return 0
    history = rj.simulate(params, smoothing, options, ts=np.linspace(0.0, t1, 20001))
    if plot is not None:
        from .._figures.histories import plot_history

        path = plot_history(history, plot, title=describe(used))
        print(f"wrote {path}", file=sys.stderr)
    if trace is not None:
        print(f"wrote {rjx.Trace.of_history(history, params).to_csv(trace)}", file=sys.stderr)
    return 0


def add_command(commands: Commands) -> None:
    """`recoil-jax simulate`'s arguments."""
    sim = commands.add(
        "simulate",
        run_simulate,
        help="simulate one design and print its peaks",
        description="Simulate one design. Parameters as name=value (SI units): "
        + names()
        + ". m=0 gives the simplified model (no absorber).",
    )
    sim.add_argument("assignments", nargs="*", metavar="name=value")
    sim.add_argument("--hard", action="store_true", help="exact model with hard switches")
    sim.add_argument("--json", action="store_true", help="print one JSON object")
    sim.add_argument(
        "--plot", metavar="FILE.png", help="plot displacements and every force against time"
    )
    sim.add_argument(
        "--csv",
        metavar="FILE.csv",
        help="write the histories as a trace (20001 times over [0, t1]; header t,x_M,v_M,"
        "x_m,v_m,F_AN,F_ct, without x_m, v_m, F_ct for m=0), as calibrate and "
        "rj.read_trace read it",
    )
    add_force_table(sim)
    add_max_steps(sim)


def _envelope_rows(result: dict) -> list[tuple[str, str, str]]:
    """The firing envelope's metrics as rows of the summary (none without it)."""
    if result["returned"] is None:
        return []
    metrics = rj.METRICS
    if result["returned"]:
        back = f"{result[metrics['return_time'].key]:.4f} s"
        speed = f"{result[metrics['battery_speed'].key]:.4f} m/s"
        rows = [("back in battery (x_r + 1 mm)", back, f"at {speed}")]
    else:
        rows = [("back in battery (x_r + 1 mm)", "never, by t1", "")]
    rest = result[metrics["residual_displacement"].key]
    rows.append(("barrel from its rest at t1", f"{rest:+.6f} m", ""))
    for name in ("peak_pull_force", "peak_mount_load"):
        m = metrics[name]
        rows.append((m.meaning, f"{result[m.key]:.2f} N", f"at {result[m.time_key]:.4f} s"))
    margin = metrics["stability_margin"]
    if result[margin.key] is not None:
        rows.append(
            (margin.meaning, f"{result[margin.key]:.4f}", f"at {result[margin.time_key]:.4f} s")
        )
    return rows
