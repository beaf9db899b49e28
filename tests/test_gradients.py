"""Gradients of every peak metric against central finite differences of the same
smoothed model at a tight tolerance, and finiteness across the design space."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import ABSORBER, all_ok, batch_params, documented_values

import recoil_jax as rj
import recoil_jax.extend as rjx
from recoil_jax._model.metrics import ENVELOPE_FIELDS

# The metrics these designs have (the firing envelope's are NaN without it).
METRICS = tuple(name for name, m in rj.METRICS.items() if not m.envelope)
DESIGN = ("gap", "m", "k_r", "c_r")
DEFAULTS = {k: float(v) for k, v in rj.params_to_values(rj.RecoilParams()).items()}

# 24 designs: gap 0 (contact at once, then several late impacts), impacting gaps around
# the optimum, and gaps beyond the last impact (no contact at all).
GRADIENT_DESIGNS = (
    [dict(m=m, gap=0.0) for m in (100.0, 500.0, 1000.0, 1500.0)]
    + [dict(m=1500.0, gap=g) for g in (0.01, 0.03, 0.05, 0.062, 0.07)]
    + [dict(m=1000.0, gap=0.059), dict(m=500.0, gap=0.044), dict(m=100.0, gap=0.005)]
    + [
        dict(m=800.0, gap=0.02, k_r=5e4, c_r=500.0),
        dict(m=2500.0, gap=0.09, k_r=3e3),
        dict(m=3000.0, gap=0.04, c_r=1.5e4),
        dict(m=300.0, gap=0.0, k_r=8e4, c_r=0.0),
        dict(m=1200.0, gap=0.05, k_c=1e9, n_c=1.5, lambda_c=1.2),
        dict(m=600.0, gap=0.0, k_c=5e6, n_c=1.8, lambda_c=0.2),
    ]
    + [
        dict(m=100.0, gap=0.05),
        dict(m=500.0, gap=0.15),
        dict(m=1000.0, gap=0.12),
        dict(m=1500.0, gap=0.18),
        dict(m=50.0, gap=0.03),
        dict(m=4000.0, gap=0.2),
    ]
)
NO_IMPACT = slice(18, 24)


@pytest.fixture(scope="module")
def jacobians():
    run = eqx.filter_jit(jax.vmap(rj.peak_gradients, in_axes=(0, None, None, None)))
    peaks, grads = run(batch_params(GRADIENT_DESIGNS), rj.Smoothing(), rj.GRADIENT_OPTIONS, DESIGN)
    assert all_ok(peaks.status)
    return peaks, np.stack([np.asarray(getattr(grads, m)) for m in METRICS], axis=1)


@pytest.mark.slow
def test_gradients_match_finite_differences(jacobians):
    """|g − g_FD| · (documented range) / |peak| <= 1e-4 for every metric and each of gap,
    m, k_r, c_r; central differences (second-order one-sided at gap = 0) at rtol 1e-12."""
    _, grads = jacobians  # grads: (design, metric, parameter)
    tight = rj.SolverOptions(rtol=1e-12, atol=1e-15, max_steps=200_000)
    # The designs, then per parameter the designs moved by +h, -h (0 where that would
    # leave the range) and +2h, all in one sweep.
    offsets = (1.0, -1.0, 2.0)
    designs = list(GRADIENT_DESIGNS)
    for name in DESIGN:
        h = 1e-6 * rj.parameter_scale(name)
        for offset in offsets:
            for d in GRADIENT_DESIGNS:
                value = d.get(name, DEFAULTS[name])
                step = 0.0 if (value - h < 0 and offset == -1.0) else offset
                designs.append({**d, name: value + step * h})
    solved = rj.sweep(designs, options=tight, progress=False)
    assert np.all(solved.ok)
    n = len(GRADIENT_DESIGNS)
    blocks = np.stack([solved.peaks[m] for m in METRICS], axis=-1).reshape(-1, n, len(METRICS))
    base = blocks[0]
    for j, name in enumerate(DESIGN):
        scale = rj.parameter_scale(name)
        h = 1e-6 * scale
        up, down, up2 = blocks[1 + len(offsets) * j : 1 + len(offsets) * (j + 1)]
        one_sided = np.array([d.get(name, DEFAULTS[name]) - h < 0 for d in GRADIENT_DESIGNS])
        central = (up - down) / (2 * h)
        forward = (-3 * base + 4 * up - up2) / (2 * h)
        fd = np.where(one_sided[:, None], forward, central)
        size = np.maximum(np.abs(base), 1e-12)
        error = np.abs(grads[:, :, j] - fd) * scale / size
        # A peak that is exactly zero (no contact) has an exactly zero gradient.
        zero = base == 0
        assert np.all(grads[:, :, j][zero] == 0.0), name
        error = np.where(zero, 0.0, error)
        worst = np.max(error)
        print(f"{name}: worst scaled gradient error {worst:.1e}")
        assert worst <= 1e-4, (name, worst, np.unravel_index(np.argmax(error), error.shape))


def test_no_impact_gap_gradient_is_exactly_zero(jacobians):
    peaks, grads = jacobians
    assert np.all(np.asarray(peaks.peak_contact_force)[NO_IMPACT] == 0.0)
    assert np.all(grads[NO_IMPACT, :, DESIGN.index("gap")] == 0.0)
    impacting = grads[:18, :2, DESIGN.index("gap")]  # x_M and F_AN do depend on gap
    assert np.all(impacting != 0.0)


def test_jacobian_api_and_single_design():
    params = rj.params_from_values(m=1500.0, gap=0.062)
    peaks, grads = rj.peak_jacobian(params, wrt=("gap", "m", "k_c"))
    assert grads.wrt == ("gap", "m", "k_c") and grads.peak_anchoring_force.shape == (3,)
    assert float(peaks.peak_anchoring_force) == pytest.approx(5514.05, abs=0.02)
    table = grads.to_dict()
    assert set(table["peak_contact_force_N"]) == {"gap", "m", "k_c"}
    with pytest.raises(rj.ParameterError, match="cannot differentiate"):
        rj.peak_jacobian(params, wrt=("mass",))
    with pytest.raises(rj.ParameterError, match="simplified model"):
        rj.peak_jacobian(rj.params_from_values(m=0.0), wrt=("gap",))


def test_forward_sensitivity_gradients_agree_with_jacfwd_where_steps_resolve():
    """Away from contact (simplified model, barrel parameters) differentiating the loop
    and integrating forward sensitivities agree: two independent derivative paths."""
    params = rj.params_from_values(m=0.0)
    _, grads = rj.peak_jacobian(params, wrt=("k", "c_out", "v0"))

    def peak(x):
        p = rj.RecoilParams(barrel=rj.Barrel(k=x[0], c_out=x[1], v0=x[2]), absorber=None)
        r = rj.peak_metrics(
            p, rj.Smoothing(), rj.SolverOptions(rtol=1e-10, atol=1e-13, max_steps=100_000)
        )
        return jnp.stack([r.peak_displacement, r.peak_anchoring_force])

    x = jnp.array([27500.0, 6239.0, 0.6909])
    jac = jax.jit(jax.jacfwd(peak))(x)
    np.testing.assert_allclose(grads.peak_displacement, jac[0], rtol=1e-5)
    np.testing.assert_allclose(grads.peak_anchoring_force, jac[1], rtol=1e-5)


def _random_designs(count, seed):
    """Random designs over every documented range; a third pinned to the boundaries."""
    rng = np.random.default_rng(seed)
    designs = []
    for i in range(count):
        d = documented_values(rng, ("M", "v0", "k", "c_out", "c_ret", *ABSORBER))
        if i % 3 == 0:
            d.update(gap=0.0, c_r=0.0, n_c=1.0)
        if i % 5 == 0:
            d.update(lambda_c=0.0, c_out=0.0)
        designs.append(d)
    return designs


@pytest.mark.slow
def test_values_and_gradients_finite_over_1000_random_designs():
    designs = _random_designs(1000, seed=3)
    # every parameter of the paper's model (the hardware groups have their own tests)
    wrt = tuple(n for n, p in rj.PARAMETERS.items() if p.group in ("barrel", "absorber", "contact"))
    # Through the sweep's queued lanes: each design takes its own steps (a plain vmap
    # steps every lane until the slowest design ends).
    result = rj.sweep(designs, wrt=wrt, options=rj.SolverOptions(), progress=False)
    assert np.all(result.ok), result.failures()[:5]
    # (The firing envelope's metrics are NaN without it, by design: left out.)
    solved = {n: v for n, v in result.peaks.items() if n not in ENVELOPE_FIELDS}
    gradients = [v for n, v in result.gradients.items() if n not in ENVELOPE_FIELDS]
    assert len(gradients) == 5
    for values in (solved, *gradients):
        for name, value in values.items():
            assert np.all(np.isfinite(value)), name


def test_smooth_maximum_stops_early_without_changing_value_or_gradient(monkeypatch):
    """The smooth maximum stops once the energy bound says the rest of the run can add
    less than 1e-12 to its log-integral: fewer steps than integrating to t1, the same
    value and gradient (a throttling buffer at T = 10 N, where the stop saves most)."""
    from recoil_jax._model import derivatives

    knots = {f"orifice_{i}": 5e-4 * (1.0 - 0.04 * i) for i in range(8)}
    params = rj.params_from_values(
        m=0.0, piston_area=0.01, oil_density=870.0, discharge_coefficient=0.7,
        orifice_length=0.15, **knots,
    )  # fmt: skip
    wrt = tuple(knots)
    smooth = rj.SmoothMax(("peak_anchoring_force",), jnp.array([10.0]))

    def solve():
        # A fresh function each time: the tail threshold is read when traced.
        return eqx.filter_jit(
            lambda p: derivatives.tangent_solve(p, rj.Smoothing(), rj.GRADIENT_OPTIONS, wrt, smooth)
        )(params)

    early = solve()
    monkeypatch.setattr(derivatives, "_SMOOTH_TAIL", 0.0)  # never stops: integrates to t1
    full = solve()
    assert all_ok(early.peaks.status) and all_ok(full.peaks.status)
    assert int(early.peaks.num_steps) < 0.8 * int(full.peaks.num_steps)
    np.testing.assert_allclose(early.smooth_values, full.smooth_values, rtol=1e-12)
    np.testing.assert_allclose(early.smooth_gradients, full.smooth_gradients, rtol=1e-9)
    assert float(full.smooth_values[0]) < float(full.peaks.peak_anchoring_force)


def test_metric_series_matches_the_history_and_finite_differences():
    """The anchoring force on a `MetricSeries` equals `simulate`'s at the same times, its
    gradients equal central differences of `simulate` (tight tolerance), and save times
    after the run stopped (its peaks certain) are NaN."""
    from recoil_jax._model import derivatives

    knots = {f"orifice_{i}": 4e-4 * (1.0 - 0.1 * i) for i in range(4)}
    values = dict(
        m=0.0, piston_area=0.01, oil_density=870.0, discharge_coefficient=0.7,
        orifice_length=0.15, **knots,
    )  # fmt: skip
    wrt = tuple(knots)
    ts = np.concatenate([np.linspace(0.01, 0.3, 7), [9.9]])  # the last after the run
    series = rj.MetricSeries(("peak_anchoring_force",), ts)
    solve = eqx.filter_jit(
        lambda p: derivatives.tangent_solve(
            p, rj.Smoothing(), rj.GRADIENT_OPTIONS, wrt, None, series
        )
    )
    solved = solve(rj.params_from_values(values))
    peaks, force, slopes = solved.peaks, solved.series_values, solved.series_gradients
    assert all_ok(peaks.status)
    force, slopes = np.asarray(force[0]), np.asarray(slopes[0])
    assert np.isnan(force[-1]) and np.all(np.isnan(slopes[-1]))
    force, slopes, ts = force[:-1], slopes[:-1], ts[:-1]
    tight = rj.SolverOptions(rtol=1e-11, atol=1e-14, max_steps=400_000)
    history = jax.jit(lambda p: rj.simulate(p, rj.Smoothing(), tight, jnp.asarray(ts)))
    np.testing.assert_allclose(
        force, history(rj.params_from_values(values)).anchoring_force, rtol=1e-5
    )
    for j, name in enumerate(wrt):
        h = 1e-4 * values[name]
        up = history(rj.params_from_values({**values, name: values[name] + h}))
        down = history(rj.params_from_values({**values, name: values[name] - h}))
        fd = (np.asarray(up.anchoring_force) - np.asarray(down.anchoring_force)) / (2 * h)
        # Relative to the force's change over the parameter's own size.
        np.testing.assert_allclose(
            slopes[:, j] * values[name], fd * values[name], atol=2e-3 * np.max(force)
        )


@pytest.mark.parametrize("hardware", [False, True], ids=["paper", "burst"])
def test_the_tangent_system_is_traced_once(hardware):
    """The state with a tangent column per parameter is the largest part of a gradient
    program. Its vector field is traced once, inside diffrax's stage loop: not again for
    the first step's size, at t = 0, or after a load's stops, each of which was a whole
    further copy for XLA to compile (4 and 5 traces before)."""
    from recoil_jax._model import derivatives
    from recoil_jax.apps._bench.speed import hardware_designs

    traces = []
    original = derivatives._tangent_vf

    def counted(*args, **kwargs):
        traces.append(1)
        return original(*args, **kwargs)

    params, wrt = rj.RecoilParams(), ("gap", "m")
    if hardware:
        params = jax.tree.map(lambda x: x[0], rjx.batch_params(hardware_designs(1))[0])
        wrt = ("gap", "orifice_2", "recuperator_force")
    derivatives._tangent_term.cache_clear()
    derivatives._tangent_vf = counted
    try:
        jax.eval_shape(
            lambda p: derivatives.tangent_solve(p, rj.Smoothing(), rj.GRADIENT_OPTIONS, wrt),
            params,
        )
    finally:
        derivatives._tangent_vf = original
        derivatives._tangent_term.cache_clear()
    assert len(traces) == 1
