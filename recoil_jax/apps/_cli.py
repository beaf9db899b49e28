"""The `recoil-jax` command line: argument parsing, the `simulate` command, and dispatch
to the other commands (each in its own module, imported when used)."""

from __future__ import annotations

import argparse
import json
import os
import sys

import recoil_jax as rj
import recoil_jax.extend as rjx

from ._boundary import INTERRUPTED, run_command
from ._inputs import (
    MADE_FOLDERS,
    check_figure_path,
    check_output_file,
    design_warnings,
    names,
    output_folder,
    parse_assignments,
    remove_unused_folders,
    results_folder,
    warn,
)
from ._json import dumps as json_dumps

__all__ = ["INFEASIBLE", "INTERRUPTED", "build_parser", "describe", "main"]

#: The exit status of `optimise` when no design met every limit (0 done, 1 a solve
#: failed, 2 bad input).
INFEASIBLE = 3


def _simulate(args) -> int:
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
    from ._exported import exported_peaks

    peaks = exported_peaks(params, smoothing, options)
    if not bool(np.all(peaks.status == rj.Status.ok)):
        print(f"recoil-jax: solver failed: {rjx.status_messages(peaks.status)[0]}", file=sys.stderr)
        return 1
    result = peaks.to_dict()
    used = used_parameters(params, table, args.force_table)
    used["t1"] = t1
    if args.json:
        print(
            json.dumps(result | {"model": "hard" if args.hard else "smoothed", "parameters": used})
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
        rows.append(("solver steps", f"{result['num_steps']}", ""))
        for name, value, when in rows:
            print(f"  {name:28s} {value:>22s}  {when}")
    if plot is None and trace is None:
        return 0
    history = rj.simulate(params, smoothing, options, ts=np.linspace(0.0, t1, 20001))
    if plot is not None:
        from ._figures import plot_history

        path = plot_history(history, plot, title=describe(used))
        print(f"wrote {path}", file=sys.stderr)
    if trace is not None:
        print(f"wrote {rjx.Trace.of_history(history, params).to_csv(trace)}", file=sys.stderr)
    return 0


def used_parameters(params: rj.RecoilParams, table=None, source=None) -> dict:
    """The parameters a solve of `params` uses, by flat name (integers as integers); with a
    force `table` (read from `source`) the table's summary replaces `v0` and
    `pulse_time`, which it makes unused."""
    import numpy as np

    used: dict = {}
    for name, value in rj.params_to_values(params).items():
        if table is not None and name in ("v0", "pulse_time"):
            continue
        number = float(np.asarray(value))
        integer = name in rj.PARAMETERS and rj.PARAMETERS[name].integer
        used[name] = int(number) if integer else number
    if table is not None:
        t, F = np.asarray(table.t, dtype=float), np.asarray(table.F, dtype=float)
        used["force_table"] = {
            "file": str(source),
            "points": int(t.size),
            "duration_s": float(t[-1]),
            "impulse_N_s": float(np.sum(0.5 * (F[1:] + F[:-1]) * np.diff(t))),
        }
    return used


def describe(values: dict) -> str:
    """A one-line description of a design, for figure titles."""
    parts = []
    if values.get("m", 0.0) > 0:
        parts.append(f"absorber m={values['m']:g} kg, gap={1e3 * values['gap']:g} mm")
    else:
        parts.append("no absorber")
    if "shots" in values:
        shots = int(values["shots"])
        if "force_table" in values:
            load = "the force table"
        elif values.get("pulse_time"):
            load = f"a {values['pulse_time'] * 1e3:g} ms pulse"
        else:
            load = "an impulse"
        rounds = f"1 round of {load}" if shots == 1 else f"{shots} rounds of {load}"
        every = f" every {values['fire_interval']:g} s" if shots > 1 else ""
        parts.append(rounds + every)
    knots = sum(1 for name in values if name.startswith("orifice_") and name[8:].isdigit())
    if knots and values.get("piston_area", 0.0) > 0:
        parts.append(f"{knots}-knot orifice")
    if values.get("recuperator_force", 0.0) > 0:
        parts.append(f"recuperator {values['recuperator_force']:g} N")
    return ", ".join(parts)


def _reproduce(args) -> int:
    from ._reproduce import format_table, reproduce

    print(format_table(reproduce(output_folder(args.out))))
    return 0


def _progress(args) -> int:
    progress = rj.campaign_progress(args.store)
    if args.json:  # unknown figures (NaN) as null
        known = {k: None if v != v else v for k, v in progress._asdict().items()}
        print(json.dumps(known))
    else:
        print(f"{args.store}: {progress.line()}")
    return 0


def _sweep(args) -> int:
    from ._sweep import run_sweep

    return run_sweep(args)


def _optimise(args) -> int:
    from ._studies import run_study, study_summary

    report = run_study(
        args.study,
        args.out,
        progress=True,
        seed=args.seed,
        store=args.store,
        workers=args.workers,
        scheduler=args.scheduler,
    )
    if args.json:
        print(json_dumps(report))
    if not report["feasible"]:
        print(f"recoil-jax: infeasible: {report['message']}", file=sys.stderr)
        return INFEASIBLE
    if not args.json:
        print(study_summary(report))
    return 0


def _calibrate(args) -> int:
    from ._calibration import run_calibration

    args.out = results_folder(args.out, "calibrate", args.source)
    return run_calibration(args)


def _sensitivity(args) -> int:
    from ._sensitivity import run_sensitivity

    return run_sensitivity(args)


def _explore(args) -> int:
    from ._explore import main_explore

    return main_explore(args, parse_assignments(args.assignments))


def _bench_tuning(args) -> int:
    from ._bench_tuning import main_tuning_bench

    return main_tuning_bench(args)


def _bench_store(args) -> int:
    from ._bench_store import main_store_bench

    return main_store_bench(args)


def _bench_calibration(args) -> int:
    from ._bench_calibration import main_calibration_bench

    return main_calibration_bench(args)


def _bench_sensitivity(args) -> int:
    from ._bench_sensitivity import main_sensitivity_bench

    return main_sensitivity_bench(args)


def _bench(args) -> int:
    from ._bench import main_bench

    return main_bench(args)


def _add_max_steps(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--max-steps",
        type=int,
        default=rj.SolverOptions().max_steps,
        metavar="N",
        help="most solver steps per design (default %(default)s); a solve that needs more "
        "fails with status max_steps",
    )


class _Parser(argparse.ArgumentParser):
    """argparse's parser, whose errors (an unknown option, `--starts x`) are one line like
    every other refusal: `recoil-jax: error: ...`, status 2 (its subcommands' parsers are
    of this class too)."""

    def error(self, message: str):  # pyright: ignore[reportIncompatibleMethodOverride]
        command = self.prog.removeprefix("recoil-jax").strip()
        where = f"{command}: " if command else ""
        self.exit(2, f"recoil-jax: error: {where}{message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="recoil-jax",
        description="Differentiable recoil-system models: gun barrel with an impact absorber.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {rj.__version__}")
    # Every command takes --no-cache.
    common = _Parser(add_help=False)
    common.add_argument(
        "--no-cache",
        action="store_true",
        help="do not keep compiled programs on disk (default: kept in "
        "$RECOIL_JAX_CACHE or ~/.cache/recoil-jax/jax, so a repeated command does not "
        "compile again; RECOIL_JAX_CACHE=off also turns it off; the benchmarks never use "
        "it)",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    sim = sub.add_parser(
        "simulate",
        parents=[common],
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
    sim.add_argument(
        "--force-table", metavar="FILE.csv", help="breech force of one round (header t_s,F_N)"
    )
    _add_max_steps(sim)
    sim.set_defaults(func=_simulate)
    swp = sub.add_parser(
        "sweep",
        parents=[common],
        help="peaks over a grid or a list of designs",
        description="Sweep designs: name=a,b,c (a list), name=start:stop:count (a range, "
        "inclusive) or name=value (fixed), over the cartesian grid of the swept names; "
        "or --points FILE (CSV with a header of names, or a JSON list of objects). "
        "Names: " + names() + ". m=0 (no absorber) may be mixed with m > 0. "
        "Writes sweep.csv, sweep.npz (arrays + metadata) and figures to --out.",
    )
    swp.add_argument("assignments", nargs="*", metavar="name=values")
    swp.add_argument("--points", metavar="FILE", help="designs from CSV or JSON")
    swp.add_argument(
        "--json",
        action="store_true",
        help="print a JSON list, in input order (keys as simulate --json + status)",
    )
    swp.add_argument("--out", metavar="DIR", help="folder for sweep.csv, sweep.npz, figures")
    swp.add_argument(
        "--force-table", metavar="FILE.csv", help="breech force of one round (header t_s,F_N)"
    )
    swp.add_argument(
        "--store",
        metavar="FILE.sqlite",
        help="commit each finished chunk to this SQLite file; the same command with the "
        "same store resumes a stopped sweep (docs/campaigns.md)",
    )
    swp.add_argument(
        "--workers",
        type=int,
        metavar="N",
        help="run the chunks on a local Dask cluster of N worker processes",
    )
    swp.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="run the chunks on the running Dask cluster at ADDRESS (tcp://host:8786)",
    )
    _add_max_steps(swp)
    swp.set_defaults(func=_sweep)
    prog = sub.add_parser(
        "progress",
        parents=[common],
        help="where a campaign stands, from its store",
        description="Read a store (sweep --store) while its campaign runs or after it "
        "stopped: designs done of the total, runs, the rate of the latest run and the time "
        "left.",
    )
    prog.add_argument("store", metavar="FILE.sqlite", help="the store")
    prog.add_argument("--json", action="store_true", help="print one JSON object")
    prog.set_defaults(func=_progress)
    bench = sub.add_parser(
        "bench",
        parents=[common],
        help="throughput and Jacobians/s against a compiled scalar loop and scipy",
        description="Solves/s of sweeps of 1, 64, 1024 and 16384 random absorber designs; "
        "a compiled scalar loop (numba, one core, the same smoothed model and step-size "
        "rule, the bench extra) on the 16384 designs, and its lead per step and per design; "
        "4-parameter Jacobians/s; the hardware designs; compile times; scipy's solve_ivp "
        "(DOP853 at rtol 1e-6, the hard-switch model with events, one core) on the same "
        "peaks, and the largest relative difference from it. About 3 minutes on 2 cores. "
        "--full adds the cost of a gradient by forward sensitivities and by reverse mode "
        "for 1 to 22 parameters, and the first and second run of simulate, sweep and "
        "optimise (the compilation cache): about 10 minutes more.",
    )
    bench.add_argument("--json", action="store_true", help="print one JSON object")
    bench.add_argument("--quick", action="store_true", help="small batches (a smoke run)")
    bench.add_argument(
        "--full", action="store_true", help="add the gradient modes and the CLI cache timings"
    )
    bench.set_defaults(func=_bench)
    store_bench = sub.add_parser(
        "bench-store",
        parents=[common],
        help="what a store and a Dask cluster cost a sweep: time, memory, disk",
        description="Sweep random absorber designs in several ways, each in a fresh process "
        "(compiled on one chunk first, not timed): plain (no store), store (results kept "
        "in memory and stored), stream (results only in the store: rj.sweep_to_store) and "
        "cluster (streamed, on a local Dask cluster of 2 workers). Prints seconds, "
        "designs/s, the peak memory of the process that sweeps, the overheads against "
        "plain and a store's size on disk.",
    )
    store_bench.add_argument(
        "--ways",
        metavar="W,W",
        help="which ways, comma-separated (default plain,store,stream,cluster)",
    )
    store_bench.add_argument(
        "--designs", type=int, default=1_000_000, metavar="N", help="designs (default 1000000)"
    )
    store_bench.add_argument("--json", action="store_true", help="print one JSON object")
    store_bench.set_defaults(func=_bench_store)
    opt = sub.add_parser(
        "optimise",
        parents=[common],
        help="run an optimisation study (optimise/<study>.toml)",
        description='Tune design parameters as the study file says (method "search": '
        'global samples, then SLSQP with exact gradients; "adam": optax from many '
        "starts); write result.json, convergence.png, best_history.png (and front/robust "
        "figures). STUDY is a path, or the name of a study shipped in optimise/ (e.g. "
        "paper_gap). Exit status: 0 done, 1 a solve failed, 2 bad input, 3 no design met "
        "every limit (result.json then has feasible: false, best: null and the closest "
        "design with the limits it misses).",
    )
    opt.add_argument("study", help="study file or name, e.g. optimise/paper_gap.toml")
    opt.add_argument("--out", help="output folder (default results/<study name>)")
    opt.add_argument("--json", action="store_true", help="print result.json to stdout")
    opt.add_argument(
        "--seed",
        type=int,
        metavar="N",
        help="seed of the optimiser's samples and starts (default: the study's, else 0)",
    )
    opt.add_argument(
        "--store",
        metavar="FILE.sqlite",
        help="commit every evaluation of the optimiser to this SQLite file; the same "
        "command with the same store resumes a stopped study (docs/campaigns.md)",
    )
    opt.add_argument(
        "--workers",
        type=int,
        metavar="N",
        help='run the global phase (method "search") on a local Dask cluster of N worker processes',
    )
    opt.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help='run the global phase (method "search") on the running Dask cluster at ADDRESS',
    )
    opt.set_defaults(func=_optimise)
    tuning = sub.add_parser(
        "bench-tuning",
        parents=[common],
        help="our optimiser against Nelder-Mead, differential evolution and CMA-ES",
        description="On each problem (shipped studies; default tuned_absorber, "
        "tuned_absorber_global, throttling, burst, burst_recuperator), run recoil-jax's "
        "search and, with the same solver and wall-time budget, scipy's Nelder-Mead "
        "(multistart), scipy's differential_evolution (vectorized, batches through the "
        "sweep) and CMA-ES (cmaes, batches through the sweep). Reports the best feasible "
        "objective, solves, and wall seconds to within 0.1 % of the best known value.",
    )
    tuning.add_argument(
        "problems", nargs="*", help="shipped study names (default: all five problems)"
    )
    tuning.add_argument("--json", action="store_true", help="print one JSON object")
    tuning.add_argument("--seed", type=int, default=0, help="seed of every method (default 0)")
    tuning.add_argument(
        "--seeds",
        type=int,
        metavar="K",
        help="run every method from seeds 0..K-1 (replaces --seed) and report, per "
        "method, how many reach the target and the median and worst time to it, cold and "
        "warm; the speedup is of the medians",
    )
    tuning.add_argument(
        "--budget-scale",
        type=float,
        default=1.0,
        help="multiply every problem's wall-time budget (default 1)",
    )
    tuning.add_argument(
        "--methods",
        nargs="+",
        metavar="METHOD",
        help="the methods to run: recoil-jax, nelder_mead, differential_evolution, "
        "cma_es (default: all four)",
    )
    tuning.add_argument("--out", help="folder for the convergence figures (default: none)")
    tuning.add_argument(
        "--workers",
        type=int,
        metavar="N",
        help="run every batch of plain solves on a local Dask cluster of N worker processes",
    )
    tuning.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="run every batch of plain solves on the running Dask cluster at ADDRESS",
    )
    tuning.set_defaults(func=_bench_tuning)
    calibrate = sub.add_parser(
        "calibrate",
        parents=[common],
        help="fit the model to measured firing traces",
        description="Fit parameters to measured traces: a calibration file (TOML: "
        "[design], [fit], [[experiment]]), or one trace (CSV: t and signal columns) with "
        "--fit. Writes result.json (values, standard errors, 95% intervals, "
        "correlation, identifiability, chi2, AIC, BIC), fit.png and correlation.png. "
        "Exit 0 fitted, 1 a solve failed, 2 bad input, 4 the fit did not converge, 5 the "
        "model does not explain the traces (residuals far above the traces' own noise, "
        "or far from white).",
    )
    calibrate.add_argument("source", help="a calibration file (.toml) or a trace (.csv)")
    calibrate.add_argument("assignments", nargs="*", metavar="name=value",
                           help="known values, with a trace (e.g. v0=0.69)")  # fmt: skip
    calibrate.add_argument(
        "--fit",
        metavar="NAMES",
        help="with a trace: the parameters to fit, comma-separated (bounds: each one's "
        "documented range; t_shift: the trigger delay, -0.01 to 0.01 s)",
    )
    calibrate.add_argument(
        "--out", help="output folder (default results/calibrate/<file name, no suffix>)"
    )
    calibrate.add_argument(
        "--starts", type=int, metavar="N", help="fit from N starts (the given, then Sobol)"
    )
    calibrate.add_argument(
        "--validate",
        action="append",
        metavar="TRACE",
        help="a trace to score the fit on, not fitted (repeatable)",
    )
    calibrate.add_argument(
        "--profile",
        action="store_true",
        help="also profile-likelihood intervals: each value held at 12 points while the "
        "others are refitted (profiles.png)",
    )
    calibrate.add_argument(
        "--predict",
        nargs="*",
        metavar="name=value",
        help="then predict this design's peaks with 95%% bands from the fitted "
        "uncertainty (10,000 samples and linear propagation; prediction.png)",
    )
    calibrate.add_argument(
        "--store",
        metavar="FILE.sqlite",
        help="commit each finished part of the fit (8 starts, the profiles) to this "
        "SQLite file; the same command with the same store resumes a stopped calibration",
    )
    calibrate.add_argument(
        "--force-table",
        metavar="FILE.csv",
        help="with a trace: the breech force of one round it fired (header t_s,F_N)",
    )
    calibrate.add_argument("--json", action="store_true", help="print result.json")
    _add_max_steps(calibrate)
    calibrate.set_defaults(func=_calibrate)
    sens = sub.add_parser(
        "sensitivity",
        parents=[common],
        help="global sensitivity: which tolerances move the peaks",
        description="Sample the parameters over their ranges (a TOML file: [design], "
        "[ranges], [metrics], [method]; or a shipped example's name: "
        "paper_absorber, throttling), solve every design through the sweep and rank "
        "the parameters: Sobol first-order and total indices (SALib), Morris "
        "elementary effects, or DGSM from exact gradients, each with bootstrap 95% "
        "intervals. Writes result.json, samples.csv, indices.png, scatter.png (and "
        "morris.png). Failed solves are counted, and the indices say how many designs "
        "they rest on. Exit 0 done, 1 no design group solved, 2 bad input.",
    )
    sens.add_argument("source", help="a sensitivity file (.toml) or a shipped example's name")
    sens.add_argument(
        "--out", help="output folder (default results/sensitivity/<example or file name>)"
    )
    sens.add_argument("--json", action="store_true", help="print result.json")
    sens.add_argument(
        "--store",
        metavar="FILE.sqlite",
        help="keep every design's result in this SQLite file; the same command resumes "
        "a stopped run (docs/campaigns.md)",
    )
    sens.add_argument(
        "--workers", type=int, metavar="N", help="solve on a local Dask cluster of N processes"
    )
    sens.add_argument(
        "--scheduler", metavar="ADDRESS", help="solve on the running Dask cluster at ADDRESS"
    )
    _add_max_steps(sens)
    sens.set_defaults(func=_sensitivity)
    calibration_bench = sub.add_parser(
        "bench-calibration",
        parents=[common],
        help="calibration against scipy least_squares on solve_ivp",
        description="On synthetic firing tests made by the independent scipy solver with "
        "noise, compare recoil-jax's calibration with scipy's least_squares (finite "
        "differences) on solve_ivp DOP853 with events: one fit, 100 fits (noise draws), "
        "the fraction of 20 random starts reaching the best (absorber and 3-round burst "
        "traces), the prediction band's time and the command line cold and cached.",
    )
    calibration_bench.add_argument("--quick", action="store_true", help="small sizes")
    calibration_bench.add_argument(
        "--burst-seeds",
        type=int,
        default=0,
        metavar="K",
        help="also the burst's random starts from K more traces and sets of starts",
    )
    calibration_bench.add_argument("--json", action="store_true", help="print JSON")
    calibration_bench.set_defaults(func=_bench_calibration)
    sensitivity_bench = sub.add_parser(
        "bench-sensitivity",
        parents=[common],
        help="global sensitivity against SALib on a scipy solve_ivp loop",
        description="On the paper's absorber (sensitivity/paper_absorber.toml, 8 "
        "parameters): Sobol indices with second order from 2^12 base samples (73,728 "
        "designs) and DGSM from exact gradients on 4,096 designs, cold and warm; SALib's "
        "finite-difference DGSM on the same points through the sweep; and the scipy "
        "solve_ivp loop a SALib user writes (one process per core) on a slice of the "
        "same designs, its time for all of them and how far its peaks are from ours.",
    )
    sensitivity_bench.add_argument("--quick", action="store_true", help="small sizes")
    sensitivity_bench.add_argument("--json", action="store_true", help="print JSON")
    sensitivity_bench.set_defaults(func=_bench_sensitivity)
    explore = sub.add_parser(
        "explore",
        parents=[common],
        help="a live design explorer in the browser",
        description="Serve the design explorer: a number field for every parameter, "
        "the displacements and forces against time, the peaks against their limits and "
        "the gradient of the peak anchoring force, updated as you type. Optional "
        "name=value items set the starting design.",
    )
    explore.add_argument("assignments", nargs="*", metavar="name=value")
    explore.add_argument("--port", type=int, default=5006, help="port (default 5006)")
    explore.add_argument("--address", default="localhost", help="address (default localhost)")
    explore.add_argument("--no-browser", action="store_true", help="do not open a browser tab")
    explore.add_argument(
        "--trace", metavar="CSV", help="a measured trace to show over the histories (points)"
    )
    explore.set_defaults(func=_explore)
    rep = sub.add_parser(
        "reproduce",
        parents=[common],
        help="the paper's numbers beside ours, and its figures",
        description="Compare with the paper's Table 2 and text and the hard-switch "
        "reference; write reproduce.csv and Fig. 4, 7, 8, 9 as PNG.",
    )
    rep.add_argument("--out", default="results/reproduce", help="output folder")
    rep.set_defaults(func=_reproduce)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command line with `argv` (default `sys.argv[1:]`); returns the exit code:
    0 done, 1 a solve failed (or the disk, the pipe or a store failed the run), 2 bad
    input, 3 (`optimise`) no design met every limit, 4 (`calibrate`) the fit did not
    converge, 5 (`calibrate`) the model does not explain the traces, 130 interrupted
    (Ctrl-C). An output folder the command made and left
    empty is removed when it does not succeed."""
    rj.use_avx2_codegen()  # before any computation: the flag is read as the backend starts
    parser = build_parser()
    # name=value items may come after the flags (`simulate m=500 --hard t1=2`).
    args, extra = parser.parse_known_args(argv)
    if extra:
        if args.command not in ("simulate", "sweep", "explore", "calibrate") or any(
            item.startswith("-") for item in extra
        ):
            parser.error(f"unrecognized arguments: {' '.join(extra)}")
        args.assignments = list(args.assignments) + extra
    # The benchmarks measure compilation among other things: they never load from disk.
    if not args.no_cache and not args.command.startswith("bench"):
        try:
            rj.enable_compilation_cache()
        except OSError as error:  # RECOIL_JAX_CACHE naming a file, or under /proc
            folder = error.filename or os.environ.get("RECOIL_JAX_CACHE", "")
            print(f"recoil-jax: warning: the compilation cache {folder} cannot be used "
                  f"({error.strerror}); running without it", file=sys.stderr)  # fmt: skip
    MADE_FOLDERS.clear()  # this command's folders only (main may run many times)
    status = 1
    try:
        status = run_command(args)
    finally:
        if status != 0:
            remove_unused_folders()
    return status


if __name__ == "__main__":
    sys.exit(main())
