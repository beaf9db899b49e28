"""The solver machinery: peak location between steps, failure reporting, and the
transformations (jit, vmap, jacfwd, grad) the API promises."""

import dataclasses

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import all_ok, batch_params, batch_peaks, compiled_programs

import recoil_jax as rj
import recoil_jax.extend as rjx
from recoil_jax._model.bounds import future_metric_bounds
from recoil_jax._model.dense import hermite_max
from recoil_jax._model.equations import (
    RECOIL_TERM,
    initial_state,
    model_args,
    tracked_metrics,
    vector_field,
)
from recoil_jax._model.metrics import ENVELOPE_FIELDS


@pytest.mark.parametrize("size", [4, 20, 21, 115])
def test_error_norm_is_the_root_mean_square_either_way(size):
    """The step-size controller's norm: a chain of adds up to 20 components, a sum above
    (the sensitivities of many parameters); the same root mean square, zero at zero with
    a finite gradient there."""
    from recoil_jax._model.stepping import _rms_norm

    x = jnp.asarray(np.random.default_rng(size).normal(size=size))
    np.testing.assert_allclose(
        float(_rms_norm(x)), np.sqrt(np.mean(np.asarray(x) ** 2)), rtol=1e-14
    )
    zero = jnp.zeros(size)
    assert float(_rms_norm(zero)) == 0.0
    assert np.all(np.isfinite(np.asarray(jax.grad(_rms_norm)(zero))))


def test_hermite_max_matches_brute_force():
    rng = np.random.default_rng(0)
    p0, d0, p1, d1 = (jnp.asarray(rng.normal(size=500)) for _ in range(4))
    value, s = hermite_max(p0, d0, p1, d1)
    grid = np.linspace(0.0, 1.0, 20001)[:, None]
    h00, h10 = 2 * grid**3 - 3 * grid**2 + 1, grid**3 - 2 * grid**2 + grid
    h01, h11 = -2 * grid**3 + 3 * grid**2, grid**3 - grid**2
    brute = h00 * p0 + h10 * d0 + h01 * p1 + h11 * d1
    # The grid's spacing (5e-5) bounds how far below the true maximum it can fall.
    assert np.all(value >= brute.max(axis=0) - 1e-12)
    np.testing.assert_allclose(value, brute.max(axis=0), atol=1e-7)
    np.testing.assert_allclose(s, grid[brute.argmax(axis=0), 0], atol=1e-3)
    # Degenerate cubics (flat, linear, quadratic) give finite values and gradients.
    degenerate = [
        jnp.zeros(3),
        jnp.array([0.0, 1.0, 1.0]),
        jnp.array([1.0, 0.0, 0.0]),
        jnp.array([1.0, 0.0, 1.0]),
    ]
    assert np.isfinite(hermite_max(*degenerate)[0]).all()
    grads = jax.grad(lambda a: hermite_max(a, a, a, a)[0].sum())(jnp.zeros(3))
    assert np.isfinite(grads).all()


def test_tsit5_last_stage_is_the_end_derivative():
    """The peak loop takes f(y1) from Tsit5's FSAL stage: guard that assumption."""
    params, smoothing = rj.params_from_values(m=500.0, gap=0.0), rj.Smoothing()
    args = model_args(params, smoothing)
    solver = diffrax.Tsit5(scan_kind="lax")  # as the peak loop builds it
    y0 = initial_state(args)
    dt = 1e-3
    state = solver.init(RECOIL_TERM, 0.0, dt, y0, args)
    y1, _, dense, _, _ = solver.step(RECOIL_TERM, 0.0, dt, y0, args, state, False)
    np.testing.assert_allclose(dense["k"][-1] / dt, vector_field(dt, y1, args), rtol=1e-12)


@pytest.mark.parametrize("design", [dict(m=0.0), dict(m=500.0, gap=0.0), dict(m=1500.0, gap=0.062)])
def test_peaks_agree_with_dense_history(design):
    """Peaks lie between steps: no point of a fine history exceeds them, and the fine
    history comes within its own resolution of them. (The history is a separate
    diffeqsolve; a tight tolerance keeps the two solves' own errors out of the check.)"""
    params = rj.params_from_values(design)
    options = rj.SolverOptions(rtol=1e-10, atol=1e-13, max_steps=100_000)
    result = rj.peaks(params, options=options)
    history = rj.simulate(params, options=options, ts=jnp.linspace(0.0, 1.0, 100001))
    for peak, series in [
        (result.peak_displacement, history.x_M),
        (result.peak_anchoring_force, history.anchoring_force),
        (result.peak_contact_force, history.contact_force),
    ]:
        sampled = float(jnp.max(series))
        assert sampled <= float(peak) * (1 + 1e-8) + 1e-9
        assert sampled >= float(peak) * (1 - 1e-4) - 1e-9
    if params.absorber is not None:
        stroke = history.x_m - history.x_M
        assert float(jnp.max(stroke)) == pytest.approx(float(result.max_stroke), rel=1e-4)
        assert float(jnp.min(stroke)) == pytest.approx(float(result.min_stroke), rel=1e-4, abs=1e-7)


@pytest.mark.slow
def test_failed_solve_is_reported_not_truncated():
    params = rj.params_from_values(m=500.0, gap=0.0)
    options = rj.SolverOptions(max_steps=50)
    result = rj.peaks(params, options=options, throw=False)
    assert bool(result.status == rj.Status.max_steps)
    assert rj.Status[result.status] == rjx.status_messages(rj.Status.max_steps)[0]
    with pytest.raises(rj.SolveError, match="max_steps reached before t1"):
        rj.peaks(params, options=options)
    with pytest.raises(rj.SolveError, match="max_steps"):
        rj.simulate(params, options=options)
    # Without raising, a history says where it stopped: NaN after, never zeros.
    history = rj.simulate(params, options=options, ts=jnp.linspace(0.0, 2.0, 201), throw=False)
    assert bool(history.status == rj.Status.max_steps)
    x = np.asarray(history.x_M)
    reached = np.isfinite(x)
    assert reached[0] and not reached[-1] and 0.0 in x[reached]
    assert np.all(np.diff(reached.astype(int)) <= 0)  # finite, then NaN to the end
    assert np.all(np.isnan(np.asarray(history.anchoring_force)[~reached]))
    with pytest.raises(rj.SolveError, match="max_steps"):
        rj.peak_jacobian(params, options=options)
    # In a batch, each point carries its own status.
    batch = batch_peaks(
        [dict(m=500.0, gap=0.0), dict(m=500.0, gap=0.15)], options=rj.SolverOptions(max_steps=100)
    )
    assert rjx.status_messages(batch.status) == [
        rj.Status[rj.Status.max_steps],
        rj.Status[rj.Status.ok],
    ]


@pytest.mark.slow
def test_failures_raise_inside_a_users_jit_and_vmap():
    """`throw=True` checks inside the compiled program (equinox's error_if), so it works
    under a user's `jit` and `vmap`: `SolveError` under `eqx.filter_jit`, JAX's runtime
    error with the same message under `jax.jit`. A clean reason is recoverable."""
    options = rj.SolverOptions(max_steps=100)

    def force(gap):
        params = rj.RecoilParams(absorber=rj.Absorber(m=500.0, gap=gap))
        return rj.peaks(params, options=options).peak_anchoring_force

    filtered = eqx.filter_jit(force)
    assert float(filtered(jnp.asarray(0.15))) > 0  # a design that finishes in 100 steps
    with pytest.raises(rj.SolveError, match="max_steps reached before t1") as info:
        filtered(jnp.asarray(0.0))
    assert rj.failure_message(info.value) == rj.Status[rj.Status.max_steps]
    with pytest.raises(rj.SolveError, match="max_steps"):
        eqx.filter_jit(jax.vmap(force))(jnp.asarray([0.15, 0.0]))
    with pytest.raises(jax.errors.JaxRuntimeError, match="max_steps reached before t1"):
        jax.jit(force)(jnp.asarray(0.0))
    # Without `throw` the status is returned, per point, and nothing is raised.
    quiet = jax.jit(
        jax.vmap(
            lambda g: (
                rj.peaks(
                    rj.RecoilParams(absorber=rj.Absorber(m=500.0, gap=g)),
                    options=options,
                    throw=False,
                ).status
            )
        )
    )(jnp.asarray([0.15, 0.0]))
    assert rjx.status_messages(quiet) == ["ok", rj.Status[rj.Status.max_steps]]


@pytest.mark.slow
def test_outputs_are_finite():
    for design in (
        dict(m=0.0),
        dict(m=10.0, gap=0.0, n_c=1.0, lambda_c=0.0),
        dict(m=5000.0, gap=0.2, k_c=1e10, n_c=2.0, lambda_c=2.0, v0=2.0),
        # The firing envelope, with a mount: every metric it has, finite too.
        dict(friction_force=1000.0, elevation=10.0, mount_mass=9000.0),
    ):
        result = rj.peaks(rj.params_from_values(design))
        # (A design without the envelope has none of its metrics: NaN, by design.)
        unsolved = () if "mount_mass" in design else ENVELOPE_FIELDS
        fields = [f.name for f in dataclasses.fields(result) if f.name not in unsolved]
        assert all(
            np.isfinite(np.asarray(getattr(result, f))).all() for f in fields if f != "status"
        )
        history = rj.simulate(rj.params_from_values(design))
        states = (history.ts, history.x_M, history.v_M, history.x_m, history.v_m)
        leaves = jax.tree.leaves((states, history.forces))
        assert all(np.isfinite(np.asarray(leaf)).all() for leaf in leaves)


def test_batched_equals_loop():
    """vmap changes nothing but roundoff. XLA's batched and scalar transcendental
    functions can differ in the last bit, which may tip one accept/reject decision and so
    move a result by about the solver tolerance; at rtol 1e-10 that is far below 1e-8."""
    designs = [
        dict(m=100.0, gap=0.0),
        dict(m=800.0, gap=0.03, k_r=5e4),
        dict(m=1500.0, gap=0.062),
        dict(m=2500.0, gap=0.12, c_r=0.0),
    ]
    options = rj.SolverOptions(rtol=1e-10, atol=1e-13, max_steps=50_000)
    batch = batch_peaks(designs, options=options)
    for i, design in enumerate(designs):
        single = rj.peaks(rj.params_from_values(design), options=options)
        for field in rjx.PEAK_FIELDS:
            if field.startswith("num_"):
                continue
            rel = 1e-6 if field.endswith("time") else 1e-8  # a flat maximum's time: looser
            assert float(getattr(batch, field)[i]) == pytest.approx(
                float(getattr(single, field)), rel=rel, abs=1e-10, nan_ok=True
            ), field


def _peak_vector(x, autodiff="forward", rtol=1e-6):
    gap, m, k_r, c_r = x
    params = rj.RecoilParams(absorber=rj.Absorber(m=m, gap=gap, k_r=k_r, c_r=c_r))
    options = rj.SolverOptions(rtol=rtol, atol=rtol * 1e-3, autodiff=autodiff, max_steps=100_000)
    r = rj.peak_metrics(params, rj.Smoothing(), options)
    return jnp.stack([r.peak_displacement, r.peak_anchoring_force])


@pytest.mark.slow
def test_forward_and_reverse_mode_agree_with_finite_differences():
    """jacfwd (default loop) and grad/jacrev (checkpointed loop) give the same Jacobian,
    and it matches central differences (gap, m, k_r, c_r at the paper's best design)."""
    x = jnp.array([0.062, 1500.0, 13000.0, 3675.0])
    forward = jax.jit(jax.jacfwd(lambda x: _peak_vector(x, "forward", 1e-8)))(x)
    reverse = jax.jit(jax.jacrev(lambda x: _peak_vector(x, "reverse", 1e-8)))(x)
    np.testing.assert_allclose(forward, reverse, rtol=1e-9, atol=1e-12)
    tight = jax.jit(lambda x: _peak_vector(x, "forward", 1e-11))
    ranges = np.array([0.2, 5000.0, 1e5, 2e4])  # documented range widths
    steps = 1e-5 * ranges
    for j in range(4):
        e = jnp.zeros(4).at[j].set(steps[j])
        fd = (tight(x + e) - tight(x - e)) / (2 * steps[j])
        value = tight(x)
        scaled = np.abs(forward[:, j] - fd) * ranges[j] / np.abs(value)
        assert np.all(scaled <= 1e-3), (j, forward[:, j], fd)


def test_jit_compiles_once_for_new_values():
    """Parameter values are traced, not static: new values reuse the compilation."""
    counted = eqx.debug.assert_max_traces(rj.peak_metrics, max_traces=1)
    run = eqx.filter_jit(counted)
    for gap in (0.0, 0.03, 0.062):
        run(rj.params_from_values(m=800.0, gap=gap), rj.Smoothing(), rj.SolverOptions())
    assert eqx.debug.get_num_traces(counted) == 1


def test_hard_switches_and_other_tolerances_compile_nothing_more(reference_cases):
    """Widths and tolerances are values: after one solve, the hard-switch model and other
    tolerances (the defaults given explicitly, or tighter ones) run the same compiled
    program, for `peaks` and for `peak_jacobian`; the hard model still gives its own
    numbers (the exact contact onset)."""
    params = rj.params_from_values(m=1500.0, gap=0.062)
    smoothed = rj.peaks(params)
    rj.peak_jacobian(params, wrt=("gap",))
    with compiled_programs() as compiled:
        hard = rj.peaks(params, rj.Smoothing.exact(), rj.SolverOptions(rtol=1e-9, atol=1e-12))
        rj.peaks(params, options=rj.SolverOptions(rtol=1e-6, atol=1e-9))
        rj.peak_jacobian(params, rj.Smoothing.exact(), wrt=("gap",))
    assert not [name for name in compiled if "peak" in name], compiled
    assert rj.Smoothing.exact().hard and not rj.Smoothing().hard
    assert float(hard.peak_contact_force) != float(smoothed.peak_contact_force)
    # The paper's best design against the independent hard-switch reference.
    (case,) = [c for c in reference_cases if c["params"] == {"m": 1500.0, "gap": 0.062}]
    reference = case["reference"]["peak_anchoring_force_N"]
    assert float(hard.peak_anchoring_force) == pytest.approx(reference, rel=1e-6)


def test_vmap_over_smoothing_and_tolerance_leaves():
    """Widths and tolerances are leaves too (traced, vmappable)."""
    params = batch_params([dict(m=500.0, gap=0.0)] * 2)
    smoothing = rj.Smoothing(
        damping_width=jnp.array([1e-3, 1e-3]),
        contact_width_fraction=jnp.array([0.02, 0.01]),
        knot_width_fraction=jnp.array([1e-4, 1e-4]),
    )
    # Every leaf batched, as `in_axes=0` says.
    smoothing = jax.tree.map(lambda leaf: jnp.broadcast_to(leaf, (2,)), smoothing)
    run = eqx.filter_jit(jax.vmap(rj.peak_metrics, in_axes=(0, 0, None)))
    result = run(params, smoothing, rj.SolverOptions())
    assert all_ok(result.status)
    assert float(result.peak_contact_force[0]) != float(result.peak_contact_force[1])


def test_stopping_when_the_peaks_are_certain_changes_no_peak():
    """The loop stops once the energy bounds show no metric can rise again: the peaks
    and their times are exactly those of the run to t1, in far fewer steps."""
    from recoil_jax._model.solve import peaks_of_run
    from recoil_jax._model.stepping import StopWhenCertain, integrate_peaks

    rng = np.random.default_rng(7)
    designs = [
        dict(m=float(m), gap=float(g), k_r=float(k), c_r=float(c))
        for m, g, k, c in zip(
            rng.uniform(100, 3000, 48),
            rng.uniform(0, 0.15, 48),
            rng.uniform(5e3, 5e4, 48),
            rng.uniform(0, 1e4, 48),
            strict=True,
        )
    ]
    designs[:2] = [dict(m=500.0, gap=0.0), dict(m=1500.0, gap=0.062)]
    smoothing, options = rj.Smoothing(), rj.SolverOptions(rtol=1e-6, atol=1e-9)

    def solve(bounds_fn):
        def one(params):
            args = model_args(params, smoothing)
            stop = None if bounds_fn is None else StopWhenCertain(bounds_fn)
            run = integrate_peaks(
                RECOIL_TERM, initial_state(args), args, 10.0, tracked_metrics, options, stop=stop
            )
            return peaks_of_run(params, smoothing, run, 10.0, args.rest)

        return eqx.filter_jit(jax.vmap(one))(batch_params(designs))

    early, full = solve(future_metric_bounds), solve(None)
    assert all_ok(early.status) and all_ok(full.status)
    for field in (
        "peak_displacement",
        "peak_displacement_time",
        "peak_anchoring_force",
        "peak_anchoring_force_time",
        "peak_contact_force",
        "peak_contact_force_time",
        "min_stroke",
        "max_stroke",
    ):
        np.testing.assert_array_equal(getattr(early, field), getattr(full, field), field)
    assert np.all(early.num_steps <= full.num_steps)
    assert early.num_steps.sum() < 0.6 * full.num_steps.sum()


def test_testing_the_bounds_every_few_iterations_changes_no_peak_or_failure(monkeypatch):
    """The lane scheduler tests whether the peaks are certain at one iteration in
    `BOUNDS_EVERY` only: against the same scheduler testing at every iteration, the same
    designs succeed under a tight `max_steps` (one that became certain between tests is
    not reported as out of steps), with the same peaks, a few steps later."""
    import recoil_jax._model.lanes as queue
    from recoil_jax._model.solve import _peaks_batch

    rng = np.random.default_rng(11)
    designs = {
        "m": rng.uniform(100, 3000, 40),
        "gap": rng.uniform(0, 0.15, 40),
        "k_r": rng.uniform(5e3, 5e4, 40),
        "c_r": rng.uniform(0, 1e4, 40),
    }
    params = rjx.batch_params(designs)[0]
    t1 = jnp.full(40, 10.0)
    options = rj.SolverOptions(max_steps=90)  # some designs need more

    def solve(every):
        monkeypatch.setattr(queue, "BOUNDS_EVERY", every)
        program = eqx.filter_jit(lambda p, t: _peaks_batch(p, t, rj.Smoothing(), options, 8, None))
        return program(params, t1)

    each, fourth = solve(1), solve(4)
    ok = np.asarray(each.status == rj.Status.ok)
    assert 5 <= ok.sum() <= 35  # the limit bites for some, not all
    np.testing.assert_array_equal(np.asarray(fourth.status == rj.Status.ok), ok)
    for field in ("peak_displacement", "peak_anchoring_force", "peak_contact_force", "max_stroke"):
        np.testing.assert_array_equal(
            np.asarray(getattr(fourth, field))[ok], np.asarray(getattr(each, field))[ok], field
        )
    extra = np.asarray(fourth.num_steps - each.num_steps)[ok]
    assert extra.min() >= 0 and extra.max() <= 8 and extra.mean() > 0
