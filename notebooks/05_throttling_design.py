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
# # 5. Designing a throttling orifice
#
# A hydraulic recoil buffer brakes the barrel by forcing oil through an orifice whose
# area `A_o(x)` changes along the stroke: `F_h = ρ A_p³ v|v| / (2 C_d² A_o(x)²)`. Shaping
# that area profile is the classic recoil-design problem. The best any brake can do is
# a **constant force** over the whole stroke: stopping the recoil energy `E0 = M v0²/2`
# within a travel `L` needs at least `E0/L` on the mounting (8910.4 N for the paper's
# gun and L = 0.15 m). Here `rj.search` shapes a 16-knot profile towards that limit from
# no start design at all, and we compare the result with the paper's linear damper.

# %%
import os

import matplotlib.pyplot as plt
import numpy as np
from scipy.optimize import brentq

import recoil_jax as rj

FAST = os.environ.get("RECOIL_JAX_FAST") == "1"  # the test suite runs a small version

# %% [markdown]
# ## The problem
# The simplified model (no absorber), the paper's barrel and impulse, a buffer with a
# 0.01 m² piston in oil. The 16 knot areas span three decades (1e-5 to 1e-2 m²), so
# the search moves them in log coordinates. The objective is the peak anchoring force,
# which jumps between local maxima (knots) as they move, so `search` takes it as a
# minimax over time (`local=rj.TrustRegionLP()`). The limit is the stroke.

# %%
KNOTS = [f"orifice_{i}" for i in range(16)]
buffer = dict(
    m=0.0, piston_area=0.01, oil_density=870.0, discharge_coefficient=0.7, orifice_length=0.15
)
params = rj.params_from_values(buffer | {name: 1e-3 for name in KNOTS})
problem = rj.DesignProblem(
    params=params,
    objective=rj.Objective({"peak_anchoring_force": 1.0}),
    tune=tuple(KNOTS),
    bounds={name: (1e-5, 1e-2) for name in KNOTS},
    constraints=(rj.Constraint("peak_displacement", upper=0.15),),
)
barrel = rj.params_to_values(params)
ideal = 0.5 * float(barrel["M"]) * float(barrel["v0"]) ** 2 / 0.15
print(f"constant-force limit E0/L = {ideal:.1f} N")

# %% [markdown]
# ## The search
# A Sobol sample of the box runs through the batched sweep; the local phase then polishes the best
# samples with exact gradients (one sensitivity solve per iteration gives the gradient
# of the objective and of the limit): the minimax levels the force at a thousand times
# over the stroke at once, each iteration a linear programme in a trust region
# (`min max_k F(t_k) + ∇F(t_k)·d`, `|d| <= radius`).

# %%
result = rj.search(
    problem,
    global_phase=rj.SobolStarts(64, 1) if FAST else rj.SobolStarts(512, 2),
    local=rj.TrustRegionLP(maxiter=15 if FAST else 100),
    use_design=False,
    max_seconds=60 if FAST else 300,
    progress=False,
)
best = rj.peaks(result.best_params())
hard = rj.peaks(result.best_params(), rj.Smoothing.exact())
print(f"feasible: {result.feasible[0]}; {result.solves} solves, {result.gradient_solves} gradient")
print(
    f"peak anchoring force {float(best.peak_anchoring_force):.1f} N "
    f"({float(best.peak_anchoring_force) / ideal - 1:+.2%} over E0/L), "
    f"stroke {1e3 * float(best.peak_displacement):.2f} mm; "
    f"hard switches: {1e3 * float(hard.peak_displacement):.2f} mm"
)

# %%
seconds, best_so_far = result.trace["seconds"], result.best_so_far()
fig, ax = plt.subplots(figsize=(8, 4))
sampled = result.trace["phase"] == "sample"
ax.plot(seconds[~sampled], result.trace["objective"][~sampled], ".", ms=3, alpha=0.4,
        label="gradient solves")  # fmt: skip
ax.step(seconds, best_so_far, "k", where="post", label="best feasible so far")
ax.axhline(ideal, color="C3", ls="--", label="E0/L")
finite = best_so_far[np.isfinite(best_so_far)]
ax.set_ylim(0.98 * ideal, 1.5 * ideal if finite.size == 0 else max(1.3 * finite.min(), ideal))
ax.set_xlabel("wall time (s)")
ax.set_ylabel("peak anchoring force (N)")
ax.set_title("search convergence")
ax.legend()
plt.show()

# %% [markdown]
# ## The orifice profile and the force over the stroke
# The tuned area closes along the stroke as the barrel slows, so that `v²/A_o²` (and
# with it the force) stays level. For comparison, the paper's linear damper, its
# outward damping `c_out` tuned by Brent's method to give the same stroke.

# %%
design = result.best_design()
areas = np.array([design[name] for name in KNOTS])
stroke = float(best.peak_displacement)
# The same barrel and impulse without the buffer (m = 0: no absorber either).
plain = {k: v for k, v in barrel.items() if k in ("M", "k", "c_out", "c_ret", "v0")} | {"m": 0.0}


def stroke_of(c_out):
    return float(rj.peaks(rj.params_from_values(plain | {"c_out": c_out})).peak_displacement)


c_out = brentq(lambda c: stroke_of(c) - stroke, 1e3, 1e6, xtol=1.0)
damper = rj.params_from_values(plain | {"c_out": c_out})


def recoil(params):
    end = float(rj.peaks(params).peak_displacement_time)
    history = rj.simulate(params, ts=np.linspace(0.0, end, 801))
    return 1e3 * np.asarray(history.x_M), 1e-3 * np.asarray(history.anchoring_force)


fig, (left, right) = plt.subplots(1, 2, figsize=(12, 4))
left.semilogy(1e3 * np.linspace(0.0, 0.15, len(KNOTS)), 1e4 * areas, "o-")
left.set_xlabel("stroke position x (mm)")
left.set_ylabel("orifice area A_o (cm²)")
left.set_title("tuned orifice profile (16 knots)")
right.plot(*recoil(result.best_params()), label="tuned orifice")
damper_peak = float(rj.peaks(damper).peak_anchoring_force)
right.plot(*recoil(damper), label=f"linear damper, c_out = {c_out:.0f} N·s/m")
right.plot([0.0, 1e3 * stroke], [1e-3 * ideal] * 2, "--", label=f"E0/L = {ideal:.0f} N")
right.set_xlabel("barrel travel x_M (mm)")
right.set_ylabel("anchoring force F_AN (kN)")
right.set_title("force over the recoil stroke")
right.legend()
plt.show()
print(
    f"linear damper: peak {damper_peak:.0f} N, "
    f"{damper_peak / float(best.peak_anchoring_force):.2f}x the tuned orifice's"
)
