"""`recoil-jax bench`: throughput of vmapped solves and Jacobians against a serial scipy
`solve_ivp` loop computing the same peaks, all measured in one run."""

from __future__ import annotations

import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any, NamedTuple

import equinox as eqx
import jax
import numpy as np

import recoil_jax as rj
import recoil_jax.extend as rjx

from .._files.options import Commands, add_json

__all__ = [
    "CLI_COMMANDS",
    "GRADIENT_STUDY",
    "SCIPY_SETTINGS",
    "add_command",
    "bench_designs",
    "cli_cache_timings",
    "envelope_designs",
    "format_bench",
    "gradient_modes",
    "hardware_designs",
    "host_description",
    "main_bench",
    "run_bench",
]


def bench_designs(count: int, seed: int = 0) -> dict[str, np.ndarray]:
    """Absorber designs around the paper's: m 100–3000 kg, gap 0–0.15 m, k_r 5e3–5e4,
    c_r 0–1e4 (a mix of impact-heavy, optimal and impact-free designs)."""
    rng = np.random.default_rng(seed)
    return {
        "m": rng.uniform(100.0, 3000.0, count),
        "gap": rng.uniform(0.0, 0.15, count),
        "k_r": rng.uniform(5e3, 5e4, count),
        "c_r": rng.uniform(0.0, 1e4, count),
    }


def hardware_designs(count: int, seed: int = 1) -> dict[str, np.ndarray]:
    """Designs with all the hardware on: the absorber designs of `bench_designs`, fired
    in a 3-round burst of 5 ms pulses, with an 8-knot throttling orifice and a gas
    recuperator (knots, recuperator force and interval drawn at random)."""
    rng = np.random.default_rng(seed)
    columns = bench_designs(count, seed)
    columns |= {
        "shots": np.full(count, 3.0),
        "fire_interval": rng.uniform(0.8, 1.5, count),
        "pulse_time": np.full(count, 0.005),
        "piston_area": np.full(count, 0.01),
        "orifice_length": np.full(count, 0.2),
        "recuperator_force": rng.uniform(1000.0, 5000.0, count),
        "recuperator_length": np.full(count, 1.0),
    }
    columns |= {f"orifice_{i}": rng.uniform(2e-4, 6e-4, count) for i in range(8)}
    return columns


def envelope_designs(count: int, seed: int = 2, absorber: bool = True) -> dict[str, np.ndarray]:
    """Designs with the firing envelope on, friction, the battery stop and the
    counter-recoil buffer among it: the absorber designs of `bench_designs` on rails at
    0–70° with packing and slide friction, a preloaded recuperator on a battery stop, a
    counter-recoil buffer and a mount (elevation, friction, preload and buffer drawn at
    random). `absorber=False`: the same without the absorber (`m = 0`)."""
    rng = np.random.default_rng(seed)
    columns = bench_designs(count, seed)
    if not absorber:
        columns = {k: v for k, v in columns.items() if k not in ("gap", "k_r", "c_r")}
        columns["m"] = np.zeros(count)
    columns |= {
        "elevation": rng.uniform(0.0, 70.0, count),
        "friction_force": rng.uniform(500.0, 3000.0, count),
        "friction_coefficient": rng.uniform(0.0, 0.1, count),
        "stop_stiffness": np.full(count, 2e8),
        "recuperator_length": np.full(count, 1.5),
        "recuperator_preload": rng.uniform(7e4, 1.2e5, count),
        "buffer_damping": rng.uniform(5e4, 2e5, count),
        "buffer_length": np.full(count, 0.15),
        "mount_mass": np.full(count, 2e4),
    }
    return columns


def _take(columns, index):
    """The designs at `index` of `columns`."""
    return {k: v[index] for k, v in columns.items()}


def _timed(fn, *args):
    """`fn(*args)`, waited for, and its wall seconds."""
    start = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return out, time.perf_counter() - start


#: The problem of the gradient-mode comparison: P of its tuned parameters are
#: differentiated, P up to all 22.
GRADIENT_STUDY = "burst_recuperator"


def gradient_modes(
    sizes=(1, 4, 8, 16, 22), repeats: int = 5, log=None, study: str = GRADIENT_STUDY
) -> list[dict]:
    """Milliseconds per gradient of the peak anchoring force with respect to P tuned
    parameters of `study` (default `GRADIENT_STUDY`; at its start design, the orifice
    knots first), for each P in `sizes`:
    a plain solve, forward sensitivities (P columns, error-controlled; what the
    optimisers use) and reverse mode through the solver's steps (`autodiff="reverse"`,
    diffrax's checkpointed loop; one backward pass for any P), with the largest
    relative difference between the two gradients."""
    import dataclasses

    from .._studies.study_file import load_study

    log = log or (lambda msg: None)
    problem = load_study(study).problem
    params, smoothing, options = problem.params, problem.smoothing, problem.options
    reverse_options = dataclasses.replace(options, autodiff="reverse")

    def best_ms(fn, *args):
        jax.block_until_ready(fn(*args))
        return 1e3 * min(_timed(fn, *args)[1] for _ in range(repeats))

    # The orifice knots first: they act on every design (an absorber that the wall does
    # not reach at the start design would give zero gradients).
    order = sorted(problem.tune, key=lambda name: not name.startswith("orifice_"))
    rows = []
    for size in sizes:
        wrt = tuple(order[:size])
        theta = jax.numpy.asarray(rj.values_of(params, wrt))

        def force(theta, options, wrt=wrt):
            design = rj.with_values(params, wrt, theta)
            return rj.peak_metrics(design, smoothing, options).peak_anchoring_force

        def forward(theta, wrt=wrt):
            design = rj.with_values(params, wrt, theta)
            _, gradients = rj.peak_jacobian(design, smoothing, options, wrt, throw=False)
            return gradients.peak_anchoring_force

        plain = eqx.filter_jit(force)
        reverse = eqx.filter_jit(jax.grad(force))
        forward = eqx.filter_jit(forward)
        row = {
            "parameters": size,
            "plain_ms": best_ms(plain, theta, options),
            "forward_ms": best_ms(forward, theta),
            "reverse_ms": best_ms(reverse, theta, reverse_options),
        }
        exact, discrete = np.asarray(forward(theta)), np.asarray(reverse(theta, reverse_options))
        row["max_abs_gradient"] = float(np.max(np.abs(exact)))
        row["max_rel_difference"] = float(
            np.max(np.abs(discrete - exact)) / max(row["max_abs_gradient"], 1e-300)
        )
        rows.append(row)
        log(
            f"  gradient, {size:2d} parameters: plain {row['plain_ms']:.1f} ms, forward "
            f"sensitivities {row['forward_ms']:.1f} ms, reverse {row['reverse_ms']:.1f} ms"
        )
        jax.clear_caches()  # each P is its own program: keep memory flat
    return rows


#: The commands whose first and second run `cli_cache_timings` measures.
CLI_COMMANDS = (
    ("simulate", "m=1000", "gap=0.05", "--json"),
    ("sweep", "m=500:1500:11", "gap=0.05", "--json"),
    ("optimise", "tuned_absorber", "--json"),
    ("optimise", "envelope", "--json"),  # issue 66: within 15 s warm
)


def cli_cache_timings(commands=CLI_COMMANDS, log=None) -> list[dict]:
    """Wall seconds of each command's first and second run, each in a fresh process,
    with the compilation cache in a new empty folder: the second run loads what the
    first compiled."""
    import os
    import subprocess
    import tempfile

    log = log or (lambda msg: None)
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        env = os.environ | {"RECOIL_JAX_CACHE": str(Path(folder) / "cache")}
        for command in commands:
            argv = [sys.executable, "-m", "recoil_jax.apps._cli", *command]
            if command[0] == "optimise":
                argv += ["--out", str(Path(folder) / "study")]
            seconds = []
            for _ in range(2):
                start = time.perf_counter()
                subprocess.run(argv, check=True, capture_output=True, env=env)
                seconds.append(time.perf_counter() - start)
            rows.append(
                {"command": " ".join(command), "first_s": seconds[0], "second_s": seconds[1]}
            )
            log(f"  recoil-jax {' '.join(command)}: {seconds[0]:.2f} s, then {seconds[1]:.2f} s")
    return rows


#: The scipy baseline's settings: the hard-switch model with its switches and peaks
#: located as events (`reference_peaks`), at the tolerances the library uses for the paper
#: model. DOP853 is the fastest of solve_ivp's methods there that holds them (measured on
#: 20 designs: DOP853 59 sims/s at 2.7e-6 from a 1e-10 solution, RK45 43 at 6.9e-6, Radau
#: 12, BDF 12, RK23 12; LSODA fails on the event search).
SCIPY_SETTINGS = {"method": "DOP853", "rtol": 1e-6, "atol": 1e-9}


#: x86 vector extensions, widest first: the one a host's figures are labelled with.
_VECTOR_EXTENSIONS = ("avx512f", "avx2", "avx", "sse4_2")


def host_description() -> dict:
    """The machine the figures come from: its CPU's model name, the widest x86 vector
    extension it lists (`avx512f`, `avx2`, ...; None where `/proc/cpuinfo` does not say)
    and the cores this process may use. Figures from different hosts do not compare: on
    two 2-core AMD EPYC machines, one with AVX-512 and one with AVX2 only, nearly the same
    code ran the bench's largest batch at 29-31k and at 14.5-21.3k sims/s, and the
    compiled scalar loop led 3.9-4.4x and 4.4-5.6x per step."""
    from .anchor import cores

    model, flags = platform.processor() or platform.machine(), set()
    try:
        with open("/proc/cpuinfo") as info:
            for line in info:
                key, _, value = line.partition(":")
                if key.strip() == "model name":
                    model = value.strip()
                elif key.strip() == "flags":
                    flags = set(value.split())
                    break  # every core lists the same; the model name comes first
    except OSError:  # not Linux
        pass
    widest = next((name for name in _VECTOR_EXTENSIONS if name in flags), None)
    return {"cpu": model, "vector_extension": widest, "cores": cores()}


def anchor_comparison(designs, ours_seconds: float, ours_steps, log=None) -> dict | None:
    """The compiled scalar loop (`anchor`, numba, one core) on `designs`, beside our
    sweep of the same designs (`ours_seconds`, `ours_steps` per design, on every core):
    each one's sims/s and accepted steps/s per core, and the anchor's lead per step and
    per design (a ratio > 1: the anchor is faster). None without numba."""
    from .anchor import anchor_peaks, cores

    log = log or (lambda msg: None)
    try:
        anchor = anchor_peaks(designs)
    except rj.ParameterError as error:
        log(f"  compiled scalar loop: skipped ({error})")
        return None
    n = len(anchor["num_steps"])
    used = cores()
    ours = {
        "sims_per_s": n / ours_seconds,
        "mean_steps": float(np.mean(ours_steps)),
        "steps_per_s_per_core": float(np.sum(ours_steps)) / ours_seconds / used,
        "cores": used,
    }
    theirs = {
        "sims_per_s": n / anchor["seconds"],
        "mean_steps": float(np.mean(anchor["num_steps"])),
        "steps_per_s_per_core": float(np.sum(anchor["num_steps"])) / anchor["seconds"],
        "cores": 1,
    }
    result = {
        "designs": n,
        "anchor": theirs,
        "ours": ours,
        "ratio_per_step": theirs["steps_per_s_per_core"] / ours["steps_per_s_per_core"],
        "ratio_per_design": theirs["sims_per_s"] / (ours["sims_per_s"] / used),
    }
    log(
        f"  compiled scalar loop (numba, 1 core, to t1): {theirs['sims_per_s']:.0f} sims/s, "
        f"{theirs['mean_steps']:.1f} steps, {theirs['steps_per_s_per_core'] / 1e6:.2f} M "
        f"steps/s; ours {ours['steps_per_s_per_core'] / 1e6:.2f} M steps/s per core: "
        f"{result['ratio_per_step']:.1f}x per step, {result['ratio_per_design']:.1f}x per "
        "design per core"
    )
    return result


def run_bench(
    batch_sizes=(1, 64, 1024, 16384),
    scipy_designs: int = 20,
    jacobian_batch: int = 4096,
    gradient_sizes=(1, 4, 8, 16, 22),
    cli_commands=CLI_COMMANDS,
    anchor: bool = True,
    log=None,
    gradient_study: str = GRADIENT_STUDY,
) -> dict:
    """Measure and return the figures (see `recoil-jax bench --help`). `gradient_sizes`
    and `cli_commands` empty: those parts are left out; `gradient_study`: the study whose
    tuned parameters the gradient modes differentiate; `anchor`: the compiled scalar
    loop beside the largest batch (skipped without numba)."""
    log = log or (lambda msg: print(msg, file=sys.stderr, flush=True))
    largest = max(batch_sizes)
    columns = bench_designs(max(largest, jacobian_batch, scipy_designs))
    batches = _batch_throughput(columns, batch_sizes, log)

    # The compiled scalar loop on the designs of the largest batch, beside our sweep.
    designs = _spread(columns, largest)
    ours = batches.timed[largest]
    anchored = anchor_comparison(designs, ours.seconds, ours.steps, log) if anchor else None

    one_worker_per_s = _one_worker_throughput(designs, log)
    vmap_per_s = _plain_vmap_throughput(columns, log)
    jacobians = _jacobian_throughput(columns, jacobian_batch, log)
    hardware = _hardware_throughput(largest, log)
    envelope = _envelope_throughput(largest, log)
    bare_envelope = _envelope_throughput(largest, log, absorber=False)
    baseline = _scipy_baseline(columns, scipy_designs, log)

    gradient_rows = (
        gradient_modes(gradient_sizes, log=log, study=gradient_study) if gradient_sizes else []
    )
    cli_rows = cli_cache_timings(cli_commands, log=log) if cli_commands else []

    best = max(batches.rows, key=lambda r: r["sims_per_s"])
    return {
        "sims_per_s": best["sims_per_s"],
        "batch_size": best["batch_size"],
        "scipy_sims_per_s": baseline.sims_per_s,
        "scipy_settings": SCIPY_SETTINGS,
        "speedup_vs_scipy": best["sims_per_s"] / baseline.sims_per_s,
        "compiled_scalar_loop": anchored,
        "plain_vmap_sims_per_s": vmap_per_s,
        "one_worker_sims_per_s": one_worker_per_s,
        "workers": rjx.default_workers(jax.local_devices()),
        "jacobians_per_s": jacobians.per_s,
        "hardware_sims_per_s": hardware.sims_per_s,
        "hardware_batch_size": largest,
        "hardware_mean_steps": float(np.mean(hardware.result.peaks["num_steps"])),
        "hardware_failed": len(hardware.result.failures()),
        "envelope_sims_per_s": envelope.sims_per_s,
        "envelope_vs_paper": envelope.sims_per_s / (largest / ours.seconds),
        "envelope_mean_steps": float(np.mean(envelope.result.peaks["num_steps"])),
        "envelope_max_steps": int(np.max(envelope.result.peaks["num_steps"])),
        # A batch's wall time over its mean steps a design, against the paper model's at
        # the same batch (issue 66's goal: within 1.5x): 1 where a batch's time follows
        # its mean steps and a step costs the paper's.
        "envelope_time_per_mean_step_vs_paper": float(
            (largest / envelope.sims_per_s / np.mean(envelope.result.peaks["num_steps"]))
            / (ours.seconds / np.mean(ours.steps))
        ),
        "envelope_failed": len(envelope.result.failures()),
        "envelope_no_absorber_sims_per_s": bare_envelope.sims_per_s,
        "envelope_no_absorber_vs_paper": bare_envelope.sims_per_s / (largest / ours.seconds),
        "envelope_no_absorber_mean_steps": float(np.mean(bare_envelope.result.peaks["num_steps"])),
        "envelope_no_absorber_failed": len(bare_envelope.result.failures()),
        "jacobian_compile_s": jacobians.compile_s,
        "compile_s": batches.compile_s,
        "max_rel_error": baseline.max_rel_error,
        "batches": batches.rows,
        "gradient_modes": gradient_rows,
        "gradient_study": gradient_study,
        "cli_cache": cli_rows,
        "devices": [str(d) for d in jax.local_devices()],
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "host": host_description(),
        "dtype": "float64",
    }


def _spread(columns: dict[str, np.ndarray], size: int) -> dict[str, np.ndarray]:
    """`size` designs evenly spread through `columns`, so that each batch has the same
    mix."""
    return _take(columns, np.linspace(0, len(columns["m"]) - 1, size).astype(int))


class _Sweep(NamedTuple):
    """A timed sweep: its result and its wall seconds."""

    result: Any
    seconds: float


def _timed_sweep(designs, **kwargs) -> _Sweep:
    """`rj.sweep` of `designs` (no progress line) and its wall seconds."""
    start = time.perf_counter()
    result = rj.sweep(designs, progress=False, **kwargs)
    return _Sweep(result, time.perf_counter() - start)


class _BatchTiming(NamedTuple):
    """One batch size's best wall seconds, and each of its designs' accepted steps."""

    seconds: float
    steps: Any


class _Batches(NamedTuple):
    """The sweep's throughput at each batch size: a row each (`batch_size`, `seconds`,
    `sims_per_s`), the best seconds and each design's steps by batch size, and the
    compilation's seconds (the first sweep's extra time)."""

    rows: list[dict]
    timed: dict[int, _BatchTiming]
    compile_s: float | None


def _batch_throughput(columns, batch_sizes, log) -> _Batches:
    """Time the sweep at each batch size (the best of a few runs after a first one,
    which compiles)."""
    rows = []
    timed = {}  # per batch size: the best seconds and each design's steps
    compile_s = None
    for size in batch_sizes:
        designs = _spread(columns, size)
        result, first = _timed_sweep(designs)
        repeats = max(2, min(5, int(2048 // size)))
        run = min(_timed_sweep(designs).seconds for _ in range(repeats))
        timed[size] = _BatchTiming(run, result.peaks["num_steps"])
        if compile_s is None:  # the first sweep compiles (later sizes up to 1024 share it)
            compile_s = max(first - run, 0.0)
        rows.append({"batch_size": size, "seconds": run, "sims_per_s": size / run})
        log(f"  batch {size:6d}: {size / run:9.0f} sims/s  ({run:.3f} s)")
    return _Batches(rows, timed, compile_s)


def _one_worker_throughput(designs, log) -> float:
    """Sims/s of the same sweep in one part on one thread, for comparison."""
    _timed_sweep(designs, workers=1)
    size = len(designs["m"])
    per_s = size / min(_timed_sweep(designs, workers=1).seconds for _ in range(2))
    log(f"  one worker, batch {size}: {per_s:.0f} sims/s")
    return per_s


def _plain_vmap_throughput(columns, log) -> float:
    """Sims/s of the plain vmap of the stepping loop, on the 1024-design batch (sorted by
    gap), for comparison."""
    designs = _spread(columns, 1024)
    designs = _take(designs, np.argsort(designs["gap"], kind="stable"))
    params = rjx.batch_params(designs)[0]
    if 1024 % jax.local_device_count() == 0:
        params = rjx.shard_batch(params)
    smoothing, options = rj.Smoothing(), rj.SolverOptions()
    solve = eqx.filter_jit(jax.vmap(rj.peak_metrics, in_axes=(0, None, None)))
    _timed(solve, params, smoothing, options)
    per_s = 1024 / _timed(solve, params, smoothing, options)[1]
    log(f"  plain vmap, batch 1024: {per_s:.0f} sims/s")
    return per_s


class _Jacobians(NamedTuple):
    """The sweep's Jacobians per second, and the seconds their first run spent
    compiling."""

    per_s: float
    compile_s: float


def _jacobian_throughput(columns, jacobian_batch: int, log) -> _Jacobians:
    """The sweep with the Jacobian of the design parameters, at `jacobian_batch`."""
    designs = _spread(columns, jacobian_batch)
    first = _timed_sweep(designs, wrt=rj.DESIGN_PARAMETERS).seconds
    run = min(_timed_sweep(designs, wrt=rj.DESIGN_PARAMETERS).seconds for _ in range(2))
    per_s = jacobian_batch / run
    log(f"  jacobians (4 parameters, batch {jacobian_batch}): {per_s:.0f}/s")
    return _Jacobians(per_s, max(first - run, 0.0))


class _Hardware(NamedTuple):
    """The all-hardware sweep: its sims/s and its (fastest run's) result."""

    sims_per_s: float
    result: Any


def _hardware_throughput(size: int, log) -> _Hardware:
    """All the hardware on, at batch `size` (its steps per design go beside the paper
    model's)."""
    hardware = hardware_designs(size)
    _timed_sweep(hardware)
    result, seconds = min((_timed_sweep(hardware) for _ in range(2)), key=lambda r: r.seconds)
    per_s = size / seconds
    log(
        f"  hardware designs (3-round burst, 8 knots, recuperator), batch {size}: "
        f"{per_s:.0f} sims/s"
    )
    return _Hardware(per_s, result)


def _envelope_throughput(size: int, log, absorber: bool = True) -> _Hardware:
    """The firing envelope on (`envelope_designs`), at batch `size`, beside the paper
    model's sweep of the same size."""
    designs = envelope_designs(size, absorber=absorber)
    _timed_sweep(designs)
    result, seconds = min((_timed_sweep(designs) for _ in range(2)), key=lambda r: r.seconds)
    per_s = size / seconds
    which = "" if absorber else " without the absorber"
    log(f"  envelope designs{which} (friction, stop, buffer, preload, mount), batch {size}: "
        f"{per_s:.0f} sims/s")  # fmt: skip
    return _Hardware(per_s, result)


class _Baseline(NamedTuple):
    """The scipy loop's sims/s, and the largest relative difference of our peaks from
    its peaks."""

    sims_per_s: float
    max_rel_error: float


def _scipy_baseline(columns, scipy_designs: int, log) -> _Baseline:
    """The baseline, in its strongest form: scipy's best method for this model at our
    tolerances (`SCIPY_SETTINGS`), the hard switches and the peaks located as events,
    one design at a time on one core, on `scipy_designs` designs spread over the set."""
    chosen = _spread(columns, scipy_designs)
    # Warm: the first solve also imports scipy.integrate and fills its caches, which
    # made a 20-design loop timed cold run at 0.6-0.7 times the rate.
    rj.reference_peaks({k: float(v[0]) for k, v in chosen.items()}, t1=10.0, **SCIPY_SETTINGS)
    start = time.perf_counter()
    baseline = [
        rj.reference_peaks({k: float(v[i]) for k, v in chosen.items()}, t1=10.0, **SCIPY_SETTINGS)
        for i in range(scipy_designs)
    ]
    per_s = scipy_designs / (time.perf_counter() - start)
    ours = rj.sweep(chosen, progress=False).peaks
    errors = [
        abs(float(ours[key][i]) / ref[key] - 1.0)
        for i, ref in enumerate(baseline)
        for key in ("peak_displacement", "peak_anchoring_force")
    ]
    log(f"  scipy solve_ivp ({_scipy_label()}, serial): {per_s:.1f} sims/s")
    return _Baseline(per_s, max(errors))


def format_bench(result: dict) -> str:
    """The figures of `run_bench` as the lines `recoil-jax bench` prints."""
    lines = [f"{'batch size':>10s} {'sims/s':>10s} {'seconds':>9s}"]
    for row in result["batches"]:
        lines.append(f"{row['batch_size']:10d} {row['sims_per_s']:10.0f} {row['seconds']:9.3f}")
    anchored = result["compiled_scalar_loop"]
    if anchored is not None:
        theirs, ours = anchored["anchor"], anchored["ours"]
        lines.append(
            f"compiled scalar loop (numba, 1 core, to t1, {anchored['designs']} designs): "
            f"{theirs['sims_per_s']:.0f} sims/s, {theirs['mean_steps']:.1f} steps a design, "
            f"{theirs['steps_per_s_per_core'] / 1e6:.2f} M steps/s; ours "
            f"{ours['steps_per_s_per_core'] / 1e6:.2f} M steps/s per core "
            f"({ours['mean_steps']:.1f} steps, {ours['cores']} cores): the loop leads "
            f"{anchored['ratio_per_step']:.1f}x per step, {anchored['ratio_per_design']:.1f}x "
            "per design per core"
        )
    else:
        lines.append("compiled scalar loop: not run (needs numba, the bench extra)")
    lines += [
        f"scipy solve_ivp loop ({_scipy_label()}, hard switches as events, one core): "
        f"{result['scipy_sims_per_s']:.1f} sims/s",
        f"best: {result['sims_per_s']:.0f} sims/s at batch {result['batch_size']} = "
        f"{result['speedup_vs_scipy']:.0f}x the scipy loop",
        f"same sweep, one worker instead of {result['workers']}: "
        f"{result['one_worker_sims_per_s']:.0f} sims/s",
        f"plain vmap of the stepping loop (batch 1024): {result['plain_vmap_sims_per_s']:.0f} "
        "sims/s",
        f"jacobians (gap, m, k_r, c_r): {result['jacobians_per_s']:.0f}/s",
        f"all the hardware (3-round burst of 5 ms pulses, 8-knot orifice, recuperator): "
        f"{result['hardware_sims_per_s']:.0f} sims/s at batch {result['hardware_batch_size']}, "
        f"{result['hardware_mean_steps']:.0f} steps a design, "
        f"{result['hardware_failed']} failed",
        f"the firing envelope (friction, battery stop, counter-recoil buffer, preload, mount; "
        f"each solved to its rest): {result['envelope_sims_per_s']:.0f} sims/s at batch "
        f"{result['hardware_batch_size']} ({result['envelope_vs_paper']:.2f}x the paper "
        f"model's at that batch; goal 0.5x), {result['envelope_mean_steps']:.0f} steps a "
        f"design (max {result['envelope_max_steps']}), its time over its mean steps "
        f"{result['envelope_time_per_mean_step_vs_paper']:.2f}x the paper model's (goal "
        f"1.5x), {result['envelope_failed']} failed; without the absorber "
        f"{result['envelope_no_absorber_sims_per_s']:.0f} sims/s "
        f"({result['envelope_no_absorber_vs_paper']:.2f}x), "
        f"{result['envelope_no_absorber_mean_steps']:.0f} steps a design, "
        f"{result['envelope_no_absorber_failed']} failed",
        f"compile: {result['compile_s']:.2f} s (solve), {result['jacobian_compile_s']:.2f} s "
        "(jacobian)",
        f"max relative error vs the scipy baseline's peaks: {result['max_rel_error']:.1e}",
        f"devices: {', '.join(result['devices'])}; XLA_FLAGS: {result['xla_flags'] or '(none)'}",
        f"host: {_host_label(result['host'])} (figures from another host do not compare)",
    ]
    if result["gradient_modes"]:
        lines.append(
            f"gradient of the peak anchoring force ({result['gradient_study']}), ms: "
            "parameters, plain solve, forward sensitivities, reverse through the steps, "
            "their largest difference"
        )
    for row in result["gradient_modes"]:
        lines.append(
            f"{row['parameters']:10d} {row['plain_ms']:8.1f} {row['forward_ms']:8.1f} "
            f"{row['reverse_ms']:8.1f} {row['max_rel_difference']:10.1e}"
        )
    if result["cli_cache"]:
        lines.append("command line, first and second run (compilation cache on):")
    for row in result["cli_cache"]:
        lines.append(
            f"  recoil-jax {row['command']}: {row['first_s']:.2f} s, then "
            f"{row['second_s']:.2f} s ({row['second_s'] / row['first_s']:.2f} of the first)"
        )
    if not result["gradient_modes"] and not result["cli_cache"]:
        lines.append("(--full adds gradients by forward and reverse mode and the CLI's cache)")
    return "\n".join(lines)


def _host_label(host: dict) -> str:
    """A host (`host_description`) in a few words: CPU, vector extension, cores."""
    extension = host["vector_extension"]
    extension = extension.upper() if extension else "vector extensions unknown"
    return f"{host['cpu']}, {extension}, {host['cores']} cores"


def _scipy_label() -> str:
    """The scipy baseline's method and tolerances, in a few words."""
    s = SCIPY_SETTINGS
    return f"{s['method']}, rtol {s['rtol']:g}, atol {s['atol']:g}"


def main_bench(args) -> int:
    """`recoil-jax bench`: run the benchmark at the sizes the options ask for, and print
    its figures (as lines, or one JSON object)."""
    sizes = (1, 64, 1024) if args.quick else (1, 64, 1024, 16384)
    full = args.full and not args.quick
    result = run_bench(
        batch_sizes=sizes,
        scipy_designs=5 if args.quick else 20,
        jacobian_batch=64 if args.quick else 4096,
        gradient_sizes=(1, 4, 8, 16, 22) if full else (),
        cli_commands=CLI_COMMANDS if full else (),
    )
    print(json.dumps(result) if args.json else format_bench(result))
    return 0


def add_command(commands: Commands) -> None:
    """`recoil-jax bench`'s arguments."""
    bench = commands.add(
        "bench",
        main_bench,
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
    add_json(bench, "one JSON object")
    bench.add_argument("--quick", action="store_true", help="small batches (a smoke run)")
    bench.add_argument(
        "--full", action="store_true", help="add the gradient modes and the CLI cache timings"
    )
