"""The optimiser: differentiable peaks, the smooth maximum, constraints, one compilation,
agreement with a dense grid, and the study command line."""

import dataclasses
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from conftest import SMALL_STUDY, assert_complete_result, study_text

import recoil_jax as rj
import recoil_jax.extend as rjx

ROOT = Path(__file__).resolve().parents[1]
PAPER_BEST = rj.RecoilParams(absorber=rj.Absorber(m=1500.0, gap=0.062))


@pytest.mark.slow
def test_grad_through_differentiable_peaks_equals_sensitivity_jacobian():
    """jax.grad (reverse), jax.jacfwd and value_and_grad of a function built on the
    metrics reproduce the forward-sensitivity Jacobian."""
    wrt = ("gap", "m", "k_r", "c_r")
    fn = rj.differentiable_peaks(PAPER_BEST, wrt)
    theta = jnp.array([0.05, 1400.0, 15000.0, 3000.0])

    def objective(th):
        metrics, _ = fn(th)
        return metrics["peak_anchoring_force"] + 1e4 * metrics["max_stroke"]

    value, grad = jax.jit(jax.value_and_grad(objective))(theta)
    forward = jax.jit(jax.jacfwd(objective))(theta)
    params = rj.RecoilParams(absorber=rj.Absorber(m=1400.0, gap=0.05, k_r=15000.0, c_r=3000.0))
    peaks, grads = rj.peak_jacobian(params, wrt=wrt)
    expected = np.asarray(grads.peak_anchoring_force) + 1e4 * np.asarray(grads.max_stroke)
    # Same solve, compiled in a different program: roundoff can move an accept/reject
    # decision and with it the step grid, so the two agree to within the solver's
    # gradient accuracy (rtol 1e-7; gradients to ~1e-5 relative), not bitwise.
    np.testing.assert_allclose(grad, expected, rtol=1e-5)
    np.testing.assert_allclose(forward, grad, rtol=1e-12)
    np.testing.assert_allclose(
        value, peaks.peak_anchoring_force + 1e4 * peaks.max_stroke, rtol=1e-8
    )


def _smooth_force(gap, temperature, options):
    params = rj.RecoilParams(absorber=rj.Absorber(m=1500.0, gap=gap))
    smooth = rj.SmoothMax(("peak_anchoring_force",), jnp.atleast_1d(temperature))
    fn = rj.differentiable_peaks(params, ("gap",), options=options, smooth_max=smooth)
    return fn(jnp.atleast_1d(gap))[0]["smooth_peak_anchoring_force"]


@pytest.mark.slow
def test_smooth_max_value_and_gradient():
    """The log-sum-exp maximum over time lies below the peak by a few temperatures, falls
    towards it as T shrinks, and its gradient matches central differences (before, at
    and after the kink of the optimum). One compilation each: gap and T are traced."""
    gaps = jnp.array([0.055, 0.062, 0.07])
    peak = np.asarray(
        rj.sweep({"m": np.full(3, 1500.0), "gap": np.asarray(gaps)}, progress=False).peaks[
            "peak_anchoring_force"
        ]
    )
    value_and_grad = jax.jit(jax.vmap(jax.value_and_grad(_smooth_force), (0, None, None)))
    tight = rj.SolverOptions(rtol=1e-11, atol=1e-14, max_steps=200_000)
    tight_values = jax.jit(jax.vmap(_smooth_force, (0, None, None)))
    h = 1e-6
    below = {}
    for temperature in (20.0, 2.0):
        values, grads = value_and_grad(gaps, temperature, rj.GRADIENT_OPTIONS)
        below[temperature] = peak - np.asarray(values)
        assert np.all((below[temperature] > 0) & (below[temperature] < 10 * temperature))
        fd = (
            np.asarray(tight_values(gaps + h, temperature, tight))
            - np.asarray(tight_values(gaps - h, temperature, tight))
        ) / (2 * h)
        # Scaled like the peak gradients: by the gap's range over the value.
        error = np.abs(np.asarray(grads) - fd) * 0.2 / peak
        assert np.all(error <= 1e-4), (np.asarray(grads), fd)
    assert np.all(below[2.0] < below[20.0])


@pytest.mark.slow
def test_paper_gap_optimum_matches_dense_grid_with_one_compilation():
    """Tuning the gap at m = 1500 lands on the dense grid's optimum (0.1 mm grid), traces
    the step once, and keeps every iterate inside the bounds."""
    problem = rj.DesignProblem(
        params=rj.RecoilParams(absorber=rj.Absorber(m=1500.0, gap=0.03)),
        objective=rj.Objective(
            {"peak_anchoring_force": 1.0}, temperatures={"peak_anchoring_force": 10.0}
        ),
        tune=("gap",),
        bounds={"gap": (0.0, 0.12)},
    )
    result = rj.optimise(problem, starts=4, steps=120, progress=False)
    assert result.compilations == 1
    assert_complete_result(result, "optax", 1)
    assert len(result.history["objective"]) > 1
    theta = result.history["theta"]
    assert np.all((theta >= 0.0) & (theta <= 0.12))
    grid = np.linspace(0.055, 0.07, 151)
    sweep = rj.sweep({"m": np.full_like(grid, 1500.0), "gap": grid}, progress=False)
    forces = sweep.peaks["peak_anchoring_force"]
    i = int(np.argmin(forces))
    best_gap = float(result.best_theta[0, 0])
    assert abs(best_gap - grid[i]) <= 2 * (grid[1] - grid[0]), (best_gap, grid[i])
    assert float(result.best_objective[0]) <= forces[i] * (1 + 1e-5)
    assert abs(float(result.best_objective[0]) - 5514.05) < 0.5
    # The clusters account for every run, best first; each cluster's objective is the
    # peak force of its design, and runs flagged as impact-free end with no contact.
    clusters = result.clusters()
    assert sorted(r for c in clusters for r in c["runs"]) == [0, 1, 2, 3]
    objectives = [c["objective"] for c in clusters]
    assert objectives == sorted(objectives)
    for cluster in clusters:
        gap = cluster["design"]["gap"]
        single = rj.peaks(
            rj.RecoilParams(absorber=rj.Absorber(m=1500.0, gap=gap)), options=rj.GRADIENT_OPTIONS
        )
        # (The optimiser's solve also carries sensitivities, hence its own step grid.)
        assert float(single.peak_anchoring_force) == pytest.approx(cluster["objective"], rel=1e-6)
        last_contact = result.history["peak_contact_force"][-1, cluster["runs"]]
        assert cluster["no_impact"] == int(np.sum(last_contact == 0.0))


def test_metric_constraint_is_held_and_active():
    """A stroke limit below the unconstrained optimum's stroke is held by the best design
    and is active there (the augmented Lagrangian pushes right up to it)."""
    limit = 0.11  # the unconstrained gap optimum has max stroke ≈ 0.118 m
    problem = rj.DesignProblem(
        params=rj.RecoilParams(absorber=rj.Absorber(m=1500.0, gap=0.062)),
        objective=rj.Objective({"peak_anchoring_force": 1.0}),
        tune=("gap", "c_r"),
        bounds={"gap": (0.0, 0.12), "c_r": (500.0, 8000.0)},
        constraints=(rj.Constraint("max_stroke", upper=limit),),
    )
    result = rj.optimise(problem, starts=3, steps=120, progress=False)
    design = result.best_params(0)
    # Held on an accurate solve: at rtol 1e-7 a stroke (a difference of two displacements)
    # carries ~5e-6 relative error, the size of the margin the optimiser leaves.
    peaks = rj.peaks(design, problem.smoothing, rj.SolverOptions(rtol=1e-10, atol=1e-13))
    assert float(peaks.max_stroke) <= limit
    assert float(peaks.max_stroke) >= 0.98 * limit
    # Better than the paper's design, which breaks the limit only barely less well.
    assert float(result.best_objective[0]) < 5600.0
    report = rj.constraint_report(problem, result.best_design(0), peaks.metrics())
    assert report["max_stroke (max)"]["satisfied"]


def test_parameter_constraint_tightens_bounds_exactly():
    problem = rj.DesignProblem(
        params=PAPER_BEST,
        objective=rj.Objective({"peak_anchoring_force": 1.0}),
        constraints=(rj.Constraint("m", upper=1200.0), rj.Constraint("gap", lower=0.01)),
    )
    lower, upper = problem.box()
    assert upper[problem.tune.index("m")] == 1200.0
    assert lower[problem.tune.index("gap")] == 0.01


def test_scatter_objective_is_the_worst_case():
    offsets = (-0.05, 0.0, 0.05)
    problem = rj.DesignProblem(
        params=PAPER_BEST,
        tune=("gap",),
        objective=rj.Objective({"peak_anchoring_force": 1.0}, scatter=("v0", offsets)),
    )
    evaluation = jax.jit(lambda th: rjx.evaluate_design(problem, th))(jnp.array([0.062]))
    status, worst = evaluation.status, evaluation.objective
    assert bool(status == rj.Status.ok)
    v0 = float(PAPER_BEST.barrel.v0)
    separate = [
        float(
            rj.peaks(
                rj.RecoilParams(barrel=rj.Barrel(v0=v0 * (1 + o)), absorber=PAPER_BEST.absorber),
                options=rj.GRADIENT_OPTIONS,
            ).peak_anchoring_force
        )
        for o in offsets
    ]
    np.testing.assert_allclose(float(worst), max(separate), rtol=1e-6)
    # At a quantile: numpy's, of the same solves (the median of three is the middle one).
    median = dataclasses.replace(
        problem, objective=dataclasses.replace(problem.objective, quantile=0.5)
    )
    evaluation = jax.jit(lambda th: rjx.evaluate_design(median, th))(jnp.array([0.062]))
    np.testing.assert_allclose(float(evaluation.objective), np.median(separate), rtol=1e-6)
    np.testing.assert_allclose(
        float(evaluation.metrics["peak_anchoring_force"]), np.median(separate), rtol=1e-6
    )
    for bad, message in ((0.0, "valid 0 < quantile <= 1"), (1.5, "valid 0 < quantile <= 1")):
        with pytest.raises(rj.ParameterError, match=message):
            rj.Objective({"peak_anchoring_force": 1.0}, scatter=("v0", offsets), quantile=bad)
    with pytest.raises(rj.ParameterError, match="quantile needs a scatter"):
        rj.Objective({"peak_anchoring_force": 1.0}, quantile=0.9)


@pytest.mark.slow
def test_optimiser_accepts_any_optax_transformation():
    """A plain optax SGD drives every run downhill, step after step, along the gradient
    sign: near the paper's design less coupling damping c_r lowers the peak
    displacement."""
    problem = rj.DesignProblem(
        params=PAPER_BEST,
        tune=("c_r",),
        bounds={"c_r": (1000.0, 6000.0)},
        objective=rj.Objective({"peak_displacement": 1.0}),
    )
    result = rj.optimise(problem, optimiser=optax.sgd(0.5), starts=2, steps=5, progress=False)
    assert len(result.history["objective"]) == 5 and result.compilations == 1
    objective, c_r = result.history["objective"], result.history["theta"][..., 0]
    assert np.all(np.diff(objective, axis=0) < 0)
    _, grads = rj.peak_jacobian(PAPER_BEST, wrt=("c_r",))
    assert float(grads.peak_displacement[0]) > 0
    assert np.all(np.diff(c_r, axis=0) < 0)


@pytest.mark.parametrize(
    "build, match",
    [
        (lambda: rj.Objective({"peak_force": 1.0}), "unknown metric"),
        (
            lambda: rj.Objective(
                {"peak_anchoring_force": 1.0}, temperatures={"peak_anchoring_force": -1.0}
            ),
            "valid > 0",
        ),
        (lambda: rj.Constraint("max_stroke"), "neither upper nor lower"),
        (lambda: rj.Constraint("stroke", upper=1.0), "unknown quantity"),
        (
            lambda: rj.DesignProblem(
                params=PAPER_BEST,
                tune=("gap", "mass"),
                objective=rj.Objective({"peak_displacement": 1.0}),
            ),
            "mass",
        ),
        (
            lambda: rj.DesignProblem(
                params=PAPER_BEST,
                tune=("gap",),
                bounds={"gap": (-1.0, 0.1)},
                objective=rj.Objective({"peak_displacement": 1.0}),
            ),
            "bounds.gap = -1",
        ),
        (
            lambda: rj.DesignProblem(
                params=PAPER_BEST,
                tune=("gap",),
                constraints=(rj.Constraint("gap", upper=-0.1),),
                objective=rj.Objective({"peak_displacement": 1.0}),
            ),
            "no room for gap",
        ),
    ],
)
def test_bad_problems_raise_clear_errors(build, match):
    with pytest.raises(rj.ParameterError, match=match):
        build()


def test_every_shipped_study_parses():
    from recoil_jax.apps import load_study

    studies = sorted((ROOT / "optimise").glob("*.toml"))
    assert {p.stem for p in studies} >= {
        "paper_gap",
        "tuned_absorber",
        "min_displacement",
        "pareto",
        "robust",
    }
    for path in studies:
        load_study(path)


@pytest.mark.slow  # two processes, each starting JAX
def test_a_study_run_again_loads_its_exported_programs(tmp_path):
    """With the compilation cache on, `optimise` exports its gradient program, its
    batched solve and its checks' solve of one design to the cache's folder; the same
    study again, in another process, loads them (each counted as its one build:
    `compilations`) and finds the same design, to the bit."""
    import os
    import subprocess
    import sys

    pytest.importorskip("flatbuffers")  # (jax.export's files: the apps extra)
    study = tmp_path / "small.toml"
    study.write_text(study_text(
        **SMALL_STUDY | {"design": "m = 1500.0\ngap = 0.062"},
        optimiser='method = "search"\nsamples = 16\nstarts = 1',
    ))  # fmt: skip
    env = os.environ | {"RECOIL_JAX_CACHE": str(tmp_path / "cache")}
    # The command, counting the programs it loads from the folder.
    counted = (
        "import sys, jax\n"
        "loads = []\n"
        "load = jax.export.deserialize\n"
        "jax.export.deserialize = lambda data: loads.append(1) or load(data)\n"
        "from recoil_jax.apps import main\n"
        "code = main(sys.argv[1:])\n"
        "print(f'loaded {len(loads)}')\n"
        "sys.exit(code)\n"
    )
    results, loaded = [], []
    for run in range(2):
        out = tmp_path / f"out{run}"
        argv = [sys.executable, "-c", counted, "optimise", str(study), "--out", str(out)]
        done = subprocess.run(argv, check=True, capture_output=True, text=True, env=env,
                              timeout=600)  # fmt: skip
        loaded.append(done.stdout.strip().splitlines()[-1])
        results.append(json.loads((out / "result.json").read_text()))
        if run == 0:
            folder = tmp_path / "cache" / "exported"
            written = {p.name for p in folder.iterdir()}
    exported = {"_gradient_solve", "_peaks_batch", "_peaks_jit"}  # (the last: the checks')
    assert {name.split("-")[0] for name in written} == exported
    assert not any("." in name for name in written)  # programs, not markers
    assert {p.name for p in folder.iterdir()} == written  # none written again
    assert loaded == ["loaded 0", "loaded 3"]
    first, second = results
    assert first["best"] == second["best"] and first["objective"] == second["objective"]
    assert first["optimiser"]["compilations"] == second["optimiser"]["compilations"] == 1


@pytest.mark.slow
def test_study_command_writes_result_json(tmp_path, capsys):
    """`recoil-jax optimise` on a small study writes result.json with the documented keys
    and the figures."""
    from recoil_jax.apps import main

    study = tmp_path / "small.toml"
    study.write_text(study_text(
        description="small",
        design="m = 1500.0\ngap = 0.04",
        tune="gap = [0.0, 0.12]\nc_r = [1000.0, 6000.0]",
        constraints="max_stroke = { max = 0.13 }",
        optimiser="starts = 2\nsteps = 30",
        rest="[check]\nhard = true\ngrid = { gap = [0.04, 0.08, 5] }\n",
    ))  # fmt: skip
    out = tmp_path / "out"
    assert main(["optimise", str(study), "--out", str(out)]) == 0
    result = json.loads((out / "result.json").read_text())
    # Every parameter of the design (the paper's model: no hardware groups).
    assert set(result["best"]) == set(rj.params_to_values(rj.RecoilParams(absorber=rj.Absorber())))
    assert set(result["metrics"]) >= {
        "peak_anchoring_force_N",
        "peak_displacement_m",
        "max_stroke_m",
        "status",
    }
    assert result["objective"] == pytest.approx(result["metrics"]["peak_anchoring_force_N"])
    stroke = result["constraints"]["max_stroke (max)"]
    assert stroke["limit"] == 0.13
    assert stroke["satisfied"] == (stroke["value"] <= 0.13)
    assert result["simulations"] >= 60
    assert result["optimiser"]["compilations"] == 1
    # How many of the 2 starts reached the best (within 0.1 %), said on the summary.
    agreement = result["optimiser"]["agreement"]
    assert agreement["starts"] == agreement["regions"] == 2
    groups = result["optimiser"]["where_starts_ended"]  # best first
    best = groups[0]["objective"]
    assert agreement["reached"] == sum(
        g["count"] for g in groups if g["objective"] is not None and g["objective"] <= best * 1.001
    )
    summary = capsys.readouterr().out
    assert rj.Agreement(**agreement).line() in summary
    # The objective and the limits with their units.
    assert result["objective_unit"] == "N"
    assert f"objective {result['objective']:.6g} N, " in summary
    assert f"max_stroke (max): {stroke['value']:.6g} m (limit 0.13 m)" in summary
    assert result["hard_model"]["max_relative_difference"] < 1e-3
    # The reported metrics are those of the problem's own solver options (rtol 1e-7).
    best = rj.params_from_values(result["best"])
    assert result["metrics"] == rj.peaks(best, options=rj.GRADIENT_OPTIONS).to_dict()
    for name in ("convergence.png", "best_history.png"):
        assert (out / name).stat().st_size > 10_000


def test_an_objective_has_its_metrics_unit():
    assert rj.Objective({"peak_anchoring_force": 1.0}).unit == "N"
    assert rj.Objective({"peak_displacement": 1.0, "max_stroke": 2.0}).unit == "m"
    mixed = rj.Objective({"peak_anchoring_force": 1.0, "peak_displacement": 1e4})
    assert mixed.unit == "N + m (weighted)"


def test_bad_study_file_exits_with_a_message(tmp_path, capsys):
    from recoil_jax.apps import main

    study = tmp_path / "bad.toml"
    study.write_text("[tune]\nmass = [0, 1]\n[objective]\npeak_anchoring_force = 1.0\n")
    assert main(["optimise", str(study)]) == 2
    assert "unknown parameter 'mass'" in capsys.readouterr().err


@pytest.mark.slow
def test_tuning_benchmark_smoke(tmp_path):
    """Every method runs on the same problem within its budget and reports the keys of
    `bench-tuning --json`; the best known value is the best any of them found."""
    from recoil_jax.apps._bench.tuning import METHODS, format_report, run_tuning_bench

    study = tmp_path / "tiny.toml"
    study.write_text(study_text(
        **SMALL_STUDY | {"design": "m = 1500.0\ngap = 0.062",
                         "tune": "gap = [0.0, 0.12]\nc_r = [1000.0, 6000.0]"},
        optimiser='method = "search"\nsamples = 32\nstarts = 1',
    ))  # fmt: skip
    budget = 2.5
    report = run_tuning_bench({str(study): budget}, seeds=(0, 1), out=tmp_path, log=lambda _: None)
    problem = report["problems"]["tiny"]  # keyed by the study's name
    assert problem["dimension"] == 2 and set(problem["methods"]) == set(METHODS)
    bests = []
    for method, run in problem["methods"].items():
        assert set(run) >= {"best", "wall_s", "solves", "gradient_solves", "to_target_s"}
        assert run["wall_s"] <= budget + 0.01
        assert (run["gradient_solves"] > 0) == (method == "recoil-jax")
        if run["best"] is not None:
            bests.append(run["best"])
            assert run["best"] >= problem["best_known"]
    # The best known is the best of every run, every seed, cold and warm.
    warm_best = min(run["over_seeds"]["best_min"] for run in problem["methods"].values())
    assert problem["best_known"] <= warm_best <= problem["best_known"] * (1 + 1e-4)
    assert problem["target"] == pytest.approx(problem["best_known"] * 1.001)
    assert problem["methods"]["recoil-jax"]["to_target_s"] is not None
    ours = problem["methods"]["recoil-jax"]["over_seeds"]
    assert ours["seeds"] == 2 and ours["successes"] == 2  # a smooth 2-parameter problem
    assert ours["median_to_target_s"] <= ours["worst_to_target_s"] <= budget
    assert ours["best_min"] == pytest.approx(problem["best_known"], rel=1e-3)
    assert (tmp_path / "bench_tuning_tiny.png").stat().st_size > 10_000
    text = format_report(report)
    assert "differential_evolution" in text and "over 2 seeds: 2 reach the target" in text


def test_tuning_benchmark_speedup_is_a_ratio_or_a_lower_bound(capsys):
    """Against the best other method that reached the target, a ratio; when none did
    within the budget, the budget over our time, marked as a lower bound."""
    from recoil_jax.apps import main
    from recoil_jax.apps._bench.tuning import over_seeds, speedup

    def problem(ours, *others):
        methods = {"recoil-jax": {"to_target_s": ours}}
        methods |= {f"other{i}": {"to_target_s": t} for i, t in enumerate(others)}
        return {"budget_s": 90.0, "methods": methods}

    assert speedup(problem(2.0, 30.0, None, 12.0)) == {"factor": 6.0, "at_least": False}
    assert speedup(problem(4.5, None, None)) == {"factor": 20.0, "at_least": True}
    assert speedup(problem(None, 3.0)) is None
    assert speedup(problem(1.0)) is None
    # Over seeds: the medians, where a run that never reached the target counts as never.
    over = over_seeds([1.0, None, 3.0, 2.0], [5.0, 6.0, None, None], [10.0, 11.0, 10.0, 10.0])
    assert over == {
        "seeds": 4, "successes": 3, "median_to_target_s": 2.5, "worst_to_target_s": None,
        "cold": {"successes": 2, "median_to_target_s": None, "worst_to_target_s": None},
        "best_min": 10.0, "best_max": 11.0,
    }  # fmt: skip
    seeded = problem(0.0, 0.0)
    seeded["methods"]["recoil-jax"]["over_seeds"] = over
    seeded["methods"]["other0"]["over_seeds"] = over_seeds(
        [20.0, 30.0, 40.0], [None] * 3, [1.0] * 3
    )
    assert speedup(seeded) == {"factor": 12.0, "at_least": False}  # 30 s / 2.5 s
    # An unknown method, or no seed, is refused before anything runs.
    assert main(["bench-tuning", "throttling", "--methods", "simplex"]) == 2
    assert "unknown method(s) ['simplex']" in capsys.readouterr().err
    assert main(["bench-tuning", "throttling", "--seeds", "0"]) == 2
    assert "--seeds 0: valid >= 1" in capsys.readouterr().err


@pytest.mark.slow
def test_scenarios_and_epsilon_limits_run_in_one_vmap():
    """Fronts: one problem per absorber mass (batched params) and per limit (an
    ε-constraint), each scenario with its own starts, in one compiled step."""
    problem = rj.DesignProblem(
        params=PAPER_BEST,
        tune=("gap",),
        bounds={"gap": (0.0, 0.12)},
        objective=rj.Objective({"peak_anchoring_force": 1.0}),
        constraints=(rj.Constraint("peak_contact_force", upper=2e5),),
    )
    masses = np.array([500.0, 1500.0])
    scenarios = rj.params_from_values(m=masses, gap=np.full(2, 0.05))
    result = rj.optimise(problem, scenarios=scenarios, starts=2, steps=25, progress=False)
    assert result.compilations == 1 and result.best_objective.shape == (2,)
    for s, m in enumerate(masses):
        assert result.best_design(s)["m"] == m
        peaks = rj.peaks(result.best_params(s), options=rj.GRADIENT_OPTIONS)
        np.testing.assert_allclose(
            float(peaks.peak_anchoring_force), result.best_objective[s], rtol=1e-5
        )
    # A heavier absorber brings the force lower (the paper's Fig. 10).
    assert result.best_objective[1] < result.best_objective[0]
    # ε-constraint: a tighter contact-force limit can only cost force, and it holds.
    limits = [6.0e4, 4.5e4]  # active: the unconstrained optimum has ≈ 67 kN
    tight = rj.optimise(
        problem, scenario_limits={"peak_contact_force": limits}, starts=2, steps=25, progress=False
    )
    for s, limit in enumerate(limits):
        contact = rj.peaks(tight.best_params(s), options=rj.GRADIENT_OPTIONS).peak_contact_force
        assert float(contact) <= limit * (1 + 1e-6)
    # Both stay on the impacting side (5989 N without impact), and tighter costs more.
    assert tight.best_objective[0] < tight.best_objective[1] < 5900.0


def test_weighted_objective_is_the_weighted_sum():
    objective = rj.Objective({"peak_anchoring_force": 1.0, "peak_displacement": 3e4})
    metrics = {"peak_anchoring_force": 5500.0, "peak_displacement": 0.18}
    assert objective(metrics) == pytest.approx(5500.0 + 3e4 * 0.18)


@pytest.mark.slow
def test_study_with_scatter_nominal_comparison_and_front(tmp_path):
    from recoil_jax.apps import run_study

    study = tmp_path / "robust_front.toml"
    study.write_text("""
[design]
m = 1500.0
gap = 0.062
[tune]
gap = [0.0, 0.12]
[objective]
peak_anchoring_force = 1.0
[objective.scatter]
v0 = [-0.05, 0.05]
[optimiser]
starts = 2
steps = 8
[[front]]
vary = "m"
values = [1000.0, 1500.0]
[check]
nominal = true
""")
    report = run_study(study, tmp_path / "out", progress=False)
    # The robust objective is the worst case: at +5 % v0 the force is higher.
    assert report["objective"] >= report["metrics"]["peak_anchoring_force_N"]
    comparison = report["nominal_comparison"]
    assert comparison["robust"]["objective_worst"] <= comparison["nominal"]["objective_worst"] + 1.0
    (front,) = report["fronts"]
    assert [p["m"] for p in front["points"]] == [1000.0, 1500.0]
    for name in ("robust_vs_nominal.png", "front_m.png", "front_m.csv"):
        assert (tmp_path / "out" / name).exists()


def test_studies_resolve_by_name_from_any_directory(tmp_path, monkeypatch):
    from recoil_jax.apps import load_study

    monkeypatch.chdir(tmp_path)
    study = load_study("tuned_absorber")
    assert study.name == "tuned_absorber" and study.problem.tune == ("gap", "m", "k_r", "c_r")
    assert load_study("paper_gap.toml").name == "paper_gap"
    with pytest.raises(rj.ParameterError, match=r"shipped studies: .*tuned_absorber"):
        load_study("no_such_study")


@pytest.mark.parametrize(
    "front, match",
    [
        ('vary = "m"\nvalues = []', "needs values"),
        ('vary = "m"\nvalues = ["heavy"]', "must be numbers"),
        ('vary = "gap"\nvalues = [0.01, -0.1]', r"Absorber\.gap\[1\] = -0\.1 m is invalid"),
        ('vary = "max_stroke"\nvalues = [0.1, inf]', "must be finite"),
        ('vary = "stroke"\nvalues = [0.1]', "give a parameter or a constrained metric"),
    ],
)
def test_bad_front_values_are_clear_errors(tmp_path, front, match):
    from recoil_jax.apps import load_study

    study = tmp_path / "front.toml"
    study.write_text(f"""
[tune]
c_r = [1000.0, 6000.0]
[objective]
peak_anchoring_force = 1.0
[constraints]
max_stroke = {{ max = 0.15 }}
[[front]]
{front}
""")
    with pytest.raises(rj.ParameterError, match=match):
        load_study(study)


def test_study_axis_labels_carry_units():
    from recoil_jax.apps._studies.checks import _label

    assert _label("k_r") == "k_r (N/m)" and _label("m") == "m (kg)"
    assert _label("gap") == "gap (m)" and _label("c_r") == "c_r (N*s/m)"
    assert _label("peak_displacement") == "peak barrel displacement from its rest (m)"


_IMPOSSIBLE = """
description = "no absorber design keeps the barrel within 10 mm"
[design]
m = 1500.0
gap = 0.05
[tune]
gap = [0.0, 0.12]
[objective]
peak_anchoring_force = 1.0
[constraints]
peak_displacement = {{ max = 0.01 }}
[optimiser]
method = "{method}"
{settings}
[check]
hard = true
"""


@pytest.mark.parametrize(
    "method, settings",
    [
        # The fast tier runs the search's; optax's takes longer to trace.
        pytest.param("adam", "starts = 2\nsteps = 10", marks=pytest.mark.slow),
        ("search", "samples = 16\nstarts = 1"),
    ],
)
def test_an_impossible_limit_is_reported_infeasible_by_every_method(
    tmp_path, capsys, method, settings
):
    """No design meets the limit: exit status 3 with a one-line message (with and without
    --json), `feasible: false`, `best: null`, and the closest design with the limit it
    misses, by the amount a re-solve of that design gives; never a traceback."""
    from recoil_jax.apps import main

    study = tmp_path / f"{method}.toml"
    study.write_text(_IMPOSSIBLE.format(method=method, settings=settings))
    for json_flag in ([], ["--json"]):
        out = tmp_path / f"out{len(json_flag)}"
        code = main(["optimise", str(study), "--out", str(out), "--seed", "3", *json_flag])
        captured = capsys.readouterr()
        assert code == 3
        assert "Traceback" not in captured.err
        (line,) = [x for x in captured.err.splitlines() if x.startswith("recoil-jax:")]
        assert line.startswith("recoil-jax: infeasible: no design met every limit")
        assert "peak_displacement (max)" in line and "against the limit 0.01 m" in line
        result = json.loads((out / "result.json").read_text())
        if json_flag:
            assert json.loads(captured.out) == result
        else:
            assert captured.out == ""
        assert result["feasible"] is False
        assert result["best"] is None and result["objective"] is None
        assert result["optimiser"]["seed"] == 3
        assert "hard_model" not in result  # no checks of a design that is not one
        closest = result["closest"]
        (miss,) = closest["missed"].values()
        displacement = rj.peaks(
            rj.params_from_values(closest["design"]), options=rj.GRADIENT_OPTIONS
        ).peak_displacement
        assert miss["value"] == pytest.approx(float(displacement), rel=1e-12)
        assert miss["missed_by"] == pytest.approx(float(displacement) - 0.01, rel=1e-12)
        assert miss["missed_by_relative"] == pytest.approx(miss["missed_by"] / 0.01)
        assert (out / "convergence.png").stat().st_size > 10_000


def test_one_feasibility_rule():
    """`rj.feasible`: solved, finite objective, every normalised violation at most
    -FEASIBILITY_TOLERANCE; `rj.metric_violations` normalises by |limit| (1 for 0)."""
    problem = rj.DesignProblem(
        params=PAPER_BEST,
        objective=rj.Objective({"peak_anchoring_force": 1.0}),
        tune=("gap",),
        constraints=(
            rj.Constraint("peak_displacement", upper=0.2),
            rj.Constraint("min_stroke", lower=0.0),
        ),
    )
    metrics = {
        "peak_displacement": np.asarray([0.1, 0.2, 0.3, 0.1, 0.1]),
        "min_stroke": np.asarray([0.01, 0.01, 0.01, -0.5, 0.01]),
    }
    violations = rj.metric_violations(problem, metrics)
    np.testing.assert_allclose(
        violations, [[-0.5, -0.01], [0.0, -0.01], [0.5, -0.01], [-0.5, 0.5], [-0.5, -0.01]]
    )
    ok = np.asarray([True, True, True, True, False])
    objective = np.asarray([1.0, 1.0, 1.0, 1.0, 1.0])
    np.testing.assert_array_equal(
        rj.feasible(ok, objective, violations), [True, False, False, False, False]
    )
    assert not rj.feasible(True, np.nan, [-1.0])
    assert rj.feasible(True, 1.0, [-rj.FEASIBILITY_TOLERANCE])
    assert not rj.feasible(True, 1.0, [-0.5 * rj.FEASIBILITY_TOLERANCE])
    missed = rj.closest_miss(problem, violations[3])
    assert missed == {
        "min_stroke (min)": {
            "limit": 0.0, "value": -0.5, "missed_by": 0.5, "missed_by_relative": 0.5,
        }
    }  # fmt: skip
