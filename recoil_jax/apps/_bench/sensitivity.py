"""`recoil-jax bench-sensitivity`: global sensitivity on the paper's absorber
(`sensitivity/paper_absorber.toml`: 8 parameters), against what a user writes with
SALib alone: its samples through a scipy `solve_ivp` loop (the hard-switch model with
its switches and peaks as events, `rj.reference_peaks`, at the library's tolerances)
in a process per core, then SALib's analysis.

Measured, side by side in one run: Sobol indices with second order from 2^12 base
samples (73,728 designs), cold and warm; DGSM from exact gradients on 4,096 designs,
cold and warm, beside SALib's finite-difference DGSM on the same points through our
sweep (9 solves a point); the scipy loop's rate on a slice of the same designs, and
how far its peaks are from ours. Speed is reported, never asserted.
"""

from __future__ import annotations

import json
import multiprocessing
import sys
import time

import numpy as np

import recoil_jax as rj

from .._files.options import Commands, add_json
from .._studies.sensitivity_file import load_sensitivity
from .anchor import cores
from .speed import SCIPY_SETTINGS, host_description

__all__ = ["add_command", "main_sensitivity_bench", "run_sensitivity_bench"]

#: Indices below this are the solver's noise (rtol 1e-6 moves a peak by ~1e-6 of itself,
#: which is ~(1e-6 · 5500 N / 250 N)² ≈ 5e-10 of the variance): left out of comparisons.
NOISE_FLOOR = 1e-6

#: The metrics the scipy loop's peaks are compared on.
_COMPARED = ("peak_anchoring_force", "peak_displacement", "max_stroke")


def _scipy_peaks(values: dict) -> dict:
    return rj.reference_peaks(values, t1=10.0, **SCIPY_SETTINGS)


def _timed(fn):
    start = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - start


def scipy_loop(designs: list[dict], log) -> dict:
    """The designs through `reference_peaks` in a pool of one process per core (each
    warmed by one solve first: the first imports scipy.integrate); designs a second."""
    processes = cores()
    # spawn: the parent runs JAX's threads, which fork would copy mid-flight.
    with multiprocessing.get_context("spawn").Pool(processes) as pool:
        pool.map(_scipy_peaks, designs[:processes], chunksize=1)
        peaks, seconds = _timed(lambda: pool.map(_scipy_peaks, designs, chunksize=8))
    log(f"  scipy solve_ivp loop ({processes} processes): {len(designs) / seconds:.1f} designs/s")
    return {"designs": len(designs), "processes": processes, "seconds": seconds, "peaks": peaks}


def run_sensitivity_bench(base_samples: int = 4096, scipy_designs: int = 256, log=None) -> dict:
    """Every figure of the sensitivity bench (see the module docstring)."""
    log = log or (lambda msg: print(msg, file=sys.stderr, flush=True))
    arguments, _ = load_sensitivity("paper_absorber")
    design, ranges, metrics = arguments["design"], arguments["ranges"], arguments["metrics"]
    log(f"sensitivity bench: the paper's absorber, {len(ranges)} parameters")

    def cold_and_warm(method, label):
        """The analysis twice: compiling, then with its programs compiled."""
        runs = []
        for when in ("cold", "warm"):
            result, seconds = _timed(
                lambda: rj.sensitivity(design, ranges, metrics, method, progress=False)
            )
            runs.append(seconds)
            log(f"  {label}, {len(result.ok):,} designs, {when}: {seconds:.2f} s")
        return result, runs

    result, runs = cold_and_warm(rj.SobolIndices(samples=base_samples, second_order=True), "sobol")
    sobol_row = {
        "designs": len(result.ok), "failed": int((~result.ok).sum()), "cold_s": runs[0],
        "warm_s": runs[1], "ranking": {m: result.ranking(m) for m in metrics},
    }  # fmt: skip

    exact, runs = cold_and_warm(rj.DGSM(samples=base_samples), "dgsm (exact gradients)")
    finite = _finite_difference_dgsm(exact, design, log)
    dgsm_row = {
        "designs": len(exact.ok), "cold_s": runs[0], "warm_s": runs[1], **finite,
        "sobol_under_bound": all(
            result.indices[m][p]["ST"] - result.indices[m][p]["ST_conf"]
            <= exact.indices[m][p]["dgsm"] + exact.indices[m][p]["dgsm_conf"] + NOISE_FLOOR
            for m in metrics for p in ranges
        ),
    }  # fmt: skip

    # The scipy loop on an even slice of the same Sobol designs; its rate gives its time
    # for all of them (the designs are independent: the loop's time is linear in them).
    chosen = np.linspace(0, len(result.ok) - 1, scipy_designs).astype(int)
    slice_designs = [
        design | dict(zip(result.parameters, map(float, result.samples[i]), strict=True))
        for i in chosen
    ]
    theirs = scipy_loop(slice_designs, log)
    apart = max(
        abs(result.outputs[m][i] / p[m] - 1.0)
        for i, p in zip(chosen, theirs.pop("peaks"), strict=True)
        for m in _COMPARED
    )
    per_design = theirs["seconds"] / theirs["designs"]
    scipy_total = per_design * len(result.ok)
    ratio = scipy_total / sobol_row["warm_s"]
    log(f"  scipy for all {len(result.ok):,}: {scipy_total:.0f} s (from its rate); "
        f"{ratio:.0f}x ours warm; peaks apart <= {apart:.1e}")  # fmt: skip
    return {
        "sobol": sobol_row,
        "dgsm": dgsm_row,
        "scipy": theirs
        | {
            "settings": SCIPY_SETTINGS,
            "all_designs_s": scipy_total,
            "ratio_to_warm": scipy_total / sobol_row["warm_s"],
            "ratio_to_cold": scipy_total / sobol_row["cold_s"],
            "max_relative_apart": apart,
        },
        "host": host_description(),
    }


def _finite_difference_dgsm(exact: rj.SensitivityResult, design: dict, log) -> dict:
    """SALib's DGSM way on the same points: its finite-difference sample (each point and
    a 1 % step in each parameter) through our sweep, then `SALib.analyze.dgsm`."""
    from SALib.analyze import dgsm
    from SALib.sample import finite_diff

    problem = {
        "num_vars": len(exact.parameters), "names": list(exact.parameters),
        "bounds": np.stack([exact.lower, exact.upper], axis=1).tolist(),
    }  # fmt: skip
    x = finite_diff.sample(problem, len(exact.ok))
    columns = {n: np.full(len(x), v) for n, v in design.items()}
    columns |= {n: x[:, i] for i, n in enumerate(exact.parameters)}
    options = rj.GRADIENT_OPTIONS
    rj.sweep(columns, options=options, progress=False)  # compiles
    swept, seconds = _timed(lambda: rj.sweep(columns, options=options, progress=False))
    worst, noise = 0.0, 0
    for metric in exact.metrics:
        theirs = dgsm.analyze(problem, x, swept.peaks[metric], seed=1)
        for i, name in enumerate(exact.parameters):
            ours = exact.indices[metric][name]
            if theirs["dgsm"][i] < NOISE_FLOOR:
                noise += 1
                continue
            worst = max(worst, abs(ours["vi"] - theirs["vi"][i]) / theirs["dgsm_conf"][i])
    log(f"  dgsm by finite differences (SALib's sample, {len(x):,} designs through the "
        f"sweep, warm): {seconds:.2f} s; exact vi within {worst:.2f} of its interval "
        f"({noise} pairs at the solver's noise left out)")  # fmt: skip
    return {"finite_difference_designs": len(x), "finite_difference_warm_s": seconds,
            "exact_apart_in_intervals": worst, "noise_pairs": noise}  # fmt: skip


def format_sensitivity_bench(result: dict) -> str:
    s, d, c = result["sobol"], result["dgsm"], result["scipy"]
    host = result["host"]
    return "\n".join([
        f"host: {host['cpu']}, {host['cores']} cores",
        f"sobol (second order), {s['designs']:,} designs: {s['cold_s']:.1f} s cold, "
        f"{s['warm_s']:.1f} s warm; {s['failed']} failed",
        f"dgsm (exact gradients), {d['designs']:,} designs x 8 parameters: "
        f"{d['cold_s']:.1f} s cold, {d['warm_s']:.1f} s warm; SALib's finite differences "
        f"on the same points ({d['finite_difference_designs']:,} designs through our "
        f"sweep): {d['finite_difference_warm_s']:.1f} s; vi apart by <= "
        f"{d['exact_apart_in_intervals']:.2f} of its interval; Sobol ST under the bound: "
        f"{d['sobol_under_bound']}",
        f"scipy solve_ivp loop ({c['settings']['method']}, rtol {c['settings']['rtol']:g}, "
        f"{c['processes']} processes): {c['designs'] / c['seconds']:.1f} designs/s on "
        f"{c['designs']}: {c['all_designs_s']:.0f} s for the Sobol designs, "
        f"{c['ratio_to_warm']:.0f}x ours warm ({c['ratio_to_cold']:.0f}x cold); peaks "
        f"apart by <= {c['max_relative_apart']:.1e}",
    ])  # fmt: skip


def main_sensitivity_bench(args) -> int:
    result = run_sensitivity_bench(
        base_samples=256 if args.quick else 4096, scipy_designs=16 if args.quick else 256
    )
    print(json.dumps(result) if args.json else format_sensitivity_bench(result))
    return 0


def add_command(commands: Commands) -> None:
    """`recoil-jax bench-sensitivity`'s arguments."""
    sensitivity_bench = commands.add(
        "bench-sensitivity",
        main_sensitivity_bench,
        help="global sensitivity against SALib on a scipy solve_ivp loop",
        description="On the paper's absorber (sensitivity/paper_absorber.toml, 8 "
        "parameters): Sobol indices with second order from 2^12 base samples (73,728 "
        "designs) and DGSM from exact gradients on 4,096 designs, cold and warm; SALib's "
        "finite-difference DGSM on the same points through the sweep; and the scipy "
        "solve_ivp loop a SALib user writes (one process per core) on a slice of the "
        "same designs, its time for all of them and how far its peaks are from ours.",
    )
    sensitivity_bench.add_argument("--quick", action="store_true", help="small sizes")
    add_json(sensitivity_bench, "JSON")
