"""What a newcomer met on the envelope (issue 63), each kept fixed: one type for a
returned barrel in `simulate --json` and `sweep --json`, and a unitless limit printed
without a stray space."""

from __future__ import annotations

import json

import recoil_jax as rj
from recoil_jax.apps import main
from recoil_jax.apps._studies.study import study_summary

#: The hand design of `optimise/envelope.toml` at 35°.
HOWITZER = {"M": 1800.0, "v0": 10.0, "m": 0.0, "pulse_time": 0.004, "k": 0.0, "t1": 6.0,
            "friction_force": 1500.0, "friction_coefficient": 0.05, "stop_stiffness": 2.1e8,
            "recuperator_length": 1.8, "buffer_length": 0.15, "c_out": 16000.0,
            "c_ret": 30000.0, "recuperator_preload": 30000.0, "buffer_damping": 40000.0,
            "elevation": 35.0}  # fmt: skip


def test_a_return_is_true_or_false_in_every_json(capsys):
    assert main(["simulate", "--json", *(f"{k}={v}" for k, v in HOWITZER.items())]) == 0
    simulated = json.loads(capsys.readouterr().out)
    records = rj.sweep([HOWITZER], progress=False).records()
    assert simulated["returned"] is True and records[0]["returned"] is True
    (paper,) = rj.sweep([{"m": 0.0}], progress=False).records()
    assert paper["returned"] is None  # no firing envelope: no return to judge


def test_a_unitless_limit_has_no_stray_space():
    report = {"study": "s", "objective": 1.0, "objective_unit": "N", "simulations": 1,
              "seconds": 1.0, "best": {"c_out": 1.0}, "tuned": ["c_out"], "conditions": {},
              "constraints": {"stability_margin": {"value": 0.4, "limit": 0.1,
                                                   "satisfied": True}}}  # fmt: skip
    text = study_summary(report)
    assert "stability_margin: 0.4 (limit 0.1) ok" in text, text


def test_the_force_figure_shows_every_part_of_the_envelope_gun(tmp_path, monkeypatch):
    """Preload, counter-recoil buffer, friction, stop and gravity drawn (not a flat
    recuperator at 0 under a 30 kN preload), no absorber drawn for m = 0, the elevation
    in the title, and the axis cut where the gun is back at rest under its static load."""
    import numpy as np

    import recoil_jax.apps._figures.histories as histories

    figures = []
    monkeypatch.setattr(histories, "save", lambda fig, path: figures.append(fig) or path)
    params = rj.params_from_values({k: v for k, v in HOWITZER.items() if k != "t1"})
    history = rj.simulate(params, options=rj.SolverOptions(t1=6.0),
                          ts=np.linspace(0.0, 6.0, 3001))  # fmt: skip
    from recoil_jax.apps._files.describe import describe

    histories.plot_history(history, tmp_path / "h.png", title=describe(HOWITZER))
    (fig,) = figures
    labels = [t.get_text() for ax in fig.axes if ax.get_legend() for t in ax.get_legend().texts]
    for part in ("preload $F_p$", "counter-recoil buffer", "rail friction", "battery stop",
                 "gravity on the barrel"):  # fmt: skip
        assert any(part in label for label in labels), (part, labels)
    assert not any("absorber" in label or "contact" in label or "gas" in label for label in labels)
    assert "elevation 35°" in fig._suptitle.get_text()
    assert "of 6 s" in fig.axes[-1].get_xlabel() and fig.axes[-1].get_xlim()[1] < 3.0


def test_the_shipped_files_are_inside_the_documented_ranges():
    """What is shipped (every study, every plan) warns of nothing: its designs, bounds,
    conditions and candidates lie in the documented ranges, or set a part to 0 (`k`, `m`)."""
    from recoil_jax.apps._files.inputs import design_warnings, values_taken
    from recoil_jax.apps._studies.plan_file import SHIPPED as PLANS, load_plan
    from recoil_jax.apps._studies.study_file import SHIPPED as STUDIES, load_study, study_values

    studies, plans = sorted(STUDIES.glob("*.toml")), sorted(PLANS.glob("*.toml"))
    assert len(studies) >= 10 and plans
    for path in studies:
        assert design_warnings(study_values(load_study(path).problem)) == [], path.name
    for path in plans:
        plan, _ = load_plan(path)
        values = values_taken(plan.design, plan.fit, plan.candidates)
        assert design_warnings(values) == [], path.name
    # (and a value outside does warn: the check is not empty)
    assert design_warnings({"v0": 13.0, "k": 0.0, "m": 0.0}) == [
        "v0=13 is outside the documented range 0.1 to 12 m/s, where the model's accuracy is tested"
    ]


def test_every_command_warns_of_a_value_outside_its_documented_range(tmp_path, capsys):
    """`optimise`, `plan` and `calibrate` warn as `simulate` and `sweep` do, before their
    work (here the output folder, a file, stops each at once)."""
    from recoil_jax.apps._studies.plan_file import SHIPPED as PLANS
    from recoil_jax.apps._studies.study_file import SHIPPED as STUDIES

    blocked = tmp_path / "a file"
    blocked.write_text("")
    study = (STUDIES / "envelope.toml").read_text().replace("v0 = 10.0", "v0 = 13.0")
    plan = (PLANS / "envelope_friction.toml").read_text().replace("v0 = 10.0", "v0 = 13.0")
    (tmp_path / "study.toml").write_text(study)
    (tmp_path / "plan.toml").write_text(plan)
    trace = tmp_path / "trace.csv"
    trace.write_text("t,x_M\n" + "".join(f"{i / 1000},{1e-3 * i}\n" for i in range(1, 50)))
    (tmp_path / "calibration.toml").write_text(
        '[design]\nv0 = 13.0\n[fit]\nc_out = [1e3, 4e4]\n[[experiment]]\ntrace = "trace.csv"\n'
    )
    for command in (["optimise", "study.toml"], ["plan", "plan.toml"],
                    ["calibrate", "calibration.toml"]):  # fmt: skip
        path = tmp_path / command[1]
        assert main([command[0], str(path), "--out", str(blocked)]) == 2, command
        err = capsys.readouterr().err
        assert "warning: v0" in err and "v0=13" in err, command
        assert "outside the documented range 0.1 to 12 m/s" in err, command
