"""Sweeps: grids and design lists, chunking, statuses, sharding, accuracy per point."""

import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from conftest import compiled_programs

import recoil_jax as rj
import recoil_jax.extend as rjx


def test_grid_sweep_matches_single_solves_and_reference(reference_cases):
    masses = [100.0, 500.0, 1000.0, 1500.0]
    gaps = [0.0, 0.015, 0.044, 0.059, 0.062]
    result = rj.sweep_grid({"m": masses, "gap": gaps}, chunk_size=8)
    assert result.grid_shape == (4, 5) and result.swept == ("m", "gap") and len(result) == 20
    assert np.all(result.ok)
    F = result.peaks["peak_anchoring_force"].reshape(result.grid_shape)
    for i, m in enumerate(masses):
        for j, gap in enumerate(gaps):
            single = rj.peaks(rj.params_from_values(m=m, gap=gap))
            # The same solve, but batched and scalar kernels round differently, which can
            # tip a step decision: agreement to solver-error level (rtol 1e-6).
            assert F[i, j] == pytest.approx(float(single.peak_anchoring_force), rel=1e-5)
    # Every swept point that is a paper case is within 1e-4 of the hard reference.
    checked = 0
    for case in reference_cases:
        if case["params"]["m"] == 0:
            continue
        i = masses.index(case["params"]["m"])
        j = gaps.index(case["params"]["gap"])
        ref = case["reference"]
        assert F[i, j] == pytest.approx(ref["peak_anchoring_force_N"], rel=1e-4)
        x = result.peaks["peak_displacement"].reshape(result.grid_shape)[i, j]
        assert x == pytest.approx(ref["peak_displacement_m"], rel=1e-4)
        checked += 1
    assert checked == 8


def test_a_grid_made_a_chunk_at_a_time_equals_its_columns(tmp_path):
    """`Grid` makes the designs of `grid` (C order, as itertools.product) on demand; a
    sweep of it, cut into blocks of one chunk each, gives the columns' results bit for
    bit, and its checks name the design in the grid that fails."""
    import itertools

    axes = {"m": [0.0, 500.0, 1500.0], "gap": np.linspace(0.0, 0.09, 3), "k_r": [9e3, 13e3]}
    designs = rjx.Grid(axes, {"c_r": 300.0})
    columns, shape = rj.grid(axes, {"c_r": 300.0})
    product = np.array(list(itertools.product(*axes.values())))
    assert len(designs) == 18 and designs.shape == shape == (3, 3, 2)
    for i, name in enumerate(axes):
        np.testing.assert_array_equal(columns[name], product[:, i])
        np.testing.assert_array_equal(designs.columns(slice(4, 15))[name], product[4:15, i])
        np.testing.assert_array_equal(designs.columns(np.array([17, 0, 9]))[name],
                                      product[[17, 0, 9], i])  # fmt: skip
    in_memory = rj.sweep(columns, chunk_size=8, progress=False)
    made = rj.sweep(designs, chunk_size=8, progress=False)  # 3 blocks, each 2 structures
    for field in rjx.PEAK_FIELDS:
        np.testing.assert_array_equal(made.peaks[field], in_memory.peaks[field])
    assert set(made.values) == set(in_memory.values)
    for name, values in made.values.items():
        np.testing.assert_array_equal(values, in_memory.values[name])
    # The probe meets every check between values: the load against t1 at the right design.
    burst = rjx.Grid({"shots": [1, 3], "fire_interval": [0.5, 4.0], "gap": [0.01, 0.02]})
    with pytest.raises(rj.ParameterError, match=r"design 6\): the last of 3 rounds fires at 8 s"):
        rj.sweep(rjx.Grid(burst.axes, {"t1": 6.0}))
    with pytest.raises(rj.ParameterError, match=r"Absorber\.gap\[1\] = -0\.02 m"):
        rj.sweep(rjx.Grid({"m": [500.0, 600.0], "gap": [0.01, -0.02]}))
    with pytest.raises(rj.ParameterError, match="both swept and fixed"):
        rjx.Grid({"m": [1.0, 2.0]}, {"m": 3.0})
    with pytest.raises(rj.ParameterError, match="axis gap has no values"):
        rjx.Grid({"gap": []})
    with pytest.raises(rj.ParameterError, match="at least one axis or fixed value"):
        rjx.Grid({})
    # A knot missing before one that is there: the design's index in the grid, not in
    # the probe (which keeps positions 0 and 3 of orifice_0).
    holes = rjx.Grid({"orifice_0": [1e-4, 2e-4, 3e-4, np.nan], "orifice_1": [2e-4]})
    with pytest.raises(rj.ParameterError, match=r"design 3: orifice knots must be numbered"):
        rj.sweep(holes)
    # A store knows its grid by its axes in their order (the order sets each index).
    store = tmp_path / "grid.sqlite"
    rj.sweep(designs, chunk_size=8, progress=False, store=store)
    turned = rjx.Grid(dict(reversed(list(axes.items()))), {"c_r": 300.0})
    with pytest.raises(rj.ParameterError, match="holds the results of a different sweep"):
        rj.sweep(turned, chunk_size=8, progress=False, store=store)


def test_a_resumed_grid_does_not_rebuild_the_blocks_it_has(tmp_path, monkeypatch):
    """A grid stopped after two of its five blocks resumes with the other three: the
    stored blocks are not made, grouped or checked again (the solves stubbed)."""
    import recoil_jax._sweeps.chunks as chunks_module
    import recoil_jax._sweeps.dispatch as dispatch_module

    solved, grouped, stop = [], [], [True]

    def stub(batch, t1, count, *args):
        solved.append(count)
        if len(solved) == 3 and stop[0]:  # the first run only
            stop[0] = False
            raise KeyboardInterrupt
        peaks = {key: np.ones(count) for key in rjx.PEAK_FIELDS.values()}
        return peaks | {"status_code": np.zeros(count, np.int32)}, 0.01

    real_groups = chunks_module._groups

    def counted(columns, *args, **kwargs):
        grouped.append(len(next(iter(columns.values()))))
        return real_groups(columns, *args, **kwargs)

    monkeypatch.setattr(dispatch_module, "_solve_chunk", stub)
    monkeypatch.setattr(chunks_module, "_groups", counted)
    designs = rjx.Grid({"m": np.linspace(500.0, 1500.0, 5), "gap": np.linspace(0.0, 0.1, 8)})
    store = tmp_path / "grid.sqlite"
    with pytest.raises(KeyboardInterrupt):
        rj.sweep_to_store(designs, store, chunk_size=8, workers=1, progress=False)
    assert rj.campaign_progress(store).done == 16
    solved.clear()
    grouped.clear()
    done = rj.sweep_to_store(designs, store, chunk_size=8, workers=1, progress=False)
    assert done.stored == 16 and done.designs == 40 and solved == [8, 8, 8]
    assert grouped[1:] == [8, 8, 8]  # the probe, then only the three blocks left


def test_order_chunking_and_sorting_do_not_change_results():
    rng = np.random.default_rng(5)
    designs = [
        dict(m=float(m), gap=float(g))
        for m, g in zip(rng.uniform(50, 3000, 37), rng.uniform(0, 0.15, 37), strict=True)
    ]
    a = rj.sweep(designs, chunk_size=16, sort_by_gap=True)
    b = rj.sweep(designs, chunk_size=64, sort_by_gap=False, workers=3)  # 3 parts, threads
    np.testing.assert_allclose(a.values["gap"], [d["gap"] for d in designs])
    for key in ("peak_displacement", "peak_anchoring_force", "max_stroke"):
        np.testing.assert_allclose(a.peaks[key], b.peaks[key], rtol=1e-6)


def test_failed_points_are_flagged_not_silent(capsys):
    designs = [dict(m=500.0, gap=0.0), dict(m=500.0, gap=0.15), dict(m=1500.0, gap=0.0)]
    result = rj.sweep(designs, options=rj.SolverOptions(max_steps=100), progress=True)
    assert list(result.ok) == [False, True, False]
    message = rj.Status[rj.Status.max_steps]
    assert result.failures() == [(0, message), (2, message)]
    assert np.isnan(result.peaks["peak_anchoring_force"][0])
    assert np.isfinite(result.peaks["peak_anchoring_force"][1])
    records = result.records()
    assert records[0]["peak_anchoring_force_N"] is None
    assert records[0]["status"].startswith("max_steps")
    assert records[1]["status"] == "ok"
    err = capsys.readouterr().err
    assert "2 of 3 designs failed" in err and "sweep [" in err
    # progress=False (as the optimiser calls it): the status says it, nothing is printed.
    quiet = rj.sweep(designs, options=rj.SolverOptions(max_steps=100), progress=False)
    assert quiet.failures() == result.failures()
    assert capsys.readouterr().err == ""


def test_bad_points_raise_before_compiling():
    with pytest.raises(rj.ParameterError, match=r"Absorber\.gap\[1\] = -0\.1 m"):
        rj.sweep([dict(gap=0.01), dict(gap=-0.1)])
    # The index is the point's in the input, also where the groups run apart.
    with pytest.raises(rj.ParameterError, match=r"Absorber\.m\[2\] = -5 kg"):
        rj.sweep({"m": [0.0, 500.0, -5.0]})
    with pytest.raises(rj.ParameterError, match=r"SolverOptions\.t1\[0\] = 0 s"):
        rj.sweep([dict(m=500.0, t1=0.0)])
    with pytest.raises(rj.ParameterError, match="t1 is given for some points"):
        rj.sweep([dict(m=500.0, t1=1.0), dict(m=600.0)])
    with pytest.raises(rj.ParameterError, match="unknown parameter"):
        rj.sweep({"mass": [1.0]})


@pytest.mark.slow
def test_no_absorber_beside_absorbers_runs_in_input_order():
    """`m = 0` (the simplified model) and absorbers in one sweep run as two groups and
    come back in input order, each point equal to its own solve; gradients with respect
    to absorber parameters are exactly 0 where there is no absorber."""
    designs = [dict(m=1500.0, gap=0.05), dict(m=0.0), dict(m=500.0, gap=0.0), dict(m=0.0, v0=0.5)]
    result = rj.sweep(designs, wrt=("gap", "v0"))
    assert np.all(result.ok)
    for i, design in enumerate(designs):
        single, grads = rj.peak_jacobian(
            rj.params_from_values(design), wrt=("v0",) if design["m"] == 0 else ("gap", "v0")
        )
        assert result.peaks["peak_anchoring_force"][i] == pytest.approx(
            float(single.peak_anchoring_force), rel=1e-6
        )
        dF_dv0 = result.gradients["peak_anchoring_force"]["v0"][i]
        assert dF_dv0 == pytest.approx(float(grads.peak_anchoring_force[-1]), rel=1e-5)
    assert result.gradients["peak_anchoring_force"]["gap"][[1, 3]].tolist() == [0.0, 0.0]
    assert result.peaks["peak_contact_force"][[1, 3]].tolist() == [0.0, 0.0]
    records = result.records()
    assert "gap" not in records[1]["parameters"] and records[0]["parameters"]["gap"] == 0.05
    assert records[1]["parameters"]["m"] == 0.0


@pytest.mark.slow
def test_end_time_per_point():
    """`t1` may differ between points (it is carried per design): each point equals its
    own solve to that end time."""
    designs = [dict(m=500.0, gap=0.0, t1=0.3), dict(m=500.0, gap=0.0, t1=2.0), dict(m=0.0, t1=0.2)]
    result = rj.sweep(designs)
    assert result.values["t1"].tolist() == [0.3, 2.0, 0.2]
    for i, design in enumerate(designs):
        design = dict(design)
        options = rj.SolverOptions(t1=design.pop("t1"))
        single = rj.peaks(rj.params_from_values(design), options=options)
        assert result.peaks["peak_displacement"][i] == pytest.approx(
            float(single.peak_displacement), rel=1e-9
        )
    # The barrel is still recoiling at 0.3 s (its peak comes at ~0.65 s).
    assert result.peaks["peak_displacement"][0] < result.peaks["peak_displacement"][1]


def test_sweep_gradients_and_simplified_model():
    result = rj.sweep([dict(m=1500.0, gap=0.03), dict(m=1500.0, gap=0.18)], wrt=("gap", "m"))
    dF_dgap = result.gradients["peak_anchoring_force"]["gap"]
    assert dF_dgap[0] < 0 and dF_dgap[1] == 0.0  # no impact at 0.18 m: exactly zero
    _, single = rj.peak_jacobian(rj.params_from_values(m=1500.0, gap=0.03), wrt=("gap", "m"))
    assert dF_dgap[0] == pytest.approx(float(single.peak_anchoring_force[0]), rel=1e-6)
    simplified = rj.sweep({"m": [0.0, 0.0], "v0": [0.5, 0.7]})
    assert "gap" not in simplified.values and np.all(simplified.ok)
    assert simplified.peaks["peak_contact_force"].tolist() == [0.0, 0.0]


_SHARDED = textwrap.dedent("""
    import json, sys
    import jax, numpy as np
    import recoil_jax as rj
    assert jax.local_device_count() == 4, jax.local_devices()
    designs = [dict(m=float(m), gap=float(g)) for m in (100, 800, 1500)
               for g in np.linspace(0, 0.12, 11)]
    sharded = rj.sweep(designs, chunk_size=16)
    single = rj.sweep(designs, chunk_size=16, devices=jax.local_devices()[:1])
    steps = np.array_equal(sharded.peaks["num_steps"], single.peaks["num_steps"])
    worst = {"value": 0.0, "time": 0.0}
    for k, a in sharded.peaks.items():
        b = single.peaks[k]
        scale = np.maximum(np.abs(b), 1e-6)
        kind = "time" if k.endswith("_time") else "value"
        worst[kind] = max(worst[kind], float(np.max(np.abs(a - b) / scale)))
    print(json.dumps({"same_steps": bool(steps), "max_rel": worst,
                      "same_status": bool(np.all(sharded.status == single.status)),
                      "ok": bool(np.all(sharded.ok))}))
""")


@pytest.mark.slow
def test_sharded_over_four_host_devices_equals_single_device():
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4")
    done = subprocess.run(
        [sys.executable, "-c", _SHARDED], capture_output=True, text=True, env=env, timeout=600
    )
    assert done.returncode == 0, done.stderr[-2000:]
    out = json.loads(done.stdout.strip().splitlines()[-1])
    # The same steps and statuses; values equal up to roundoff (measured ~1e-15; the
    # time of a flat maximum amplifies roundoff, measured 1e-10).
    assert out["ok"] and out["same_steps"] and out["same_status"], out
    assert out["max_rel"]["value"] <= 1e-12 and out["max_rel"]["time"] <= 1e-8, out


def test_padding_is_never_solved_and_small_sweeps_share_one_program():
    """A chunk's padding is never solved (its designs take no step), and sweeps of 5, 300
    and 1024 designs of one structure run one compiled program (`SHARED_CHUNK`), with
    the same peaks as single solves; so does the hard-switch model at other tolerances
    (widths and tolerances are values)."""
    import jax

    from recoil_jax._model.solve import peaks_batch

    designs = [{"m": 1000.0, "gap": g, "c_r": 500.0} for g in np.linspace(0.01, 0.1, 8)]
    params, _ = rjx.batch_params(designs)
    t1 = np.asarray(rjx.end_time(params, rj.SolverOptions()))
    out = peaks_batch(params, t1, rj.Smoothing(), rj.SolverOptions(), 4, np.asarray(3))
    steps = np.asarray(out.num_steps)
    assert np.all(steps[:3] > 0) and np.all(steps[3:] == 0)
    for i in range(3):
        single = rj.peaks(rj.params_from_values(designs[i]))
        assert float(out.peak_anchoring_force[i]) == pytest.approx(
            float(single.peak_anchoring_force), rel=1e-5
        )

    jax.clear_caches()  # whatever an earlier test compiled
    with compiled_programs() as programs:
        for n in (5, 300, 1024):
            gaps = np.linspace(0.0, 0.12, n)
            result = rj.sweep({"gap": gaps, "m": np.full(n, 700.0), "k_r": np.full(n, 3.3e4)})
            assert np.all(result.ok) and len(result) == n
        hard = rj.sweep(
            {"gap": gaps[[400, -1]], "m": np.full(2, 700.0), "k_r": np.full(2, 3.3e4)},
            smoothing=rj.Smoothing.exact(),
            options=rj.SolverOptions(rtol=1e-9, atol=1e-12),
        )
    compiled = [name for name in programs if "_peaks_batch" in name]
    assert len(compiled) == 1
    single = rj.peaks(rj.params_from_values(gap=0.12, m=700.0, k_r=3.3e4))
    exact = rj.peaks(
        rj.params_from_values(gap=0.12, m=700.0, k_r=3.3e4),
        rj.Smoothing.exact(),
        rj.SolverOptions(rtol=1e-9, atol=1e-12),
    )
    assert hard.peaks["peak_anchoring_force"][-1] == pytest.approx(
        float(exact.peak_anchoring_force), rel=1e-9
    )
    # Not the smoothed model's numbers (an impact, gap 47 mm): the widths reached the program.
    assert hard.peaks["peak_contact_force"][0] > 0
    assert hard.peaks["peak_contact_force"][0] != result.peaks["peak_contact_force"][400]
    assert result.peaks["peak_anchoring_force"][-1] == pytest.approx(
        float(single.peak_anchoring_force), rel=1e-5
    )


def test_knots_with_a_hole_are_refused_naming_the_design():
    nan = float("nan")
    designs = {"orifice_0": [1e-4, nan, 1e-4], "orifice_1": [1e-4, 1e-4, nan]}
    with pytest.raises(rj.ParameterError, match=r"design 1: .*orifice_0 is missing"):
        rj.sweep(designs, progress=False)
