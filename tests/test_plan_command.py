"""`recoil-jax plan`: its file's refusals (one line, exit 2, before anything compiles), the
shipped example against the exhaustive optimum and the hand-drawn plans, what it writes,
and the calibration skeleton read by `calibrate` with the independent reference solver's
traces."""

import json
import re

import numpy as np
import pytest
import tomllib

import recoil_jax as rj
import recoil_jax.extend as rjx
from recoil_jax._planning.choose import exhaustive, greedy
from recoil_jax.apps import main
from recoil_jax.apps._studies.plan_file import SHIPPED, load_plan

EXAMPLE = SHIPPED / "envelope_friction.toml"


def _refused(capsys, argv, fragment):
    assert main(argv) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, captured.err  # one line, no traceback
    assert lines[0].startswith("recoil-jax: error:") and fragment in lines[0], lines[0]


def _edited(tmp_path, old: str, new: str) -> str:
    text = EXAMPLE.read_text()
    assert old in text, old
    path = tmp_path / "plan.toml"
    path.write_text(text.replace(old, new))
    return str(path)


@pytest.mark.parametrize(
    "old, new, fragment",
    [
        ("F_AN = { sigma", "F_XY = { sigma", "signals.F_XY: no such signal"),
        ("elevation = [0, 15,", "elevation = [0, 95,", "candidates.elevation = 95 deg is invalid"),
        ("cost = 4.0 ", "cost = 0.5 ", "budget.cost = 0.5: no firing fits"),
        ('name = "D"', 'name = "k"', "criterion = 'k': valid D, A or a fitted parameter"),
        ("c_ret = [5e3, 5e4]", "c_rett = [5e3, 5e4]", "fit: unknown parameter 'c_rett'"),
        ("c_out = [5e3, 5e4]", "c_out = [2e4, 5e4]", "the guess c_out = 16000 is outside"),
        ("v0 = [8.0, 10.0]", "c_out = [8.0, 10.0]", "candidates.c_out: c_out is fitted"),
        ("x_M = { sigma = 3e-4", "x_M = { sigma = -3e-4", "signals.x_M.sigma"),
        ("firings = 3", "firings = 0", "firings = 0"),
        ("duration = 3.0", "duration = 3000.0", "sampling.duration = 3000.0: valid 0.01 to 60"),
        ("[design]", "[design]\nelevation_deg = 3.0", "design: unknown parameter 'elevation_deg'"),
        ("[sampling]", "[samplings]", "unknown section 'samplings'"),
        ("x_M = { sigma = 3e-4, cost = 1.0 }", "x_m = { sigma = 3e-4 }", "absorber"),
    ],
)
def test_a_bad_plan_file_is_one_line(tmp_path, capsys, monkeypatch, old, new, fragment):
    def refuse(*args, **kwargs):
        raise AssertionError("planned a refused file")

    monkeypatch.setattr(rj, "plan_firings", refuse)
    _refused(capsys, ["plan", _edited(tmp_path, old, new), "--out", str(tmp_path / "o")], fragment)


def test_a_bad_check_count_and_a_missing_file_are_one_line(tmp_path, capsys):
    _refused(capsys, ["plan", str(EXAMPLE), "--check", "1"], "--check 1: valid 2 to 10,000")
    _refused(capsys, ["plan", str(EXAMPLE), "--check", "0"], "--check 0: valid 2 to 10,000")
    _refused(capsys, ["plan", str(tmp_path / "none.toml")], "plan file")
    _refused(capsys, ["plan", str(EXAMPLE), "--check", "5", "--seed", "-1"], "--seed -1: valid")


def test_the_even_spread_and_the_signals_the_cost_allows():
    from recoil_jax._planning.plan import _affordable_signals, _even_spread

    problem, _ = load_plan(EXAMPLE)
    signals = tuple(problem.signals)
    # Two signals at most within 4; of those pairs, x_M + F_AN and v_M + F_AN spend
    # all 4; the first in the file's order.
    assert signals == ("x_M", "v_M", "F_AN")
    assert _affordable_signals(problem, signals) == (0, 2)
    spread = [problem.conditions[c] for c, _ in _even_spread(problem, signals)]
    assert spread == [
        {"elevation": 0.0, "v0": 8.0},
        {"elevation": 45.0, "v0": 10.0},  # 2.5 of 5 steps, halves up; 0.5 of 1 step
        {"elevation": 70.0, "v0": 10.0},
    ]


@pytest.fixture(scope="module")
def planned(tmp_path_factory):
    """The shipped example through the command (one compilation for the module)."""
    out = tmp_path_factory.mktemp("plan")
    assert main(["plan", "envelope_friction", "--out", str(out)]) == 0
    problem, _ = load_plan(EXAMPLE)
    return out, problem, json.loads((out / "result.json").read_text())


def test_the_shipped_plan_is_the_exhaustive_optimum(planned):
    """Every multiset of 3 firings over the 12 candidates × the signal sets the cost
    allows, from the same information: the plan's determinant is at least 99 % of the
    optimum's, and at least greedy selection's."""
    _, problem, result = planned
    plan = rj.plan_firings(problem)  # warm: the program is cached
    opts = plan.firing_options()
    optimum = exhaustive(opts, problem.firings, "D")
    assert np.exp(plan.plan.criterion - optimum.value) >= 0.99
    assert plan.plan.criterion >= greedy(opts, problem.firings, "D").value - 1e-9
    assert result["criterion"]["plan"] == pytest.approx(plan.plan.criterion)
    assert result["criterion"]["plan"] >= result["criterion"]["baseline"]
    # Fired at 0° only, packing and slide friction are not separated: named, no interval.
    first = result["first_candidate"]
    assert {c["elevation"] for c in first["plan"]} == {0.0}
    assert first["predicted"]["friction_force"] == {"stderr": None, "ci95": None}
    assert first["predicted"]["friction_coefficient"] == {"stderr": None, "ci95": None}
    assert any("friction_force" in t and "friction_coefficient" in t for t in first["undetermined"])
    assert result["criterion"]["first_candidate"] is None
    # The plan determines every value, and fires at more than one elevation.
    assert result["undetermined"] == []
    assert len({f["elevation"] for f in result["plan"]}) >= 2
    for name, entry in result["predicted"].items():
        lo, hi = entry["ci95"]
        assert lo < problem.guess[name] < hi and entry["stderr"] > 0


def test_the_command_writes_its_files(planned):
    out, problem, result = planned
    for name in ("result.json", "summary.txt", "calibration.toml", "intervals.png",
                 "information.png"):  # fmt: skip
        assert (out / name).stat().st_size > 0, name
    assert set(result) >= {"plan", "predicted", "baseline", "criterion", "first_candidate"}
    assert set(result["baseline"]) >= {"plan", "predicted"}
    for firing in result["plan"]:
        assert set(firing) == {"elevation", "v0", "signals"}
        assert sum(problem.signals[s].cost for s in firing["signals"]) <= problem.cost
    text = (out / "summary.txt").read_text()
    assert "spread evenly" in text and "not determined" in text
    # Every plan compared is listed, and each error has its unit and its share.
    assert "  spread evenly: elevation 0, v0 8 (x_M, F_AN); elevation 45" in text
    assert "  all at the first candidate: elevation 0, v0 8 (x_M, F_AN); elevation 0" in text
    assert re.search(r"c_out +planned [0-9.]+ N\*s/m \([0-9.]+ %; 95 %: [0-9.]+ to ", text), text
    assert re.search(r"friction_coefficient +planned [0-9.e-]+ \([0-9.]+ %; 95 %", text), text
    skeleton = tomllib.loads((out / "calibration.toml").read_text())
    assert len(skeleton["experiment"]) == problem.firings
    assert set(skeleton["fit"]) == set(problem.fit)


def test_calibrate_reads_the_skeleton_with_the_traces(planned):
    """Once the traces exist (here by the reference solver), the skeleton is a
    calibration file: each experiment at its firing's conditions, with its noise."""
    out, problem, result = planned
    from recoil_jax.apps._files.calibration_file import load_calibration

    for i, firing in enumerate(result["plan"], 1):
        conditions = {k: v for k, v in firing.items() if k != "signals"}
        history = rjx.reference_history(problem.guess | conditions, problem.times)
        columns = {s: history[s] for s in firing["signals"]}
        rows = [
            ",".join(repr(float(v)) for v in (t, *(columns[s][j] for s in columns)))
            for j, t in enumerate(problem.times)
        ]
        header = ",".join(["t", *columns])
        (out / f"firing_{i}.csv").write_text(header + "\n" + "\n".join(rows) + "\n")
    calibration, _ = load_calibration(out / "calibration.toml")
    assert dict(calibration.fit) == dict(problem.fit)
    for experiment, firing in zip(calibration.experiments, result["plan"], strict=True):
        assert {k: experiment.design[k] for k in ("elevation", "v0")} == {
            k: firing[k] for k in ("elevation", "v0")
        }
        assert set(experiment.sigma) == set(firing["signals"])


@pytest.mark.slow
def test_the_prediction_holds_on_the_reference_solver_traces(planned):
    """Noisy tests drawn by the independent reference solver at a truth inside the box,
    fitted by the calibration (`fit_many`): each parameter's spread of fitted values is
    within 0.7–1.4× the standard error predicted at that truth (40 tests: the sample
    deviation's own error is about 11 %, so this is about 3 of its deviations).

    Since the stick became a mode (model revision 3) `F_AN` jumps where a stick or
    slip crosses a sample time, and χ² is a staircase there: the fits from the truth
    stayed on its tread (about half within 1e-6 of where they started), and the spread
    of `friction_coefficient` was 0.51 of the prediction. The fit now refits without
    the samples either side of a jump (`fit_off_the_jumps`), and the spread is the
    noise's again."""
    _, problem, _ = planned
    plan = rj.plan_firings(problem)
    truth = {"c_out": 20000.0, "c_ret": 12000.0, "recuperator_preload": 35000.0,
             "friction_force": 1200.0, "friction_coefficient": 0.08}  # fmt: skip
    check = rjx.check_plan(plan, 40, which=("plan",), truth=truth, reference=True)["plan"]
    assert check.converged == 40
    print("\nspread over the predicted standard error:", check.ratio)
    for name, ratio in check.ratio.items():
        assert ratio is not None and 0.7 < ratio < 1.4, (name, ratio)


def test_the_check_s_ratio_range_is_the_sample_deviation_s():
    """The range printed beside `--check`'s ratios: where 99 % of the ratios of N
    Gaussian fits' sample deviation to the true one fall (here against draws)."""
    from recoil_jax.apps._cli.plan import ratio_range

    low, high = ratio_range(40)
    rng = np.random.default_rng(0)
    ratios = rng.standard_normal((20_000, 40)).std(axis=1, ddof=1)
    inside = np.mean((ratios > low) & (ratios < high))
    assert abs(inside - 0.99) < 0.003, inside
    assert ratio_range(100) == pytest.approx((0.82, 1.185), abs=0.002)
