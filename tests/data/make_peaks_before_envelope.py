"""Peaks and gradients of designs without the envelope, to compare bit for bit."""

import json
import sys

import recoil_jax as rj

DESIGNS = {
    "paper": {},
    "simplified": {"m": 0.0},
    "pulse": {"pulse_time": 0.004},
    "burst": {"pulse_time": 0.003, "shots": 3, "fire_interval": 0.5},
    "recuperator": {
        "m": 0.0,
        "recuperator_force": 8000.0,
        "recuperator_length": 1.5,
        "c_out": 30000.0,
    },
    "orifice": {
        "m": 0.0,
        "oil_density": 900.0,
        "piston_area": 0.01,
        "discharge_coefficient": 0.7,
        "orifice_length": 0.5,
        "orifice_0": 2e-4,
        "orifice_1": 1.5e-4,
        "orifice_2": 1e-4,
    },
}
out = {}
for name, d in DESIGNS.items():
    p = rj.params_from_values(d)
    peaks = rj.peaks(p).to_dict()
    wrt = ("c_out", "k") if "m" in d else ("gap", "m", "k_r", "c_r", "c_out")
    _, grads = rj.peak_gradients(p, wrt=wrt)
    out[name] = {"peaks": {k: v for k, v in peaks.items()}, "gradients": grads.to_dict()}
json.dump(out, open(sys.argv[1], "w"), indent=1)
