"""The sticking law's first form (issue 54; `docs/model.md`, *Sticking*), on its own,
as it was measured before the model used it: friction `F_f = clamp(N + M·v/τ, −F_max,
F_max)`, N the net force on the barrel from everything but friction. (The model's law
holds the same way and turns at `v = 0` when the barrel reverses:
`tests/test_envelope_model.py` tests it against the closed form and the reference.) On a Coulomb
oscillator (closed form: half-cycles about ±F/k, the amplitude falling by 2F/k each, at
rest for good once a turning point lies within |x| ≤ F/k) it holds (no creep after the
stick), comes to rest within (ωτ)²-order of the exact place, and a bristle state (the
LuGre/Dahl kind, friction from the state alone) is measured beside it."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import recoil_jax  # noqa: F401  (float64 on import, as for the model)

M, K, F_MAX, V0, T1 = 5600.0, 27500.0, 2000.0, 1.0, 6.0


def coulomb_rest() -> tuple[float, float]:
    """Where and when the oscillator sticks for good, in closed form."""
    w = np.sqrt(K / M)
    x, v, t, direction = 0.0, V0, 0.0, 1.0
    while True:
        centre = -direction * F_MAX / K  # sliding with direction·v > 0
        amplitude = np.hypot(x - centre, v / w)
        phase = np.arctan2(-v / w, x - centre)
        dt = (-phase) % np.pi or np.pi
        t += dt / w
        x, v = centre + amplitude * np.cos(phase + dt), 0.0  # a turning point
        if abs(K * x) <= F_MAX:
            return x, t
        direction = -np.sign(x)


def relaxation_friction(net, v, tau, width=0.0):
    """The chosen law, its clamp smoothed by softplus over `width` (N); 0: exact."""
    u = net + M * v / tau
    if width == 0.0:
        return jnp.clip(u, -F_MAX, F_MAX)
    soft = lambda z: width * jax.nn.softplus(z / width)  # noqa: E731
    return u - soft(u - F_MAX) + soft(-F_MAX - u)


def _solve(field, y0):
    ts = jnp.linspace(0.0, T1, 601)
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(field), diffrax.Tsit5(), 0.0, T1, None, jnp.asarray(y0),
        stepsize_controller=diffrax.PIDController(rtol=1e-8, atol=1e-10),
        max_steps=400_000, saveat=diffrax.SaveAt(ts=ts),
    )  # fmt: skip
    return np.asarray(sol.ys), int(sol.stats["num_steps"])


@pytest.mark.parametrize(("tau", "width", "error"), [(1e-3, 0.0, 2e-6), (1e-3, 10.0, 2e-6),
                                                     (3e-3, 0.0, 2e-5)])  # fmt: skip
def test_the_relaxation_law_holds_and_rests_where_coulomb_does(tau, width, error):
    x_rest, t_rest = coulomb_rest()
    assert x_rest == pytest.approx(0.0520071, abs=1e-7) and t_rest == pytest.approx(
        4.8898, abs=1e-4
    )

    def field(t, y, args):
        x, v = y
        net = -K * x
        return jnp.stack([v, (net - relaxation_friction(net, v, tau, width)) / M])

    ys, steps = _solve(field, [0.0, V0])
    stuck = int(t_rest / T1 * 600) + 10
    assert abs(ys[-1, 0] - x_rest) < error  # measured 1.12 µm at 1 ms, 10.1 µm at 3 ms
    assert abs(ys[-1, 0] - ys[stuck, 0]) < 1e-9  # no creep once stuck
    assert abs(ys[-1, 1]) < 1e-9 and steps < 1500


@pytest.mark.slow
def test_a_bristle_state_is_slower_and_further_off():
    """The alternative, friction from a bristle deflection z (no net force needed):
    `F_f = σ0·z + σ1·ż`, `ż = v − σ0·|v|·z/F_max`, critically damped. Stiff enough to hold
    within microns it is stiff to step, and it still rests far off: measured 2.5 mm off
    in 25,000 steps at σ0 = 1e8 N/m, against the relaxation law's 1.1 µm in ~700."""
    x_rest, _ = coulomb_rest()
    s0 = 1e8
    s1 = 2.0 * np.sqrt(s0 * M)

    def field(t, y, args):
        x, v, z = y
        dz = v - s0 * jnp.abs(v) * z / F_MAX
        return jnp.stack([v, (-K * x - s0 * z - s1 * dz) / M, dz])

    ys, steps = _solve(field, [0.0, V0, 0.0])
    assert abs(ys[-1, 0] - x_rest) > 1e-3 and steps > 10_000
