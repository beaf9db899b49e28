"""The leaner step of issue 66, item 3: the prototype `docs/speed.md` (*The leaner step*)
measures. A record of that measurement, not part of the package: it reads the engine's
private pieces as they are at the commit that added it, and replaces one of them while it
traces (`stepping._best_steps`).

    python docs/lean_step_prototype.py paper 512 22528
    python docs/lean_step_prototype.py envelope 1536 53760

(the designs; the records an iteration writes when every attempt is kept, at most; the
kept steps of all lanes together, at most). Each variant runs the same lanes' loop,
outside the `vmap` as `queued_map`'s is (the iteration an index every lane shares), 256
designs in 256 lanes, no queue:

- `today`: the engine's loop, its peak search in each step, `PeakLoop.finish`;
- `lean loop alone`: the quantities at the steps' ends only (their running maxima feed
  the stop test), no rates, no Hermite or sampled maximum, no best step per quantity;
- `lean, every attempt recorded`: that loop, each attempt written at the iteration's
  index, then one pass over every record;
- `lean, kept steps only`: each kept step written to one flat buffer (an exclusive
  cumulative sum of the lanes' kept flags gives each its place), then one pass over
  them, each quantity's largest per lane (`segment_max`), its first step holding it,
  and the engine's own polish there.
"""

from __future__ import annotations

import sys
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import recoil_jax as rj
from recoil_jax._model import stepping
from recoil_jax._model.dense import hermite_max, polish
from recoil_jax._model.equations import initial_state, model_args
from recoil_jax._model.params import params_from_values
from recoil_jax._model.settings import Smoothing, SolverOptions, end_time, with_default_tolerances
from recoil_jax._model.solve import model_loop
from recoil_jax._model.stepping import PeakLoop, _sampled_max
from recoil_jax.apps._bench.speed import bench_designs, envelope_designs

VARIANTS = ("today", "lean loop alone", "lean, every attempt recorded", "lean, kept steps only")


def _the_step(c, step, improve):
    """Stands in for `stepping._best_steps`: the attempt itself, with its mode and verdict."""
    record = dict(t0=c.t, t1=step.t_end, keep=step.keep, **step.dense_info)
    if "mode" in c.best_step:
        record["mode"] = c.mode
    return record


class LeanLoop(PeakLoop):
    """`PeakLoop` without its peak search: the step ends' values, no rates, no maximum
    between them; `best_step` holds the last attempt (`_the_step`)."""

    def _metric_and_rate(self, names, t, z, f, args):
        values = self._vector(names, t, z, args)
        return values, jnp.zeros_like(values)

    def _step_max(self, c, args, step):
        later = step.metric1 > step.metric0
        return jnp.maximum(step.metric0, step.metric1), jnp.where(later, 1.0, 0.0)

    def init(self, z0, args, t1, save_ts=None):
        c = super().init(z0, args, t1, save_ts)
        record = jax.tree.map(lambda x: x[0], c.best_step) | {"keep": jnp.array(False)}
        if c.mode is not None:
            record["mode"] = c.mode
        return eqx.tree_at(lambda c: c.best_step, c, record)

    def step_max(self, record, args, names):
        """The engine's maximum over one recorded step, `(values, s)`: the sampled one on
        the dense polynomial, or the Hermite one from the ends' values and rates."""
        if self.modes is not None:
            args = self.modes.enter(args, record["mode"])
        dense = {k: v for k, v in record.items() if k not in ("mode", "keep")}
        t0, t1 = record["t0"], record["t1"]
        dt = t1 - t0
        if self.sampling.samples:
            interp = self.solver.interpolation_cls(**dense)
            first = self._vector(names, t0, record["y0"], args)
            last = self._vector(names, t1, record["y1"], args)
            return _sampled_max(
                lambda t: self._vector(names, t, interp.evaluate(t), args),
                t0, dt, self.sampling.samples, first, last,
            )  # fmt: skip
        safe = jnp.where(dt > 0, dt, 1.0)
        rate = super()._metric_and_rate
        m0, d0 = rate(names, t0, record["y0"], record["k"][0] / safe, args)
        m1, d1 = rate(names, t1, record["y1"], record["k"][-1] / safe, args)
        return hermite_max(m0, d0 * dt, m1, d1 * dt)


def stacked(columns):
    count = len(next(iter(columns.values())))
    rows = [params_from_values({k: float(v[i]) for k, v in columns.items()}) for i in range(count)]
    return jax.tree.map(lambda *x: jnp.stack([jnp.asarray(a) for a in x]), *rows)


def program(first, variant, iterations, capacity):
    options = with_default_tolerances(first, SolverOptions())
    smoothing = Smoothing()

    def setup(p):
        args = model_args(p, smoothing)
        return initial_state(args), args, end_time(p, options)

    def run(designs):
        one = jax.tree.map(lambda x: x[0], designs)
        loop = model_loop(one, options, structure=model_args(one, smoothing).structure)
        if variant != "today":
            parts = ("stop", "events", "ceilings", "sampling", "crossing", "leading", "modes")
            config = {part: getattr(loop, part) for part in parts}
            loop = LeanLoop(loop.term, loop.metrics_fn, loop.options, **config)
        z0, args, t1 = jax.vmap(setup)(designs)
        lanes = z0.shape[0]
        saved = stepping._best_steps
        if variant != "today":
            stepping._best_steps = _the_step
        try:
            c = jax.vmap(loop.init)(z0, args, t1)
            records = None
            if variant == VARIANTS[2]:
                records = jax.tree.map(
                    lambda x: jnp.zeros((iterations, *x.shape), x.dtype), c.best_step
                )
            elif variant == VARIANTS[3]:
                single = jax.tree.map(lambda x: x[0], c.best_step)
                records = (
                    jax.tree.map(lambda x: jnp.zeros((capacity, *x.shape), x.dtype), single),
                    jnp.zeros(capacity, int),  # each record's lane
                    jnp.array(0),  # records written
                )

            def running(state):
                i, c, _ = state
                return jnp.any(jax.vmap(loop.running)(c)) & (i < iterations)

            def body(state):
                i, c, records = state
                on = jax.vmap(loop.running)(c)
                new = jax.vmap(lambda c, a: loop.body(c, a, check_bounds=(i % 4) == 0))(c, args)
                c = jax.tree.map(
                    lambda n, o: (
                        jnp.where(on.reshape((-1,) + (1,) * (n.ndim - 1)), n, o) if n.ndim else n
                    ),
                    new,
                    c,
                )
                if variant == VARIANTS[2]:
                    step = new.best_step | {"keep": new.best_step["keep"] & on}
                    records = jax.tree.map(
                        lambda r, x: jax.lax.dynamic_update_index_in_dim(r, x, i, 0), records, step
                    )
                elif variant == VARIANTS[3]:
                    flat, lane_of, count = records
                    kept = new.best_step["keep"] & on
                    at = jnp.where(kept, count + jnp.cumsum(kept) - kept, capacity)
                    flat = jax.tree.map(
                        lambda f, x: f.at[at].set(x, mode="drop"), flat, new.best_step
                    )
                    lane_of = lane_of.at[at].set(jnp.arange(lanes), mode="drop")
                    records = (flat, lane_of, count + jnp.sum(kept))
                return i + 1, c, records

            i, final, records = jax.lax.while_loop(running, body, (jnp.array(0), c, records))
        finally:
            stepping._best_steps = saved
        names = final.names
        if variant == VARIANTS[0]:
            best = jax.vmap(loop.finish)(final, args).best
        elif variant == VARIANTS[1]:
            best = final.best
        elif variant == VARIANTS[2]:
            assert isinstance(loop, LeanLoop)

            def lane_max(records, args):
                values = jax.vmap(lambda r: loop.step_max(r, args, names)[0])(records)
                return jnp.max(jnp.where(records["keep"][:, None], values, -jnp.inf), axis=0)

            by_lane = jax.tree.map(lambda x: jnp.moveaxis(x, 0, 1), records)
            best = jax.vmap(lane_max)(by_lane, args)
        else:
            assert isinstance(loop, LeanLoop)
            flat, lane_of, count = records
            lane_args = jax.tree.map(lambda a: a[lane_of], args)
            values, s = jax.vmap(lambda r, a: loop.step_max(r, a, names))(flat, lane_args)
            values = jnp.where((jnp.arange(capacity) < count)[:, None], values, -jnp.inf)
            best = jax.ops.segment_max(values, lane_of, num_segments=lanes)  # (lanes, n)
            # Each quantity's first step holding its largest value, then the polish.
            first = jnp.where(values == best[lane_of], jnp.arange(capacity)[:, None], capacity)
            at = jnp.minimum(jax.ops.segment_min(first, lane_of, num_segments=lanes), capacity - 1)
            steps = {k: v[at] for k, v in flat.items() if k not in ("keep", "mode")}
            quantity = jnp.arange(s.shape[1])[None, :]
            best_time = steps["t0"] + s[at, quantity] * (steps["t1"] - steps["t0"])
            peak_args = None
            if (modes := loop.modes) is not None:
                enter = jax.vmap(modes.enter, in_axes=(None, 0))
                peak_args = jax.vmap(enter)(args, flat["mode"][at])

            def polished(args, best, best_time, steps, peak_args):
                vector = lambda t, z, a: loop._vector(names, t, z, a)  # noqa: E731
                return polish(loop.solver, args, vector, best, best_time, steps,
                              search=loop.sampling.samples > 0, step_args=peak_args)[0]  # fmt: skip

            best = jax.vmap(polished)(args, best, best_time, steps, peak_args)
            best = jnp.where(count > capacity, jnp.nan, best)  # records dropped: no result
        return best, final.num_steps, final.num_attempts, i

    return jax.jit(run)


def main(which: str, iterations: int, capacity: int, size: int = 256) -> None:
    columns = {
        "paper": lambda: bench_designs(size),
        "envelope": lambda: envelope_designs(size),
        "envelope-no-absorber": lambda: envelope_designs(size, absorber=False),
    }[which]()
    designs = stacked(columns)
    first = jax.tree.map(lambda x: x[0], designs)
    programs = {v: program(first, v, iterations, capacity) for v in VARIANTS}
    peaks = {}
    for run in range(3):
        for name, solve in programs.items():
            started = time.perf_counter()
            out = jax.block_until_ready(solve(designs))
            compiled = time.perf_counter() - started
            seconds = []
            for _ in range(2):
                started = time.perf_counter()
                jax.block_until_ready(solve(designs))
                seconds.append(time.perf_counter() - started)
            best, steps, _, done = (np.asarray(x) for x in out)
            wall = min(seconds)
            print(
                f"{which}, {name}, run {run}: {wall * 1e3:.1f} ms, {size / wall:.0f} sims/s, "
                f"steps {steps.mean():.1f} a design (at most {steps.max()}), {done} iterations,"
                f" {1e6 * wall / done / size:.3f} us a lane and iteration"
                + (f", first call {compiled:.1f} s" if run == 0 else ""),
                flush=True,
            )
            peaks[name] = best
    for name in VARIANTS[2:]:
        apart = np.abs(peaks[name] - peaks["today"]) / np.maximum(np.abs(peaks["today"]), 1e-300)
        print(f"{which}, {name}: peaks within {np.nanmax(apart):.2e} of today's (relative), "
              f"NaN {np.isnan(peaks[name]).any()}")  # fmt: skip


if __name__ == "__main__":
    rj.use_avx2_codegen()
    main(sys.argv[1], int(sys.argv[2]), int(sys.argv[3]))
