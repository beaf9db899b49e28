"""Parameter pytrees: defaults, conversions and the error messages for bad input."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import recoil_jax as rj
from recoil_jax._model.equations import model_args


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
        (lambda: rj.Barrel(k=-1.0), "Barrel.k", "valid k >= 0 N/m"),
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
        "Absorber.gap = -0.25 m is invalid (out of range): valid gap >= 0 m, at most "
        "200000 m; documented range 0 to 0.2 m (clearance to wall A)"
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


# --- The firing envelope's parameters (issue 54, envelope.md) ------------------------

#: Every new parameter of the firing envelope at a value off its default.
ENVELOPE_VALUES = dict(
    elevation=35.0,
    friction_force=1500.0,
    friction_coefficient=0.05,
    recuperator_preload=3e4,
    stop_stiffness=2.1e8,
    stop_exponent=1.3,
    stop_damping=0.4,
    buffer_damping=1.5e5,
    buffer_length=0.15,
    mount_mass=8000.0,
    cg_distance=3.2,
    trunnion_height=1.1,
    spade_distance=3.6,
)


def test_envelope_parameters_are_registered_with_their_groups():
    groups = {
        "elevation": ("rails", "deg", 0.0),
        "friction_force": ("rails", "N", 0.0),
        "friction_coefficient": ("rails", "", 0.0),
        "recuperator_preload": ("recuperator", "N", 0.0),
        "stop_stiffness": ("battery_stop", "N/m^n_s", 0.0),
        "stop_exponent": ("battery_stop", "", 1.5),
        "stop_damping": ("battery_stop", "s/m", 0.6),
        "buffer_damping": ("counter_recoil_buffer", "N*s/m", 0.0),
        "buffer_length": ("counter_recoil_buffer", "m", 0.1),
        "mount_mass": ("mount", "kg", 0.0),
        "cg_distance": ("mount", "m", 2.0),
        "trunnion_height": ("mount", "m", 1.2),
        "spade_distance": ("mount", "m", 3.0),
    }
    assert set(groups) == set(ENVELOPE_VALUES)
    for name, (group, unit, default) in groups.items():
        p = rj.PARAMETERS[name]
        assert (p.group, p.unit, p.default) == (group, unit, default), name
        assert p.documented is not None and p.meaning, name  # `wrt` scales by the range
    assert rj.PARAMETERS["elevation"].documented == (0.0, 75.0)
    assert rj.PARAMETERS["friction_coefficient"].documented == (0.0, 0.3)
    # The valid ranges of envelope.md, at their ends.
    rj.Rails(elevation=-10.0)
    rj.Rails(elevation=85.0, friction_coefficient=1.0)
    rj.BatteryStop(stop_exponent=1.0)
    rj.BatteryStop(stop_exponent=2.0, stop_damping=0.0)
    rj.Mount(spade_distance=0.0)


def test_envelope_parameters_round_trip():
    values = {**ENVELOPE_VALUES, "M": 1800.0, "m": 0.0}
    params = rj.params_from_values(values)
    assert float(params.rails.elevation) == 35.0
    assert float(params.recuperator.recuperator_preload) == 3e4
    assert float(params.recuperator.recuperator_force) == 0.0  # a preload alone: F_r's default
    back = {k: float(v) for k, v in rj.params_to_values(params).items()}
    defaults = {n: rj.PARAMETERS[n].default for n in ("recuperator_force", "recuperator_length",
                                                      "polytropic_index")}  # fmt: skip
    barrel = {n: rj.PARAMETERS[n].default for n in ("k", "c_out", "c_ret", "v0")}
    contact = {n: rj.PARAMETERS[n].default for n in ("k_c", "n_c", "lambda_c")}
    assert back == values | defaults | barrel | contact
    # with_values and values_of reach every new name.
    names = tuple(ENVELOPE_VALUES)
    moved = rj.with_values(params, names, [v * 1.01 for v in ENVELOPE_VALUES.values()])
    np.testing.assert_allclose(
        rj.values_of(moved, names), [v * 1.01 for v in ENVELOPE_VALUES.values()], rtol=1e-15
    )
    # Batches: one column per design.
    batch = rj.params_from_values(elevation=np.array([0.0, 35.0, 70.0]), friction_force=1e3)
    assert batch.rails.elevation.shape == (3,)


def test_a_design_without_envelope_names_has_todays_leaves():
    for values in ({}, {"m": 0.0}, {"recuperator_force": 2e3, "pulse_time": 0.004}):
        params = rj.params_from_values(values)
        assert params.rails is None and params.battery_stop is None
        assert params.counter_recoil_buffer is None and params.mount is None
        names = [n for n in rj.params_to_values(params) if rj.PARAMETERS[n].group in
                 ("rails", "battery_stop", "counter_recoil_buffer", "mount")]  # fmt: skip
        assert names == []
    # The paper's design: the same leaves (values, shapes, order) as the groups it had.
    paper = rj.RecoilParams()
    old_groups = (paper.barrel, paper.absorber, paper.contact)
    leaves = jax.tree.leaves(paper)
    expected = [leaf for group in old_groups for leaf in jax.tree.leaves(group)]
    assert len(leaves) == len(expected) == 12
    for a, b in zip(leaves, expected, strict=True):
        assert a is b
    built = jax.tree.leaves(rj.params_from_values({}))
    assert len(built) == len(leaves)
    for a, b in zip(built, leaves, strict=True):
        assert a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b)
    # The structure differs only by the new groups' None fields.
    assert jax.tree.structure(paper).num_leaves == 12


@pytest.mark.parametrize(
    "values, start, fragment",
    [
        ({"elevation": 95.0}, "Rails.elevation = 95 deg", "valid elevation >= -10 and <= 85"),
        ({"elevation": -11.0}, "Rails.elevation = -11 deg", "valid elevation >= -10 and <= 85"),
        ({"friction_force": -1.0}, "Rails.friction_force = -1 N", "valid friction_force >= 0"),
        (
            {"friction_coefficient": -0.1},
            "Rails.friction_coefficient = -0.1",
            "valid friction_coefficient >= 0 and <= 1",
        ),
        (
            {"friction_coefficient": 1.5},
            "Rails.friction_coefficient = 1.5",
            "valid friction_coefficient >= 0 and <= 1",
        ),
        (
            {"recuperator_preload": -5.0},
            "Recuperator.recuperator_preload = -5 N",
            "valid recuperator_preload >= 0",
        ),
        (
            {"stop_stiffness": -1.0},
            "BatteryStop.stop_stiffness = -1",
            "valid stop_stiffness >= 0",
        ),
        ({"stop_exponent": 2.5}, "BatteryStop.stop_exponent = 2.5", "valid stop_exponent >= 1"),
        ({"stop_damping": -0.1}, "BatteryStop.stop_damping = -0.1", "valid stop_damping >= 0"),
        (
            {"buffer_damping": -1.0},
            "CounterRecoilBuffer.buffer_damping = -1",
            "valid buffer_damping >= 0",
        ),
        (
            {"buffer_length": 0.0},
            "CounterRecoilBuffer.buffer_length = 0 m",
            "valid buffer_length > 0",
        ),
        ({"mount_mass": -1.0}, "Mount.mount_mass = -1 kg", "valid mount_mass >= 0"),
        (
            {"mount_mass": 8000.0, "cg_distance": 0.0},
            "Mount.cg_distance = 0 m",
            "valid cg_distance > 0",
        ),
        (
            {"mount_mass": 8000.0, "trunnion_height": -1.0},
            "Mount.trunnion_height = -1 m",
            "valid trunnion_height > 0",
        ),
        (
            {"mount_mass": 8000.0, "spade_distance": -0.5},
            "Mount.spade_distance = -0.5 m",
            "valid spade_distance >= 0",
        ),
    ],
)
def test_envelope_out_of_range_messages(values, start, fragment):
    with pytest.raises(rj.ParameterError) as info:
        rj.params_from_values(values)
    message = str(info.value)
    assert message.startswith(start) and "out of range" in message, message
    assert fragment in message and "\n" not in message, message


def test_a_preload_needs_the_battery_stop():
    expected = (
        "Recuperator.recuperator_preload = 30000 N is invalid: a preload needs the battery "
        "stop to hold the barrel in battery against it; valid recuperator_preload 0 without "
        "a stop, >= 0 N with stop_stiffness > 0"
    )
    with pytest.raises(rj.ParameterError) as info:
        rj.params_from_values(recuperator_preload=3e4)
    assert str(info.value) == expected
    with pytest.raises(rj.ParameterError, match="a preload needs the battery stop"):
        rj.params_from_values(recuperator_preload=3e4, stop_stiffness=0.0)
    with pytest.raises(rj.ParameterError, match=r"recuperator_preload\[1\] = 30000 N"):
        rj.params_from_values(
            recuperator_preload=np.array([0.0, 3e4]), stop_stiffness=np.array([2e8, 0.0])
        )
    with pytest.raises(rj.ParameterError, match="a preload needs the battery stop"):
        rj.RecoilParams(recuperator=rj.Recuperator(recuperator_preload=1.0))
    with pytest.raises(rj.ParameterError, match="a preload needs the battery stop"):
        rj.with_values(rj.params_from_values(recuperator_force=1e3), ("recuperator_preload",),
                       [5.0])  # fmt: skip
    # With the stop, or at zero, it is a design.
    rj.params_from_values(recuperator_preload=3e4, stop_stiffness=2.1e8)
    rj.params_from_values(recuperator_preload=0.0)


def test_a_stop_too_soft_to_hold_the_preload_is_refused():
    """A stop that cannot by itself hold the preload within `recuperator_length` is
    refused before anything compiles (it used to fail in the solve, as a recuperator
    bottomed out). The bound `P·2^−γ / L^n_s` is where the stop alone holds it at `L`:
    with nothing else to help (no recoil spring, level rails), the model's own static
    rest lies just inside `L` at 1.01 times that stiffness."""
    design = {"recuperator_preload": 3.5e4, "recuperator_length": 1.5, "elevation": 0.0}
    least = 3.5e4 * 2.0**-1.3 / 1.5**1.5  # the defaults: gamma 1.3, n_s 1.5
    for stiffness in (1e-300, 1e3, 0.99 * least):
        with pytest.raises(rj.ParameterError) as info:
            rj.params_from_values(design, stop_stiffness=stiffness)
        message = str(info.value)
        assert message.startswith(f"BatteryStop.stop_stiffness = {stiffness:g} N/m^n_s")
        assert f"valid stop_stiffness >= {least:.3g} N/m^n_s" in message
    with pytest.raises(rj.ParameterError, match=r"stop_stiffness\[1\] = 1000 N/m"):
        rj.params_from_values(design, stop_stiffness=np.array([2e8, 1e3]))
    alone = rj.params_from_values(design, k=0.0, stop_stiffness=1.01 * least)
    rest = float(model_args(alone, rj.Smoothing()).rest)
    assert -1.5 < rest < -1.45, rest  # the bound is tight: the stop alone, just inside L
    # Without a preload any stop holds.
    rj.params_from_values(stop_stiffness=1e-300, recuperator_length=1.5)


def test_a_mount_is_heavier_than_its_recoiling_parts():
    with pytest.raises(rj.ParameterError) as info:
        rj.params_from_values(mount_mass=5000.0)
    assert str(info.value) == (
        "Mount.mount_mass = 5000 kg is invalid: a mount lighter than its recoiling parts "
        "cannot carry them; valid mount_mass 0 (no mount) or >= M + m = 7100 kg (the whole "
        "gun on the ground, recoiling parts included)"
    )
    with pytest.raises(rj.ParameterError, match=r"mount_mass\[2\] = 100 kg .* = 7100 kg"):
        rj.params_from_values(mount_mass=np.array([0.0, 8000.0, 100.0]))
    with pytest.raises(rj.ParameterError, match="M \\+ m = 5600 kg"):
        rj.params_from_values(m=0.0, mount_mass=5599.0)
    rj.params_from_values(m=0.0, mount_mass=5600.0)  # exactly M + m
    rj.params_from_values(mount_mass=7100.0)
    rj.params_from_values(mount_mass=0.0)  # no mount
    with pytest.raises(rj.ParameterError, match="lighter than its recoiling parts"):
        rj.with_values(rj.params_from_values(mount_mass=8000.0), ("M",), [7000.0])
    # The mount's geometry without its mass is no mount (a warning on the command line,
    # as for a recuperator_length without a recuperator), and round-trips.
    for values in ({"cg_distance": 3.0}, {"mount_mass": 0.0}):
        params = rj.params_from_values(values)
        assert float(params.mount.mount_mass) == 0.0
        assert rj.params_from_values(rj.params_to_values(params)) is not None


def test_envelope_validation_happens_before_compilation():
    traced = []

    @jax.jit
    def f(x):
        traced.append(1)
        return x

    with pytest.raises(rj.ParameterError):
        f(rj.params_from_values(elevation=95.0).barrel.M)
    assert traced == []
    # Tracers pass the checks across groups (checked when the inputs were built).
    built = jax.jit(lambda p: rj.RecoilParams(recuperator=rj.Recuperator(recuperator_preload=p)))
    assert built(jnp.float64(5.0)).recuperator is not None
