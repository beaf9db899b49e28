"""Designing over the firing envelope (issue 54, item 4): a study's firing conditions,
each design solved at every condition in one batched program, the objective their worst
case, limits of their own; `optimise/envelope.toml` against the issue's hand design and
the exact reference; every optimiser method."""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_envelope_model import LIMITS, compare
from test_reference_envelope import HOWITZER

import recoil_jax as rj
import recoil_jax.extend as rjx
from recoil_jax.apps._studies.study import run_study
from recoil_jax.apps._studies.study_file import load_study

#: The hand design (issue 62): it meets every limit at 169.2 kN.
HAND = {"c_out": 16000.0, "c_ret": 30000.0, "recuperator_preload": 30000.0,
        "buffer_damping": 40000.0}  # fmt: skip
HAND_OBJECTIVE = 169248.6  # N, its mount load at 70° (the push; the reference's 169.25 kN)
ELEVATIONS = {"0 deg": 0.0, "35 deg": 35.0, "70 deg": 70.0}


@pytest.fixture(scope="module")
def envelope() -> rj.DesignProblem:
    return load_study("envelope").problem


def eqx_replace(problem, **changes):
    return dataclasses.replace(problem, **changes)


def theta_of(problem, design):
    return jnp.asarray([design[name] for name in problem.tune])


def test_the_study_file_states_the_issue(envelope):
    """`optimise/envelope.toml` is the issue's gun, rails, mount, bounds, conditions and
    limits."""
    p = rj.params_to_values(envelope.params)
    gun = {k: v for k, v in HOWITZER.items() if k not in HAND and k != "elevation"}
    assert {k: float(p[k]) for k in gun} == gun
    assert float(envelope.options.t1) == 6.0
    assert envelope.bounds == {
        "c_out": (2e3, 6e4), "c_ret": (2e3, 6e4), "recuperator_preload": (5e3, 8e4),
        "buffer_damping": (0.0, 4e5),
    }  # fmt: skip
    assert {c.name: dict(c.values) for c in envelope.conditions} == {
        name: {"elevation": e} for name, e in ELEVATIONS.items()
    }
    limits = dict(zip(envelope.limit_labels, envelope.metric_constraints, strict=True))
    assert limits == {
        "return_time (max)": ("return_time", "max", 2.5),
        "battery_speed (max)": ("battery_speed", "max", 0.5),
        "residual_displacement (max)": ("residual_displacement", "max", 1e-3),
        "stability_margin (min)": ("stability_margin", "min", 0.1),
        "peak_displacement (max) at 0 deg": ("peak_displacement", "max", 1.0),
        "peak_displacement (max) at 35 deg": ("peak_displacement", "max", 1.0),
        "peak_displacement (max) at 70 deg": ("peak_displacement", "max", 0.8),
    }
    assert dict(envelope.objective.weights) == {"peak_mount_load": 1.0}


def test_conditions_in_one_program_equal_each_solved_alone(envelope):
    """`evaluate_design` solves the three elevations in one vmapped program: each
    condition's metrics equal the same program's for that condition alone (a loop) and a
    plain solve's, within the solver's tolerance; the objective is the worst
    condition's and each limit's violation the worst over its own conditions (by hand);
    the batched evaluator (the search's global phase) agrees."""
    theta = theta_of(envelope, HAND)
    evaluation = jax.jit(lambda t: rjx.evaluate_design(envelope, t))(theta)
    design = rj.params_to_values(envelope.params) | HAND
    alone = {
        name: rj.peaks(rj.params_from_values(design | {"elevation": e}), envelope.smoothing,
                       envelope.options)
        for name, e in ELEVATIONS.items()
    }  # fmt: skip
    for k, (name, condition) in enumerate(zip(ELEVATIONS, envelope.conditions, strict=True)):
        one = eqx_replace(envelope, conditions=(condition,), constraints=())
        looped = rjx.evaluate_design(one, theta).conditions
        for metric in rj.METRICS:
            ours = float(evaluation.conditions[metric][k])
            # vmap moves results by roundoff, which may tip one step's acceptance
            # (`test_solver.test_batched_equals_loop`): measured 3e-9 on the peak force,
            # 2e-6 on the margin at 70° (whose minimum is at the buffer's onset), 1.3e-9 m
            # on where friction holds the barrel at 0° (its residual, 63 µm from the rest).
            floor = 5e-9 if metric == "residual_displacement" else 1e-9
            assert ours == pytest.approx(float(looped[metric][0]), rel=1e-5, abs=floor)
            single = float(getattr(alone[name], metric))
            assert ours == pytest.approx(single, rel=1e-5, abs=floor), (name, metric)
    loads = [float(alone[name].peak_mount_load) for name in ELEVATIONS]
    assert float(evaluation.objective) == pytest.approx(max(loads), rel=1e-6)
    assert max(loads) == pytest.approx(HAND_OBJECTIVE, abs=1.0)
    # The violations by hand: each limit over the conditions it names.
    by_hand = []
    for (metric, kind, limit), label in zip(
        envelope.metric_constraints, envelope.limit_labels, strict=True
    ):
        at = [n for n in ELEVATIONS if label.endswith(f" at {n}")] or list(ELEVATIONS)
        values = [float(getattr(alone[n], metric)) for n in at]
        worst = max(values) if kind == "max" else min(values)
        by_hand.append(
            (worst - limit) / abs(limit) if kind == "max" else (limit - worst) / abs(limit)
        )
    np.testing.assert_allclose(np.asarray(evaluation.violations), by_hand, rtol=1e-5, atol=1e-7)
    assert np.all(np.asarray(evaluation.violations) < 0)  # the hand design meets every limit
    batch = rjx.BatchEvaluator(envelope)
    z = np.asarray(batch.space.z(np.asarray(theta)))
    swept = batch(np.stack([z, 0.8 * z]))
    # (The sweep solves without the tangents, whose error the steps control too.)
    assert swept.objective[0] == pytest.approx(float(evaluation.objective), rel=1e-6)
    np.testing.assert_allclose(swept.violations[0], by_hand, rtol=1e-5, atol=1e-7)
    other = rjx.evaluate_design(envelope, jnp.asarray(swept.theta[1]))
    assert swept.objective[1] == pytest.approx(float(other.objective), rel=1e-6)


def test_conditions_that_set_different_parameters(envelope):
    """A charge (v0) and an elevation as two conditions: each fires at the design's
    value of what it does not set, in the batched evaluator (the search's global phase)
    as in `evaluate_design`, beside plain solves of those designs."""
    problem = eqx_replace(
        envelope,
        conditions=(rj.Condition("charge", {"v0": 8.0}), rj.Condition("high", {"elevation": 70.0})),
        constraints=(rj.Constraint("return_time", upper=2.5, conditions=["high"]),),
    )
    assert problem.constraints[0].conditions == ("high",)  # (a list is taken as a tuple)
    theta = theta_of(problem, HAND)
    evaluation = rjx.evaluate_design(problem, theta)
    batch = rjx.BatchEvaluator(problem)
    swept = batch(np.asarray(batch.space.z(np.asarray(theta)))[None])
    design = rj.params_to_values(problem.params) | HAND  # elevation 0, v0 10
    plain = [
        rj.peaks(rj.params_from_values(design | change), problem.smoothing, problem.options)
        for change in ({"v0": 8.0}, {"elevation": 70.0})
    ]
    loads = [float(p.peak_mount_load) for p in plain]
    np.testing.assert_allclose(evaluation.conditions["peak_mount_load"], loads, rtol=1e-6)
    assert swept.objective[0] == pytest.approx(max(loads), rel=1e-6)
    high = float(plain[1].return_time)
    assert swept.violations[0, 0] == pytest.approx((high - 2.5) / 2.5, rel=1e-5)


def test_a_front_cannot_vary_a_metric_with_several_limits(envelope):
    with pytest.raises(rj.ParameterError, match="has 3 limits"):
        rj.optimise(envelope, scenario_limits={"peak_displacement": [0.9, 1.0]}, starts=1, steps=1)


@pytest.mark.slow
def test_the_minimax_pieces_and_their_gradients(envelope):
    """At level 0 the gradient solve gives each condition's objective and its gradient
    (the minimax's pieces); above it, the worst one. Both against central differences of
    the exact solves (in the normalised coordinates the optimiser moves in)."""
    evaluator = rjx.GradientEvaluator(envelope)
    space = evaluator.space
    z = np.asarray(space.z(np.asarray(theta_of(envelope, HAND))))
    pieces = evaluator(z, 0.0)
    assert np.shape(pieces.f) == (3,) and np.shape(pieces.df) == (3, 4)
    worst = evaluator(z, 1.0)
    assert float(worst.f) == pytest.approx(float(np.max(pieces.f)), rel=1e-12)
    np.testing.assert_allclose(worst.df, pieces.df[np.argmax(pieces.f)], rtol=1e-12)

    def conditions(z):
        evaluation = rjx.evaluate_design(envelope, space.theta(jnp.asarray(z)))
        return np.asarray(evaluation.conditions["peak_mount_load"]), np.asarray(
            evaluation.violations
        )

    # Each error against the row's largest gradient (c_ret and the buffer hardly move
    # the peak force: their differences are the solver's noise, ~1e-7 of 170 kN).
    h = 1e-3
    fd_f, fd_g = np.zeros_like(pieces.df), np.zeros_like(pieces.dg)
    for j in range(len(envelope.tune)):
        step = np.zeros_like(z)
        step[j] = h
        (f_plus, g_plus), (f_minus, g_minus) = conditions(z + step), conditions(z - step)
        fd_f[:, j], fd_g[:, j] = (f_plus - f_minus) / (2 * h), (g_plus - g_minus) / (2 * h)
    for exact, fd in ((pieces.df, fd_f), (pieces.dg, fd_g)):
        scale = np.max(np.abs(fd), axis=1, keepdims=True)
        assert np.max(np.abs(exact - fd) / scale) < 1e-3


@pytest.mark.parametrize(
    "build, fragment",
    [
        (lambda: rj.Condition("a", {}), "sets no parameter"),
        (lambda: rj.Condition("a", {"elevation": 95.0}), "elevation"),
        (lambda: rj.Condition("a", {"nonsense": 1.0}), "nonsense"),
        (lambda: rj.Condition("", {"elevation": 5.0}), "non-empty"),
        (lambda: rj.Constraint("m", upper=1.0, conditions=("a",)), "only a metric's limit"),
        (lambda: rj.Constraint("return_time", upper=1.0, conditions="a"), "tuple"),
    ],
)
def test_bad_conditions_are_refused(build, fragment):
    with pytest.raises(rj.ParameterError, match=fragment):
        build()


@pytest.mark.parametrize(
    "change, fragment",
    [
        (dict(conditions=(rj.Condition("a", {"c_out": 1e4}),)), "which is tuned"),
        (
            dict(conditions=(rj.Condition("a", {"v0": 9.0}), rj.Condition("a", {"v0": 10.0}))),
            "share a name",
        ),
        (
            dict(constraints=(rj.Constraint("return_time", upper=2.0, conditions=("b",)),)),
            "names condition 'b'",
        ),
        (
            dict(objective=rj.Objective({"peak_anchoring_force": 1.0}, scatter=("v0", (0.0, 0.1)))),
            "cannot both",
        ),
        (
            dict(conditions=(rj.Condition("a", {"stop_stiffness": 1e8}),), params="paper"),
            "give stop_stiffness in the design",
        ),
    ],
)
def test_bad_condition_problems_are_refused(envelope, change, fragment):
    kwargs = dict(
        params=envelope.params, objective=envelope.objective, tune=envelope.tune,
        bounds=envelope.bounds, conditions=(rj.Condition("a", {"v0": 9.0}),),
    )  # fmt: skip
    kwargs |= change
    if kwargs["params"] == "paper":
        kwargs |= dict(params=rj.params_from_values(m=0.0), tune=("c_out",), bounds={})
    with pytest.raises(rj.ParameterError, match=fragment):
        rj.DesignProblem(**kwargs)


@pytest.fixture(scope="module")
def studies(tmp_path_factory) -> dict[int, tuple]:
    """`recoil-jax optimise envelope` at seeds 0 to 3: each report and its folder."""
    out = tmp_path_factory.mktemp("envelope")
    return {
        seed: (
            run_study("envelope", out=out / str(seed), progress=False, seed=seed),
            out / str(seed),
        )
        for seed in range(4)
    }


@pytest.mark.slow
def test_the_envelope_study_beats_the_hand_design(studies):
    """`recoil-jax optimise envelope`: feasible, its worst mount load at least 20 % below
    the hand design's 169.2 kN, under 5 minutes, with no hazard at any elevation;
    result.json holds each condition's metrics and hazards and the side-by-side figure
    is written; at each condition the best design's metrics are the exact reference's
    (`test_envelope_model`'s tolerances) and every limit holds on the reference too."""
    report, tmp_path = studies[0]
    assert report["feasible"]
    assert report["objective"] <= 0.8 * HAND_OBJECTIVE  # measured 126 234 N
    assert report["seconds"] < 300.0
    assert all(c["hazards"] == [] for c in report["conditions"].values())
    assert all(c["satisfied"] for c in report["constraints"].values())
    assert set(report["conditions"]) == set(ELEVATIONS)
    assert (tmp_path / "conditions.png").stat().st_size > 10_000
    written = json.loads((tmp_path / "result.json").read_text())
    assert written["conditions"]["70 deg"]["values"] == {"elevation": 70.0}
    problem = load_study("envelope").problem
    for name, elevation in ELEVATIONS.items():
        design = report["best"] | {"elevation": elevation}
        errors = compare(design, None, 6.0)
        assert all(errors[m] <= LIMITS[m] for m in errors), (name, errors)
        metrics = report["conditions"][name]["metrics"]
        assert metrics["peak_mount_load_N"] <= report["objective"] + 1e-6
        assert metrics["peak_pull_force_N"] < metrics["peak_anchoring_force_N"]
    # The limits on the reference's numbers, within its tolerance of ours.
    peaks = {name: report["conditions"][name]["metrics"] for name in ELEVATIONS}
    for (metric, kind, limit), label in zip(
        problem.metric_constraints, problem.limit_labels, strict=True
    ):
        at = [n for n in ELEVATIONS if label.endswith(f" at {n}")] or list(ELEVATIONS)
        key = rj.METRICS[metric].key
        for n in at:
            value, slack = (
                peaks[n][key],
                LIMITS[metric] * (abs(limit) if metric == "peak_displacement" else 1.0),
            )
            assert value <= limit + slack if kind == "max" else value >= limit - slack, (label, n)


@pytest.mark.slow
def test_the_envelope_study_finds_one_optimum_over_seeds(studies):
    """Seeds 0 to 3 of the study end at the same worst mount load, within 0.1 %, each
    feasible and below 0.8 of the hand design's."""
    assert all(report["feasible"] for report, _ in studies.values())
    objectives = [report["objective"] for report, _ in studies.values()]
    assert max(objectives) <= 0.8 * HAND_OBJECTIVE
    assert (max(objectives) - min(objectives)) / min(objectives) <= 1e-3, objectives


@pytest.mark.slow
@pytest.mark.parametrize(
    "local", [rj.SLSQP(), rj.EpigraphMinimax(), rj.TrustRegionLP(), rj.OptaxLocal(maxiter=100)]
)
def test_every_search_method_designs_over_the_conditions(envelope, local):
    """Each local method of `search` takes the conditions (their worst case, through the
    minimax pieces or the worst piece) and ends feasible below the hand design."""
    result = rj.search(
        envelope, global_phase=rj.SobolStarts(64, 2), local=local, progress=False, seed=0
    )
    assert bool(result.feasible[0])
    assert float(result.best_objective[0]) < 0.9 * HAND_OBJECTIVE
    assert result.solves == 3 * 64  # every sample at each of the three conditions


@pytest.mark.slow
def test_optax_designs_over_the_conditions(envelope):
    """`optimise` (optax from several starts, vmapped) with the conditions vmapped inside
    each evaluation: feasible, below the hand design. (Measured: 166,210 N in 150 steps
    from 4 starts on the mount load with the margin held at every elevation; the
    search reaches 126,234 N. Before revision 2, on the push alone, it went below 0.9 of
    the hand design.)"""
    result = rj.optimise(envelope, starts=4, steps=150, seed=0, progress=False)
    assert bool(result.feasible[0])
    assert float(result.best_objective[0]) < HAND_OBJECTIVE
