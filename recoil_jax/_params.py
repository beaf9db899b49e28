"""The parameter registry and the parameter pytrees.

`PARAMETERS` is the one registry of design parameters: flat name (as used on the command
line, in TOML, JSON, CSV, `wrt` and `tune`), the pytree group it lives in, its unit,
default, valid range and documented range. The pytrees (`Barrel`, `Absorber`,
`Contact`), their validation, the flat-name conversions and every error message derive
from it.

Every physical parameter is a pytree leaf (so `jax.grad`, `jax.jacfwd` and `jax.vmap`
apply to it); configuration that changes the compiled program (the hard/smoothed mode,
`max_steps`) is static. Values are validated in `__check_init__` whenever they are
concrete (Python numbers, NumPy or JAX arrays), i.e. before anything is compiled.
Tracers (values inside `jit`/`grad`/`vmap`) are not checked: they were checked when the
concrete inputs were built.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import numpy as np

__all__ = [
    "PARAMETERS",
    "T1_LIMITS",
    "Absorber",
    "Barrel",
    "Contact",
    "Limits",
    "Parameter",
    "ParameterError",
    "RecoilParams",
    "Smoothing",
    "SolverOptions",
    "check_value",
    "default_end_time",
    "end_time",
    "is_concrete",
    "parameter",
    "params_from_values",
    "params_to_values",
    "values_of",
    "with_values",
]


class ParameterError(ValueError):
    """An invalid parameter value. The message names the parameter, its value and the
    valid range."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class Limits:
    """Unit, valid range and documented range of one scalar.

    `lower`/`upper` bound the *valid* domain (values outside raise `ParameterError`);
    `documented` is the range over which accuracy is tested (see the README).
    """

    unit: str
    lower: float
    upper: float = math.inf
    lower_open: bool = False  # True: the lower bound itself is invalid (> lower)
    documented: tuple[float, float] | None = None
    meaning: str = ""

    def describe(self) -> str:
        low = f"> {self.lower:g}" if self.lower_open else f">= {self.lower:g}"
        valid = low if math.isinf(self.upper) else f"{low} and <= {self.upper:g}"
        unit = f" {self.unit}" if self.unit else ""
        return f"{valid}{unit}"


@dataclasses.dataclass(frozen=True, kw_only=True)
class Parameter(Limits):
    """A design parameter: its flat `name`, the `group` of `RecoilParams` holding it
    (`barrel`, `absorber`, `contact`) and its `default` (SI units)."""

    name: str
    group: str
    default: float

    @property
    def owner(self) -> str:
        """The class holding it (`Barrel`, `Absorber`, `Contact`), for messages."""
        return _GROUPS[self.group].__name__

    @property
    def label(self) -> str:
        """`name (unit)`, for axis labels."""
        return f"{self.name} ({self.unit})" if self.unit else self.name


# Projectile data of the paper (6.86 kg at 564 m/s); v0 = m_p v_p / M = 0.6909 m/s.
PAPER_PROJECTILE_MASS = 6.86
PAPER_MUZZLE_VELOCITY = 564.0
PAPER_BARREL_MASS = 5600.0

#: The design parameters by flat name, in the order the command line lists them.
PARAMETERS: dict[str, Parameter] = {
    p.name: p
    for p in (
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
    )
}


def parameter(name: str) -> Parameter:
    """The registry entry of the flat parameter `name`; a `ParameterError` listing the
    known names if there is none."""
    try:
        return PARAMETERS[name]
    except KeyError:
        raise ParameterError(
            f"unknown parameter {name!r}; known: {', '.join(PARAMETERS)}"
        ) from None


def is_concrete(value: Any) -> bool:
    """No leaf of `value` is a tracer (so it can be checked now)."""
    return not any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves(value))


def check_value(owner: str, name: str, value: Any, limits: Limits) -> None:
    """Raise `ParameterError` if a concrete `value` (scalar or array) is not a finite
    number inside `limits`; the message names `owner.name`, the bad value (and its index
    in an array) and the valid range. Tracers and `None` pass."""
    if value is None or not is_concrete(value):
        return
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ParameterError(
            f"{owner}.{name} = {value!r} is not a number; valid: {limits.describe()}"
        ) from None
    flat = array.reshape(-1)
    bad_finite = ~np.isfinite(flat)
    if limits.lower_open:
        bad_range = flat <= limits.lower
    else:
        bad_range = flat < limits.lower
    bad_range |= flat > limits.upper
    bad = bad_finite | bad_range
    if not bad.any():
        return
    index = int(np.argmax(bad))
    where = ""
    if array.ndim:
        where = "[" + ", ".join(str(int(i)) for i in np.unravel_index(index, array.shape)) + "]"
    bad_value = flat[index]
    unit = f" {limits.unit}" if limits.unit else ""
    if bad_finite[index]:
        reason = "must be finite (NaN and inf are not allowed)"
    else:
        reason = "out of range"
    documented = ""
    if limits.documented is not None:
        lo, hi = limits.documented
        documented = f"; documented range {lo:g} to {hi:g}{unit}"
    raise ParameterError(
        f"{owner}.{name}{where} = {bad_value:g}{unit} is invalid ({reason}): "
        f"valid {name} {limits.describe()}{documented}"
        + (f" ({limits.meaning})" if limits.meaning else "")
    )


def _as_float_array(value: Any) -> Any:
    """Leaves become float64 arrays so that `eqx.filter_jit` traces them (it would hold
    Python floats static and recompile for every new value). Tracers and JAX arrays pass."""
    if value is None or isinstance(value, jax.Array):
        return value
    try:
        return np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        return value  # left for __check_init__ to report with the parameter's name


def _leaf(default: Any) -> Any:
    return eqx.field(default=default, converter=_as_float_array)


def _registered(name: str) -> Any:
    """A pytree leaf for the registered parameter `name`, with its default."""
    return _leaf(PARAMETERS[name].default)


class _Validated(eqx.Module):
    """Base class: checks every field listed in `LIMITS` when values are concrete."""

    LIMITS: ClassVar[Mapping[str, Limits]] = {}

    def __check_init__(self):
        limits = type(self).LIMITS
        for field in dataclasses.fields(self):
            if field.name in limits:
                check_value(
                    type(self).__name__,
                    field.name,
                    getattr(self, field.name),
                    limits[field.name],
                )


def _group_limits(group: str) -> dict[str, Limits]:
    return {name: p for name, p in PARAMETERS.items() if p.group == group}


class Barrel(_Validated):
    """The recoiling barrel, its recoil spring and its direction-dependent damper.

    Defaults are the paper's values. Units: kg, N/m, N·s/m, m/s.

    - `M`: recoiling mass.
    - `k`: recoil spring stiffness (barrel to mounting wall P).
    - `c_out`: recoil damping while the barrel moves rearwards (`v_M > 0`).
    - `c_ret`: damping on the return stroke (`v_M < 0`).
    - `v0`: barrel velocity right after the shot; see `Barrel.from_shot`.
    """

    M: Any = _registered("M")
    k: Any = _registered("k")
    c_out: Any = _registered("c_out")
    c_ret: Any = _registered("c_ret")
    v0: Any = _registered("v0")

    LIMITS: ClassVar[Mapping[str, Limits]] = _group_limits("barrel")

    @classmethod
    def from_shot(
        cls, projectile_mass: Any, muzzle_velocity: Any, M: Any = PAPER_BARREL_MASS, **kwargs
    ) -> Barrel:
        """Barrel whose initial velocity comes from momentum conservation at the shot:
        `v0 = projectile_mass * muzzle_velocity / M` (kg, m/s, kg)."""
        check_value(
            "Barrel.from_shot",
            "projectile_mass",
            projectile_mass,
            Limits(unit="kg", lower=0.0, lower_open=True),
        )
        check_value(
            "Barrel.from_shot",
            "muzzle_velocity",
            muzzle_velocity,
            Limits(unit="m/s", lower=0.0, lower_open=True),
        )
        check_value("Barrel", "M", M, cls.LIMITS["M"])
        return cls(M=M, v0=projectile_mass * muzzle_velocity / M, **kwargs)


class Absorber(_Validated):
    """The on-board absorber mass, its coupling to the barrel and its clearance.

    Units: kg, m, N/m, N·s/m. Defaults: the paper's best design (m = 1500 kg, gap = 62 mm)
    with the paper's coupling (k_r = 13000 N/m, c_r = 3675 N·s/m).

    - `m`: absorber mass.
    - `gap`: clearance between the absorber and wall A (fixed to the barrel behind it).
    - `k_r`, `c_r`: spring and damper between absorber and barrel.
    """

    m: Any = _registered("m")
    gap: Any = _registered("gap")
    k_r: Any = _registered("k_r")
    c_r: Any = _registered("c_r")

    LIMITS: ClassVar[Mapping[str, Limits]] = _group_limits("absorber")


class Contact(_Validated):
    """Hunt–Crossley contact between wall A and the absorber.

    `F_ct = max(0, k_c δ^n_c (1 + λ_c δ̇))` for penetration `δ > 0`.

    - `k_c`: contact stiffness, N/m^n_c.
    - `n_c`: contact exponent (1: linear, 1.5: Hertz), dimensionless, >= 1.
    - `lambda_c`: Hunt–Crossley damping factor, s/m.
    """

    k_c: Any = _registered("k_c")
    n_c: Any = _registered("n_c")
    lambda_c: Any = _registered("lambda_c")

    LIMITS: ClassVar[Mapping[str, Limits]] = _group_limits("contact")


class RecoilParams(eqx.Module):
    """All physical parameters of one design. `absorber=None` is the simplified model
    (barrel, spring and damper only)."""

    barrel: Barrel = Barrel()
    absorber: Absorber | None = Absorber()
    contact: Contact = Contact()


_GROUPS: dict[str, type[_Validated]] = {"barrel": Barrel, "absorber": Absorber, "contact": Contact}


class Smoothing(_Validated):
    """Widths, in physical units, over which the model's switches are smoothed.

    Each switch `max(0, x)` is replaced by a C² ramp that equals it exactly for
    `|x| >= width` (see `smooth_relu`), so the smoothed model differs from the exact one
    only inside the band.

    - `damping_width` (m/s): the damping switch at `v_M = 0` and the contact's no-pull
      clamp at `1 + λ_c δ̇ = 0` (in relative velocity).
    - `contact_width` (m): the contact onset at `δ = 0`. `None` (default) picks
      `contact_width_fraction` × the characteristic penetration of a head-on impact,
      `δ* = ((n_c+1) μ v0² / (2 k_c))^(1/(n_c+1))` with `μ = M m / (M + m)`,
      so the relative smoothing error is the same over the whole range of `k_c`, `n_c`, `m`, `v0`.
    - `hard=True` (static): the exact model with hard switches, same code path with
      zero widths (not differentiable at the switches; for reference and checks).

    See `docs/model.md`, *Smoothing*.
    """

    damping_width: Any = _leaf(1e-3)
    contact_width: Any = _leaf(None)
    contact_width_fraction: Any = _leaf(0.005)
    hard: bool = eqx.field(default=False, static=True)

    LIMITS: ClassVar[Mapping[str, Limits]] = {
        "damping_width": Limits(
            unit="m/s",
            lower=0.0,
            lower_open=True,
            documented=(1e-4, 1e-1),
            meaning="damping and clamp smoothing width",
        ),
        "contact_width": Limits(
            unit="m",
            lower=0.0,
            lower_open=True,
            documented=(1e-6, 1e-3),
            meaning="contact onset smoothing width",
        ),
        "contact_width_fraction": Limits(
            unit="",
            lower=0.0,
            lower_open=True,
            upper=1.0,
            meaning="contact width / characteristic penetration",
        ),
    }

    @classmethod
    def exact(cls) -> Smoothing:
        """The hard-switch model."""
        return cls(hard=True)


#: Limits of the end time, the one solver setting that may differ between the points
#: of a sweep (`t1` on the command line and in `sweep --points`).
T1_LIMITS = Limits(unit="s", lower=0.0, lower_open=True, documented=(0.1, 60.0), meaning="end time")


class SolverOptions(_Validated):
    """Time span and adaptive-step settings (Tsit5 with a PID controller).

    - `t1` (s): end of the simulation; `None` (default) is the model's end time,
      `default_end_time` (10 s).
    - `rtol`, `atol`: tolerances of the step-size controller (atol in SI units of the
      state: m and m/s).
    - `max_steps` (static): bound on solver steps (accepted + rejected); reaching it is
      reported as a failure, never a truncated result.
    - `autodiff` (static): `"forward"` (default) runs the stepping loop as a
      `lax.while_loop`: fastest, supports `jax.jvp`/`jax.jacfwd`. `"reverse"` runs it as a
      checkpointed loop that supports `jax.grad`/`jax.vjp` (not forward mode).
    """

    t1: Any = _leaf(None)
    rtol: Any = _leaf(1e-6)
    atol: Any = _leaf(1e-9)
    max_steps: int = eqx.field(default=65536, static=True)
    autodiff: str = eqx.field(default="forward", static=True)

    LIMITS: ClassVar[Mapping[str, Limits]] = {
        "t1": T1_LIMITS,
        "rtol": Limits(
            unit="", lower=0.0, lower_open=True, upper=1.0, meaning="relative tolerance"
        ),
        "atol": Limits(unit="", lower=0.0, lower_open=True, meaning="absolute tolerance"),
    }

    def __check_init__(self):
        super().__check_init__()
        if not isinstance(self.max_steps, int) or self.max_steps < 1:
            raise ParameterError(
                f"SolverOptions.max_steps = {self.max_steps!r} is invalid: valid max_steps is "
                "an integer >= 1"
            )
        if self.autodiff not in ("forward", "reverse"):
            raise ParameterError(
                f"SolverOptions.autodiff = {self.autodiff!r} is invalid: valid autodiff is "
                "'forward' or 'reverse'"
            )


def default_end_time(params: RecoilParams) -> Any:
    """The model's end time when `SolverOptions.t1` is not given: 10 s (the paper's)."""
    return jnp.full(jnp.shape(params.barrel.v0), 10.0)


def end_time(params: RecoilParams, options: SolverOptions) -> Any:
    """The end time of a solve (s): `options.t1`, or the model's default."""
    t1 = default_end_time(params) if options.t1 is None else options.t1
    return jnp.asarray(t1, dtype=float)


def params_from_values(values: Mapping[str, Any] | None = None, **kwargs: Any) -> RecoilParams:
    """Build `RecoilParams` from flat parameter names (`PARAMETERS`).

    **Arguments:**

    - `values`, `**kwargs`: flat name → value (scalars, or arrays for a batch); names not
      given take their defaults. `m = 0` gives the simplified model (no absorber).

    **Returns:** the validated `RecoilParams`.

    **Raises:** `ParameterError` for an unknown name, a value outside its valid range, or
    absorber parameters given with `m = 0`.
    """
    values = {**(values or {}), **kwargs}
    for name in values:
        parameter(name)
    grouped: dict[str, dict[str, Any]] = {g: {} for g in _GROUPS}
    for name, value in values.items():
        grouped[PARAMETERS[name].group][name] = value
    m = grouped["absorber"].get("m", None)
    simplified = m is not None and is_concrete(m) and bool(np.all(np.asarray(m) == 0))
    if simplified:
        extra = sorted(set(grouped["absorber"]) - {"m"})
        if extra:
            raise ParameterError(
                f"m = 0 selects the simplified model (no absorber), so {', '.join(extra)} "
                "cannot be set; give m > 0 to use them"
            )
        absorber = None
    else:
        absorber = Absorber(**grouped["absorber"])
    return RecoilParams(
        barrel=Barrel(**grouped["barrel"]),
        absorber=absorber,
        contact=Contact(**grouped["contact"]),
    )


def params_to_values(params: RecoilParams) -> dict[str, Any]:
    """Inverse of `params_from_values`: the flat name → value mapping (m = 0 for the
    simplified model, whose other absorber parameters are absent)."""
    out: dict[str, Any] = {}
    for name, p in PARAMETERS.items():
        module = getattr(params, p.group)
        if module is None:
            if name == "m":
                out[name] = 0.0
            continue
        out[name] = getattr(module, name)
    return out


def with_values(params: RecoilParams, names: Sequence[str], values: Any) -> RecoilParams:
    """`params` with the parameters `names` (flat names) set to `values` (shape
    `(len(names),)`). Concrete values are validated like the constructors do (tracers,
    inside transformations, are not)."""
    for j, name in enumerate(names):
        p = parameter(name)
        value = values[j]
        check_value(p.owner, name, value, p)
        params = eqx.tree_at(
            lambda q, g=p.group, f=name: getattr(getattr(q, g), f),
            params,
            jnp.asarray(value, dtype=float),
        )
    return params


def values_of(params: RecoilParams, names: Sequence[str]) -> jax.Array:
    """The parameters `names` of `params` as one array, shape `(len(names),)`."""
    return jnp.stack(
        [jnp.asarray(getattr(getattr(params, PARAMETERS[n].group), n), dtype=float) for n in names]
    )
