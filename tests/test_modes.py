"""The stepping loop's modes (`Modes`): a hybrid system's discrete mode carried beside
the state and switched at the exact roots of its guard, against the closed form of a
block on a spring with Coulomb friction (stick and slip), with its derivatives."""

from __future__ import annotations

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import recoil_jax as rj
from recoil_jax._model.lanes import queued_map
from recoil_jax._model.modes import Modes, guard_root
from recoil_jax._model.stepping import Events, PeakLoop, StopWhenCertain, integrate_peaks

# A unit block on a unit spring, with friction F: it slides back and forth about ±F/k,
# each half-swing F/k·2 shorter, and sticks at the first turn within ±F/k.
K, M, V0 = 1.0, 1.0, 1.0


def _field(t, z, args):
    """Held (mode 0): still. Sliding with direction s = ±1: `M a = −k x − s F`."""
    mode = args["mode"]
    sliding = mode != 0
    acceleration = (-args["k"] * z[0] - mode * args["F"]) / M
    return jnp.where(sliding, jnp.stack([z[1], acceleration]), jnp.zeros(2))


def _settle(t, z, args):
    """Moving: sliding its way. At rest: held within the friction's band, else sliding
    the way the spring pushes."""
    push = -args["k"] * z[0]
    at_rest_mode = jnp.where(jnp.abs(push) <= args["F"], 0.0, jnp.sign(push))
    mode = jnp.where(z[1] != 0, jnp.sign(z[1]), at_rest_mode)
    return jnp.where(mode == 0, z.at[1].set(0.0), z), mode


def _guard(t, z, args):
    """Sliding: its speed in its direction. Held: the band's margin."""
    mode = args["mode"]
    return jnp.where(mode != 0, mode * z[1], args["F"] - jnp.abs(args["k"] * z[0]))


def _switch(t, z, args):
    """At a turn or a slip: at rest, then as `_settle` has it."""
    return _settle(t, z.at[1].set(0.0), args)


MODES = Modes(
    enter=lambda args, mode: args | {"mode": mode}, settle=_settle, guard=_guard, switch=_switch
)
OPTIONS = rj.SolverOptions(rtol=1e-10, atol=1e-12, max_steps=4096)


def _metrics(t, z, args):
    return {"x": z[0], "minus_x": -z[0]}


def _solve(friction, t1, stop=None, z0=None, **config):
    args = {"k": jnp.asarray(K), "F": friction, "mode": jnp.asarray(0.0)}
    z0 = jnp.array([0.0, V0]) if z0 is None else z0
    return integrate_peaks(
        diffrax.ODETerm(_field), z0, args, t1, _metrics, OPTIONS, modes=MODES, stop=stop, **config
    )


def _closed_form(friction):
    """The turning points and where the block sticks (the last turn)."""
    a = friction / K
    radius = np.hypot(a, V0 / np.sqrt(K / M))
    turns = [-a + radius]
    while abs(turns[-1]) > a:
        turns.append(2 * a * np.sign(turns[-1]) - turns[-1])
    return np.array(turns), radius


@pytest.mark.parametrize("friction", [0.1, 0.3])
def test_a_block_sticks_where_the_closed_form_has_it_and_stays(friction):
    turns, _ = _closed_form(friction)
    omega = np.sqrt(K / M)
    first = np.arctan2(V0 / omega, friction / K) / omega  # the first turn's time
    stuck = first + (len(turns) - 1) * np.pi / omega
    run = eqx.filter_jit(_solve)(jnp.asarray(friction), 200.0)
    assert run.status == rj.Status.ok
    assert float(run.final_time) == 200.0
    np.testing.assert_allclose(float(run.final_state[0]), turns[-1], rtol=0, atol=1e-9)
    assert float(run.final_state[1]) == 0.0  # held: still, exactly
    assert float(run.final_mode) == 0.0
    # Each peak is at a turn, where either sliding mode holds it (never the held one).
    np.testing.assert_array_equal(np.abs(np.asarray(run.best_mode)), [1.0, 1.0])
    peaks = run.by_name(run.best)
    np.testing.assert_allclose(float(peaks["x"]), turns[0], rtol=1e-9)
    np.testing.assert_allclose(float(peaks["minus_x"]), -min(turns), rtol=1e-9)
    np.testing.assert_allclose(float(run.by_name(run.best_time)["x"]), first, rtol=1e-8)
    # Held, nothing is left to integrate: ~200 s at rest cost a few steps, not a
    # stiff law's thousands. A run to just after the stick takes nearly as many.
    just_after = eqx.filter_jit(_solve)(jnp.asarray(friction), stuck + 1.0)
    assert int(run.num_steps) - int(just_after.num_steps) <= 12


def test_the_switch_times_carry_their_derivatives():
    """The rest position and the first peak's height and time, differentiated in F by
    `jax.jvp` through the loop, against the closed form's derivatives and central
    differences of the solve."""
    friction = 0.1

    def outputs(f):
        run = _solve(f, 60.0)
        return jnp.stack([run.final_state[0], run.by_name(run.best)["x"],
                          run.by_name(run.best_time)["x"]])  # fmt: skip

    solve = eqx.filter_jit(lambda f: jax.jvp(outputs, (f,), (jnp.ones_like(f),)))
    values, tangents = solve(jnp.asarray(friction))
    turns, radius = _closed_form(friction)
    a = friction / K
    # The rest is `(4n+2)a − x1` after 2n+1 half-swings back (here 5), x1 = −a + R.
    half_swings = len(turns) - 1
    assert half_swings == 5
    dx1 = (-1.0 + a / radius) / K
    omega = np.sqrt(K / M)
    expected = np.array([
        ((2 * half_swings) / K - dx1),  # d/dF of 10a − x1
        dx1,
        -(V0 / omega) / (a**2 + (V0 / omega) ** 2) / K / omega,  # d/dF of atan2(v0/ω, a)/ω
    ])  # fmt: skip
    np.testing.assert_allclose(np.asarray(tangents), expected, rtol=1e-6)
    h = 1e-6
    plus, minus = (np.asarray(solve(jnp.asarray(friction + d))[0]) for d in (h, -h))
    np.testing.assert_allclose(np.asarray(tangents), (plus - minus) / (2 * h), rtol=1e-5)
    np.testing.assert_allclose(np.asarray(values)[0], turns[-1], atol=1e-9)


def _half_swings(friction):
    return len(_closed_form(friction)[0]) - 1


def test_the_rest_has_a_kink_where_a_stick_comes_earlier_and_each_side_its_derivative():
    """Where the friction grows past the value at which the block sticks one half-swing
    earlier, its rest `x(F)` has a kink: continuous, its derivative jumping. On each side
    the derivative through the loop is that side's closed form and its central
    differences (the step not crossing the kink)."""
    lower, upper = 0.1, 0.105  # 5 half-swings at the one, 4 at the other
    assert (_half_swings(lower), _half_swings(upper)) == (5, 4)
    for _ in range(60):  # the kink, by bisection on the closed form
        middle = 0.5 * (lower + upper)
        lower, upper = (middle, upper) if _half_swings(middle) == 5 else (lower, middle)
    kink = 0.5 * (lower + upper)

    def rest(f):
        return _solve(f, 80.0).final_state[0]

    solve = eqx.filter_jit(lambda f: jax.jvp(rest, (f,), (jnp.ones_like(f),)))
    offset, h = 2e-3, 1e-6
    slopes = {}
    for side, friction in (("5 half-swings", kink - offset), ("4 half-swings", kink + offset)):
        turns, radius = _closed_form(friction)
        half_swings = len(turns) - 1
        a = friction / K
        # The rest is `2n·a − x1` (n half-swings back, n odd) or `x1 − 2n·a` (n even).
        parity = -1.0 if half_swings % 2 else 1.0
        expected = parity * ((-1.0 + a / radius) / K) - parity * 2 * half_swings / K
        value, slope = solve(jnp.asarray(friction))
        np.testing.assert_allclose(float(value), turns[-1], atol=1e-9, err_msg=side)
        np.testing.assert_allclose(float(slope), expected, rtol=1e-6, err_msg=side)
        plus, minus = (float(solve(jnp.asarray(friction + d))[0]) for d in (h, -h))
        np.testing.assert_allclose(float(slope), (plus - minus) / (2 * h), rtol=1e-5, err_msg=side)
        slopes[side] = float(slope)
    # Continuous across the kink (to the slopes' reach), its derivative not.
    across = float(solve(jnp.asarray(kink + offset))[0] - solve(jnp.asarray(kink - offset))[0])
    assert abs(across) <= offset * (abs(slopes["5 half-swings"]) + abs(slopes["4 half-swings"]))
    assert abs(slopes["5 half-swings"] - slopes["4 half-swings"]) > 1.0


def test_a_state_at_a_fixed_time_has_its_derivatives_mid_slide():
    """Cut at t1 = 3 s, between the first turn and the second, the block slides back about
    +a: `x = a + (x1 − a) cos ω(t − t_turn)`. The end time does not move with F, so the
    end state's tangents are the closed form's at a fixed time (the first turn's time
    moves with F), and the end time's tangent is 0."""
    friction, t1 = 0.1, 3.0

    def ends(f):
        run = _solve(f, t1)
        return jnp.concatenate([run.final_state, run.final_time[None]])

    values, tangents = eqx.filter_jit(lambda f: jax.jvp(ends, (f,), (jnp.ones_like(f),)))(
        jnp.asarray(friction)
    )
    a, omega = friction / K, np.sqrt(K / M)
    turns, radius = _closed_form(friction)
    turn = np.arctan2(V0 / omega, a) / omega
    d_turn = -(V0 / omega) / (a**2 + (V0 / omega) ** 2) / K / omega
    d_x1 = (-1.0 + a / radius) / K
    phase = omega * (t1 - turn)
    x = a + (turns[0] - a) * np.cos(phase)
    v = -(turns[0] - a) * omega * np.sin(phase)
    dx = (
        (1 - np.cos(phase)) / K
        + d_x1 * np.cos(phase)
        + (turns[0] - a) * omega * np.sin(phase) * d_turn
    )
    dv = (
        -(d_x1 - 1 / K) * omega * np.sin(phase) + (turns[0] - a) * omega**2 * np.cos(phase) * d_turn
    )
    np.testing.assert_allclose(np.asarray(values)[:2], [x, v], rtol=1e-8)
    np.testing.assert_allclose(np.asarray(tangents), [dx, dv, 0.0], rtol=1e-6, atol=1e-9)


def test_a_stop_when_certain_sees_the_mode():
    """The loop's other functions get the arguments in the mode: a bound that says
    'certain' only once the block is held stops the run then."""

    def bounds(z, args, t, t1):
        certain = jnp.where(args["mode"] == 0, -jnp.inf, jnp.inf)
        return {"x": certain, "minus_x": certain}

    run = eqx.filter_jit(lambda f: _solve(f, 200.0, stop=StopWhenCertain(bounds)))(jnp.asarray(0.1))
    turns, _ = _closed_form(0.1)
    assert run.status == rj.Status.ok and float(run.final_time) < 20.0
    np.testing.assert_allclose(float(run.final_state[0]), turns[-1], atol=1e-9)


def test_a_guard_root_is_on_the_bracket_and_never_its_start():
    root = guard_root(lambda t: 0.3 - t, jnp.asarray(0.0), jnp.asarray(1.0))
    assert float(root) == pytest.approx(0.3, abs=1e-15)
    # A guard already at 0 at the start: the root is just after it, a step of some length.
    at_start = guard_root(lambda t: -t, jnp.asarray(0.0), jnp.asarray(1.0))
    assert float(at_start) == 1e-12


def test_a_held_block_struck_by_a_load_slides_as_if_fired_then():
    """A load's jump (`Events`) meets a held block: the mode is settled afresh after it
    (`Modes.settle`), and the block slides as one fired at the stop's time."""
    strike = 1.5
    events = Events(
        stops=lambda args: jnp.array([strike]),
        jump=lambda before, t, z, f_before, args: z.at[1].add(V0),
        restart=lambda args: jnp.asarray(1e-3),
    )
    run = eqx.filter_jit(lambda f: _solve(f, 60.0, z0=jnp.zeros(2), events=events))(
        jnp.asarray(0.1)
    )
    fired = eqx.filter_jit(_solve)(jnp.asarray(0.1), 60.0)
    turns, _ = _closed_form(0.1)
    np.testing.assert_allclose(float(run.final_state[0]), turns[-1], atol=1e-9)
    np.testing.assert_allclose(np.asarray(run.best), np.asarray(fired.best), rtol=1e-9)
    np.testing.assert_allclose(
        np.asarray(run.best_time), np.asarray(fired.best_time) + strike, rtol=1e-9
    )


def test_lanes_carry_the_modes_as_a_loop_of_single_solves():
    """Through the lane scheduler (`queued_map`, 2 lanes for 5 designs, refilled as they
    finish), each design's peaks and end state are its single solve's (to 1e-12: a
    vectorised operation may round its last bit otherwise)."""
    frictions = jnp.array([0.05, 0.1, 0.2, 0.3, 0.45])
    loop = PeakLoop(diffrax.ODETerm(_field), _metrics, OPTIONS, modes=MODES)

    def setup(friction):
        args = {"k": jnp.asarray(K), "F": friction, "mode": jnp.asarray(0.0)}
        return jnp.array([0.0, V0]), args, jnp.asarray(30.0)

    def post(friction, args, run):
        return run.best, run.final_state, run.num_steps

    batched = eqx.filter_jit(lambda fs: queued_map(loop, setup, post, fs, lanes=2))(frictions)
    for i, friction in enumerate(frictions):
        single = eqx.filter_jit(_solve)(friction, 30.0)
        np.testing.assert_allclose(np.asarray(batched[0][i]), np.asarray(single.best), rtol=1e-12)
        np.testing.assert_allclose(
            np.asarray(batched[1][i]), np.asarray(single.final_state), rtol=0, atol=1e-12
        )
        # (A last bit can tip a step-size decision: the same steps to 1 %.)
        assert abs(int(batched[2][i]) - int(single.num_steps)) <= 0.01 * int(single.num_steps)
