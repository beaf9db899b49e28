"""Solving one design, or a batch: peak metrics (`peak_metrics`, `peaks`), time histories
(`simulate`), and batches through the lane scheduler."""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._model.bounds import future_metric_bounds, held_bounds
from .._model.equations import (
    BATTERY,
    RECOIL_TERM,
    UNTRACKED,
    initial_state,
    model_args,
    mounted,
    tracked_metrics,
)
from .._model.forces.loads import load_jump, load_stops, restart_step
from .._model.forces.orifice import knot_crossing
from .._model.forces.recuperator import metric_ceilings
from .._model.forces.system import Forces, Structure, forces
from .._model.lanes import queued_map
from .._model.metrics import EXTREMES, METRICS, Peaks
from .._model.params import RecoilParams
from .._model.programs import structure_jit
from .._model.registry import ParameterError, is_concrete
from .._model.settings import Smoothing, SolverOptions, end_time, with_default_tolerances
from .._model.status import Status, raise_on_failure
from .._model.stepping import (
    Ceilings,
    Crossing,
    Events,
    PeakLoop,
    PeakRun,
    Sampling,
    StopWhenCertain,
)
from .._model.sticking import STICKING

__all__ = [
    "MODEL_CEILINGS",
    "MODEL_EVENTS",
    "History",
    "battery_crossing",
    "envelope_values",
    "last_firing",
    "model_events",
    "model_loop",
    "model_sampling",
    "peak_metrics",
    "peaks",
    "peaks_batch",
    "peaks_of_run",
    "simulate",
]


#: The model's load events, for `args = model_args(params, smoothing)`.
MODEL_EVENTS = Events(
    stops=lambda args: load_stops(args.params),
    jump=lambda before, t, y, f_before, args: load_jump(t, y, args.params),
    restart=lambda args: restart_step(args.params),
)


def model_events(params: RecoilParams) -> Events | None:
    """`MODEL_EVENTS` for a design with a load; None (no stops) without one."""
    return None if params.load is None else MODEL_EVENTS


def model_sampling(params: RecoilParams, structure: Structure) -> Sampling:
    """Where else in each step the peaks are looked for (`Sampling`): with a throttling
    orifice, whose force (`∝ v²/A(x)²`) is far from cubic over a step and has a corner at
    each knot (smoothed over a band narrower than a step), at 3 interior points and where
    the barrel crosses a knot. With the firing envelope, at the step's midpoint: the
    battery stop and the buffer make the anchoring force far from cubic over a step (the
    Hermite estimate alone missed a peak by 1.4e-3), and one point finds what three did
    (the friction's turns, for which there were three, now end steps: the stick is a
    mode). Else nowhere."""
    buffer = params.buffer
    if buffer is None or buffer.orifice is None:
        return Sampling(1) if structure.envelope else Sampling()
    return Sampling(
        3,
        lambda t0, dt, evaluate, z0, z1, args: knot_crossing(t0, dt, evaluate, z0, z1, args.params),
    )


#: The ceilings of the model's `args` (or the tangent system's): `metric_ceilings`.
MODEL_CEILINGS = Ceilings(lambda args: metric_ceilings(args.params))


def last_firing(params: RecoilParams):
    """The last round's firing time (s): `(shots − 1) · fire_interval`, 0 for one round."""
    load = params.load
    if load is None or load.shots == 1:
        return jnp.zeros(())
    return (load.shots - 1) * jnp.asarray(load.fire_interval, dtype=float)


def battery_crossing(params: RecoilParams, rest):
    """`(level, after)` of the barrel's return into battery (`Crossing`):
    `x_M = x_r + 1 mm` (`rest`: `x_r`, m), after the last round's firing."""
    return rest + BATTERY, last_firing(params)


def model_loop(
    params: RecoilParams, options: SolverOptions, stop_early: bool = True, structure=None
) -> PeakLoop:
    """The stepping loop of the recoil model for the structure of `params`: the one place
    that wires the model (its term, tracked metrics, load events, ceilings and peak
    samples) into a solve. `stop_early`: stop once the peaks are certain (a history runs
    to `t1`; so does a design with the firing envelope, whose return and rest are
    metrics). Its `integrate(initial_state(args), args, t1)` with
    `args = model_args(p, smoothing)` solves. `structure`: the design's `Structure`, where
    the program has resolved it already (`ModelArgs.structure`)."""
    structure = structure or Structure.of(params)
    envelope = structure.envelope
    return PeakLoop(
        RECOIL_TERM,
        tracked_metrics,
        with_default_tolerances(params, options),
        stop=StopWhenCertain(held_bounds if envelope else future_metric_bounds)
        if stop_early
        else None,
        events=model_events(params),
        ceilings=MODEL_CEILINGS,
        sampling=model_sampling(params, structure),
        crossing=Crossing(lambda args: battery_crossing(args.params, args.rest))
        if envelope
        else None,
        modes=None if params.rails is None else STICKING,
    )


def envelope_values(params: RecoilParams, run: PeakRun, values: dict, end, rest, envelope) -> dict:
    """`values` (extremes by metric name) with the firing envelope's metrics of `run`:
    the return's (from its crossing), `residual_displacement` (`x_M(t1) − x_r`, with
    `end = t1` and the rest `x_r`; a run that stopped before `t1` stopped held, still),
    the stability margin (NaN without a
    mount), the pull (no less than 0) and `returned`; all NaN for a design without the
    envelope (`envelope`: whether the design has it, `Structure`)."""
    out = dict(values)
    nan = jnp.full_like(out["peak_displacement"], jnp.nan)
    if not envelope:
        out |= {name: nan for name, m in METRICS.items() if m.envelope}
        return out | {"returned": jnp.zeros(nan.shape, bool)}
    returned = run.crossed
    last = last_firing(params)
    out["return_time"] = jnp.where(returned, run.cross_time - last, end - last)
    out["battery_speed"] = jnp.where(returned, -run.cross_state[1], 0.0)
    out["residual_displacement"] = run.final_state[..., 0] - rest
    out["stability_margin"] = jnp.where(mounted(params), out["stability_margin"], jnp.nan)
    out["peak_pull_force"] = jnp.maximum(out["peak_pull_force"], 0.0)
    out["peak_mount_load"] = jnp.maximum(out["peak_anchoring_force"], out["peak_pull_force"])
    return out | {"returned": returned}


def peaks_of_run(
    params: RecoilParams, smoothing: Smoothing, run: PeakRun, end, rest, structure=None
) -> Peaks:
    """The `Peaks` of a loop run that tracked `tracked_metrics` (maxima of `sign · signal`,
    so a minimum comes back with its sign restored), with the envelope's metrics
    (`envelope_values`); `end` is the solve's end time `t1` (s), `rest` the static rest
    `x_r` (m) it started from (`ModelArgs.rest`); `structure` the design's `Structure`
    (default: resolved here)."""
    best, times = run.by_name(run.best), run.by_name(run.best_time)
    zero = jnp.zeros_like(best["peak_displacement"])
    values = {
        name: m.sign * best[name] if name in best else zero + UNTRACKED[name]
        for name, m in EXTREMES.items()
    }
    times = {name: times.get(name, zero) for name in EXTREMES}
    envelope = (structure or Structure.of(params)).envelope
    values = envelope_values(params, run, values, end, rest, envelope)
    present = mounted(params) if envelope else False
    times["stability_margin"] = jnp.where(present, times["stability_margin"], jnp.nan)
    pushed = values["peak_anchoring_force"] >= values["peak_pull_force"]
    either = jnp.where(pushed, times["peak_anchoring_force"], times["peak_pull_force"])
    times["peak_pull_force"] = jnp.where(envelope, times["peak_pull_force"], jnp.nan)
    times["peak_mount_load"] = jnp.where(envelope, either, jnp.nan)
    return Peaks.of(values, times, run.num_steps, run.num_attempts, run.status, values["returned"])


def peak_metrics(
    params: RecoilParams = RecoilParams(),
    smoothing: Smoothing = Smoothing(),
    options: SolverOptions = SolverOptions(),
) -> Peaks:
    """The peak metrics of one design: the unjitted, transformable core of `peaks`.

    `jax.vmap` applies, and so do `jax.jacfwd`/`jax.jvp` (default `autodiff="forward"`)
    and `jax.grad`/`jax.vjp` (`SolverOptions(autodiff="reverse")`); these differentiate
    the discrete solver, whose step grid does not follow the forward sensitivities. For
    accurate gradients use `peak_gradients` or `differentiable_peaks`.

    **Arguments:**

    - `params`: the design (`RecoilParams`).
    - `smoothing`: the switch widths (`Smoothing`; `Smoothing.exact()` for hard switches).
    - `options`: end time, tolerances and step limit (`SolverOptions`).

    **Returns:** `Peaks`, whose `status` says whether the solve succeeded (a failure is
    never raised here: see `peaks`).
    """
    t1 = end_time(params, options)
    args = model_args(params, smoothing)
    run = model_loop(params, options, structure=args.structure).integrate(
        initial_state(args), args, t1
    )
    return peaks_of_run(params, smoothing, run, t1, args.rest, args.structure)


@functools.partial(structure_jit, exported=lambda leaves: jax.tree.unflatten(_peaks_tree(), leaves))
def _peaks_jit(params, smoothing, options) -> Peaks:
    return peak_metrics(params, smoothing, options)


def peaks(
    params: RecoilParams = RecoilParams(),
    smoothing: Smoothing = Smoothing(),
    options: SolverOptions = SolverOptions(),
    *,
    throw: bool = True,
) -> Peaks:
    """The peak metrics of one design, jitted (new parameter values do not recompile).

    **Arguments:**

    - `params`, `smoothing`, `options`: as `peak_metrics`.
    - `throw`: raise if the solve fails (default), instead of returning a `Peaks` whose
      `status` says why.

    **Returns:** `Peaks`: peak barrel displacement, anchoring force and contact force with
    their times, the absorber's stroke range, step counts and `status`.

    **Raises:** `SolveError` (with `throw=True`) if the step limit is reached, the state
    becomes non-finite or the step size underflows. Inside a user's `jit` the check
    runs within that program (`equinox.error_if`), so it works there too.
    `ParameterError` for a load that does not fit in the solve (`end_time`), before
    compiling.
    """
    end_time(params, options)  # checks concrete inputs, before compiling
    # Tolerances as values, also the defaults: one program for any tolerances.
    result = _peaks_jit(params, smoothing, with_default_tolerances(params, options))
    return raise_on_failure(result, result.status) if throw else result


class History(eqx.Module):
    """Time histories on the save grid `ts` (shape `(n,)`, s); each field has shape `(n,)`.

    - `x_M, v_M, x_m, v_m` (m, m/s): the state.
    - `anchoring_force` (N), `contact_force` (N); also by the paper's symbols (the
      names of traces, `SIGNALS`), `F_AN` and `F_ct` (`SIGNAL_ALIASES`).
    - `forces`: every force of the design (`Forces`: spring, damper, buffer, recuperator,
      breech, coupling, contact; `None` for elements it does not have), shape `(n,)` each.
    - `peaks`: the `Peaks` of the same solve, over all of `[0, t1]`.
    - `status` (a `Status`) says whether the solve reached `t1`; if it stopped early
      (`simulate(..., throw=False)`), the times after it stopped are NaN.
    """

    ts: jax.Array
    x_M: jax.Array
    v_M: jax.Array
    x_m: jax.Array
    v_m: jax.Array
    anchoring_force: jax.Array
    contact_force: jax.Array
    forces: Forces
    peaks: Peaks
    status: Any

    @property
    def F_AN(self) -> jax.Array:
        """`anchoring_force` by its symbol."""
        return self.anchoring_force

    @property
    def F_ct(self) -> jax.Array:
        """`contact_force` by its symbol."""
        return self.contact_force


@structure_jit
def _simulate_jit(params, smoothing, options, ts) -> History:
    args = model_args(params, smoothing)
    t1 = end_time(params, options)
    run = model_loop(params, options, stop_early=False, structure=args.structure).integrate(
        initial_state(args), args, t1, save_ts=ts
    )
    ys = run.saved
    f = jax.vmap(lambda t, y: forces(y, params, smoothing, args.contact_width, t=t))(ts, ys)
    return History(
        ts=ts,
        x_M=ys[:, 0],
        v_M=ys[:, 1],
        x_m=ys[:, 2],
        v_m=ys[:, 3],
        anchoring_force=f.anchoring,
        contact_force=f.contact,
        forces=f,
        peaks=peaks_of_run(params, smoothing, run, t1, args.rest, args.structure),
        status=run.status,
    )


def simulate(
    params: RecoilParams = RecoilParams(),
    smoothing: Smoothing = Smoothing(),
    options: SolverOptions = SolverOptions(),
    ts=None,
    *,
    throw: bool = True,
) -> History:
    """Time histories of one design, jitted: the same stepping as `peaks` (run to `t1`),
    with the state written at `ts` from the solver's dense polynomial.

    **Arguments:**

    - `params`, `smoothing`, `options`: as `peak_metrics`.
    - `ts`: the save times (s), shape `(n,)`, sorted, within `[0, t1]`; default 4001
      points over `[0, t1]`.
    - `throw`: raise if the solve fails (default).

    **Returns:** `History` on `ts`.

    **Raises:** `ParameterError` for save times that are not sorted or outside `[0, t1]`;
    `SolveError` (with `throw=True`) if the solve fails, inside `jit` too.
    """
    t1 = end_time(params, options)
    if ts is None:
        ts = jnp.linspace(0.0, t1, 4001)
    ts = jnp.asarray(ts, dtype=float)
    if is_concrete((ts, t1)):
        times, end = np.asarray(ts), float(np.max(np.asarray(t1)))
        if times.ndim != 1 or np.any(np.diff(times) < 0) or times.min() < 0 or times.max() > end:
            raise ParameterError(
                f"simulate: ts must be sorted save times within [0, t1 = {end:g} s]"
            )
    history = _simulate_jit(params, smoothing, with_default_tolerances(params, options), ts)
    return raise_on_failure(history, history.status) if throw else history


def _peaks_batch(
    params: RecoilParams, t1, smoothing: Smoothing, options: SolverOptions, lanes: int, count
) -> Peaks:
    structure = Structure.of(params)  # (the batch's: one structure)
    loop = model_loop(params, options, structure=structure)

    def setup(design):
        p, end = design
        args = model_args(p, smoothing, structure=structure)
        return initial_state(args), args, end

    def post(design, args, run):
        return peaks_of_run(design[0], smoothing, run, design[1], args.rest, structure)

    return queued_map(
        loop,
        setup,
        post,
        (params, t1),
        lanes,
        count,
    )


#: `jax.vmap(peak_metrics)` over a batch of designs (a leading axis on every leaf of
#: `params`, and per-design end times `t1`, shape `(n,)`), run through `queued_map` with
#: `lanes` designs in flight; only the first `count` (an integer array) are solved.
#: Jitted; `lanes` is static.
peaks_batch = structure_jit(
    _peaks_batch, exported=lambda leaves: jax.tree.unflatten(_peaks_tree(), leaves)
)


@functools.cache
def _peaks_tree():
    """The pytree structure of a `Peaks` (every field an array, its status a `Status`)."""
    fields = {f.name: 0.0 for f in dataclasses.fields(Peaks) if f.name != "status"}
    return jax.tree.structure(Peaks(**fields, status=Status.ok))  # pyright: ignore[reportArgumentType]
