"""The fit's continuation over the smoothing widths (`rjx.Continuation`): checked when
made, applied only where a design has the switch, and what it is for: the counter-
recoil buffer's jump in `F_AN` steps χ² as its engagement crosses a sample time, and a
fit at the calibration's widths alone stops on a step that the continuation's wide widths
smooth."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import recoil_jax as rj
import recoil_jax.extend as rjx

#: The envelope gun of `optimise/plans/envelope_friction.toml`, and a truth for it.
GUN = {"M": 1800.0, "m": 0.0, "k": 0.0, "v0": 10.0, "pulse_time": 0.004,
       "stop_stiffness": 2.1e8, "recuperator_length": 1.8, "buffer_length": 0.15,
       "buffer_damping": 150000.0, "c_out": 16000.0, "recuperator_preload": 30000.0,
       "friction_force": 1500.0, "friction_coefficient": 0.05}  # fmt: skip
TRUTH = {"c_ret": 29836.4, "recuperator_preload": 34273.5}
BOX = {"c_ret": (5e3, 5e4), "recuperator_preload": (1e4, 6e4)}
NOISE = {"x_M": 3e-4, "F_AN": 200.0}


@pytest.mark.parametrize(
    ("widths", "message"),
    [
        ({"gap_width": (1e-2,)}, "'gap_width' is not a width it can continue: valid"),
        ({"buffer_width": (1e-4, 1e-2)}, "must not widen, widest first"),
        ({"buffer_width": (0.0,)}, r"each > 0"),
        ({"buffer_width": (1e-2, 1e-4), "stop_width": (1e-2,)}, "the same number of stages"),
        ({"slip_width": (1e-2,)}, "'slip_width' is not a width it can continue: valid"),
        ({"buffer_width": "wide"}, "give its widths as a list of numbers"),
    ],
)
def test_a_bad_continuation_is_refused_naming_the_width(widths, message):
    with pytest.raises(rj.ParameterError, match=message):
        rjx.Continuation(widths)


def test_a_continuation_acts_only_where_the_design_has_the_switch():
    default = rjx.Continuation()
    fitting = rj.Smoothing()
    assert default.stages == 5
    assert rjx.DEFAULT_CONTINUATION == default and default.fallback is None
    assert default.for_design(rj.params_from_values({"m": 0.0}), fitting) is None  # no buffer
    gun = rj.params_from_values(GUN)
    # The last stage is the fit's own widths: the buffer's four stages before it.
    assert default.for_design(gun, fitting).widths == {"buffer_width": (1e-2, 1e-3, 1e-4, 1e-5)}
    no_buffer = rj.params_from_values(
        {k: v for k, v in GUN.items() if k not in ("buffer_length", "buffer_damping")}
    )
    assert no_buffer.counter_recoil_buffer is None
    assert default.for_design(no_buffer, fitting) is None  # the rails have no width
    both = rjx.Continuation({"buffer_width": (1e-2, 1e-4), "stop_width": (1e-5, 1e-6)})
    assert both.for_design(no_buffer, fitting).widths == {"stop_width": (1e-5, 1e-6)}
    # A fallback path is kept where it differs; a store of one without keeps its identity.
    with_fallback = rjx.Continuation(fallback=both)
    path = with_fallback.for_design(gun, fitting)
    assert path.fallback.widths == both.widths
    assert default.identity() == (default.to_json(),)
    assert path.identity() == (path.to_json(), path.fallback.to_json())
    with pytest.raises(rj.ParameterError, match="fallback = 'wide': give a Continuation"):
        rjx.Continuation(fallback="wide")
    stage = both.smoothing(rj.Smoothing(), 1)
    assert float(stage.buffer_width) == 1e-4 and float(stage.stop_width) == 1e-6
    assert float(stage.damping_width) == float(rj.Smoothing().damping_width)


def _firing(seed: int) -> rj.Calibration:
    """One firing at 70°, 1 s of x_M and F_AN at 1 kHz from the independent hard-switch
    solver with noise; c_ret and the preload fitted from the guess of the plan."""
    ts = np.arange(0.0, 1.0 + 1e-12, 1e-3)
    design = {**GUN, "elevation": 70.0, "v0": 8.0}
    history = rjx.reference_history(design | TRUTH, ts)
    rng = np.random.default_rng(seed)
    noisy = {s: history[s] + sigma * rng.standard_normal(ts.size) for s, sigma in NOISE.items()}
    experiment = rjx.Experiment(rjx.Trace.of(ts, **noisy), design={"elevation": 70.0, "v0": 8.0,
                                "t1": 1.0}, sigma=NOISE)  # fmt: skip
    known = {k: v for k, v in GUN.items() if k not in BOX}
    return rj.Calibration([experiment], BOX, start={"c_ret": 15000.0,
                          "recuperator_preload": 30000.0}, design=known)  # fmt: skip


def test_the_continuation_reaches_the_truth_where_the_model_widths_stall():
    """From the plan's guess, far from the truth: the default fit (two starts through
    the continuation) reaches the truth within 3 standard errors and both starts agree;
    one start at the calibration's widths alone ends on a step of χ², far above the noise."""
    calibration = _firing(seed=3)
    fitted = rj.calibrate(calibration, progress=False)
    assert fitted.converged and fitted.explains and fitted.verdict == "explains"
    assert fitted.starts_at_best == 2
    assert fitted.continuation == {"buffer_width": [1e-2, 1e-3, 1e-4, 1e-5]}
    assert not fitted.fallback and fitted.starts == 2  # no fallback path
    for name, value in TRUTH.items():
        assert abs(fitted.values[name] - value) < 3 * fitted.fitted[name].stderr, name
    # The result says the widths it is at (result.json's "smoothing").
    assert fitted.to_json()["smoothing"]["buffer_width"] == float(rj.Smoothing().buffer_width)
    plain = rj.calibrate(calibration, starts=1, continuation=None, progress=False)
    assert plain.continuation == {}
    assert plain.reduced_chi2 > 10 * fitted.reduced_chi2, (plain.values, plain.reduced_chi2)
    assert plain.verdict == "local_minimum"


def test_a_fit_the_model_check_rejects_takes_the_fallback_path_before_its_verdict():
    """The wrong counter-recoil buffer (its damping 100,000 known, the truth's 150,000):
    the check fails at the best point of the default path, so the fit runs its starts
    through the fallback path too (4 fits) and says the model does not explain the
    traces only then; without a fallback, one path."""
    calibration = _firing(seed=4)
    wrong = dataclasses.replace(calibration, design=calibration.design | {"buffer_damping": 1e5})
    with_fallback = rjx.Continuation(fallback=rjx.Continuation({"buffer_width": (1e-2, 1e-4)}))
    result = rj.calibrate(wrong, continuation=with_fallback, progress=False)
    assert result.fallback and result.starts == 4
    assert not result.explains and result.to_json()["fallback"] is True
    if result.verdict == "local_minimum":  # what the command line then says
        from recoil_jax.apps._cli.calibrate import _stuck_line

        assert "of 4 fits (2 starts through both continuation paths)" in _stuck_line(result)
    single = rj.calibrate(wrong, progress=False)  # the default: no fallback
    assert not single.fallback and single.starts == 2 and not single.explains


def test_starts_at_one_point_are_fitted_once_from_it():
    """The same start given twice: its first stage ends both at one point, and each later
    stage fits that point once (4 calls of the fit's program, not 6), the outcome the second start's
    too. The result is the single start's bit for bit, reached from both starts."""
    from recoil_jax._calibration import calibrate as module

    calibration = _firing(seed=3)
    path = rjx.Continuation({"buffer_width": (1e-2, 1e-4)})
    start = np.array([calibration.start[name] for name in BOX])
    calls = []
    program = module.fit_program

    def counted(u0, *args):
        calls.append(len(u0))
        return program(u0, *args)

    single = rj.calibrate(calibration, starts=start[None], continuation=path, progress=False)
    module.fit_program = counted
    try:
        twice = rj.calibrate(calibration, starts=np.stack([start, start]), continuation=path,
                             progress=False)  # fmt: skip
    finally:
        module.fit_program = program
    assert calls == [1, 1, 1, 1]  # stage 1 from each start, then stage 2 and the fit once
    assert twice.starts == 2 and twice.starts_at_best == 2
    assert twice.values == single.values and twice.steps == single.steps
    assert twice.chi2 == single.chi2


@pytest.mark.parametrize(
    ("cost", "z", "same", "expected"),
    [
        ([10.0, 10.005, 10.0], [0.5, 0.5005, 0.5], [0, 1, 2], [0, 0, 0]),
        ([10.0, 10.02, 10.0], [0.5, 0.5, 0.5], [0, 1, 2], [0, 1, 0]),  # χ² apart
        ([10.0, 10.0, 10.0], [0.5, 0.502, 0.5], [0, 1, 2], [0, 1, 0]),  # values apart
        ([10.0, 11.0, 11.0], [0.5, 0.6, 0.6], [0, 1, 1], [0, 1, 1]),  # followers stay
        ([11.0, 11.0, 11.0], [0.6, 0.6, 0.6], [0, 1, 1], [0, 0, 0]),  # ... and move with it
        ([np.nan, np.nan, 10.0], [0.5, 0.5, 0.5], [0, 1, 2], [0, 1, 2]),  # failed: never
    ],
)
def test_the_points_starts_share_after_a_stage(cost, z, same, expected):
    from recoil_jax._calibration.calibrate import _same_points

    u = np.arcsin(2.0 * np.asarray(z)[:, None] - 1.0)
    out = _same_points(u, np.asarray(cost), np.asarray(same))
    assert out.tolist() == expected
