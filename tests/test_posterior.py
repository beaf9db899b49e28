"""The posterior of a calibration (`rj.sample_posterior`): NUTS on the fit's likelihood.

Where the model is near-linear in its parameters over their intervals (the paper
absorber's k, c_out and gap from one firing), the posterior under flat priors is the
Laplace approximation: means at the least-squares optimum, standard deviations the
Laplace standard errors, the same correlations. A normal prior then combines with it as
two Gaussians do (closed form). Bad settings are refused before anything runs.
"""

from __future__ import annotations

import dataclasses
import json
import threading
import time

import numpy as np
import pytest
from test_calibration import BOX, NOISE, TRUTH, synthetic, trace, write_trace

import recoil_jax as rj
import recoil_jax.extend as rjx
from recoil_jax._calibration import calibrate as calibrate_module, posterior as posterior_module
from recoil_jax._sweeps.memory import cores
from recoil_jax.apps._cli import main
from recoil_jax.apps._cli.calibrate import POSTERIOR_NOT_CONVERGED

#: Draws per chain and warm-up steps in these tests: 4 × 500 draws give a bulk ESS of
#: about 2,000, so a standard deviation to about 2 % and a mean to 0.03 of it.
DRAWS = 500


@pytest.fixture(scope="module")
def absorber():
    """The paper absorber's k, c_out and gap fitted to one synthetic firing."""
    calibration = rj.Calibration([rjx.Experiment(trace(TRUTH, seed=3))], fit=BOX)
    fit = rj.calibrate(calibration, progress=False)
    assert fit.explains and fit.converged
    return calibration, fit


@pytest.fixture(scope="module")
def posterior(absorber):
    calibration, fit = absorber
    return rj.sample_posterior(
        calibration, fit=fit, draws=DRAWS, warmup=DRAWS, chains=4, seed=0, progress=False
    )


def test_the_posterior_is_the_laplace_approximation_where_the_fit_is_near_linear(
    absorber, posterior
):
    """Means within 0.2 sd of the least-squares optimum, sds within 10 % of the Laplace
    standard errors, correlations within 0.03 (k and c_out: −0.985); the sampler
    converged (R̂ ≤ 1.01, bulk ESS ≥ 400, no divergence) and reports no disagreement."""
    _, fit = absorber
    assert posterior.converged, posterior.problems
    assert posterior.divergences == 0
    assert posterior.disagreements == []
    # k and c_out correlate (−0.985), but the data determine each: not a ridge. The
    # contact's fall in F_AN is steep but resolved: no sample is left out.
    assert posterior.unseparated == [] and posterior.left_out == 0
    print()
    for label, row in posterior.summary.items():
        stderr = fit.fitted[label].stderr
        print(
            f"{label}: mean {row['mean']:.6g} (fit {row['value']:.6g}), sd {row['sd']:.4g} "
            f"(Laplace {stderr:.4g}), R-hat {row['r_hat']:.4f}, bulk ESS {row['ess_bulk']:.0f}"
        )
        assert abs(row["mean"] - row["value"]) <= 0.2 * row["sd"], (label, row)
        assert abs(row["sd"] / stderr - 1.0) <= 0.1, (label, row)
        assert row["r_hat"] <= 1.01 and row["ess_bulk"] >= 400
        assert not row["disagree"]
    flat = posterior.draws.reshape(-1, len(posterior.labels))
    assert np.allclose(np.corrcoef(flat.T), fit.correlation, atol=0.03)
    # Every draw within the bounds, and the draws are not one point.
    for i, label in enumerate(posterior.labels):
        assert np.all((flat[:, i] >= BOX[label][0]) & (flat[:, i] <= BOX[label][1]))
    assert posterior.draws.shape == (4, DRAWS, 3)
    print(f"ESS/s {posterior.ess_per_second:.0f}, seconds {posterior.seconds}")


def test_chains_run_at_once_on_the_cores_and_give_the_same_draws(absorber, posterior):
    """By default the chains run as many at once as there are cores (on 2 cores: about
    twice the draws a second, `docs/calibration.md`); one at a time, each chain's draws,
    step size and sample statistics are the same to the bit."""
    calibration, fit = absorber
    assert posterior.parallel_chains == min(4, cores())
    other = 1 if posterior.parallel_chains > 1 else 2  # threads either way, on 1 core too
    alone = rj.sample_posterior(calibration, fit=fit, draws=DRAWS, warmup=DRAWS, chains=4,
                                seed=0, progress=False, parallel_chains=other)  # fmt: skip
    assert alone.parallel_chains == other and alone.to_json()["parallel_chains"] == other
    assert np.array_equal(alone.draws, posterior.draws)
    assert np.array_equal(alone.step_size, posterior.step_size)
    stats, alone_stats = posterior.inference_data.sample_stats, alone.inference_data.sample_stats
    for name in ("n_steps", "diverging", "lp"):
        assert np.array_equal(alone_stats[name].values, stats[name].values), name
    print(f"\nsampling {posterior.seconds['sampling']:.1f} s with {posterior.parallel_chains} "
          f"at once, {alone.seconds['sampling']:.1f} s with {other}")  # fmt: skip


@pytest.mark.parametrize("failing", [0, 1])
def test_a_failing_chain_stops_the_others_at_their_next_block(failing):
    """Chains on threads, two at a time: where any one fails (or Ctrl-C reaches the
    caller), its error comes back at once, not `_Stopped`: the other running chain
    (chain 1 failing while chain 0 runs, or 0 while 1 runs) stops at
    its next block and the rest never start (each chain here would take 2 s)."""
    stopping, blocks = threading.Event(), []

    def run(chain):
        for block in range(1000):
            if chain == failing and block == 10:
                raise ValueError(f"chain {chain} failed")
            time.sleep(0.002)
            if stopping.is_set():
                raise posterior_module._Stopped
            blocks.append(chain)

    started = time.perf_counter()
    with pytest.raises(ValueError, match=f"chain {failing} failed"):
        posterior_module._each_chain(run, 4, 2, stopping)
    assert time.perf_counter() - started < 1.0 and len(blocks) < 250
    # Without a failure, every chain's result in chain order.
    results = posterior_module._each_chain(lambda c: c * c, 4, 2, threading.Event())
    assert results == [0, 1, 4, 9]


def test_the_draws_and_diagnostics_are_written(posterior, tmp_path):
    """`posterior.nc` holds the draws as ArviZ reads them, with the sample statistics
    and the traces; the summary is JSON."""
    import arviz as az

    path = tmp_path / "posterior.nc"
    posterior.to_netcdf(path)
    idata = az.from_netcdf(str(path))
    theta = idata.posterior["theta"]
    assert list(theta.coords["parameter"].values) == list(posterior.labels)
    assert np.array_equal(np.asarray(theta), posterior.draws)
    assert int(idata.sample_stats["diverging"].sum()) == posterior.divergences
    assert {"x_M in experiment 0", "F_AN in experiment 0"} <= set(idata.observed_data)
    # The noise the likelihood held: the fit's estimate (none was given).
    assert posterior.noise[0]["x_M"] == {"sigma": posterior.fit.sigma[0]["x_M"], "given": False}
    text = json.dumps(posterior.to_json())
    assert json.loads(text)["summary"]["gap"]["ess_bulk"] == posterior.summary["gap"]["ess_bulk"]


def test_a_ridge_is_said_to_be_unseparated_and_a_determined_correlation_is_not():
    """Draws along friction's ridge at one elevation (F_0 + μ·M·g = 2,383 N, uniform
    along it within the bounds, 1 N across) are called unseparated; two values as
    correlated (−0.985) but each a thousandth of its prior wide are not, nor are two
    loose values that do not correlate."""
    from recoil_jax._calibration.posterior import _unseparated

    rng = np.random.default_rng(0)
    mu = rng.uniform(0.0, 0.1, 4000)
    force = 2383.0 - 1800 * 9.81 * mu + rng.normal(0.0, 1.0, mu.size)
    prior_sd = np.array([2000.0, 0.1]) / np.sqrt(12.0)
    labels = ("friction_force", "friction_coefficient")
    (words,) = _unseparated(np.stack([force, mu], axis=1), labels, prior_sd)
    assert words.startswith("friction_force and friction_coefficient: correlation -1.000")
    assert "the data do not separate them" in words
    tight = rng.multivariate_normal([0.0, 0.0], [[1.0, -0.985], [-0.985, 1.0]], 4000)
    assert _unseparated(tight * prior_sd * 1e-3, labels, prior_sd) == []
    loose = rng.uniform(-1.0, 1.0, (4000, 2)) * prior_sd * np.sqrt(3.0)
    assert _unseparated(loose, labels, prior_sd) == []


#: The envelope howitzer (`optimise/plans/envelope_friction.toml`'s gun) with its
#: friction: fired at 0° only, the data determine `F_0 + μ·M·g` and not each.
HOWITZER = {"M": 1800.0, "m": 0.0, "k": 0.0, "v0": 10.0, "pulse_time": 0.004,
            "stop_stiffness": 2.1e8, "recuperator_length": 1.8, "buffer_length": 0.15,
            "buffer_damping": 150000.0, "c_out": 16000.0, "recuperator_preload": 30000.0,
            "c_ret": 29836.4, "friction_force": 1500.0, "friction_coefficient": 0.05}  # fmt: skip
FRICTION_BOX = {"friction_force": (500.0, 2500.0), "friction_coefficient": (0.0, 0.1)}


@pytest.mark.slow
def test_friction_at_one_elevation_is_sampled_as_the_ridge_it_is():
    """Fired at 0° only (501 samples of x_M and F_AN over 1 s, from the independent
    hard-switch solver with noise), the slide friction's `F_0` and `μ` are a ridge,
    `F_0 + μ·M·g = const`, a newton or two wide and 1,766 N long within the bounds. The
    fit says it cannot confine them; the draws lie on the ridge (within 10 N of the
    truth's combination), correlate below −0.95, each spread over most of its prior
    (95 % interval over 60 % of the bounds), along it as the uniform priors say
    (μ's mean and sd those of a uniform over [0, 0.1], to 4 standard errors of the
    chains' ESS and 25 %), and the report says the data do not separate them and gives
    no Laplace interval for either."""
    ts = np.linspace(0.0, 1.0, 501)
    history = rjx.reference_history({**HOWITZER, "elevation": 0.0}, ts)
    rng = np.random.default_rng(0)
    noise = {"x_M": 3e-4, "F_AN": 200.0}
    noisy = {s: history[s] + sigma * rng.standard_normal(ts.size) for s, sigma in noise.items()}
    experiment = rjx.Experiment(rjx.Trace.of(ts, **noisy), design={"elevation": 0.0, "t1": 1.0},
                                sigma=noise)  # fmt: skip
    known = {k: v for k, v in HOWITZER.items() if k not in FRICTION_BOX}
    calibration = rj.Calibration([experiment], FRICTION_BOX, design=known)
    fit = rj.calibrate(calibration, progress=False)
    assert fit.explains and not any(f.identifiable for f in fit.fitted.values())
    posterior = rj.sample_posterior(calibration, fit=fit, draws=200, warmup=200, chains=2,
                                    progress=False)  # fmt: skip
    force, mu = (posterior.draws[..., i].ravel() for i in range(2))
    weight = HOWITZER["M"] * 9.81
    truth = HOWITZER["friction_force"] + HOWITZER["friction_coefficient"] * weight
    assert np.max(np.abs(force + mu * weight - truth)) < 10.0
    assert np.corrcoef(force, mu)[0, 1] < -0.95
    for label, (lower, upper) in FRICTION_BOX.items():
        row = posterior.summary[label]
        assert row["q97.5"] - row["q2.5"] > 0.6 * (upper - lower), (label, row)
        assert row["ci95"] is None  # the fit claims no interval
    ess = posterior.summary["friction_coefficient"]["ess_bulk"]
    uniform_sd = 0.1 / np.sqrt(12.0)
    print(f"\nμ mean {mu.mean():.4f} (0.05), sd {mu.std():.4f} ({uniform_sd:.4f}),"
          f" ESS {ess:.0f}, divergences {posterior.divergences},"
          f" {posterior.ess_per_second:.2f} ESS/s")  # fmt: skip
    assert abs(mu.mean() - 0.05) < 4 * uniform_sd / np.sqrt(ess)
    assert abs(mu.std() / uniform_sd - 1.0) < 0.25
    (words,) = posterior.unseparated
    assert words.startswith("friction_force and friction_coefficient") and (
        "the data do not separate them" in words
    )


def test_the_samples_either_side_of_a_jump_are_left_out_of_the_likelihood():
    """Friction fired at 0°: the counter-recoil buffer's engagement is a jump in `F_AN`
    (≈5 kN) between two samples, and 2 N less friction moves it across one of them:
    χ² +280, a cliff no gradient sampler crosses. The samples either side of each jump
    at the optimum are left out (`_off_the_jumps`), and then the same 2 N change moves
    χ² by its smooth part only."""
    import jax.numpy as jnp
    from test_reference_envelope import HOWITZER

    from recoil_jax._calibration.layout import Layout, prepare
    from recoil_jax._calibration.least_squares import FitSettings, evaluate_program
    from recoil_jax._calibration.posterior import _off_the_jumps

    design = HOWITZER | {"elevation": 0.0}
    ts = np.arange(0.0, 1.0 + 1e-12, 2e-3)
    history = rj.simulate(rj.params_from_values(design), rj.Smoothing(),
                          rj.SolverOptions(t1=1.0), ts)  # fmt: skip
    sigma = {"x_M": 3e-4, "F_AN": 300.0}
    rng = np.random.default_rng(3)
    signals = {n: np.asarray(getattr(history, n)) + s * rng.standard_normal(ts.size)
               for n, s in sigma.items()}  # fmt: skip
    known = {k: v for k, v in design.items()
             if k not in ("friction_force", "friction_coefficient")}  # fmt: skip
    experiment = rjx.Experiment(rjx.Trace.of(ts, **signals), design=known, sigma=sigma)
    box = {"friction_force": (500.0, 2500.0), "friction_coefficient": (0.0, 0.1)}
    calibration = rj.Calibration([experiment], fit=box)
    fit = rj.calibrate(calibration, starts=1, progress=False)
    assert fit.explains
    layout = Layout.of(calibration)
    data = prepare(calibration, calibration.experiments, layout)
    static = FitSettings(layout.wrt, layout.signals, calibration.loss, calibration.f_scale, 1,
                         estimate_noise=False)  # fmt: skip
    kept, left_out = _off_the_jumps(data, static, fit, layout)
    assert 2 <= left_out <= 12, left_out
    dropped = np.argwhere(np.asarray(data.present) & ~np.asarray(kept.present))
    assert any(abs(ts[i] - 0.986) < 3e-3 for _, s, i in dropped if s == 1), dropped

    def chi2(data_, force):
        theta = jnp.asarray([force, fit.values["friction_coefficient"]])
        return float(np.sum(np.asarray(evaluate_program(theta, data_, static).residuals) ** 2))

    # Within 6 N of the optimum (its sd across the ridge is about 1 N), half a newton
    # at a time: where the buffer's jump crosses a sample, χ² steps.
    forces = fit.values["friction_force"] + np.arange(-6.0, 6.01, 0.5)
    steps = np.diff([chi2(data, f) for f in forces])
    smooth = np.diff([chi2(kept, f) for f in forces])
    print(
        f"\nχ² change a half newton at a time, all samples: {np.round(steps, 1)}; "
        f"{left_out} left out: {np.round(smooth, 1)}"
    )
    assert np.max(np.abs(steps)) > 100 and np.max(np.abs(smooth)) < 10


def test_the_predictive_band_holds_the_measured_samples_as_often_as_it_says(posterior):
    """The model at 200 draws, widened by the likelihood's noise, holds 95 % of the
    measured samples (601 a signal: 0.95 ± 0.02 at two binomial sd); the same band made
    with half the noise holds far fewer (a normal's ±0.98 sd: 67 %), so the check can
    fail. The model's own band is narrow about the least-squares traces."""
    from recoil_jax._calibration.posterior import _predictive

    predictive = posterior.predictive()
    assert predictive.draws == 200 and predictive.failed == 0
    assert predictive.experiments == [posterior.fit.experiments[0]["name"]]
    print()
    for name, share in predictive.coverage[0].items():
        low, median, high = predictive.model[0][name]
        fitted = posterior.fit.model[0][name]
        sigma = posterior.noise[0][name]["sigma"]
        print(f"{name}: {share:.1%} inside; the model's band {np.median(high - low):.3g} "
              f"wide (noise sd {sigma:.3g})")  # fmt: skip
        assert 0.93 <= share <= 0.97, (name, share)
        assert np.max(np.abs(median - fitted)) < 0.2 * sigma
        assert np.median(high - low) < sigma  # the parameters' share is small here
    halved = [{k: {**v, "sigma": v["sigma"] / 2} for k, v in e.items()} for e in posterior.noise]
    flat = posterior.draws.reshape(-1, posterior.draws.shape[-1])[::10]
    signals, codes = posterior._signals(flat)
    assert np.all(codes == 0)
    narrow = _predictive(posterior.fit, halved, signals, 0, 0)
    for name, share in narrow.coverage[0].items():
        assert 0.6 <= share <= 0.75, (name, share)
    with pytest.raises(rj.ParameterError, match="draws must be in"):
        posterior.predictive(draws=1)
    with pytest.raises(rj.ParameterError, match="holds no model to solve"):
        dataclasses.replace(posterior, _signals=None).predictive()


def test_the_chains_coordinates_are_the_box_inside_and_bend_only_at_its_bounds():
    """`_box`, `y → z`: the identity on the box's inside (a ridge straight in the values
    stays straight: off by `δ·e^{−d/δ}` at `d` from a bound), into [0, 1] for any y,
    with the log slope the density uses equal to autodiff's (to a constant), finite
    with its gradient at any y, and inverted by `_box_inverse`."""
    import jax
    import jax.numpy as jnp

    from recoil_jax._calibration.posterior import EDGE, _box, _box_inverse, _log_box_slope

    inside = np.linspace(3 * EDGE, 1 - 3 * EDGE, 101)
    off = np.abs(np.asarray(_box(jnp.asarray(inside))) - inside)
    distance = np.minimum(inside, 1.0 - inside)  # to the nearer bound
    assert np.all(off <= 1.01 * EDGE * np.exp(-distance / EDGE) + 1e-15)
    y = np.concatenate([np.linspace(-50.0, 51.0, 1011), inside])
    z = np.asarray(_box(jnp.asarray(y)))
    assert np.all((z >= 0.0) & (z <= 1.0)) and np.all(np.diff(z[:1011]) >= 0.0)
    slope = np.asarray(jax.vmap(jax.grad(_box))(jnp.asarray(y)))
    kept = slope > 1e-250  # where autodiff's slope has not underflowed
    constant = np.log(-np.expm1(-1.0 / EDGE))
    np.testing.assert_allclose(np.asarray(_log_box_slope(jnp.asarray(y)))[kept] + constant,
                               np.log(slope[kept]), rtol=1e-9, atol=1e-9)  # fmt: skip
    gradient = np.asarray(jax.vmap(jax.grad(_log_box_slope))(jnp.asarray(y)))
    assert np.all(np.isfinite(np.asarray(_log_box_slope(jnp.asarray(y))))) and np.all(
        np.isfinite(gradient)
    )
    z_inner = np.concatenate([[1e-9, 1e-4, EDGE, 0.5, 1 - EDGE, 1 - 1e-4, 1 - 1e-9], inside])
    np.testing.assert_allclose(np.asarray(_box(jnp.asarray(_box_inverse(z_inner)))), z_inner,
                               rtol=1e-9, atol=1e-15)  # fmt: skip


def test_the_chains_are_scaled_by_the_laplace_covariance_where_the_data_determine_all(
    absorber,
):
    """The chains' coordinates (`_whitening`): the data's `JᵀJ` plus the priors'
    curvature, in the chains' coordinates `y` (the box coordinates inside their bends at
    the bounds). Where the data determine every value (the paper absorber), that is the
    fit's Laplace covariance carried into
    those coordinates (`Σ_y = D Σ_θ D`, `D = dy/dθ`): sds within 2 %, correlations within
    0.01."""
    import jax
    import jax.numpy as jnp

    from recoil_jax._calibration.layout import Layout
    from recoil_jax._calibration.posterior import EDGE, _likelihood, _priors, _whitening

    calibration, fit = absorber
    layout = Layout.of(calibration)
    data, static, left_out = _likelihood(calibration, fit, layout)
    assert left_out == 0
    priors, _ = _priors(None, layout)
    factor = np.asarray(_whitening(fit, layout, data, static, priors).factor)
    chains = factor @ factor.T
    z = np.asarray(data.space.z(np.array([fit.values[k] for k in layout.labels])))
    slope = np.asarray(jax.jvp(data.space.theta, (jnp.asarray(z),), (jnp.ones(len(z)),))[1])
    # Inside the box's bends (each value here is), y = z: dy/dθ = 1/slope.
    assert np.all((z > 10 * EDGE) & (z < 1 - 10 * EDGE))
    dy_dtheta = 1.0 / slope
    laplace = np.asarray(fit.covariance) * np.outer(dy_dtheta, dy_dtheta)
    sd_chains, sd_laplace = np.sqrt(np.diag(chains)), np.sqrt(np.diag(laplace))
    np.testing.assert_allclose(sd_chains, sd_laplace, rtol=0.02)
    np.testing.assert_allclose(chains / np.outer(sd_chains, sd_chains),
                               laplace / np.outer(sd_laplace, sd_laplace), atol=0.01)  # fmt: skip


def test_the_density_without_gradients_is_the_density_nuts_samples(absorber):
    """The log density a sampler without gradients gets (emcee's in `bench-calibration
    --posterior`: one solve of the state alone, `model_residuals`, at a hundredth of the
    tolerances) is the one NUTS samples, to 0.01 across the chains' scale; at the same
    tolerances it is not (NUTS's solve controls the sensitivities' error too, and is the
    more accurate). A failed solve is the fit's failed residual."""
    import jax
    import jax.numpy as jnp

    from recoil_jax._calibration.layout import Layout
    from recoil_jax._calibration.least_squares import FAILED_RESIDUAL, model_residuals
    from recoil_jax._calibration.posterior import _likelihood, _log_density, _priors, _whitening
    from recoil_jax.apps._bench.posterior import emcee_data

    calibration, fit = absorber
    layout = Layout.of(calibration)
    data, static, _ = _likelihood(calibration, fit, layout)
    priors, _ = _priors(None, layout)
    whitening = _whitening(fit, layout, data, static, priors)
    points = jnp.asarray(np.random.default_rng(0).standard_normal((6, len(layout.labels))) * 2)

    def density(data, gradient):
        return np.asarray(jax.jit(jax.vmap(
            lambda w: _log_density(w, data, priors, whitening, static, gradient)
        ))(points))  # fmt: skip

    with_sensitivities = density(data, True)
    assert np.ptp(with_sensitivities) > 1.0  # the points span the posterior
    np.testing.assert_allclose(density(emcee_data(data), False), with_sensitivities,
                               atol=0.01, rtol=0)  # fmt: skip
    assert np.max(np.abs(density(data, False) - with_sensitivities)) > 0.02
    # A solve that fails (a step budget of 1) gives every present sample the failed
    # residual, as the fit's own evaluation does.
    starved = eqx_replace_max_steps(data, 1)
    theta = jnp.asarray([fit.values[k] for k in layout.labels])
    r = np.asarray(model_residuals(theta, starved, static))
    present = np.asarray(starved.present)
    assert np.all(r[present] == FAILED_RESIDUAL) and np.all(r[~present] == 0.0)


def eqx_replace_max_steps(data, max_steps: int):
    """`data` whose solves get `max_steps` steps at most."""
    import equinox as eqx

    return eqx.tree_at(lambda d: d.options, data,
                       dataclasses.replace(data.options, max_steps=max_steps))  # fmt: skip


def test_the_posterior_hardware_gives_its_draws_to_predict(posterior):
    """`Posterior.hardware()`: the fit's hardware values with the draws' covariance
    (near the Laplace one here); `sample` gives the draws themselves, thinned evenly
    over every chain, and past their number uses each once or twice, evenly."""
    hardware = posterior.hardware()
    laplace = posterior.fit.hardware()
    assert hardware.names == laplace.names and np.all(hardware.identifiable)
    np.testing.assert_allclose(np.sqrt(np.diag(hardware.covariance)),
                               np.sqrt(np.diag(laplace.covariance)), rtol=0.1)  # fmt: skip
    flat = posterior.draws.reshape(-1, posterior.draws.shape[-1])
    total = len(flat)
    drawn, _ = hardware.sample(total)
    np.testing.assert_array_equal(drawn, flat[:, [posterior.labels.index(n)
                                                  for n in hardware.names]])  # fmt: skip
    # Fewer: evenly thinned; past their number, each draw once or twice, over every
    # chain. (Draws numbered: a chain's draws repeat where a transition was refused.)
    numbered = dataclasses.replace(hardware, draws=np.repeat(
        np.arange(total, dtype=float)[:, None], len(hardware.names), axis=1))  # fmt: skip
    fewer, _ = numbered.sample(total // 4)
    np.testing.assert_array_equal(fewer[:, 0], np.arange(0, total, 4))  # every 4th
    more, _ = numbered.sample(2 * total - 1)
    _, uses = np.unique(more[:, 0], return_counts=True)
    assert len(uses) == total and set(uses) == {1, 2}
    halves = np.array_split(uses, 2)  # the first chains' draws against the last's
    assert abs(int(halves[0].sum()) - int(halves[1].sum())) <= 2


@pytest.mark.slow
def test_a_normal_prior_combines_with_the_likelihood_as_two_gaussians_do(absorber):
    """A normal prior on gap, one standard error wide and one above the optimum: the
    posterior's mean and covariance are the product of it and the Laplace Gaussian
    (closed form: the precisions add), to 0.2 sd and 10 %."""
    calibration, fit = absorber
    labels = list(fit.fitted)
    g = labels.index("gap")
    mu = np.array([fit.values[k] for k in labels])
    covariance = fit.covariance
    s = fit.fitted["gap"].stderr
    prior_mean = mu[g] + s
    posterior = rj.sample_posterior(
        calibration,
        fit=fit,
        draws=DRAWS,
        warmup=DRAWS,
        chains=4,  # R-hat's 1.01 gate is for four chains or more (Vehtari et al. 2021)
        seed=1,
        progress=False,
        priors={"gap": {"kind": "normal", "mean": prior_mean, "sd": s}},
    )
    precision = np.linalg.inv(covariance)
    e = np.zeros(len(labels))
    e[g] = 1.0
    combined = np.linalg.inv(precision + np.outer(e, e) / s**2)
    mean = combined @ (precision @ mu + e * prior_mean / s**2)
    assert posterior.converged, posterior.problems
    for i, label in enumerate(labels):
        row, sd = posterior.summary[label], np.sqrt(combined[i, i])
        print(
            f"{label}: mean {row['mean']:.6g} (closed form {mean[i]:.6g}), sd {row['sd']:.4g} "
            f"({sd:.4g})"
        )
        assert abs(row["mean"] - mean[i]) <= 0.2 * sd, label
        assert abs(row["sd"] / sd - 1.0) <= 0.1, label
    # The prior narrowed gap by about 1/√2, which the Laplace interval does not know.
    assert posterior.summary["gap"]["sd"] < 0.85 * s


@pytest.mark.slow
def test_a_sampled_noise_is_the_closed_form_and_comes_back_from_a_wrong_one(absorber):
    """`sample_noise=True`: each trace's noise sampled with the values, under a
    half-normal prior. With n Gaussian samples the posterior of σ is, to first order,
    normal about the fit's estimate with sd σ̂/√(2n) (the χ² of n samples): sds within
    15 % of it, the true noise inside the 95 % interval, the values' sds still the
    Laplace ones (their optimum does not depend on σ). Told twice the true noise, the
    sampled noise comes back to the truth (the given value far outside its interval)."""
    calibration, fit = absorber
    posterior = rj.sample_posterior(calibration, fit=fit, draws=DRAWS, warmup=DRAWS, chains=4,
                                    seed=0, progress=False, sample_noise=True)  # fmt: skip
    assert posterior.converged, posterior.problems
    n = 601
    for name, noise in posterior.noise[0].items():
        sampled = noise["sampled"]
        assert sampled["sd"] == pytest.approx(noise["sigma"] / np.sqrt(2 * n), rel=0.15)
        assert sampled["q2.5"] < NOISE[name] < sampled["q97.5"], (name, sampled)
        assert sampled["half_normal_scale"] == pytest.approx(2 * noise["sigma"])
    for label, row in posterior.summary.items():
        assert row["sd"] == pytest.approx(row["stderr"], rel=0.1), label
    assert posterior.inference_data.posterior["sigma"].shape == (4, DRAWS, 2)

    told = rj.Calibration([rjx.Experiment(trace(TRUTH, seed=3),
                                          sigma={k: 2 * v for k, v in NOISE.items()})],
                          fit=BOX)  # fmt: skip
    told_fit = rj.calibrate(told, progress=False)
    posterior = rj.sample_posterior(told, fit=told_fit, draws=300, warmup=300, chains=2,
                                    seed=1, progress=False, sample_noise=True)  # fmt: skip
    for name, noise in posterior.noise[0].items():
        sampled = noise["sampled"]
        assert noise["given"] and noise["sigma"] == 2 * NOISE[name]
        assert sampled["q2.5"] < NOISE[name] < sampled["q97.5"], (name, sampled)
        assert sampled["q97.5"] < 1.2 * NOISE[name]


@pytest.fixture
def no_fit(monkeypatch):
    """A `calibrate` that fails the test if called: what is refused must be refused
    before any fit or compilation."""

    class Reached(Exception):
        pass

    def reached(*_, **__):
        raise Reached

    monkeypatch.setattr(calibrate_module, "calibrate", reached)
    return Reached


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        ({"draws": 0}, "draws must be in [1, 100000], got 0"),
        ({"draws": 2.5}, "draws must be an integer in [1, 100000], got 2.5"),
        ({"warmup": True}, "warmup must be an integer"),
        ({"chains": 10**6}, "chains must be in [1, 64], got 1000000"),
        ({"chains": "4"}, "chains must be an integer"),
        ({"parallel_chains": 0}, "parallel_chains must be in [1, 64], got 0"),
        ({"parallel_chains": 2.0}, "parallel_chains must be an integer in [1, 64], got 2.0"),
        ({"seed": -1}, "seed must be in [0, 9223372036854775807], got -1"),
        ({"seed": 2**63}, "seed must be in [0, 9223372036854775807]"),
        ({"target_acceptance": "x"}, "target_acceptance must be in [0.5, 1), got 'x'"),
        ({"priors": ["gap"]}, "priors: a mapping of fitted names to priors"),
        ({"priors": {"gap": {"mean": "x", "sd": 0.01}}}, "needs a finite number for its mean"),
        ({"priors": {"gap": {"mean": True, "sd": 0.01}}}, "needs a finite number for its mean"),
        ({"target_acceptance": 1.0}, "target_acceptance must be in [0.5, 1)"),
        ({"dense_mass": "yes"}, "dense_mass must be True or False, got 'yes'"),
        ({"priors": {"m": "uniform"}}, "prior for 'm': not a fitted value (fitted: k, c_out, gap)"),
        ({"priors": {"gap": {"kind": "normal", "mean": 0.02, "sd": 0.0}}}, "prior sd must be > 0"),
        (
            {"priors": {"gap": {"kind": "normal", "mean": 0.02}}},
            "a normal prior needs a finite number for its sd, got None",
        ),
        ({"priors": {"gap": {"kind": "cauchy", "mean": 0.0, "sd": 1.0}}}, "prior kind 'cauchy'"),
        ({"priors": {"gap": {"mean": 0.02, "sd": 0.01, "width": 1}}}, "unknown key 'width'"),
        ({"priors": {"k": {"kind": "lognormal", "mean": -1.0, "sd": 1.0}}}, "mean must be > 0"),
        ({"priors": {"k": {"kind": "uniform", "mean": 1.0}}}, "a uniform prior takes no mean"),
        ({"sample_noise": "yes"}, "sample_noise must be True or False, got 'yes'"),
        ({"noise_scale": {"F_AN": 300.0}}, "noise_scale is the sampled noise's prior: give "
                                           "sample_noise=True"),
        ({"sample_noise": True, "noise_scale": {"v_M": 1.0}},
         "noise_scale for 'v_M': not a measured signal (measured: x_M, F_AN)"),
        ({"sample_noise": True, "noise_scale": {"F_AN": 0.0}},
         "noise_scale for 'F_AN' must be a number > 0, got 0.0"),
        ({"sample_noise": True, "noise_scale": {"F_AN": float("inf")}},
         "noise_scale for 'F_AN' must be a number > 0, got inf"),
        ({"sample_noise": True, "noise_scale": [300.0]}, "noise_scale: a mapping of signals"),
        ({"sample_noise": True, "loss": "soft_l1"},
         "sample_noise needs the linear loss (a soft_l1 loss has no normalised likelihood"),
    ],
)  # fmt: skip
def test_bad_settings_are_refused_before_anything_runs(no_fit, settings, message):
    settings = dict(settings)
    loss = settings.pop("loss", "linear")
    calibration = rj.Calibration([rjx.Experiment(trace(TRUTH, seed=3))], fit=BOX, loss=loss)
    with pytest.raises(rj.ParameterError) as raised:
        rj.sample_posterior(calibration, **settings)
    assert message in str(raised.value)


def test_a_normal_prior_mostly_outside_the_bounds_is_warned(no_fit):
    calibration = rj.Calibration([rjx.Experiment(trace(TRUTH, seed=3))], fit=BOX)
    with pytest.warns(UserWarning, match=r"prior for 'gap'.* 98% of its mass outside the bounds"):
        with pytest.raises(no_fit):  # warned, then on to the fit
            rj.sample_posterior(calibration, priors={"gap": rjx.Prior("normal", -0.2, 0.1)})


def test_a_fit_of_another_calibration_is_refused(absorber):
    """The fit's values must be this calibration's, with the same bounds: its noise and
    optimum start the chains."""
    _, fit = absorber
    other = rj.Calibration([rjx.Experiment(trace(TRUTH, seed=3))], fit=BOX | {"gap": (0.0, 0.05)})
    with pytest.raises(rj.ParameterError, match="a result of another calibration"):
        rj.sample_posterior(other, fit=fit)


@pytest.mark.slow
def test_with_a_flat_likelihood_the_draws_are_the_priors():
    """Traces said to be a million times noisier than they are leave the priors alone:
    k's lognormal, c_out's uniform and gap's normal, each truncated to its bounds, are
    what the draws follow (Kolmogorov–Smirnov on every 5th draw, p > 0.001). This checks
    the transform's Jacobian and each prior's density, which a likelihood as narrow as
    the others' hides. The threshold: the errors this is for (a Jacobian term missing or
    wrong, a wrong density) move a whole distribution, which 400 draws show far below
    it; at 0.01 on three values a correct sampler failed by chance (c_out's p 0.00996 on
    one machine, where seeds 2 to 7 gave 0.03 to 0.84 on another)."""
    from scipy import stats

    calibration = rj.Calibration(
        [rjx.Experiment(trace(TRUTH, seed=3), sigma={"x_M": 200.0, "F_AN": 3e8})], fit=BOX
    )
    fit = rj.calibrate(calibration, progress=False)
    assert fit.explains
    priors = {"k": rjx.Prior("lognormal", 4e4, 2e4), "gap": rjx.Prior("normal", 0.06, 0.03)}
    posterior = rj.sample_posterior(calibration, fit=fit, draws=1000, warmup=500, chains=2,
                                    seed=2, priors=priors, progress=False)  # fmt: skip
    assert posterior.divergences == 0
    sigma = np.sqrt(np.log1p((2e4 / 4e4) ** 2))
    cdfs = {
        "k": stats.lognorm(sigma, scale=4e4 * np.exp(-(sigma**2) / 2)).cdf,
        "c_out": stats.uniform(BOX["c_out"][0], np.diff(BOX["c_out"])[0]).cdf,
        "gap": stats.norm(0.06, 0.03).cdf,
    }
    print()
    for i, label in enumerate(posterior.labels):
        lower, upper = BOX[label]
        cdf = cdfs[label]
        draws = posterior.draws[:, ::5, i].ravel()
        within = (cdf(draws) - cdf(lower)) / (cdf(upper) - cdf(lower))  # uniform if right
        p = stats.kstest(within, "uniform").pvalue
        print(f"{label}: KS p {p:.3f}, ESS {posterior.summary[label]['ess_bulk']:.0f}")
        assert p > 0.001, (label, p)


def test_a_model_that_does_not_explain_the_traces_is_not_sampled():
    """The absorber's k fitted alone, its gap wrong by 2.5×: the model check fails, and
    the posterior of the wrong model is refused, naming the failing signals."""
    calibration = rj.Calibration(
        [rjx.Experiment(trace(TRUTH, seed=3), design={"c_out": TRUTH["c_out"], "gap": 0.05})],
        fit={"k": BOX["k"]},
    )
    fit = rj.calibrate(calibration, progress=False)
    assert not fit.explains
    with pytest.raises(rjx.ModelMisfitError, match=r"does not explain the traces \(.*(x_M|F_AN)"):
        rj.sample_posterior(calibration, fit=fit)


#: Simulation-based calibration (Talts et al. 2018): the prior of each replication's truth
#: (uniform over these bounds, ±10 % about the paper absorber's k, c_out and gap), the
#: noise the traces are drawn with, and the draws each posterior's ranks are taken among.
SBC_PRIOR = {"k": (2.5e4, 3.1e4), "c_out": (5.0e3, 7.0e3), "gap": (0.015, 0.025)}
SBC_NOISE = {"x_M": 2e-4, "F_AN": 300.0}
SBC_RANKED = 100


def sbc_ranks(replications: int, noise_said: float = 1.0, seed: int = 0) -> dict[str, np.ndarray]:
    """Each replication: a truth drawn from `SBC_PRIOR`, one firing of 201 samples
    simulated by the model itself with `SBC_NOISE`, the fit and the posterior (one
    chain, 300 warm-up steps, 400 draws) under a likelihood told the noise times
    `noise_said` (the fit and its model check told the truth); the truth's rank among
    `SBC_RANKED` thinned draws, randomised to a fraction `(rank + U) / (SBC_RANKED +
    1)`, uniform on (0, 1) when the posterior is right."""
    rng = np.random.default_rng(seed)
    ts = np.linspace(0.0, 0.6, 201)
    fractions: dict[str, list[float]] = {k: [] for k in SBC_PRIOR}
    for r in range(replications):
        truth = {k: rng.uniform(*b) for k, b in SBC_PRIOR.items()}
        history = rj.simulate(rj.params_from_values(truth), ts=ts)
        signals = {
            "x_M": np.asarray(history.x_M) + SBC_NOISE["x_M"] * rng.standard_normal(ts.size),
            "F_AN": np.asarray(history.anchoring_force)
            + SBC_NOISE["F_AN"] * rng.standard_normal(ts.size),
        }
        calibration = rj.Calibration(
            [rjx.Experiment(rjx.Trace.of(ts, **signals), sigma=SBC_NOISE)], fit=SBC_PRIOR
        )
        fit = rj.calibrate(calibration, starts=1, progress=False)
        # The likelihood's noise is the fit's (a broken one: told another).
        said = [{k: v * noise_said for k, v in noise.items()} for noise in fit.sigma]
        fit = dataclasses.replace(fit, sigma=said)
        posterior = rj.sample_posterior(
            calibration, fit=fit, draws=4 * SBC_RANKED, warmup=300, chains=1, seed=r,
            progress=False,
        )  # fmt: skip
        thinned = posterior.draws[0, ::4]
        for i, label in enumerate(posterior.labels):
            rank = int(np.sum(thinned[:, i] < truth[label]))
            fractions[label].append((rank + rng.uniform()) / (SBC_RANKED + 1))
    return {k: np.asarray(v) for k, v in fractions.items()}


def uniformity(fractions: np.ndarray) -> tuple[float, bool]:
    """The χ² test's p over 10 equal bins, and whether the ECDF lies inside ArviZ's
    simultaneous 99 % band for a uniform sample of that size."""
    from arviz.stats.ecdf_utils import compute_ecdf, ecdf_confidence_band
    from scipy.stats import chisquare

    counts = np.histogram(fractions, bins=10, range=(0.0, 1.0))[0]
    p = float(chisquare(counts).pvalue)
    points = np.linspace(0.02, 0.98, 49)
    lower, upper = ecdf_confidence_band(fractions.size, points, points, prob=0.99)
    ecdf = compute_ecdf(np.sort(fractions), points)
    return p, bool(np.all((lower <= ecdf) & (ecdf <= upper)))


@pytest.mark.slow
def test_simulation_based_calibration_ranks_are_uniform():
    """200 replications: for k, c_out and gap the truth's rank among the posterior's
    draws is uniform (χ² p > 0.01 over 10 bins, and the ECDF inside ArviZ's 99 % band):
    the posterior's intervals cover the truth as often as they say."""
    fractions = sbc_ranks(200)
    print()
    for label, values in fractions.items():
        p, inside = uniformity(values)
        counts = np.histogram(values, bins=10, range=(0.0, 1.0))[0]
        print(f"{label}: χ² p {p:.3f}, ECDF inside the band: {inside}, counts {counts.tolist()}")
        assert p > 0.01 and inside, (label, p, counts)


@pytest.mark.slow
def test_simulation_based_calibration_fails_a_likelihood_told_half_the_noise():
    """The same check on a broken likelihood (told half the traces' noise, so every
    posterior is half as wide as it should be) fails it: the truth falls at the ends of
    the draws, and the ranks are far from uniform for every value: the check (χ² p >
    0.01 and the ECDF inside its band) fails on each."""
    fractions = sbc_ranks(60, noise_said=0.5, seed=1)
    print()
    for label, values in fractions.items():
        p, inside = uniformity(values)
        counts = np.histogram(values, bins=10, range=(0.0, 1.0))[0]
        print(f"{label}: χ² p {p:.2g}, ECDF inside the band: {inside}, counts {counts.tolist()}")
        assert not (p > 0.01 and inside), (label, p, counts)


def calibration_file(folder, posterior: str = "") -> str:
    """A calibration file of one synthetic firing (k, c_out and gap fitted), with
    `posterior` as its `[posterior]` table's body."""
    ts, signals = synthetic(TRUTH, seed=5)
    write_trace(folder / "firing_1.csv", ts, {"x_M": signals["x_M"], "F_AN": signals["F_AN"]})
    path = folder / "cal.toml"
    path.write_text(
        "[fit]\nk = [1e4, 1e5]\nc_out = [1e3, 3e4]\ngap = [0.0, 0.1]\n"
        '[[experiment]]\ntrace = "firing_1.csv"\n'
        + (f"[posterior]\n{posterior}" if posterior else "")
    )
    return str(path)


def test_the_command_line_samples_the_posterior(tmp_path, capsys):
    """`calibrate --posterior` with a `[posterior]` table (its draws, chains and a prior):
    the summary beside the Laplace intervals, `posterior.nc`, `posterior.png`, the
    posterior in `result.json`; a sampler that has not converged (too few draws) is exit
    7, naming the value and what to try."""
    import arviz as az

    source = calibration_file(
        tmp_path, 'draws = 300\nwarmup = 300\nchains = 2\nparallel_chains = 2\nseed = 3\n'
        '[posterior.prior]\ngap = { kind = "normal", mean = 0.02, sd = 0.01 }\n'
        'k = { kind = "normal", mean = 3e4, sd = 1e4 }\n',
    )  # fmt: skip
    out = tmp_path / "out"
    # `--prior` over the file's k; `--predict` alone: the calibration's own design.
    assert main(["calibrate", source, "--posterior", "--prior", "k=lognormal:28000,3000",
                 "--predict", "--out", str(out)]) == 0  # fmt: skip
    captured = capsys.readouterr()
    assert "posterior: 2 chains × 300 draws (NUTS), 0 divergent" in captured.out
    assert "converged" in captured.out and "Laplace 95 %" in captured.out
    assert "the likelihood's noise, held fixed: x_M" in captured.out
    assert "(estimated by the fit)" in captured.out
    report = json.loads((out / "result.json").read_text())
    summary = report["posterior"]["summary"]
    assert set(summary) == {"k", "c_out", "gap"} and report["posterior"]["converged"]
    assert report["posterior"]["parallel_chains"] == 2
    assert report["posterior"]["priors"]["gap"] == {"kind": "normal", "mean": 0.02, "sd": 0.01}
    assert report["posterior"]["priors"]["k"] == {"kind": "lognormal", "mean": 28000, "sd": 3000}
    # The traces under the posterior: the measured samples inside the 95 % band of a
    # repeated firing as often as it says.
    coverage = report["posterior"]["predictive"]["coverage"][0]
    assert 0.92 <= min(coverage.values()) and max(coverage.values()) <= 0.98, coverage
    assert "inside the 95 % predictive band (200 draws): x_M" in captured.out
    # The design predicted from the draws agrees with the fit's normal here (near-linear).
    assert "(600 samples of the posterior's draws" in captured.out
    compared = 0
    for name, band in report["posterior_prediction"]["sampled"].items():
        laplace = report["prediction"]["sampled"][name]["ci95"]
        if laplace[0] is None:  # a metric this design does not have (no return stroke)
            assert band["ci95"][0] is None, name
            continue
        compared += 1
        width = max(laplace[1] - laplace[0], 1e-12 * abs(laplace[0]))
        apart = max(abs(a - b) for a, b in zip(band["ci95"], laplace, strict=True))
        assert apart <= 0.25 * width, (name, band["ci95"], laplace)
    assert compared >= 5
    for figure in ("posterior.png", "posterior_predictive.png", "posterior_prediction.png"):
        assert str(out / figure) in report["figures"] and (out / figure).stat().st_size
    assert (
        str(out / "posterior.png") in report["figures"] and (out / "posterior.png").stat().st_size
    )
    draws = az.from_netcdf(str(out / "posterior.nc")).posterior["theta"]
    assert draws.shape == (2, 300, 3)
    for name, row in summary.items():
        assert row["q2.5"] <= report["fitted"][name]["value"] <= row["q97.5"], name

    # The noise sampled too (`--sample-noise`), on too few draws: its rows, and the gates
    # name it as they name a value.
    status = main(["calibrate", source, "--posterior", "--draws", "20", "--warmup", "30",
                   "--sample-noise", "--parallel-chains", "1",
                   "--out", str(tmp_path / "short")])  # fmt: skip
    assert status == POSTERIOR_NOT_CONVERGED
    captured = capsys.readouterr()
    assert "the sampler has not converged: k: bulk ESS" in captured.err
    assert "more draws" in captured.err and "noise of F_AN in experiment 0: " in captured.err
    assert "the noise, sampled from the fit's: x_M" in captured.out
    assert "half-normal prior, scale" in captured.out
    report = json.loads((tmp_path / "short" / "result.json").read_text())
    assert set(report["posterior"]["noise"][0]["F_AN"]["sampled"]) >= {"mean", "q97.5", "r_hat"}
    assert report["posterior"]["parallel_chains"] == 1  # the flag over the file's 2


@pytest.mark.parametrize(
    ("posterior", "arguments", "message"),
    [
        ("", ["--draws", "10"], "--draws is for --posterior"),
        ("chains = 0\n", ["--posterior"], "chains must be in [1, 64], got 0"),
        ("parallel_chains = 0\n", ["--posterior"], "parallel_chains must be in [1, 64], got 0"),
        ("", ["--posterior", "--parallel-chains", "65"], "parallel_chains must be in [1, 64]"),
        ("", ["--parallel-chains", "2"], "--parallel-chains is for --posterior"),
        ("", ["--posterior", "--warmup", "0"], "warmup must be in [1, 100000], got 0"),
        ("thin = 2\n", ["--posterior"], "[posterior] unknown key 'thin'"),
        ("dense_mass = 1\n", ["--posterior"], "[posterior] dense_mass = 1: give true or false"),
        ('[posterior.prior]\nm = "uniform"\n', ["--posterior"], "prior for 'm': not a fitted"),
        ('[posterior.prior]\nk = { kind = "normal", mean = 3e4, sd = -1 }\n', ["--posterior"],
         "[posterior.prior] k: prior sd must be > 0"),
        ('[posterior.prior]\nk = { kind = "normal", mean = "x", sd = 1.0 }\n', ["--posterior"],
         "[posterior.prior] k: a normal prior needs a finite number for its mean, got 'x'"),
        ("", ["--prior", "k=uniform"], "--prior is for --posterior"),
        ("", ["--posterior", "--prior", "m=uniform"], "prior for 'm': not a fitted value"),
        ("", ["--posterior", "--prior", "k=normal:3e4"], "--prior k=normal:3e4: give NAME="),
        ("", ["--posterior", "--prior", "k=normal:a,b"], "--prior k=normal:a,b: give NAME="),
        ("", ["--posterior", "--prior", "k=normal:3e4,0"], "--prior k=normal:3e4,0: prior sd"),
        ("", ["--posterior", "--prior", "k=beta:1,2"], "--prior k=beta:1,2: prior kind 'beta'"),
        ("", ["--posterior", "--prior", "k=uniform", "--prior", " k=normal:3e4,1e4"],
         "--prior k given twice"),
        ("", ["--sample-noise"], "--sample-noise is for --posterior"),
        ("sample_noise = 1\n", ["--posterior"], "[posterior] sample_noise = 1: give true or false"),
        ("[posterior.noise_scale]\nF_AN = 600.0\n", ["--posterior"],
         "noise_scale is the sampled noise's prior: give sample_noise=True"),
        ("sample_noise = true\n[posterior.noise_scale]\nv_M = 1.0\n", ["--posterior"],
         "noise_scale for 'v_M': not a measured signal"),
        ("noise_scale = 3\n", ["--posterior", "--sample-noise"],
         "write each noise's prior scale under [posterior.noise_scale]"),
        ('[posterior.noise_scale]\nF_AN = "x"\n', ["--posterior", "--sample-noise"],
         "[posterior.noise_scale] F_AN"),
    ],
)  # fmt: skip
def test_bad_posterior_settings_exit_2_before_the_fit(tmp_path, capsys, posterior, arguments,
                                                      message):  # fmt: skip
    source = calibration_file(tmp_path, posterior)
    assert main(["calibrate", source, *arguments, "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err
    assert not (tmp_path / "out" / "result.json").exists()
