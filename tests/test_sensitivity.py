"""Global sensitivity (`rj.sensitivity`, `recoil-jax sensitivity`): the indices against
closed forms (Ishigami, a linear model), DGSM from exact gradients against SALib's
finite differences on the model, Sobol's total index under the DGSM bound, two seeds
agreeing, failed solves counted, and every bad input one line."""

from __future__ import annotations

import dataclasses
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

import recoil_jax as rj
import recoil_jax.extend as rjx
from recoil_jax._global_sensitivity.analysis import _analysed, _problem
from recoil_jax.apps._cli import main
from recoil_jax.apps._files.inputs import results_folder
from recoil_jax.apps._studies.sensitivity_file import SHIPPED, load_sensitivity

ABSORBER = {"m": 1500.0, "gap": 0.062}
RANGES = {"k": 0.1, "c_out": 0.15, "v0": 0.05, "gap": (0.059, 0.065)}

# The Ishigami function, a = 7, b = 0.1, on [-π, π]³, and its variances in closed form.
A, B = 7.0, 0.1
ISHIGAMI = _problem(["x1", "x2", "x3"], np.full(3, -math.pi), np.full(3, math.pi))
_V1 = 0.5 * (1 + B * math.pi**4 / 5) ** 2
_V2 = A**2 / 8
_V13 = 8 * B**2 * math.pi**8 / 225
_V = _V1 + _V2 + _V13


def ishigami(x):
    return np.sin(x[:, 0]) + A * np.sin(x[:, 1]) ** 2 + B * x[:, 2] ** 4 * np.sin(x[:, 0])


def ishigami_gradient(x):
    return np.stack(
        [
            np.cos(x[:, 0]) * (1 + B * x[:, 2] ** 4),
            2 * A * np.sin(x[:, 1]) * np.cos(x[:, 1]),
            4 * B * x[:, 2] ** 3 * np.sin(x[:, 0]),
        ],
        axis=1,
    )


def _run(method, problem, fn, gradient=None, ok=None):
    x = method.sample(problem)
    outputs = {"f": fn(x)}
    ok = np.ones(len(x), dtype=bool) if ok is None else ok(x)
    gradients = {"f": gradient(x)} if gradient is not None else None
    return _analysed(method, problem, x, outputs, ok, gradients)


def test_sobol_intervals_cover_the_ishigami_indices_as_often_as_they_say():
    s1 = np.array([_V1, _V2, 0.0]) / _V
    st = np.array([_V1 + _V13, _V2, _V13]) / _V
    covered = total = 0
    for seed in range(30):
        result = _run(rj.SobolIndices(samples=256, seed=seed), ISHIGAMI, ishigami)
        for i, name in enumerate(ISHIGAMI["names"]):
            entry = result.indices["f"][name]
            for key, truth in (("S1", s1[i]), ("ST", st[i])):
                covered += abs(entry[key] - truth) <= entry[f"{key}_conf"]
                total += 1
    # 95 % intervals over 180 checks: binomial 2.5 % tail at 164; measured 178 of 180
    # (SALib's bootstrap intervals are a little wide, never narrow).
    assert total == 180 and covered >= 164, covered


def test_second_order_sobol_finds_ishigamis_one_interaction():
    """Ishigami's only interaction is x1 with x3: S13 = V13/V; S12 = S23 = 0."""
    result = _run(rj.SobolIndices(samples=1024, second_order=True), ISHIGAMI, ishigami)
    assert result.second_order is not None
    pairs = result.second_order["f"]
    for pair, truth in (("x1,x2", 0.0), ("x1,x3", _V13 / _V), ("x2,x3", 0.0)):
        assert abs(pairs[pair]["S2"] - truth) <= pairs[pair]["S2_conf"], (pair, pairs[pair])


def test_dgsm_of_ishigami_equals_the_closed_form():
    # ν_i = E[(∂f/∂x_i)²] for x uniform on [-π, π]: E[x⁴] = π⁴/5, E[x⁶] = π⁶/7, E[x⁸] = π⁸/9.
    pi = math.pi
    nu = [
        0.5 * (1 + 2 * B * pi**4 / 5 + B**2 * pi**8 / 9),
        A**2 / 2,
        8 * B**2 * pi**6 / 7,
    ]
    result = _run(rj.DGSM(samples=4096), ISHIGAMI, ishigami, ishigami_gradient)
    st = np.array([_V1 + _V13, _V2, _V13]) / _V
    for i, name in enumerate(ISHIGAMI["names"]):
        entry = result.indices["f"][name]
        assert abs(entry["vi"] - nu[i]) <= entry["vi_conf"], (name, entry, nu[i])
        # The bound it implies holds over the true total index.
        assert entry["dgsm"] + entry["dgsm_conf"] >= st[i]


def test_a_linear_model_gives_the_exact_indices_of_every_method():
    coefficients = np.array([3.0, -1.0, 0.5])
    lower, upper = np.array([0.0, 10.0, -2.0]), np.array([1.0, 14.0, 2.0])
    width = upper - lower
    problem = _problem(["a", "b", "c"], lower, upper)

    def linear(x):
        return x @ coefficients

    def gradient(x):
        return np.broadcast_to(coefficients, x.shape)

    shares = (coefficients * width) ** 2 / np.sum((coefficients * width) ** 2)
    sobol = _run(rj.SobolIndices(samples=2048), problem, linear)
    morris = _run(rj.MorrisEffects(trajectories=16), problem, linear)
    dgsm = _run(rj.DGSM(samples=1024), problem, linear, gradient)
    for i, name in enumerate(problem["names"]):
        entry = sobol.indices["f"][name]
        assert abs(entry["S1"] - shares[i]) <= entry["S1_conf"]
        assert abs(entry["ST"] - shares[i]) <= entry["ST_conf"]
        # An elementary effect is the change over the whole range, for every step.
        effect = morris.indices["f"][name]
        assert effect["mu_star"] == pytest.approx(abs(coefficients[i]) * width[i], rel=1e-9)
        assert effect["sigma"] == pytest.approx(0.0, abs=1e-9 * width[i])
        measure = dgsm.indices["f"][name]
        assert measure["vi"] == pytest.approx(coefficients[i] ** 2, rel=1e-12)
        assert measure["vi_conf"] == pytest.approx(0.0, abs=1e-9)
    # Its bound, 12/π² times the share, with the sample variance (a QMC sample: close).
    bounds = np.array([dgsm.indices["f"][n]["dgsm"] for n in problem["names"]])
    np.testing.assert_allclose(bounds, 12 / math.pi**2 * shares, rtol=0.02)
    assert sobol.ranking("f") == morris.ranking("f") == dgsm.ranking("f") == ["b", "a", "c"]


def test_failed_solves_leave_their_whole_group_out_and_are_counted():
    method = rj.SobolIndices(samples=256)
    d, size = 3, 5  # Saltelli blocks of d + 2 rows

    def fails(x):  # a corner of the box fails to solve
        return ~((x[:, 0] > 2.5) & (x[:, 1] > 2.5))

    result = _run(method, ISHIGAMI, ishigami, ok=fails)
    x = method.sample(ISHIGAMI)
    bad_blocks = (~fails(x)).reshape(-1, size).any(axis=1)
    assert 0 < bad_blocks.sum() < 256 and method.group(d) == size
    assert result.used == size * (256 - bad_blocks.sum())
    assert int((~result.ok).sum()) == int((~fails(x)).sum())
    assert all(np.isfinite(v) for e in result.indices["f"].values() for v in e.values())
    with pytest.raises(rj.SolveError, match="no group of 5 designs solved"):
        _run(method, ISHIGAMI, ishigami, ok=lambda x: np.zeros(len(x), dtype=bool))


@pytest.mark.parametrize(
    ("method", "size"), [(rj.MorrisEffects(trajectories=32), 4), (rj.DGSM(samples=256), 1)]
)
def test_a_failed_solve_leaves_out_its_morris_trajectory_or_its_dgsm_point(method, size):
    def fails(x):
        return ~((x[:, 0] > 2.0) & (x[:, 1] > 2.0))

    gradient = ishigami_gradient if method.gradients else None
    result = _run(method, ISHIGAMI, ishigami, gradient, ok=fails)
    x = method.sample(ISHIGAMI)
    assert method.group(3) == size
    bad = (~fails(x)).reshape(-1, size).any(axis=1)
    assert 0 < bad.sum() < len(bad)
    assert result.used == size * int((~bad).sum())
    assert all(np.isfinite(v) for e in result.indices["f"].values() for v in e.values())


def test_a_metric_that_does_not_vary_has_zero_indices_and_is_named():
    result = _run(rj.SobolIndices(samples=64), ISHIGAMI, lambda x: np.full(len(x), 2.0))
    assert result.constant == ("f",)
    assert all(v == 0.0 for e in result.indices["f"].values() for v in e.values())


def test_the_model_designs_are_the_sweeps_and_the_objective_is_their_weighted_sum():
    objective = rj.Objective({"peak_anchoring_force": 1.0, "peak_displacement": 1e4})
    result = rj.sensitivity(
        ABSORBER, {"k": 0.1, "gap": (0.059, 0.065)}, metrics=["peak_anchoring_force"],
        method=rj.SobolIndices(samples=64), objective=objective, progress=False,
    )  # fmt: skip
    assert result.metrics == ("peak_anchoring_force", "objective")
    assert len(result.ok) == 64 * 4 and result.used == 256 and result.ok.all()
    assert result.design["m"] == 1500.0 and result.design["c_out"] == 6239.0
    for i in (0, 77, 255):  # the batched results equal single solves of the same designs
        values = ABSORBER | dict(zip(result.parameters, result.samples[i], strict=True))
        one = rj.peaks(rj.params_from_values(values))
        force = float(one.peak_anchoring_force)
        # The sweep's lanes may tip a step decision: solver-error level (rtol 1e-6).
        assert result.outputs["peak_anchoring_force"][i] == pytest.approx(force, rel=1e-5)
        total = force + 1e4 * float(one.peak_displacement)
        assert result.outputs["objective"][i] == pytest.approx(total, rel=1e-5)
    assert result.ranking("peak_anchoring_force")[0] == "k"
    json.dumps(result.to_json())


def test_the_objectives_gradient_matches_central_differences():
    """DGSM's gradient of an objective whose metrics are not all analysed: the weighted
    sum of the metrics' exact gradients, against central differences of the objective."""
    objective = rj.Objective({"peak_anchoring_force": 1.0, "peak_displacement": 1e4})
    result = rj.sensitivity(
        ABSORBER, RANGES, metrics=["max_stroke"], method=rj.DGSM(samples=16),
        objective=objective, progress=False,
    )  # fmt: skip
    assert result.gradients is not None and result.metrics == ("max_stroke", "objective")
    point = ABSORBER | dict(zip(result.parameters, result.samples[3], strict=True))
    for j, name in enumerate(result.parameters):
        # 1e-3: at 1e-4 the solves' own noise (rtol 1e-7) over the step shows (0.9 %).
        step = 1e-3 * point[name]
        sides = [point | {name: point[name] + sign * step} for sign in (1.0, -1.0)]
        swept = rj.sweep(sides, options=rj.GRADIENT_OPTIONS, progress=False)
        difference = np.diff(objective(swept.peaks)[::-1])[0] / (2 * step)
        assert result.gradients["objective"][3, j] == pytest.approx(difference, rel=2e-3), name


def test_dgsm_from_exact_gradients_equals_salibs_finite_differences_on_the_same_points():
    from SALib.analyze import dgsm as salib_dgsm
    from SALib.sample import finite_diff

    samples = 64
    result = rj.sensitivity(ABSORBER, RANGES, method=rj.DGSM(samples=samples), progress=False)
    problem = _problem(result.parameters, result.lower, result.upper)
    apart = {}
    for delta in (1e-2, 1e-3):  # SALib's default step (1 %), and a tenth of it
        x = finite_diff.sample(problem, samples, delta=delta)  # base points and steps
        np.testing.assert_array_equal(x[:: len(RANGES) + 1], result.samples)
        fixed = {n: np.full(len(x), v) for n, v in ABSORBER.items()}
        swept = rj.sweep(
            fixed | {n: x[:, i] for i, n in enumerate(result.parameters)}, progress=False,
            options=rj.GRADIENT_OPTIONS,
        )  # fmt: skip
        assert swept.ok.all()
        apart[delta] = 0.0
        for metric in result.metrics:
            theirs = salib_dgsm.analyze(problem, x, swept.peaks[metric], seed=1)
            for i, name in enumerate(result.parameters):
                ours = result.indices[metric][name]
                # SALib's dgsm_conf is the interval of its vi (its bootstrap is of vi).
                assert abs(ours["vi"] - theirs["vi"][i]) <= theirs["dgsm_conf"][i], (metric, name)
                # The bound is SALib's formula (width, π², the variance of the same designs,
                # solved with and without sensitivities: 1e-6 apart) on our vi.
                ratio = ours["vi"] / theirs["vi"][i]
                assert ours["dgsm"] / theirs["dgsm"][i] == pytest.approx(ratio, rel=1e-4)
                apart[delta] = max(apart[delta], abs(ratio - 1.0))
    # The finite differences' bias is first order in the step: a tenth of the step comes
    # ten times closer to the exact gradients (measured: 5.1e-2 -> 4.6e-3 on 1,024 points).
    assert apart[1e-3] < 0.3 * apart[1e-2], apart


@pytest.mark.slow
def test_sobol_of_the_paper_absorber_agrees_over_seeds_and_stays_under_the_dgsm_bound():
    runs = [
        rj.sensitivity(
            ABSORBER, RANGES, method=rj.SobolIndices(samples=512, seed=s), progress=False
        )
        for s in (1, 2)
    ]
    bound = rj.sensitivity(ABSORBER, RANGES, method=rj.DGSM(samples=512), progress=False)
    for metric in runs[0].metrics:
        for name in RANGES:
            a, b = (r.indices[metric][name] for r in runs)
            for key in ("S1", "ST"):  # the two intervals overlap
                assert abs(a[key] - b[key]) <= a[f"{key}_conf"] + b[f"{key}_conf"]
            upper = bound.indices[metric][name]
            # 1e-6: the solver's noise (c_ret does not reach the peaks: its ST is ~1e-9
            # of the variance, its exact derivative 0).
            assert a["ST"] - a["ST_conf"] <= upper["dgsm"] + upper["dgsm_conf"] + 1e-6
        assert runs[0].ranking(metric)[:2] == runs[1].ranking(metric)[:2]


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"ranges": {"spring": (1.0, 2.0)}}, "spring"),
        ({"ranges": {"k": (-5.0, 3e4)}}, r"ranges, at their low ends: .*k"),
        ({"ranges": {"k": (3e4, 2e4)}}, "need finite low < high"),
        ({"ranges": {"k": 1.5}}, r"relative half-width is in \(0, 1\)"),
        ({"ranges": {"shots": (1.0, 3.0)}}, "shots is a count"),
        ({"ranges": {"c_r": 0.1}, "design": {"m": 1500.0, "c_r": 0.0}}, "c_r is 0"),
        ({"ranges": {"gap": 0.1}, "design": {"m": 0.0}}, "gap has no value in the design"),
        ({"ranges": {}}, "ranges is empty"),
        ({"metrics": ["peak_force"]}, "unknown metric 'peak_force'"),
        ({"metrics": ["objective"]}, "needs objective="),
        ({"method": "sobol"}, "give SobolIndices"),
    ],
)
def test_bad_input_is_refused_before_anything_runs(kwargs, message):
    arguments = {"design": ABSORBER, "ranges": {"k": 0.1}} | kwargs
    with pytest.raises(rj.ParameterError, match=message):
        rj.sensitivity(**arguments, progress=False)


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: rj.SobolIndices(samples=32), "samples = 32: valid an integer >= 64"),
        (lambda: rj.SobolIndices(samples=1000), "a power of 2 .e.g. 512 or 1024"),
        (lambda: rj.MorrisEffects(levels=5), "levels = 5: give an even number"),
        (lambda: rj.MorrisEffects(trajectories=2), "trajectories = 2"),
        (lambda: rj.DGSM(samples=8), "samples = 8"),
        (lambda: rj.DGSM(seed=-1), "seed = -1"),
    ],
)
def test_too_few_samples_for_a_method_is_refused(make, message):
    with pytest.raises(rj.ParameterError, match=message):
        make()


def test_ranges_from_a_calibration_are_its_fitted_values_within_sigmas(tmp_path):
    fitted = rjx.FittedParameters(
        ("k", "c_out"), np.array([28000.0, 6000.0]), np.diag([500.0, 2000.0]) ** 2,
        np.array([1e4, 5000.0]), np.array([1e5, 3e4]), np.array([True, True]),
        {"m": 1500.0, "gap": 0.062},
    )  # fmt: skip
    assert fitted.box(2.0) == {"k": (27000.0, 29000.0), "c_out": (5000.0, 10000.0)}
    (tmp_path / "fit.json").write_text(json.dumps({"hardware": fitted.to_json()}))
    (tmp_path / "s.toml").write_text(
        '[calibration]\nfrom = "fit.json"\nsigmas = 1.0\n[ranges]\nv0 = { relative = 0.05 }\n'
        '[metrics]\nnames = ["peak_anchoring_force"]\n[method]\nname = "dgsm"\nsamples = 16\n'
    )
    arguments, _ = load_sensitivity(tmp_path / "s.toml")
    assert arguments["ranges"] == {"k": (27500.0, 28500.0), "c_out": (5000.0, 8000.0),
                                   "v0": 0.05}  # fmt: skip
    assert arguments["design"] == {"m": 1500.0, "gap": 0.062, "k": 28000.0, "c_out": 6000.0}
    loose = dataclasses.replace(fitted, identifiable=np.array([True, False]))
    with pytest.raises(rj.ParameterError, match="c_out not determined"):
        loose.box()


@pytest.mark.parametrize("name", sorted(p.stem for p in SHIPPED.glob("*.toml")))
def test_the_shipped_examples_load(name):
    arguments, description = load_sensitivity(name)
    assert description and arguments["metrics"] and arguments["ranges"]


SMALL = """
description = "two tolerances"
[design]
m = 1500.0
gap = 0.062
[ranges]
k = { relative = 0.1 }
gap = [0.059, 0.065]
[metrics]
names = ["peak_anchoring_force", "max_stroke"]
[method]
name = "sobol"
samples = 64
"""


def test_the_command_writes_its_report_and_figures_and_a_store_resumes(tmp_path, capsys):
    (tmp_path / "s.toml").write_text(SMALL)
    argv = ["sensitivity", str(tmp_path / "s.toml"), "--out", str(tmp_path / "out"), "--json",
            "--store", str(tmp_path / "s.sqlite"), "--no-cache"]  # fmt: skip
    assert main(argv) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["designs"] == 256 and report["used"] == 256 and report["failed"] == 0
    assert set(report["indices"]["max_stroke"]["k"]) == {"S1", "S1_conf", "ST", "ST_conf"}
    assert report["parameters"]["k"] == pytest.approx([24750.0, 30250.0])
    for figure in ("indices.png", "scatter.png", "result.json", "samples.csv"):
        assert (tmp_path / "out" / figure).stat().st_size > 0
    rows = (tmp_path / "out" / "samples.csv").read_text().splitlines()
    assert rows[0] == "k,gap,peak_anchoring_force,max_stroke,ok" and len(rows) == 257
    assert main(argv) == 0  # again: every design read from the store
    again = json.loads(capsys.readouterr().out)
    assert again["stored"] == 256 and again["indices"] == report["indices"]


def test_a_studys_objective_and_limits_screened_by_morris_from_the_command(tmp_path, capsys):
    """`study = ...` gives the study's objective and its limited metrics indices of their
    own; Morris through the command writes its μ*–σ figure."""
    text = SMALL.replace('names = ["peak_anchoring_force", "max_stroke"]',
                         'names = []\nstudy = "tuned_absorber"')  # fmt: skip
    text = text.replace('name = "sobol"\nsamples = 64', 'name = "morris"\ntrajectories = 8')
    (tmp_path / "s.toml").write_text(text)
    argv = ["sensitivity", str(tmp_path / "s.toml"), "--out", str(tmp_path / "out"), "--json",
            "--no-cache"]  # fmt: skip
    assert main(argv) == 0
    report = json.loads(capsys.readouterr().out)
    # tuned_absorber: minimise the peak anchoring force with max_stroke <= 0.15 m (m is
    # held by its bounds, not a metric).
    assert set(report["indices"]) == {"objective", "max_stroke"}
    assert report["designs"] == 8 * 3 and report["failed"] == 0
    effects = report["indices"]["objective"]
    assert set(effects) == {"k", "gap"}
    assert {"mu_star", "mu_star_conf", "sigma"} <= set(effects["k"])
    # The objective is the peak anchoring force (weight 1): k moves it, within the box.
    samples = (tmp_path / "out" / "samples.csv").read_text().splitlines()
    header = samples[0].split(",")
    assert "objective" in header and "peak_anchoring_force" not in header
    assert effects["k"]["mu_star"] > 0
    assert (tmp_path / "out" / "morris.png").stat().st_size > 0


def test_each_example_has_its_own_default_output_folder(tmp_path, monkeypatch, capsys):
    """Without --out, a run on one input does not replace another's results."""
    monkeypatch.chdir(tmp_path)
    text = SMALL.replace('name = "sobol"\nsamples = 64', 'name = "morris"\ntrajectories = 4')
    for name in ("first", "second"):
        (tmp_path / f"{name}.toml").write_text(text.replace("two tolerances", name))
        assert main(["sensitivity", f"{name}.toml", "--no-cache"]) == 0
    for name in ("first", "second"):
        report = json.loads(
            (tmp_path / "results" / "sensitivity" / name / "result.json").read_text()
        )
        assert report["description"] == name
    assert "wrote results/sensitivity/second/result.json" in capsys.readouterr().out
    # The shipped examples by name, as the docs run them.
    folders = {
        results_folder(None, "sensitivity", name) for name in ("paper_absorber", "throttling")
    }
    assert folders == {
        Path("results/sensitivity/paper_absorber"),
        Path("results/sensitivity/throttling"),
    }


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (SMALL.replace('name = "sobol"', 'name = "fast"'), "name = 'fast': give one of \"sobol\""),
        (SMALL.replace("samples = 64", "trajectories = 8"), "'trajectories' is not a setting"),
        (SMALL.replace("samples = 64", "samples = 100"), "a power of 2"),
        (SMALL.replace("samples = 64", "samples = 32"), r"samples = 32: valid an integer >= 64"),
        (
            SMALL.replace("gap = [0.059, 0.065]", "kk = [1.0, 2.0]"),
            "unknown parameter 'kk'; known: M, k,",
        ),
        (SMALL.replace("[ranges]", "[range]"), "unknown section 'range'"),
        (SMALL.replace('"max_stroke"', '"stroke"'), "unknown metric 'stroke'"),
        (SMALL.replace("gap = [0.059, 0.065]", "gap = [0.059]"), r"\[ranges\] gap"),
        (SMALL.replace("gap = [0.059, 0.065]", "gap = [-0.01, 0.065]"), "at their low ends.*gap"),
        (SMALL.replace("m = 1500.0", "mass = 1500.0"), "mass"),
        (SMALL + "[calibration]\nfrom = 'missing.json'\n", "missing.json"),
        ("not toml [", "not valid TOML"),
        (
            SMALL.replace("[design]\nm = 1500.0\ngap = 0.062\n", "").replace(
                '"two tolerances"', '"two tolerances"\ndesign = 5'
            ),
            r"\[design\] must be a table",
        ),
        (SMALL.replace('name = "sobol"', 'name = ["sobol"]'), r"name = \['sobol'\]: give one of"),
        (SMALL.replace("samples = 64", "samples = 1073741824"), "more than 16,777,216"),
        (SMALL.replace("samples = 64", "samples = 64\nsecond_order = 'yes'"), "true or false"),
        (SMALL.replace("samples = 64", "samples = 64\nresamples = 1000000"), "from 10 to 10,000"),
        (
            SMALL.replace("names = [", "objective = { bogus = 1.0 }\nnames = ["),
            r"\[metrics\] objective: unknown metric 'bogus'",
        ),
        (SMALL.replace("names = [", "study = 5\nnames = ["), "study = 5: give a study"),
        (SMALL.replace("names = [", "study = 'nonesuch'\nnames = ["), "study: study file"),
        (
            SMALL.replace("gap = [0.059, 0.065]", "pulse_time = [0.001, 0.002]"),
            "pulse_time has no value in the design",
        ),
        ("[metrics]\nnames = []\n[method]\nname = 'dgsm'\n", r"missing \[ranges\]"),
        (SMALL.replace('description = "two tolerances"', "description = 3"), "must be a string"),
    ],
)
def test_a_bad_file_is_one_line_and_status_2(tmp_path, capsys, text, message):
    (tmp_path / "s.toml").write_text(text)
    assert main(["sensitivity", str(tmp_path / "s.toml"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("recoil-jax: error:"), err
    assert re.search(message, err), err
    assert not (tmp_path / "o" / "result.json").exists()


def test_failed_solves_are_counted_and_said_and_none_left_is_status_1(tmp_path, capsys):
    (tmp_path / "s.toml").write_text(SMALL.replace("[0.059, 0.065]", "[0.0, 0.1]"))
    argv = ["sensitivity", str(tmp_path / "s.toml"), "--out", str(tmp_path / "o"), "--json"]
    assert main([*argv, "--max-steps", "100"]) == 0  # some designs need more steps
    captured = capsys.readouterr()
    report = json.loads(captured.out)
    ok = np.array([line.endswith(",1") for line in
                   (tmp_path / "o" / "samples.csv").read_text().splitlines()[1:]])  # fmt: skip
    assert report["failed"] == int((~ok).sum()) > 0
    assert report["used"] == 4 * int(ok.reshape(-1, 4).all(axis=1).sum()) < 256
    assert sum(report["failures"].values()) == report["failed"]
    line = captured.err.strip().splitlines()[-1]
    assert f"{report['failed']} of 256 solves failed" in line and "max_steps" in line
    assert f"rest on the other {report['used']} designs" in line
    assert main([*argv, "--max-steps", "5"]) == 1
    assert "no group of 4 designs solved completely" in capsys.readouterr().err


def test_an_unknown_example_names_the_shipped_ones(capsys):
    assert main(["sensitivity", "nonesuch"]) == 2
    assert "shipped examples: paper_absorber, throttling" in capsys.readouterr().err
