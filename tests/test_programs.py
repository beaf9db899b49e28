"""The compiled programs a process keeps are bounded (`rj.set_max_programs`): the least
recently used is dropped, and its memory (the memory regions XLA maps for it, of which
Linux allows a process about 65,000) is freed."""

import gc
import weakref

import jax.numpy as jnp
import numpy as np
import pytest

import recoil_jax as rj
import recoil_jax._cache as cache


@pytest.fixture
def limit():
    """Set the limit for one test; the suite's own limit comes back after it."""
    previous = rj.set_max_programs(32)
    yield rj.set_max_programs
    rj.set_max_programs(previous)


def test_least_recently_used_programs_are_dropped(limit):
    traces = []

    @rj.structure_jit
    def total(x, power):
        traces.append((x.shape, power))  # runs once per compilation (trace)
        return jnp.sum(x**power)

    limit(3)
    for n in (1, 2, 3):
        assert float(total(jnp.ones(n), 2)) == n
    assert len(traces) == 3 and rj.live_programs() <= 3
    total(jnp.ones(1), 2)  # used again: no new program, and now the most recent
    assert len(traces) == 3
    dropped = [weakref.ref(p) for k, p in cache._programs.items() if k[0] is total.__wrapped__]
    total(jnp.ones(4), 2)  # a fourth structure: shape 2, the least recently used, goes
    assert len(traces) == 4 and rj.live_programs() == 3
    total(jnp.ones(1), 2)
    total(jnp.ones(3), 2)
    assert len(traces) == 4  # kept
    total(jnp.ones(2), 2)
    assert len(traces) == 5  # compiled again
    total(jnp.ones(2), 3)  # a non-array argument is part of the structure
    assert traces[-1] == ((2,), 3)
    # Nothing but the cache held a dropped program: it is freed.
    gc.collect()
    assert sum(ref() is None for ref in dropped) >= 2
    with pytest.raises(rj.ParameterError, match="max programs"):
        limit(0)


def _mappings() -> int:
    with open("/proc/self/maps") as maps:
        return sum(1 for _ in maps)


def _design(knots: int) -> rj.RecoilParams:
    values = {f"orifice_{i}": 4e-4 for i in range(knots)}
    return rj.params_from_values(values | {"piston_area": 0.01, "orifice_length": 0.2})


@pytest.mark.slow
def test_many_structures_stay_below_a_bound_of_memory_mappings(limit):
    """Solves of 6 model structures (2 to 7 orifice knots) in one process, 2 programs
    kept: the memory mappings after all of them are about those of 2 programs, not 6."""
    limit(2)
    gc.collect()
    base = _mappings()
    rj.peaks(_design(2))
    gc.collect()
    one = _mappings() - base  # what one structure's program maps
    for knots in range(3, 8):
        assert np.isfinite(float(rj.peaks(_design(knots)).peak_anchoring_force))
    gc.collect()
    grown = _mappings() - base
    assert rj.live_programs() <= 2
    # Unbounded, 6 programs would map about 6 times one; bounded, about 2.
    assert one > 100, one
    assert grown < 3.5 * one, (one, grown)
