"""Solving one design, or a batch: peak metrics (`peak_metrics`, `peaks`), time histories
(`simulate`), and batches through the lane scheduler."""

from __future__ import annotations

from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp

from ._metrics import METRICS, Peaks
from ._model import (
    RECOIL_TERM,
    forces,
    future_metric_bounds,
    initial_state,
    model_args,
    tracked_metrics,
)
from ._params import RecoilParams, Smoothing, SolverOptions, end_time
from ._queue import queued_map
from ._status import Status, raise_on_failure
from ._stepping import PeakLoop, PeakRun, integrate_peaks, make_controller, make_solver

__all__ = [
    "History",
    "peak_metrics",
    "peaks",
    "peaks_batch",
    "peaks_of_run",
    "simulate",
]


def peaks_of_run(run: PeakRun) -> Peaks:
    """The `Peaks` of a loop run that tracked `tracked_metrics` (maxima of `sign · signal`,
    so a minimum comes back with its sign restored)."""
    best, times = run.by_name(run.best), run.by_name(run.best_time)
    return Peaks.of(
        {name: m.sign * best[name] for name, m in METRICS.items()},
        times,
        run.num_steps,
        run.num_attempts,
        run.status,
    )


def peak_metrics(
    params: RecoilParams = RecoilParams(),
    smoothing: Smoothing = Smoothing(),
    options: SolverOptions = SolverOptions(),
) -> Peaks:
    """The peak metrics of one design: the unjitted, transformable core of `peaks`.

    `jax.vmap` applies, and so do `jax.jacfwd`/`jax.jvp` (default `autodiff="forward"`)
    and `jax.grad`/`jax.vjp` (`SolverOptions(autodiff="reverse")`); these differentiate
    the discrete solver, whose step grid does not follow the sensitivities. For accurate
    gradients use `peak_gradients` or `differentiable_peaks`.

    **Arguments:**

    - `params`: the design (`RecoilParams`).
    - `smoothing`: the switch widths (`Smoothing`; `Smoothing.exact()` for hard switches).
    - `options`: end time, tolerances and step limit (`SolverOptions`).

    **Returns:** `Peaks`, whose `status` says whether the solve succeeded (a failure is
    never raised here: see `peaks`).
    """
    args = model_args(params, smoothing)
    run = integrate_peaks(
        RECOIL_TERM,
        initial_state(params),
        args,
        end_time(params, options),
        tracked_metrics,
        options,
        future_metric_bounds,
    )
    return peaks_of_run(run)


@eqx.filter_jit
def _peaks_jit(params, smoothing, options, throw: bool) -> Peaks:
    result = peak_metrics(params, smoothing, options)
    return raise_on_failure(result, result.status) if throw else result


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
    becomes non-finite or the step size underflows. The check runs inside the compiled
    program (`equinox.error_if`), so it also works inside a user's `jit`.
    """
    return _peaks_jit(params, smoothing, options, throw)


class History(eqx.Module):
    """Time histories on the save grid `ts` (shape `(n,)`, s); each field has shape `(n,)`.

    `x_M, v_M, x_m, v_m` (m, m/s), `anchoring_force` F_AN (N), `contact_force` F_ct (N);
    `status` (a `Status`) says whether the solve reached `t1`.
    """

    ts: jax.Array
    x_M: jax.Array
    v_M: jax.Array
    x_m: jax.Array
    v_m: jax.Array
    anchoring_force: jax.Array
    contact_force: jax.Array
    status: Any


@eqx.filter_jit
def _simulate_jit(params, smoothing, options, ts, throw: bool) -> History:
    args = model_args(params, smoothing)
    solution = diffrax.diffeqsolve(
        RECOIL_TERM,
        make_solver(options),
        t0=0.0,
        t1=end_time(params, options),
        dt0=None,
        y0=initial_state(params),
        args=args,
        saveat=diffrax.SaveAt(ts=ts),
        stepsize_controller=make_controller(options),
        max_steps=options.max_steps,
        throw=False,
    )
    ys = solution.ys
    assert ys is not None
    f = jax.vmap(lambda y: forces(y, params, smoothing, args[2]))(ys)
    ok = solution.result == diffrax.RESULTS.successful
    max_steps = solution.result == diffrax.RESULTS.max_steps_reached
    status = Status.where(ok, Status.ok, Status.where(max_steps, Status.max_steps, Status.failed))
    status = Status.where(ok & ~jnp.all(jnp.isfinite(ys)), Status.nonfinite, status)
    history = History(
        ts=ts,
        x_M=ys[:, 0],
        v_M=ys[:, 1],
        x_m=ys[:, 2],
        v_m=ys[:, 3],
        anchoring_force=f.anchoring,
        contact_force=f.contact,
        status=status,
    )
    return raise_on_failure(history, status) if throw else history


def simulate(
    params: RecoilParams = RecoilParams(),
    smoothing: Smoothing = Smoothing(),
    options: SolverOptions = SolverOptions(),
    ts=None,
    *,
    throw: bool = True,
) -> History:
    """Time histories of one design (diffrax's `diffeqsolve` with dense saving), jitted.

    **Arguments:**

    - `params`, `smoothing`, `options`: as `peak_metrics`.
    - `ts`: the save times (s), shape `(n,)`; default 4001 points over `[0, t1]`.
    - `throw`: raise if the solve fails (default).

    **Returns:** `History` on `ts`.

    **Raises:** `SolveError` (with `throw=True`) if the solve fails; inside `jit` too.
    """
    if ts is None:
        ts = jnp.linspace(0.0, end_time(params, options), 4001)
    ts = jnp.asarray(ts, dtype=float)
    return _simulate_jit(params, smoothing, options, ts, throw)


def _peaks_batch(
    params: RecoilParams, t1, smoothing: Smoothing, options: SolverOptions, lanes: int
) -> Peaks:
    loop = PeakLoop(RECOIL_TERM, tracked_metrics, options, future_metric_bounds)

    def setup(design):
        p, end = design
        return initial_state(p), model_args(p, smoothing), end

    return queued_map(loop, setup, lambda design, args, run: peaks_of_run(run), (params, t1), lanes)


#: `jax.vmap(peak_metrics)` over a batch of designs (a leading axis on every leaf of
#: `params`, and per-design end times `t1`, shape `(n,)`), run through `queued_map` with
#: `lanes` designs in flight. Jitted; `lanes` is static.
peaks_batch = eqx.filter_jit(_peaks_batch)
