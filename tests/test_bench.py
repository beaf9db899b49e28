"""The benchmark runs and reports what it promises (speed itself is not asserted), and
its anchor, the compiled scalar loop, solves the library's model."""

import os
import platform
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import recoil_jax as rj
import recoil_jax.extend as rjx
from recoil_jax._model.equations import (
    RECOIL_TERM,
    initial_state,
    model_args,
    tracked_metrics,
    vector_field,
)
from recoil_jax._model.stepping import integrate_peaks
from recoil_jax._sweeps.memory import cores
from recoil_jax.apps._bench.anchor import anchor_field, anchor_peaks
from recoil_jax.apps._bench.speed import (
    _host_label,
    bench_designs,
    format_bench,
    host_description,
    run_bench,
)

pytest.importorskip("numba")


def test_the_compiled_scalar_loop_solves_the_library_model():
    """The anchor is a yardstick only if it does the library's work: its vector field is
    the library's at random states (in contact and out, both damping regimes), and run to
    t1 it takes the steps the library's loop takes there (same tableau and step-size rule;
    the grids drift apart by rounding) and finds the same peaks, read at step ends (so at
    most the located peak, up to the solver's accuracy)."""
    designs = bench_designs(128, seed=3)
    rng = np.random.default_rng(0)
    n = len(designs["m"])
    x_barrel = rng.uniform(0.0, 0.2, n)
    states = np.column_stack(
        [
            x_barrel,
            rng.uniform(-1.0, 1.0, n),
            x_barrel - designs["gap"] + rng.uniform(-2e-4, 2e-4, n),  # around the contact
            rng.uniform(-1.0, 1.0, n),
        ]
    )
    states[::7, 1] = rng.uniform(-1e-4, 1e-4, len(states[::7]))  # inside the damping band
    params, _ = rjx.batch_params(designs)
    smoothing = rj.Smoothing()
    ours = jax.vmap(lambda p, y: jnp.stack(vector_field(0.0, y, model_args(p, smoothing))))(
        params, jnp.asarray(states)
    )
    np.testing.assert_allclose(anchor_field(states, designs), ours, rtol=1e-12, atol=1e-12)

    anchor = anchor_peaks(designs)
    options = rj.SolverOptions(rtol=1e-6, atol=1e-9)
    run = eqx.filter_jit(
        jax.vmap(
            lambda p: integrate_peaks(
                RECOIL_TERM,
                initial_state(model_args(p, smoothing)),
                model_args(p, smoothing),
                10.0,
                tracked_metrics,
                options,
            )
        )
    )(params)
    steps = np.asarray(run.num_steps)
    assert abs(anchor["num_steps"].mean() / steps.mean() - 1) < 0.02
    best = dict(zip(run.names, np.asarray(run.best).T, strict=True))
    for name in ("peak_displacement", "peak_anchoring_force"):
        ratio = anchor[name] / best[name]
        assert np.all(ratio < 1 + 1e-4) and np.all(ratio > 1 - 5e-3), (name, ratio.min())
    assert anchor["seconds"] > 0


def test_the_host_is_described():
    """The bench's figures carry the machine they come from (figures from two hosts do
    not compare): its CPU, the widest vector extension the CPU lists, and the cores."""
    host = host_description()
    assert host["cpu"] and 1 <= host["cores"] <= (os.cpu_count() or 1)
    info = Path("/proc/cpuinfo")
    if platform.machine().lower() in ("x86_64", "amd64") and info.exists():
        flags = next(
            set(line.split(":", 1)[1].split())
            for line in info.read_text().splitlines()
            if line.startswith("flags")
        )
        # The widest the CPU lists: the one named is there, and none wider is.
        named = host["vector_extension"]
        ladder = ("avx512f", "avx2", "avx", "sse4_2")
        if named is None:
            assert not flags & set(ladder)
        else:
            assert named in flags and not flags & set(ladder[: ladder.index(named)])
    label = _host_label({**host, "vector_extension": None})
    assert "vector extensions unknown" in label and str(host["cores"]) in label


@pytest.mark.slow
def test_bench_smoke():
    result = run_bench(
        batch_sizes=(1, 8),
        scipy_designs=2,
        jacobian_batch=4,
        gradient_sizes=(2,),
        # The paper model's study: the burst_recuperator default's reverse-mode program
        # alone compiles for ~22 s, and the smoke test checks the plumbing, not the size.
        gradient_study="tuned_absorber",
        cli_commands=(("simulate", "m=0", "--json"),),
        log=lambda msg: None,
    )
    for key in (
        "sims_per_s",
        "batch_size",
        "scipy_sims_per_s",
        "jacobians_per_s",
        "compile_s",
        "max_rel_error",
    ):
        assert key in result
    assert result["sims_per_s"] > 0 and result["scipy_sims_per_s"] > 0
    assert result["scipy_settings"]["method"] == "DOP853"
    anchored = result["compiled_scalar_loop"]
    assert anchored["designs"] == 8 and anchored["anchor"]["cores"] == 1
    assert anchored["ratio_per_step"] > 0 and anchored["ratio_per_design"] > 0
    assert anchored["anchor"]["mean_steps"] > anchored["ours"]["mean_steps"]  # no early stop
    assert "compiled scalar loop (numba, 1 core" in format_bench(result)
    assert result["host"] == host_description()
    assert f"host: {result['host']['cpu']}" in format_bench(result)
    assert result["jacobians_per_s"] > 0 and result["compile_s"] >= 0
    # Both solve the same model to rtol ~1e-5: peaks agree well inside 1e-3.
    assert result["max_rel_error"] < 1e-3
    assert "x the scipy loop" in format_bench(result)
    assert result["hardware_sims_per_s"] > 0 and result["hardware_failed"] == 0
    assert result["hardware_mean_steps"] > 0
    assert result["envelope_sims_per_s"] > 0 and result["envelope_failed"] == 0
    assert result["envelope_vs_paper"] > 0 and "the firing envelope" in format_bench(result)
    assert result["envelope_max_steps"] >= result["envelope_mean_steps"] > 0
    assert result["envelope_time_per_mean_step_vs_paper"] > 0
    assert "its time over its mean steps" in format_bench(result)
    assert result["envelope_no_absorber_sims_per_s"] > 0
    assert result["envelope_no_absorber_failed"] == 0
    assert [row["batch_size"] for row in result["batches"]] == [1, 8]
    assert result["batch_size"] in (1, 8)
    assert "(tuned_absorber), ms" in format_bench(result)
    (row,) = result["gradient_modes"]
    assert row["parameters"] == 2
    assert row["plain_ms"] > 0 and row["forward_ms"] > 0 and row["reverse_ms"] > 0
    assert row["max_abs_gradient"] > 0  # a comparison of something, not of zeros
    # Forward sensitivities and the derivative of the discrete steps: same gradient to
    # within the solver's accuracy, on a design of the study (no kink at its peak).
    assert row["max_rel_difference"] < 1e-2
    (cli,) = result["cli_cache"]
    assert cli["first_s"] > 0 and cli["second_s"] > 0
    assert "then" in format_bench(result)


@pytest.mark.slow
def test_calibration_bench_reports_both_fits():
    """`bench-calibration` fits the same tests both ways and reports every figure."""
    from recoil_jax.apps._bench.calibration import (
        format_calibration_bench,
        run_calibration_bench,
    )

    result = run_calibration_bench(
        samples=401, draws=2, scipy_draws=1, starts=2, prediction_samples=100, cli=False,
        burst_seeds=1, log=lambda m: None,
    )  # fmt: skip
    one = result["one_fit"]
    assert one["ours_s"] > 0 and one["scipy_solves"] > 0
    # Both ways reach the same optimum (the models differ by the smoothing only).
    assert one["max_apart_stderr"] < 0.5 and result["many_fits"]["max_apart_stderr"] < 0.5
    assert [r["trace"] for r in result["random_starts"]] == ["absorber", "burst", "burst"]
    assert [r["seeds"] for r in result["random_starts"]] == [[3, 5], [3, 5], [100, 200]]
    text = format_calibration_bench(result)
    assert "scipy" in text and "random starts" in text and "prediction band" in text
    bursts = result["random_starts"][1:]
    total = f"burst, all 2 traces: of 4 random starts, ours reached the best from " \
            f"{sum(r['ours_reached'] for r in bursts)}, scipy from "  # fmt: skip
    assert total in text


@pytest.mark.slow
def test_sensitivity_bench_reports_every_figure():
    """`bench-sensitivity` runs both methods and the scipy loop on the same designs; the
    methods agree with SALib's finite differences and the scipy peaks with ours."""
    from recoil_jax.apps._bench.sensitivity import (
        format_sensitivity_bench,
        run_sensitivity_bench,
    )

    result = run_sensitivity_bench(base_samples=64, scipy_designs=4, log=lambda m: None)
    assert result["sobol"]["designs"] == 64 * 18 and result["dgsm"]["designs"] == 64
    assert result["sobol"]["warm_s"] > 0 and result["scipy"]["all_designs_s"] > 0
    assert result["dgsm"]["sobol_under_bound"]
    assert result["dgsm"]["exact_apart_in_intervals"] < 3.0
    # Hard switches (scipy) against the smoothed model: the paper's 1e-4 level.
    assert result["scipy"]["max_relative_apart"] < 1e-3
    assert "scipy solve_ivp loop" in format_sensitivity_bench(result)


@pytest.mark.slow
def test_posterior_bench_reports_both_samplers_on_one_density():
    """`bench-calibration --posterior`: NUTS and emcee sample the same density (emcee's
    within 0.01 of NUTS's, their means within a posterior sd on small runs), on the same
    budget of solves; the chains one after another and in lockstep make the same number
    of transitions; on the envelope plan's firings too; every figure is reported."""
    from recoil_jax.apps._bench.posterior import format_posterior_bench, posterior_bench

    result = posterior_bench(samples=401, draws=100, warmup=100, chains=2, walkers=16,
                             lockstep_transitions=4, envelope_draws=100, log=lambda m: None,
                             progress=False)  # fmt: skip
    nuts, emcee = result["nuts"], result["emcee"]
    assert nuts["solves"] > 0 and nuts["ess_per_s"] > 0 and emcee["ess_per_s"] > 0
    # The chains at once on the cores (emcee's points split over as many threads: its
    # density through the split is NUTS's, below).
    assert nuts["parallel_chains"] == min(2, cores())
    # The same budget: emcee's steps are whole ensembles of 16 solves.
    assert nuts["solves"] - 16 < emcee["solves"] <= nuts["solves"]
    assert emcee["log_density_apart"] < 0.01
    assert result["means_apart_sd"] < 1.0
    lock = result["lockstep"]
    assert lock["sequential_s"] > 0 and lock["vmapped_s"] > 0
    assert lock["lockstep_steps"] >= lock["leapfrog_steps"] > 0
    # The envelope plan's firings: the round trip's traces, its fit's defaults; the
    # posterior's means on the truth (measured, 2 x 100 draws: within 1.9 sd; 4 x 200: 1.8).
    envelope = result["envelope"]
    assert envelope["nuts"]["solves"] > 0 and envelope["nuts"]["ess_per_s"] > 0
    assert len(envelope["firings"]) == 3 and envelope["measurements"] == 3 * 2 * 3001
    assert set(envelope["truth_apart_sd"]) == set(envelope["values"])
    assert max(envelope["truth_apart_sd"].values()) < 4.0, envelope["truth_apart_sd"]
    text = format_posterior_bench(result)
    assert "NUTS over emcee" in text and "vmapped" in text
    assert "envelope plan's firings" in text and "apart from the truth" in text
