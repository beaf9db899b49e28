"""The parameter registry's data: every design parameter by its flat name (as used on the
command line, in TOML, JSON, CSV, `wrt` and `tune`) with the pytree group it lives in,
its unit, default, valid range, documented range and meaning (`PARAMETERS`), in the order
the command line lists them, and the family of orifice knots. The pytrees (`params`),
their validation, the flat-name conversions and every error message derive from it.
"""

from __future__ import annotations

from .._model.registry import Parameter, ParameterRegistry

__all__ = [
    "PAPER_BARREL_MASS",
    "PAPER_MUZZLE_VELOCITY",
    "PAPER_PROJECTILE_MASS",
    "PARAMETERS",
    "parameter",
]

#: Projectile data of the paper (6.86 kg at 564 m/s); v0 = m_p v_p / M = 0.6909 m/s.
PAPER_PROJECTILE_MASS = 6.86
PAPER_MUZZLE_VELOCITY = 564.0
PAPER_BARREL_MASS = 5600.0

#: The scalar design parameters, in the order the command line lists them.
_SCALARS = (
    Parameter(
        name="M",
        group="barrel",
        default=PAPER_BARREL_MASS,
        unit="kg",
        lower=0.0,
        lower_open=True,
        documented=(1e3, 2e4),
        meaning="barrel mass",
    ),
    Parameter(
        name="k",
        group="barrel",
        default=27500.0,
        unit="N/m",
        lower=0.0,
        lower_open=True,
        documented=(1e3, 1e6),
        meaning="recoil spring stiffness",
    ),
    Parameter(
        name="c_out",
        group="barrel",
        default=6239.0,
        unit="N*s/m",
        lower=0.0,
        documented=(0.0, 5e4),
        meaning="recoil damping, v_M > 0",
    ),
    Parameter(
        name="c_ret",
        group="barrel",
        default=14050.0,
        unit="N*s/m",
        lower=0.0,
        documented=(0.0, 5e4),
        meaning="return damping, v_M < 0",
    ),
    Parameter(
        name="v0",
        group="barrel",
        default=PAPER_PROJECTILE_MASS * PAPER_MUZZLE_VELOCITY / PAPER_BARREL_MASS,
        unit="m/s",
        lower=0.0,
        lower_open=True,
        documented=(0.1, 2.0),
        meaning="initial barrel velocity",
    ),
    Parameter(
        name="m",
        group="absorber",
        default=1500.0,
        unit="kg",
        lower=0.0,
        lower_open=True,
        documented=(10.0, 5000.0),
        meaning="absorber mass",
    ),
    Parameter(
        name="gap",
        group="absorber",
        default=0.062,
        unit="m",
        lower=0.0,
        documented=(0.0, 0.2),
        meaning="clearance to wall A",
    ),
    Parameter(
        name="k_r",
        group="absorber",
        default=13000.0,
        unit="N/m",
        lower=0.0,
        lower_open=True,
        documented=(1e3, 1e5),
        meaning="absorber-barrel spring stiffness",
    ),
    Parameter(
        name="c_r",
        group="absorber",
        default=3675.0,
        unit="N*s/m",
        lower=0.0,
        documented=(0.0, 2e4),
        meaning="absorber-barrel damping",
    ),
    Parameter(
        name="k_c",
        group="contact",
        default=2.1e8,
        unit="N/m^n_c",
        lower=0.0,
        lower_open=True,
        documented=(1e6, 1e10),
        meaning="contact stiffness",
    ),
    Parameter(
        name="n_c",
        group="contact",
        default=1.3,
        unit="",
        lower=1.0,
        documented=(1.0, 2.0),
        meaning="contact exponent",
    ),
    Parameter(
        name="lambda_c",
        group="contact",
        default=0.6,
        unit="s/m",
        lower=0.0,
        documented=(0.0, 2.0),
        meaning="Hunt-Crossley damping factor",
    ),
    Parameter(
        name="pulse_time",
        group="load",
        default=0.0,
        unit="s",
        lower=0.0,
        documented=(0.0, 0.02),
        meaning="rise time of the breech-force pulse; 0 is the impulse",
    ),
    Parameter(
        name="shots",
        group="load",
        default=1,
        unit="",
        lower=1.0,
        integer=True,
        documented=(1, 10),
        meaning="rounds fired",
    ),
    Parameter(
        name="fire_interval",
        group="load",
        default=0.5,
        unit="s",
        lower=0.0,
        lower_open=True,
        documented=(0.1, 5.0),
        meaning="time between rounds",
    ),
    Parameter(
        name="oil_density",
        group="buffer",
        default=870.0,
        unit="kg/m^3",
        lower=0.0,
        lower_open=True,
        documented=(700.0, 1000.0),
        meaning="oil density of the hydraulic buffer",
    ),
    Parameter(
        name="piston_area",
        group="buffer",
        default=0.0,
        unit="m^2",
        lower=0.0,
        documented=(0.0, 0.02),
        meaning="buffer piston area; 0 is no buffer",
    ),
    Parameter(
        name="discharge_coefficient",
        group="buffer",
        default=0.7,
        unit="",
        lower=0.0,
        lower_open=True,
        upper=1.0,
        documented=(0.5, 1.0),
        meaning="orifice discharge coefficient",
    ),
    Parameter(
        name="orifice_length",
        group="buffer",
        default=0.25,
        unit="m",
        lower=0.0,
        lower_open=True,
        documented=(0.05, 0.5),
        meaning="stroke over which the orifice profile is given",
    ),
    Parameter(
        name="recuperator_force",
        group="recuperator",
        default=0.0,
        unit="N",
        lower=0.0,
        documented=(0.0, 2e4),
        meaning="recuperator gas pressure times piston area; 0 is none",
    ),
    Parameter(
        name="recuperator_length",
        group="recuperator",
        default=1.0,
        unit="m",
        lower=0.0,
        lower_open=True,
        documented=(0.3, 3.0),
        meaning="recuperator gas column length",
    ),
    Parameter(
        name="polytropic_index",
        group="recuperator",
        default=1.3,
        unit="",
        lower=1.0,
        upper=1.67,
        documented=(1.0, 1.67),
        meaning="polytropic index of the recuperator gas",
    ),
)

#: The orifice knots `orifice_0` ... `orifice_31`, as one entry (`ParameterRegistry`).
_KNOT = Parameter(
    name="orifice_<i>",
    group="buffer",
    field="orifice",
    default=float("nan"),
    unit="m^2",
    lower=0.0,
    lower_open=True,
    documented=(1e-5, 1e-2),
    meaning="orifice area at knot i, x = orifice_length * i / (K - 1)",
)

#: The design parameters by flat name (see `ParameterRegistry`).
PARAMETERS = ParameterRegistry(_SCALARS, _KNOT)


def parameter(name: str) -> Parameter:
    """The registry entry of the flat parameter `name`; a `ParameterError` listing the
    known names if there is none."""
    try:
        return PARAMETERS[name]
    except KeyError:
        raise PARAMETERS.unknown(name) from None
