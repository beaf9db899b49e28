"""Gradients of the peak metrics: forward sensitivities with error control.

`jax.jacfwd` through the adaptive stepping loop differentiates the *discrete* solution
on a step grid chosen for the state alone. Through a contact onset the state is smooth
but its sensitivity to `gap` changes over microseconds, and a grid that does not see it
gives gap gradients that are off by percents. So the Jacobian here integrates the
forward sensitivities `S = ∂y/∂θ` alongside `y` (`dS/dt = ∂f/∂y S + ∂f/∂θ`), and the
step-size controller sees both (as CVODES does with sensitivity error control). The
gradient of a peak `g(y(t*), θ)` then follows from the envelope theorem,
`dg/dθ = ∇_y g · S(t*) + ∂g/∂θ`, with `y(t*)` and `S(t*)` taken from the solver's dense
polynomial at the located peak.

Each tangent direction is scaled by its parameter's documented range, so that all
sensitivity columns have the size of the state and one error norm suits them all.
"""

from __future__ import annotations

import functools

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp

from ._model import contact_width, future_metric_bounds, initial_state, vector_field
from ._params import (
    PARAMETER_NAMES,
    ParameterError,
    RecoilParams,
    Smoothing,
    SolverOptions,
    _is_concrete,
    parameter_limits,
    values_of,
    with_values,
)
from ._solve import (
    Peaks,
    _integrate_peaks,
    _metrics,
    _PeakLoop,
    _peaks_from_run,
    _queued_map,
    _raise_on_failure,
)

#: The default parameters to differentiate with respect to: the absorber design.
DESIGN_PARAMETERS = ("gap", "m", "k_r", "c_r")

#: Default solver options for gradients. With error control on the sensitivities the
#: gradient error follows the tolerance, whatever the smoothing widths: measured against
#: central differences (scaled by the parameter's range over the peak), rtol 1e-6 gave
#: <= 1.8e-4 and rtol 1e-7 <= 8.2e-5 over 24 designs (tests/test_gradients.py).
GRADIENT_OPTIONS = SolverOptions(rtol=1e-7, atol=1e-10)

def parameter_scale(name: str) -> float:
    """Width of a parameter's documented range (the tangent scaling; SI units)."""
    lo, hi = parameter_limits(name).documented
    return hi - lo


class PeakGradients(eqx.Module):
    """Derivatives of the peak metrics with respect to the parameters `wrt` (flat names,
    static). Each field has shape `(..., len(wrt))`; units: metric unit per parameter unit.

    There is no gradient of the peak *times*: a peak can jump from one local maximum to
    another, and its time with it.
    """

    peak_displacement: jax.Array
    peak_anchoring_force: jax.Array
    peak_contact_force: jax.Array
    min_stroke: jax.Array
    max_stroke: jax.Array
    wrt: tuple[str, ...] = eqx.field(static=True)

    def to_dict(self) -> dict[str, dict[str, float]]:
        """`{metric_key: {parameter: derivative}}` for one (unbatched) design."""
        keys = {
            "peak_displacement_m": self.peak_displacement,
            "peak_anchoring_force_N": self.peak_anchoring_force,
            "peak_contact_force_N": self.peak_contact_force,
            "min_stroke_m": self.min_stroke,
            "max_stroke_m": self.max_stroke,
        }
        return {k: {n: float(v[j]) for j, n in enumerate(self.wrt)} for k, v in keys.items()}


def _check_wrt(params: RecoilParams, wrt: tuple[str, ...]) -> None:
    if not wrt:
        raise ParameterError("wrt is empty: name at least one parameter")
    for name in wrt:
        if name not in PARAMETER_NAMES:
            raise ParameterError(
                f"cannot differentiate with respect to {name!r}; known parameters: "
                f"{', '.join(PARAMETER_NAMES)}"
            )
        group, _ = PARAMETER_NAMES[name]
        if getattr(params, group) is None:
            raise ParameterError(
                f"{name} is an absorber parameter, but this is the simplified model "
                "(absorber=None)"
            )
    if len(set(wrt)) != len(wrt):
        raise ParameterError(f"wrt names a parameter twice: {wrt}")


def _directions(wrt: tuple[str, ...]):
    """Tangent directions in the space of the parameters `wrt`, shape `(k, k)`: direction
    j moves parameter wrt[j] by its documented range."""
    return jnp.diag(jnp.asarray([parameter_scale(name) for name in wrt]))


def _model_vf(t, y, params, smoothing):
    return vector_field(t, y, (params, smoothing, contact_width(params, smoothing)))


def _model_metrics(y, params, smoothing):
    return _metrics(y, (params, smoothing, contact_width(params, smoothing)))


#: Metrics that have a smooth maximum over time (index into `_metrics`).
SMOOTH_MAX_METRICS = {"peak_displacement": 0, "peak_anchoring_force": 1}
# The log-integral starts from a seed worth `_SEED * t1` seconds at the initial value,
# so that it is finite at t = 0 and its first steps are not stiff.
_SEED = 1e-3
_N_STATE = 4


class SmoothMax(eqx.Module):
    """Smooth maxima over time of peak metrics: `T · log((1/t1) ∫_0^t1 exp(g(t)/T) dt)`
    for each metric `g` named in `metrics` (static; keys of `SMOOTH_MAX_METRICS`) with
    temperature `T` in the metric's unit (`temperatures`, shape `(len(metrics),)`).

    As `T → 0` this tends to `max_t g`, from below by about `T · log(t1 / w)` where `w`
    is the width of the peak. Unlike the peak, it is smooth where the maximum jumps
    from one local maximum to another: both contribute, weighted by `exp(g/T)`.
    It is integrated as one extra state per metric, `L = log((1/t1) ∫ exp(g/T))`, with
    `dL/dt = exp(g/T − L) / t1`, under the same error control as the rest.
    """

    metrics: tuple[str, ...] = eqx.field(static=True)
    temperatures: jax.Array = eqx.field(converter=lambda x: jnp.asarray(x, dtype=float))

    def __check_init__(self):
        for name in self.metrics:
            if name not in SMOOTH_MAX_METRICS:
                raise ParameterError(
                    f"no smooth maximum of {name!r}; choose from {', '.join(SMOOTH_MAX_METRICS)}"
                )
        if jnp.shape(self.temperatures)[-1:] != (len(self.metrics),):
            raise ParameterError("SmoothMax needs one temperature per metric")
        if _is_concrete(self.temperatures) and not bool(jnp.all(self.temperatures > 0)):
            raise ParameterError(
                f"SmoothMax.temperatures = {self.temperatures} is invalid: valid > 0 "
                "(in the metric's unit)"
            )


def _augmented_vf(t, y, params, smoothing, smooth_max, t1):
    f = _model_vf(t, y[:_N_STATE], params, smoothing)
    if smooth_max is None:
        return f
    g = _model_metrics(y[:_N_STATE], params, smoothing)
    index = jnp.asarray([SMOOTH_MAX_METRICS[name] for name in smooth_max.metrics])
    # Clipped so that a sudden rise far above the running integral cannot overflow.
    exponent = jnp.minimum(g[index] / smooth_max.temperatures - y[_N_STATE:], 700.0)
    return jnp.concatenate([f, jnp.exp(exponent) / t1])


def _augmented_metrics(y, params, smoothing):
    # The log-integrals increase monotonically: their maximum is their value at t1.
    return jnp.concatenate([_model_metrics(y[:_N_STATE], params, smoothing), y[_N_STATE:]])


def _augmented_initial_state(params, smoothing, smooth_max):
    y0 = initial_state(params)
    if smooth_max is None:
        return y0
    g0 = _model_metrics(y0, params, smoothing)
    index = jnp.asarray([SMOOTH_MAX_METRICS[name] for name in smooth_max.metrics])
    return jnp.concatenate([y0, g0[index] / smooth_max.temperatures + jnp.log(_SEED)])


def _sensitivity_vf(t, z, args, wrt):
    params, smoothing, smooth_max, t1 = args
    n = _state_size(smooth_max)
    y, sensitivities = z[:n], z[n:].reshape(-1, n)
    # Linearised in the parameters `wrt` only: the others are constants here, so no
    # tangent flows through them.
    f_y, f_jvp = jax.linearize(
        lambda y_, theta: _augmented_vf(t, y_, with_values(params, wrt, theta), smoothing,
                                        smooth_max, t1),
        y, values_of(params, wrt))
    d_sensitivities = jax.vmap(f_jvp)(sensitivities, _directions(wrt))
    return jnp.concatenate([f_y, d_sensitivities.reshape(-1)])


@functools.cache
def _sensitivity_term(wrt: tuple[str, ...]) -> diffrax.ODETerm:
    """The state and its sensitivities to `wrt` as one diffrax term (one per `wrt`)."""
    return diffrax.ODETerm(functools.partial(_sensitivity_vf, wrt=wrt))


def _sensitivity_solve(params, smoothing, options, wrt, smooth_max=None):
    """Peaks, their gradients, and (with `smooth_max`) the smooth maxima `(k,)` and their
    gradients `(k, len(wrt))`."""
    z0, args = _sensitivity_setup(params, smoothing, options, wrt, smooth_max)
    # A smooth maximum integrates over all of [0, t1]: no stopping once the peaks settle.
    bounds = _sensitivity_bounds if smooth_max is None else None
    run = _integrate_peaks(_sensitivity_term(wrt), z0, args, _sensitivity_metrics, options,
                           bounds)
    return _sensitivity_post(args, run, wrt)


def _state_size(smooth_max) -> int:
    return _N_STATE + (0 if smooth_max is None else len(smooth_max.metrics))


def _sensitivity_metrics(z, args):
    params, smoothing, smooth_max, _ = args
    return _augmented_metrics(z[:_state_size(smooth_max)], params, smoothing)


def _sensitivity_bounds(z, args, time_left):
    """`future_metric_bounds` of the state part of `z` (without smooth maxima)."""
    params, smoothing, _, _ = args
    model_args = (params, smoothing, contact_width(params, smoothing))
    return future_metric_bounds(z[:_N_STATE], model_args, time_left)


def _sensitivity_setup(params, smoothing, options, wrt, smooth_max):
    """`(z0, args)` of the sensitivity system: the state, then one sensitivity column per
    parameter in `wrt` (scaled by its range)."""
    def initial(theta):
        return _augmented_initial_state(with_values(params, wrt, theta), smoothing, smooth_max)

    theta = values_of(params, wrt)
    y0 = initial(theta)
    s0 = jax.vmap(lambda d: jax.jvp(initial, (theta,), (d,))[1])(_directions(wrt))
    z0 = jnp.concatenate([y0, s0.reshape(-1)])
    return z0, (params, smoothing, smooth_max, jnp.asarray(options.t1, dtype=float))


def _sensitivity_post(args, run, wrt):
    """Gradients at the located peaks by the envelope theorem: `∇_y g · S(t*) + ∂g/∂θ`."""
    params, smoothing, smooth_max, _ = args
    n = _state_size(smooth_max)
    theta = values_of(params, wrt)

    def gradient_of_metric(i, state):
        y, sensitivities = state[:n], state[n:].reshape(-1, n)

        def metric(y_, theta_):
            return _augmented_metrics(y_, with_values(params, wrt, theta_), smoothing)[i]

        return jax.vmap(lambda s, d: jax.jvp(metric, (y, theta), (s, d))[1])(
            sensitivities, _directions(wrt))

    indices = jnp.arange(run.best_state.shape[0])
    directional = jax.vmap(gradient_of_metric)(indices, run.best_state)
    scales = jnp.asarray([parameter_scale(name) for name in wrt])
    grads = directional / scales
    gradients = PeakGradients(
        peak_displacement=grads[0],
        peak_anchoring_force=grads[1],
        peak_contact_force=grads[2],
        min_stroke=-grads[4],
        max_stroke=grads[3],
        wrt=wrt,
    )
    peaks = _peaks_from_run(run)
    if smooth_max is None:
        return peaks, gradients, None, None
    temperatures = smooth_max.temperatures
    smooth_values = temperatures * run.best[5:]
    smooth_grads = temperatures[:, None] * grads[5:]
    return peaks, gradients, smooth_values, smooth_grads


def _peak_gradients_batch(params, smoothing, options, wrt, lanes):
    """`jax.vmap(peak_gradients)` over a batch, run through `_queued_map` with `lanes`
    designs in flight."""
    loop = _PeakLoop(_sensitivity_term(wrt), _sensitivity_metrics, options,
                     _sensitivity_bounds)
    return _queued_map(
        loop,
        lambda design: _sensitivity_setup(design, smoothing, options, wrt, None),
        lambda design, args, run: _sensitivity_post(args, run, wrt)[:2],
        params, lanes)


_peak_gradients_batch_jit = eqx.filter_jit(_peak_gradients_batch)


def _peaks_and_gradients(params, smoothing, options, wrt):
    peaks, gradients, _, _ = _sensitivity_solve(params, smoothing, options, wrt)
    return peaks, gradients


def peak_gradients(
    params: RecoilParams = RecoilParams(),
    smoothing: Smoothing = Smoothing(),
    options: SolverOptions = GRADIENT_OPTIONS,
    wrt: tuple[str, ...] = DESIGN_PARAMETERS,
) -> tuple[Peaks, PeakGradients]:
    """Peaks and their gradients with respect to the parameters `wrt` (flat names, static),
    by forward sensitivities with error control (see the module docstring). Unjitted and
    transformable (`jax.vmap` applies); each result carries its `status`.

    Designs with no impact have gradients with respect to the absorber's `gap` that are
    exactly zero: the contact force is identically zero and nothing depends on `gap`.
    """
    wrt = tuple(wrt)
    _check_wrt(params, wrt)
    return _peaks_and_gradients(params, smoothing, options, wrt)


_peak_gradients_jit = eqx.filter_jit(_peaks_and_gradients)


def peak_jacobian(
    params: RecoilParams = RecoilParams(),
    smoothing: Smoothing = Smoothing(),
    options: SolverOptions = GRADIENT_OPTIONS,
    wrt: tuple[str, ...] = DESIGN_PARAMETERS,
    *,
    throw: bool = True,
) -> tuple[Peaks, PeakGradients]:
    """Jitted `peak_gradients` for one design: its peaks and their Jacobian with respect
    to `wrt`. Raises `SolveError` on failure when `throw=True`. For batches, `jax.vmap`
    `peak_gradients`."""
    wrt = tuple(wrt)
    _check_wrt(params, wrt)
    peaks, gradients = _peak_gradients_jit(params, smoothing, options, wrt)
    if throw:
        _raise_on_failure(peaks.status)
    return peaks, gradients
