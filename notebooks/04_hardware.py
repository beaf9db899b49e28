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
# # 4. Recoil hardware: breech pulse, burst fire, throttling orifice, gas recuperator
#
# The paper's gun is an idealisation: one impulse, a linear spring, a linear two-rate
# damper. Real recoil systems are driven by a **breech-force history** (the propellant
# gas pushes for milliseconds, not an instant), fire **bursts** of rounds, brake the
# barrel with oil forced through a **throttling orifice** whose area changes along the
# stroke (`F_h = ρ A_p³ v|v| / (2 C_d² A_o(x)²)`), and return it to battery with a **gas
# recuperator**, a nonlinear air spring (`F_g = F_r((L_r/(L_r − x))^γ − 1)`). Each part is
# optional and has flat parameter names (`pulse_time`, `shots`, `fire_interval`,
# `piston_area`, `orifice_0` …, `recuperator_force`, …) that work everywhere: in
# `params_from_values`, on the command line, in sweeps, in `wrt` and in `tune`.

# %%
import os

import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

import recoil_jax as rj

FAST = os.environ.get("RECOIL_JAX_FAST") == "1"  # the test suite runs a small version

# %% [markdown]
# ## A burst of three rounds, every element's force
# Three 5 ms pulses one second apart, an 8-knot orifice that closes along the stroke,
# and a recuperator. The anchoring force — everything that loads the mounting — is the
# sum of the spring, the damper, the orifice and the gas spring.

# %%
knots = {f"orifice_{i}": a for i, a in enumerate(np.linspace(4e-4, 1.5e-4, 8))}
design = (
    dict(
        m=0.0,
        shots=3,
        fire_interval=1.0,
        pulse_time=0.005,
        piston_area=0.01,
        orifice_length=0.2,
        recuperator_force=3000.0,
        recuperator_length=1.0,
    )
    | knots
)
params = rj.params_from_values(design)
history = rj.simulate(params, ts=jnp.linspace(0.0, 4.0, 2001 if FAST else 8001))
print(
    f"peak displacement {float(history.peaks.peak_displacement):.4f} m, peak anchoring "
    f"force {float(history.peaks.peak_anchoring_force):.0f} N"
)

f = history.forces
fig, axes = plt.subplots(3, 1, figsize=(9, 8), sharex=True)
axes[0].plot(history.ts, 1e3 * history.x_M)
axes[0].set_ylabel("barrel $x_M$ (mm)")
for label, force in (
    ("anchoring $F_{AN}$", history.anchoring_force),
    ("spring", f.recoil_spring),
    ("damper", f.recoil_damper),
    ("orifice $F_h$", f.buffer),
    ("recuperator $F_g$", f.recuperator),
):
    axes[1].plot(history.ts, 1e-3 * force, label=label)
axes[1].set_ylabel("force (kN)")
axes[1].legend(fontsize=8)
axes[2].plot(history.ts, 1e-3 * f.breech, color="C4")
axes[2].set_ylabel("breech force $F_b$ (kN)")
axes[2].set_xlabel("time (s)")
fig.tight_layout()

# %% [markdown]
# ## The pulse tends to the impulse
# As the pulse gets shorter the model tends to the paper's impulse: the state at a given
# time at first order, the peaks at second order.

# %%
impulse = rj.peaks(rj.params_from_values(m=1500.0, gap=0.062))
times = np.array([8e-3, 4e-3, 2e-3, 1e-3])
errors = [
    abs(
        float(rj.peaks(rj.params_from_values(m=1500.0, gap=0.062, pulse_time=tp)).peak_displacement)
        - float(impulse.peak_displacement)
    )
    for tp in times
]
fig, ax = plt.subplots(figsize=(6, 4))
ax.loglog(1e3 * times, errors, "o-")
ax.set_xlabel("pulse_time (ms)")
ax.set_ylabel("|peak displacement − impulse's| (m)")
print("order:", np.polyfit(np.log(times), np.log(errors), 1)[0])

# %% [markdown]
# ## Shaping the orifice: which knot matters
# The gradient of the peak anchoring force with respect to every knot, from one solve
# with forward sensitivities: the knots the peak depends on are those the barrel passes
# near the moment of the peak.

# %%
single = rj.params_from_values(dict(m=0.0, piston_area=0.01, orifice_length=0.2) | knots)
names = tuple(knots)
peaks, grads = rj.peak_jacobian(single, wrt=names)
fig, ax = plt.subplots(figsize=(8, 3.5))
ax.bar(names, 1e-4 * np.asarray(grads.peak_anchoring_force))
ax.set_ylabel("∂F_AN/∂area × 1 cm² (N)")
ax.tick_params(axis="x", rotation=45)
fig.tight_layout()

# %% [markdown]
# ## Sweeping the firing rhythm
# Rounds fired faster pile up: the barrel has not returned when the next one comes.

# %%
intervals = np.linspace(0.3, 1.5, 7 if FAST else 25)
sweep = rj.sweep(
    {
        "m": np.zeros_like(intervals),
        "shots": np.full_like(intervals, 3.0),
        "fire_interval": intervals,
        "recuperator_force": np.full_like(intervals, 3e3),
    },
    progress=False,
)
fig, ax = plt.subplots(figsize=(6, 4))
ax.plot(intervals, 1e-3 * sweep.peaks["peak_anchoring_force"], "o-")
ax.set_xlabel("fire_interval (s)")
ax.set_ylabel("peak anchoring force (kN)")
