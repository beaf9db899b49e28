"""The fit itself: weighted least squares over every experiment, signal and sample,
`Σ ρ(((model − measured) / σ)²)`, solved by optimistix's Levenberg–Marquardt, and its
compiled programs (`fit_program`, `evaluate_program`).

The Jacobian is the library's forward sensitivities of the signals at the sample times
(the same error-controlled solve as the peaks' gradients; no finite differences), given
to optimistix through a `jax.custom_jvp`, so that one solve per step gives the residuals
and their Jacobian (`evaluate`). The experiments, and the starts or noise draws, run one
after another inside one compiled program (on a CPU, lockstep lanes cost more than they
save: `docs/speed.md`).

The parameters move in the search space's coordinates (`SearchSpace`: linear between the
bounds, or logarithmic over three decades and more) through lmfit's bounded transform
`z = (sin u + 1) / 2` (`theta_of_u`), so that no step leaves the bounds. The solver is
optimistix's with Marquardt's first damping and two more stopping tests, in standard
errors and in the gain a step has left (`_LevenbergMarquardt`). Each fit runs on every
sample, then again without the samples either side of a jump in the model's signal
(`fit_off_the_jumps`), under the noise the first one's residuals show where a noise
is estimated (`FitOutcome`).

`_Static` keeps its name and fields: it is in the identity of every calibration store
(`campaign_identity`), as `layout._Data` is. Other modules use its alias `FitSettings`.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .._model.derivatives import signal_history, signal_sensitivities
from .._model.params import with_values
from .._model.programs import structure_jit
from .._model.status import OK_CODE
from .._sweeps.space import SearchSpace
from .layout import CalibrationData

__all__ = [
    "FAILED_RESIDUAL",
    "JUMP_RATIO",
    "Evaluation",
    "FitOutcome",
    "FitSettings",
    "OffTheJumps",
    "evaluate",
    "evaluate_program",
    "fit_off_the_jumps",
    "fit_program",
    "jump_samples",
    "jumps_at",
    "log_likelihood_term",
    "model_residuals",
    "robust",
    "solve_lm",
    "theta_of_u",
    "u_of_z",
]

#: The residual given to the fit where an experiment's solve failed (in noise
#: deviations): large and finite, so that the step is refused rather than NaN.
FAILED_RESIDUAL = 1e6

#: Levenberg–Marquardt stops once a step changes `u` by less than this (relatively) and
#: every residual by less than this many noise deviations (optimistix's own test) ...
_LM_TOLERANCE = 1e-4
#: ... or once the Gauss–Newton step from its last accepted point would move the fit by
#: less than this many standard errors (the Mahalanobis length of that step, under the
#: covariance the report gives). The first test alone waited, at the optimum, for a
#: step whose predicted gain (10⁻¹⁰ in χ²) the solve's rounding hides, and refused up
#: to 20 of them one by one (measured on 20 noise draws of the bench's absorber test:
#: 16–37 steps a fit before, 6–7 after; the values the same within 0.001 standard
#: errors).
_LM_STANDARD_ERRORS = 1e-3
#: ... or once a step was refused, the next is predicted to gain under this share of
#: the residual variance in χ² (the cost of ~0.03 standard errors), and the Gauss–Newton
#: step would move the fit by under `_LM_GAIN_STANDARD_ERRORS`: on a χ² the solve's
#: rounding and the friction's stick make rough at that scale, the Gauss–Newton step
#: stays longer than the first test's 0.001 and the trust region shrinks fourfold a step
#: to nothing (measured on the round trip's last stage, truth 0 draw 0: 22 of its 45
#: steps refused one by one at χ² within 0.004 of the optimum, the step 0.02 standard
#: errors long).
_LM_GAIN = 1e-3
#: The second half of that test: a damped step's gain is small wherever the damping is
#: large, also with standard errors to go along a sloppy valley; the Gauss–Newton step
#: bounds the distance left (on a rough χ² its length is mostly the ripples', so a
#: bound much under 1 would keep the test from ever passing there).
_LM_GAIN_STANDARD_ERRORS = 1.0
#: Marquardt's first damping, a fraction of the largest diagonal of `JᵀJ` at the start
#: (Madsen, Nielsen and Tingleff's τ for a start that may be far), instead of
#: optimistix's damping of 1 whatever the residuals' scale: in noise units `JᵀJ` is
#: 10⁴–10⁸, so a damping of 1 is a Gauss–Newton step from a far start, refused and
#: shrunk by 4 up to seven times before one is taken.
_LM_FIRST_DAMPING = 1e-3
#: A step in the model's signal between two samples over this many times what its
#: rates there explain (plus twice the noise) is a jump (`jump_samples`).
JUMP_RATIO = 3.0
#: The fits off the jumps after the one on every sample, at most (`fit_off_the_jumps`):
#: each from the last one's optimum, while that optimum's jumps sit beside other samples
#: than the ones it left out. Where the last still moved them, its optimum is kept, off
#: its own jumps.
_JUMP_PASSES = 3


class _Static(eqx.Module):
    """What shapes the fit's program: the model parameters fitted, the signals, the
    loss, the LM step limit, and whether any noise is estimated (from the first fit's
    residuals)."""

    wrt: tuple[str, ...] = eqx.field(static=True)
    signals: tuple[str, ...] = eqx.field(static=True)
    loss: str = eqx.field(static=True)
    f_scale: float = eqx.field(static=True)
    max_steps: int = eqx.field(static=True)
    estimate_noise: bool = eqx.field(static=True, default=True)
    lanes: int = eqx.field(static=True, default=1)
    # Levenberg–Marquardt's stopping tests (fields, so that a program made with others
    # is another program, never a cached one).
    lm_tolerance: float = eqx.field(static=True, default=_LM_TOLERANCE)
    lm_standard_errors: float = eqx.field(static=True, default=_LM_STANDARD_ERRORS)
    lm_gain: float = eqx.field(static=True, default=_LM_GAIN)
    # The fits off the jumps (`fit_off_the_jumps`): a field, so that a fit made on
    # every sample (a store's from before) is another fit.
    jump_passes: int = eqx.field(static=True, default=_JUMP_PASSES)


#: The name other modules use for `_Static`, whose own name stays (it is in the identity
#: of every calibration store).
FitSettings = _Static


def _experiment_signals(theta_e, params, times, t1, data: CalibrationData, static: _Static):
    """One experiment's signals at its sample times `(S, n)`, their Jacobian `(S, n, K)`
    with respect to its K columns (`wrt`, then `t_shift`) and their rates in time `(S,
    n)`, and its status code."""
    params = with_values(params, static.wrt, theta_e[:-1])
    model_times = times - theta_e[-1]
    before = model_times < 0  # before the firing the gun is at rest
    solved = signal_sensitivities(
        params,
        data.smoothing,
        dataclasses.replace(data.options, t1=t1),
        static.wrt,
        jnp.clip(model_times, 0.0, t1),
        t1,
        static.signals,
    )
    gradients = jnp.concatenate([solved.gradients, -solved.rates[..., None]], axis=-1)
    # Before the trigger the trace records the gun at rest, which no delay moves.
    rest_gradients = jnp.concatenate(
        [solved.rest_gradients, jnp.zeros_like(solved.rest_values)[:, None]], axis=-1
    )
    values = jnp.where(before, solved.rest_values[:, None], solved.values)
    gradients = jnp.where(before[:, None], rest_gradients[:, None, :], gradients)
    # At and before the firing the gun is at rest: the rate there is not an event's.
    rates = jnp.where(model_times <= 0, 0.0, solved.rates)
    (code,) = jax.tree.leaves(solved.status)
    return values, gradients, rates, code


class Evaluation(eqx.Module):
    """The fit's pieces at one point θ: the normalised residuals `(E, S, n)` (0 where
    no sample), their Jacobian with respect to θ `(E, S, n, P)`, the model's signals
    `(E, S, n)`, their rates in time `(E, S, n)` (per second) and each experiment's
    status code `(E,)`."""

    residuals: jax.Array
    jacobian: jax.Array
    signals: jax.Array
    rates: jax.Array
    codes: jax.Array


def evaluate(theta, data: CalibrationData, static: _Static) -> Evaluation:
    """The fit's pieces at the fitted values `theta (P,)` (SI units; `Evaluation`): every
    experiment's solve, the residuals in noise units and their Jacobian. A sample of an
    experiment whose solve failed takes `FAILED_RESIDUAL`, its Jacobian rows 0."""
    P = theta.shape[0]
    # The experiments one after another (`lax.map`), not in lockstep: a vmapped solve
    # selects its whole carry, the saved signals included, at every step (measured, one
    # experiment of 5,001 samples: 13 ms vmapped, 3 ms alone).
    values, gradients, rates, codes = jax.lax.map(
        lambda a: _experiment_signals(a[0], a[1], a[2], a[3], data, static),
        (_columns(theta, data), data.params, data.times, data.t1),
    )
    ok = (codes == OK_CODE)[:, None, None]
    select = jax.nn.one_hot(data.index, P) * (data.index >= 0)[..., None]  # (E, K, P)
    jacobian = jnp.einsum("esnk,ekp->esnp", gradients, select) / data.sigma[..., None, None]
    jacobian = jnp.where((data.present & ok)[..., None], jacobian, 0.0)
    return Evaluation(_residuals(values, codes, data), jacobian, values, rates, codes)


def model_residuals(theta, data: CalibrationData, static: _Static):
    """`evaluate`'s residuals `(E, S, n)` alone, from one solve of the state per
    experiment without its sensitivities: the likelihood of a sampler that needs no
    gradient (emcee's, in `bench-calibration --posterior`), at what it costs."""

    def one(theta_e, params, times, t1):
        params = with_values(params, static.wrt, theta_e[:-1])
        model_times = times - theta_e[-1]
        solved = signal_history(params, data.smoothing,
                                dataclasses.replace(data.options, t1=t1),
                                jnp.clip(model_times, 0.0, t1), t1, static.signals)  # fmt: skip
        (code,) = jax.tree.leaves(solved.status)
        return jnp.where(model_times < 0, solved.rest_values[:, None], solved.values), code

    values, codes = jax.lax.map(
        lambda a: one(*a), (_columns(theta, data), data.params, data.times, data.t1)
    )
    return _residuals(values, codes, data)


def _columns(theta, data: CalibrationData):
    """Each experiment's model columns `(E, K)`: the fitted values where fitted, else
    its known ones."""
    index = data.index
    return jnp.where(index >= 0, theta[jnp.maximum(index, 0)], data.known)


def _residuals(values, codes, data: CalibrationData):
    """The residuals `(E, S, n)` in noise units of the model's `values`; a sample of an
    experiment whose solve failed takes `FAILED_RESIDUAL`, an absent one 0."""
    ok = (codes == OK_CODE)[:, None, None]
    residuals = (values - data.measured) / data.sigma[..., None]
    return jnp.where(data.present & ok, residuals, jnp.where(data.present, FAILED_RESIDUAL, 0))


def robust(r, loss: str, f_scale: float):
    """The residual whose square is the loss `ρ(r²)`: `r` (linear), or scipy's soft-L1
    and Huber of `r / f_scale`, times `f_scale` (smooth in r; the same near 0)."""
    if loss == "linear":
        return r
    x = r / f_scale
    if loss == "soft_l1":  # ρ(z) = 2(√(1+z) − 1) = 2z / (√(1+z) + 1)
        return r * jnp.sqrt(2.0 / (jnp.sqrt(1.0 + x * x) + 1.0))
    # Huber: ρ(z) = z for z <= 1, else 2√z − 1.
    big = jnp.abs(x) > 1.0
    safe = jnp.where(big, jnp.abs(x), 1.0)
    return jnp.where(big, r * jnp.sqrt((2.0 * safe - 1.0) / (safe * safe)), r)


def theta_of_u(u, space: SearchSpace):
    """lmfit's bounded transform: `z = (sin u + 1) / 2`, `θ = space.theta(z)`."""
    return space.theta((jnp.sin(u) + 1.0) / 2.0)


def u_of_z(z):
    """The fit's coordinates `u` of box coordinates `z` (NumPy): the inverse of the
    bounded transform of `theta_of_u`, on its branch `|u| <= π/2`."""
    return np.arcsin(np.clip(2.0 * np.asarray(z) - 1.0, -1.0, 1.0))


def _lm_function(static: _Static):
    """`(u, (data, held, held_theta)) → robust residuals (N,)`, whose Jacobian
    (`custom_jvp`) comes from the same forward-sensitivity solve as the residuals. The
    values `held (P,)` stay at `held_theta` (a profile's fixed parameter)."""

    def value_and_jacobian(u, args):
        data, held, held_theta = args
        theta, dtheta = jax.jvp(lambda u_: theta_of_u(u_, data.space), (u,), (jnp.ones_like(u),))
        theta = jnp.where(held, held_theta, theta)
        dtheta = jnp.where(held, 0.0, dtheta)
        evaluation = evaluate(theta, data, static)
        r = evaluation.residuals.reshape(-1)
        J = evaluation.jacobian.reshape(r.shape[0], -1) * dtheta
        robust_r, slope = jax.jvp(
            lambda x: robust(x, static.loss, static.f_scale), (r,), (jnp.ones_like(r),)
        )
        return robust_r, J * slope[:, None]

    @jax.custom_jvp
    def residuals(u, data):
        return value_and_jacobian(u, data)[0]

    @residuals.defjvp
    def _(primals, tangents):
        u, data = primals
        du = tangents[0]
        r, J = value_and_jacobian(u, data)
        return r, J @ du

    return residuals


def _quiet(**_) -> None:
    """optimistix's `verbose` hook, silent."""


class _MarquardtTrustRegion(optx.ClassicalTrustRegion):
    """optimistix's trust region with Marquardt's first damping (`_LM_FIRST_DAMPING`)
    and Moré's cutoff for relaxing it: a step that gains three quarters of its predicted
    reduction, not 99 %, lets the next one be longer."""

    high_cutoff: float = 0.75  # pyright: ignore[reportIncompatibleVariableOverride]
    first_damping: float = _LM_FIRST_DAMPING

    def step(self, first_step, y, y_eval, f_info, f_eval_info, state):
        """optimistix's step, with Marquardt's first damping at the first step."""
        step_size, accept, result, state = super().step(
            first_step, y, y_eval, f_info, f_eval_info, state
        )
        diagonal = jnp.sum(f_eval_info.jac.as_matrix() ** 2, axis=0)  # pyright: ignore[reportAttributeAccessIssue]
        first = 1.0 / (self.first_damping * jnp.maximum(jnp.max(diagonal), 1e-300))
        # A Jacobian that is not finite at the start: optimistix's damping of 1, whose
        # step is then refused (not a NaN damping, whose zero steps it would accept).
        first = jnp.where(jnp.isfinite(first), first, 1.0)
        step_size = jnp.where(first_step, first, step_size)
        return step_size, accept, result, eqx.tree_at(lambda s: s.step_size, state, step_size)


class _LevenbergMarquardt(optx.AbstractGaussNewton):
    """Levenberg–Marquardt (optimistix's Gauss–Newton with a damped Newton descent)
    with `_MarquardtTrustRegion` and two more stopping tests: the Gauss–Newton step from
    the last accepted point would move the fit by under `standard_errors`; or a step was
    refused, the next is predicted to gain under `gain` of the residual variance in χ²,
    and the Gauss–Newton step is under `_LM_GAIN_STANDARD_ERRORS`. Never at a point
    where an experiment's solve failed (a residual of at least `failed`)."""

    rtol: float
    atol: float
    standard_errors: float
    gain: float
    failed: float
    norm: Any = optx.max_norm
    # optimistix declares these abstract; its own LevenbergMarquardt narrows them so.
    descent: optx.DampedNewtonDescent = optx.DampedNewtonDescent()  # pyright: ignore[reportIncompatibleVariableOverride]
    search: _MarquardtTrustRegion = _MarquardtTrustRegion()  # pyright: ignore[reportIncompatibleVariableOverride]
    verbose: Any = _quiet

    def terminate(self, fn, y, args, options, state, tags):
        """optimistix's test, or the Gauss–Newton step left is under `standard_errors`,
        or a refused step leaves nothing to gain (not at the first step, nor where an
        experiment's solve failed)."""
        done, result = super().terminate(fn, y, args, options, state, tags)
        data, held, _ = args
        jacobian, residuals = state.f_info.jac.as_matrix(), state.f_info.residual
        step = jnp.linalg.lstsq(jacobian, residuals)[0]
        # The step's squared length in standard errors: ‖J δ‖² over the residual
        # variance (the covariance's scale: the samples present, the values free).
        length2 = jnp.sum((jacobian @ step) ** 2)
        freedom = jnp.maximum(data.present.sum() - jnp.sum(~held), 1)
        variance = jnp.sum(residuals**2) / freedom
        near = length2 <= self.standard_errors**2 * jnp.maximum(variance, 1e-300)
        # The step proposed next, after a refused one: its gain by the linear model.
        proposed = jacobian @ (state.y_eval - y)
        predicted = -jnp.sum(proposed * (2.0 * residuals + proposed))
        spent = (state.num_steps_since_acceptance > 0) & (predicted < self.gain * variance)
        spent &= length2 <= _LM_GAIN_STANDARD_ERRORS**2 * variance
        near = (near | spent) & jnp.all(jnp.abs(residuals) < self.failed) & ~state.first_step
        return done | near, result


def solve_lm(u0, data: CalibrationData, static: _Static, held=None, held_theta=None):
    """One Levenberg–Marquardt fit from `u0 (P,)` (the fit's coordinates) under the noise
    `data.sigma`, the values `held (P,)` (none by default) fixed at `held_theta (P,)`:
    `(u (P,), converged, steps)`, never raising (`throw=False`)."""
    with jax.ensure_compile_time_eval():  # half the failed residual, as the loss gives it
        failed = float(robust(jnp.asarray(0.5 * FAILED_RESIDUAL), static.loss, static.f_scale))
    solver = _LevenbergMarquardt(
        rtol=static.lm_tolerance,
        atol=static.lm_tolerance,
        standard_errors=static.lm_standard_errors,
        gain=static.lm_gain,
        failed=failed,
    )
    held = jnp.zeros(u0.shape, dtype=bool) if held is None else held
    held_theta = jnp.zeros(u0.shape) if held_theta is None else held_theta
    solution = optx.least_squares(
        _lm_function(static),
        solver,
        u0,
        args=(data, held, held_theta),
        max_steps=static.max_steps,
        throw=False,
    )
    return solution.value, solution.result == optx.RESULTS.successful, solution.stats["num_steps"]


def _residual_scale(residuals, present, loss: str):
    """Each signal's noise in units of the assumed one, from the residuals `(E, S, n)`:
    the RMS, or with a robust loss the MAD's normal-consistent scale."""
    if loss == "linear":
        count = jnp.maximum(present.sum(-1), 1)
        return jnp.sqrt(jnp.sum(jnp.where(present, residuals**2, 0.0), -1) / count)
    absolute = jnp.where(present, jnp.abs(residuals), jnp.nan)
    return 1.4826 * jnp.nanmedian(absolute, axis=-1)


class FitOutcome(eqx.Module):
    """One lane of a batched fit: the optimum `u`, whether the fit converged, its steps,
    the noise it settled on `(E, S)`, the cost there, and its `score`: −2 log-likelihood
    of the Gaussian noise model up to a constant (the cost plus `Σ n log σ²` over every
    experiment and signal), which ranks fits whose noise was estimated each on its own
    (their costs are all about N)."""

    u: jax.Array
    converged: jax.Array
    steps: jax.Array
    sigma: jax.Array
    cost: jax.Array
    score: jax.Array


def log_likelihood_term(sigma, present):
    """`Σ n log σ²` over experiments and signals (`n` samples each), any array module."""
    xp = jnp if isinstance(sigma, jax.Array) else np
    return xp.sum(present.sum(-1) * xp.log(sigma**2))


def jump_samples(times, signals, rates, present, sigma):
    """Which present samples `(E, S, n)` lie either side of a jump in the model's
    signal: a step between two neighbouring sample times of `signals (E, S, n)` over
    `JUMP_RATIO` times what their `rates (E, S, n)` explain over their spacing (`times
    (E, n)`), plus twice the noise `sigma (E, S)`. The model's signal is known at every
    sample time, so a jump beside an absent sample (`present (E, S, n)` false) still
    leaves out the present one on its other side. Any array module (the fit's program
    and the posterior's set-up call it).

    Such a sample carries an event's time (a stick, a slip, the buffer's engagement)
    only to within its spacing, and the jump makes χ² a staircase there: a µs of the
    event's time moves the sample from one side of it to the other (measured, the
    counter-recoil buffer's step in `F_AN` with friction at 0°: χ² +279 for half a
    newton), which no gradient step crosses."""
    xp = jnp if any(isinstance(a, jax.Array) for a in (signals, rates, present)) else np
    step = xp.abs(xp.diff(signals, axis=-1))
    rate = xp.maximum(xp.abs(rates[..., :-1]), xp.abs(rates[..., 1:]))
    explained = rate * xp.diff(times, axis=-1)[:, None, :]
    jump = step > JUMP_RATIO * explained + 2.0 * sigma[..., None]
    edge = xp.zeros((*jump.shape[:-1], 1), dtype=bool)
    beside = xp.concatenate([jump, edge], axis=-1) | xp.concatenate([edge, jump], axis=-1)
    return beside & present


class OffTheJumps(eqx.Module):
    """A fit off the jumps (`fit_off_the_jumps`): its optimum `u (P,)`, the samples
    left out there `jumps (E, S, n)`, the noise `sigma (E, S)` it fitted under, its
    `cost` over the samples it counts (the robust `Σ r²`), whether every pass
    converged, and their steps."""

    u: jax.Array
    jumps: jax.Array
    sigma: jax.Array
    cost: jax.Array
    converged: jax.Array
    steps: jax.Array


def jumps_at(evaluation: Evaluation, data: CalibrationData):
    """`jump_samples` of `evaluation`'s signals, in the experiments whose solve
    succeeded (a failed one's samples keep `FAILED_RESIDUAL`)."""
    ok = (evaluation.codes == OK_CODE)[:, None, None]
    jumps = jump_samples(data.times, evaluation.signals, evaluation.rates, data.present,
                         data.sigma)  # fmt: skip
    return jumps & ok


def fit_off_the_jumps(
    u, data: CalibrationData, static: _Static, held=None, held_theta=None
) -> OffTheJumps:
    """Levenberg–Marquardt from `u (P,)` on every sample under the noise `data.sigma`;
    then from its optimum without the samples either side of a jump in the model's
    signal there (`jumps_at`), where it has any, and (where `static.estimate_noise`)
    under the noise the first fit's residuals off the jumps show; again from each
    optimum while the samples beside its jumps are other ones than it left out, at
    most `static.jump_passes` times after the first (the last optimum kept, off its
    own jumps). The values `held (P,)` stay at `held_theta (P,)` (`solve_lm`'s).

    Where the model's signal jumps (a stick or slip of the rails, exact events since
    model revision 3; the buffer's engagement), χ² is a staircase in the values: on
    every sample a fit reaches the step the optimum lies on and stays there (measured
    on 40 reference traces of the planned friction test, started at the truth: half
    stayed within 1e-6 of it). Without those samples χ² is smooth about that optimum
    while the events move by under a sample's spacing.

    One loop, whose first pass is the fit on every sample, so that the program holds
    one Levenberg–Marquardt and one solve (each copy doubles its compilation)."""
    held = jnp.zeros(u.shape, dtype=bool) if held is None else held
    held_theta = jnp.zeros(u.shape) if held_theta is None else held_theta

    def again(carry):
        *_, passes, go = carry
        return go & (passes <= static.jump_passes)

    def refit(carry):
        u, jumps, sigma, _, ok, steps, passes, _ = carry
        under = eqx.tree_at(lambda d: d.sigma, data, sigma)
        off = eqx.tree_at(lambda d: d.present, under, data.present & ~jumps)
        u, ok_, steps_ = solve_lm(u, off, static, held, held_theta)
        at = evaluate(jnp.where(held, held_theta, theta_of_u(u, data.space)), under, static)
        residuals, moved = at.residuals, jumps_at(at, under)
        go = jnp.any(moved != jumps)
        if static.estimate_noise:  # after the first fit, under the noise it shows
            first = passes == 0
            scale = _residual_scale(residuals, data.present & ~moved, static.loss)
            scale = jnp.where(jnp.isfinite(scale) & (scale > 0), scale, 1.0)
            shown = jnp.where(data.sigma_given, sigma, sigma * scale)
            new = jnp.where(first, shown, sigma)
            residuals = residuals * (sigma / new)[..., None]
            moved = jumps_at(at, eqx.tree_at(lambda d: d.sigma, data, new))
            sigma, go = new, first | jnp.any(moved != jumps)
        steps = steps + jnp.asarray(steps_, dtype=steps.dtype)
        return u, moved, sigma, residuals, ok & ok_, steps, passes + 1, go

    none = jnp.zeros(data.present.shape, dtype=bool)
    start = (u, none, data.sigma, jnp.zeros(data.present.shape), jnp.asarray(True),
             jnp.asarray(0), jnp.asarray(0), jnp.asarray(True))  # fmt: skip
    u, jumps, sigma, residuals, ok, steps, _, _ = jax.lax.while_loop(again, refit, start)
    cost = jnp.sum(robust(jnp.where(jumps, 0.0, residuals), static.loss, static.f_scale) ** 2)
    return OffTheJumps(u, jnp.asarray(jumps), sigma, cost, ok, steps)


def _fit_one(u0, measured, data: CalibrationData, static: _Static) -> FitOutcome:
    """One fit from `u0 (P,)` on `measured (E, S, n)` (`fit_off_the_jumps`), scored over
    every sample: fits leave out different ones, and each left out counts the χ² a
    sample expects (1)."""
    data = eqx.tree_at(lambda d: d.measured, data, measured)
    fit = fit_off_the_jumps(u0, data, static)
    score = fit.cost + jnp.sum(fit.jumps) + log_likelihood_term(fit.sigma, data.present)
    return FitOutcome(fit.u, fit.converged, fit.steps, fit.sigma, fit.cost, score)


@functools.partial(structure_jit, exported=lambda leaves: FitOutcome(*leaves))
def fit_program(u0, measured, data: CalibrationData, static: _Static) -> FitOutcome:
    """`_fit_one` over a batch, `u0 (B, P)`, `measured (B, E, S, n)`, in one program:
    `static.lanes` fits at a time in lockstep (`vmap`), the groups one after another
    (`lax.map`). On a CPU one lane is fastest: lanes in lockstep run until the slowest
    has converged, a vmapped loop selects its whole carry at every step, and a CPU gains
    nothing from solving lanes side by side (measured, 8 fits of 1,001 samples: 2.6 s in
    lockstep, 0.5 s as lanes of one, 0.28 s as a plain scan)."""
    # `batch_size=1` would still vmap (lanes of one, carrying selects); None does not.
    lanes = static.lanes if static.lanes > 1 else None
    return jax.lax.map(lambda a: _fit_one(a[0], a[1], data, static), (u0, measured),
                       batch_size=lanes)  # fmt: skip


@functools.partial(structure_jit, exported=lambda leaves: Evaluation(*leaves))
def evaluate_program(theta, data: CalibrationData, static: _Static) -> Evaluation:
    """`evaluate` as one compiled program (exported to the compilation cache when it is
    on)."""
    return evaluate(theta, data, static)
