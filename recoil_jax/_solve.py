"""Solving the models: peak metrics (manual stepping) and time histories (diffeqsolve)."""

from __future__ import annotations

from typing import ClassVar, NamedTuple

import diffrax
import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp

from ._model import RECOIL_TERM, forces, future_metric_bounds, initial_state, model_args
from ._params import RecoilParams, Smoothing, SolverOptions

# PID coefficients: damp the step-size oscillation at impacts (measured on a prototype).
_PCOEFF, _ICOEFF = 0.3, 0.4


class Status:
    """Per-solve status codes (`Peaks.status`)."""

    OK = 0
    MAX_STEPS = 1
    NONFINITE = 2
    STEP_UNDERFLOW = 3
    FAILED = 4

    MESSAGES: ClassVar[dict[int, str]] = {
        OK: "ok",
        MAX_STEPS: "max_steps reached before t1: increase SolverOptions.max_steps or "
        "loosen the tolerances",
        NONFINITE: "the state became NaN or inf",
        STEP_UNDERFLOW: "the step size underflowed (t + dt == t) before t1",
        FAILED: "the diffrax solve failed",
    }

    @classmethod
    def message(cls, code: int) -> str:
        return cls.MESSAGES.get(int(code), f"unknown status {int(code)}")


class Peaks(eqx.Module):
    """Peak metrics of one solve (scalars; leading batch axes under `vmap`).

    Peaks are the maxima over `[0, t1]` of each step's cubic Hermite interpolant, so they
    lie between solver steps, not on a save grid.

    - `peak_displacement` (m), `peak_displacement_time` (s): max of x_M.
    - `peak_anchoring_force` (N), `peak_anchoring_force_time` (s): max of F_AN.
    - `peak_contact_force` (N), `peak_contact_force_time` (s): max of F_ct (0, at t = 0,
      when there is no contact or no absorber).
    - `min_stroke`, `max_stroke` (m): min and max of the absorber's travel relative to the
      barrel, x_m − x_M (both 0 for the simplified model).
    - `num_steps`: accepted steps; `num_attempts`: accepted + rejected. The solve stops
      before `t1` once the mechanical energy left shows that no metric can exceed its
      peak again (`future_metric_bounds`); the peaks are those over all of `[0, t1]`.
    - `status`: `Status.OK` (0) or the reason the solve failed (then the other fields are
      not to be trusted).
    """

    peak_displacement: jax.Array
    peak_displacement_time: jax.Array
    peak_anchoring_force: jax.Array
    peak_anchoring_force_time: jax.Array
    peak_contact_force: jax.Array
    peak_contact_force_time: jax.Array
    min_stroke: jax.Array
    max_stroke: jax.Array
    num_steps: jax.Array
    num_attempts: jax.Array
    status: jax.Array

    def to_dict(self) -> dict:
        """JSON-ready dict of one (unbatched) solve; the keys of `recoil-jax simulate
        --json`."""
        return {
            key: (int if key in _INT_KEYS else float)(getattr(self, field))
            for key, field in PEAK_KEYS.items()
        } | {"status": Status.message(int(self.status))}


#: `simulate --json` key -> `Peaks` field.
PEAK_KEYS = {
    "peak_displacement_m": "peak_displacement",
    "peak_displacement_time_s": "peak_displacement_time",
    "peak_anchoring_force_N": "peak_anchoring_force",
    "peak_anchoring_force_time_s": "peak_anchoring_force_time",
    "peak_contact_force_N": "peak_contact_force",
    "peak_contact_force_time_s": "peak_contact_force_time",
    "min_stroke_m": "min_stroke",
    "max_stroke_m": "max_stroke",
    "num_steps": "num_steps",
}
_INT_KEYS = {"num_steps"}


def _metrics(y, args):
    """The quantities whose running maxima are tracked: x_M, F_AN, F_ct, x_m − x_M and
    its negative (so that its minimum is a maximum too)."""
    params, smoothing, width_contact = args
    f = forces(y, params, smoothing, width_contact)
    # The simplified model has no absorber, hence no stroke.
    stroke = jnp.zeros_like(y[0]) if params.absorber is None else y[2] - y[0]
    return jnp.stack([y[0], f.anchoring, f.contact, stroke, -stroke])


def _safe_divide(numerator, denominator):
    ok = denominator != 0
    return jnp.where(ok, numerator / jnp.where(ok, denominator, 1.0), jnp.inf)


def hermite_max(p0, d0, p1, d1):
    """Max over `s ∈ [0, 1]` of the cubic with values `p0, p1` and slopes `d0, d1` (per
    unit `s`) at the ends; elementwise. Returns `(value, s)`.

    The interior critical points are the roots of the quadratic `p'(s)`, taken in the
    cancellation-free form; double-`where`s keep gradients finite when the discriminant
    or the leading coefficients vanish.
    """
    a = p0
    b = d0
    c = -3.0 * p0 - 2.0 * d0 + 3.0 * p1 - d1
    d = 2.0 * p0 + d0 - 2.0 * p1 + d1

    def cubic(s):
        return a + s * (b + s * (c + s * d))

    # p'(s) = b + 2c s + 3d s².
    disc = c * c - 3.0 * d * b
    real = disc > 0
    root = jnp.sqrt(jnp.where(real, disc, 1.0))
    q = -(c + jnp.where(c >= 0, root, -root))
    s1 = _safe_divide(q, 3.0 * d)
    s2 = _safe_divide(b, q)
    candidates = [jnp.zeros_like(p0), jnp.ones_like(p1)]
    for s in (s1, s2):
        inside = real & (s > 0) & (s < 1)
        candidates.append(jnp.where(inside, s, 1.0))
    s_all = jnp.stack(candidates)
    values = cubic(s_all)
    best = jnp.argmax(values, axis=0)
    value = jnp.take_along_axis(values, best[None], axis=0)[0]
    s_best = jnp.take_along_axis(s_all, best[None], axis=0)[0]
    return value, s_best


def _initial_best_step(t0, y0, count):
    """Placeholder dense info (a zero-length step at t0) for each tracked metric."""
    step = dict(t0=t0, t1=t0, y0=y0, y1=y0, k=jnp.zeros((7, *y0.shape), y0.dtype))
    return jax.tree.map(lambda x: jnp.broadcast_to(x, (count, *jnp.shape(x))), step)


_REFINE_ITERATIONS = 4


def _polish(solver, args, metrics_fn, final):
    """Refine each peak on the solver's own dense polynomial (Tsit5's 4th-order
    interpolant of the step holding it), by successive parabolic interpolation started
    from the Hermite estimate; kept where it raises the interpolated value. Maxima at a
    step's end are solver points and keep their value. Derivative-free, so it adds
    little to compile times under `jacfwd`/`grad`.

    Returns `(values, times, states)`: the state at each peak (interpolated), shape
    `(n_metrics, n_state)`."""

    def polish_one(i, best, best_time, step):
        dt = step["t1"] - step["t0"]
        has_step = dt > 0
        safe_dt = jnp.where(has_step, dt, 1.0)
        interp = solver.interpolation_cls(**step)

        def state(t):
            return interp.evaluate(jnp.clip(t, step["t0"], step["t0"] + safe_dt))

        def values(ts):  # one traced copy of the interpolant for several times
            return jax.vmap(lambda t: metrics_fn(state(t), args)[i])(ts)

        def refine(_, carry):
            # Vertex of the parabola through three points of the interpolant, with a
            # shrinking spacing: converges on the maximum of the solver's polynomial.
            t, h = carry
            a, b, c = values(jnp.stack([t - h, t, t + h]))
            curvature = a - 2.0 * b + c
            concave = curvature < 0
            shift = jnp.where(concave, 0.5 * h * (a - c) / jnp.where(concave, curvature, -1.0),
                              0.0)
            t = jnp.clip(t + jnp.clip(shift, -h, h), step["t0"], step["t0"] + safe_dt)
            return t, 0.1 * h

        t, _ = jax.lax.fori_loop(0, _REFINE_ITERATIONS, refine, (best_time, 1e-2 * safe_dt))
        start, polished = values(jnp.stack([best_time, t]))
        interior = has_step & (best_time > step["t0"]) & (best_time < step["t1"])
        better = (polished > start) & jnp.isfinite(polished)
        value_i = jnp.where(interior, jnp.where(better, polished, start), best)
        time_i = jnp.where(interior & better, t, best_time)
        state_i = jnp.where(has_step, state(time_i), step["y0"])
        return value_i, time_i, state_i

    # One traced copy for all metrics (vmap over the metric index), not five.
    indices = jnp.arange(final.best.shape[0])
    return jax.vmap(polish_one)(indices, final.best, final.best_time, final.best_step)


class _Carry(eqx.Module):
    t: jax.Array
    t_next: jax.Array
    y: jax.Array
    solver_state: object
    controller_state: object
    made_jump: jax.Array
    metric: jax.Array
    metric_rate: jax.Array
    best: jax.Array
    best_time: jax.Array
    best_step: dict  # per metric: the step holding its max (t0, t1, y0, y1, k)
    num_steps: jax.Array
    num_attempts: jax.Array
    status: jax.Array
    settled: jax.Array  # no metric can exceed its running max any more


def _solver(options: SolverOptions):
    # Forward-mode autodiff through the stepping loop needs the stages as a lax.scan;
    # reverse mode needs diffrax's default (checkpointed) stage loop.
    return diffrax.Tsit5(scan_kind="lax" if options.autodiff == "forward" else None)


def _rms_norm(x):
    """Root mean square of the (1-D) scaled error, as a chain of adds: the default norm's
    `dot` becomes a library call per step on XLA:CPU, several times slower for a
    4–20-element vector under `vmap`. Zero at zero with finite derivatives."""
    total = x[0] * x[0]
    for i in range(1, x.shape[0]):
        total = total + x[i] * x[i]
    positive = total > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, total, 1.0) / x.shape[0]), 0.0)


def _controller(options: SolverOptions):
    return diffrax.PIDController(
        rtol=jnp.asarray(options.rtol), atol=jnp.asarray(options.atol),
        pcoeff=_PCOEFF, icoeff=_ICOEFF, norm=_rms_norm,
    )


class _PeakRun(NamedTuple):
    best: jax.Array  # (n_metrics,) running maxima of metrics_fn
    best_time: jax.Array  # (n_metrics,)
    best_state: jax.Array  # (n_metrics, n_state): the state at each maximum
    num_steps: jax.Array
    num_attempts: jax.Array
    status: jax.Array


class _PeakLoop:
    """The stepping loop of `_integrate_peaks`, in pieces (`init`, `running`, `body`,
    `finish`), so that the queued driver (`_queued_map`) can run many designs through
    the same loop. `term`, `metrics_fn`, `options` and `bounds_fn` are static.

    `bounds_fn(z, args, time_left)`, if given, returns upper bounds on every metric for
    the rest of the run; the loop stops (status OK) once none can beat its running max,
    since the peaks over `[0, t1]` are then known."""

    def __init__(self, term, metrics_fn, options: SolverOptions, bounds_fn=None):
        self.term, self.metrics_fn, self.options = term, metrics_fn, options
        self.bounds_fn = bounds_fn
        self.solver, self.controller = _solver(options), _controller(options)
        self.error_order = self.solver.order(term) + 1

    def _t1(self):
        t1 = jnp.asarray(self.options.t1, dtype=float)
        # Round the last step up to t1 within 100 ULPs, as diffeqsolve does (one
        # `nextafter` rather than its 100 `prevbefore`s, which took 0.7 s to trace).
        t1_floor = t1 - 100.0 * (t1 - jnp.nextafter(t1, jnp.zeros_like(t1)))
        return t1, t1_floor

    def _metric_and_rate(self, z, f, args):
        return jax.jvp(lambda x: self.metrics_fn(x, args), (z,), (f,))

    def init(self, z0, args) -> _Carry:
        term, solver = self.term, self.solver
        t0 = jnp.zeros((), dtype=float)
        t1, _ = self._t1()
        t_next, controller_state = self.controller.init(
            term, t0, t1, z0, None, args, solver.func, self.error_order
        )
        t_next = jnp.minimum(t_next, t1)
        f0 = term.vf(t0, z0, args)
        metric0, rate0 = self._metric_and_rate(z0, f0, args)
        return _Carry(
            t=t0,
            t_next=t_next,
            y=z0,
            # Tsit5 is FSAL: hand it f(t0, z0) rather than diffrax's "first step" flag,
            # which under vmap makes every lane evaluate the first stage while any one
            # lane has it set (as a freshly loaded lane of `_queued_map` does).
            solver_state=(jnp.array(False), f0),
            controller_state=controller_state,
            made_jump=jnp.array(False),
            metric=metric0,
            metric_rate=rate0,
            best=metric0,
            best_time=jnp.zeros_like(metric0),
            best_step=_initial_best_step(t0, z0, metric0.shape[0]),
            num_steps=jnp.array(0),
            num_attempts=jnp.array(0),
            status=jnp.array(Status.OK),
            settled=jnp.array(False),
        )

    def running(self, c: _Carry):
        t1, _ = self._t1()
        return (c.t < t1) & (c.status == Status.OK) & ~c.settled

    def body(self, c: _Carry, args) -> _Carry:
        term, solver = self.term, self.solver
        t1, t1_floor = self._t1()
        dt = c.t_next - c.t
        z1, z_error, dense_info, solver_state, _ = solver.step(
            term, c.t, c.t_next, c.y, args, c.solver_state, c.made_jump
        )
        keep, t_prev, t_next, made_jump, controller_state, _ = (
            self.controller.adapt_step_size(
                c.t, c.t_next, c.y, z1, args, z_error, self.error_order, c.controller_state
            ))
        t_prev = jnp.minimum(t_prev, t1)
        t_next = jnp.where(
            t_next > t1_floor, jnp.where(keep, t1, t_prev + 0.5 * (t1 - t_prev)), t_next
        )
        # Tsit5 is FSAL: its last stage is dt * f(t + dt, z1).
        metric1, rate1 = self._metric_and_rate(z1, dense_info["k"][-1] / dt, args)
        step_best, s = hermite_max(c.metric, c.metric_rate * dt, metric1, rate1 * dt)
        improve = keep & (step_best > c.best)
        best = jnp.where(improve, step_best, c.best)
        settled = c.settled
        if self.bounds_fn is not None:
            bounds = self.bounds_fn(z1, args, t1 - c.t_next)
            settled = settled | (keep & jnp.all(bounds <= best))
        step = dict(t0=c.t, t1=c.t_next, **dense_info)
        best_step = jax.tree.map(
            lambda new, old: jnp.where(
                improve.reshape((-1,) + (1,) * (old.ndim - 1)), new[None], old),
            step, c.best_step)
        finite = jnp.all(jnp.isfinite(z1)) & jnp.isfinite(dt)
        status = jnp.where(keep & ~finite, Status.NONFINITE, c.status)
        status = jnp.where((t_prev < t1) & (t_next <= t_prev), Status.STEP_UNDERFLOW, status)

        def select(new, old):
            return jax.tree.map(lambda a, b: jnp.where(keep, a, b), new, old)

        return _Carry(
            t=t_prev,
            t_next=t_next,
            y=select(z1, c.y),
            solver_state=select(solver_state, c.solver_state),
            controller_state=controller_state,
            made_jump=jnp.where(keep, made_jump, c.made_jump),
            metric=select(metric1, c.metric),
            metric_rate=select(rate1, c.metric_rate),
            best=best,
            best_time=jnp.where(improve, c.t + s * dt, c.best_time),
            best_step=best_step,
            num_steps=c.num_steps + keep.astype(int),
            num_attempts=c.num_attempts + 1,
            status=status,
            settled=settled,
        )

    def finish(self, final: _Carry, args) -> _PeakRun:
        t1, _ = self._t1()
        status = jnp.where(
            (final.status == Status.OK) & (final.t < t1) & ~final.settled, Status.MAX_STEPS,
            final.status
        )
        best, best_time, best_state = _polish(self.solver, args, self.metrics_fn, final)
        return _PeakRun(best, best_time, best_state, final.num_steps, final.num_attempts,
                        status)


def _integrate_peaks(term, z0, args, metrics_fn, options: SolverOptions,
                     bounds_fn=None) -> _PeakRun:
    """Integrate `term` from `z0` over `[0, t1]` with Tsit5 + PID, stepping manually
    (diffrax's documented `solver.step` + `adapt_step_size` pattern) in one while loop,
    and keep the running maxima of `metrics_fn(z, args)` (a vector), located between
    steps: each accepted step's cubic Hermite interpolant (end values and rates) finds
    the step holding a maximum; `_polish` then refines it on Tsit5's dense polynomial.
    With `bounds_fn` (see `_PeakLoop`) it stops once the peaks are certain."""
    loop = _PeakLoop(term, metrics_fn, options, bounds_fn)
    kind = "lax" if options.autodiff == "forward" else "checkpointed"
    final = eqxi.while_loop(loop.running, lambda c: loop.body(c, args), loop.init(z0, args),
                            max_steps=options.max_steps, kind=kind)
    return loop.finish(final, args)


def _queued_map(loop: _PeakLoop, setup, post, designs, lanes: int):
    """`jax.vmap(lambda d: post(d, loop.finish(solve(*setup(d)))))(designs)`, but with
    `lanes` designs in flight at a time, each lane taking the next design as soon as its
    own has finished (refilled in groups of at least `lanes // 16`).

    A plain `vmap` of the stepping loop runs every member for as many steps as the
    slowest one needs; over random designs that used under a third of the lanes' steps.

    `setup(design) -> (z0, args)`; `post(design, args, run) -> result`. `designs`: a
    pytree with a leading axis `N`. Not vmappable; jit it."""
    n = jax.tree.leaves(designs)[0].shape[0]
    lanes = min(lanes, n)
    max_steps = loop.options.max_steps

    def take(index):
        return jax.tree.map(lambda x: x[index], designs)

    def start(index):
        z0, args = setup(take(index))
        return loop.init(z0, args), args

    # Every lane starts idle; the first refill loads the first `lanes` designs (so the
    # setup is traced once, inside the refill).
    lane_state, lane_args = jax.tree.map(
        lambda x: jnp.zeros((lanes, *x.shape), x.dtype), jax.eval_shape(start, 0))
    finals = jax.tree.map(lambda x: jnp.zeros((n, *x.shape[1:]), x.dtype), lane_state)
    carry = (lane_state, lane_args, jnp.full(lanes, -1), jnp.array(0), finals, jnp.array(0))
    threshold = max(1, lanes // 16)

    def running(c):
        return loop.running(c) & (c.num_attempts < max_steps)

    def cond(carry):
        return carry[-1] < n

    def refill(state, args, index, next_index):
        idle = index < 0
        new_index = next_index + jnp.cumsum(idle) - 1
        fill = idle & (new_index < n)
        count = jnp.sum(fill)

        def load(operands):
            state, args, index, next_index = operands
            fresh_state, fresh_args = jax.vmap(start)(jnp.where(fill, new_index, 0))

            def pick(new, old):
                return jnp.where(fill.reshape((-1,) + (1,) * (new.ndim - 1)), new, old)

            state = jax.tree.map(pick, fresh_state, state)
            args = jax.tree.map(pick, fresh_args, args)
            return state, args, jnp.where(fill, new_index, index), next_index + count

        now = (count >= threshold) | ((count > 0) & ~jnp.any(index >= 0))
        return jax.lax.cond(now, load, lambda operands: operands,
                            (state, args, index, next_index))

    def body(carry):
        state, args, index, next_index, finals, done = carry
        state, args, index, next_index = refill(state, args, index, next_index)
        # Every lane holding a design is still running: a lane is emptied the moment its
        # design finishes, and a freshly loaded one starts at t = 0 < t1.
        active = index >= 0
        stepped = jax.vmap(loop.body)(state, args)
        state = jax.tree.map(
            lambda new, old: jnp.where(active.reshape((-1,) + (1,) * (new.ndim - 1)), new,
                                       old),
            stepped, state)
        finished = active & ~jax.vmap(running)(state)
        slot = jnp.where(finished, index, n)  # out of range: dropped
        finals = jax.tree.map(lambda buf, x: buf.at[slot].set(x, mode="drop"), finals, state)
        done = done + jnp.sum(finished)
        index = jnp.where(finished, -1, index)
        return state, args, index, next_index, finals, done

    finals = jax.lax.while_loop(cond, body, carry)[4]

    def finish(design, final):
        _, args = setup(design)
        return post(design, args, loop.finish(final, args))

    return jax.vmap(finish)(designs, finals)


def _peaks_from_run(run: _PeakRun) -> Peaks:
    best, best_time = run.best, run.best_time
    return Peaks(
        peak_displacement=best[0],
        peak_displacement_time=best_time[0],
        peak_anchoring_force=best[1],
        peak_anchoring_force_time=best_time[1],
        peak_contact_force=best[2],
        peak_contact_force_time=best_time[2],
        min_stroke=-best[4],
        max_stroke=best[3],
        num_steps=run.num_steps,
        num_attempts=run.num_attempts,
        status=run.status,
    )


def _peaks(
    params: RecoilParams = RecoilParams(),
    smoothing: Smoothing = Smoothing(),
    options: SolverOptions = SolverOptions(),
) -> Peaks:
    args = model_args(params, smoothing)
    run = _integrate_peaks(RECOIL_TERM, initial_state(params), args, _metrics, options,
                           future_metric_bounds)
    return _peaks_from_run(run)


class SolveError(RuntimeError):
    """A solve failed (max steps, non-finite state, step-size underflow)."""


def _raise_on_failure(status) -> None:
    codes = jnp.unique(jnp.asarray(status).reshape(-1))
    bad = [int(c) for c in codes if int(c) != Status.OK]
    if bad:
        raise SolveError("; ".join(Status.message(c) for c in bad))


_peaks_jit = eqx.filter_jit(_peaks)


def peaks(
    params: RecoilParams = RecoilParams(),
    smoothing: Smoothing = Smoothing(),
    options: SolverOptions = SolverOptions(),
    *,
    throw: bool = True,
) -> Peaks:
    """Peak metrics of one design (see `Peaks`), jitted. With `throw=True` a failed solve
    raises `SolveError` instead of returning numbers that cannot be trusted.

    For transformations use `peak_metrics`, the same computation unjitted and without the
    check: `jax.vmap`, `jax.jacfwd`/`jax.jvp` (default `autodiff="forward"`) and
    `jax.grad`/`jax.vjp` (`SolverOptions(autodiff="reverse")`) apply to it, and each result
    carries its `status`.
    """
    result = _peaks_jit(params, smoothing, options)
    if throw:
        _raise_on_failure(result.status)
    return result


#: The unjitted, transformable core: `peak_metrics(params, smoothing, options) -> Peaks`.
peak_metrics = _peaks


class History(eqx.Module):
    """Time histories on the save grid `ts` (shape `(n,)`, s); each field has shape `(n,)`.

    `x_M, v_M, x_m, v_m` (m, m/s), `anchoring_force` F_AN (N), `contact_force` F_ct (N).
    """

    ts: jax.Array
    x_M: jax.Array
    v_M: jax.Array
    x_m: jax.Array
    v_m: jax.Array
    anchoring_force: jax.Array
    contact_force: jax.Array
    status: jax.Array


def _simulate(params, smoothing, options, ts) -> History:
    args = model_args(params, smoothing)
    solution = diffrax.diffeqsolve(
        RECOIL_TERM,
        _solver(options),
        t0=0.0,
        t1=options.t1,
        dt0=None,
        y0=initial_state(params),
        args=args,
        saveat=diffrax.SaveAt(ts=ts),
        stepsize_controller=_controller(options),
        max_steps=options.max_steps,
        throw=False,
    )
    ys = solution.ys
    f = jax.vmap(lambda y: forces(y, params, smoothing, args[2]))(ys)
    ok = solution.result == diffrax.RESULTS.successful
    max_steps = solution.result == diffrax.RESULTS.max_steps_reached
    status = jnp.where(ok, Status.OK, jnp.where(max_steps, Status.MAX_STEPS, Status.FAILED))
    status = jnp.where(ok & ~jnp.all(jnp.isfinite(ys)), Status.NONFINITE, status)
    return History(
        ts=ts,
        x_M=ys[:, 0],
        v_M=ys[:, 1],
        x_m=ys[:, 2],
        v_m=ys[:, 3],
        anchoring_force=f.anchoring,
        contact_force=f.contact,
        status=status,
    )


_simulate_jit = eqx.filter_jit(_simulate)


def simulate(
    params: RecoilParams = RecoilParams(),
    smoothing: Smoothing = Smoothing(),
    options: SolverOptions = SolverOptions(),
    ts=None,
    *,
    throw: bool = True,
) -> History:
    """Time histories of one design on the grid `ts` (default: 4001 points over
    `[0, t1]`). Raises `SolveError` on failure when `throw=True`."""
    if ts is None:
        ts = jnp.linspace(0.0, options.t1, 4001)
    ts = jnp.asarray(ts, dtype=float)
    result = _simulate_jit(params, smoothing, options, ts)
    if throw:
        _raise_on_failure(result.status)
    return result


def _peaks_batch(params: RecoilParams, smoothing: Smoothing, options: SolverOptions,
                 lanes: int) -> Peaks:
    """`jax.vmap(peak_metrics)` over a batch of designs (leading axis on every leaf of
    `params`), run through `_queued_map` with `lanes` designs in flight."""
    loop = _PeakLoop(RECOIL_TERM, _metrics, options, future_metric_bounds)

    def setup(design):
        return initial_state(design), model_args(design, smoothing)

    return _queued_map(loop, setup, lambda design, args, run: _peaks_from_run(run), params,
                       lanes)


_peaks_batch_jit = eqx.filter_jit(_peaks_batch)
