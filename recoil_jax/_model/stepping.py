"""The stepping engine: Tsit5 with a PID controller, stepped by hand in one loop that keeps
the running maximum of each tracked quantity and stops once the peaks are certain.

Following diffrax's documented `solver.step` + `adapt_step_size` pattern, so that no save
grid is involved: each accepted step's cubic Hermite interpolant locates the step holding
a maximum (`hermite_max`), which is then refined on the solver's dense polynomial
(`polish`). The loop comes in pieces (`PeakLoop.init`, `running`, `body`, `finish`) so
that the lane scheduler (`queued_map`) can run many designs through the same loop.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import diffrax
import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp

from .._model.dense import hermite_max, placeholder_steps, polish
from .._model.modes import Modes, guard_root
from .._model.settings import SolverOptions
from .._model.status import Status

__all__ = [
    "Ceilings",
    "Crossing",
    "Events",
    "LeadingTerm",
    "Modes",
    "PeakLoop",
    "PeakRun",
    "Sampling",
    "StopWhenCertain",
    "integrate_peaks",
    "make_controller",
    "make_solver",
]

# PID coefficients: damp the step-size oscillation at impacts (measured on a prototype).
_PCOEFF, _ICOEFF = 0.3, 0.4

#: `metrics_fn(t, y, args) -> {name: scalar}`: the quantities whose running maxima are kept.
MetricsFn = Callable[[Any, Any, Any], dict[str, Any]]


class Events(eqx.Module):
    """Known times at which the dynamics change (a load's rounds, a force table's points),
    as three static functions of the loop's `args`:

    - `stops(args)`: the times (s, shape `(n,)`) at which a step must end, or None. A
      step ends one ULP before a stop (evaluations on its left side see the left limits),
      and the next starts at the stop itself;
    - `jump(t_before, t, z, f_before, args)`: the state at the stop `t`, from the state
      `z` one ULP before it, where the vector field is `f_before` (a velocity jump, or
      `z` itself);
    - `restart(args)`: the longest first step at t = 0 and after a stop (s), so that a
      short pulse is not stepped over.
    """

    stops: Callable[[Any], Any]
    jump: Callable[[Any, Any, Any, Any, Any], Any]
    restart: Callable[[Any], Any]


class _Carry(eqx.Module):
    t: jax.Array
    t_next: jax.Array
    t1: jax.Array  # this design's end time
    y: jax.Array
    solver_state: Any
    controller_state: Any
    made_jump: jax.Array
    metric: jax.Array  # (n,) the tracked quantities at t, in the order of `names`
    metric_rate: jax.Array
    best: jax.Array
    best_time: jax.Array
    best_step: dict  # per quantity: the step holding its max (t0, t1, y0, y1, k)
    num_steps: jax.Array
    num_attempts: jax.Array
    status: Any  # Status
    settled: jax.Array  # no quantity can exceed its running max any more
    names: tuple[str, ...] = eqx.field(static=True)
    saved: Any = None  # (n_ts, n_state): the state at the save times, when saving
    save_index: Any = None  # the first save time not yet written
    crossed: Any = None  # with a `Crossing`: whether the crossing was found
    cross_step: Any = None  # the dense info of the step that holds it
    mode: Any = None  # with `Modes`: the mode the state is in
    switch_time: Any = None  # the root of its guard the next step ends at (inf: none)
    best_mode: Any = None  # (n,) the mode of each quantity's best step


class _Attempt(NamedTuple):
    """One attempted step of `PeakLoop.body`, from the carry's `t` to `t_end` (`dt`): its
    end state `z1`, the solver's dense output and state, the controller's verdict `keep`
    and next step (`t_prev`, `t_next`, `made_jump`, `controller_state`), the tracked
    quantities and their rates at the step's start (`metric0`, `rate0`) and end
    (`metric1`, `rate1`), and `f_end`, the vector field at the end."""

    t_end: jax.Array
    dt: jax.Array
    z1: jax.Array
    dense_info: dict
    solver_state: Any
    keep: Any  # a bool array (diffrax types it as a bool scalar)
    t_prev: jax.Array
    t_next: jax.Array
    made_jump: Any
    controller_state: Any
    metric0: jax.Array
    rate0: jax.Array
    f_end: jax.Array
    metric1: jax.Array
    rate1: jax.Array


class PeakRun(eqx.Module):
    """What one run of the loop found: for each tracked quantity (in the order of
    `names`) its maximum `best`, the time `best_time` and the state `best_state` there
    (`(n, n_state)`), plus the step counts and the `Status`."""

    best: jax.Array
    best_time: jax.Array
    best_state: jax.Array
    num_steps: jax.Array
    num_attempts: jax.Array
    status: Any
    names: tuple[str, ...] = eqx.field(static=True)
    saved: Any = None  # (n_ts, n_state), with `save_ts`
    save_count: Any = None  # how many rows of `saved` were written (the run may stop early)
    final_time: Any = None  # where the run ended (s)
    final_state: Any = None  # (n_state,) the state there
    crossed: Any = None  # with a `Crossing`: whether the crossing was found
    cross_time: Any = None  # its time (s)
    cross_state: Any = None  # (n_state,) the state there
    best_mode: Any = None  # with `Modes`: (n,) the mode of each quantity's best step
    final_mode: Any = None  # with `Modes`: the mode at `final_time`

    def by_name(self, stacked) -> dict[str, Any]:
        """Rows of an array stacked in the order of `names`, keyed by name."""
        return {name: stacked[i] for i, name in enumerate(self.names)}


def make_solver(options: SolverOptions) -> diffrax.Tsit5:
    # Forward-mode autodiff through the stepping loop needs the stages as a lax.scan;
    # reverse mode needs diffrax's default (checkpointed) stage loop.
    return diffrax.Tsit5(scan_kind="lax" if options.autodiff == "forward" else None)


#: Error vectors up to this length are normed as a chain of adds, longer ones as a sum.
_CHAIN_NORM_MAX = 20


def _rms_norm(x):
    """Root mean square of the (1-D) scaled error. A short vector as a chain of adds:
    diffrax's default norm is a `dot`, which XLA:CPU sends to a library call per step,
    slower for a 4–20-element vector under `vmap`. A longer one (the forward
    sensitivities of many parameters) as a sum: a long chain bloats the gradient
    program (`docs/speed.md` measures both). Zero at zero with finite derivatives."""
    if x.shape[0] > _CHAIN_NORM_MAX:
        total = jnp.sum(x * x)
    else:
        total = x[0] * x[0]
        for i in range(1, x.shape[0]):
            total = total + x[i] * x[i]
    positive = total > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, total, 1.0) / x.shape[0]), 0.0)


def make_controller(options: SolverOptions) -> diffrax.PIDController:
    return diffrax.PIDController(
        rtol=jnp.asarray(options.rtol),
        atol=jnp.asarray(options.atol),
        pcoeff=_PCOEFF,
        icoeff=_ICOEFF,
        norm=_rms_norm,
    )


def _end_times(t1):
    t1 = jnp.asarray(t1, dtype=float)
    # Round the last step up to t1 within 100 ULPs, as diffeqsolve does (one `nextafter`
    # rather than its 100 `prevbefore`s, which took 0.7 s to trace).
    t1_floor = t1 - 100.0 * (t1 - jnp.nextafter(t1, jnp.zeros_like(t1)))
    return t1, t1_floor


def _before(t):
    """The float just below `t`."""
    return jnp.nextafter(t, jnp.full_like(t, -jnp.inf))


class StopWhenCertain(eqx.Module):
    """Stop (status ok) once no tracked quantity can beat its running maximum, since
    the peaks over `[0, t1]` are then known: `bounds(z, args, t, t1)` returns upper
    bounds on every tracked quantity (by name) for the rest of the run."""

    bounds: Callable[[Any, Any, Any, Any], dict[str, Any]]


class Ceilings(eqx.Module):
    """Values a tracked quantity must stay below: `values(args)` returns them by name
    (or None); reaching one ends the solve with `Status.bottomed_out`."""

    values: Callable[[Any], dict[str, Any] | None]


class Sampling(eqx.Module):
    """Where else in each step the tracked quantities are looked for, beside the cubic
    Hermite estimate from the step's ends (for quantities far from cubic over a step,
    such as the orifice force), on the solver's dense polynomial:

    - `samples`: interior points of each step; 0 for none;
    - `kinks(t0, dt, evaluate, z0, z1, args)`, or None: times in the step (shape
      `(m,)`) where a tracked quantity may have a corner (the barrel crossing an
      orifice knot). `evaluate(t)` is the step's dense polynomial."""

    samples: int = eqx.field(default=0, static=True)
    kinks: Callable | None = None


class Crossing(eqx.Module):
    """Find the first time after `after` at which the state's first component comes down
    through `level` (the barrel back into battery), with `(level, after) = where(args)`,
    from the step that holds it, and the state there (`PeakRun.cross_time`,
    `cross_state`). A step that crosses up and down within itself is not seen (steps
    are short against a recoil)."""

    where: Callable[[Any], tuple[Any, Any]]


class LeadingTerm(eqx.Module):
    """A term for the first `size` components of the state alone (their derivatives do
    not depend on the rest, as the model's do not on its forward sensitivities). The
    first step is then chosen on them: diffrax's initial-step rule evaluates the vector
    field twice, and a gradient program's compile time grew by a whole copy of the
    tangent system for it."""

    term: Any
    size: int = eqx.field(static=True)


class PeakLoop:
    """The stepping loop of `integrate_peaks`, in pieces. `term`, `metrics_fn`, `options`
    and the configuration are static; the end time `t1` is per design (it is carried).
    Each part of the configuration is a module, as diffrax's `SaveAt` and `Event` are,
    and None (or the default) leaves it out:

    - `stop` (`StopWhenCertain`): stop once the peaks are certain;
    - `events` (`Events`): the stops, jumps and restarts of a load;
    - `ceilings` (`Ceilings`): values the tracked quantities must stay below;
    - `sampling` (`Sampling`): where else in each step the peaks are looked for;
    - `crossing` (`Crossing`): the barrel's return into battery, located;
    - `leading` (`LeadingTerm`): the term the first step is chosen on;
    - `modes` (`Modes`): a discrete mode carried beside the state, switched at the roots
      of its guard.

    `integrate(..., save_ts)` (shape `(n,)`, sorted), if given, also writes the state at
    these times (`PeakRun.saved`), from the solver's dense polynomial.
    """

    def __init__(
        self,
        term,
        metrics_fn: MetricsFn,
        options: SolverOptions,
        *,
        stop: StopWhenCertain | None = None,
        events: Events | None = None,
        ceilings: Ceilings | None = None,
        sampling: Sampling = Sampling(),
        crossing: Crossing | None = None,
        leading: LeadingTerm | None = None,
        modes: Modes | None = None,
    ):
        self.term, self.metrics_fn, self.options = term, metrics_fn, options
        self.stop, self.events, self.ceilings = stop, events, ceilings
        self.sampling, self.crossing, self.leading = sampling, crossing, leading
        self.modes = modes
        self.solver, self.controller = make_solver(options), make_controller(options)
        self.error_order = self.solver.order(term) + 1

    def integrate(self, z0, args, t1, save_ts=None) -> PeakRun:
        """One solve from `z0` over `[0, t1]` in one while loop (`integrate_peaks`)."""
        kind = "lax" if self.options.autodiff == "forward" else "checkpointed"
        final = eqxi.while_loop(
            self.running,
            lambda c: self.body(c, args, save_ts),
            self.init(z0, args, t1, save_ts),
            max_steps=self.options.max_steps,
            kind=kind,
        )
        return self.finish(final, args)

    def _vector(self, names, t, z, args):
        values = self.metrics_fn(t, z, args)
        return jnp.stack([values[name] for name in names])

    def _metric_and_rate(self, names, t, z, f, args):
        """The tracked quantities at `(t, z)` and their rates along `dz/dt = f`."""
        return jax.jvp(lambda s, x: self._vector(names, s, x, args), (t, z), (jnp.ones_like(t), f))

    def _start(self, c: _Carry, f_start, args):
        """The tracked quantities and their rates at the start of the step: carried from
        the last accepted step, or after a jump (and at t = 0) evaluated at `c.y` with
        `f_start`, the step's first stage. Under `vmap` the evaluation runs only on the
        iterations where a lane needs it (a flag the lanes share keeps the `cond` a
        branch), as diffrax's own first stage does."""
        stale = c.made_jump

        def fresh():
            metric, rate = self._metric_and_rate(c.names, c.t, c.y, f_start, args)
            return jnp.where(stale, metric, c.metric), jnp.where(stale, rate, c.metric_rate)

        return jax.lax.cond(eqxi.unvmap_any(stale), fresh, lambda: (c.metric, c.metric_rate))

    def _certain(self, names, z, args, t, t1, best):
        """Whether no tracked quantity can exceed its running maximum `best` after `t`
        (`StopWhenCertain.bounds` at state `z`)."""
        assert self.stop is not None
        bounds = self.stop.bounds(z, args, t, t1)
        return jnp.all(jnp.stack([bounds[name] for name in names]) <= best)

    def _stops(self, args):
        return None if self.events is None else self.events.stops(args)

    def init(self, z0, args, t1, save_ts=None) -> _Carry:
        term, solver = self.term, self.solver
        t0 = jnp.zeros((), dtype=float)
        t1, _ = _end_times(t1)
        mode = switch_time = None
        if self.modes is not None:
            z0, mode = self.modes.settle(t0, z0, args)
            switch_time = jnp.asarray(jnp.inf)
            args = self.modes.enter(args, mode)
        first_term, first_state = term, z0
        if self.leading is not None:
            first_term, first_state = self.leading.term, z0[: self.leading.size]
        t_next, controller_state = self.controller.init(
            first_term, t0, t1, first_state, None, args, solver.func, self.error_order
        )
        t_next = jnp.minimum(t_next, t1)
        if self.events is not None:
            t_next = jnp.minimum(t_next, t0 + self.events.restart(args))
        names = tuple(self.metrics_fn(t0, z0, args))
        metric0 = self._vector(names, t0, z0, args)
        saved = save_index = None
        if save_ts is not None:
            # NaN until written: a solve that stops early leaves the later times NaN,
            # not zeros that read as a state.
            saved = jnp.full((save_ts.shape[0], *z0.shape), jnp.nan, z0.dtype)
            saved, save_index = _write_saves(save_ts, saved, jnp.array(0), t0, lambda t: z0)
        crossed = cross_step = None
        if self.crossing is not None:
            crossed = jnp.array(False)
            cross_step = jax.tree.map(lambda x: x[0], placeholder_steps(t0, z0, 1))
        return _Carry(
            t=t0,
            t_next=t_next,
            t1=t1,
            y=z0,
            # Tsit5 is FSAL; with `made_jump` set, the first step evaluates f(t0, z0) as
            # its first stage (inside diffrax's stage loop, so the program holds no
            # other copy of the vector field), and the rates at the start come from it.
            solver_state=(jnp.array(False), jnp.zeros_like(z0)),
            controller_state=controller_state,
            made_jump=jnp.array(True),
            metric=metric0,
            metric_rate=jnp.zeros_like(metric0),
            best=metric0,
            best_time=jnp.zeros_like(metric0),
            best_step=placeholder_steps(t0, z0, metric0.shape[0]),
            num_steps=jnp.array(0),
            num_attempts=jnp.array(0),
            status=Status.ok,
            settled=jnp.array(False),
            names=names,
            saved=saved,
            save_index=save_index,
            crossed=crossed,
            cross_step=cross_step,
            mode=mode,
            switch_time=switch_time,
            best_mode=None if mode is None else jnp.full(metric0.shape, mode),
        )

    def running(self, c: _Carry):
        return (c.t < c.t1) & (c.status == Status.ok) & ~c.settled

    def body(self, c: _Carry, args, save_ts=None, check_bounds=None) -> _Carry:
        """One attempted step. `check_bounds` (a traced bool, the same for every lane
        under `vmap`; None: always): whether to test if the peaks are now certain."""
        t1, t1_floor = _end_times(c.t1)
        given = args  # (each mode is entered from these)
        if self.modes is not None:
            args = self.modes.enter(args, c.mode)
        t_end, stops, upcoming, landing = self._step_end(c, args, t1)
        step = self._attempt(c, args, t_end, t1, t1_floor)
        switch_time = c.switch_time
        if self.modes is not None:
            step, switch_time = self._guarded(c, args, step)
        step_best, s = self._step_max(c, args, step)
        keep = step.keep
        improve = keep & (step_best > c.best)
        best = jnp.where(improve, step_best, c.best)
        settled = c.settled
        if self.modes is None:
            settled = self._settled(c, args, step, t1, best, check_bounds)
        best_step = _best_steps(c, step, improve)
        status = self._status(c, args, step, t1, step_best)
        saved, save_index = c.saved, c.save_index
        if save_ts is not None:
            interpolation = self.solver.interpolation_cls(t0=c.t, t1=step.t_end, **step.dense_info)
            saved, save_index = _write_saves(
                save_ts, saved, save_index, jnp.where(keep, step.t_end, c.t), interpolation.evaluate
            )
        crossed, cross_step = self._crossing(c, args, step)
        mode, best_mode = c.mode, c.best_mode
        if self.modes is not None:
            best_mode = jnp.where(improve, c.mode, c.best_mode)
            step, mode, switch_time = self._switched(c, args, step, switch_time)
            # Certain or not in the mode the step leaves the state in.
            entered = self.modes.enter(given, mode)
            settled = self._settled(c, entered, step, t1, best, check_bounds)
        if stops is not None:
            step, saved, save_index = self._past_stop(
                c, args, step, upcoming, landing, t1, save_ts, saved, save_index
            )
            if (modes := self.modes) is not None:
                hit = step.keep & landing

                def settle():
                    z, new = modes.settle(step.t_prev, step.z1, given)
                    return z.astype(step.z1.dtype), jnp.asarray(new, mode.dtype)

                # Only where a lane jumped (as `_switched`).
                settled_z, settled_mode = jax.lax.cond(
                    eqxi.unvmap_any(hit), settle, lambda: (step.z1, mode)
                )
                step = step._replace(z1=jnp.where(hit, settled_z, step.z1))
                mode = jnp.where(hit, settled_mode, mode)
                switch_time = jnp.where(hit, jnp.inf, switch_time)

        def select(new, old):
            return jax.tree.map(lambda a, b: jnp.where(keep, a, b), new, old)

        return _Carry(
            t=step.t_prev,
            t_next=step.t_next,
            t1=c.t1,
            y=select(step.z1, c.y),
            solver_state=select(step.solver_state, c.solver_state),
            controller_state=step.controller_state,
            made_jump=jnp.where(keep, step.made_jump, c.made_jump),
            metric=select(step.metric1, c.metric),
            metric_rate=select(step.rate1, c.metric_rate),
            best=best,
            best_time=jnp.where(improve, c.t + s * step.dt, c.best_time),
            best_step=best_step,
            num_steps=c.num_steps + jnp.asarray(keep, dtype=int),
            num_attempts=c.num_attempts + 1,
            status=status,
            settled=settled,
            names=c.names,
            saved=saved,
            save_index=save_index,
            crossed=crossed,
            cross_step=cross_step,
            mode=mode,
            switch_time=switch_time,
            best_mode=best_mode,
        )

    def _guarded(self, c: _Carry, args, step: _Attempt):
        """The attempt, not kept if its end leaves the mode (`Modes.guard`): the next one
        then ends at the guard's root. Returns `(step, switch_time)`."""
        assert self.modes is not None
        guard = self.modes.guard
        landing = c.switch_time == step.t_end
        leaves = step.keep & ~landing & (guard(step.t_end, step.z1, args) < 0)

        def root():
            interpolation = self.solver.interpolation_cls(t0=c.t, t1=step.t_end, **step.dense_info)
            found = guard_root(lambda t: guard(t, interpolation.evaluate(t), args), c.t, step.t_end)
            return jnp.where(leaves, found, jnp.inf)

        # A flag the lanes share keeps the `cond` a branch under `vmap`.
        at = jax.lax.cond(eqxi.unvmap_any(leaves), root, lambda: jnp.full_like(c.t, jnp.inf))
        step = step._replace(
            keep=step.keep & ~leaves,
            t_prev=jnp.where(leaves, c.t, step.t_prev),
            t_next=jnp.where(leaves, at, step.t_next),
            made_jump=jnp.where(leaves, c.made_jump, step.made_jump),
            controller_state=jax.tree.map(
                lambda old, new: jnp.where(leaves, old, new),
                c.controller_state,
                step.controller_state,
            ),
        )
        return step, jnp.where(leaves, at, c.switch_time)

    def _switched(self, c: _Carry, args, step: _Attempt, switch_time):
        """After a kept step that ends at the guard's root: the state and mode switched
        (`Modes.switch`), the next step's first stage evaluated afresh. Returns
        `(step, mode, switch_time)`."""
        modes = self.modes
        assert modes is not None
        landed = step.keep & (c.switch_time == step.t_end)

        def switch():
            z, mode = modes.switch(step.t_end, step.z1, args)
            return z.astype(step.z1.dtype), jnp.asarray(mode, c.mode.dtype)

        # Evaluated only where a lane landed (a switch is a few steps in hundreds; a flag
        # the lanes share keeps the `cond` a branch under `vmap`).
        z, mode = jax.lax.cond(eqxi.unvmap_any(landed), switch, lambda: (step.z1, c.mode))
        step = step._replace(z1=jnp.where(landed, z, step.z1), made_jump=step.made_jump | landed)
        return step, jnp.where(landed, mode, c.mode), jnp.where(landed, jnp.inf, switch_time)

    def _crossing(self, c: _Carry, args, step: _Attempt):
        """`(crossed, cross_step)` after the step: the step kept as the one holding the
        crossing (`Crossing`) if it is the first to come down through the level after
        its time."""
        if self.crossing is None:
            return c.crossed, c.cross_step
        level, after = self.crossing.where(args)
        down = step.keep & ~c.crossed & (c.t >= after) & (c.y[0] > level) & (step.z1[0] <= level)
        new_step = dict(t0=c.t, t1=step.t_end, **step.dense_info)
        cross_step = jax.tree.map(
            lambda new, old: jnp.where(down, new, old), new_step, c.cross_step
        )
        return c.crossed | down, cross_step

    def _step_end(self, c: _Carry, args, t1):
        """Where the step from `c.t` ends: at `c.t_next`, or one ULP before the next stop
        of the load if the step would reach it. Returns `(t_end, stops, upcoming,
        landing)`: the stops (None without events), the next stop and whether the step
        lands before it."""
        t_end = c.t_next
        if self.modes is not None:
            t_end = jnp.minimum(t_end, c.switch_time)
        stops = self._stops(args)
        upcoming, landing = jnp.inf, jnp.array(False)  # (set below when there are stops)
        if stops is not None:
            # The next stop: end the step one ULP before it, if the step would reach it.
            upcoming = jnp.min(jnp.where(stops > c.t, stops, jnp.inf))
            before = _before(upcoming)
            landing = (upcoming < t1) & (t_end >= before)
            t_end = jnp.where(landing, before, t_end)
        return t_end, stops, upcoming, landing

    def _attempt(self, c: _Carry, args, t_end, t1, t1_floor) -> _Attempt:
        """The solver's step from `c.t` to `t_end`, the controller's verdict on it, and
        the tracked quantities with their rates at both ends of the step."""
        dt = t_end - c.t
        z1, z_error, dense_info, solver_state, _ = self.solver.step(
            self.term, c.t, t_end, c.y, args, c.solver_state, c.made_jump
        )
        keep, t_prev, t_next, made_jump, controller_state, _ = self.controller.adapt_step_size(
            c.t, t_end, c.y, z1, args, z_error, self.error_order, c.controller_state
        )
        t_prev = jnp.minimum(t_prev, t1)
        if self.modes is not None:
            # The next step's end moves with its start (a switch's time moves with the
            # parameters) but not its size: the controller's sizes would carry a switch's
            # derivative on, growing with each step (the same value, to the bit). The
            # end time `t1` does not move.
            sg = jax.lax.stop_gradient
            t_next = sg(t_next) + (t_prev - sg(t_prev))
        metric0, rate0 = self._start(c, dense_info["k"][0] / dt, args)
        t_next = jnp.where(
            t_next > t1_floor, jnp.where(keep, t1, t_prev + 0.5 * (t1 - t_prev)), t_next
        )
        # Tsit5 is FSAL: its last stage is dt * f(t + dt, z1).
        f_end = dense_info["k"][-1] / dt
        metric1, rate1 = self._metric_and_rate(c.names, t_end, z1, f_end, args)
        return _Attempt(
            t_end=t_end,
            dt=dt,
            z1=z1,
            dense_info=dense_info,
            solver_state=solver_state,
            keep=keep,
            t_prev=t_prev,
            t_next=t_next,
            made_jump=made_jump,
            controller_state=controller_state,
            metric0=metric0,
            rate0=rate0,
            f_end=f_end,
            metric1=metric1,
            rate1=rate1,
        )

    def _step_max(self, c: _Carry, args, step: _Attempt):
        """The largest value of each tracked quantity over the step and where it is,
        `(values, s)` with `s` the position in the step (0 to 1): the cubic Hermite
        maximum from the step's ends, or with `Sampling` the maximum sampled on the
        dense polynomial, and at its kinks."""
        dt, metric0, metric1 = step.dt, step.metric0, step.metric1
        if not self.sampling.samples:
            return hermite_max(metric0, step.rate0 * dt, metric1, step.rate1 * dt)
        interpolation = self.solver.interpolation_cls(t0=c.t, t1=step.t_end, **step.dense_info)
        # Sampled on the dense polynomial instead: the end rates of a quantity that is
        # far from cubic over the step can push the Hermite maximum far above (or
        # below) the polynomial's, and the largest estimate would win the peak.
        step_best, s = _sampled_max(
            lambda t: self._vector(c.names, t, interpolation.evaluate(t), args),
            c.t,
            dt,
            self.sampling.samples,
            metric0,
            metric1,
        )
        if self.sampling.kinks is not None:
            kinks = self.sampling.kinks(c.t, dt, interpolation.evaluate, c.y, step.z1, args)
            at_kinks = jax.vmap(
                lambda t: self._vector(c.names, t, interpolation.evaluate(t), args)
            )(kinks)
            j = jnp.argmax(at_kinks, axis=0)
            higher = jnp.max(at_kinks, axis=0) > step_best
            step_best = jnp.where(higher, jnp.max(at_kinks, axis=0), step_best)
            s = jnp.where(higher, (kinks[j] - c.t) / dt, s)
        return step_best, s

    def _settled(self, c: _Carry, args, step: _Attempt, t1, best, check_bounds):
        """Whether the peaks are certain after the step (with `StopWhenCertain`; tested
        only where `check_bounds` is true, see `body`)."""
        settled = c.settled
        if self.stop is None:
            return settled

        def certain():
            return settled | (
                step.keep & self._certain(c.names, step.z1, args, step.t_end, t1, best)
            )

        # A flag not batched keeps the `cond` a branch under `vmap`, not a select.
        return (
            certain()
            if check_bounds is None
            else jax.lax.cond(check_bounds, certain, lambda: settled)
        )

    def _status(self, c: _Carry, args, step: _Attempt, t1, step_best):
        """The `Status` after the step: a kept step that is not finite, a step size that
        underflows, or a tracked quantity that reaches its ceiling (`Ceilings`) ends the
        solve."""
        keep, t_prev = step.keep, step.t_prev
        finite = jnp.all(jnp.isfinite(step.z1)) & jnp.isfinite(step.dt)
        status = Status.where(keep & ~finite, Status.nonfinite, c.status)
        status = Status.where(
            (t_prev < t1) & (step.t_next <= t_prev), Status.step_underflow, status
        )
        ceilings = None if self.ceilings is None else self.ceilings.values(args)
        if ceilings is not None:
            limits = jnp.stack([ceilings.get(name, jnp.inf) for name in c.names])
            status = Status.where(keep & jnp.any(step_best >= limits), Status.bottomed_out, status)
        return status

    def _past_stop(
        self, c: _Carry, args, step: _Attempt, upcoming, landing, t1, save_ts, saved, save_index
    ):
        """The step continued past the stop `upcoming` where it `landing` one ULP before
        it: from the stop itself, with the state after any jump and a first step of at
        most `restart`; `made_jump` makes that step evaluate its first stage afresh, and
        the rates at its start (and the quantities, counted then as the step's start)
        come from it. Returns `(step, saved, save_index)`, the jumped state also saved."""
        assert self.events is not None
        keep, t_next, t_prev = step.keep, step.t_next, step.t_prev
        hit = keep & landing
        jumped = self.events.jump(step.t_end, upcoming, step.z1, step.f_end, args)
        restart = jnp.minimum(t_next - t_prev, self.events.restart(args))
        t_next = jnp.where(hit, jnp.minimum(upcoming + restart, t1), t_next)
        t_prev = jnp.where(hit, upcoming, t_prev)
        z1 = jnp.where(hit, jumped, step.z1)
        made_jump = step.made_jump | hit
        if save_ts is not None:
            saved, save_index = _write_saves(
                save_ts, saved, save_index, jnp.where(hit, upcoming, c.t), lambda t: jumped
            )
        step = step._replace(t_prev=t_prev, t_next=t_next, z1=z1, made_jump=made_jump)
        return step, saved, save_index

    def finish(self, final: _Carry, args) -> PeakRun:
        settled = final.settled
        peak_args = None
        if self.modes is not None:
            enter = self.modes.enter
            peak_args = jax.vmap(lambda mode: enter(args, mode))(final.best_mode)
            args = enter(args, final.mode)
        if self.stop is not None:
            # A solve that tested its bounds only at some steps (`check_bounds`) and ran
            # out of attempts may have become certain since its last test.
            t1 = _end_times(final.t1)[0]
            certain = self._certain(final.names, final.y, args, final.t, t1, final.best)
            settled = settled | certain
        unfinished = (final.status == Status.ok) & (final.t < final.t1) & ~settled
        status = Status.where(unfinished, Status.max_steps, final.status)
        best, best_time, best_state = polish(
            self.solver,
            args,
            lambda t, z, a: self._vector(final.names, t, z, a),
            final.best,
            final.best_time,
            final.best_step,
            search=self.sampling.samples > 0,
            step_args=peak_args,
        )
        cross_time = cross_state = None
        if self.crossing is not None:
            level, _ = self.crossing.where(args)
            cross_time, cross_state = _crossing_point(self.solver, final.cross_step, level)
        return PeakRun(
            best=best,
            best_time=best_time,
            best_state=best_state,
            num_steps=final.num_steps,
            num_attempts=final.num_attempts,
            status=status,
            names=final.names,
            saved=final.saved,
            save_count=final.save_index,
            final_time=final.t,
            final_state=final.y,
            crossed=final.crossed,
            cross_time=cross_time,
            cross_state=cross_state,
            best_mode=final.best_mode,
            final_mode=final.mode,
        )


#: Bisections of a crossing's step before Newton's steps (each halves the bracket).
_BISECTIONS = 24
_NEWTON = 3


def _crossing_point(solver, step, level):
    """`(t, state)` where the dense polynomial of `step` has its first component come down
    through `level`: bisection, then Newton's steps on the position with the velocity
    (the second component) as its rate. A zero-length placeholder step gives its start."""
    interp = solver.interpolation_cls(**step)
    t0, t1 = step["t0"], step["t1"]
    has_step = t1 > t0
    safe_t1 = jnp.where(has_step, t1, t0 + 1.0)

    def state(t):
        return interp.evaluate(jnp.clip(t, t0, safe_t1))

    def bisect(_, bracket):
        low, high = bracket
        middle = 0.5 * (low + high)
        above = state(middle)[0] > level
        return jnp.where(above, middle, low), jnp.where(above, high, middle)

    low, high = jax.lax.fori_loop(0, _BISECTIONS, bisect, (t0, safe_t1))

    def newton(_, t):
        y = state(t)
        moving = y[1] != 0
        shift = jnp.where(moving, (y[0] - level) / jnp.where(moving, y[1], 1.0), 0.0)
        return jnp.clip(t - shift, low, high)

    t = jax.lax.fori_loop(0, _NEWTON, newton, 0.5 * (low + high))
    t = jnp.where(has_step, t, t0)
    return t, jnp.where(has_step, state(t), step["y0"])


def _sampled_max(vector_at, t0, dt, samples, first, last):
    """The maximum over a step of each tracked quantity, from its values at the ends
    (`first`, `last`), at `samples` interior points of the dense polynomial
    (`vector_at(t)`), and at the vertex of the parabola through the largest and its
    neighbours (evaluated there, not taken from the parabola, which overshoots at a
    corner). Returns `(values, s)`, `s` the position in the step (0 to 1)."""
    fractions = jnp.arange(1, samples + 1) / (samples + 1.0)
    interior = jax.vmap(lambda u: vector_at(t0 + u * dt))(fractions)
    values = jnp.concatenate([first[None], interior, last[None]])  # (samples + 2, n)
    grid = jnp.concatenate([jnp.zeros(1), fractions, jnp.ones(1)])
    j = jnp.clip(jnp.argmax(values, axis=0), 1, samples)
    a, b, c = (jnp.take_along_axis(values, (j + k)[None], axis=0)[0] for k in (-1, 0, 1))
    curvature = a - 2.0 * b + c
    concave = curvature < 0
    shift = jnp.where(concave, 0.5 * (a - c) / jnp.where(concave, curvature, -1.0), 0.0)
    vertex = grid[j] + jnp.clip(shift, -1.0, 1.0) / (samples + 1.0)  # (n,)
    at_vertex = jax.vmap(lambda u: vector_at(t0 + u * dt))(vertex)  # (n, n)
    at_vertex = jnp.diagonal(at_vertex)  # quantity i at its own vertex
    best = jnp.max(values, axis=0)
    s_best = grid[jnp.argmax(values, axis=0)]
    higher = at_vertex > best
    return jnp.where(higher, at_vertex, best), jnp.where(higher, vertex, s_best)


def _best_steps(c: _Carry, step: _Attempt, improve):
    """`c.best_step` with the attempted step (its ends, states and stages) written for
    each quantity whose maximum it `improve`s."""
    new_step = dict(t0=c.t, t1=step.t_end, **step.dense_info)
    return jax.tree.map(
        lambda new, old: jnp.where(improve.reshape((-1,) + (1,) * (old.ndim - 1)), new[None], old),
        new_step,
        c.best_step,
    )


def _write_saves(save_ts, saved, index, until, state_at):
    """Write `state_at(t)` for the save times from `index` up to `until` (inclusive)."""

    def more(carry):
        i, _ = carry
        return (i < save_ts.shape[0]) & (save_ts[jnp.minimum(i, save_ts.shape[0] - 1)] <= until)

    def write(carry):
        i, buffer = carry
        return i + 1, buffer.at[i].set(state_at(save_ts[i]))

    index, saved = jax.lax.while_loop(more, write, (index, saved))
    return saved, index


def integrate_peaks(
    term, z0, args, t1, metrics_fn: MetricsFn, options: SolverOptions, *, save_ts=None, **config
) -> PeakRun:
    """Integrate `term` from `z0` over `[0, t1]` with Tsit5 + PID in one while loop, keeping
    the running maxima of `metrics_fn(t, z, args)` (a dict of scalars) located between steps.
    `config`: `PeakLoop`'s configuration (`stop=StopWhenCertain(bounds)` stops once the
    peaks are certain; `events`, `ceilings`, `sampling`, ...); `save_ts` as
    `PeakLoop.integrate`."""
    return PeakLoop(term, metrics_fn, options, **config).integrate(z0, args, t1, save_ts)
