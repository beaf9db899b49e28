"""The `recoil-jax` command line."""

import argparse
import csv
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import recoil_jax as rj
import recoil_jax.extend as rjx
from recoil_jax.apps import main
from recoil_jax.apps._cli import build_parser

REQUIRED_KEYS = {
    "peak_displacement_m",
    "peak_displacement_time_s",
    "peak_anchoring_force_N",
    "peak_anchoring_force_time_s",
    "peak_contact_force_N",
}


def _run_json(capsys, *argv):
    assert main(["simulate", *argv, "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_simulate_json_matches_python_api(capsys):
    out = _run_json(capsys, "m=1000", "gap=0.059")
    assert REQUIRED_KEYS <= set(out)
    expected = rj.peaks(rj.params_from_values(m=1000.0, gap=0.059)).to_dict()
    for key in REQUIRED_KEYS:
        assert out[key] == pytest.approx(expected[key], rel=1e-12)
    assert out["peak_anchoring_force_N"] == pytest.approx(6017.82, rel=1e-4)  # Table 2
    assert out["parameters"]["gap"] == 0.059 and out["model"] == "smoothed"


def test_simulate_simplified_and_hard(capsys):
    out = _run_json(capsys, "m=0")
    assert out["peak_displacement_m"] == pytest.approx(0.221477, rel=1e-5)
    assert out["peak_contact_force_N"] == 0.0
    # The text lists what the design has: no contact or stroke rows without an absorber.
    assert main(["simulate", "m=0"]) == 0
    text = capsys.readouterr().out
    assert "peak anchoring force" in text and "0.221477 m" in text
    assert "contact" not in text and "stroke" not in text
    assert main(["simulate", "m=1000", "gap=0.059"]) == 0
    text = capsys.readouterr().out
    assert "peak contact force" in text and "absorber stroke" in text
    hard = _run_json(capsys, "m=500", "gap=0", "--hard", "t1=2")
    assert hard["model"] == "hard" and hard["parameters"]["t1"] == 2.0
    assert hard["peak_anchoring_force_N"] == pytest.approx(6661.40, rel=1e-5)


def test_simulate_table_and_plot(capsys, tmp_path):
    plot = tmp_path / "history.png"
    assert main(["simulate", "m=1500", "gap=0.062", "--plot", str(plot)]) == 0
    out = capsys.readouterr().out
    assert "peak anchoring force" in out and "5514" in out
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_simulate_csv_is_a_trace_that_reads_back_and_calibrates(capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["simulate", "--csv", "firing.csv"]) == 0  # the paper's best design
    assert "wrote firing.csv" in capsys.readouterr().err
    trace = rj.read_trace("firing.csv")
    params = rj.RecoilParams()
    ts = np.linspace(0.0, float(rjx.end_time(params, rj.SolverOptions())), 20001)
    history = rj.simulate(params, ts=ts)
    np.testing.assert_array_equal(trace.t, ts)
    assert list(trace.signals) == list(rjx.SIGNALS) and trace.skipped == dict.fromkeys(
        rjx.SIGNALS, 0
    )
    for name, values in trace.signals.items():
        np.testing.assert_allclose(values, getattr(history, name), rtol=1e-12, atol=1e-12)
    # calibrate fits it (the default folder named after the trace) to the true stiffness.
    assert main(["calibrate", "firing.csv", "--fit", "k", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["fitted"]["k"]["value"] == pytest.approx(27500.0, rel=1e-5)
    assert (tmp_path / "results" / "calibrate" / "firing" / "result.json").exists()
    # Without an absorber, only the signals the design has.
    assert main(["simulate", "m=0", "--csv", "plain.csv"]) == 0
    assert (tmp_path / "plain.csv").read_text().splitlines()[0] == "t,x_M,v_M,F_AN"


@pytest.mark.parametrize(
    ("path", "message"),
    [
        ("{tmp}/file.txt/h.csv", "--csv's folder {tmp}/file.txt is a file, not a folder"),
        ("/proc/recoil/h.csv", "--csv's folder /proc/recoil cannot be made"),
        ("{tmp}", "--csv {tmp} is a folder: give a file"),
    ],
)
def test_simulate_refuses_a_csv_it_cannot_write_before_solving(capsys, tmp_path, path, message):
    (tmp_path / "file.txt").write_text("a file")
    path, message = (x.replace("{tmp}", str(tmp_path)) for x in (path, message))
    assert main(["simulate", "--csv", path, "--max-steps", "1"]) == 2  # 1 step would fail
    err = capsys.readouterr().err
    assert message in err and err.startswith("recoil-jax: error:") and err.count("\n") == 1


def test_no_help_escapes_a_percent_sign(capsys):
    # argparse expands % in an option's help, not in a description: "%%" there is printed.
    parser = build_parser()
    commands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for command in [[], *([name] for name in commands.choices)]:
        with pytest.raises(SystemExit):
            main([*command, "--help"])
        text = capsys.readouterr().out
        assert "usage: recoil-jax" in text and "%%" not in text, command
    assert "95% intervals" in commands.choices["calibrate"].format_help()


@pytest.mark.parametrize(
    "argv, fragment",
    [
        (["gap=-1"], "Absorber.gap = -1 m is invalid"),
        (["t1=0"], "SolverOptions.t1 = 0 s is invalid"),
        (["n_c=0.5"], "valid n_c >= 1"),
        (["M=nan"], "must be finite"),
        (["mass=3"], "unknown parameter 'mass'"),
        (["gap"], "expected name=value"),
        (["gap=wide"], "gap = 'wide' is not a number"),
    ],
)
def test_simulate_bad_input(capsys, argv, fragment):
    assert main(["simulate", *argv]) == 2
    err = capsys.readouterr().err
    assert fragment in err and err.startswith("recoil-jax: error:")


def test_reproduce_writes_table_and_figures(capsys, tmp_path):
    assert main(["reproduce", "--out", str(tmp_path)]) == 0
    printed = capsys.readouterr().out
    assert "table2 m=1500 gap=62mm" in printed and "vs paper" in printed
    with open(tmp_path / "reproduce.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 9 * 5
    table2 = [r for r in rows if r["quantity"] == "peak_anchoring_force_N" and r["paper"]]
    assert len(table2) == 9
    assert all(abs(float(r["ours_vs_paper"])) < 0.01 for r in table2)
    for name in (
        "fig4_simplified_displacement",
        "fig7_contact_force_gap0",
        "fig8_contact_force_gap0_first_impact",
        "fig9_anchoring_force",
    ):
        assert (tmp_path / f"{name}.png").read_bytes()[:4] == b"\x89PNG"


def _console_script():
    beside_python = Path(sys.executable).parent / "recoil-jax"
    return str(beside_python) if beside_python.exists() else shutil.which("recoil-jax")


@pytest.mark.skipif(_console_script() is None, reason="console script not installed")
def test_console_script():
    script = _console_script()
    done = subprocess.run(
        [script, "simulate", "m=0", "--json"], capture_output=True, text=True, check=True
    )
    assert json.loads(done.stdout)["peak_anchoring_force_N"] == pytest.approx(6949.98, rel=1e-5)
    bad = subprocess.run([script, "simulate", "k_c=-1"], capture_output=True, text=True)
    assert bad.returncode == 2 and "Contact.k_c" in bad.stderr


def _cache_entries(folder: Path) -> set[str]:
    return {p.name for p in folder.rglob("*") if p.is_file()}


@pytest.mark.slow  # five processes, each starting JAX and compiling or loading its solve
@pytest.mark.skipif(_console_script() is None, reason="console script not installed")
def test_compilation_cache_makes_a_repeated_command_compile_nothing(tmp_path):
    """The first `simulate` writes its compiled (and exported) programs to the cache
    folder; the same command again, and another design, find every one of them there
    (no new entry) and print the peaks `rj.peaks` gives; `--no-cache` and
    RECOIL_JAX_CACHE=off write nothing."""
    script = _console_script()
    command = [script, "simulate", "m=1000", "gap=0.05", "--json"]
    cache = tmp_path / "cache"
    env = os.environ | {"RECOIL_JAX_CACHE": str(cache)}
    first = subprocess.run(command, capture_output=True, text=True, check=True, env=env)
    written = _cache_entries(cache)
    assert written, "the first run cached nothing"
    second = subprocess.run(command, capture_output=True, text=True, check=True, env=env)
    assert _cache_entries(cache) == written
    assert json.loads(second.stdout) == json.loads(first.stdout)
    # Another design of the same structure runs the same exported program: its peaks
    # are this process's `rj.peaks`, to the last digit.
    other_design = [script, "simulate", "m=500", "gap=0.044", "k_r=2e4", "--json"]
    third = subprocess.run(other_design, capture_output=True, text=True, check=True, env=env)
    assert _cache_entries(cache) == written
    params = rj.params_from_values(m=500.0, gap=0.044, k_r=2e4)
    expected = rj.peaks(params).to_dict()
    assert {k: json.loads(third.stdout)[k] for k in expected} == expected

    other = tmp_path / "other"
    subprocess.run(
        [*command, "--no-cache"],
        check=True,
        capture_output=True,
        env=env | {"RECOIL_JAX_CACHE": str(other)},
    )
    subprocess.run(
        command,
        check=True,
        capture_output=True,
        env=os.environ | {"RECOIL_JAX_CACHE": "off", "XDG_CACHE_HOME": str(other)},
    )
    assert not other.exists() or not _cache_entries(other)
