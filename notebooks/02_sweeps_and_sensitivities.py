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
# # 2. Sweeps and sensitivities
#
# The recoil model maps a design (absorber mass m, clearance gap, coupling spring k_r and
# damper c_r) to peaks: barrel displacement, anchoring force (the load on the mounting),
# contact force and absorber stroke. Because every switch in the model is smoothed over a
# narrow band, these peaks are differentiable, and recoil-jax computes their gradients
# by forward sensitivities with error control. This notebook maps the peaks and their
# gradients over the design space, and shows where the peak switches from one local
# maximum to another — the kinks that matter for tuning.

# %%
import os

import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

import recoil_jax as rj

FAST = os.environ.get("RECOIL_JAX_FAST") == "1"

# %% [markdown]
# ## A vmapped grid with gradients

# %%
n = 9 if FAST else 41
masses = np.linspace(250.0, 3000.0, n)
gaps = np.linspace(0.0, 0.15, n)
result = rj.sweep_grid({"m": masses, "gap": gaps}, wrt=("gap", "m"))
print(f"{len(result)} designs in {result.seconds:.1f} s, failures: {result.failures()}")
force = result.peaks["peak_anchoring_force"].reshape(result.grid_shape)
dforce_dgap = result.gradients["peak_anchoring_force"]["gap"].reshape(result.grid_shape)

fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
mesh = axes[0].pcolormesh(1e3 * gaps, masses, force, shading="nearest")
fig.colorbar(mesh, ax=axes[0], label="peak anchoring force (N)")
limit = np.nanpercentile(np.abs(dforce_dgap), 98)
mesh = axes[1].pcolormesh(
    1e3 * gaps, masses, dforce_dgap, shading="nearest", cmap="RdBu_r", vmin=-limit, vmax=limit
)
fig.colorbar(mesh, ax=axes[1], label="d(peak F_AN)/d(gap) (N/m)")
for ax in axes:
    ax.set_xlabel("gap (mm)")
    ax.set_ylabel("absorber mass (kg)")
fig.tight_layout()

# %% [markdown]
# **The plateau.** Beyond some gap the barrel never reaches the absorber: no impact, and
# the gap gradient is *exactly* zero there. A gradient-based tuner started on the
# plateau cannot move the gap — which is why the optimiser runs many starts at once.

# %%
no_impact = result.peaks["peak_contact_force"].reshape(result.grid_shape) == 0
print(
    f"{no_impact.mean():.0%} of the grid has no impact; gap gradient there: "
    f"{np.abs(dforce_dgap[no_impact]).max() if no_impact.any() else 0.0}"
)

# %% [markdown]
# ## Where the peak switches: a kink at the optimum
# Along the gap at m = 1500 kg, the time of the peak anchoring force jumps: before the
# optimum the impact-driven maximum is the larger, after it the later spring-driven one.
# The gradient changes sign in a jump, not smoothly.

# %%
gaps_fine = np.linspace(0.045, 0.08, 15 if FAST else 141)
line = rj.sweep({"m": np.full_like(gaps_fine, 1500.0), "gap": gaps_fine}, wrt=("gap",))
fig, axes = plt.subplots(3, 1, figsize=(8, 8), sharex=True)
axes[0].plot(1e3 * gaps_fine, line.peaks["peak_anchoring_force"])
axes[0].set_ylabel("peak F_AN (N)")
axes[1].plot(1e3 * gaps_fine, line.peaks["peak_anchoring_force_time"], ".")
axes[1].set_ylabel("time of the peak (s)")
axes[2].plot(1e3 * gaps_fine, line.gradients["peak_anchoring_force"]["gap"])
axes[2].set_ylabel("dF/dgap (N/m)")
axes[2].set_xlabel("gap (mm)")
fig.tight_layout()

# %% [markdown]
# ## The smooth maximum over time
# `SmoothMax` replaces max_t F_AN(t) by T·log((1/t1)∫exp(F_AN/T)dt): both local maxima
# contribute, so the kink is rounded off over a few T. It sits a little below the peak.


# %%
def smooth_force(gap, temperature):
    params = rj.RecoilParams(absorber=rj.Absorber(m=1500.0, gap=gap))
    fn = rj.differentiable_peaks(
        params, ("gap",), smooth_max=rj.SmoothMax(("peak_anchoring_force",), [temperature])
    )
    return fn(jnp.atleast_1d(gap))[0]["smooth_peak_anchoring_force"]


smooth = jax.jit(jax.vmap(smooth_force, in_axes=(0, None)))
fig, ax = plt.subplots(figsize=(8, 4.5))
ax.plot(1e3 * gaps_fine, line.peaks["peak_anchoring_force"], "k", label="peak")
for temperature in (5.0, 20.0):
    ax.plot(
        1e3 * gaps_fine,
        smooth(jnp.asarray(gaps_fine), temperature),
        label=f"smooth max, T = {temperature:g} N",
    )
ax.set_xlabel("gap (mm)")
ax.set_ylabel("N")
ax.legend()

# %% [markdown]
# ## Sensitivity of the best design to every parameter
# Scaled by each parameter's documented range: which parameters matter most?

# %%
best = rj.RecoilParams(absorber=rj.Absorber(m=1500.0, gap=0.062))
wrt = tuple(rj.params_to_values(best))  # every parameter this design has
peaks, grads = rj.peak_jacobian(best, wrt=wrt)
scaled = {
    name: float(grads.peak_anchoring_force[j]) * rj.parameter_scale(name)
    for j, name in enumerate(wrt)
}
fig, ax = plt.subplots(figsize=(8, 4))
ax.bar(list(scaled), list(scaled.values()))
ax.set_ylabel("dF_AN/dθ × range (N)")
ax.tick_params(axis="x", rotation=45)
fig.tight_layout()

# %% [markdown]
# ## Global sensitivity over a tolerance box
# The local gradient above holds near the design. Over the tolerances a gun is built
# and fired with, `rj.sensitivity` ranks the parameters by their Sobol indices: the
# share of the peak's variance each causes alone (`S1`) and with its interactions (`ST`),
# from SALib's Saltelli sample solved through one sweep. DGSM, from the exact gradients,
# bounds `ST` from above (docs/sensitivity.md).

# %%
tolerances = {"k": 0.10, "c_out": 0.15, "v0": 0.05, "c_r": 0.15, "gap": (0.059, 0.065)}
metrics = ["peak_anchoring_force", "max_stroke"]
sobol = rj.sensitivity(best, tolerances, metrics, rj.SobolIndices(samples=1024))
bound = rj.sensitivity(best, tolerances, metrics, rj.DGSM(samples=1024))
print(f"{len(sobol.ok)} designs for Sobol, {len(bound.ok)} gradient solves for DGSM")

fig, axes = plt.subplots(1, 2, figsize=(10, 3.8), layout="constrained")
for ax, metric in zip(axes, metrics, strict=True):
    names = sobol.ranking(metric)[::-1]
    y = np.arange(len(names))
    for offset, (result, key, label) in zip(
        (-0.27, 0.0, 0.27),
        ((sobol, "S1", "S1"), (sobol, "ST", "ST"), (bound, "dgsm", "DGSM bound on ST")),
        strict=True,
    ):
        values = [result.indices[metric][n][key] for n in names]
        errors = [result.indices[metric][n][f"{key}_conf"] for n in names]
        ax.barh(y + offset, values, height=0.27, xerr=errors, label=label)
    ax.set_yticks(y, names)
    ax.set_title(metric)
axes[0].legend(loc="lower right")
