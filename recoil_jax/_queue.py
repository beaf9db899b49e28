"""The lane scheduler: many designs through one vmapped stepping loop, each lane taking the
next design as soon as its own has finished."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ._stepping import PeakLoop

__all__ = ["queued_map"]


def queued_map(loop: PeakLoop, setup, post, designs, lanes: int, count=None):
    """`jax.vmap(lambda d: post(d, loop.finish(solve(*setup(d)))))(designs)`, but with
    `lanes` designs in flight at a time, each lane taking the next design as soon as its
    own has finished (refilled in groups of at least `lanes // 16`).

    A plain `vmap` of the stepping loop runs every member for as many steps as the
    slowest one needs; over random designs that used under a third of the lanes' steps.

    `setup(design) -> (z0, args, t1)`; `post(design, args, run) -> result`. `designs`: a
    pytree with a leading axis `N`. `count` (traced, default `N`): only the first `count`
    designs are solved (the rest pad a batch to a shape already compiled; their results
    are meaningless). Not vmappable; jit it."""
    n = jax.tree.leaves(designs)[0].shape[0]
    solved = n if count is None else jnp.minimum(count, n)
    lanes = min(lanes, n)
    max_steps = loop.options.max_steps

    def take(index):
        return jax.tree.map(lambda x: x[index], designs)

    def start(index):
        z0, args, t1 = setup(take(index))
        return loop.init(z0, args, t1), args

    # Every lane starts idle; the first refill loads the first `lanes` designs (so the
    # setup is traced once, inside the refill).
    lane_state, lane_args = jax.tree.map(
        lambda x: jnp.zeros((lanes, *x.shape), x.dtype), jax.eval_shape(start, 0)
    )
    finals = jax.tree.map(lambda x: jnp.zeros((n, *x.shape[1:]), x.dtype), lane_state)
    carry = (lane_state, lane_args, jnp.full(lanes, -1), jnp.array(0), finals, jnp.array(0))
    threshold = max(1, lanes // 16)

    def running(c):
        return loop.running(c) & (c.num_attempts < max_steps)

    def cond(carry):
        return carry[-1] < solved

    def refill(state, args, index, next_index):
        idle = index < 0
        new_index = next_index + jnp.cumsum(idle) - 1
        fill = idle & (new_index < solved)
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
        return jax.lax.cond(now, load, lambda operands: operands, (state, args, index, next_index))

    def body(carry):
        state, args, index, next_index, finals, done = carry
        state, args, index, next_index = refill(state, args, index, next_index)
        # Every lane holding a design is still running: a lane is emptied the moment its
        # design finishes, and a freshly loaded one starts at t = 0 < t1.
        active = index >= 0
        stepped = jax.vmap(loop.body)(state, args)
        state = jax.tree.map(
            lambda new, old: jnp.where(active.reshape((-1,) + (1,) * (new.ndim - 1)), new, old),
            stepped,
            state,
        )
        finished = active & ~jax.vmap(running)(state)
        slot = jnp.where(finished, index, n)  # out of range: dropped
        finals = jax.tree.map(lambda buf, x: buf.at[slot].set(x, mode="drop"), finals, state)
        done = done + jnp.sum(finished)
        index = jnp.where(finished, -1, index)
        return state, args, index, next_index, finals, done

    finals = jax.lax.while_loop(cond, body, carry)[4]

    def finish(design, final):
        _, args, _ = setup(design)
        return post(design, args, loop.finish(final, args))

    return jax.vmap(finish)(designs, finals)
