"""The newest surfaces hold the contract (issue 64): a bad study, plan or calibration is
one line and exit 2, before anything compiles, naming the file and the entry; nothing is
reported for a state that was not reached."""

from __future__ import annotations

import csv
import json
import os
import time
from pathlib import Path

import numpy as np
import pytest

import recoil_jax as rj
from recoil_jax.apps import main
from recoil_jax.apps._studies.study_file import SHIPPED as STUDIES

ENVELOPE = (STUDIES / "envelope.toml").read_text()


def refused(capsys, argv, *fragments, seconds=10.0):
    """`argv` ends in exit 2 with one line on stderr holding every fragment, within
    `seconds` (before any compilation)."""
    started = time.perf_counter()
    status = main(argv)
    took = time.perf_counter() - started
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert status == 2, captured.err
    errors = [line for line in lines if line.startswith("recoil-jax: error:")]
    assert len(errors) == 1 and "Traceback" not in captured.err, captured.err
    for fragment in fragments:
        assert fragment in errors[0], errors[0]
    assert took < seconds, took
    return errors[0]


def study(tmp_path, text: str):
    path = tmp_path / "study.toml"
    path.write_text(text)
    return ["optimise", str(path), "--out", str(tmp_path / "out")]


@pytest.mark.parametrize(
    "condition, fragments",
    [
        # A mount lighter than the gun on it: the condition's design, checked whole.
        ("mount_mass = 100.0", ["study.toml", "condition '0 deg'", "mount_mass"]),
        # Absurd values past the ceiling: the value named, not another one.
        ("M = 1e308", ["study.toml", "[[condition]] 1", "M = 1e+308", "at most 2e+10 kg"]),
        # No mount at a condition where the margin is limited (every condition).
        ("mount_mass = 0.0", ["study.toml", "condition '0 deg'", "stability_margin needs a mount"]),
    ],
)
def test_a_condition_is_checked_as_the_whole_design_it_makes(
    tmp_path, capsys, condition, fragments
):
    text = ENVELOPE.replace(
        'name = "0 deg"\nelevation = 0.0', f'name = "0 deg"\nelevation = 0.0\n{condition}'
    )
    assert text != ENVELOPE
    refused(capsys, study(tmp_path, text), *fragments)


@pytest.mark.parametrize(
    "old, new, fragments",
    [
        (
            "return_time = { max = 2.5 }",
            "return_time = { max = nan }",
            ["return_time", "max = nan", "not a finite number"],
        ),
        ("return_time = { max = 2.5 }", "return_time = { max = inf }", ["max = inf"]),
        (
            "peak_mount_load = 1.0",
            "peak_mount_load = nan",
            ["peak_mount_load", "nan", "not a finite number"],
        ),
        (
            "[objective]",
            "[objective.scatter]\nv0 = 0.05\n[objective]",
            ["[objective.scatter]", "v0 = 0.05"],
        ),
        (
            "[objective]",
            '[objective.scatter]\nv0 = ["a"]\n[objective]',
            ["[objective.scatter]", "v0 = ['a']"],
        ),
        ("peak_mount_load = 1.0", "peak_mount_load = 1.0\nscatter = 5", ["[objective.scatter]"]),
        (
            "samples = 256",
            "samples = 1000000000000",
            ["a global phase of", "samples needs about", "give fewer samples"],
        ),
        # A [design] value that is not a number, or out of range: the design's, at once.
        ("spade_distance = 3.6", "spade_distance = [1, 2]", ["spade_distance = [1, 2]: valid a"]),
        ("M = 1800.0", "M = 1e308", ["[design]", "Barrel.M = 1e+308 kg", "at most 2e+10 kg"]),
        ("M = 1800.0", "M = 1800.0\nshots = 2.5", ["[design]", "Load.shots = 2.5", "an integer"]),
    ],
)
def test_a_bad_limit_weight_scatter_or_count_is_refused_at_once(
    tmp_path, capsys, old, new, fragments
):
    assert old in ENVELOPE
    refused(capsys, study(tmp_path, ENVELOPE.replace(old, new, 1)), *fragments)


def test_too_many_conditions_are_refused_at_once(tmp_path, capsys):
    extra = "".join(f'\n[[condition]]\nname = "c{i}"\nelevation = {i % 70}.0\n' for i in range(120))
    refused(capsys, study(tmp_path, ENVELOPE + extra), "123 [[condition]]s", "at most 100")


def test_an_absurd_end_time_is_refused_at_once(tmp_path, capsys):
    refused(
        capsys,
        study(tmp_path, ENVELOPE.replace("t1 = 6.0", "t1 = 1e9")),
        "[design] t1 = 1000000000.0",
        "at most 6e+07 s",
    )


def test_a_start_per_sample_at_most():
    """`SobolStarts.choose` takes at most one start a sample, whatever `starts` says (a
    billion starts once asked for a list of two billion spacings)."""
    phase = rj.SobolStarts(samples=4, starts=10**9)
    sampled = {
        "z": np.eye(4),
        "objective": np.arange(4.0),
        "violation": np.zeros(4),
        "ok": np.ones(4, dtype=bool),
    }
    assert len(phase.choose(sampled)) == 4


def test_a_barrel_that_has_not_returned_has_no_return_metrics_in_a_sweep(tmp_path, capsys):
    """`sweep` says what `simulate` says of a barrel still out at t1: no return time, no
    battery speed, `returned` false, in its JSON, its CSV and its arrays."""
    gun = ["M=1800", "v0=10", "m=0", "k=0", "friction_force=1500", "friction_coefficient=0.05",
           "stop_stiffness=2.1e8", "recuperator_length=1.8", "recuperator_preload=30000",
           "c_out=16000", "c_ret=30000", "t1=0.2"]  # fmt: skip
    assert main(["simulate", "--json", *gun]) == 0
    simulated = json.loads(capsys.readouterr().out)
    assert simulated["returned"] is False and simulated["return_time_s"] is None
    out = tmp_path / "sweep"
    assert (
        main(["sweep", *gun[:-2], "c_ret=20000,30000", "t1=0.2", "--json", "--out", str(out)]) == 0
    )
    records = json.loads(capsys.readouterr().out)
    for record in records:
        assert record["returned"] is False
        assert record["return_time_s"] is None and record["battery_speed_m_per_s"] is None
    with open(out / "sweep.csv") as f:
        rows = list(csv.DictReader(f))
    assert all(r["return_time_s"] == "" and r["returned"] == "False" for r in rows)
    arrays = np.load(out / "sweep.npz")
    assert np.all(np.isnan(arrays["return_time_s"])) and np.all(arrays["returned"] == 0)


def test_an_absurd_mount_mass_is_refused_not_reported_null(capsys):
    refused(capsys, ["simulate", "--json", "mount_mass=1e308"], "mount_mass = 1e+308", "at most")


def _calibration(tmp_path, design: str, fit: str, experiment: str = "") -> str:
    trace = tmp_path / "trace.csv"
    trace.write_text("t,x_M\n" + "".join(f"{i / 1000},{1e-3 * i}\n" for i in range(1, 50)))
    path = tmp_path / "calibration.toml"
    path.write_text(
        f'[design]\n{design}\n[fit]\n{fit}\n[[experiment]]\ntrace = "trace.csv"\n{experiment}\n'
    )
    return str(path)


def test_predict_is_checked_before_the_fit(tmp_path, capsys):
    path = _calibration(tmp_path, "M = 1800.0", "c_out = [1e3, 4e4]")
    refused(
        capsys,
        ["calibrate", path, "--predict", "elevation=95", "--out", str(tmp_path / "o")],
        "--predict", "elevation = 95",
    )  # fmt: skip
    refused(
        capsys,
        ["calibrate", path, "--predict", "c_out=5000", "--out", str(tmp_path / "o")],
        "--predict c_out=5000", "is fitted",
    )  # fmt: skip


def test_a_fitted_preload_needs_a_battery_stop(tmp_path, capsys):
    """As `simulate` refuses the design, so does `calibrate` (the fit would solve it)."""
    path = _calibration(
        tmp_path, "M = 1800.0\nrecuperator_length = 1.8", "recuperator_preload = [1e4, 6e4]"
    )
    refused(
        capsys, ["calibrate", path, "--out", str(tmp_path / "o")],
        "at the fit's start (recuperator_preload = 35000)",
        "battery stop",
    )  # fmt: skip


def test_a_fitted_value_in_an_experiment_is_refused(tmp_path, capsys):
    path = _calibration(tmp_path, "M = 1800.0", "c_out = [1e3, 4e4]", "c_out = 9000.0")
    refused(
        capsys, ["calibrate", path, "--out", str(tmp_path / "o")],
        "[[experiment]] 1: c_out = 9000 is fitted ([fit]), so it would not be held there",
    )  # fmt: skip


def test_a_failed_write_leaves_no_file_and_names_it(tmp_path):
    """`rjx.written`: a write that fails half-way (a full disk) leaves neither the file nor
    its temporary, and the error names the file; a finished one replaces it whole."""
    import errno

    import recoil_jax.extend as rjx

    path = tmp_path / "figure.png"
    with pytest.raises(OSError) as caught, rjx.written(path) as temporary:
        temporary.write_bytes(b"half")
        raise OSError(errno.ENOSPC, "No space left on device")
    assert caught.value.filename == str(path) and caught.value.errno == errno.ENOSPC
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(OSError) as caught, rjx.written(tmp_path / "gone" / "f.csv") as temporary:
        temporary.write_text("x")  # (its folder is missing: the error names the file)
    assert caught.value.filename == str(tmp_path / "gone" / "f.csv")
    path.write_text("old")
    with rjx.written(path) as temporary:
        temporary.write_text("new")
    assert path.read_text() == "new" and len(list(tmp_path.iterdir())) == 1


def test_every_file_the_package_writes_is_written_whole():
    """Every write of a file in the package goes through `rjx.written` (or the compiled
    programs' own `partial` file): no figure, CSV or array file is written in place."""
    import re

    package = Path(rj.__file__).parent
    writes = re.compile(r'open\([^)]*"(w|wb|a)"|\.write_text\(|\.write_bytes\(|np\.savez|savefig\(')
    found = []
    for path in package.rglob("*.py"):
        for number, line in enumerate(path.read_text().splitlines(), 1):
            if writes.search(line) and not re.search(
                r"temporary|partial|devnull|buffer|\(f,", line
            ):
                found.append(f"{path.relative_to(package)}:{number}: {line.strip()}")
    assert found == []


def test_a_full_standard_output_is_not_blamed_on_the_output_folder(tmp_path):
    import subprocess
    import sys

    out = tmp_path / "sweep"
    with open("/dev/full", "w") as full:
        done = subprocess.run(
            [sys.executable, "-m", "recoil_jax.apps._cli", "sweep", "m=0", "k=1e4,2e4",
             "--json", "--out", str(out)],
            stdout=full, stderr=subprocess.PIPE, text=True, timeout=300,
            env=os.environ | {"PYTHONUNBUFFERED": "1"},  # the JSON's write fails, not the exit's
        )  # fmt: skip
    assert done.returncode == 1, done.stderr
    assert "cannot write standard output: No space left on device" in done.stderr, done.stderr
    assert "writing into" not in done.stderr and "Traceback" not in done.stderr
    assert (out / "sweep.csv").exists() and (out / "sweep.npz").exists()


def test_plan_does_not_overwrite_its_own_input_nor_write_into_an_empty_name(tmp_path, capsys):
    from recoil_jax.apps._studies.plan_file import SHIPPED as PLANS

    source = tmp_path / "calibration.toml"
    source.write_text((PLANS / "envelope_friction.toml").read_text())
    before = source.read_text()
    refused(capsys, ["plan", str(source), "--out", str(tmp_path)], "would overwrite the input")
    assert source.read_text() == before
    refused(capsys, ["plan", str(source), "--out", ""], "--out '' is empty")


@pytest.mark.parametrize("text", ["a\tb\rc", "\u0000", "del \x7f", 'q"uo\\te', "é 😀\nline"])
def test_a_description_of_any_characters_is_written_as_toml(text):
    """The plan's skeleton writes its description as a TOML string that reads back the
    same, control characters included (`calibrate` once refused the file)."""
    import tomllib

    from recoil_jax.apps._files.calibration_file import toml_string

    assert tomllib.loads(f"description = {toml_string(text)}\n")["description"] == text


@pytest.mark.parametrize(
    "argv_tail, edit, fragment",
    [
        (["--check", "10000"], None, "a check of 10,000 simulated tests needs about"),
        ([], ("[sampling]", "[sampling]\n"), None),
    ],
)
def test_a_plan_larger_than_memory_is_refused_before_its_work(
    tmp_path, capsys, monkeypatch, argv_tail, edit, fragment
):
    """`--check` at the top of its range and `robust` at the top of its own are refused
    by what memory is free (here 2 GB), not by an allocation error after the work."""
    import recoil_jax._sweeps.memory as memory
    from recoil_jax.apps._studies.plan_file import SHIPPED as PLANS

    monkeypatch.setattr(memory, "_available_memory", lambda: 2 * 10**9)
    text = (PLANS / "envelope_friction.toml").read_text()
    if edit is not None:
        text = text.replace('description = "', 'robust = 256\ndescription = "', 1)
        fragment = "a plan of 257 truths needs about"
    source = tmp_path / "plan.toml"
    source.write_text(text)
    refused(capsys, ["plan", str(source), "--out", str(tmp_path / "o"), *argv_tail], fragment)


@pytest.mark.parametrize("sigma", ["1e-300", "1e-160", "1e13"])
def test_a_noise_the_information_cannot_hold_is_refused(tmp_path, capsys, sigma):
    from recoil_jax.apps._studies.plan_file import SHIPPED as PLANS

    text = (PLANS / "envelope_friction.toml").read_text()
    assert "x_M = { sigma = 3e-4" in text
    source = tmp_path / "plan.toml"
    source.write_text(text.replace("x_M = { sigma = 3e-4", f"x_M = {{ sigma = {sigma}"))
    refused(capsys, ["plan", str(source), "--out", str(tmp_path / "o")],
            "signals.x_M.sigma", "valid 1e-12 to 1e+12")  # fmt: skip


def test_a_study_keeps_its_result_when_a_step_after_the_search_fails(tmp_path, monkeypatch):
    """`result.json` holds the optimiser's result, with the failed after-step beside it,
    and the failure is raised as it was (a bug keeps its traceback)."""
    import recoil_jax.apps._studies.study as study_module

    def failing(*args, **kwargs):
        raise RuntimeError("the history could not be drawn")

    monkeypatch.setattr(study_module, "check_best", failing)
    path = tmp_path / "gap.toml"
    path.write_text(
        "[design]\nm = 1500.0\ngap = 0.03\n[tune]\ngap = [0.0, 0.12]\n"
        "[objective]\npeak_anchoring_force = 1.0\n[optimiser]\nstarts = 2\nsteps = 3\n"
    )
    with pytest.raises(RuntimeError, match="could not be drawn"):
        study_module.run_study(path, tmp_path / "out", progress=False)
    report = json.loads((tmp_path / "out" / "result.json").read_text())
    assert report["feasible"] and report["best"]["gap"] > 0
    assert report["failed_after"]["error"] == "RuntimeError: the history could not be drawn"


def test_a_million_candidate_values_are_refused_at_once(tmp_path, capsys):
    from recoil_jax.apps._studies.plan_file import SHIPPED as PLANS

    text = (PLANS / "envelope_friction.toml").read_text()
    values = ", ".join(f"{i * 1e-4:.4f}" for i in range(200_000))
    text = text.replace("elevation = [0, 15, 30, 45, 60, 70]", f"elevation = [{values}]")
    source = tmp_path / "plan.toml"
    source.write_text(text)
    refused(capsys, ["plan", str(source), "--out", str(tmp_path / "o")],
            "candidates: 400,000 combinations; valid at most 1,000", seconds=5.0)  # fmt: skip


def test_a_failed_history_is_one_solve_error_not_a_callback_traceback(capfd):
    """The best design's history at an end time its steps cannot reach (a study with
    `t1 = 6e7`) fails with the solve's status, not JAX's callback traceback."""
    import dataclasses

    from recoil_jax.apps._studies.checks import _history

    problem = rj.DesignProblem(
        params=rj.RecoilParams(),
        objective=rj.Objective({"peak_anchoring_force": 1.0}),
        options=dataclasses.replace(rj.GRADIENT_OPTIONS, max_steps=5),
    )
    with pytest.raises(rj.SolveError) as caught:
        _history(problem, problem.params, 1.0)
    assert "max_steps reached" in rj.failure_message(caught.value)
    assert "Traceback" not in capfd.readouterr().err


def test_a_trace_larger_than_memory_allows_is_refused_before_the_fit(tmp_path, capsys, monkeypatch):
    """The calibration's arrays for a long trace, measured at about 270 bytes a sample and
    start, are checked against the free memory (here 200 MB) before the fit."""
    import recoil_jax._sweeps.memory as memory

    monkeypatch.setattr(memory, "_available_memory", lambda: 200 * 10**6)
    t = np.linspace(1e-4, 3.0, 200_000)
    rows = "\n".join(f"{a:.7g},{b:.6g}" for a, b in zip(t, 0.1 * np.sin(3 * t), strict=True))
    (tmp_path / "long.csv").write_text("t,x_M\n" + rows + "\n")
    refused(capsys, ["calibrate", str(tmp_path / "long.csv"), "--fit", "k,c_out",
                     "--out", str(tmp_path / "o")],
            "a calibration of 2 starts at once needs about")  # fmt: skip


def test_a_fit_whose_box_reaches_an_impossible_design_is_refused_before_it_starts():
    """Checked at the fit's start (valid here: M = 3000 under a 20 t mount) and with each
    fitted value at its upper bound, where the fit may go (M = 60 t: heavier than the
    mount that carries it)."""
    import recoil_jax.extend as rjx

    ts = np.linspace(0.01, 1.0, 50)
    experiment = rjx.Experiment(rjx.Trace.of(ts, x_M=np.sin(ts)), {})
    design = {"M": 3000.0, "mount_mass": 2e4}
    with pytest.raises(rj.ParameterError, match="with M at its upper bound 60000, where the fit"):
        rj.Calibration([experiment], fit={"M": (1e3, 6e4)}, design=design)
    calibration = rj.Calibration([experiment], fit={"M": (1e3, 1.5e4)}, design=design)
    assert calibration.shared_start() == {"M": pytest.approx(3000.0)}


def test_a_value_checked_by_itself_names_its_flat_name():
    """`Parameter.check`: a knot by its own name, 0 where it leaves its part out."""
    with pytest.raises(rj.ParameterError, match=r"Buffer\.orifice_3 = -1"):
        rj.PARAMETERS["orifice_3"].check(-1.0)
    rj.PARAMETERS["m"].check(0.0)  # no absorber
    with pytest.raises(rj.ParameterError, match=r"Absorber\.m = -1"):
        rj.PARAMETERS["m"].check(-1.0)
