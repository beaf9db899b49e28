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
# # 6. The design explorer
#
# One solve takes about a millisecond once compiled, so a design can be explored live:
# change a parameter and watch the barrel, the absorber and the force on the mounting
# respond. The explorer has a number field for every parameter, grouped by part (a part
# is off at its "none" value: `m = 0`, `piston_area = 0`, `recuperator_force = 0`), and
# shows the displacements and forces against time, the peaks against their limits, and
# the change in the peak anchoring force for +1 % of each parameter ("which knob
# matters here"). The same page is served by `recoil-jax explore`.
#
# In a live notebook the cell below is interactive (Panel with Bokeh plots); on a static
# page it shows the layout only. The cells after it show, as figures, what it computes.

# %%
import matplotlib.pyplot as plt
import numpy as np
import panel as pn

import recoil_jax as rj
from recoil_jax.apps import explorer

pn.extension()
explorer({"m": 1500.0, "gap": 0.062}, duration=1.5)

# %% [markdown]
# ## What the explorer computes, for the paper's best absorber
# One compiled program per model structure returns the history, the peaks (as
# `recoil-jax simulate` reports them) and the gradient of the peak anchoring force by
# forward sensitivities. After the first compilation an update takes milliseconds.

# %%
params = rj.params_from_values(m=1500.0, gap=0.062)
history = rj.simulate(params, ts=np.linspace(0.0, 1.5, 1500))
wrt = ("M", "k", "c_out", "c_ret", "v0", "m", "gap", "k_r", "c_r", "k_c", "n_c", "lambda_c")
peaks, gradients = rj.peak_jacobian(params, wrt=wrt)
values = rj.params_to_values(params)
change = np.asarray(gradients.peak_anchoring_force) * np.array([values[n] for n in wrt]) * 0.01
order = np.argsort(np.abs(change))

fig, (left, right) = plt.subplots(1, 2, figsize=(13, 4))
t = np.asarray(history.ts)
left.plot(t, 1e-3 * np.asarray(history.anchoring_force), "k", label="anchoring F_AN")
left.plot(t, 1e-3 * np.asarray(history.contact_force), color="firebrick", label="contact F_ct")
left.set_xlabel("time (s)")
left.set_ylabel("force (kN)")
left.set_ylim(-10, 100)
left.legend()
left.set_title(f"peak anchoring force {float(peaks.peak_anchoring_force):.0f} N")
right.barh([wrt[i] for i in order], change[order], color="steelblue")
right.set_xlabel("change in the peak anchoring force for +1 % (N)")
right.set_title("which knob matters here")
fig.tight_layout()
plt.show()
