"""The firing test's round trip through the command line: `plan` writes the calibration
of its firings, `simulate --from` that file writes each firing's noisy trace at the
plan's rate and duration under the name the file expects, and `calibrate` fits them
with no edit and no option, recovering the truth within its intervals. And what
`simulate --from` refuses, before anything is solved."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from recoil_jax.apps import main
from recoil_jax.apps._studies.plan_file import SHIPPED

#: A truth inside the shipped plan's box, away from its guess (c_out 16,000, c_ret
#: 15,000, preload 30,000 N, F_0 1,500 N, μ 0.05).
TRUTH = {"c_out": 27981.2, "c_ret": 29836.4, "recuperator_preload": 34273.5,
         "friction_force": 1758.12, "friction_coefficient": 0.102876}  # fmt: skip
STUDY = SHIPPED.parent / "envelope.toml"


def _refused(capsys, argv, fragment):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("recoil-jax: error:"), err
    assert fragment in err[0], err[0]


@pytest.mark.slow
def test_a_planned_test_round_trips_from_the_defaults(tmp_path, capsys):
    out = tmp_path / "plan"
    assert main(["plan", "envelope_friction", "--out", str(out)]) == 0
    capsys.readouterr()
    skeleton = out / "calibration.toml"
    for i in (1, 2, 3):
        argv = ["simulate", "--from", str(skeleton), "--experiment", str(i), "--rate", "1000",
                "--csv", str(out / f"firing_{i}.csv"), "--noise", "--seed", str(i),
                *(f"{k}={v}" for k, v in TRUTH.items())]  # fmt: skip
        assert main(argv) == 0
    capsys.readouterr()
    lines = (out / "firing_2.csv").read_text().splitlines()
    assert len(lines) == 3001 and lines[1].startswith("0.001,")  # 1 kHz over 3 s, as planned
    code = main(["calibrate", str(skeleton), "--out", str(tmp_path / "fit"), "--json"])
    report = json.loads(capsys.readouterr().out)
    assert code == 0 and report["verdict"] == "explains" and report["starts_at_best"] == 2
    for name, value in TRUTH.items():
        low, high = report["fitted"][name]["ci95"]
        assert low <= value <= high, (name, low, value, high)


def test_simulate_takes_one_experiment_of_a_calibration_file(tmp_path, capsys):
    """The experiment's values and the fitted values' starts make the design; the trace
    comes at the rate and duration asked for, with only the noisy signals."""
    calibration = tmp_path / "cal.toml"
    calibration.write_text(
        "[design]\nm = 0.0\n[fit]\nc_out = { bounds = [1e3, 3e4], start = 5000.0 }\n"
        'k = [1e4, 1e5]\n[[experiment]]\ntrace = "a.csv"\nv0 = 0.5\nt1 = 1.0\n'
        'sigma = { x_M = 1e-4 }\n[[experiment]]\nname = "second"\ntrace = "b.csv"\n'
        "v0 = 0.8\n"
    )
    trace = tmp_path / "b.csv"
    argv = ["simulate", "--from", str(calibration), "--experiment", "second", "--json",
            "--csv", str(trace), "--rate", "200", "--duration", "0.5",
            "--noise", "x_M=1e-4"]  # fmt: skip
    assert main(argv) == 0
    used = json.loads(capsys.readouterr().out)["parameters"]
    assert used["v0"] == 0.8 and used["c_out"] == 5000.0 and used["k"] == 55000.0
    assert used["t1"] == 0.5  # the duration, where the file gives none
    lines = trace.read_text().splitlines()
    assert lines[0] == "t,x_M" and len(lines) == 101 and lines[-1].startswith("0.5,")
    # Bare --noise: the experiment's own sigma; the same seed, the same trace.
    for name in ("a1.csv", "a2.csv"):
        assert main(["simulate", "--from", str(calibration), "--experiment", "a",
                     "--csv", str(tmp_path / name), "--rate", "100", "--noise"]) == 0  # fmt: skip
    capsys.readouterr()
    first, second = ((tmp_path / n).read_text() for n in ("a1.csv", "a2.csv"))
    assert first == second and first.splitlines()[0] == "t,x_M"
    values = np.loadtxt(tmp_path / "a1.csv", delimiter=",", skiprows=1)
    assert values.shape == (100, 2) and values[-1, 0] == 1.0  # the experiment's t1


@pytest.mark.parametrize(
    "argv, fragment",
    [
        (["--from", "{cal}"], "has 2 experiments: choose one with --experiment (1: a.csv;"),
        (["--from", "{cal}", "--experiment", "7"], "--experiment 7: "),
        (["--experiment", "1"], "give the file with --from"),
        (["--from", "{study}", "--experiment", "70 deg"], "the study tunes c_out, c_ret"),
        (["--from", "{cal}", "--experiment", "1", "--rate", "100"], "give --csv FILE.csv"),
        (["m=0", "--csv", "{out}", "--noise", "x_M=-1"], "must be >= 0 and finite"),
        (["m=0", "--csv", "{out}", "--noise", "y=1"], "'y' is not a signal; valid x_M"),
        (["m=0", "--csv", "{out}", "--noise", "F_ct=1"], "a signal of the absorber"),
        (["m=0", "--csv", "{out}", "--noise"], "takes the file's noise"),
        (["m=0", "t1=1", "--csv", "{out}", "--rate", "100", "--duration", "2"], "past t1"),
        (["m=0", "--csv", "{out}", "--rate", "1e9", "--duration", "1"], "--rate 1e+09"),
        (["--from", "{cal_csv}"], "not valid TOML"),
    ],
)
def test_simulate_from_a_file_refuses_what_it_cannot_do(tmp_path, capsys, argv, fragment):
    calibration = tmp_path / "cal.toml"
    calibration.write_text('[design]\nm = 0.0\n[fit]\nk = [1e4, 1e5]\n[[experiment]]\n'
                           'trace = "a.csv"\n[[experiment]]\ntrace = "b.csv"\n')  # fmt: skip
    (tmp_path / "x.csv").write_text("t,x_M\n0,1\n")
    names = {"cal": calibration, "study": STUDY, "out": tmp_path / "o.csv",
             "cal_csv": tmp_path / "x.csv"}  # fmt: skip
    argv = [a.format(**{k: str(Path(v)) for k, v in names.items()}) for a in argv]
    _refused(capsys, ["simulate", *argv], fragment)


@pytest.mark.slow
def test_the_exact_stick_leaves_the_fit_unbiased():
    """The shipped plan's firings by the independent reference solver at truth 0 of
    `bench-calibration --round-trip`, fitted from the truth itself at the model's own
    widths (a calibration's default: the stick is a mode, exact). Without noise the fit
    lands on the truth to 1e-3 of a standard error (measured: 1e-4; χ² per sample
    1.3e-11 of the noise's): the model has no bias against the reference. (Before the
    stick was a mode, the model's smoothed stick put `μ` 2.3 standard errors high, and a
    calibration fitted at friction widths of its own.) With the plan's noise (its draw
    0) every value is within 3 standard errors (measured: at most 1.8)."""
    import recoil_jax as rj
    import recoil_jax.extend as rjx
    from recoil_jax.apps._bench.round_trip import planned_traces, truth_of
    from recoil_jax.apps._studies.plan_file import load_plan

    assert rj.Calibration.__dataclass_fields__["smoothing"].default == rj.Smoothing()
    problem, _ = load_plan(SHIPPED / "envelope_friction.toml")
    plan = rj.plan_firings(problem)
    truth = truth_of(problem, 0)
    assert truth == pytest.approx(TRUTH, rel=1e-5)
    noisy = planned_traces(plan, plan.plan, truth, 0)
    clean = []
    for (condition, signals), trace in zip(plan.plan.firings, noisy, strict=True):
        design = {**problem.guess, **plan.conditions[condition], **truth}
        history = rjx.reference_history(design, np.asarray(trace.t))
        clean.append(rjx.Trace.of(np.asarray(trace.t), **{s: history[s] for s in signals}))
    fits = {}
    for label, traces in (("noisy", noisy), ("clean", clean)):
        calibration = rjx.plan_calibration(plan, plan.plan, traces)
        assert calibration.smoothing == rj.Smoothing()
        start = np.asarray([[truth[n] for n in calibration.fit]])
        fits[label] = rj.calibrate(calibration, starts=start, continuation=None, progress=False)
        assert fits[label].converged and fits[label].verdict == "explains", label
    stderr = {n: fits["noisy"].fitted[n].stderr for n in truth}
    for label, limit in (("clean", 1e-3), ("noisy", 3.0)):
        apart = {n: (fits[label].values[n] - v) / stderr[n] for n, v in truth.items()}
        print(label, "standard errors from the truth:", apart)
        assert all(abs(a) < limit for a in apart.values()), (label, apart)
