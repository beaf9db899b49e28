"""`recoil-jax sweep` on the command line."""

import csv
import json

import numpy as np
import pytest

from recoil_jax.apps import main


def test_grid_sweep_writes_files_and_figures(tmp_path, capsys):
    out = tmp_path / "sweep"
    assert main(["sweep", "m=500,1500", "gap=0:0.09:10", "k_r=13000", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "swept 20 designs" in printed and "lowest peak anchoring force" in printed
    rows = list(csv.DictReader(open(out / "sweep.csv")))
    assert len(rows) == 20 and rows[0]["status"] == "ok"
    assert {"m", "gap", "k_r", "peak_anchoring_force_N", "d(peak_anchoring_force_N)/d(gap)"} <= set(
        rows[0]
    )
    data = np.load(out / "sweep.npz")
    meta = json.loads(str(data["metadata"]))
    assert meta["swept"] == ["m", "gap"] and meta["grid_shape"] == [2, 10]
    assert data["peak_anchoring_force_N"].shape == (20,)
    assert np.all(data["param_k_r"] == 13000.0)
    for name in (
        "fig6_peak_displacement_vs_gap",
        "fig10_peak_anchoring_force_vs_gap",
        "heatmap_peak_anchoring_force_N",
        "map_dF_AN_dgap",
    ):
        assert (out / f"{name}.png").read_bytes()[:4] == b"\x89PNG"


@pytest.mark.parametrize("kind", ["csv", "json"])
def test_points_file_json_output_in_input_order(tmp_path, capsys, kind):
    points = [dict(m=1500.0, gap=0.062), dict(m=100.0, gap=0.0), dict(m=1000.0, gap=0.059)]
    path = tmp_path / f"points.{kind}"
    if kind == "json":
        path.write_text(json.dumps(points))
    else:
        path.write_text("m,gap\n" + "\n".join(f"{p['m']},{p['gap']}" for p in points))
    assert main(["sweep", "--points", str(path), "--json"]) == 0
    records = json.loads(capsys.readouterr().out)
    assert [r["parameters"]["m"] for r in records] == [1500.0, 100.0, 1000.0]
    keys = {
        "peak_displacement_m",
        "peak_displacement_time_s",
        "peak_anchoring_force_N",
        "peak_anchoring_force_time_s",
        "peak_contact_force_N",
        "status",
    }
    assert all(keys <= set(r) for r in records)
    assert records[0]["peak_anchoring_force_N"] == pytest.approx(5514.05, abs=0.05)
    assert records[2]["peak_anchoring_force_N"] == pytest.approx(6017.82, abs=0.05)
    assert all(r["status"] == "ok" for r in records)


@pytest.mark.parametrize(
    "argv, fragment",
    [
        (["m=1,2", "gap=0:0.1"], "start:stop:count"),
        (["gap=-0.1,0.1"], "Absorber.gap[0] = -0.1 m"),
        (["m=100"], "nothing to sweep"),
        (["mass=1,2"], "unknown parameter"),
    ],
)
def test_sweep_bad_input(capsys, argv, fragment):
    assert main(["sweep", *argv]) == 2
    assert fragment in capsys.readouterr().err


def test_no_absorber_beside_absorbers_and_end_time_in_points(tmp_path, capsys):
    """`sweep m=0,500,1500 gap=0.05` (the first comparison a user makes) runs, and `t1`
    is accepted per point in `--points`, as by `simulate`."""
    assert main(["sweep", "m=0,500,1500", "gap=0.05", "--json"]) == 0
    records = json.loads(capsys.readouterr().out)
    assert [r["parameters"]["m"] for r in records] == [0.0, 500.0, 1500.0]
    assert records[0]["peak_anchoring_force_N"] == pytest.approx(6949.98, abs=0.01)
    assert "gap" not in records[0]["parameters"]
    assert all(r["status"] == "ok" for r in records)
    path = tmp_path / "points.csv"
    path.write_text("m,gap,t1\n500,0.0,0.3\n500,0.0,2.0\n")
    assert main(["sweep", "--points", str(path), "--json"]) == 0
    records = json.loads(capsys.readouterr().out)
    assert [r["parameters"]["t1"] for r in records] == [0.3, 2.0]
    assert records[0]["peak_displacement_m"] < records[1]["peak_displacement_m"]


def test_points_file_errors(tmp_path, capsys):
    path = tmp_path / "bad.csv"
    path.write_text("m,mass\n100,1\n")
    assert main(["sweep", "--points", str(path)]) == 2
    assert "unknown parameter 'mass'" in capsys.readouterr().err
    # A name both on the command line and as a column is refused, not resolved (#45).
    path = tmp_path / "p.csv"
    path.write_text("m,gap\n500,0.02\n")
    assert main(["sweep", "--points", str(path), "gap=0.05"]) == 2
    err = capsys.readouterr().err
    assert f"gap is given both on the command line (gap=0.05) and as a column of {path}" in err
    assert err.count("\n") == 1 and "Traceback" not in err


def test_one_swept_parameter_draws_both_peaks_and_points_say_why_not(tmp_path, capsys):
    out = tmp_path / "one"
    assert main(["sweep", "k_r=1e4:3e4:3", "--out", str(out)]) == 0
    capsys.readouterr()
    for name in ("peak_displacement_m_vs_k_r", "peak_anchoring_force_N_vs_k_r"):
        assert (out / f"{name}.png").read_bytes()[:4] == b"\x89PNG"
    points = tmp_path / "points.csv"
    points.write_text("m,gap\n500,0.01\n1500,0.06\n")
    assert main(["sweep", "--points", str(points), "--out", str(tmp_path / "p")]) == 0
    assert "no figures for a list of points" in capsys.readouterr().err
    assert not list((tmp_path / "p").glob("*.png"))
