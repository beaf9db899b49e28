"""`recoil-jax bench-calibration`: our calibration against the fit a Python engineer
writes (scipy `least_squares` with a finite-difference Jacobian on `solve_ivp` DOP853,
the switches and the contact as events), on synthetic firing tests made by that same
independent solver with noise.

Measured, side by side in one run: one 5-parameter fit (warm); many fits (noise draws:
ours as one batch, scipy looping); the fraction of random starts that reach the best
(both from the same points); the prediction band; how often the model check flags a
wrong model and a right one (`model_check_rates`); the command line cold and cached.
Speed is reported, never asserted.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import scipy.optimize

import recoil_jax as rj
import recoil_jax.extend as rjx

from .._files.options import Commands, add_json
from .firing import BOX, NOISE, calibration_of, firing_test
from .speed import host_description

__all__ = [
    "add_command",
    "format_calibration_bench",
    "main_calibration_bench",
    "run_calibration_bench",
]

#: The burst test: three rounds, half a second apart.
BURST = {"shots": 3.0, "fire_interval": 0.5}
#: The scipy way's solver settings: the reference solver's DOP853 with events, at a
#: tolerance whose finite differences hold (at 1e-6 they are noise).
SCIPY_SOLVER = {"rtol": 1e-8, "atol": 1e-11}
#: How many times the cached command line runs (the median is reported: one run on a
#: shared machine moves by a few tenths of a second).
CACHED_RUNS = 5
#: A start reached the best when its cost is within this of the best (χ² units, noise
#: given): 0.01 is a tenth of a standard error in the worst direction.
REACHED = 0.01


class ScipyFit:
    """What a Python engineer writes: weighted residuals of the hard-switch model solved
    by `solve_ivp` (DOP853, events), fitted by `least_squares` (trf, bounds, a 2-point
    Jacobian, `x_scale="jac"`). Counts its solves."""

    def __init__(self, known: dict, ts, measured: dict):
        self.known, self.ts, self.measured = known, ts, measured
        self.names = list(BOX)
        self.solves = 0

    def residuals(self, theta) -> np.ndarray:
        self.solves += 1
        values = self.known | dict(zip(self.names, theta, strict=True))
        history = rjx.reference_history(
            values, self.ts, rtol=SCIPY_SOLVER["rtol"], atol=SCIPY_SOLVER["atol"]
        )
        return np.concatenate([(history[s] - self.measured[s]) / NOISE[s] for s in NOISE])

    def fit(self, start) -> scipy.optimize.OptimizeResult:
        import scipy.optimize  # here: the command line loads this module

        lower, upper = (np.asarray([BOX[n][i] for n in self.names]) for i in (0, 1))
        return scipy.optimize.least_squares(
            self.residuals, start, bounds=(lower, upper), x_scale="jac", method="trf"
        )


def _timed(fn):
    start = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - start


def one_fit(samples: int, log) -> dict:
    """One 5-parameter fit of one trace, warm: ours, then scipy's from the same start."""
    ts, measured = firing_test({}, samples, 1.0, seed=7)
    calibration = calibration_of({}, ts, measured)
    # One start, as scipy's one fit (the default's second start would double ours).
    rj.calibrate(calibration, starts=1, progress=False)  # compiles
    ours, ours_s = _timed(lambda: rj.calibrate(calibration, starts=1, progress=False))
    start = np.asarray([rj.PARAMETERS[n].default for n in BOX])
    scipy_fit = ScipyFit({}, ts, measured)
    theirs, theirs_s = _timed(lambda: scipy_fit.fit(start))
    stderr = np.asarray([ours.fitted[n].stderr for n in BOX])
    apart = np.abs(theirs.x - np.asarray([ours.values[n] for n in BOX])) / stderr
    log(f"  one fit: ours {ours_s:.3f} s ({ours.steps} LM steps), scipy {theirs_s:.2f} s "
        f"({scipy_fit.solves} solves); values apart by <= {apart.max():.2f} stderr")  # fmt: skip
    return {
        "samples": samples,
        "ours_s": ours_s,
        "ours_steps": ours.steps,
        "scipy_s": theirs_s,
        "scipy_solves": scipy_fit.solves,
        "speedup": theirs_s / ours_s,
        "max_apart_stderr": float(apart.max()),
    }


def many_fits(samples: int, draws: int, scipy_draws: int, log) -> dict:
    """`draws` noise draws of one test: ours as one batch (warm), scipy looping over
    `scipy_draws` of them (its time per fit times `draws`: the fits are independent)."""
    ts, _ = firing_test({}, samples, 1.0, seed=0)
    sets = [firing_test({}, samples, 1.0, seed=1000 + b)[1] for b in range(draws)]
    calibration = calibration_of({}, ts, sets[0])
    rjx.fit_many(calibration, [[s] for s in sets])  # compiles
    rows, ours_s = _timed(lambda: rjx.fit_many(calibration, [[s] for s in sets]))
    start = np.asarray([rj.PARAMETERS[n].default for n in BOX])
    apart, scipy_s = [], 0.0
    for b in range(scipy_draws):
        fit, seconds = _timed(lambda b=b: ScipyFit({}, ts, sets[b]).fit(start))
        scipy_s += seconds
        ours_b = np.asarray([rows[b][n] for n in BOX])
        stderr = np.asarray([rows[b][f"{n}.stderr"] for n in BOX])
        apart.append(float(np.max(np.abs(fit.x - ours_b) / stderr)))
    per_fit = scipy_s / scipy_draws
    log(f"  {draws} fits: ours {ours_s:.2f} s in one program; scipy {per_fit:.2f} s a fit "
        f"(on {scipy_draws}), {per_fit * draws:.1f} s for {draws}")  # fmt: skip
    return {
        "draws": draws,
        "ours_s": ours_s,
        "scipy_draws": scipy_draws,
        "scipy_s_per_fit": per_fit,
        "speedup": per_fit * draws / ours_s,
        "converged": int(sum(r["converged"] for r in rows)),
        "max_apart_stderr": max(apart),
    }


#: The model check's cases: a wrong model, (the truth, the design fitted, the trigger
#: delay of the truth's firing (s)) by name; and the right ones, by noise correlation.
WRONG_MODELS = {
    "absorber trace fitted without the absorber": ({}, {"m": 0.0}, 0.0),
    "simplified trace fitted with the absorber": ({"m": 0.0}, {}, 0.0),
    "10 ms pulse fitted as an impulse": ({"pulse_time": 0.01}, {}, 0.0),
    "20 ms trigger delay fitted with t_shift = 0": ({}, {}, 0.02),
}
RIGHT_MODELS = {
    "absorber, white noise": ({}, 0.0),
    "absorber, AR(1) noise, phi 0.5": ({}, 0.5),
    "simplified, white noise": ({"m": 0.0}, 0.0),
    "simplified, AR(1) noise, phi 0.5": ({"m": 0.0}, 0.5),
}
#: The model check's test: the newcomer's noise (issue 52), three values fitted over
#: the bounds `calibrate TRACE --fit k,c_out,c_ret` took then (their documented ranges
#: before issue 63 widened the dampers' to 1e5), with the noise estimated.
CHECK_NOISE = {"x_M": 3e-4, "F_AN": 40.0}
CHECK_FIT = {"k": (1e3, 1e6), "c_out": (0.0, 5e4), "c_ret": (0.0, 5e4)}


def _coloured(rng, samples: int, phi: float) -> np.ndarray:
    """Unit-variance AR(1) noise `n_t = phi n_(t-1) + sqrt(1 - phi^2) e_t` (a data
    logger's filter), started in its stationary state."""
    import scipy.signal

    e = rng.standard_normal(samples)
    return scipy.signal.lfilter([math.sqrt(1 - phi * phi)], [1.0, -phi], e,
                                zi=[phi * e[0]])[0]  # fmt: skip


def model_check_rates(draws: int, samples: int, log, end: float = 1.0) -> dict:
    """How often the model check flags a fit, over `draws` noise draws of each wrong
    model (`WRONG_MODELS`; white noise) and `draws // 2` with AR(1) noise (φ = 0.5), and
    `draws // 2` of each right one (`RIGHT_MODELS`), each trace made by the independent
    reference solver, fitted as one batch per case (`fit_many`): flagged, flagged naming
    a signal, and the margins (each window's size over the noise, its lag-1
    autocorrelation above the trace's own noise's)."""
    ts = np.linspace(0.0, end, samples)

    def flagged(truth: dict, design: dict, delay: float, phi: float, count: int, seed: int):
        history = rjx.reference_history(truth, np.clip(ts - delay, 0.0, None))
        clean = {s: np.where(ts < delay, 0.0, history[s]) for s in CHECK_NOISE}
        sets = []
        for b in range(count):
            rng = np.random.default_rng(seed + b)
            sets.append({s: clean[s] + CHECK_NOISE[s] * _coloured(rng, samples, phi)
                         for s in CHECK_NOISE})  # fmt: skip
        experiment = rjx.Experiment(rjx.Trace.of(ts, **sets[0]), design=design)
        rows = rjx.fit_many(rj.Calibration([experiment], fit=CHECK_FIT), [[x] for x in sets])
        windows = [(w, c.trace_correlation) for r in rows for c in r["check"].signals
                   for w in c.windows]  # fmt: skip
        return {
            "draws": count,
            "flagged": sum(not r["explains"] for r in rows),
            "named": sum(bool(r["failing"]) for r in rows),
            "converged": sum(bool(r["converged"]) for r in rows),
            # The margins: the windows' largest and smallest size over the noise, and
            # their largest lag-1 autocorrelation above the trace's own noise's.
            "window_ratio": [min(w.ratio for w, _ in windows), max(w.ratio for w, _ in windows)],
            "correlation_above_noise": max(w.correlation - phi for w, phi in windows),
        }

    cases = [
        ("wrong", name + colour, truth, design, delay, phi, count)
        for phi, colour, count in ((0.0, "", draws), (0.5, ", AR(1) noise, phi 0.5", draws // 2))
        for name, (truth, design, delay) in WRONG_MODELS.items()
    ]
    cases += [("right", name, truth, truth, 0.0, phi, draws // 2)
              for name, (truth, phi) in RIGHT_MODELS.items()]  # fmt: skip
    out: dict[str, dict] = {"wrong": {}, "right": {}}
    for i, (kind, name, truth, design, delay, phi, count) in enumerate(cases):
        start = time.perf_counter()
        row = flagged(truth, design, delay, phi, count, 10_000 * (i + 1))
        out[kind][name] = row
        log(f"  model check, {kind} model, {name}: {row['flagged']} of {count} flagged "
            f"({time.perf_counter() - start:.1f} s)")  # fmt: skip
    return {"samples": samples, "end": end, "noise": CHECK_NOISE, **out}


def random_starts(
    name: str, known: dict, end: float, samples: int, starts: int, log, seeds=(3, 5)
) -> dict:
    """The fraction of `starts` random points in the box (the same for both) from which
    each fit reaches its best cost (within `REACHED`); `seeds`: the trace's noise and the
    starts'."""
    ts, measured = firing_test(known, samples, end, seed=seeds[0])
    rng = np.random.default_rng(seeds[1])
    lower, upper = (np.asarray([BOX[n][i] for n in BOX]) for i in (0, 1))
    points = lower + (upper - lower) * rng.random((starts, len(BOX)))
    calibration = calibration_of(known, ts, measured)
    rj.calibrate(calibration, starts=points, progress=False)  # compiles
    ours, ours_s = _timed(lambda: rj.calibrate(calibration, starts=points, progress=False))
    costs, theirs_s = [], 0.0
    for point in points:
        fit, seconds = _timed(lambda p=point: ScipyFit(known, ts, measured).fit(p))
        costs.append(2 * fit.cost)  # scipy's cost is half the sum of squares
        theirs_s += seconds
    costs = np.asarray(costs)
    theirs = int(np.sum(costs <= costs.min() + REACHED))
    log(f"  {name}, {starts} random starts: ours {ours.starts_at_best} reach the best "
        f"({ours_s:.1f} s), scipy {theirs} ({theirs_s:.1f} s)")  # fmt: skip
    return {
        "trace": name,
        "seeds": list(seeds),
        "starts": starts,
        "ours_reached": ours.starts_at_best,
        "scipy_reached": theirs,
        "ours_s": ours_s,
        "scipy_s": theirs_s,
        "ours_best_chi2": ours.chi2,
        "scipy_best_chi2": float(costs.min()),
    }


def prediction(samples: int, log) -> dict:
    """The 95 % band of one design from `samples` covariance samples (warm)."""
    ts, measured = firing_test({}, 2001, 1.0, seed=7)
    hardware = rj.calibrate(calibration_of({}, ts, measured), starts=1, progress=False).hardware()
    design = {"k_r": 20000.0}  # a design change the test did not fire
    rj.predict(hardware, design, samples=samples, progress=False)
    result, seconds = _timed(lambda: rj.predict(hardware, design, samples=samples, progress=False))
    log(f"  prediction band, {samples} samples: {seconds:.2f} s ({result.failed} failed)")
    return {"samples": samples, "seconds": seconds, "failed": result.failed}


def command_line(samples: int, log) -> dict:
    """`recoil-jax calibrate TRACE --fit ...` in a fresh process: cold (an empty cache),
    then with the compilation cache holding its programs."""
    with tempfile.TemporaryDirectory() as folder:
        ts, measured = firing_test({}, samples, 1.0, seed=7)
        trace = Path(folder) / "trace.csv"
        rows = ["t,x_M,F_AN"] + [
            f"{t:.9g},{x:.9g},{f:.9g}"
            for t, x, f in zip(ts, measured["x_M"], measured["F_AN"], strict=True)
        ]
        with rjx.written(trace) as temporary:
            temporary.write_text("\n".join(rows) + "\n")
        env = os.environ | {"RECOIL_JAX_CACHE": str(Path(folder) / "cache")}
        argv = [sys.executable, "-m", "recoil_jax.apps._cli", "calibrate", str(trace),
                "--fit", ",".join(BOX), "--out", str(Path(folder) / "out")]  # fmt: skip
        seconds = []
        for _ in range(1 + CACHED_RUNS):
            start = time.perf_counter()
            subprocess.run(argv, check=True, capture_output=True, env=env)
            seconds.append(time.perf_counter() - start)
    cached = seconds[1:]
    log(f"  recoil-jax calibrate: {seconds[0]:.1f} s cold, {np.median(cached):.2f} s cached "
        f"(median of {len(cached)}, {min(cached):.2f}-{max(cached):.2f} s)")  # fmt: skip
    return {"cold_s": seconds[0], "cached_s": float(np.median(cached)), "cached_runs": cached}


def run_calibration_bench(
    samples: int = 5001,
    draws: int = 100,
    scipy_draws: int = 10,
    starts: int = 20,
    prediction_samples: int = 10_000,
    cli: bool = True,
    burst_seeds: int = 0,
    log=None,
) -> dict:
    """Every figure of the calibration bench (see the module docstring); `burst_seeds`:
    the burst's random starts again from that many more traces and sets of starts
    (noise seeds 100, 101, ..., start seeds 200, 201, ...)."""
    log = log or (lambda msg: print(msg, file=sys.stderr, flush=True))
    log("calibration bench (ours against scipy least_squares on solve_ivp DOP853):")
    burst = min(samples, 3001)
    return {
        "one_fit": one_fit(samples, log),
        "many_fits": many_fits(min(samples, 1001), draws, scipy_draws, log),
        "random_starts": [
            random_starts("absorber", {}, 1.0, min(samples, 2001), starts, log),
            random_starts("burst", BURST, 1.5, burst, starts, log),
            *(
                random_starts("burst", BURST, 1.5, burst, starts, log, (100 + i, 200 + i))
                for i in range(burst_seeds)
            ),
        ],
        "prediction": prediction(prediction_samples, log),
        "model_check": model_check_rates(draws, min(samples, 1001), log),
        "command_line": command_line(samples, log) if cli else None,
        "scipy_solver": {"method": "DOP853", **SCIPY_SOLVER},
        "host": host_description(),
    }


def format_calibration_bench(result: dict) -> str:
    one, many = result["one_fit"], result["many_fits"]
    lines = [
        f"host: {result['host']['cpu']}, {result['host']['cores']} cores",
        f"one fit (5 parameters, {one['samples']} samples of x_M and F_AN), warm: ours "
        f"{one['ours_s']:.3f} s, scipy {one['scipy_s']:.2f} s ({one['scipy_solves']} "
        f"solves): {one['speedup']:.1f}x; values apart by <= "
        f"{one['max_apart_stderr']:.2f} stderr",
        f"{many['draws']} fits (noise draws): ours {many['ours_s']:.2f} s in one program, "
        f"scipy {many['scipy_s_per_fit']:.2f} s a fit (looping; measured on "
        f"{many['scipy_draws']}): {many['speedup']:.0f}x; {many['converged']} converged; "
        f"values apart by <= {many['max_apart_stderr']:.2f} stderr",
    ]
    for row in result["random_starts"]:
        lines.append(
            f"{row['trace']} (seeds {row['seeds']}): of {row['starts']} random starts, ours "
            "reached the best from "
            f"{row['ours_reached']} ({row['ours_s']:.1f} s), scipy from "
            f"{row['scipy_reached']} ({row['scipy_s']:.1f} s)"
        )
    bursts = [row for row in result["random_starts"] if row["trace"] == "burst"]
    if len(bursts) > 1:
        lines.append(
            f"burst, all {len(bursts)} traces: of {sum(r['starts'] for r in bursts)} random "
            f"starts, ours reached the best from {sum(r['ours_reached'] for r in bursts)}, "
            f"scipy from {sum(r['scipy_reached'] for r in bursts)}"
        )
    p = result["prediction"]
    lines.append(f"prediction band, {p['samples']} samples: {p['seconds']:.2f} s")
    check = result["model_check"]
    for kind, says in (("wrong", "flagged, naming a signal"), ("right", "flagged")):
        key = "named" if kind == "wrong" else "flagged"
        for name, row in check[kind].items():
            low, high = row["window_ratio"]
            lines.append(f"model check, {kind} model ({name}): {row[key]} of {row['draws']} "
                         f"{says}; windows {low:.2f}-{high:.3g} times the noise, lag-1 "
                         f"correlation up to {row['correlation_above_noise']:.2f} above "
                         "the noise's")  # fmt: skip
    right = check["right"].values()
    lines.append(f"model check, false alarms: {sum(r['flagged'] for r in right)} of "
                 f"{sum(r['draws'] for r in right)} right fits")  # fmt: skip
    if result["command_line"]:
        c = result["command_line"]
        runs = c.get("cached_runs") or [c["cached_s"]]
        lines.append(f"recoil-jax calibrate: {c['cold_s']:.1f} s cold, {c['cached_s']:.2f} s "
                     f"with the compilation cache (median of {len(runs)}, "
                     f"{min(runs):.2f}-{max(runs):.2f} s)")  # fmt: skip
    return "\n".join(lines)


def main_calibration_bench(args) -> int:
    if args.round_trip and args.posterior:
        print("recoil-jax bench-calibration: --round-trip or --posterior, not both",
              file=sys.stderr)  # fmt: skip
        return 2
    if args.posterior:
        from .posterior import format_posterior_bench, posterior_bench

        if args.quick:  # small sizes
            result = posterior_bench(samples=1001, draws=200, warmup=200, chains=2,
                                     envelope_draws=100)  # fmt: skip
        else:
            result = posterior_bench()
        print(json.dumps(result) if args.json else format_posterior_bench(result))
        return 0
    if args.round_trip:
        from .round_trip import format_round_trip, round_trip

        trip = round_trip(draws=args.draws, compare=args.compare)
        print(json.dumps(trip) if args.json else format_round_trip(trip))
        return 0
    quick = args.quick
    result = run_calibration_bench(
        samples=1001 if quick else 5001,
        draws=8 if quick else 100,
        scipy_draws=2 if quick else 10,
        starts=4 if quick else 20,
        prediction_samples=1000 if quick else 10_000,
        cli=not quick,
        burst_seeds=args.burst_seeds,
    )
    print(json.dumps(result) if args.json else format_calibration_bench(result))
    return 0


def add_command(commands: Commands) -> None:
    """`recoil-jax bench-calibration`'s arguments."""
    calibration_bench = commands.add(
        "bench-calibration",
        main_calibration_bench,
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
    calibration_bench.add_argument(
        "--round-trip",
        action="store_true",
        help="instead: the round trip from the defaults (the shipped plan's firings, "
        "reference traces with noise at 2 truths, each fitted by calibrate with no "
        "option; beside it, on --compare draws, 1 start and 16 starts without "
        "continuation); run from the repository's root",
    )
    calibration_bench.add_argument(
        "--posterior",
        action="store_true",
        help="instead: the posterior's speed on the 5-value fit (NUTS's bulk ESS per "
        "second and per solve, beside emcee vectorised over its walkers on the same "
        "solves; chains vmapped against one after another), then NUTS on the round "
        "trip's traces of the shipped plan's firings (run from the repository's root; "
        "about 20 minutes in all); --quick for small sizes",
    )
    calibration_bench.add_argument(
        "--draws", type=int, default=20, metavar="N", help="with --round-trip: draws a truth"
    )
    calibration_bench.add_argument(
        "--compare", type=int, default=1, metavar="N",
        help="with --round-trip: draws a truth fitted the other ways too",
    )  # fmt: skip
    add_json(calibration_bench, "JSON")
