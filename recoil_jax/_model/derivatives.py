"""Gradients of the peak metrics: forward sensitivities with error control.

`jax.jacfwd` through the adaptive stepping loop differentiates the *discrete* solution
on a step grid chosen for the state alone. Through a contact onset the state is smooth
but its forward sensitivity to `gap` changes over microseconds, and a grid that does not
see it gives gap gradients that are off by percents. So the Jacobian here integrates the
forward sensitivities `S = ∂y/∂θ` (the tangents) alongside `y` (`dS/dt = ∂f/∂y S +
∂f/∂θ`), and the step-size controller sees both (as CVODES does with forward-sensitivity
error control). The gradient of a peak `g(y(t*), θ)` then follows from the envelope
theorem, `dg/dθ = ∇_y g · S(t*) + ∂g/∂θ`, with `y(t*)` and `S(t*)` taken from the
solver's dense polynomial at the located peak (`docs/model.md`, *Gradients*).

Each tangent direction is scaled by its parameter's `parameter_scale` (its documented
range's width, or its `tangent_scale`), so that all tangent columns have the size of the
state and one error norm suits them all. (The global sensitivity analysis over a box is
another thing: `_global_sensitivity`.)
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Sequence
from typing import Any, NamedTuple

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp

from .._model.bounds import future_metric_bounds, held_bounds
from .._model.equations import (
    ModelArgs,
    initial_state,
    model_args,
    mounted,
    tracked_metrics,
    vector_field,
)
from .._model.forces.absorber import contact_width
from .._model.forces.loads import load_jump, load_stops, restart_step
from .._model.forces.system import Structure, forces
from .._model.lanes import queued_map
from .._model.metrics import EXTREMES, METRICS, PeakGradients, Peaks
from .._model.parameter_table import PARAMETERS
from .._model.params import RecoilParams, values_of, with_values
from .._model.programs import structure_jit
from .._model.registry import ParameterError
from .._model.rest import rest_root, static_rest
from .._model.settings import Smoothing, SolverOptions, end_time, with_default_tolerances
from .._model.smooth_max import MetricSeries, SmoothMax, smooth_name
from .._model.solve import (
    MODEL_CEILINGS,
    battery_crossing,
    last_firing,
    model_loop,
    model_sampling,
    peaks_of_run,
)
from .._model.status import raise_on_failure
from .._model.stepping import (
    Crossing,
    Events,
    LeadingTerm,
    Modes,
    PeakLoop,
    PeakRun,
    StopWhenCertain,
)
from .._model.sticking import STICKING

__all__ = [
    "ABSORBER_SIGNALS",
    "DESIGN_PARAMETERS",
    "GRADIENT_OPTIONS",
    "SIGNALS",
    "SIGNAL_ALIASES",
    "SignalHistory",
    "SignalSensitivities",
    "check_wrt",
    "parameter_scale",
    "peak_gradients",
    "peak_gradients_batch",
    "peak_jacobian",
    "signal_history",
    "signal_sensitivities",
    "signal_values",
    "tangent_loop",
    "tangent_solve",
]

#: The default parameters to differentiate with respect to: the absorber design.
DESIGN_PARAMETERS = ("gap", "m", "k_r", "c_r")

#: Default solver options for gradients. With error control on the forward sensitivities
#: the gradient error follows the tolerance, whatever the smoothing widths: measured
#: against central differences (scaled by the parameter's range over the peak), rtol 1e-6
#: gave <= 1.8e-4 and rtol 1e-7 <= 8.2e-5 over 24 designs (tests/test_gradients.py).
GRADIENT_OPTIONS = SolverOptions(rtol=1e-7, atol=1e-10)


def parameter_scale(name: str) -> float:
    """The tangent scaling of a parameter (SI units): its `tangent_scale`, else the width
    of its documented range."""
    p = PARAMETERS[name]
    if p.tangent_scale is not None:
        return p.tangent_scale
    assert p.documented is not None
    lo, hi = p.documented
    return hi - lo


def check_wrt(params: RecoilParams, wrt: tuple[str, ...]) -> None:
    """Raise `ParameterError` unless `wrt` names distinct real-valued parameters that
    `params` has."""
    if not wrt:
        raise ParameterError("wrt is empty: name at least one parameter")
    for name in wrt:
        if name not in PARAMETERS:
            raise ParameterError(
                f"cannot differentiate with respect to {name!r}; known parameters: "
                f"{PARAMETERS.names()}"
            )
        p = PARAMETERS[name]
        if p.integer:
            raise ParameterError(
                f"cannot differentiate with respect to {name}: it is an integer count"
            )
        module = params.part(p.group)
        if module is None:
            if p.group == "absorber":
                raise ParameterError(
                    f"{name} is an absorber parameter, but this is the simplified model "
                    "(absorber=None)"
                )
            raise ParameterError(
                f"{name} belongs to the {p.group}, which this design does not have: give "
                f"one of its parameters to add it"
            )
        if p.index is not None and p.index >= module.knots:
            raise ParameterError(
                f"{name}: this design's orifice has {module.knots} knots (orifice_0 ... "
                f"orifice_{module.knots - 1})"
            )
    if len(set(wrt)) != len(wrt):
        raise ParameterError(f"wrt names a parameter twice: {wrt}")


def _directions(wrt: tuple[str, ...]):
    """Tangent directions in the space of the parameters `wrt`, shape `(k, k)`: direction
    j moves parameter wrt[j] by its `parameter_scale`."""
    return jnp.diag(jnp.asarray([parameter_scale(name) for name in wrt]))


# The log-integral starts from a seed worth `_SEED * t1` seconds at the initial value,
# so that it is finite at t = 0 and its first steps are not stiff.
_SEED = 1e-3
_N_STATE = 4


def _smoothed(values: dict, smooth_max: SmoothMax):
    return jnp.stack([values[name] for name in smooth_max.metrics])


def _field_args(params, smoothing, mode=None) -> ModelArgs:
    """The model's `args` for its vector field alone, which does not read the rest, in
    the stick–slip `mode` (`sticking`; None: as the state has it)."""
    return ModelArgs(params, smoothing, contact_width(params, smoothing), None, mode=mode)


class _Rest(NamedTuple):
    """The static rest of a tangent solve, found once (`_tangent_setup`): its root by
    bisection (`guess`, `rest_root`) and its value after the Newton step (`value`,
    `static_rest`), both m."""

    guess: Any
    value: Any


def _rest_args(
    params, smoothing, rest: _Rest, differentiate: bool, structure=None, mode=None
) -> ModelArgs:
    """The model's `args` with the static rest `rest`. With `differentiate` (static:
    where parameters are traced), the Newton step from its root again (`model_args`),
    which carries its derivatives in them, the implicit function's; without, its value,
    nothing solved again. `structure`: the design's `Structure`, where resolved already;
    `mode`: the stick–slip mode (`sticking`; None: as the state has it)."""
    if not differentiate:
        structure = structure or Structure.of(params)
        width = contact_width(params, smoothing)
        return ModelArgs(params, smoothing, width, rest.value, structure, mode)
    return dataclasses.replace(model_args(params, smoothing, rest.guess, structure), mode=mode)


class TangentArgs(eqx.Module):
    """The `args` of the tangent system (`_tangent_setup`):

    - `params`, `smoothing`: the design and its switch widths;
    - `smooth_max`: the smooth maxima integrated beside the state (`SmoothMax`), or None;
    - `t1` (s): the end time, which scales the smooth maxima's integrals;
    - `rest`: the static rest, found once (`_Rest`);
    - `structure`: which parts the design has (`Structure`), resolved once;
    - `mode`: the stick–slip mode the loop carries (`sticking`), None without rails."""

    params: Any
    smoothing: Any
    smooth_max: Any
    t1: Any
    rest: _Rest
    structure: Structure
    mode: Any = None

    def at(self, params) -> TangentArgs:
        """The same `args` for the design `params` (its parameters moved)."""
        return dataclasses.replace(self, params=params)

    def model(self, differentiate: bool = False, params=None) -> ModelArgs:
        """The model's `args` (`_rest_args`) in this mode, for `params` (default: its own)."""
        params = self.params if params is None else params
        return _rest_args(
            params, self.smoothing, self.rest, differentiate, self.structure, self.mode
        )


def _augmented_vf(t, y, args: TangentArgs):
    params, smoothing, smooth_max = args.params, args.smoothing, args.smooth_max
    f = vector_field(t, y[:_N_STATE], _field_args(params, smoothing, args.mode))
    if smooth_max is None:
        return f
    model = args.model(differentiate=True)
    g = _smoothed(tracked_metrics(t, y[:_N_STATE], model), smooth_max)
    # Clipped so that a sudden rise far above the running integral cannot overflow.
    exponent = jnp.minimum(g / smooth_max.temperatures - y[_N_STATE:], 700.0)
    return jnp.concatenate([f, jnp.exp(exponent) / args.t1])


def _augmented_metrics(t, y, args: ModelArgs, smooth_max) -> dict[str, Any]:
    values = tracked_metrics(t, y[:_N_STATE], args)
    if smooth_max is not None:
        # The log-integrals increase monotonically: their maximum is their value at t1.
        for j, name in enumerate(smooth_max.metrics):
            values[smooth_name(name)] = y[_N_STATE + j]
    return values


def _augmented_initial_state(params, smoothing, smooth_max, rest, structure):
    args = _rest_args(params, smoothing, rest, True, structure)
    y0 = initial_state(args)
    if smooth_max is None:
        return y0
    g0 = _smoothed(tracked_metrics(0.0, y0, args), smooth_max)
    return jnp.concatenate([y0, g0 / smooth_max.temperatures + jnp.log(_SEED)])


def _state_size(smooth_max) -> int:
    return _N_STATE + (0 if smooth_max is None else len(smooth_max.metrics))


def _tangent_vf(t, z, args: TangentArgs, wrt):
    params = args.params
    n = _state_size(args.smooth_max)
    y, tangents = z[:n], z[n:].reshape(-1, n)
    # Linearised in the parameters `wrt` only: the others are constants here, so no
    # tangent flows through them.
    f_y, f_jvp = jax.linearize(
        lambda y_, theta: _augmented_vf(t, y_, args.at(with_values(params, wrt, theta))),
        y,
        values_of(params, wrt),
    )
    d_tangents = jax.vmap(f_jvp)(tangents, _directions(wrt))
    return jnp.concatenate([f_y, d_tangents.reshape(-1)])


@functools.cache
def _tangent_term(wrt: tuple[str, ...]) -> diffrax.ODETerm:
    """The state and its tangents (forward sensitivities) to `wrt` as one diffrax term
    (one per `wrt`)."""
    return diffrax.ODETerm(functools.partial(_tangent_vf, wrt=wrt))


#: The state (and smooth maxima) of the tangent system alone, with its `args`.
_STATE_TERM = diffrax.ODETerm(_augmented_vf)


def _tangent_metrics(t, z, args: TangentArgs):
    model = args.model()
    return _augmented_metrics(t, z[: _state_size(args.smooth_max)], model, args.smooth_max)


def _tangent_bounds(z, args: TangentArgs, t, t1):
    """`future_metric_bounds` (`held_bounds` with the firing envelope) of the state part
    of `z` (without smooth maxima)."""
    bounds = held_bounds if args.structure.envelope else future_metric_bounds
    return bounds(z[:_N_STATE], args.model(), t, t1)


#: A smooth maximum stops integrating once the rest of `[t, t1]` can add less than this to
#: its log-integral (a relative change of the smooth maximum's exponential).
_SMOOTH_TAIL = 1e-12


def _smooth_tangent_bounds(z, args: TangentArgs, t, t1):
    """`_tangent_bounds`, and for each smooth maximum its log-integral `L` where the
    rest of the run cannot raise it by `_SMOOTH_TAIL` (else `+inf`): with `B` bounding
    the metric from `t` on, `L(t1) <= L(t) + log(1 + (t1 - t)/t1 · exp(B/T - L(t)))`."""
    smooth_max = args.smooth_max
    bounds = _tangent_bounds(z, args, t, t1)
    for j, name in enumerate(smooth_max.metrics):
        log_integral = z[_N_STATE + j]
        exponent = jnp.minimum(bounds[name] / smooth_max.temperatures[j] - log_integral, 700.0)
        tail = jnp.maximum(t1 - t, 0.0) / t1 * jnp.exp(exponent)
        bounds[smooth_name(name)] = jnp.where(tail < _SMOOTH_TAIL, log_integral, jnp.inf)
    return bounds


def _stops(params):
    stops = load_stops(params)
    assert stops is not None  # only called for designs with stops
    return stops


def _augmented_jump(t, y, params):
    """`load_jump` of the state part; the smooth-max integrals do not jump."""
    return y.at[:_N_STATE].set(load_jump(t, y[:_N_STATE], params))


def _tangent_jump(before, t, z, f_before, args, wrt):
    """The state and its tangents right after the stop `t` (from `z` at `before`,
    one ULP earlier, where the system's vector field is `f_before`). For a jump
    `y⁺ = g(y⁻, θ)` at a time `τ(θ)`, the tangents jump
    by `S⁺ = g_y (S⁻ + f⁻ τ_θ) + g_θ − f⁺ τ_θ`: the round's firing time moves with
    `fire_interval`, and `f⁻ ≠ f⁺` where a force table starts or ends off zero, or
    where the jump changes the barrel's stick–slip mode (a held barrel fired slides): `f⁺`
    is the field in the mode the jumped state settles in (`STICKING.settle`, as the loop
    settles it after the jump)."""
    params = args.params
    n = _state_size(args.smooth_max)
    y, tangents = z[:n], z[n:].reshape(-1, n)
    theta = values_of(params, wrt)
    index = jnp.argmin(jnp.abs(_stops(params) - t))

    def stop_time(theta_):
        return _stops(with_values(params, wrt, theta_))[index]

    def jump(y_, theta_):
        return _augmented_jump(t, y_, with_values(params, wrt, theta_))

    after = jump(y, theta)
    f_before = f_before[:n]
    if args.mode is None:  # no rails: no mode
        f_after = _augmented_vf(t, after, args)
    else:
        settled, mode = STICKING.settle(t, after[:_N_STATE], args.model())
        f_after = _augmented_vf(
            t, after.at[:_N_STATE].set(settled), dataclasses.replace(args, mode=mode)
        )

    def column(s, d):
        moved = jax.jvp(stop_time, (theta,), (d,))[1]
        jumped = jax.jvp(jump, (y, theta), (s + f_before * moved, d))[1]
        return jumped - f_after * moved

    columns = jax.vmap(column)(tangents, _directions(wrt))
    return jnp.concatenate([after, columns.reshape(-1)])


@functools.cache
def _tangent_events(wrt: tuple[str, ...]) -> Events:
    """The load's stops, jumps and restarts for the tangent system (one per `wrt`)."""
    return Events(
        stops=lambda args: load_stops(args.params),
        jump=functools.partial(_tangent_jump, wrt=wrt),
        restart=lambda args: restart_step(args.params),
    )


def _tangent_settle(t, z, args: TangentArgs):
    """`STICKING.settle` of the state part; a barrel held has no speed to move with the
    parameters either."""
    n = _state_size(args.smooth_max)
    y, tangents = z[:n], z[n:].reshape(-1, n)
    settled, mode = STICKING.settle(t, y[:_N_STATE], args.model())
    held = mode == 0
    tangents = jnp.where(held, tangents.at[:, 1].set(0.0), tangents)
    return jnp.concatenate([y.at[:_N_STATE].set(settled), tangents.reshape(-1)]), mode


def _tangent_guard(t, z, args: TangentArgs):
    return STICKING.guard(t, z[:_N_STATE], args.model())


def _tangent_switch(t, z, args: TangentArgs, wrt):
    """The state and its tangents right after a stick–slip switch at the guard's root
    `t(θ)` (`STICKING.switch`: the speed set to 0, a new mode). As for a load's jump
    (`_tangent_jump`), `S⁺ = R_y (S⁻ + f⁻ t_θ) − f⁺ t_θ`, with the root's move
    `t_θ = −(g_y S⁻ + g_θ) / (g_y f⁻ + g_t)` from the guard `g` (the implicit function):
    where the barrel stops, its speed's tangent goes (held) or is scaled by the turn's
    jump in acceleration; where it slips, nothing jumps."""
    params = args.params
    n = _state_size(args.smooth_max)
    y, tangents = z[:n], z[n:].reshape(-1, n)
    theta = values_of(params, wrt)

    def guard(t_, y_, theta_):
        return STICKING.guard(t_, y_[:_N_STATE], args.at(with_values(params, wrt, theta_)).model())

    switched, mode = STICKING.switch(t, y[:_N_STATE], args.model())
    after = y.at[:_N_STATE].set(switched)
    f_before = _augmented_vf(t, y, args)
    f_after = _augmented_vf(t, after, dataclasses.replace(args, mode=mode))
    rate = jax.jvp(lambda t_, y_: guard(t_, y_, theta), (t, y), (jnp.ones_like(t), f_before))[1]
    moving = rate != 0

    def column(s, d):
        g_dot = jax.jvp(lambda y_, th: guard(t, y_, th), (y, theta), (s, d))[1]
        moved = jnp.where(moving, -g_dot / jnp.where(moving, rate, 1.0), 0.0)
        return (s + f_before * moved).at[1].set(0.0) - f_after * moved

    columns = jax.vmap(column)(tangents, _directions(wrt))
    return jnp.concatenate([after, columns.reshape(-1)]), mode


@functools.cache
def _tangent_modes(wrt: tuple[str, ...]) -> Modes:
    """`STICKING` for the tangent system (one per `wrt`)."""
    return Modes(
        enter=STICKING.enter,  # (a `TangentArgs` takes its mode as a `ModelArgs` does)
        settle=_tangent_settle,
        guard=_tangent_guard,
        switch=functools.partial(_tangent_switch, wrt=wrt),
    )


def _events(params, wrt):
    return None if params.load is None else _tangent_events(wrt)


def _tangent_setup(params, smoothing, wrt, smooth_max, t1):
    """`(z0, args)` of the tangent system up to `t1`: the state, then one tangent
    column per parameter in `wrt` (scaled by its range). `args` (`TangentArgs`) holds
    the static rest (`_Rest`), found once, here (as the
    model's own solve finds it, `model_args`); where parameters are traced, its Newton
    step is taken again and carries its derivatives (`_rest_args`)."""
    width = contact_width(params, smoothing)
    guess = jax.lax.stop_gradient(rest_root(params, smoothing, width))
    rest = _Rest(guess, jax.lax.stop_gradient(static_rest(params, smoothing, width, guess)))
    structure = Structure.of(params)

    def initial(theta):
        return _augmented_initial_state(
            with_values(params, wrt, theta), smoothing, smooth_max, rest, structure
        )

    theta = values_of(params, wrt)
    y0 = initial(theta)
    s0 = jax.vmap(lambda d: jax.jvp(initial, (theta,), (d,))[1])(_directions(wrt))
    z0 = jnp.concatenate([y0, s0.reshape(-1)])
    return z0, TangentArgs(params, smoothing, smooth_max, t1, rest, structure)


class ForwardSensitivities(NamedTuple):
    """What one solve of the state with its forward sensitivities gives (`tangent_solve`).

    - `peaks`: the `Peaks`; `gradients`: their `PeakGradients` with respect to `wrt`;
    - `smooth_values (k,)`, `smooth_gradients (k, len(wrt))`: the smooth maxima of a
      `SmoothMax` and their gradients (None without one);
    - `series_values (k, n)`, `series_gradients (k, n, len(wrt))`: the signals of a
      `MetricSeries` at its save times and their gradients, NaN after the run's end
      (None without one).
    """

    peaks: Peaks
    gradients: PeakGradients
    smooth_values: Any = None
    smooth_gradients: Any = None
    series_values: Any = None
    series_gradients: Any = None


def _tangent_post(args: TangentArgs, run: PeakRun, wrt, series: MetricSeries | None = None):
    """Gradients at the located peaks by the envelope theorem: `∇_y g · S(t*) + ∂g/∂θ`,
    as `ForwardSensitivities`."""
    params, smoothing, smooth_max = args.params, args.smoothing, args.smooth_max
    t1, rest = args.t1, args.rest
    n = _state_size(smooth_max)
    theta = values_of(params, wrt)
    stops = None if params.load is None else load_stops(params)

    def metric(i, t_, y_, theta_, mode=None):
        """Tracked quantity `i` (in the order of `run.names`) at time `t_`, state `y_`, in
        the stick–slip `mode` (None: as the state has it)."""
        design = with_values(params, wrt, theta_)
        model = _rest_args(design, smoothing, rest, True, args.structure, mode)
        values = _augmented_metrics(t_, y_, model, smooth_max)
        return jnp.stack([values[name] for name in run.names])[i]

    def gradient_of_metric(i, state, time, mode=None):
        y, tangents = state[:n], state[n:].reshape(-1, n)
        directional = jax.vmap(
            lambda s, d: jax.jvp(lambda y_, th: metric(i, time, y_, th, mode), (y, theta), (s, d))[
                1
            ]
        )(tangents, _directions(wrt))
        if stops is None:
            return directional
        # A peak right after a round's firing (a velocity jump) stays at that instant,
        # which moves with the parameters: add the metric's rate times the move.
        index = jnp.argmin(jnp.abs(stops - time))
        f = _augmented_vf(time, y, dataclasses.replace(args, mode=mode))
        rate = jax.jvp(
            lambda t_, y_: metric(i, t_, y_, theta, mode), (time, y), (jnp.ones_like(time), f)
        )[1]
        moved = jax.vmap(
            lambda d: jax.jvp(
                lambda th: _stops(with_values(params, wrt, th))[index], (theta,), (d,)
            )[1]
        )(_directions(wrt))
        return directional + jnp.where(_stops(params)[index] == time, rate * moved, 0.0)

    indices = jnp.arange(run.best_state.shape[0])
    # A peak in the mode of the step that holds it (it may be a switch's instant).
    directional = jax.vmap(gradient_of_metric)(
        indices, run.best_state, run.best_time, run.best_mode
    )
    scales = jnp.asarray([parameter_scale(name) for name in wrt])
    grads = run.by_name(directional / scales)
    # A quantity the structure holds constant (not tracked) has no gradient.
    untracked = jnp.zeros_like(grads["peak_displacement"])
    extremes = {name: m.sign * grads.get(name, untracked) for name, m in EXTREMES.items()}
    envelope = _envelope_gradients(args, run, wrt, extremes, scales, n)
    gradients = PeakGradients.of(envelope, wrt)
    peaks = peaks_of_run(params, smoothing, run, t1, rest.value, args.structure)
    smooth_values = smooth_grads = None
    if smooth_max is not None:
        best = run.by_name(run.best)
        temperatures = smooth_max.temperatures
        smooth_values = temperatures * jnp.stack([best[smooth_name(m)] for m in smooth_max.metrics])
        smooth_grads = temperatures[:, None] * jnp.stack(
            [grads[smooth_name(m)] for m in smooth_max.metrics]
        )
    if series is None:
        return ForwardSensitivities(peaks, gradients, smooth_values, smooth_grads)

    def on_series(i):
        # The same envelope formula at each save time (a fixed time: no rate term).
        states, times = run.saved, series.ts
        values = jax.vmap(lambda state, t: metric(i, t, state[:n], theta))(states, times)
        slopes = jax.vmap(lambda st, t: gradient_of_metric(i, st, t))(states, times) / scales
        written = jnp.arange(times.shape[0]) < run.save_count
        return (
            jnp.where(written, values, jnp.nan),
            jnp.where(written[:, None], slopes, jnp.nan),
        )

    rows = [on_series(run.names.index(name)) for name in series.metrics]
    series_values = jnp.stack([r[0] for r in rows])
    series_grads = jnp.stack([r[1] for r in rows])
    return ForwardSensitivities(
        peaks, gradients, smooth_values, smooth_grads, series_values, series_grads
    )


def _envelope_gradients(args: TangentArgs, run: PeakRun, wrt, extremes, scales, n) -> dict:
    """The gradients of the envelope's metrics beside `extremes` (by metric name, scaled
    to parameter units): `residual_displacement = x_M(t1) − x_r` from the tangents at
    `t1` less the rest's derivative; the return's from those at the crossing
    `x_M(t*) = x_r + 1 mm`, which moves by `dt*/dθ = −(S_x − dx_r/dθ) / v_M`
    (`return_time = t* − t_last`, `battery_speed = −v_M(t*)`, whose rate there is the
    barrel's acceleration). Zero where there is no return, NaN without the envelope (as
    the values); the margin is an extreme, NaN without a mount; the pull's is 0 where
    `F_AN` never goes negative (the pull is then 0)."""
    params, smoothing, rest = args.params, args.smoothing, args.rest
    out = dict(extremes)
    nan = jnp.full_like(out["peak_displacement"], jnp.nan)
    if not args.structure.envelope:
        return out | {name: nan for name, m in METRICS.items() if m.envelope}
    theta = values_of(params, wrt)
    rest_move = jax.vmap(
        lambda d: jax.jvp(
            lambda th: (
                _rest_args(with_values(params, wrt, th), smoothing, rest, True, args.structure).rest
            ),
            (theta,),
            (d,),
        )[1]
    )(_directions(wrt))
    final = run.final_state[n:].reshape(-1, n)
    residual = final[:, 0] - rest_move  # (a run that stopped before t1 stopped held)
    out["residual_displacement"] = residual / scales
    y, tangents = run.cross_state[:n], run.cross_state[n:].reshape(-1, n)
    f = _augmented_vf(run.cross_time, y, args)
    moving = y[1] != 0
    # dt*/dθ, per direction
    crossing_move = -(tangents[:, 0] - rest_move) / jnp.where(moving, y[1], 1.0)
    last_move = jax.vmap(
        lambda d: jax.jvp(lambda th: last_firing(with_values(params, wrt, th)), (theta,), (d,))[1]
    )(_directions(wrt))
    returned = run.crossed & moving
    out["return_time"] = jnp.where(returned, (crossing_move - last_move) / scales, 0.0)
    speed_rate = -(tangents[:, 1] + f[1] * crossing_move)
    out["battery_speed"] = jnp.where(returned, speed_rate / scales, 0.0)
    out["stability_margin"] = jnp.where(mounted(params), out["stability_margin"], nan)
    best = run.by_name(run.best)
    pulled = best["peak_pull_force"] > 0
    out["peak_pull_force"] = jnp.where(pulled, out["peak_pull_force"], 0.0)
    pushed = best["peak_anchoring_force"] >= jnp.maximum(best["peak_pull_force"], 0.0)
    out["peak_mount_load"] = jnp.where(pushed, out["peak_anchoring_force"], out["peak_pull_force"])
    return out


def tangent_solve(
    params, smoothing, options, wrt, smooth_max=None, series=None
) -> ForwardSensitivities:
    """Peaks and their gradients with respect to `wrt`, with (given `smooth_max`) the
    smooth maxima and (given a `MetricSeries`) the signals at its save times, each with
    its gradients: one solve of the state with its forward sensitivities
    (`ForwardSensitivities`). Unjitted; `wrt` and the metric names are static."""
    t1 = end_time(params, options)
    z0, args = _tangent_setup(params, smoothing, wrt, smooth_max, t1)
    loop = tangent_loop(params, options, wrt, smooth_max)
    run = loop.integrate(z0, args, t1, save_ts=None if series is None else series.ts)
    return _tangent_post(args, run, wrt, series)


def tangent_loop(params, options, wrt, smooth_max=None, stop_early: bool = True) -> PeakLoop:
    """The stepping loop of the state with its forward sensitivities to `wrt` (and the
    smooth maxima of `smooth_max`) for the structure of `params`: the one place that wires
    the tangent system into a solve (as `model_loop` for the model alone). `stop_early`:
    stop once the peaks are certain (a calibration's signals run to `t1`)."""
    bounds = _tangent_bounds if smooth_max is None else _smooth_tangent_bounds
    structure = Structure.of(params)
    return PeakLoop(
        _tangent_term(wrt),
        _tangent_metrics,
        with_default_tolerances(params, options),
        stop=StopWhenCertain(bounds) if stop_early else None,
        events=_events(params, wrt),
        ceilings=MODEL_CEILINGS,
        sampling=model_sampling(params, structure),
        crossing=Crossing(lambda args: battery_crossing(args.params, args.rest.guess))
        if structure.envelope
        else None,
        leading=LeadingTerm(_STATE_TERM, _state_size(smooth_max)),
        modes=None if params.rails is None else _tangent_modes(wrt),
    )


def _peak_gradients_batch(params, t1, smoothing, options, wrt, lanes, count):
    loop = tangent_loop(params, options, wrt)

    def setup(design):
        p, end = design
        return *_tangent_setup(p, smoothing, wrt, None, end), end

    def post(design, args, run):
        solved = _tangent_post(args, run, wrt)
        return solved.peaks, solved.gradients

    return queued_map(
        loop,
        setup,
        post,
        (params, t1),
        lanes,
        count,
    )


#: `jax.vmap(peak_gradients)` over a batch (a leading axis on every leaf of `params`, and
#: per-design end times `t1`), run through `queued_map` with `lanes` designs in flight;
#: only the first `count` (an integer array) are solved. Jitted; `wrt` and `lanes` are
#: static.
peak_gradients_batch = structure_jit(_peak_gradients_batch)


def _peaks_and_gradients(params, smoothing, options, wrt):
    solved = tangent_solve(params, smoothing, options, wrt)
    return solved.peaks, solved.gradients


def peak_gradients(
    params: RecoilParams = RecoilParams(),
    smoothing: Smoothing = Smoothing(),
    options: SolverOptions = GRADIENT_OPTIONS,
    wrt: Sequence[str] = DESIGN_PARAMETERS,
) -> tuple[Peaks, PeakGradients]:
    """Peaks and their gradients by forward sensitivities with error control (see the
    module docstring). Unjitted and transformable (`jax.vmap` applies).

    **Arguments:**

    - `params`, `smoothing`: the design and the switch widths.
    - `options`: solver settings; default `GRADIENT_OPTIONS` (rtol 1e-7).
    - `wrt`: flat names of the parameters to differentiate with respect to (static).

    **Returns:** `(Peaks, PeakGradients)`; each field of `PeakGradients` has shape
    `(len(wrt),)`. Each result carries its `status`; nothing is raised on failure.

    **Raises:** `ParameterError` if `wrt` is empty, repeats a name, names an unknown
    parameter, or an absorber parameter of the simplified model.

    Designs with no impact have gradients with respect to the absorber's `gap` that are
    exactly zero: the contact force is identically zero and nothing depends on `gap`.
    """
    wrt = tuple(wrt)
    check_wrt(params, wrt)
    return _peaks_and_gradients(params, smoothing, options, wrt)


#: `peak_gradients` as one compiled program (its failures raised outside it).
_peak_jacobian_jit = structure_jit(_peaks_and_gradients)


def peak_jacobian(
    params: RecoilParams = RecoilParams(),
    smoothing: Smoothing = Smoothing(),
    options: SolverOptions = GRADIENT_OPTIONS,
    wrt: Sequence[str] = DESIGN_PARAMETERS,
    *,
    throw: bool = True,
) -> tuple[Peaks, PeakGradients]:
    """`peak_gradients` of one design, jitted.

    **Arguments:** as `peak_gradients`, and `throw`: raise if the solve fails (default).

    **Returns:** `(Peaks, PeakGradients)`.

    **Raises:** `ParameterError` for a bad `wrt` (before compiling); `SolveError` (with
    `throw=True`) if the solve fails, inside `jit` too. For batches, `jax.vmap`
    `peak_gradients`, or use `sweep(..., wrt=...)`.
    """
    wrt = tuple(wrt)
    check_wrt(params, wrt)
    options = with_default_tolerances(params, options)  # one program for any tolerances
    peaks, gradients = _peak_jacobian_jit(params, smoothing, options, wrt)
    return raise_on_failure((peaks, gradients), peaks.status) if throw else (peaks, gradients)


#: The model's measurable signals by name (the paper's symbols), with their unit and
#: what they are; `History` calls two of them by longer names (`SIGNAL_ALIASES`).
SIGNALS: dict[str, tuple[str, str]] = {
    "x_M": ("m", "barrel displacement"),
    "v_M": ("m/s", "barrel velocity"),
    "x_m": ("m", "absorber displacement"),
    "v_m": ("m/s", "absorber velocity"),
    "F_AN": ("N", "anchoring force"),
    "F_ct": ("N", "contact force"),
}
#: `History`'s field names of the signals that have a shorter symbol.
SIGNAL_ALIASES = {"anchoring_force": "F_AN", "contact_force": "F_ct"}
#: The signals only the absorber model has.
ABSORBER_SIGNALS = ("x_m", "v_m", "F_ct")


def signal_values(t, y, params: RecoilParams, smoothing: Smoothing, names: tuple[str, ...]):
    """The signals `names` (of `SIGNALS`) at time `t` and state `y` (4,), shape
    `(len(names),)`."""
    f = forces(y, params, smoothing, contact_width(params, smoothing), t=t)
    values = {
        "x_M": y[0],
        "v_M": y[1],
        "x_m": y[2],
        "v_m": y[3],
        "F_AN": f.anchoring,
        "F_ct": f.contact,
    }
    return jnp.stack([values[name] for name in names])


class SignalSensitivities(NamedTuple):
    """The signals of one solve at its save times, with their derivatives: `values (S,
    n)`, `gradients (S, n, k)` (with respect to the `k` parameters `wrt`, SI units),
    `rates (S, n)` (with respect to time) and the solve's `status`; and the signals of
    the gun at rest before the shot, `rest_values (S,)`, with their derivatives
    `rest_gradients (S, k)` (the static rest in battery, every velocity 0, no breech
    force: what a trace records before its trigger)."""

    values: Any
    gradients: Any
    rates: Any
    status: Any
    rest_values: Any
    rest_gradients: Any


class SignalHistory(NamedTuple):
    """The signals of one solve at its save times, without derivatives: `values (S,
    n)`, the solve's `status` and `rest_values (S,)` (as `SignalSensitivities`)."""

    values: Any
    status: Any
    rest_values: Any


def signal_history(params, smoothing, options, ts, t1, names: tuple[str, ...]) -> SignalHistory:
    """`signal_sensitivities` without the derivatives: one solve of the state alone,
    error-controlled on the state alone (what a sampler without gradients pays a
    draw). Unjitted; `names` is static."""
    args = model_args(params, smoothing)
    y0 = initial_state(args)
    run = model_loop(params, options, stop_early=False, structure=args.structure).integrate(
        y0, args, t1, save_ts=ts
    )
    values = jax.vmap(lambda t, y: signal_values(t, y, params, smoothing, names))(ts, run.saved)
    # The gun at rest before the shot: the solve's start, with no shot velocity yet.
    rest_values = signal_values(None, y0.at[1].set(0.0).at[3].set(0.0), params, smoothing, names)
    return SignalHistory(values.T, run.status, rest_values)


def signal_sensitivities(
    params, smoothing, options, wrt: tuple[str, ...], ts, t1, names: tuple[str, ...]
) -> SignalSensitivities:
    """The signals `names` at the save times `ts` (sorted, within `[0, t1]`) and their
    derivatives with respect to the parameters `wrt` and to time: one solve of the state
    with its forward sensitivities (error-controlled) run to `t1`, the same envelope
    formula as the peaks' at fixed times. Unjitted; `wrt` and `names` are static."""
    z0, args = _tangent_setup(params, smoothing, wrt, None, t1)
    run = tangent_loop(params, options, wrt, stop_early=False).integrate(z0, args, t1, save_ts=ts)
    theta = values_of(params, wrt)
    scales = jnp.asarray([parameter_scale(name) for name in wrt])

    def at(t, state):
        y, columns = state[:_N_STATE], state[_N_STATE:].reshape(-1, _N_STATE)

        def signal(t_, y_, theta_):
            return signal_values(t_, y_, with_values(params, wrt, theta_), smoothing, names)

        values = signal(t, y, theta)
        gradients = jax.vmap(
            lambda s, d: jax.jvp(lambda y_, th: signal(t, y_, th), (y, theta), (s, d))[1]
        )(columns, _directions(wrt))
        f = vector_field(t, y, _field_args(params, smoothing))
        rate = jax.jvp(lambda t_, y_: signal(t_, y_, theta), (t, y), (jnp.ones_like(t), f))[1]
        return values, gradients.T / scales, rate

    values, gradients, rates = jax.vmap(at)(ts, run.saved)
    rest = args.rest

    def at_rest(theta_):
        # The solve's own start (its rest, its derivatives the implicit function's), with
        # the shot's velocity not yet given and no breech force (t = None).
        design = with_values(params, wrt, theta_)
        y0 = initial_state(_rest_args(design, smoothing, rest, True, args.structure))
        return signal_values(None, y0.at[1].set(0.0).at[3].set(0.0), design, smoothing, names)

    rest_values, rest_jvp = jax.linearize(at_rest, theta)
    rest_gradients = jax.vmap(rest_jvp, out_axes=-1)(_directions(wrt)) / scales
    return SignalSensitivities(
        values.T, jnp.moveaxis(gradients, 0, 1), rates.T, run.status, rest_values, rest_gradients
    )
