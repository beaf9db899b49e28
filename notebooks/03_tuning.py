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
# # 3. Tuning the absorber with optax
#
# The absorber is a mass m riding on the recoiling barrel, struck by a wall on the barrel
# once the clearance `gap` closes. The impact hands the absorber momentum, and a good
# design times it so that the load on the gun's mounting (the peak anchoring force) is
# as low as possible. Here we let gradient descent find that design: multi-start optax
# runs, a limit on the absorber's travel (it must fit its housing), a Pareto front
# against the absorber mass, and a design that is robust to round-to-round scatter in
# the recoil velocity.

# %%
import os

import matplotlib.pyplot as plt
import numpy as np
import optax

import recoil_jax as rj

FAST = os.environ.get("RECOIL_JAX_FAST") == "1"
STEPS = 40 if FAST else 250
STARTS = 4 if FAST else 16

# %% [markdown]
# ## The paper's question: the best gap for m = 1500 kg
# The optimum sits on a kink (notebook 2), so the objective the optimiser sees is the
# smooth maximum over time, annealed towards the peak as the run goes on.

# %%
problem = rj.DesignProblem(
    params=rj.RecoilParams(absorber=rj.Absorber(m=1500.0, gap=0.03)),
    objective=rj.Objective(
        {"peak_anchoring_force": 1.0}, temperatures={"peak_anchoring_force": 10.0}
    ),
    tune=("gap",),
    bounds={"gap": (0.0, 0.12)},
)
result = rj.optimise(problem, starts=STARTS, steps=STEPS)
print(
    f"best gap {1e3 * result.best_theta[0, 0]:.2f} mm, peak F_AN {result.best_objective[0]:.2f} N"
)
for cluster in result.clusters():
    print(
        cluster["count"],
        "starts ended at",
        cluster["design"],
        "->",
        cluster["objective"],
        "(no impact)" if cluster["no_impact"] else "",
    )

fig, ax = plt.subplots(figsize=(8, 4))
ax.plot(1e3 * result.history["theta"][:, :, 0])
ax.set_xlabel("step")
ax.set_ylabel("gap (mm)")
ax.set_title("every start's gap, step by step")

# %% [markdown]
# ## Four parameters under a travel limit
# Tune gap, m, k_r, c_r with m ≤ 1500 kg (a bound, held exactly by the sigmoid
# reparametrisation) and max(x_m − x_M) ≤ 0.15 m (an augmented-Lagrangian constraint).
# Any optax optimiser works; here Adam with a cosine-decayed step.

# %%
problem = rj.DesignProblem(
    params=rj.RecoilParams(absorber=rj.Absorber(m=1500.0, gap=0.062)),
    objective=rj.Objective({"peak_anchoring_force": 1.0}),
    constraints=(rj.Constraint("m", upper=1500.0), rj.Constraint("max_stroke", upper=0.15)),
)
result = rj.optimise(
    problem,
    starts=STARTS,
    steps=STEPS,
    optimiser=optax.adam(optax.cosine_decay_schedule(0.1, STEPS, alpha=0.01)),
)
design = result.best_design()
metrics = rj.peaks(result.best_params(), options=problem.options).metrics()
print({k: round(design[k], 4) for k in problem.tune})
print(
    f"peak F_AN {metrics['peak_anchoring_force']:.1f} N (paper's design: 5514.1 N), "
    f"max stroke {metrics['max_stroke']:.4f} m"
)
print(rj.constraint_report(problem, design, metrics))

# %% [markdown]
# ## A Pareto front: the lowest force for each absorber mass
# One vmapped run: every mass is a scenario with its own starts.

# %%
masses = np.array(
    [250.0, 750.0, 1500.0] if FAST else [100.0, 250.0, 500.0, 750.0, 1000.0, 1500.0, 2000.0, 3000.0]
)
front_problem = rj.DesignProblem(
    params=rj.RecoilParams(absorber=rj.Absorber(m=1500.0, gap=0.062)),
    objective=rj.Objective({"peak_anchoring_force": 1.0}),
    tune=("gap", "k_r", "c_r"),
    constraints=(rj.Constraint("max_stroke", upper=0.15),),
)
scenarios = rj.params_from_values(m=masses, gap=np.full_like(masses, 0.062))
front = rj.optimise(front_problem, scenarios=scenarios, starts=max(2, STARTS // 2), steps=STEPS)
fig, ax = plt.subplots(figsize=(8, 4))
ax.plot(masses, front.best_objective, "o-")
ax.set_xlabel("absorber mass (kg)")
ax.set_ylabel("lowest peak anchoring force (N)")

# %% [markdown]
# ## Robust design: v0 scatters ±5 %
# The objective is the worst case over five v0 values, evaluated together (vmapped).

# %%
robust_problem = rj.DesignProblem(
    params=rj.RecoilParams(absorber=rj.Absorber(m=1500.0, gap=0.062)),
    objective=rj.Objective(
        {"peak_anchoring_force": 1.0}, scatter=("v0", (-0.05, -0.025, 0.0, 0.025, 0.05))
    ),
    tune=("gap", "k_r", "c_r"),
    constraints=(rj.Constraint("max_stroke", upper=0.15),),
)
robust = rj.optimise(robust_problem, starts=max(2, STARTS // 2), steps=STEPS)
offsets = np.linspace(-0.05, 0.05, 5 if FAST else 21)
fig, ax = plt.subplots(figsize=(8, 4))
for label, params in (
    ("nominal optimum", result.best_params()),
    ("robust optimum", robust.best_params()),
):
    v0 = float(params.barrel.v0)
    forces = [
        float(
            rj.peaks(
                rj.RecoilParams(barrel=rj.Barrel(v0=v0 * (1 + o)), absorber=params.absorber)
            ).peak_anchoring_force
        )
        for o in offsets
    ]
    ax.plot(100 * offsets, forces, "o-", label=f"{label}: worst {max(forces):.0f} N")
ax.set_xlabel("v0 offset (%)")
ax.set_ylabel("peak anchoring force (N)")
ax.legend()
