"""`recoil-jax bench-calibration --posterior`: the posterior's speed on the 5-value fit
that `bench-calibration` times (the absorber's k, c_out, c_ret, gap and m from one firing
of x_M and F_AN), beside emcee, the sampler a Python engineer tries first.

Measured in one run, each figure with compilation excluded:

- **NUTS** (`sample_posterior`, its defaults): bulk ESS per second of sampling (the
  least over the values), the model solves it made (its leapfrog steps, each a solve
  with the forward sensitivities) and ESS per thousand solves;
- **emcee** in its strongest honest form: the same log density (the same priors,
  coordinates and likelihood), vectorised over the walkers in one compiled program, each
  point one solve of the state alone (no sensitivities: a sixth to a tenth of a
  gradient's cost, at tolerances a hundredth of the likelihood's so that its density is
  NUTS's to 0.01: `EMCEE_TOLERANCE`);
  its walkers start where NUTS's chains do (the least-squares optimum spread by the
  posterior's curvature), burn in on as many solves as NUTS's warm-up made, then sample
  on as many as NUTS's sampling made; its ESS from its own integrated autocorrelation
  time (`get_autocorr_time`, the walkers are not independent chains);
- **chains in lockstep** (`vmap`) against one after another: the same NUTS transitions
  from the same states, step size and mass matrix, both compiled.
- **the envelope plan's firings** (`envelope_posterior`): NUTS alone on the round
  trip's first traces (the shipped plan's firings by the reference solver, with the
  plan's noise), fitted by `calibrate` as a user runs it; each posterior mean's distance
  from the truth, in posterior sds.

Figures printed, never asserted (`docs/calibration.md`).
"""

from __future__ import annotations

import dataclasses
import importlib.util
import math
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import recoil_jax as rj
from recoil_jax._calibration.posterior import PosteriorDensity, posterior_density
from recoil_jax._sweeps.memory import cores

from .firing import calibration_of, firing_test
from .round_trip import ROUND_TRIP_PLAN, plan_file, planned_calibration, shipped_plan, truth_of

__all__ = [
    "envelope_posterior",
    "format_envelope_posterior",
    "format_posterior_bench",
    "posterior_bench",
]

#: emcee's walkers: a few times the values, as its documentation advises (and an even
#: number, for its stretch move's two halves).
WALKERS = 32
#: emcee's autocorrelation time is reliable once the run is this many times it.
EMCEE_RELIABLE = 50
#: emcee's solve of the state alone at the likelihood's tolerances times this: NUTS's
#: solve controls the error of the sensitivities too, which makes its signals 10³ times
#: more accurate than the state's alone at the same tolerances (measured on the paper
#: absorber: 8e-7 against 4e-4 noise units, log densities 0.1–2 apart). At a hundredth
#: both densities agree to 0.004 (at a tenth, 0.75), for a quarter more a solve.
EMCEE_TOLERANCE = 0.01
#: Draws and warm-up steps a chain on the envelope plan's firings: its solves are 11
#: times the 5-value fit's (3 firings of 3 s at 1 kHz, the envelope's forces). At 30 the
#: warm-up is too short to adapt (measured: 18 of 60 transitions divergent).
ENVELOPE_DRAWS = 200


def emcee_data(data):
    """The likelihood's `data` with the tolerances emcee's solve of the state alone
    needs to give NUTS's density (`EMCEE_TOLERANCE`)."""
    options = dataclasses.replace(data.options, rtol=data.options.rtol * EMCEE_TOLERANCE,
                                  atol=data.options.atol * EMCEE_TOLERANCE)  # fmt: skip
    return eqx.tree_at(lambda d: d.options, data, options)


def _emcee(density: PosteriorDensity, burn_solves: int, solves: int, walkers: int, seed: int,
           log) -> dict:  # fmt: skip
    """emcee on the posterior's own log density (`density`, its solve of the state alone
    at `emcee_data`'s tolerances): burn-in on `burn_solves` solves, then sampling on
    `solves`. The walkers' points are evaluated one after another in one compiled program
    (a vmapped solve selects its whole carry, the saved signals included, at every step:
    measured, 97–150 ms a point against 0.7 ms), split over the cores on threads as
    NUTS's chains are."""
    import emcee

    alone = density._replace(data=emcee_data(density.data))
    many = jax.jit(lambda points: jax.lax.map(lambda w: alone.log_density(w, False), points))
    nuts = jax.jit(jax.vmap(density.log_density))
    threads = cores()
    pool = ThreadPoolExecutor(threads, thread_name_prefix="walkers")

    def log_density(points):
        parts = np.array_split(np.asarray(points), min(threads, len(points)))
        return np.concatenate(list(pool.map(lambda part: np.asarray(many(part)), parts)))

    labels = density.layout.labels
    start = np.random.default_rng(seed).standard_normal((walkers, len(labels)))
    # The density emcee samples against NUTS's, at its starting points.
    apart = np.max(np.abs(log_density(start) - np.asarray(nuts(jnp.asarray(start)))))
    # The stretch move updates half the walkers at a time: one step is `walkers` solves.
    burn, steps = max(1, burn_solves // walkers), max(2, solves // walkers)
    sampler = emcee.EnsembleSampler(walkers, len(labels), log_density, vectorize=True)
    with pool:
        state = sampler.run_mcmc(start, burn)
        sampler.reset()
        started = time.perf_counter()
        sampler.run_mcmc(state, steps)
        seconds = time.perf_counter() - started
    theta = np.asarray(density.theta(jnp.asarray(sampler.get_chain())))  # (steps, walkers, P)
    flat = theta.reshape(-1, theta.shape[-1])
    tau = np.asarray(emcee.autocorr.integrated_time(theta, quiet=True))
    ess = walkers * steps / tau
    log(f"  emcee: {walkers} walkers, {steps} steps after {burn} of burn-in, {seconds:.1f} s; "
        f"autocorrelation {tau.max():.0f} steps at the most")  # fmt: skip
    return {
        "walkers": walkers,
        "threads": threads,
        "burn_in_steps": burn,
        "steps": steps,
        "solves": walkers * steps,
        "sampling_s": seconds,
        "acceptance": float(np.mean(sampler.acceptance_fraction)),
        "log_density_apart": float(apart),
        "autocorrelation_steps": dict(zip(labels, tau.tolist(), strict=True)),
        "reliable": bool(steps >= EMCEE_RELIABLE * tau.max()),
        "ess": dict(zip(labels, ess.tolist(), strict=True)),
        "least_ess": float(ess.min()),
        "ess_per_s": float(ess.min() / seconds),
        "ess_per_1000_solves": float(1000.0 * ess.min() / (walkers * steps)),
        "mean": dict(zip(labels, flat.mean(axis=0).tolist(), strict=True)),
    }


def _lockstep(density: PosteriorDensity, posterior, chains: int, transitions: int,
              log) -> dict:  # fmt: skip
    """The same NUTS transitions, chains one after another against `vmap`ped: from the
    same states (`w` standard normal: the coordinates are whitened), with the chains'
    mean step size and a unit mass matrix, both compiled."""
    import blackjax

    step = jnp.asarray(float(np.mean(posterior.step_size)))
    mass = jnp.ones(len(posterior.labels))
    kernel: Any = blackjax.nuts(density.log_density, step_size=step, inverse_mass_matrix=mass)
    w0 = jnp.asarray(np.random.default_rng(1).standard_normal((chains, len(posterior.labels))))
    states = jax.vmap(kernel.init)(w0)
    keys = jax.random.split(jax.random.key(2), chains)

    def one(key, state):
        return density.nuts_transitions(key, state, step, mass, transitions)

    alone, together = jax.jit(one), jax.jit(jax.vmap(one))
    pick = lambda c: jax.tree.map(lambda a: a[c], states)  # noqa: E731
    jax.block_until_ready(alone(keys[0], pick(0)))  # compiles
    jax.block_until_ready(together(keys, states))
    started = time.perf_counter()
    steps_alone = sum(int(jnp.sum(jax.block_until_ready(alone(keys[c], pick(c)))[1].steps))
                      for c in range(chains))  # fmt: skip
    alone_s = time.perf_counter() - started
    started = time.perf_counter()
    _, block = jax.block_until_ready(together(keys, states))
    together_s = time.perf_counter() - started
    steps_together = int(jnp.sum(block.steps))
    # In lockstep each transition waits for the batch's longest trajectory.
    waited = int(jnp.sum(jnp.max(block.steps, axis=0))) * chains
    log(f"  {chains} chains x {transitions} transitions: one after another {alone_s:.2f} s, "
        f"vmapped {together_s:.2f} s")  # fmt: skip
    return {
        "chains": chains,
        "transitions": transitions,
        "sequential_s": alone_s,
        "vmapped_s": together_s,
        "vmapped_over_sequential": together_s / alone_s,
        "sequential_steps": steps_alone,
        "leapfrog_steps": steps_together,
        "same_steps": steps_alone == steps_together,
        "lockstep_steps": waited,
    }


def _nuts_figures(posterior, warmup: int) -> dict:
    """A sampled posterior's figures: its seconds, solves, ESS and ESS per second."""
    chains, draws = posterior.draws.shape[:2]
    solves = int(posterior.inference_data.sample_stats["n_steps"].sum())
    seconds = posterior.seconds
    # The warm-up's solves are not recorded: its time over the sampling's time a solve.
    warmup_solves = round(seconds["warmup"] * solves / seconds["sampling"])
    least = min(row["ess_bulk"] for row in posterior.summary.values())
    return {
        "draws": draws,
        "warmup": warmup,
        "chains": chains,
        "parallel_chains": posterior.parallel_chains,
        "compile_s": seconds["compile"],
        "warmup_s": seconds["warmup"],
        "sampling_s": seconds["sampling"],
        "solves": solves,
        "warmup_solves": warmup_solves,
        # Wall time over the solves of every chain: the chains ran `parallel_chains` at once.
        "ms_per_solve": 1000.0 * seconds["sampling"] / solves,
        "ess": {k: row["ess_bulk"] for k, row in posterior.summary.items()},
        "least_ess": least,
        "ess_per_s": posterior.ess_per_second,
        "ess_per_1000_solves": 1000.0 * least / solves,
        "converged": posterior.converged,
        "divergences": posterior.divergences,
        "mean": {k: row["mean"] for k, row in posterior.summary.items()},
        "sd": {k: row["sd"] for k, row in posterior.summary.items()},
    }


def posterior_bench(
    samples: int = 5001,
    draws: int = 1000,
    warmup: int = 1000,
    chains: int = 4,
    walkers: int = WALKERS,
    lockstep_transitions: int = 10,
    envelope_draws: int = ENVELOPE_DRAWS,
    log=None,
    progress: bool = True,
) -> dict:
    """NUTS against emcee, and chains in lockstep against one after another, on the
    bench's 5-value fit of one firing of `samples` samples; then NUTS alone on the
    envelope plan's firings, `envelope_draws` draws after as many warm-up steps a chain
    (0: not; `envelope_posterior`). Module docstring."""
    log = log or (lambda message: print(message, file=sys.stderr, flush=True))
    if importlib.util.find_spec("emcee") is None:  # before anything is fitted or sampled
        raise rj.ParameterError(
            "the posterior's benchmark compares with emcee: pip install 'recoil-jax[bench]'"
        )
    if envelope_draws:  # nor here
        plan_file(ROUND_TRIP_PLAN)
    ts, measured = firing_test({}, samples, 1.0, seed=7)
    calibration = calibration_of({}, ts, measured)
    fit = rj.calibrate(calibration, starts=1, progress=False)
    posterior = rj.sample_posterior(calibration, fit=fit, draws=draws, warmup=warmup,
                                    chains=chains, seed=0, progress=False)  # fmt: skip
    nuts = _nuts_figures(posterior, warmup)
    log(f"  NUTS: {chains} chains x {draws} draws, {nuts['sampling_s']:.1f} s, "
        f"{nuts['solves']} solves, least bulk ESS {nuts['least_ess']:.0f}")  # fmt: skip
    density = posterior_density(calibration, fit)
    layout = density.layout
    emcee = _emcee(density, nuts["warmup_solves"], nuts["solves"], walkers, seed=0, log=log)
    # The two samplers' means apart, in the posterior's sds: both sample one density.
    apart = max(abs(emcee["mean"][k] - nuts["mean"][k]) / nuts["sd"][k] for k in layout.labels)
    return {
        "samples": samples,
        "values": list(layout.labels),
        "nuts": nuts,
        "emcee": emcee,
        "ratio_ess_per_s": nuts["ess_per_s"] / emcee["ess_per_s"],
        "ratio_ess_per_solve": nuts["ess_per_1000_solves"] / emcee["ess_per_1000_solves"],
        "means_apart_sd": apart,
        "lockstep": _lockstep(density, posterior, chains, lockstep_transitions, log),
        "envelope": (
            envelope_posterior(envelope_draws, envelope_draws, chains, log=log, progress=progress)
            if envelope_draws
            else None
        ),
    }


def envelope_posterior(
    draws: int = ENVELOPE_DRAWS,
    warmup: int = ENVELOPE_DRAWS,
    chains: int = 4,
    plan_path=ROUND_TRIP_PLAN,
    log=None,
    progress: bool = True,
) -> dict:
    """NUTS (`sample_posterior`, its defaults but the sizes) on the envelope plan's
    firings: the round trip's first traces (truth 0, draw 0: `round_trip`), fitted by
    `calibrate` as a user runs it. Each value's posterior mean is also given apart from
    the truth, in posterior sds."""
    log = log or (lambda message: print(message, file=sys.stderr, flush=True))
    problem, plan, report = shipped_plan(plan_path)
    truth = truth_of(problem, 0)
    calibration = planned_calibration(plan, report, truth, seed=0)
    log(f"  the envelope plan's {len(report.firings)} firings ({plan_path}): fitting")
    started = time.perf_counter()
    fit = rj.calibrate(calibration, progress=False)
    fit_s = time.perf_counter() - started
    log(f"  fitted in {fit_s:.1f} s ({fit.verdict}); sampling")
    posterior = rj.sample_posterior(calibration, fit=fit, draws=draws, warmup=warmup,
                                    chains=chains, seed=0, progress=progress)  # fmt: skip
    nuts = _nuts_figures(posterior, warmup)
    return {
        "plan": str(plan_path),
        "firings": [plan.conditions[c] | {"signals": list(s)} for c, s in report.firings],
        "measurements": sum(e.trace.t.size * len(e.trace.signals) for e in calibration.experiments),
        "values": list(posterior.labels),
        "fit_s": fit_s,
        "truth": truth,
        "truth_apart_sd": {k: abs(nuts["mean"][k] - v) / nuts["sd"][k] for k, v in truth.items()},
        "nuts": nuts,
    }


def _nuts_line(nuts: dict) -> str:
    return (
        f"{nuts['chains']} chains x {nuts['draws']} draws after {nuts['warmup']} "
        f"warm-up, {nuts['parallel_chains']} at once, sampling {nuts['sampling_s']:.1f} s "
        f"(compile {nuts['compile_s']:.1f} s, warm-up {nuts['warmup_s']:.1f} s); "
        f"{nuts['solves']} solves with sensitivities, {nuts['ms_per_solve']:.2f} ms of wall "
        f"time each; least bulk ESS {nuts['least_ess']:.0f}: {nuts['ess_per_s']:.1f} ESS/s, "
        f"{nuts['ess_per_1000_solves']:.1f} per 1000 solves"
        f" ({'converged' if nuts['converged'] else 'NOT converged'},"
        f" {nuts['divergences']} divergences)"
    )


def format_posterior_bench(result: dict) -> str:
    """The figures as text."""
    nuts, emcee, lock = result["nuts"], result["emcee"], result["lockstep"]
    values = ", ".join(result["values"])
    lines = [
        f"The posterior of one firing ({result['samples']} samples of x_M and F_AN; {values})",
        "  NUTS : " + _nuts_line(nuts),
        f"  emcee: {emcee['walkers']} walkers x {emcee['steps']} steps after "
        f"{emcee['burn_in_steps']} burn-in, sampling {emcee['sampling_s']:.1f} s, "
        f"{emcee['solves']} solves (state alone, on {emcee['threads']} threads, "
        f"{1000.0 * emcee['sampling_s'] / emcee['solves']:.2f} ms of wall time each); least ESS "
        f"{emcee['least_ess']:.0f} (autocorrelation up to "
        f"{max(emcee['autocorrelation_steps'].values()):.0f} steps"
        f"{'' if emcee['reliable'] else ', run under 50 of it: an estimate'}): "
        f"{emcee['ess_per_s']:.1f} ESS/s, {emcee['ess_per_1000_solves']:.1f} per 1000 solves,"
        f" acceptance {emcee['acceptance']:.2f}; its log density within "
        f"{emcee['log_density_apart']:.1e} of NUTS's",
        f"  NUTS over emcee: {result['ratio_ess_per_s']:.2f}x in ESS/s, "
        f"{result['ratio_ess_per_solve']:.2f}x per solve; means apart by "
        f"<= {result['means_apart_sd']:.2f} posterior sd",
        f"  chains: {lock['chains']} x {lock['transitions']} NUTS transitions one after "
        f"another {lock['sequential_s']:.2f} s, vmapped {lock['vmapped_s']:.2f} s "
        f"({lock['vmapped_over_sequential']:.2f}x the time; in lockstep each transition "
        f"waits for the batch's longest: {lock['lockstep_steps']} leapfrog steps' time for "
        f"{lock['leapfrog_steps']} of work)",
    ]
    if not math.isfinite(result["ratio_ess_per_s"]):
        lines.append("  (a ratio is not finite: a sampler gave no ESS)")
    if result["envelope"]:
        lines.append(format_envelope_posterior(result["envelope"]))
    return "\n".join(lines)


def format_envelope_posterior(result: dict) -> str:
    """`envelope_posterior`'s figures as text."""
    nuts = result["nuts"]
    firings = "; ".join(
        f"{f['elevation']:g} deg, v0 {f['v0']:g} m/s: {', '.join(f['signals'])}"
        for f in result["firings"]
    )
    apart = ", ".join(f"{k} {v:.2f}" for k, v in result["truth_apart_sd"].items())
    return "\n".join([
        f"The posterior of the envelope plan's firings ({result['plan']}: {firings}; "
        f"{result['measurements']} measurements; {', '.join(result['values'])})",
        f"  fit: {result['fit_s']:.1f} s (calibrate, its defaults)",
        "  NUTS : " + _nuts_line(nuts),
        f"  posterior means apart from the truth, in posterior sds: {apart}",
    ])  # fmt: skip
