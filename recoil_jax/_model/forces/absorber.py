"""The absorber and its contact with the barrel (`docs/model.md`, *Contact*): their
parameters, the coupling spring and damper and the Hunt–Crossley contact between them,
and the contact onset's smoothing width, from the penetration of a free impact."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from ..._model.forces.family import Design, Part, registered
from ..._model.forces.smoothing import positive_power, smooth_relu
from ..._model.registry import (
    GROUPS,
    Group,
    ParameterError,
    element_label,
    is_concrete,
)
from ..._model.settings import Smoothing

__all__ = [
    "Absorber",
    "Contact",
    "characteristic_penetration",
    "contact_width",
    "coupling_forces",
]


class Absorber(Part):
    """The on-board absorber mass, its coupling to the barrel and its clearance.

    Units: kg, m, N/m, N·s/m. Defaults: the paper's best design (m = 1500 kg, gap = 62 mm)
    with the paper's coupling (k_r = 13000 N/m, c_r = 3675 N·s/m).

    - `m`: absorber mass.
    - `gap`: clearance between the absorber and wall A (fixed to the barrel behind it).
    - `k_r`, `c_r`: spring and damper between absorber and barrel.
    """

    m: Any = registered("m")
    gap: Any = registered("gap")
    k_r: Any = registered("k_r")
    c_r: Any = registered("c_r")

    GROUP: ClassVar[Group] = GROUPS["absorber"]

    def __check_init__(self):  # before Validated's range check: m = 0 is a model, not a mass
        zero = _first_zero(self.m)
        if zero is not None:
            batch = "; a batch that mixes m = 0 and m > 0 is a sweep (rj.sweep)" if zero else ""
            raise ParameterError(
                f"Absorber.m{zero} = 0 kg: an absorber has a mass (m > 0); a design without "
                "absorber is absorber=None (RecoilParams(absorber=None)), or m=0 in the "
                f"flat-name forms (params_from_values, the command line){batch}"
            )


def _first_zero(value: Any) -> str | None:
    """Where a concrete `value` first is zero: `""` for a scalar, `"[i]"` in an array;
    None if nowhere, or for a tracer, `None` or a value that is not a number (the range
    check reports the latter)."""
    if value is None or not is_concrete(value):
        return None
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        return None
    zero = array.reshape(-1) == 0
    return element_label(array, int(np.argmax(zero))) if zero.any() else None


class Contact(Part):
    """Hunt–Crossley contact between wall A and the absorber.

    `F_ct = max(0, k_c δ^n_c (1 + λ_c δ̇))` for penetration `δ > 0`.

    - `k_c`: contact stiffness, N/m^n_c.
    - `n_c`: contact exponent (1: linear, 1.5: Hertz), dimensionless, >= 1.
    - `lambda_c`: Hunt–Crossley damping factor, s/m.
    """

    k_c: Any = registered("k_c")
    n_c: Any = registered("n_c")
    lambda_c: Any = registered("lambda_c")

    GROUP: ClassVar[Group] = GROUPS["contact"]


def contact_width(params: Design, smoothing: Smoothing):
    """The contact-onset smoothing width in metres (see `Smoothing`)."""
    if smoothing.contact_width is not None:
        return smoothing.contact_width
    return smoothing.contact_width_fraction * characteristic_penetration(params)


def characteristic_penetration(params: Design):
    """Peak penetration (m) of a free head-on impact at the barrel's initial speed:
    `δ* = ((n_c+1) μ v0² / (2 k_c))^(1/(n_c+1))`, `μ = M m / (M + m)` (elastic contact).
    Sets the scale of the contact smoothing. Zero for the simplified model."""
    if params.absorber is None:
        return 0.0
    barrel, absorber, contact = params.barrel, params.absorber, params.contact
    reduced_mass = barrel.M * absorber.m / (barrel.M + absorber.m)
    energy = 0.5 * reduced_mass * barrel.v0**2
    return ((contact.n_c + 1.0) * energy / contact.k_c) ** (1.0 / (contact.n_c + 1.0))


def coupling_forces(y, design: Design, smoothing, width_contact) -> dict[str, Any]:
    """The forces between the barrel and the absorber at state `y` (N), by `Forces`
    field: the coupling spring `k_r (x_M − x_m)` and damper `c_r (v_M − v_m)`, and the
    contact `F_ct = k_c δ₊^n_c max(0, 1 + λ_c δ̇)` (>= 0, pushing the absorber forward;
    `contact_elastic` its conservative part), its onset smoothed over `width_contact` (m)
    and its no-pull clamp over a relative-velocity band `damping_width`."""
    x_M, v_M, x_m, v_m = y[0], y[1], y[2], y[3]
    absorber, contact = design.absorber, design.contact
    width_v = smoothing.damping_width
    penetration = x_M - x_m - absorber.gap
    penetration_rate = v_M - v_m
    elastic = contact.k_c * positive_power(smooth_relu(penetration, width_contact), contact.n_c)
    damping_factor = smooth_relu(
        1.0 + contact.lambda_c * penetration_rate, contact.lambda_c * width_v
    )
    return {
        "coupling_spring": absorber.k_r * (x_M - x_m),
        "coupling_damper": absorber.c_r * (v_M - v_m),
        "contact": elastic * damping_factor,
        "contact_elastic": elastic,
    }
