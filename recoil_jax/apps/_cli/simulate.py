"""`recoil-jax simulate`: one design's peaks, its histories as a figure or a trace."""

from __future__ import annotations

import json
import sys
from typing import Any

import recoil_jax as rj
import recoil_jax.extend as rjx

from .._files.describe import describe, used_parameters
from .._files.design_source import design_from_file
from .._files.inputs import (
    check_figure_path,
    check_output_file,
    design_warnings,
    names,
    parse_assignments,
    warn,
)
from .._files.options import Commands, add_force_table, add_json, add_max_steps

__all__ = ["MAX_TRACE_SAMPLES", "add_command", "run_simulate"]

#: The most samples a trace `simulate` writes may have (`--rate` × `--duration`).
MAX_TRACE_SAMPLES = 10_000_000
#: The signals only a design with an absorber has.
_ABSORBER_SIGNALS = ("x_m", "v_m", "F_ct")
#: Bare `--noise`: the file's noise.
_FILE_NOISE = "<the file's>"


def run_simulate(args) -> int:
    """Run `recoil-jax simulate` with the parsed `args`; its exit status."""
    import numpy as np

    values, source = _design_values(args)
    plot = check_figure_path(args.plot) if args.plot else None  # before the solve
    trace = check_output_file(args.csv, "--csv") if args.csv else None
    sampling = _sampling(args, source, values, trace)
    noise = _noise(args, source, trace)
    options = rj.SolverOptions(t1=values.pop("t1", None), max_steps=args.max_steps)
    params = rj.params_from_values(values)
    if params.absorber is None and (absent := [n for n in noise if n in _ABSORBER_SIGNALS]):
        raise rj.ParameterError(f"--noise {absent[0]}: a signal of the absorber, and this "
                                "design has none (m = 0)")  # fmt: skip
    table = rj.ForceTable.from_csv(args.force_table) if args.force_table else None
    if table is not None:
        params = rj.with_table(params, table)
    t1 = float(rjx.end_time(params, options))  # refuses a load that does not fit
    warn(design_warnings(values | {"t1": options.t1}, table))
    if args.hard:
        smoothing = rj.Smoothing.exact()
    else:
        smoothing = rj.Smoothing()
    peaks = rj.peaks(params, smoothing, options, throw=False)  # its status said below
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
        _print_peaks(result, hazards, used, params, table, args.hard)
    if plot is None and trace is None:
        return 0
    history = rj.simulate(params, smoothing, options, ts=np.linspace(0.0, t1, 20001))
    if plot is not None:
        from .._figures.histories import plot_history

        path = plot_history(history, plot, title=describe(used))
        print(f"wrote {path}", file=sys.stderr)
    if trace is not None:
        if sampling is not None:  # the trace on the recorder's own times
            history = rj.simulate(params, smoothing, options, ts=sampling)
        print(f"wrote {_trace(history, params, noise, args.seed).to_csv(trace)}", file=sys.stderr)
    return 0


def _design_values(args) -> tuple[dict, Any]:
    """The design's flat values: from `--from` (a study, calibration or plan file, its
    `--experiment`), the command line's assignments winning; and the file's design
    (None without one)."""
    values = parse_assignments(args.assignments)
    if args.source is None:
        if args.experiment is not None:
            raise rj.ParameterError("--experiment picks one of a file's: give the file with --from")
        return values, None
    source = design_from_file(args.source, args.experiment)
    missing = [n for n in source.required if n not in values]
    if missing:
        raise rj.ParameterError(
            f"{source.label}: the study tunes {', '.join(missing)}; give "
            + " ".join(f"{n}=..." for n in missing)
            + " (its result.json's best design, or any you want to see)"
        )
    return source.values | values, source  # the command line's win


def _print_peaks(result: dict, hazards: list, used: dict, params, table, hard: bool):
    """The text report of one design's peaks: the model, the parameters used, each
    metric with its time, and the hazards."""
    model = "simplified (no absorber)" if params.absorber is None else "with absorber"
    switches = "hard" if hard else "smoothed"
    print(f"recoil-jax: {model}, {switches} switches")
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


def _sampling(args, source, values: dict, trace):
    """The trace's sample times, `1/rate, 2/rate, …` up to the duration (as a plan's),
    from `--rate`/`--duration` or the plan file's sampling; None: 20,001 times over
    `[0, t1]`. Sets `t1` to the duration where none is given. Checked before any solve."""
    import numpy as np

    rate = args.rate if args.rate is not None else (source.rate if source else None)
    duration = args.duration if args.duration is not None else (source.duration if source else None)
    if args.rate is None and args.duration is None and (source is None or source.rate is None):
        return None
    if trace is None:
        raise rj.ParameterError("--rate and --duration shape the trace: give --csv FILE.csv")
    if rate is None:
        raise rj.ParameterError("--duration: give the sample rate too (--rate, samples per s)")
    if not (np.isfinite(rate) and 0 < rate <= 1e6):
        raise rj.ParameterError(f"--rate {rate:g}: valid > 0 and <= 1e6 samples per second")
    duration = duration if duration is not None else values.get("t1")
    if duration is None:
        raise rj.ParameterError("--rate: give the duration recorded too (--duration, s)")
    if not (np.isfinite(duration) and duration > 0):
        raise rj.ParameterError(f"--duration {duration:g}: valid > 0 s")
    samples = int(np.floor(rate * duration + 1e-9))
    if not 1 <= samples <= MAX_TRACE_SAMPLES:
        raise rj.ParameterError(
            f"--rate {rate:g} over --duration {duration:g} s is {samples:,} samples: valid "
            f"1 to {MAX_TRACE_SAMPLES:,}"
        )
    t1 = values.setdefault("t1", float(duration))
    if duration > t1:
        raise rj.ParameterError(
            f"--duration {duration:g} s is past t1 = {t1:g} s: give t1={duration:g} or a "
            "shorter duration"
        )
    return np.arange(1, samples + 1) / rate


def _noise(args, source, trace) -> dict[str, float]:
    """`--noise x_M=3e-4,F_AN=300` as signal → standard deviation; bare `--noise`, the
    file's noise (a calibration experiment's `sigma`, a plan's signals). Checked before
    any solve."""
    if args.noise is None:
        return {}
    if trace is None:
        raise rj.ParameterError("--noise is for the trace: give --csv FILE.csv")
    if args.noise == _FILE_NOISE:
        if source is None or not source.sigma:
            raise rj.ParameterError(
                "--noise without values takes the file's noise: give --from a calibration "
                "or plan file, or the noise as --noise x_M=3e-4,F_AN=300"
            )
        return dict(source.sigma)
    noise = {}
    for item in args.noise.split(","):
        name, _, text = item.partition("=")
        signal = rjx.SIGNALS.get(name.strip()) and name.strip()
        if not signal:
            raise rj.ParameterError(
                f"--noise {item!r}: {name.strip()!r} is not a signal; valid "
                + ", ".join(rjx.SIGNALS)
            )
        try:
            value = float(text)
        except ValueError:
            raise rj.ParameterError(
                f"--noise {item!r}: give signal=deviation, e.g. x_M=3e-4"
            ) from None
        if not (value >= 0 and value < float("inf")):
            raise rj.ParameterError(f"--noise {item!r}: the deviation must be >= 0 and finite")
        noise[signal] = value
    return noise


def _trace(history, params, noise: dict[str, float], seed: int):
    """The history as a trace: every signal, or with `noise` only those signals, each
    with Gaussian noise of its deviation (seeded): what a recorder of them would give."""
    import numpy as np

    full = rjx.Trace.of_history(history, params)
    if not noise:
        return full
    rng = np.random.default_rng(seed)
    noisy = {s: np.asarray(full.signals[s]) + sigma * rng.standard_normal(full.t.size)
             for s, sigma in noise.items()}  # fmt: skip
    return rjx.Trace.of(full.t, source="simulate", **noisy)


def add_command(commands: Commands) -> None:
    """`recoil-jax simulate`'s arguments."""
    sim = commands.add(
        "simulate",
        run_simulate,
        help="simulate one design and print its peaks",
        description="Simulate one design. Parameters as name=value (SI units; elevation "
        "in degrees): " + names() + ". m=0 gives the simplified model (no absorber).",
    )
    sim.add_argument("assignments", nargs="*", metavar="name=value")
    sim.add_argument("--hard", action="store_true", help="exact model with hard switches")
    add_json(sim, "one JSON object")
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
        "--from", dest="source", metavar="FILE.toml",
        help="take the design from a calibration file (its [design], each fitted value's "
        "start, one [[experiment]]'s values), a study file ([design] and one "
        "[[condition]]; give the tuned values) or a plan file ([design] and one candidate "
        "firing, its sampling); name=value items win",
    )  # fmt: skip
    sim.add_argument(
        "--experiment", metavar="N|NAME",
        help="with --from: which experiment, condition or candidate (a number from 1, or "
        "its name or trace)",
    )  # fmt: skip
    sim.add_argument("--rate", type=float, metavar="HZ",
                     help="with --csv: samples per second (times 1/rate, 2/rate, ... as a "
                     "plan's)")  # fmt: skip
    sim.add_argument("--duration", type=float, metavar="S",
                     help="with --csv: seconds recorded (default t1; sets t1 where not "
                     "given)")  # fmt: skip
    sim.add_argument(
        "--noise", nargs="?", const=_FILE_NOISE, metavar="SIGNAL=SIGMA,...",
        help="with --csv: write only these signals, each with Gaussian noise of this "
        "deviation (e.g. x_M=3e-4,F_AN=300); bare, the file's noise (--from a "
        "calibration experiment's sigma, a plan's signals)",
    )  # fmt: skip
    sim.add_argument("--seed", type=int, default=0, help="with --noise: the noise's seed")
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
