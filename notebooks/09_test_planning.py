# ---
# jupyter:
#   jupytext:
#     formats: ipynb,py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # 9. Planning a firing test
#
# A calibration (notebook 7) fits the model to the traces a test produced. The test is
# where the money goes, and a test that records the wrong signals at the wrong
# conditions leaves the model undetermined whatever the fit does. The envelope gun
# (notebook 8) rubs on its slides with Coulomb friction
# `F_max = F_0 + μ (M + m) g cos θ`: fired only at 0°, packing friction `F_0` and slide
# friction `μ` act as the one sum `F_0 + μ (M + m) g`, and no number of horizontal rounds
# separates them. Two elevations do, since `cos θ` changes.
#
# Planning is the calibration's information matrix `JᵀJ/σ²` computed before the data
# exist, from the exact sensitivities of each signal at each sample time. For every
# candidate firing (an elevation and a charge) and every signal it could record,
# `rj.plan_firings` computes it in one program and chooses the firings and records
# within a budget by Fedorov's exchange (`docs/planning.md`).

# %%
import os
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from IPython.display import Image, display

import recoil_jax as rj
import recoil_jax.extend as rjx
from recoil_jax.apps import plot_plan_information, plot_plan_intervals

FAST = os.environ.get("RECOIL_JAX_FAST") == "1"  # the test suite runs a small version
FIGURES = Path(tempfile.mkdtemp())  # the figures' files (shown below, not kept)

# %% [markdown]
# ## The test to plan
# The envelope gun's hand design is the best guess. The test must determine the two
# dampers, the recuperator's preload and both frictions. Each of 3 rounds may be fired
# at 6 elevations with 2 charges, and record the barrel's travel `x_M` and velocity
# `v_M` (cost 1 each) and the anchoring force `F_AN` (cost 3), within 4 a round.

# %%
gun = {
    "M": 1800.0,
    "m": 0.0,
    "k": 0.0,
    "v0": 10.0,
    "pulse_time": 0.004,
    "stop_stiffness": 2.1e8,
    "recuperator_length": 1.8,
    "buffer_length": 0.15,
    "buffer_damping": 150000.0,
    "c_out": 16000.0,
    "c_ret": 15000.0,
    "recuperator_preload": 30000.0,
    "friction_force": 1500.0,
    "friction_coefficient": 0.05,
}
problem = rj.PlanProblem(
    design=gun,
    fit={
        "c_out": (5e3, 5e4),
        "c_ret": (5e3, 5e4),
        "recuperator_preload": (1e4, 6e4),
        "friction_force": (0.0, 5e3),
        "friction_coefficient": (0.0, 0.2),
    },
    candidates={"elevation": [0, 15, 30, 45, 60, 70], "v0": [8.0, 10.0]},
    signals={
        "x_M": rj.Sensor(3e-4, 1.0),
        "v_M": rj.Sensor(3e-3, 1.0),
        "F_AN": rj.Sensor(200.0, 3.0),
    },
    rate=1000.0,
    duration=3.0,
    firings=3,
    cost=4.0,
)
plan = rj.plan_firings(problem)
for c, signals in plan.plan.firings:
    print(plan.conditions[c], "records", signals)
print(f"{plan.seconds:.1f} s (the first call compiles)")

# %% [markdown]
# ## Fired at 0° only, friction is not separated
# Beside the plan, `plan_firings` reports the two tests a person would fire without it:
# the rounds spread evenly over the candidates, and every round at the first candidate
# (0°, the test most rigs fire). The last one determines the dampers and the preload,
# but says of the friction what the calibration's report would say after the test:

# %%
for label, report in (
    ("planned", plan.plan),
    ("spread evenly", plan.baseline),
    ("all at 0°", plan.first_candidate),
):
    print(
        f"{label:>14}: criterion {report.criterion:.1f};",
        ", ".join(f"{n} ± {'—' if s is None else f'{s:.3g}'}" for n, s in report.stderr.items()),
    )
for text in plan.first_candidate.undetermined:
    print("all at 0°:", text)

# %%
display(Image(str(plot_plan_intervals(plan, FIGURES / "intervals.png"))))

# %% [markdown]
# ## Which candidates carry the information
# Left: the standard error one firing alone would give each parameter if the others
# were known. The high elevations inform the slide friction most (`cos θ` is
# smallest there); no single firing separates the two frictions, a pair at two
# elevations does. Right: what one more firing there would add to the plan,
# `tr(M⁻¹ F)`.

# %%
display(Image(str(plot_plan_information(plan, FIGURES / "information.png"))))

# %% [markdown]
# ## Along the friction line
# What "not separated" means: move the two frictions together along the line that
# keeps their horizontal sum, `F_0 + μ M g = 1500 + 0.05 · 1800 · g`, and compare each
# test's noise-free signals with the truth's, `χ² = Σ ((y − y_truth)/σ)²` over every
# sample of its firings. Fired at 0° only, every point of the line fits as well as the
# truth; the planned test rises off it at once.

# %%
M, g = gun["M"], 9.80665
total = gun["friction_force"] + gun["friction_coefficient"] * M * g
forces = np.linspace(600.0, 2350.0, 8 if FAST else 36)
fields = {"x_M": "x_M", "v_M": "v_M", "F_AN": "anchoring_force"}
options = rj.SolverOptions(t1=problem.duration, rtol=1e-9, atol=1e-12)


def signals(values, report):
    out = []
    for c, recorded in report.firings:
        params = rj.params_from_values(gun | values | plan.conditions[c])
        history = rj.simulate(params, options=options, ts=problem.times)
        out += [
            np.asarray(getattr(history, fields[s])) / problem.signals[s].sigma for s in recorded
        ]
    return np.concatenate(out)


fig, ax = plt.subplots(figsize=(6.5, 3.8))
for report, label, colour in (
    (plan.plan, "planned", "C0"),
    (plan.first_candidate, "all at 0°", "C2"),
):
    truth = signals({}, report)
    chi2 = [
        np.sum(
            (
                signals(
                    {"friction_force": f, "friction_coefficient": (total - f) / (M * g)}, report
                )
                - truth
            )
            ** 2
        )
        for f in forces
    ]
    ax.semilogy(forces, np.maximum(chi2, 1e-6), "o-", ms=3, color=colour, label=label)
ax.axhline(1.0, color="0.4", ls=":", lw=1)
ax.text(forces[0], 1.3, "χ² = 1: one noise deviation", fontsize=8, color="0.3")
ax.axvline(gun["friction_force"], color="k", lw=0.8)
ax.set_xlabel("friction_force F_0 (N), with μ keeping F_0 + μ M g fixed")
ax.set_ylabel("χ² against the truth's signals\n(zero drawn at 1e-6)")
ax.set_title("Moving the frictions along their horizontal sum")
ax.legend()
fig.tight_layout()
fig.savefig(FIGURES / "friction_line.png", dpi=110)
plt.close(fig)
display(Image(str(FIGURES / "friction_line.png")))

# %% [markdown]
# ## Does the prediction hold?
# The prediction is a linearisation. `rjx.check_plan` simulates noisy tests at a truth
# drawn from the middle of the box, fits each with the calibration (one batched
# program, each fit started at the truth), and compares each parameter's spread of
# fitted values with the standard error predicted at that truth: a ratio near 1 means
# the intervals above are the ones a real test would give.

# %%
tests = 12 if FAST else 100
checks = rjx.check_plan(plan, tests, which=("plan", "baseline"))
for name, check in checks.items():
    ratios = ", ".join(f"{p} {r:.2f}" for p, r in check.ratio.items() if r is not None)
    print(f"{name}: {check.converged}/{check.tests} fits converged; spread / predicted: {ratios}")
