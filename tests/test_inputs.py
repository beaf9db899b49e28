"""Every input a user can type or load gets a one-line message and an exit status, never a
traceback, before anything is solved or compiled; values the model accepts but a user
probably did not mean get a warning that names the documented range."""

import json
import re
import sys

import numpy as np
import pytest
from conftest import drop_programs

import recoil_jax as rj
import recoil_jax.extend as rjx
from recoil_jax.apps import main
from recoil_jax.apps._files.describe import describe
from recoil_jax.apps._files.inputs import design_warnings


@pytest.fixture
def files(tmp_path):
    """Files a user might give by mistake, and a table saved by a spreadsheet."""
    (tmp_path / "binary.csv").write_bytes(bytes(range(256)) * 8)
    (tmp_path / "folder").mkdir()
    (tmp_path / "bom.csv").write_bytes(b"\xef\xbb\xbft_s,F_N\r\n0,0\r\n0.002,1.5e6\r\n0.004,0\r\n")
    (tmp_path / "twice.csv").write_text("m,gap,m\n100,0.01,200\n")
    (tmp_path / "ragged.csv").write_text("m,gap\n100,0.01\n200\n")
    (tmp_path / "twice.json").write_text('[{"m": 100, "m": 200}]')
    (tmp_path / "broken.json").write_text('[{"m": 100,')
    (tmp_path / "empty.csv").write_text("m,gap\n")
    t = np.linspace(0.0, 0.01, 70_000)
    rows = "\n".join(f"{a:.9g},{1e5 * np.sin(np.pi * a / 0.01):.6g}" for a in t)
    (tmp_path / "long.csv").write_text("t_s,F_N\n" + rows + "\n")
    study = 'description = "x"\n[design]\n{design}\n[tune]\nc_out = [2e3, 6e4]\n'
    study += "[objective]\npeak_anchoring_force = 1.0\n[constraints]\n{limit}\n"
    envelope = "friction_force = 1500.0"
    for name, design, limit in (
        ("margin_without_mount", envelope, "stability_margin = { min = 0.1 }"),
        ("margin_mount_zero", envelope + "\nmount_mass = 0.0", "stability_margin = { min = 0.1 }"),
        ("return_without_envelope", "m = 1500.0", "return_time = { max = 2.5 }"),
        ("return_beyond_t1", envelope, "return_time = { max = 12.0 }"),
        ("t1_negative", envelope + "\nt1 = -1.0", ""),
    ):
        (tmp_path / f"{name}.toml").write_text(study.format(design=design, limit=limit))
    # Firing conditions (issue 54): what a user might write by mistake.
    for name, condition in (
        ("condition_elevation_95", 'name = "a"\nelevation = 95.0'),
        ("condition_tuned", 'name = "a"\nc_out = 1e4'),
        ("condition_unknown", 'name = "a"\nelevaton = 5.0'),
        ("condition_not_number", 'name = "a"\nelevation = "high"'),
        (
            "condition_limit_unknown",
            'name = "a"\nelevation = 5.0\nconstraints = { peak_displacment = { max = 1.0 } }',
        ),
        (
            "condition_limit_parameter",
            'name = "a"\nelevation = 5.0\nconstraints = { m = { max = 1.0 } }',
        ),
        (
            "condition_twice",
            'name = "a"\nelevation = 5.0\n[[condition]]\nname = "a"\nelevation = 9.0',
        ),
    ):
        text = study.format(design=envelope, limit="") + "[[condition]]\n" + condition + "\n"
        (tmp_path / f"{name}.toml").write_text(text)
    text = study.format(design=envelope, limit="") + '[[condition]]\nname = "a"\nv0 = 9.0\n'
    mixed = text + '[[condition]]\nname = "b"\nelevation = 70.0\n'
    (tmp_path / "condition_mixed.toml").write_text(mixed)
    (tmp_path / "condition_and_scatter.toml").write_text(
        text.replace("[constraints]", "[objective.scatter]\nv0 = [-0.05, 0.05]\n[constraints]")
    )
    return tmp_path


@pytest.fixture
def no_solve(monkeypatch):
    """Fail a test that would solve (or compile) anything."""

    def refuse(*args, **kwargs):
        raise AssertionError("a bad input reached the solver")

    monkeypatch.setattr(rj, "peaks", refuse)
    monkeypatch.setattr(rj, "sweep", refuse)
    monkeypatch.setattr(rj, "sweep_grid", refuse)


def _refused(capsys, argv, fragment, status=2):
    assert main(argv) == status
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, captured.err  # one line, no traceback
    assert lines[0].startswith("recoil-jax: error:") and fragment in lines[0], lines[0]
    assert captured.out == ""


@pytest.mark.parametrize(
    "argv, fragment",
    [
        (["simulate", "--force-table", "binary.csv"], "is not a text file (UTF-8)"),
        (["simulate", "--force-table", "folder"], "is a folder, not a file"),
        (["simulate", "--force-table", "missing.csv"], "force table"),
        (["sweep", "m=0,100", "--force-table", "binary.csv"], "is not a text file (UTF-8)"),
        (["sweep", "--points", "missing.csv"], "points file"),
        (["sweep", "--points", "binary.csv"], "is not a text file"),
        (["sweep", "--points", "folder"], "is a folder"),
        (["sweep", "--points", "twice.csv", "--out", "out"], "the column 'm' is given twice"),
        (["sweep", "--points", "ragged.csv"], "point 1: 1 values for the 2 columns"),
        (["sweep", "--points", "twice.json"], "m is given twice"),
        (["sweep", "--points", "broken.json"], "not valid JSON"),
        (["sweep", "--points", "empty.csv"], "no designs"),
        (["optimise", "binary.csv"], "is not a text file"),
        (["simulate", "--plot", "history.txt"], "cannot write a figure to history.txt"),
        (["simulate", "orifice_0=1e-3", "orifice_0=2e-3"], "orifice_0 is given twice"),
        (["sweep", "m=100,200", "m=300,400"], "m is given twice"),
        (["simulate", "orifice_32=1e-3"], "the orifice has at most 32 knots"),
        (["sweep", "orifice_40=1e-3,2e-3"], "the orifice has at most 32 knots"),
        (["simulate", "--max-steps", "0"], "valid max_steps is an integer from 1 to 2,147,483,647"),
        # Loads that cannot fit: refused before compiling, not after minutes.
        (["simulate", "--force-table", "long.csv"], "70,000 breakpoints"),
        (["simulate", "pulse_time=5"], "the pulse of the last round lasts until 50 s"),
        (["simulate", "--force-table", "bom.csv", "t1=0.003"], "lasts until 0.004 s"),
        (["simulate", "shots=3", "t1=0.9"], "the last of 3 rounds fires at 1 s"),
        # The firing envelope's metrics only where the design has what they measure.
        (["simulate", "elevation=95"], "elevation"),
        (["simulate", "friction_coefficient=-0.1"], "friction_coefficient"),
        (["simulate", "recuperator_preload=2e4", "recuperator_length=1.8"], "battery stop"),
        (["simulate", "mount_mass=1000"], "mount_mass"),
        (["optimise", "margin_without_mount.toml"], "stability_margin needs a mount"),
        (["optimise", "margin_mount_zero.toml"], "stability_margin needs a mount"),
        (["optimise", "return_without_envelope.toml"], "a metric of the firing envelope"),
        (["optimise", "return_beyond_t1.toml"], "is not below the 10 s the solve sees"),
        (["optimise", "t1_negative.toml"], "[design] t1 = -1.0: valid > 0 s"),
        (["optimise", "condition_elevation_95.toml"], "elevation"),
        (["optimise", "condition_tuned.toml"], "sets c_out, which is tuned"),
        (["optimise", "condition_unknown.toml"], "elevaton"),
        (["optimise", "condition_not_number.toml"], "elevation = 'high': valid a number"),
        (["optimise", "condition_limit_unknown.toml"], "peak_displacment"),
        (["optimise", "condition_limit_parameter.toml"], "metrics only, not the parameter m"),
        (["optimise", "condition_twice.toml"], "two conditions share a name"),
        (["optimise", "condition_and_scatter.toml"], "cannot both be given"),
        (["optimise", "condition_mixed.toml"], "'b' does not set v0"),
    ],
)
def test_a_bad_input_is_one_line_and_exit_status_2(
    capsys, files, no_solve, monkeypatch, argv, fragment
):
    monkeypatch.chdir(files)
    _refused(capsys, argv, fragment)
    assert not (files / "history.txt").exists() and not (files / "out").exists()


def test_a_load_that_does_not_fit_is_refused_by_the_library_too():
    with pytest.raises(rj.ParameterError, match="70,000 breakpoints"):
        table = rj.ForceTable(t=np.linspace(0, 0.01, 70_000), F=np.ones(70_000))
        rj.peaks(rj.with_table(rj.params_from_values(shots=1), table))
    with pytest.raises(rj.ParameterError, match=r"t1 >= 0.2 s"):
        rj.peaks(rj.params_from_values(pulse_time=0.02), options=rj.SolverOptions(t1=0.1))
    with pytest.raises(rj.ParameterError, match=r"\(design 2\).*lasts until 50 s"):
        rj.sweep({"m": [100.0, 200.0, 300.0], "pulse_time": [0.0, 0.001, 5.0]})
    # A generous step limit admits the table (checked, not solved, here).
    table = rj.ForceTable(t=np.linspace(0, 0.01, 70_000), F=np.ones(70_000))
    params = rj.with_table(rj.params_from_values(shots=1), table)
    rjx.end_time(params, rj.SolverOptions(max_steps=200_000))


def test_a_table_saved_by_a_spreadsheet_is_read_and_described(capsys, files, monkeypatch):
    """A byte-order mark and CRLF lines are read; `--json` lists the table (its points,
    length and impulse: the trapezoid of the file) instead of the `v0` and `pulse_time`
    it replaces, and writes the number of rounds as an integer."""
    monkeypatch.chdir(files)
    assert main(["simulate", "m=0", "--force-table", "bom.csv", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    used = out["parameters"]
    assert "v0" not in used and "pulse_time" not in used
    assert used["force_table"] == {
        "file": "bom.csv",
        "points": 3,
        "duration_s": 0.004,
        "impulse_N_s": pytest.approx(0.5 * 0.004 * 1.5e6),
    }
    assert used["shots"] == 1 and isinstance(used["shots"], int)
    # The momentum the table delivers moves the barrel: the peak displacement of the
    # plain barrel scales with the impulse against the paper's M v0.
    assert out["status"] == "ok" and out["peak_displacement_m"] > 0


def test_figure_titles_say_what_the_load_is():
    one = {"m": 0.0, "shots": 1, "fire_interval": 0.5, "force_table": {}}
    assert describe(one) == "no absorber, 1 round of the force table"
    burst = {"m": 1500.0, "gap": 0.05, "shots": 3, "fire_interval": 0.2, "pulse_time": 0.005}
    assert describe(burst) == "absorber m=1500 kg, gap=50 mm, 3 rounds of a 5 ms pulse every 0.2 s"
    impulse = {"m": 0.0, "shots": 2, "fire_interval": 0.5, "pulse_time": 0.0}
    assert describe(impulse) == "no absorber, 2 rounds of an impulse every 0.5 s"


def test_values_outside_the_documented_range_are_warned_about():
    table = rj.ForceTable(t=[0.0, 0.001, 0.002], F=[0.0, -5.0, 1e6])
    lines = design_warnings(
        {"m": 1e8, "piston_area": 100.0, "oil_density": 1e9, "orifice_0": 1e3, "gap": 0.05},
        table,
    )
    text = "\n".join(lines)
    assert "m=1e+08 is outside the documented range 10 to 5000 kg" in text
    assert "piston_area=100 is outside the documented range 0 to 0.02 m^2" in text
    assert "oil_density=1e+09" in text and "orifice_0=1000" in text
    assert "F = -5 N < 0 at t = 0.001 s" in text
    assert "gap" not in text
    # m = 0 is the simplified model, not a mass; unused values are said to be unused.
    assert design_warnings({"m": 0.0}) == []
    (buffer,) = design_warnings({"piston_area": 0.0, "orifice_0": 1e-4, "orifice_1": 1e-4})
    assert "no hydraulic buffer" in buffer and "orifice_0, orifice_1" in buffer
    (gas,) = design_warnings({"recuperator_force": 0.0, "recuperator_length": 0.05})
    assert "no gas recuperator: recuperator_length has no effect" in gas
    # A preload uses the gas column (issue 54); a mount's geometry needs its mass.
    preload = {"recuperator_preload": 3e4, "stop_stiffness": 2e8, "recuperator_length": 1.5}
    assert design_warnings(preload) == []
    (mount,) = design_warnings({"cg_distance": 3.0, "spade_distance": 2.0})
    assert mount == "mount_mass = 0 is no mount: cg_distance, spade_distance have no effect"
    # A sweep: how many of its values lie outside.
    (sweep,) = design_warnings({"m": np.array([0.0, 100.0, 6000.0, 7000.0])})
    assert sweep.startswith("m: 2 of 3 values (e.g. m=6000) are outside the documented")
    # The end time's documented range warns as the parameters' do (#45).
    (short,) = design_warnings({"t1": 0.05})
    assert short.startswith("t1=0.05 is outside the documented range 0.1 to 60 s")
    (long,) = design_warnings({"t1": np.array([1.0, 1e6])})
    assert long.startswith("t1: 1 of 2 values (e.g. t1=1e+06) are outside the documented")
    assert design_warnings({"t1": None}) == design_warnings({"t1": 2.0}) == []


def test_simulate_warns_of_an_end_time_outside_its_documented_range(capsys):
    assert main(["simulate", "m=0", "t1=0.05", "--json"]) == 0
    err = capsys.readouterr().err
    assert "t1=0.05 is outside the documented range 0.1 to 60 s" in err


def test_a_zero_recuperator_force_is_no_recuperator(capsys):
    """`recuperator_force = 0` is documented as no recuperator: a short gas column then
    bottoms nothing, and the peaks are those of the design without one."""
    plain = rj.peaks(rj.params_from_values(m=0.0))
    params = rj.params_from_values(m=0.0, recuperator_force=0.0, recuperator_length=0.05)
    zero = rj.peaks(params)
    for field in ("peak_displacement", "peak_anchoring_force"):
        assert float(getattr(zero, field)) == pytest.approx(float(getattr(plain, field)), rel=1e-6)
    reference = rj.reference_peaks({"m": 0.0, "recuperator_force": 0.0, "recuperator_length": 0.05})
    assert reference["status"] == "ok"
    assert main(["simulate", "m=0", "recuperator_force=0", "recuperator_length=0.05"]) == 0
    err = capsys.readouterr().err
    assert "no gas recuperator" in err and "documented range" not in err


def test_the_step_limit_can_be_raised_from_the_command_line(capsys):
    assert main(["simulate", "m=0", "--max-steps", "5"]) == 1
    err = capsys.readouterr().err
    assert "max_steps reached" in err and "--max-steps" in err


def test_a_missing_optional_dependency_is_named_with_its_extra(capsys, monkeypatch):
    """The core install leaves out the `apps` extra (panel, cmaes, flatbuffers): a
    command that needs one says which and how to install it."""
    monkeypatch.setitem(sys.modules, "panel", None)  # as if not installed
    assert main(["explore", "--no-browser"]) == 2
    err = capsys.readouterr().err
    assert "explore needs panel (the design explorer)" in err and "recoil-jax[apps]" in err
    monkeypatch.setitem(sys.modules, "cmaes", None)
    assert main(["bench-tuning", "tuned_absorber", "--methods", "cma_es"]) == 2
    assert "bench-tuning needs cmaes" in capsys.readouterr().err


def test_peaks_solve_in_process_without_flatbuffers(monkeypatch, tmp_path):
    """Without flatbuffers no program can be kept exported on disk: `rj.peaks` (and so
    `simulate`) compiles in process, gives the same peaks and writes no exported file."""
    from recoil_jax._model import programs

    params = rj.params_from_values(m=0.0)
    expected = rj.peaks(params).to_dict()
    drop_programs()  # so that the next call builds its program again
    monkeypatch.setitem(sys.modules, "flatbuffers", None)
    monkeypatch.setattr(programs, "_export_folder", lambda: str(tmp_path))
    assert rj.peaks(params).to_dict() == expected
    assert not (tmp_path / "exported").exists()


def test_inputs_beyond_what_a_run_can_hold_are_one_line(tmp_path, capsys):
    """#45: a number beyond float64 is named as typed (not as `inf`); a step limit beyond
    a step counter, a header-only force table and an empty store file each get one line,
    exit 2, before any solve; the empty file is not written to."""

    def refused(argv) -> str:
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "Traceback" not in err, err
        return err

    assert "m = '1e309' is not a number: beyond the largest float64" in refused(
        ["simulate", "m=1e309"]
    )
    assert "m='1e309,2': expected a number" in refused(["sweep", "m=1e309,2", "gap=0.05"])
    assert "beyond the largest float64" in refused(["sweep", "m=1:1e400:3", "gap=0.05"])
    assert "valid max_steps is an integer from 1 to 2,147,483,647" in refused(
        ["simulate", "--max-steps", "99999999999999999999"]
    )
    table = tmp_path / "header_only.csv"
    table.write_text("t_s,F_N\n")
    assert "no rows of t_s,F_N values" in refused(["simulate", "--force-table", str(table)])
    empty = tmp_path / "empty.sqlite"
    empty.touch()
    assert "is empty: not a recoil-jax store" in refused(["progress", str(empty)])
    assert empty.stat().st_size == 0


def test_an_output_folder_that_cannot_be_written_is_refused_before_any_solve(tmp_path, capsys):
    """#45: `--out` an existing file, through a file, or in a place that cannot be made:
    one line, exit 2, for every command that writes a folder, before anything runs."""
    a_file = tmp_path / "results.txt"
    a_file.write_text("not a folder")
    commands = (
        ["sweep", "m=100,200", "gap=0.05", "--out"],
        ["optimise", "paper_gap", "--out"],
        ["reproduce", "--out"],
    )
    places = {
        str(a_file): "is a file, not a folder",
        str(a_file / "sub"): "a part of the path is a file",
        "/proc/recoil-jax-out": "cannot be made",
    }
    for command in commands:
        for place, message in places.items():
            assert main([*command, place]) == 2, (command, place)
            err = capsys.readouterr().err
            assert message in err and err.count("\n") == 1 and "Traceback" not in err, err
    # A missing folder is simply made.
    new = tmp_path / "new" / "deeper"
    from recoil_jax.apps._files.inputs import output_folder

    assert output_folder(new) == new and new.is_dir()


def test_a_bad_value_is_refused_the_same_way_on_every_path(tmp_path, capsys):
    """One validation of a parameter's value: the command line, a sweep, a study's
    [design], a calibration file's [design], the calibration's quick form and a
    sensitivity file's [design] each refuse `c_out = -5` with the model's own words,
    exit 2, before anything is solved."""
    # (A batch names the design's index too: `c_out[0]`.)
    said = re.compile(r"Barrel\.c_out(\[\d+\])? = -5 N\*s/m is invalid \(out of range\): "
                      r"valid c_out >= 0 N\*s/m")  # fmt: skip
    ts = np.linspace(0.0, 0.5, 51)
    trace = tmp_path / "firing.csv"
    trace.write_text("t,x_M\n" + "".join(f"{float(t)!r},{0.01 * float(t)!r}\n" for t in ts))
    (tmp_path / "study.toml").write_text(
        "[design]\nc_out = -5.0\n[tune]\ngap = [0.0, 0.1]\n"
        "[objective]\npeak_anchoring_force = 1.0\n"
    )
    (tmp_path / "cal.toml").write_text(
        '[design]\nc_out = -5.0\n[fit]\nk = [1e4, 1e5]\n[[experiment]]\ntrace = "firing.csv"\n'
    )
    (tmp_path / "tolerances.toml").write_text(
        "[design]\nc_out = -5.0\n[ranges]\nk = { relative = 0.1 }\n"
        '[metrics]\nnames = ["peak_anchoring_force"]\n[method]\nname = "morris"\n'
    )
    commands = [
        ["simulate", "c_out=-5"],
        ["sweep", "c_out=-5", "m=0,500"],
        ["optimise", str(tmp_path / "study.toml"), "--out", str(tmp_path / "o")],
        ["calibrate", str(tmp_path / "cal.toml"), "--out", str(tmp_path / "c")],
        ["calibrate", str(trace), "--fit", "k", "c_out=-5", "--out", str(tmp_path / "q")],
        ["sensitivity", str(tmp_path / "tolerances.toml"), "--out", str(tmp_path / "s")],
    ]
    for command in commands:
        assert main(command) == 2, command
        err = capsys.readouterr().err
        assert said.search(err) and err.count("\n") == 1, (command, err)
