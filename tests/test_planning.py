"""Choosing a test plan (issue 55, in progress): the exchange algorithm against exhaustive
enumeration and greedy selection, on information matrices built by hand."""

import numpy as np
import pytest

from recoil_jax._planning.choose import (
    criterion_value,
    exchange,
    exhaustive,
    greedy,
    options,
)


def rank_one(direction, weight):
    v = np.asarray(direction, dtype=float)
    v = v / np.linalg.norm(v)
    return weight * np.outer(v, v)


def test_greedy_is_beaten_where_it_is_known_to_fail():
    """Two parameters, two firings. One candidate informs both together (weight 1.5a
    along (1, 1)), two inform one each (weight a). Greedy takes the joint one first (the
    largest alone) and ends at det 0.75a²; the pair of single ones gives a². The
    exchange finds the pair, as exhaustive enumeration does."""
    a = 4.0
    information = np.stack([rank_one([1, 1], 1.5 * a), rank_one([1, 0], a), rank_one([0, 1], a)])[
        :, None
    ]  # (C = 3, S = 1, 2, 2)
    opts = options(information, costs=[1.0])
    by_greedy, by_exchange = greedy(opts, 2), exchange(opts, 2)
    optimum = exhaustive(opts, 2)
    assert 0 in by_greedy.chosen
    assert by_greedy.value == pytest.approx(np.log(0.75 * a**2))
    assert by_exchange.chosen == optimum.chosen == (1, 2)
    assert by_exchange.value == pytest.approx(np.log(a**2))


def test_the_exchange_reaches_the_exhaustive_optimum_on_random_problems():
    rng = np.random.default_rng(0)
    for _ in range(20):
        C, S, P = 6, 3, 4
        rows = rng.normal(size=(C, S, 2, P)) * rng.uniform(0.1, 3.0, (C, S, 1, 1))
        information = np.einsum("csip,csiq->cspq", rows, rows)
        opts = options(information, costs=[1.0, 2.0, 3.0], cap=4.0)
        for name in ("D", "A", 2):
            optimum = exhaustive(opts, 3, name)
            found = exchange(opts, 3, name, starts=8)
            assert found.value >= optimum.value - 1e-9 * abs(optimum.value), name


def test_signal_sets_within_the_cost():
    information = np.stack([np.stack([np.eye(2)] * 3)] * 2)  # (C = 2, S = 3)
    opts = options(information, costs=[1.0, 3.0, 1.0], cap=4.0)
    # Affordable and maximal: {0, 1}, {1, 2} (4.0 each) and {0, 2} (2.0)
    assert sorted(set(opts.signals)) == [(0, 1), (0, 2), (1, 2)]
    assert len(opts.candidate) == 6
    with_all = options(information, costs=[1.0, 3.0, 1.0])
    assert set(with_all.signals) == {(0, 1, 2)}


def test_criteria():
    matrix = np.diag([4.0, 1.0])
    assert criterion_value(matrix, "D") == pytest.approx(np.log(4.0))
    assert criterion_value(matrix, "A") == pytest.approx(-1.25)
    assert criterion_value(matrix, 0) == pytest.approx(-0.25)
    singular = np.diag([4.0, 0.0])
    assert criterion_value(singular, "D") == -np.inf and criterion_value(singular, "A") == -np.inf
    # Parameter 0 is determined although parameter 1 is not.
    assert criterion_value(singular, 0) == pytest.approx(-0.25)
    assert criterion_value(singular, 1) == -np.inf


def test_candidate_information_matches_finite_differences():
    """`JᵀJ/σ²` of each candidate and signal from the exact sensitivities, against
    central differences of plain solves of the same signals (in box coordinates)."""
    import jax.numpy as jnp

    import recoil_jax as rj
    import recoil_jax.extend as rjx
    from recoil_jax._planning.information import candidate_information

    fit = ("k", "c_out")
    base = rj.params_from_values(m=0.0)
    space = rjx.SearchSpace(
        jnp.asarray([1e4, 2e3]), jnp.asarray([5e4, 2e4]), jnp.asarray([False, False])
    )
    ts = np.linspace(0.01, 0.6, 60)
    sigma = (1e-4, 50.0)
    options = rj.SolverOptions(rtol=1e-10, atol=1e-13)
    info, codes = candidate_information(
        base, fit, space, {"v0": [0.5, 0.7]}, ("x_M", "F_AN"), sigma, ts, options=options
    )
    assert info.shape == (1, 2, 2, 2, 2) and np.all(codes == 0)
    info = info[0]
    z0 = np.asarray(space.z(np.asarray(rj.values_of(base, fit))))
    h = 1e-5
    for c, v0 in enumerate((0.5, 0.7)):

        def signals(z, v0=v0):
            p = rj.with_values(
                base, (*fit, "v0"), np.append(np.asarray(space.theta(jnp.asarray(z))), v0)
            )
            history = rj.simulate(p, options=options, ts=ts)
            return np.stack([np.asarray(history.x_M), np.asarray(history.anchoring_force)])

        J = np.stack(
            [(signals(z0 + h * e) - signals(z0 - h * e)) / (2 * h) for e in np.eye(2)], axis=-1
        )  # (S, T, P)
        by_differences = np.einsum("stp,stq->spq", J, J) / np.asarray(sigma)[:, None, None] ** 2
        np.testing.assert_allclose(info[c], by_differences, rtol=1e-4)
    # At other truths, in the same program: as computed at a design with those values.
    truths = np.asarray([[2e4, 5e3], [3e4, 1.5e4]])
    at_truths, _ = candidate_information(
        base, fit, space, {"v0": [0.5, 0.7]}, ("x_M", "F_AN"), sigma, ts, options=options,
        truths=truths,
    )  # fmt: skip
    for r, theta in enumerate(truths):
        alone, _ = candidate_information(
            rj.with_values(base, fit, theta), fit, space, {"v0": [0.5, 0.7]}, ("x_M", "F_AN"),
            sigma, ts, options=options,
        )  # fmt: skip
        # (vmap over truths may tip a step: agreement to the solver's tolerance)
        np.testing.assert_allclose(at_truths[r], alone[0], rtol=1e-6, atol=1e-9 * alone.max())


def test_a_robust_plan_averages_the_criterion_over_draws_from_the_box():
    """`robust = N`: the information at N draws from the box, in the same program as at
    the guess; the plan's criterion is the mean of the criterion over the draws (each
    draw's information computed again alone), and the exchange's plan is the exhaustive
    optimum of that mean."""
    import recoil_jax as rj
    from recoil_jax._planning.choose import plan_value
    from recoil_jax._planning.information import candidate_information
    from recoil_jax._planning.plan import plan_space

    problem = rj.PlanProblem(
        design={"m": 0.0},
        fit={"k": (1e4, 5e4), "c_out": (2e3, 2e4)},
        candidates={"v0": [0.4, 0.6, 0.8]},
        signals={"x_M": rj.Sensor(1e-4, 1.0), "F_AN": rj.Sensor(50.0, 2.0)},
        rate=200.0,
        duration=0.5,
        firings=2,
        cost=2.0,
        robust=3,
        seed=1,
    )
    plan = rj.plan_firings(problem)
    assert plan.truths.shape == (4, 2)
    draws = plan.truths[1:]
    space = plan_space(problem)
    assert np.all((draws >= np.asarray(space.lower)) & (draws <= np.asarray(space.upper)))
    alone = []
    for theta in draws:
        info, _ = candidate_information(
            rj.with_values(problem.params, ("k", "c_out"), theta), ("k", "c_out"), space,
            {"v0": [0.4, 0.6, 0.8]}, ("x_M", "F_AN"), (1e-4, 50.0), problem.times,
            problem.smoothing, problem.options,
        )  # fmt: skip
        alone.append(info[0])
    alone = np.asarray(alone)  # (R, C, S, P, P)
    chosen = sum(alone[:, c, [plan.signals.index(s) for s in signals]].sum(axis=1)
                 for c, signals in plan.plan.firings)  # fmt: skip
    assert plan.plan.criterion == pytest.approx(plan_value(chosen), rel=1e-6)
    opts = options(alone, [1.0, 2.0], 2.0)
    assert plan.plan.criterion == pytest.approx(exhaustive(opts, 2).value, rel=1e-6)


def test_a_failed_solve_names_the_candidate():
    import recoil_jax as rj

    problem = rj.PlanProblem(
        design={"m": 0.0},
        fit={"k": (1e4, 5e4)},
        candidates={"v0": [0.4, 0.6]},
        signals={"x_M": rj.Sensor(1e-4)},
        rate=100.0,
        duration=0.5,
        firings=1,
        options=rj.SolverOptions(max_steps=3),
    )
    with pytest.raises(rj.SolveError, match=r"plan: the solve of candidate v0=0\.4 at the guess"):
        rj.plan_firings(problem)


BASE = {
    "design": {"m": 0.0},
    "fit": {"k": (1e4, 5e4)},
    "candidates": {"v0": [0.4, 0.6]},
    "signals": {"x_M": (1e-4, 1.0)},
    "rate": 100.0,
    "duration": 0.5,
    "firings": 1,
}


@pytest.mark.parametrize(
    "change, fragment",
    [
        ({"candidates": {"v0": "0.4"}}, "candidates.v0 = '0.4': give a list of values"),
        ({"candidates": {"v0": [0.4, "x"]}}, "candidates.v0 = 'x': give a number"),
        ({"signals": {"x_M": 1e-4}}, "signals.x_M = 0.0001: give Sensor(sigma, cost)"),
        ({"signals": {"x_M": ("a", 1.0)}}, "signals.x_M.sigma = 'a': give a number"),
        ({"rate": 1e308, "duration": 60.0}, "sampling.rate = 1e+308: valid > 0 to 1e6"),
        ({"rate": "fast"}, "sampling.rate = 'fast': give a number"),
        ({"seed": -1}, "seed = -1: valid an integer >= 0"),
        (
            {
                "robust": 256,
                "rate": 1e5,
                "duration": 1.0,
                "candidates": {"v0": [0.4, 0.5, 0.6]},
                "fit": {"k": (1e4, 5e4), "c_out": (1e3, 2e4)},
                "signals": {"x_M": (1e-4, 1.0), "v_M": (1e-3, 1.0)},
            },
            "a plan of 257 truths needs about 29.6 GB in memory, more than half of the 4.0 GB",
        ),
        (
            {
                "candidates": {
                    "v0": list(np.linspace(0.3, 0.9, 40)),
                    "pulse_time": list(np.linspace(0.001, 0.01, 30)),
                }
            },
            "candidates: 1,200 combinations",
        ),
        ({"candidates": {"mount_mass": [20000.0, 100.0]}}, "candidate mount_mass = 100: Mount"),
    ],
)
def test_a_bad_problem_is_refused_before_anything_compiles(change, fragment, monkeypatch):
    import recoil_jax as rj
    import recoil_jax._sweeps.memory as memory

    monkeypatch.setattr(memory, "_available_memory", lambda: 4 * 10**9)  # (the same anywhere)

    with pytest.raises(rj.ParameterError) as error:
        rj.PlanProblem(**(BASE | change))
    assert fragment in str(error.value)


def test_a_logarithmic_box_gives_an_interval_in_its_coordinates():
    """Over three decades and more the box is logarithmic: the 95 % interval is the
    guess times and divided by one factor (not guess ± 1.96 sd, which could go below
    zero), and the standard error is the linearised one."""
    import recoil_jax as rj

    problem = rj.PlanProblem(**(BASE | {"fit": {"c_out": (10.0, 1e5)}, "design": {"m": 0.0,
                                 "c_out": 3000.0}, "signals": {"x_M": (3e-3, 1.0)}}))  # fmt: skip
    plan = rj.plan_firings(problem)
    lo, hi = plan.plan.ci95["c_out"]
    assert lo > 0 and lo * hi == pytest.approx(3000.0**2, rel=1e-9)
    sd = plan.plan.stderr["c_out"]
    # log(hi / guess) = 1.96 sd_z log(u / l) = 1.96 sd / guess (the linearised error)
    assert np.log(hi / 3000.0) == pytest.approx(1.96 * sd / 3000.0, rel=1e-9)
