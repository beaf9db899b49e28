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
# # 8. The firing envelope: elevation, friction, return to battery, stability
#
# The paper fires one round horizontally on frictionless rails. A gun fires from 0° to its
# maximum elevation, where gravity pulls the recoiling parts down the rails (`g sin θ`);
# its slides and packings rub (Coulomb friction `F_max = F_0 + μ (M + m) g cos θ`, which
# can hold a barrel out of battery); a preloaded recuperator must bring the barrel back
# against both, onto a **battery stop** (Hunt–Crossley, like the absorber's wall), slowed
# by a **counter-recoil buffer**; and the force on the mount must not lift the gun off
# the ground. Each is an optional group of flat parameters (`elevation`,
# `friction_force`, `friction_coefficient`, `recuperator_preload`, `stop_stiffness`,
# `buffer_damping`, `buffer_length`, `mount_mass`, `cg_distance`, `trunnion_height`,
# `spade_distance`; `docs/model.md`, *Firing envelope*), and a design with any of them
# has four more metrics, each with exact gradients: `return_time` (from the last round to
# the barrel back through `x_M = 1 mm`), `battery_speed` (how fast it arrives),
# `residual_displacement` (`x_M(t1)`) and `stability_margin` (the least share of the
# gun's weight moment about the spade left at any moment; below 0 the wheels lift).
#
# Friction sticks in the model as in the exact law: a held barrel does not creep (the
# sticking law is in `docs/model.md`, *Sticking*, with what it costs against an exact
# stick, measured against the independent hard-switch reference).

# %%
import os

import matplotlib.pyplot as plt
import numpy as np

import recoil_jax as rj

FAST = os.environ.get("RECOIL_JAX_FAST") == "1"  # the test suite runs a small version

# %% [markdown]
# ## The paper's best absorber stops working within a few degrees
# Its 1,500 kg hang on 13,000 N/m: at elevation θ they sag `m g sin θ / k_r` rearward on
# their spring before the shot, which widens the 62 mm gap the absorber was tuned to at
# 0°. From 2° on the barrel no longer reaches it (no contact force); at 5° the sag alone
# (98.6 mm) is more than the gap, and the peak anchoring force has doubled.

# %%
elevations = np.linspace(0.0, 10.0, 6 if FAST else 21)
paper = rj.params_to_values(rj.RecoilParams())
swept = rj.sweep([dict(paper, elevation=float(e)) for e in elevations], progress=False)
assert np.all(swept.ok)
sag = paper["m"] * 9.80665 * np.sin(np.radians(elevations)) / paper["k_r"]

fig, (left, right) = plt.subplots(1, 2, figsize=(10, 3.6))
left.plot(elevations, swept.peaks["peak_anchoring_force"] / 1e3, "o-")
left.set_xlabel("elevation (°)")
left.set_ylabel("peak anchoring force (kN)")
right.plot(elevations, swept.peaks["peak_contact_force"] / 1e3, "o-", color="C1")
right.set_xlabel("elevation (°)")
right.set_ylabel("peak contact force (kN)", color="C1")
twin = right.twinx()
twin.plot(elevations, sag * 1e3, "--", color="C2")
twin.axhline(paper["gap"] * 1e3, color="C2", lw=0.8)
twin.set_ylabel("absorber's sag (mm); the gap", color="C2")
fig.suptitle("The paper's best absorber against elevation")
fig.tight_layout()

# %% [markdown]
# ## A barrel held out of battery by friction
# The paper's barrel with 2 kN of packing friction: its spring (27.5 kN/m) cannot pull it
# back once the spring force falls inside the friction band, so it sticks out of
# battery. The model says so: no return time (`returned = False`, `null` in the JSON),
# and the residual displacement where the exact hard-switch reference (an independent
# scipy solver with stick and slip as events) puts it.

# %%
stuck = rj.params_from_values(friction_force=2000.0)
history = rj.simulate(stuck, ts=np.linspace(0.0, 10.0, 2001))
peaks = rj.peaks(stuck)
reference = rj.reference_peaks({"friction_force": 2000.0})
print(f"returned: {bool(peaks.returned)} (reference: {reference['returned']})")
print(
    f"rests at {float(peaks.residual_displacement) * 1e3:.3f} mm "
    f"(reference {reference['residual_displacement'] * 1e3:.3f} mm)"
)

fig, ax = plt.subplots(figsize=(9, 3.4))
ax.plot(history.ts, history.x_M * 1e3, label="barrel x_M, with 2 kN of friction")
plain = rj.simulate(rj.RecoilParams(), ts=history.ts)
ax.plot(plain.ts, plain.x_M * 1e3, "--", color="0.5", label="the paper's, without")
ax.axhline(1.0, color="k", lw=0.6)
ax.set_xlabel("t (s)")
ax.set_ylabel("x_M (mm)")
ax.legend()
ax.set_title("Friction holds the barrel 54 mm out of battery")

# %% [markdown]
# ## Return and stability over elevation × preload
# A light howitzer (`M = 1,800 kg`, `v0 = 10 m/s` over a 4 ms pulse, 1.5 kN of packing
# friction and μ = 0.05, a stiff battery stop, a counter-recoil buffer over the last
# 0.15 m, on an 8,000 kg mount): the recuperator's preload must bring the barrel back at
# every elevation (at 70° gravity pulls it down the rails with 16.6 kN). The mount's
# margin is held against two moments: the recoil's push, worst at low elevation, and at
# high elevation the counter-recoil buffer's pull as a strong preload brings the barrel
# back fast (the margin's formula in `envelope.md`). Each cell is a solve with its
# metrics; a cross marks a design whose barrel never comes back.

# %%
howitzer = dict(
    M=1800.0, v0=10.0, m=0.0, pulse_time=0.004, k=1e-6, c_out=16000.0, c_ret=15000.0,
    friction_force=1500.0, friction_coefficient=0.05, stop_stiffness=2.1e8,
    recuperator_length=1.8, buffer_damping=150000.0, buffer_length=0.15,
    mount_mass=8000.0, cg_distance=3.2, trunnion_height=1.1, spade_distance=3.6,
)  # fmt: skip
n = 5 if FAST else 13
grid = rj.sweep_grid(
    {"elevation": np.linspace(0.0, 70.0, n), "recuperator_preload": np.linspace(5e3, 8e4, n)},
    howitzer,
    options=rj.SolverOptions(t1=6.0),
    progress=False,
)
assert np.all(grid.ok)
shape = (n, n)
returned = grid.peaks["returned"].reshape(shape).astype(bool)
back = np.where(returned, grid.peaks["return_time"].reshape(shape), np.nan)
margin = grid.peaks["stability_margin"].reshape(shape)
preload_kN, elevation = np.linspace(5.0, 80.0, n), np.linspace(0.0, 70.0, n)
never = np.argwhere(~returned)

fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4))
image = left.pcolormesh(preload_kN, elevation, back, shading="nearest", cmap="viridis")
left.plot(preload_kN[never[:, 1]], elevation[never[:, 0]], "x", color="k")
fig.colorbar(image, ax=left, label="return time (s)")
left.set_title("return to battery (x: never)")
image = right.pcolormesh(preload_kN, elevation, margin, shading="nearest", cmap="RdYlGn")
right.contour(preload_kN, elevation, margin, levels=[0.0], colors="k")
fig.colorbar(image, ax=right, label="least stability margin (black: 0)")
right.set_title("stability of the mount (below 0 the wheels lift)")
for ax in (left, right):
    ax.set_xlabel("recuperator preload (kN)")
    ax.set_ylabel("elevation (°)")
fig.tight_layout()
