"""The benchmark runs and reports what it promises (speed itself is not asserted)."""

import pytest

from recoil_jax.apps._bench import format_bench, run_bench


@pytest.mark.slow
def test_bench_smoke():
    result = run_bench(
        batch_sizes=(1, 8),
        scipy_designs=2,
        jacobian_batch=4,
        gradient_sizes=(2,),
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
    assert result["jacobians_per_s"] > 0 and result["compile_s"] >= 0
    # Both solve the same model to rtol ~1e-5: peaks agree well inside 1e-3.
    assert result["max_rel_error"] < 1e-3
    assert "x the scipy loop" in format_bench(result)
    assert result["hardware_sims_per_s"] > 0 and result["hardware_failed"] == 0
    assert result["hardware_mean_steps"] > 0
    assert [row["batch_size"] for row in result["batches"]] == [1, 8]
    assert result["batch_size"] in (1, 8)
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
