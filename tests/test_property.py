"""The command line's whole surface against generated mistakes (hypothesis): command
lines and files from a grammar of what a user gets wrong (numbers, ranges, names,
paths, file contents, encodings, options), run in-process through `main` with every
solve stubbed out. Each run either reaches a solve (its input was accepted) or ends with
a documented status, one `recoil-jax: error:` line (warnings aside) and no traceback,
well within 30 s: every check happens before anything is solved.

CI runs a fixed set of 150 (`derandomize`); `RECOIL_JAX_EXAMPLES=2000 pytest
tests/test_property.py` runs 2000 new ones. The examples database is off (nothing is
written into the repository).
"""

from __future__ import annotations

import contextlib
import io
import os
import string
import tempfile
import time
from pathlib import Path

import pytest

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import (  # noqa: E402
    HealthCheck,
    given,
    settings,
    strategies as st,
)

import recoil_jax as rj  # noqa: E402
from recoil_jax.apps import main  # noqa: E402

EXAMPLES = int(os.environ.get("RECOIL_JAX_EXAMPLES", "150"))
#: CI: the same examples every run; on demand (RECOIL_JAX_EXAMPLES given), new ones.
FIXED = "RECOIL_JAX_EXAMPLES" not in os.environ


class Reached(BaseException):
    """A solve was about to start: the input was accepted."""


def _reached(*args, **kwargs):
    raise Reached


SOLVES = ["peaks", "simulate", "sweep", "sweep_grid", "sweep_to_store", "search",
          "optimise", "calibrate", "sensitivity", "predict", "plan_firings"]  # fmt: skip

# --- the grammar ----------------------------------------------------------------------

ROOT = Path(__file__).resolve().parents[1]
names = st.sampled_from(
    [*rj.PARAMETERS, "t1", "M", "mass", "Gap", "orifice_99", "k ", "", "x_M", "objective"]
)
numbers = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0, -1, 1, 1e-300, 1e309, -1e309, 5600, 0.062, 1e12, 2**63]),
    st.integers(-(10**20), 10**20),
)
MISTAKES = ["", " ", "abc", "1,2", "1:2", "1:2:3", "0:1:0", "1:2:-5", "0x10", "1e", "--1",
            "٣", "1_000", "nan", "inf", "1:2:99999999999", "0:1:100000000000", ",", "1,,2",
            "1;2"]  # fmt: skip
number_texts = st.one_of(numbers.map(repr), st.sampled_from(MISTAKES))
assignments = st.builds(lambda n, v: f"{n}={v}", names, number_texts)
junk = st.text(string.printable + "éß€\ufeff\x00", max_size=60)
TOML_VALUES = ['"text"', "true", "[]", "{}", "[1.0]", "[0.0, 1.0]", "[1.0, 0.0]",
               "[0.0, 1.0, 5]", "{ relative = 0.1 }", "{ relative = 2 }", '"sobol"',
               '"search"', "-1", "1e400", "[[1]]"]  # fmt: skip
toml_values = st.one_of(
    numbers.map(lambda x: repr(x) if x == x else "nan"), st.sampled_from(TOML_VALUES)
)


def _toml_file(sections: list[str], keys: list[str]):
    """Sections of `key = value` lines, drawn from names a user might use."""
    line = st.builds(lambda k, v: f"{k} = {v}", st.sampled_from(keys), toml_values)
    section = st.builds(
        lambda name, lines: f"[{name}]\n" + "\n".join(lines),
        st.sampled_from(sections),
        st.lists(line, max_size=4),
    )
    tails = st.sampled_from(["", "\n", "\n[[", "\x00"])
    return st.builds(lambda parts, tail: "\n".join(parts) + tail, st.lists(section, max_size=5),
                     tails)  # fmt: skip


def _mutated(folder: str, texts: list[str] | None = None):
    """A shipped file (or one of `texts`) with one line dropped, or one value replaced by
    a mistake: the checks deep inside a file that is otherwise right."""
    texts = texts or [p.read_text() for p in sorted((ROOT / folder).glob("*.toml"))]

    def mutate(text: str, line: int, value: str, drop: bool) -> str:
        lines = text.splitlines()
        i = line % len(lines)
        if drop:
            del lines[i]
        elif "=" in lines[i]:
            lines[i] = lines[i].split("=")[0] + "= " + value
        return "\n".join(lines)

    values = st.one_of(toml_values, number_texts.map(repr))
    return st.builds(mutate, st.sampled_from(texts), st.integers(0, 200), values, st.booleans())


STUDY_KEYS = [*rj.PARAMETERS, "peak_anchoring_force", "peak_displacement", "method", "steps",
              "samples", "starts", "seed", "local", "grid", "hard", "vary", "values", "max",
              "min", "from", "points", "minimax", "learning_rate", "quantile"]  # fmt: skip
STUDY_SECTIONS = ["design", "tune", "objective", "constraints", "optimiser", "check",
                  "calibration", "objective.temperatures", "bogus"]  # fmt: skip
study_files = st.one_of(_toml_file(STUDY_SECTIONS, STUDY_KEYS), _mutated("optimise"))
SENSITIVITY_KEYS = [*STUDY_KEYS, "names", "objective", "study", "name", "second_order",
                    "trajectories", "levels", "resamples", "sigmas"]  # fmt: skip
sensitivity_files = st.one_of(
    _toml_file(["design", "ranges", "metrics", "method", "calibration", "bogus"],
               SENSITIVITY_KEYS),
    _mutated("sensitivity"),
)  # fmt: skip
PLAN_KEYS = [*rj.PARAMETERS, "description", "robust", "seed", "sigma", "cost", "rate",
             "duration", "firings", "criterion", "x_M", "F_AN", "v_M"]  # fmt: skip
plan_files = st.one_of(
    _toml_file(["design", "fit", "candidates", "signals", "sampling", "budget", "bogus"],
               PLAN_KEYS),
    _mutated("optimise/plans"),
)  # fmt: skip
#: What `plan` writes for a test of the envelope gun (its `calibration.toml`), traces
#: named as it names them: mutated, the skeleton a user edits.
SKELETON = """description = "calibration of the planned test: the envelope gun"
[design]
M = 1800.0
m = 0.0
k = 0.0
v0 = 10.0
pulse_time = 0.004
stop_stiffness = 210000000.0
recuperator_length = 1.8
buffer_length = 0.15
buffer_damping = 150000.0
[fit]
c_out = { bounds = [5000.0, 50000.0], start = 16000.0 }
c_ret = { bounds = [5000.0, 50000.0], start = 15000.0 }
recuperator_preload = { bounds = [10000.0, 60000.0], start = 30000.0 }
friction_force = { bounds = [0.0, 5000.0], start = 1500.0 }
friction_coefficient = { bounds = [0.0, 0.2], start = 0.05 }
[[experiment]]
trace = "trace.csv"
elevation = 0.0
v0 = 10.0
t1 = 3.0
sigma = { x_M = 0.0003, F_AN = 200.0 }
[[experiment]]
trace = "trace.csv"
elevation = 70.0
v0 = 8.0
t1 = 3.0
sigma = { x_M = 0.0003 }
"""
CALIBRATION_KEYS = [*rj.PARAMETERS, "trace", "sigma", "per_experiment", "window", "name",
                    "starts", "seed", "fit_steps", "description", "loss", "f_scale",
                    "force_table"]  # fmt: skip
calibration_files = st.one_of(
    _toml_file(["design", "fit", "[experiment]", "[validation]", "bogus"], CALIBRATION_KEYS),
    st.builds(
        lambda top, fit, count: f"{top}\n[fit]\n{fit}\n"
        + '[[experiment]]\ntrace = "trace.csv"\n' * count,
        st.sampled_from(["", "starts = 1000000000", "fit_steps = 1000000000000",
                         "description = [1, 2]", "[design]\nk = 3e4", "starts = 4"]),
        st.sampled_from(["k = [1e4, 1e5]", "k = [1e5, 1e4]", "v0 = [0.5, 0.8]"]),
        st.sampled_from([0, 1, 2, 300]),
    ),
    _mutated("", [SKELETON]),
)  # fmt: skip
csv_files = st.one_of(
    junk,
    st.builds(
        lambda header, rows, bom, end: ("\ufeff" if bom else "") + end.join([header, *rows]),
        st.sampled_from(["t,x_M", "t,F_AN", "t_s,F_N", "t,x_M,F_AN", "t,bogus", "x_M,t", "t",
                         "", "t;x_M", "t,x_M,x_M"]),
        st.lists(st.builds(lambda a, b: f"{a},{b}", number_texts, number_texts), max_size=6),
        st.booleans(),
        st.sampled_from(["\n", "\r\n", "\r"]),
    ),
)  # fmt: skip


@st.composite
def command_lines(draw, folder: Path):
    """A command line, with the files it names written into `folder`."""

    def file(name: str, content) -> str:
        path = folder / name
        data = draw(content)
        path.write_bytes(data.encode("utf-8", "surrogatepass"))
        return str(path)

    (folder / "f.txt").write_text("a file")
    # What is not a regular file: read, each would never end (a FIFO without a writer
    # waits forever; /dev/zero and /dev/urandom never run out).
    specials = ["/dev/zero", "/dev/urandom"]
    if hasattr(os, "mkfifo"):
        os.mkfifo(folder / "fifo")
        specials.append(str(folder / "fifo"))
    paths = st.sampled_from([str(folder), str(folder / "missing" / "x"), "/proc/x",
                             str(folder / "f.txt"), "", str(folder / "out"),
                             *specials])  # fmt: skip
    inputs = st.sampled_from(specials)
    command = draw(st.sampled_from(["simulate", "sweep", "optimise", "sensitivity",
                                    "calibrate", "progress", "plan"]))  # fmt: skip
    argv = [command, "--no-cache"]
    if command == "simulate":
        argv += draw(st.lists(assignments, max_size=4))
        if draw(st.booleans()):
            argv += ["--max-steps", draw(number_texts)]
        if draw(st.booleans()):
            argv += ["--plot", draw(st.one_of(paths, st.just(str(folder / "h.pdf2"))))]
        if draw(st.booleans()):
            argv += ["--force-table", file("table.csv", csv_files)]
    elif command == "sweep":
        argv += draw(st.lists(assignments, max_size=4))
        if draw(st.booleans()):
            argv += ["--points", file("points.csv", csv_files)]
        if draw(st.booleans()):
            argv += ["--out", draw(paths)]
        if draw(st.booleans()):
            argv += ["--store", draw(st.one_of(paths, st.just(file("s.sqlite", junk))))]
        if draw(st.booleans()):
            argv += ["--workers", draw(st.sampled_from(["0", "-3", "x"]))]
        if draw(st.booleans()):
            argv += ["--scheduler", draw(st.sampled_from(["", "garbage!!", "http://h:1"]))]
    elif command == "optimise":
        argv += [file("study.toml", study_files), "--out", str(folder / "out")]
        if draw(st.booleans()):
            argv += ["--seed", draw(number_texts)]
    elif command == "plan":
        argv += [file("plan.toml", plan_files), "--out",
                 draw(st.one_of(st.just(str(folder / "out")), paths))]  # fmt: skip
        if draw(st.booleans()):
            argv += ["--check", draw(number_texts)]
        if draw(st.booleans()):
            argv += ["--seed", draw(number_texts)]
    elif command == "sensitivity":
        source = st.one_of(st.just(file("s.toml", sensitivity_files)), inputs)
        argv += [draw(source), "--out", str(folder / "out")]
        if draw(st.booleans()):
            argv += ["--store", draw(st.one_of(paths, st.just(file("c.sqlite", junk))))]
    elif command == "calibrate" and draw(st.booleans()):  # a calibration file
        file("trace.csv", csv_files)
        argv += [file("c.toml", calibration_files)]
        argv += draw(st.lists(assignments, max_size=1))
        if draw(st.booleans()):
            argv += ["--starts", draw(number_texts)]
    elif command == "calibrate":
        argv += [draw(st.one_of(st.just(file("trace.csv", csv_files)), inputs))]
        argv += ["--fit", draw(st.sampled_from(["k", "k,c_out", "", "bogus", "t_shift,k",
                                                "k,k", "k,v0"]))]  # fmt: skip
        argv += draw(st.lists(assignments, max_size=2))
        if draw(st.booleans()):
            argv += ["--starts", draw(number_texts)]
        if draw(st.booleans()):
            argv += ["--validate", draw(st.one_of(paths, st.just(file("v.csv", csv_files))))]
        if draw(st.booleans()):
            argv += ["--predict", *draw(st.lists(assignments, min_size=1, max_size=2))]
        if draw(st.booleans()):
            argv += ["--store", draw(st.one_of(paths, st.just(file("c.sqlite", junk))))]
        if draw(st.booleans()):
            argv += ["--force-table", file("table.csv", csv_files)]
    else:
        argv += [draw(st.one_of(paths, st.just(file("p.sqlite", junk))))]
    if draw(st.booleans()):
        argv.append("--json")
    return argv


@pytest.fixture(scope="module")
def stubbed():
    with pytest.MonkeyPatch.context() as patch:
        for name in SOLVES:
            patch.setattr(rj, name, _reached)
        yield


@settings(
    max_examples=EXAMPLES, deadline=None, derandomize=FIXED, database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture,
                           HealthCheck.data_too_large],
)  # fmt: skip
@given(data=st.data())
def test_every_mistake_is_one_line_and_a_documented_status(stubbed, data):
    with tempfile.TemporaryDirectory() as folder:
        argv = data.draw(command_lines(Path(folder)))
        err, out = io.StringIO(), io.StringIO()
        started = time.perf_counter()
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
            try:
                status = main(argv)
            except Reached:
                hypothesis.event(f"{argv[0]}: accepted")
                return  # accepted: a solve would start
            except SystemExit as exit:  # argparse: its usage line and status 2
                assert exit.code == 2, argv
                return
        seconds = time.perf_counter() - started
        hypothesis.event(f"{argv[0]}: status {status}")
        lines = [line for line in err.getvalue().splitlines() if line.strip()]
        errors = [line for line in lines if line.startswith("recoil-jax: error:")]
        assert status in (0, 1, 2), (argv, status, lines)
        if status == 2:
            assert len(errors) == 1, (argv, lines)
        others = [line for line in lines if line not in errors]
        assert all(
            line.startswith(("recoil-jax: warning:", "sweep:", "study ")) for line in others
        ), (
            argv,
            lines,
        )
        assert "Traceback" not in err.getvalue()
        assert seconds < 30.0, (argv, seconds)  # checks, not solves: well under a second
