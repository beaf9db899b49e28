"""The reference solver's revision 2 of the firing envelope (`envelope.md`): the static
rest in the battery stop, the unfired gun that stays still there, the stability margin
net of the recoiling parts' axial weight, and the pull on the mount, against facts
computed here by hand (no JAX)."""

import math

import numpy as np
import pytest
import scipy.optimize
from test_reference_envelope import HOWITZER as HAND, SLAMMING

from recoil_jax._model.reference import (
    GRAVITY,
    reference_history,
    reference_peaks,
    reference_rest,
)

g = GRAVITY

#: Issue 54's hand design of the light howitzer: no recoil spring, a 30 kN preload on a
#: stop, a counter-recoil buffer it returns into at speed, and its mount.
HOWITZER = HAND | SLAMMING

ABSORBER = dict(m=200.0, gap=0.05, k_r=5e4, c_r=1e3)


def weight(design):
    """(M + m) g sin θ, the recoiling parts' axial weight (N)."""
    return (design["M"] + design.get("m", 0.0)) * g * math.sin(math.radians(design["elevation"]))


# --- the static rest --------------------------------------------------------------------

#: A preloaded stop with a gas spring, a recoil spring and an absorber: every term of
#: the balance at values of its own.
PRELOADED = dict(
    M=2500.0,
    k=4.0e4,
    m=300.0,
    gap=0.05,
    k_r=6e4,
    recuperator_preload=5.0e4,
    recuperator_force=8.0e3,
    recuperator_length=1.4,
    polytropic_index=1.25,
    stop_stiffness=3.0e8,
    stop_exponent=1.3,
)


def balance(design, x):
    """k_s (−x)^n_s − [P (L/(L−x))^γ + F_r ((L/(L−x))^γ − 1) + k x − W], N: zero at rest."""
    ratio = (design["recuperator_length"] / (design["recuperator_length"] - x)) ** design[
        "polytropic_index"
    ]
    held = (
        design["recuperator_preload"] * ratio
        + design["recuperator_force"] * (ratio - 1.0)
        + design["k"] * x
        - weight(design)
    )
    return design["stop_stiffness"] * (-x) ** design["stop_exponent"] - held


@pytest.mark.parametrize("elevation", [0.0, 35.0, 70.0])
def test_the_rest_balances_the_preload_against_the_stop_and_the_weight(elevation):
    design = PRELOADED | {"elevation": elevation}
    x_r = reference_rest(design)
    assert -0.01 < x_r < 0.0
    # The balance by hand: each force is ~5e4 N; the stop's stiffness ~1e7 N/m puts
    # one rounding of x_r (4e-19 m) at ~1e-11 N.
    assert abs(balance(design, x_r)) <= 1e-8
    # And the root by hand, to within rounding.
    root = scipy.optimize.brentq(lambda x: balance(design, x), -0.1, 0.0, xtol=1e-18)
    assert x_r == pytest.approx(root, abs=1e-17)
    # The solve starts there, the absorber hanging at its sag on the barrel.
    assert reference_peaks(design, t1=0.01)["rest_position"] == x_r
    start = reference_history(design, np.array([0.0]))
    sag = design["m"] * g * math.sin(math.radians(elevation)) / design["k_r"]
    assert start["x_M"][0] == x_r and start["x_m"][0] == x_r + sag
    assert start["v_m"][0] == 0.0


def test_the_absorber_counts_in_the_weight_the_rest_holds():
    design = PRELOADED | {"elevation": 60.0}
    alone = {k: v for k, v in design.items() if k not in ("gap", "k_r")} | {"m": 0.0}
    assert abs(balance(alone, reference_rest(alone))) <= 1e-8
    # Heavier on the rails, the barrel sits less deep in the stop.
    assert reference_rest(alone) < reference_rest(design) < 0.0


def test_gravity_alone_presses_the_barrel_into_the_stop_below_the_horizontal():
    """At −5° the axial weight points forward: `F_AN(0, 0) = 0 > W`, a rest in the stop
    with no preload (k_s δ^n_s = −W − k δ)."""
    design = dict(M=1800.0, m=0.0, elevation=-5.0, stop_stiffness=1e9, k=27500.0)
    x_r = reference_rest(design)
    W = weight(design)
    assert x_r < 0.0
    assert 1e9 * (-x_r) ** 1.5 == pytest.approx(27500.0 * x_r - W, rel=1e-12)


@pytest.mark.parametrize(
    "design",
    [
        {},  # the paper's model
        {"elevation": 35.0},  # no stop: the barrel sags (or friction holds it)
        {"elevation": 35.0, "friction_force": 5e4},
        {"stop_stiffness": 1e9},  # a stop without a preload, level: nothing to hold
        {"stop_stiffness": 1e9, "elevation": 35.0},  # gravity pulls it off the stop
        # A preload below the axial weight (1800 kg at 70°: 16.6 kN)
        {
            "M": 1800.0,
            "m": 0.0,
            "stop_stiffness": 1e9,
            "recuperator_preload": 1.6e4,
            "elevation": 70.0,
        },
    ],
)
def test_without_a_stop_or_a_preload_above_the_weight_the_rest_is_battery(design):
    assert reference_rest(design) == 0.0
    ref = reference_peaks(design, t1=0.5)
    assert ref["rest_position"] == 0.0
    assert reference_history(design, np.array([0.0]))["x_M"][0] == 0.0


# --- the unfired gun --------------------------------------------------------------------

UNFIRED = dict(
    M=1800.0,
    v0=1e-9,  # an impulse load: the barrel barely moves
    m=0.0,
    recuperator_preload=6e4,
    stop_stiffness=1e9,
    mount_mass=8000.0,
)


@pytest.mark.parametrize("absorber", [False, True])
@pytest.mark.parametrize("elevation", [0.0, 35.0, 70.0])
def test_a_gun_that_is_not_fired_stays_still_at_its_rest(elevation, absorber):
    """envelope.md: as v0 → 0 every state stays at its rest, F_AN = (M + m) g sin θ,
    no pull, and the stability margin 1 at every elevation (revision 1 started the
    barrel out of the stop: 60 kN on the mount, a quarter of the margin, unfired)."""
    design = UNFIRED | {"elevation": elevation} | (ABSORBER if absorber else {})
    ref = reference_peaks(design, t1=2.0)
    W = weight(design)
    assert ref["status"] == "ok" and ref["rest_position"] < 0.0
    assert ref["stability_margin"] == pytest.approx(1.0, abs=1e-6)
    assert 0.0 <= ref["peak_pull_force"] <= 1.0
    if elevation > 0:  # F_AN stays near the weight: never a pull
        assert ref["peak_pull_force"] == 0.0
    assert ref["peak_anchoring_force"] == pytest.approx(W, rel=1e-6, abs=1e-3)
    assert ref["peak_mount_load"] == pytest.approx(W, rel=1e-6, abs=1e-3)
    assert abs(ref["peak_displacement"]) <= 1e-9
    assert abs(ref["residual_displacement"]) <= 1e-9
    assert ref["peak_contact_force"] == 0.0


@pytest.mark.parametrize("elevation", [0.0, 35.0, 70.0])
def test_a_barrel_held_by_friction_at_its_rest_stays_held_under_a_feeble_pulse(elevation):
    """A pulse load starts the barrel at rest (v_M = 0): there the net force on it is 0,
    so friction holds it from t = 0; a pulse far inside the friction band never moves it,
    and friction takes the pulse: F_AN = F_b + (M + m) g sin θ."""
    design = (
        UNFIRED
        | dict(elevation=elevation, v0=1e-6, pulse_time=0.004, friction_force=1500.0)
        | ABSORBER
    )
    ref = reference_peaks(design, t1=1.0)
    W = weight(design)
    assert ref["sticks"] == [0.0] and ref["slips"] == []
    assert ref["peak_displacement"] == 0.0 and ref["residual_displacement"] == 0.0
    peak_pulse = 1800.0 * 1e-6 / 0.004 / math.e  # at one pulse time
    assert ref["peak_anchoring_force"] == pytest.approx(W + peak_pulse, rel=1e-6, abs=1e-6)
    assert ref["peak_anchoring_force_time"] == pytest.approx(0.004, rel=1e-6)
    # The mount feels the pulse through the friction (default lever d = 1.2 cos θ −
    # 3 sin θ; nothing else moves): least at its peak where d > 0, at rest where d < 0.
    theta = math.radians(elevation)
    lever = 1.2 * math.cos(theta) - 3.0 * math.sin(theta)
    least = min(1.0, 1.0 - peak_pulse * lever / (8000.0 * g * 2.0))
    assert ref["stability_margin"] == pytest.approx(least, abs=1e-12)
    history = reference_history(design, np.linspace(0.0, 1.0, 11))
    assert np.all(history["x_M"] == ref["rest_position"]) and np.all(history["v_M"] == 0.0)


# --- the stability margin, by its definition ----------------------------------------------


def margin_by_hand(design, history):
    """(S − K d) / (m_g g L_w) from a history: K = F_AN − (M + m) g sin θ, d = h cos θ −
    L_s sin θ, S = g (m_g L_w − (M (x_M − x_M(0)) + m (x_m − x_m(0))) cos θ)."""
    theta = math.radians(design["elevation"])
    sin, cos = math.sin(theta), math.cos(theta)
    m_g, L_w = design["mount_mass"], design["cg_distance"]
    lever = design["trunnion_height"] * cos - design["spade_distance"] * sin
    moved = design["M"] * (history["x_M"] - history["x_M"][0])
    moved = moved + design.get("m", 0.0) * (history["x_m"] - history["x_m"][0])
    stabilising = g * (m_g * L_w - moved * cos)
    overturning = (history["F_AN"] - weight(design)) * lever
    return (stabilising - overturning) / (m_g * g * L_w)


@pytest.mark.parametrize("elevation", [0.0, 35.0, 70.0])
def test_the_stability_margin_is_its_definition_along_the_history(elevation):
    """With an absorber on the howitzer: the margin recomputed by hand from the history's
    states and F_AN is nowhere below the reported one, which is reached (at the located
    time, or just after it where F_AN jumps: the counter-recoil buffer engaging)."""
    design = HOWITZER | ABSORBER | {"elevation": elevation}
    t1 = 4.0
    ref = reference_peaks(design, t1=t1)
    assert ref["status"] == "ok" and ref["rest_position"] < 0.0
    t_min = ref["stability_margin_time"]
    ts = np.unique(np.concatenate([np.linspace(0.0, t1, 20001), [t_min, t_min + 1e-12]]))
    history = reference_history(design, ts)
    margin = margin_by_hand(design, history)
    assert margin[0] == pytest.approx(1.0, abs=1e-12)  # at rest: no load, nothing moved
    assert ref["stability_margin"] <= margin.min() + 1e-12
    near = margin[(ts == t_min) | (ts == t_min + 1e-12)]
    assert ref["stability_margin"] == pytest.approx(near.min(), abs=1e-9)
    assert ref["stability_margin"] < 0.9  # a real load, not the rest


def test_at_high_elevation_the_axial_weight_is_not_counted_as_overturning():
    """At 70° the lever d = h cos θ − L_s sin θ is negative: revision 1's F_AN·d counted
    the axial weight, which the mechanism carries at rest, as a stabilising moment, and
    overstated the margin by W |d| / (m_g g L_w): 0.2 for the howitzer (envelope.md)."""
    design = HOWITZER | {"elevation": 70.0}
    ref = reference_peaks(design, t1=6.0)
    t_min = ref["stability_margin_time"]
    history = reference_history(design, np.array([0.0, t_min + 1e-12]))
    theta = math.radians(70.0)
    lever = 1.1 * math.cos(theta) - 3.6 * math.sin(theta)
    assert lever < 0
    assert ref["stability_margin"] == pytest.approx(margin_by_hand(design, history)[1], abs=1e-9)
    overstated = weight(design) * -lever / (8000.0 * g * 3.2)
    assert overstated == pytest.approx(0.2, abs=0.002)
    revision_1 = (
        g * (8000.0 * 3.2 - 1800.0 * history["x_M"][1] * math.cos(theta))
        - history["F_AN"][1] * lever
    ) / (8000.0 * g * 3.2)
    # (revision 1 also measured the travel from x_M = 0: 1800 g x_r cos θ apart)
    shift = 1800.0 * history["x_M"][0] * math.cos(theta) / (8000.0 * 3.2)
    assert revision_1 - ref["stability_margin"] == pytest.approx(overstated - shift, abs=1e-9)


# --- the pull on the mount ----------------------------------------------------------------


@pytest.mark.parametrize(
    ("design", "t1"),
    [
        (HOWITZER, 6.0),  # the pull where the barrel returns into the buffer: a jump
        (HOWITZER | {"elevation": 70.0}, 6.0),
        ({}, 10.0),  # the paper's model: the return damper, a smooth minimum
        (HOWITZER | ABSORBER | {"elevation": 35.0, "buffer_damping": 2e4}, 4.0),
    ],
)
def test_the_peak_pull_force_is_the_least_anchoring_force(design, t1):
    """Event-located, `peak_pull_force` is at least what a 50 µs grid of the history
    shows, and above it by no more than F_AN changes over a grid step there; at its time
    (or just after it, where F_AN jumps) the history reads it."""
    ref = reference_peaks(design, t1=t1)
    pull, t_pull = ref["peak_pull_force"], ref["peak_pull_force_time"]
    assert pull > 0.0
    ts = np.linspace(0.0, t1, round(t1 / 5e-5) + 1)
    F = reference_history(design, ts)["F_AN"]
    i = int(np.argmin(F))
    assert pull >= -F[i] - 1e-9 * pull
    step = max(abs(F[i] - F[i - 1]), abs(F[i + 1] - F[i]))
    assert pull + F[i] <= step
    at = reference_history(design, np.array([0.0, t_pull, t_pull + 1e-10]))["F_AN"][1:]
    assert pull == pytest.approx(-at.min(), rel=1e-9)
    # The mount load: the larger of the push and the pull.
    assert ref["peak_mount_load"] == max(ref["peak_anchoring_force"], pull)
    expected_time = (
        ref["peak_anchoring_force_time"] if ref["peak_anchoring_force"] >= pull else t_pull
    )
    assert ref["peak_mount_load_time"] == expected_time


def test_a_smooth_minimum_of_the_anchoring_force_is_located_where_its_rate_vanishes():
    """The paper's model pulls the mount through its return damper; the least F_AN is
    an interior minimum, located at the rising zero of dF_AN/dt: the history is above
    it on both sides, by the parabola of its curvature (no grid would find it to 1e-9)."""
    ref = reference_peaks({}, t1=10.0)
    t_pull = ref["peak_pull_force_time"]
    h = 1e-4
    F = reference_history({}, np.array([0.0, t_pull - h, t_pull, t_pull + h]))["F_AN"][1:]
    assert -F[1] == pytest.approx(ref["peak_pull_force"], rel=1e-12)
    assert F[0] > F[1] < F[2]
    # A parabola through the three: its vertex at t_pull to within the curvature's reach.
    vertex = h * (F[0] - F[2]) / (2.0 * (F[0] - 2.0 * F[1] + F[2]))
    assert abs(vertex) <= 1e-7
