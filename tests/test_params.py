"""Parameter pytrees: defaults, conversions and the error messages for bad input."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import recoil_jax as rj


def test_defaults_are_the_papers():
    p = rj.RecoilParams()
    assert float(p.barrel.M) == 5600 and float(p.barrel.k) == 27500
    assert float(p.barrel.c_out) == 6239 and float(p.barrel.c_ret) == 14050
    assert float(p.barrel.v0) == pytest.approx(6.86 * 564 / 5600, rel=1e-15)
    assert float(p.barrel.v0) == pytest.approx(0.6909, rel=1e-12)
    assert float(p.absorber.k_r) == 13000 and float(p.absorber.c_r) == 3675
    assert float(p.contact.k_c) == 2.1e8 and float(p.contact.n_c) == 1.3
    assert float(p.contact.lambda_c) == 0.6


def test_v0_from_shot():
    barrel = rj.Barrel.from_shot(projectile_mass=6.86, muzzle_velocity=564.0, M=5600.0)
    assert float(barrel.v0) == pytest.approx(0.6909, rel=1e-12)
    heavier = rj.Barrel.from_shot(10.0, 500.0, M=8000.0)
    assert float(heavier.v0) == pytest.approx(0.625) and float(heavier.M) == 8000.0
    with pytest.raises(rj.ParameterError, match="projectile_mass"):
        rj.Barrel.from_shot(-1.0, 564.0)


def test_flat_names_round_trip():
    values = dict(
        M=6000.0,
        k=3e4,
        c_out=6000.0,
        c_ret=1.2e4,
        v0=0.8,
        m=900.0,
        gap=0.03,
        k_r=2e4,
        c_r=1000.0,
        k_c=1e9,
        n_c=1.5,
        lambda_c=0.3,
    )
    p = rj.params_from_values(values)
    back = {k: float(v) for k, v in rj.params_to_values(p).items()}
    assert back == values
    simplified = rj.params_from_values(m=0)
    assert simplified.absorber is None
    assert float(rj.params_to_values(simplified)["m"]) == 0.0


def test_leaves_are_float64_arrays():
    # Python floats would be static under eqx.filter_jit (one compile per value).
    for leaf in jax.tree.leaves(rj.RecoilParams()):
        assert isinstance(leaf, np.ndarray) and leaf.dtype == np.float64


@pytest.mark.parametrize(
    "build, name, fragment",
    [
        (lambda: rj.Barrel(M=0.0), "Barrel.M", "valid M > 0 kg"),
        (lambda: rj.Absorber(m=-5.0), "Absorber.m", "valid m > 0 kg"),
        (lambda: rj.Barrel(k=0.0), "Barrel.k", "valid k > 0 N/m"),
        (lambda: rj.Absorber(k_r=-1.0), "Absorber.k_r", "valid k_r > 0 N/m"),
        (lambda: rj.Contact(k_c=0.0), "Contact.k_c", "valid k_c > 0"),
        (lambda: rj.Barrel(c_out=-1.0), "Barrel.c_out", "valid c_out >= 0"),
        (lambda: rj.Barrel(c_ret=-0.5), "Barrel.c_ret", "valid c_ret >= 0"),
        (lambda: rj.Absorber(c_r=-3.0), "Absorber.c_r", "valid c_r >= 0"),
        (lambda: rj.Absorber(gap=-0.001), "Absorber.gap", "valid gap >= 0 m"),
        (lambda: rj.Contact(n_c=0.9), "Contact.n_c", "valid n_c >= 1"),
        (lambda: rj.Contact(lambda_c=-0.1), "Contact.lambda_c", "valid lambda_c >= 0"),
        (lambda: rj.Barrel(v0=0.0), "Barrel.v0", "valid v0 > 0 m/s"),
        (
            lambda: rj.Smoothing(damping_width=-1e-3),
            "Smoothing.damping_width",
            "valid damping_width >= 0 m/s",
        ),
        (
            lambda: rj.Smoothing(contact_width=-1e-4),
            "Smoothing.contact_width",
            "valid contact_width >= 0 m",
        ),
        (lambda: rj.SolverOptions(t1=0.0), "SolverOptions.t1", "valid t1 > 0 s"),
        (lambda: rj.SolverOptions(t1=-2.0), "SolverOptions.t1", "valid t1 > 0 s"),
    ],
)
def test_out_of_range_messages(build, name, fragment):
    with pytest.raises(rj.ParameterError) as info:
        build()
    message = str(info.value)
    assert message.startswith(name), message
    assert "out of range" in message
    assert fragment in message, message


def test_range_message_gives_value_and_documented_range():
    with pytest.raises(rj.ParameterError) as info:
        rj.Absorber(gap=-0.25)
    assert str(info.value) == (
        "Absorber.gap = -0.25 m is invalid (out of range): valid gap >= 0 m; "
        "documented range 0 to 0.2 m (clearance to wall A)"
    )


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
@pytest.mark.parametrize(
    "build",
    [
        lambda v: rj.Barrel(M=v),
        lambda v: rj.Absorber(gap=v),
        lambda v: rj.Contact(n_c=v),
        lambda v: rj.Smoothing(damping_width=v),
        lambda v: rj.SolverOptions(t1=v),
    ],
)
def test_nan_and_inf_are_rejected(build, bad):
    with pytest.raises(rj.ParameterError, match="must be finite"):
        build(bad)


def test_batched_values_report_the_bad_index():
    with pytest.raises(rj.ParameterError, match=r"Absorber\.gap\[2\] = -0\.01 m"):
        rj.Absorber(gap=np.array([0.0, 0.05, -0.01]))
    ok = rj.Absorber(gap=np.linspace(0.0, 0.2, 5))  # arrays for vmap are fine
    assert ok.gap.shape == (5,)


def test_an_absorber_without_mass_points_to_the_design_without_absorber():
    with pytest.raises(rj.ParameterError, match=r"Absorber\.m = 0 kg: .*absorber=None.*m=0 in"):
        rj.Absorber(m=0.0)
    with pytest.raises(rj.ParameterError, match=r"Absorber\.m\[1\] = 0 kg: .*rj\.sweep"):
        rj.Absorber(m=np.array([500.0, 0.0]))
    with pytest.raises(rj.ParameterError, match=r"Absorber\.m = -1 kg is invalid"):
        rj.Absorber(m=-1.0)  # a negative mass is only out of range
    assert rj.RecoilParams(absorber=None).absorber is None  # what the message says works


def test_not_a_number_and_unknown_names():
    with pytest.raises(rj.ParameterError, match="not a number"):
        rj.Barrel(M="heavy")
    with pytest.raises(rj.ParameterError, match="unknown parameter"):
        rj.params_from_values(mass=3.0)
    with pytest.raises(rj.ParameterError, match="m = 0 selects the simplified model"):
        rj.params_from_values(m=0.0, gap=0.01)
    with pytest.raises(rj.ParameterError, match="max_steps"):
        rj.SolverOptions(max_steps=0)
    with pytest.raises(rj.ParameterError, match="autodiff"):
        rj.SolverOptions(autodiff="sideways")


def test_documented_ranges_are_valid():
    """The ranges the issue requires are inside the valid domain and documented."""
    required = {
        (rj.Absorber, "m"): (10, 5000),
        (rj.Absorber, "gap"): (0, 0.2),
        (rj.Absorber, "k_r"): (1e3, 1e5),
        (rj.Absorber, "c_r"): (0, 2e4),
        (rj.Contact, "k_c"): (1e6, 1e10),
        (rj.Contact, "n_c"): (1, 2),
        (rj.Contact, "lambda_c"): (0, 2),
        (rj.Barrel, "v0"): (0.1, 2),
        (rj.Barrel, "M"): (1e3, 2e4),
    }
    for (cls, name), (lo, hi) in required.items():
        documented = cls.LIMITS[name].documented
        assert documented[0] <= lo and documented[1] >= hi, (cls, name)
        cls(**{name: lo})
        cls(**{name: hi})


def test_validation_happens_before_compilation():
    """Invalid input raises at construction, in plain Python: no jit tracing happens."""
    traced = []

    @jax.jit
    def f(x):
        traced.append(1)
        return rj.peak_metrics(rj.RecoilParams(absorber=rj.Absorber(gap=x)))

    with pytest.raises(rj.ParameterError):
        rj.RecoilParams(absorber=rj.Absorber(gap=-1.0))
    assert traced == []
    # Inside transformations values are tracers: they are not checked (they were checked
    # when the concrete inputs were built).
    assert rj.Absorber(gap=jnp.float64(0.01)).gap is not None


def test_with_values_validates_like_the_constructors():
    params = rj.RecoilParams()
    moved = rj.with_values(params, ("gap", "k"), [0.03, 3e4])
    assert float(moved.absorber.gap) == 0.03 and float(moved.barrel.k) == 3e4
    with pytest.raises(rj.ParameterError, match=r"Absorber\.gap = -0\.1 m is invalid"):
        rj.with_values(params, ("gap",), [-0.1])
    with pytest.raises(rj.ParameterError, match="must be finite"):
        rj.with_values(params, ("k",), [np.nan])
    with pytest.raises(rj.ParameterError, match="unknown parameter 'mass'"):
        rj.with_values(params, ("mass",), [1.0])


def test_with_values_sets_any_orifice_knots_at_once():
    """The knots named go in one update (all of them, or any subset in any order), and
    the others keep their values, also with a batch of designs."""
    knots = np.linspace(1e-3, 4e-3, 6)
    params = rj.params_from_values(
        {"piston_area": 0.01} | {f"orifice_{i}": k for i, k in enumerate(knots)}
    )
    subset = rj.with_values(params, ("orifice_4", "gap", "orifice_1"), [9e-3, 0.02, 8e-3])
    expected = knots.copy()
    expected[[4, 1]] = [9e-3, 8e-3]
    np.testing.assert_array_equal(np.asarray(subset.buffer.orifice), expected)
    assert float(subset.absorber.gap) == 0.02
    every = rj.with_values(params, [f"orifice_{i}" for i in range(6)], knots[::-1])
    np.testing.assert_array_equal(np.asarray(every.buffer.orifice), knots[::-1])
    batch = jax.tree.map(lambda x: jnp.stack([x, x]), params)
    moved = rj.with_values(batch, ("orifice_2",), [7e-3])
    assert moved.buffer.orifice.shape == (2, 6)
    np.testing.assert_array_equal(np.asarray(moved.buffer.orifice[:, 2]), [7e-3, 7e-3])
    np.testing.assert_array_equal(np.asarray(moved.buffer.orifice[:, 3]), knots[[3, 3]])


def test_with_values_mixes_scalar_and_batched_knots():
    """A scalar knot beside a knot given per design, as when each was set on its own."""
    params = rj.params_from_values({"piston_area": 0.01} | {f"orifice_{i}": 2e-3 for i in range(4)})
    batch = jax.tree.map(lambda x: jnp.stack([x, x, x]), params)
    moved = rj.with_values(batch, ("orifice_0", "orifice_3"), [1e-3, jnp.array([4e-3, 5e-3, 6e-3])])
    np.testing.assert_array_equal(np.asarray(moved.buffer.orifice[:, 0]), [1e-3] * 3)
    np.testing.assert_array_equal(np.asarray(moved.buffer.orifice[:, 3]), [4e-3, 5e-3, 6e-3])
    np.testing.assert_array_equal(np.asarray(moved.buffer.orifice[:, 1:3]), 2e-3)
