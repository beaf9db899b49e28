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
