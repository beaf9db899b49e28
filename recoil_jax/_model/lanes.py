"""The lane scheduler: many designs through one vmapped stepping loop, each lane taking the
next design as soon as its own has finished."""

from __future__ import annotations

from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp

from .._model.stepping import PeakLoop

__all__ = ["queued_map"]

#: The lanes test whether their peaks are certain (`PeakLoop`'s bounds) at every
#: `BOUNDS_EVERY`-th iteration only, all at the same one, so that the other iterations
#: skip the bounds (a `cond` on a flag the lanes share). Lanes are loaded at those
#: iterations too, so a design is tested at its attempts 0, 4, 8, … whatever else is in
#: the batch: it ends a few attempts after a solve tested at every step would (78.3
#: against 76.7 steps on the bench's designs), with the same peaks, for 13 % more sims/s
#: on the paper's model and 10 % on the hardware designs (`docs/speed.md`).
BOUNDS_EVERY = 4


class _Lanes(NamedTuple):
    state: Any  # each lane's loop carry (leading axis: lanes)
    args: Any  # each lane's model arguments
    design: jax.Array  # (lanes,) the design in each lane, -1 when idle
    next_design: jax.Array  # the next design to load
    finals: Any  # each design's final carry (leading axis: designs)
    done: jax.Array  # designs finished
    iteration: jax.Array


def queued_map(loop: PeakLoop, setup, post, designs, lanes: int, count=None):
    """`jax.vmap(lambda d: post(d, loop.finish(solve(*setup(d)))))(designs)`, but with
    `lanes` designs in flight at a time, each lane taking the next design as soon as its
    own has finished (refilled in groups of at least `lanes // 16`), and with the peaks
    tested for certainty at every `BOUNDS_EVERY`-th attempt of a design rather than at
    each (the same peaks; a few more steps).

    A plain `vmap` of the stepping loop runs every member for as many steps as the
    slowest one needs; over random designs that used under a third of the lanes' steps.

    `setup(design) -> (z0, args, t1)`; `post(design, args, run) -> result`. `designs`: a
    pytree with a leading axis `N`. `count` (traced, default `N`): only the first `count`
    designs are solved (the rest pad a batch to a shape already compiled; their results
    are meaningless). Not vmappable; jit it."""
    n = jax.tree.leaves(designs)[0].shape[0]
    solved = n if count is None else jnp.minimum(count, n)
    lanes = min(lanes, n)
    queue = _Queue(loop, setup, designs, n, solved, lanes)

    # Every lane starts idle; the first refill loads the first `lanes` designs (so the
    # setup is traced once, inside the refill).
    lane_state, lane_args = jax.tree.map(
        lambda x: jnp.zeros((lanes, *x.shape), x.dtype), jax.eval_shape(queue.start, 0)
    )
    finals = jax.tree.map(lambda x: jnp.zeros((n, *x.shape[1:]), x.dtype), lane_state)
    zero = jnp.array(0)
    carry = _Lanes(lane_state, lane_args, jnp.full(lanes, -1), zero, finals, zero, zero)
    finals = jax.lax.while_loop(lambda c: c.done < solved, queue.step, carry).finals

    def finish(design, final):
        _, args, _ = setup(design)
        return post(design, args, loop.finish(final, args))

    return jax.vmap(finish)(designs, finals)


class _Queue:
    """The designs of a `queued_map` waiting for the lanes, and the step of its while
    loop (`step`): `N` designs (`n`), of which the first `solved` are solved by `loop`
    from `setup(design)`, with lanes refilled in groups of at least `threshold`."""

    def __init__(self, loop: PeakLoop, setup, designs, n: int, solved, lanes: int):
        self.loop, self.setup, self.designs = loop, setup, designs
        self.n, self.solved = n, solved
        self.threshold = max(1, lanes // 16)

    def start(self, index):
        """The loop's first carry and the model arguments of the design `index`."""
        z0, args, t1 = self.setup(jax.tree.map(lambda x: x[index], self.designs))
        return self.loop.init(z0, args, t1), args

    def running(self, c):
        """Whether a lane's design is still running (within its attempts)."""
        return self.loop.running(c) & (c.num_attempts < self.loop.options.max_steps)

    def refill(self, state, args, index, next_index, aligned):
        """Load the next designs into the idle lanes (`index < 0`), at a checking
        iteration (`aligned`) only, so that each design's checks fall on its own attempts
        0, 4, 8, … whatever shares the batch with it; and only once at least `threshold`
        lanes are idle, or every lane is. Returns `(state, args, index, next_index)`."""
        solved = self.solved
        idle = index < 0
        new_index = next_index + jnp.cumsum(idle) - 1
        fill = idle & (new_index < solved)
        count = jnp.sum(fill)

        def load(operands):
            state, args, index, next_index = operands
            fresh_state, fresh_args = jax.vmap(self.start)(jnp.where(fill, new_index, 0))

            def pick(new, old):
                return jnp.where(fill.reshape((-1,) + (1,) * (new.ndim - 1)), new, old)

            state = jax.tree.map(pick, fresh_state, state)
            args = jax.tree.map(pick, fresh_args, args)
            return state, args, jnp.where(fill, new_index, index), next_index + count

        now = aligned & ((count >= self.threshold) | ((count > 0) & ~jnp.any(index >= 0)))
        return jax.lax.cond(now, load, lambda operands: operands, (state, args, index, next_index))

    def step(self, carry: _Lanes) -> _Lanes:
        """One iteration: refill the idle lanes, attempt one step in every lane, and
        move the designs that finished to `finals`, emptying their lanes."""
        state, args, index, next_index, finals, done, iteration = carry
        check = iteration % BOUNDS_EVERY == 0
        state, args, index, next_index = self.refill(state, args, index, next_index, check)
        # Every lane holding a design is still running: a lane is emptied the moment its
        # design finishes, and a freshly loaded one starts at t = 0 < t1.
        active = index >= 0
        # An idle lane's `made_jump` (its design ended on a stop's step) would otherwise
        # make every lane evaluate a fresh first stage until the lane is loaded again.
        state = eqx.tree_at(lambda s: s.made_jump, state, state.made_jump & active)
        stepped = jax.vmap(lambda s, a: self.loop.body(s, a, check_bounds=check))(state, args)
        state = jax.tree.map(
            lambda new, old: jnp.where(active.reshape((-1,) + (1,) * (new.ndim - 1)), new, old),
            stepped,
            state,
        )
        finished = active & ~jax.vmap(self.running)(state)
        slot = jnp.where(finished, index, self.n)  # out of range: dropped
        finals = jax.tree.map(lambda buf, x: buf.at[slot].set(x, mode="drop"), finals, state)
        done = done + jnp.sum(finished)
        index = jnp.where(finished, -1, index)
        return _Lanes(state, args, index, next_index, finals, done, iteration + 1)
