"""The absorber's contact: the smoothing width of its onset, from the penetration of a
free impact (`docs/model.md`, *Contact*)."""

from __future__ import annotations

from ..._model.params import RecoilParams
from ..._model.settings import Smoothing

__all__ = ["characteristic_penetration", "contact_width"]


def contact_width(params: RecoilParams, smoothing: Smoothing):
    """The contact-onset smoothing width in metres (see `Smoothing`)."""
    if smoothing.contact_width is not None:
        return smoothing.contact_width
    return smoothing.contact_width_fraction * characteristic_penetration(params)


def characteristic_penetration(params: RecoilParams):
    """Peak penetration (m) of a free head-on impact at the barrel's initial speed:
    `δ* = ((n_c+1) μ v0² / (2 k_c))^(1/(n_c+1))`, `μ = M m / (M + m)` (elastic contact).
    Sets the scale of the contact smoothing. Zero for the simplified model."""
    if params.absorber is None:
        return 0.0
    barrel, absorber, contact = params.barrel, params.absorber, params.contact
    reduced_mass = barrel.M * absorber.m / (barrel.M + absorber.m)
    energy = 0.5 * reduced_mass * barrel.v0**2
    return ((contact.n_c + 1.0) * energy / contact.k_c) ** (1.0 / (contact.n_c + 1.0))
