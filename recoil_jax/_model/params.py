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

import csv
import dataclasses
import math
import os
import re
import stat
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import numpy as np

__all__ = [
    "MAX_KNOTS",
    "MAX_STEPS",
    "MAX_TEXT_BYTES",
    "MIN_KNOTS",
    "PARAMETERS",
    "T1_LIMITS",
    "Absorber",
    "Barrel",
    "Buffer",
    "Contact",
    "ForceTable",
    "Limits",
    "Load",
    "Parameter",
    "ParameterError",
    "ParameterRegistry",
    "RecoilParams",
    "Recuperator",
    "Smoothing",
    "SolverOptions",
    "check_load_fits",
    "check_value",
    "default_end_time",
    "end_time",
    "is_concrete",
    "parameter",
    "params_from_values",
    "params_to_values",
    "read_text",
    "values_of",
    "with_default_tolerances",
    "with_values",
]


class ParameterError(ValueError):
    """An invalid parameter value. The message names the parameter, its value and the
    valid range."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class Limits:
    """Unit, valid range and documented range of one scalar.

    `lower`/`upper` bound the *valid* domain (values outside raise `ParameterError`);
    `documented` is the range over which accuracy is tested (`docs/numerics.md`).
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
    field: str = ""  # attribute in the group's pytree (default: the name)
    index: int | None = None  # position in an array field (an orifice knot)
    integer: bool = False  # an integer count (static: one compilation per value)

    @property
    def attribute(self) -> str:
        return self.field or self.name

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

# The scalar design parameters, in the order the command line lists them.
_SCALARS: dict[str, Parameter] = {
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
}

#: Orifice knots: at least 2, at most this many (`orifice_0` ... `orifice_31`).
MAX_KNOTS = 32
MIN_KNOTS = 2
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
_KNOT_NAME = re.compile(r"orifice_(0|[1-9][0-9]?)")


class ParameterRegistry(Mapping[str, Parameter]):
    """The design parameters by flat name. Iterating gives the scalar parameters in the
    order the command line lists them; the orifice knots `orifice_0` ... `orifice_31`
    (`orifice_<i>`) are looked up by name like the others."""

    def __init__(self, scalars: dict[str, Parameter]):
        self._scalars = scalars

    def __getitem__(self, name: str) -> Parameter:
        if name in self._scalars:
            return self._scalars[name]
        match = _KNOT_NAME.fullmatch(name) if isinstance(name, str) else None
        if match and int(match.group(1)) < MAX_KNOTS:
            return dataclasses.replace(_KNOT, name=name, index=int(match.group(1)))
        raise KeyError(name)

    def __iter__(self):
        return iter(self._scalars)

    def __len__(self) -> int:
        return len(self._scalars)

    def names(self) -> str:
        """Every name, for messages: the scalars, then the knot family."""
        return ", ".join([*self._scalars, "orifice_<i>"])

    def unknown(self, name: str, also: Sequence[str] = ()) -> ParameterError:
        """The error for a `name` that is not a parameter (`also`: other names the caller
        takes, listed with the parameters); a knot past the last says how many there
        may be."""
        if isinstance(name, str) and re.fullmatch(r"orifice_[0-9]+", name):
            return ParameterError(
                f"unknown parameter {name!r}: the orifice has at most {MAX_KNOTS} knots "
                f"(orifice_0 ... orifice_{MAX_KNOTS - 1})"
            )
        return ParameterError(
            f"unknown parameter {name!r}; known: {', '.join([self.names(), *also])}"
        )


#: The design parameters by flat name (see `ParameterRegistry`).
PARAMETERS = ParameterRegistry(_SCALARS)


def parameter(name: str) -> Parameter:
    """The registry entry of the flat parameter `name`; a `ParameterError` listing the
    known names if there is none."""
    try:
        return PARAMETERS[name]
    except KeyError:
        raise PARAMETERS.unknown(name) from None


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
    where = _element(array, index)
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


def _element(array: np.ndarray, index: int) -> str:
    """How a message names the element at flat `index` of `array`: `[i, j]`, or nothing
    for a scalar."""
    if not array.ndim:
        return ""
    return "[" + ", ".join(str(int(i)) for i in np.unravel_index(index, array.shape)) + "]"


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

    def __check_init__(self):  # before _Validated's range check: m = 0 is a model, not a mass
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
    return _element(array, int(np.argmax(zero))) if zero.any() else None


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


#: The most bytes a text file may hold (a trace, a force table, a TOML file, a points
#: file, a calibration's result): 64 MiB, about 3 million rows of a two-signal trace,
#: which read in about 1 GB. A larger file is refused before it is read.
MAX_TEXT_BYTES = 64 * 2**20


def read_text(path, what: str) -> str:
    """The text of the file `path` (`what` it should be, for messages): a missing file, a
    folder, what is not a regular file (a pipe, a device: it could be read forever), a
    file of more than `MAX_TEXT_BYTES` or one that is not text is a `ParameterError`; a
    byte-order mark (as spreadsheets write) is dropped. Every file the command line reads
    comes through here."""
    path = Path(path)
    try:
        # Non-blocking: opening a pipe with no writer would otherwise wait forever.
        descriptor = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except FileNotFoundError:
        raise ParameterError(f"{what} {path} not found") from None
    except IsADirectoryError:
        raise ParameterError(f"{what} {path} is a folder, not a file") from None
    except OSError as error:
        raise ParameterError(f"{what} {path} cannot be read: {error.strerror}") from None
    status = os.fstat(descriptor)
    mode = status.st_mode
    if not stat.S_ISREG(mode):
        os.close(descriptor)
        if stat.S_ISDIR(mode):
            raise ParameterError(f"{what} {path} is a folder, not a file")
        raise ParameterError(
            f"{what} {path} is not a regular file (a pipe, a device or a socket): give a file"
        )
    too_large = ParameterError(
        f"{what} {path} is larger than {MAX_TEXT_BYTES / 2**20:g} MiB, the most a file "
        "read whole may hold (MAX_TEXT_BYTES): give a shorter file (a trace: fewer "
        "samples, e.g. every n-th row)"
    )
    if status.st_size > MAX_TEXT_BYTES:  # refused before a byte is read
        os.close(descriptor)
        raise too_large
    with os.fdopen(descriptor, "rb") as file:
        try:
            data = file.read(MAX_TEXT_BYTES + 1)  # a file that grows as it is read
        except OSError as error:
            raise ParameterError(f"{what} {path} cannot be read: {error.strerror}") from None
    if len(data) > MAX_TEXT_BYTES:
        raise too_large
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise ParameterError(f"{what} {path} is not a text file (UTF-8)") from None


#: The spacing (s) of the zero-force points that pad a shorter table (`ForceTable.stacked`).
_PAD_SPACING = 1e-9


class ForceTable(eqx.Module):
    """A tabulated breech force of one round: `F` (N) at times `t` (s, from the round's
    firing), linear between points and zero outside them; shape `(n,)` each, `n >= 2`
    (or `(B, n)`: each design of a batch its own, `ForceTable.stacked`), `t` strictly
    increasing from `t[0] >= 0`. The table's integral is the round's
    momentum (`Barrel.v0` is not used). `ForceTable.from_csv` reads a CSV file with the
    header `t_s,F_N`."""

    t: Any = eqx.field(converter=_as_float_array)
    F: Any = eqx.field(converter=_as_float_array)

    def __check_init__(self):
        if not is_concrete((self.t, self.F)):
            return
        check_value("ForceTable", "t", self.t, Limits(unit="s", lower=0.0))
        check_value("ForceTable", "F", self.F, Limits(unit="N", lower=-math.inf))
        t, F = np.asarray(self.t), np.asarray(self.F)
        if t.ndim < 1 or F.shape != t.shape or t.shape[-1] < 2:
            raise ParameterError(
                f"ForceTable: t and F must be of the same length >= 2, got shapes "
                f"{t.shape} and {F.shape}"
            )
        rows = t.reshape(-1, t.shape[-1])  # a batch: each design's table
        bad = np.diff(rows, axis=-1) <= 0
        if np.any(bad):
            row, i = np.unravel_index(int(np.argmax(bad)), bad.shape)
            times, i = rows[row], int(i) + 1
            where = f" (table {row})" if len(rows) > 1 else ""
            raise ParameterError(
                f"ForceTable.t[{i}] = {times[i]:g} s is invalid{where}: times must increase "
                f"strictly (t[{i - 1}] = {times[i - 1]:g} s)"
            )

    @classmethod
    def stacked(cls, tables: Sequence[ForceTable]) -> ForceTable:
        """One batched table `(B, n)` of `tables` (one round each), for designs that
        each fire their own: the shorter padded to the longest with points of zero force
        1 ns apart after their end. That is exact for a table that ends at zero force
        (outside its points a table's force is zero); one that ends at F_last gains a
        1 ns ramp to zero, an impulse of F_last · 0.5 ns."""
        length = max(int(np.shape(t.t)[-1]) for t in tables)
        times, forces = [], []
        for table in tables:
            t, F = np.asarray(table.t, dtype=float), np.asarray(table.F, dtype=float)
            if t.ndim != 1:
                raise ParameterError("ForceTable.stacked: each table must be of one round, (n,)")
            extra = length - len(t)
            times.append(np.concatenate([t, t[-1] + _PAD_SPACING * np.arange(1, extra + 1)]))
            forces.append(np.concatenate([F, np.zeros(extra)]))
        return cls(np.stack(times), np.stack(forces))

    @classmethod
    def from_csv(cls, path) -> ForceTable:
        """Read a table from a CSV file whose header is `t_s,F_N` (seconds, newtons)."""
        path = Path(path)
        rows = list(csv.DictReader(read_text(path, "force table").splitlines()))
        if not rows:
            raise ParameterError(f"{path}: no rows of t_s,F_N values (a header alone, or empty)")
        if set(rows[0]) != {"t_s", "F_N"}:
            raise ParameterError(f"{path}: expected a CSV with the header t_s,F_N")
        try:
            t = [float(r["t_s"]) for r in rows]
            F = [float(r["F_N"]) for r in rows]
        except (TypeError, ValueError):
            raise ParameterError(f"{path}: every t_s and F_N must be a number") from None
        return cls(t=t, F=F)


class Load(_Validated):
    """The breech force and the firing rhythm (`docs/model.md`, *Load*).

    - `pulse_time` (s): 0 is the paper's impulse (the barrel starts at `v0`); `t_p > 0` is
      a gamma pulse of the same momentum, `F_b = (M v0 / t_p) (t/t_p) exp(-t/t_p)`, with the
      barrel starting at rest.
    - `shots` (static): rounds fired, at `t_j = j · fire_interval`; each adds a velocity
      jump of `v0` (impulse), or its own pulse or table.
    - `fire_interval` (s): time between rounds.
    - `table`: a `ForceTable` of one round, which replaces the pulse or impulse.
    """

    pulse_time: Any = _registered("pulse_time")
    shots: int = eqx.field(default=1, static=True)
    fire_interval: Any = _registered("fire_interval")
    table: ForceTable | None = None

    LIMITS: ClassVar[Mapping[str, Limits]] = {
        n: p for n, p in _group_limits("load").items() if n != "shots"
    }

    def __check_init__(self):
        super().__check_init__()
        if isinstance(self.shots, bool) or not isinstance(self.shots, int) or self.shots < 1:
            raise ParameterError(
                f"Load.shots = {self.shots!r} is invalid: valid shots is an integer >= 1 "
                "(rounds fired)"
            )


class Buffer(_Validated):
    """The hydraulic recoil buffer with a throttling orifice (`docs/model.md`,
    *Hydraulic buffer*): `F_h = ρ A_p³ v|v| / (2 C_d² A_o(x)²)`.

    - `oil_density` ρ (kg/m³), `piston_area` A_p (m², 0: no buffer force),
      `discharge_coefficient` C_d, `orifice_length` x_a (m).
    - `orifice` (m², shape `(K,)`, 2 <= K <= 32): the orifice area at `x = x_a i/(K-1)`,
      linear between knots and constant outside `[0, x_a]`; flat names `orifice_<i>`.
    """

    oil_density: Any = _registered("oil_density")
    piston_area: Any = _registered("piston_area")
    discharge_coefficient: Any = _registered("discharge_coefficient")
    orifice_length: Any = _registered("orifice_length")
    orifice: Any = _leaf(None)

    LIMITS: ClassVar[Mapping[str, Limits]] = _group_limits("buffer")

    def __check_init__(self):
        super().__check_init__()
        if self.orifice is None:
            if is_concrete(self.piston_area) and np.any(np.asarray(self.piston_area) > 0):
                raise ParameterError(
                    "Buffer.piston_area > 0 needs the orifice: give the knots orifice_0 ... "
                    f"orifice_<K-1> ({MIN_KNOTS} <= K <= {MAX_KNOTS}), areas in m^2"
                )
            return
        count = self.knots
        if not MIN_KNOTS <= count <= MAX_KNOTS:
            raise ParameterError(
                f"Buffer.orifice has {count} knots: valid {MIN_KNOTS} to {MAX_KNOTS} "
                "(orifice_0 ... orifice_<K-1>)"
            )
        if is_concrete(self.orifice):
            knots = np.asarray(self.orifice, dtype=np.float64).reshape(-1, count)
            for i in range(count):
                name = f"orifice_{i}"
                check_value("Buffer", name, knots[:, i].squeeze(), PARAMETERS[name])

    @property
    def knots(self) -> int:
        """K, the number of orifice knots (0 without an orifice)."""
        return 0 if self.orifice is None else int(jnp.shape(self.orifice)[-1])


class Recuperator(_Validated):
    """The gas recuperator, a nonlinear air spring (`docs/model.md`, *Gas recuperator*):
    `F_g = F_r ((L_r / (L_r - x_M))^γ - 1)`.

    - `recuperator_force` F_r (N), `recuperator_length` L_r (m), `polytropic_index` γ.

    A solve in which `x_M` reaches `0.95 L_r` fails with `Status.bottomed_out`.
    """

    recuperator_force: Any = _registered("recuperator_force")
    recuperator_length: Any = _registered("recuperator_length")
    polytropic_index: Any = _registered("polytropic_index")

    LIMITS: ClassVar[Mapping[str, Limits]] = _group_limits("recuperator")


class RecoilParams(eqx.Module):
    """All physical parameters of one design. `absorber=None` is the simplified model
    (barrel, spring and damper only). The hardware beyond the paper is optional:
    `load=None` is one impulse of `v0`, `buffer=None` no hydraulic buffer,
    `recuperator=None` no gas recuperator, each as in the paper."""

    barrel: Barrel = Barrel()
    absorber: Absorber | None = Absorber()
    contact: Contact = Contact()
    load: Load | None = None
    buffer: Buffer | None = None
    recuperator: Recuperator | None = None


_GROUPS: dict[str, type[_Validated]] = {
    "barrel": Barrel,
    "absorber": Absorber,
    "contact": Contact,
    "load": Load,
    "buffer": Buffer,
    "recuperator": Recuperator,
}


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
    - `knot_width_fraction`: the kinks of the orifice profile at its knots, over this
      fraction of the knot spacing.

    A width of 0 makes its switch exact. `Smoothing.exact()` sets every width to 0: the
    hard-switch model (not differentiable at the switches; for reference and checks). It
    runs through the same code path and, its widths being values, the same compiled
    program as the smoothed model.

    See `docs/model.md`, *Smoothing*.
    """

    damping_width: Any = _leaf(1e-4)
    contact_width: Any = _leaf(None)
    contact_width_fraction: Any = _leaf(0.005)
    knot_width_fraction: Any = _leaf(1e-4)

    LIMITS: ClassVar[Mapping[str, Limits]] = {
        "damping_width": Limits(
            unit="m/s",
            lower=0.0,
            lower_open=False,
            documented=(1e-4, 1e-1),
            meaning="damping and clamp smoothing width; 0 is the exact switch",
        ),
        "contact_width": Limits(
            unit="m",
            lower=0.0,
            lower_open=False,
            documented=(1e-6, 1e-3),
            meaning="contact onset smoothing width; 0 is the exact switch",
        ),
        "knot_width_fraction": Limits(
            unit="",
            lower=0.0,
            lower_open=False,
            upper=0.5,
            meaning="orifice knot smoothing width / knot spacing",
        ),
        "contact_width_fraction": Limits(
            unit="",
            lower=0.0,
            lower_open=False,
            upper=1.0,
            meaning="contact width / characteristic penetration",
        ),
    }

    @classmethod
    def exact(cls) -> Smoothing:
        """The hard-switch model: every width 0."""
        return cls(damping_width=0.0, contact_width_fraction=0.0, knot_width_fraction=0.0)

    @property
    def hard(self) -> bool:
        """Whether every switch is exact (every width 0); for concrete widths."""
        contact = self.contact_width_fraction if self.contact_width is None else self.contact_width
        widths = (self.damping_width, contact, self.knot_width_fraction)
        return all(bool(np.all(np.asarray(w) == 0)) for w in widths)


#: Limits of the end time, the one solver setting that may differ between the points
#: of a sweep (`t1` on the command line and in `sweep --points`).
T1_LIMITS = Limits(unit="s", lower=0.0, lower_open=True, documented=(0.1, 60.0), meaning="end time")


#: The most solver steps a solve may be given (`SolverOptions.max_steps`): a step count
#: is a 32-bit integer on some devices.
MAX_STEPS = 2**31 - 1


class SolverOptions(_Validated):
    """Time span and adaptive-step settings (Tsit5 with a PID controller).

    - `t1` (s): end of the simulation; `None` (default) is the model's end time,
      `default_end_time` (10 s).
    - `rtol`, `atol`: tolerances of the step-size controller; `None` (default) is
      1e-6 and 1e-9 for the paper's model, and 1e-7 and 1e-10 for designs with a load,
      buffer or recuperator, whose peaks then agree with the hard-switch reference to
      1e-4 (`with_default_tolerances`). atol is in SI units of the
      state: m and m/s).
    - `max_steps` (static): bound on solver steps (accepted + rejected); reaching it is
      reported as a failure, never a truncated result.
    - `autodiff` (static): `"forward"` (default) runs the stepping loop as a
      `lax.while_loop`: fastest, supports `jax.jvp`/`jax.jacfwd`. `"reverse"` runs it as a
      checkpointed loop that supports `jax.grad`/`jax.vjp` (not forward mode).
    """

    t1: Any = _leaf(None)
    rtol: Any = _leaf(None)
    atol: Any = _leaf(None)
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
        if not isinstance(self.max_steps, int) or not 1 <= self.max_steps <= MAX_STEPS:
            raise ParameterError(
                f"SolverOptions.max_steps = {self.max_steps!r} is invalid: valid max_steps is "
                f"an integer from 1 to {MAX_STEPS:,}"
            )
        if self.autodiff not in ("forward", "reverse"):
            raise ParameterError(
                f"SolverOptions.autodiff = {self.autodiff!r} is invalid: valid autodiff is "
                "'forward' or 'reverse'"
            )


def default_end_time(params: RecoilParams) -> Any:
    """The model's end time when `SolverOptions.t1` is not given: 10 s after the last
    round, `10 + (shots - 1) · fire_interval` (10 s, the paper's, for one round)."""
    ten = jnp.full(jnp.shape(params.barrel.v0), 10.0)
    load = params.load
    if load is None or load.shots == 1:
        return ten
    return ten + (load.shots - 1) * jnp.asarray(load.fire_interval, dtype=float)


def with_default_tolerances(params: RecoilParams, options: SolverOptions) -> SolverOptions:
    """`options` with the tolerances it leaves to the design filled in: rtol 1e-6 and
    atol 1e-9 for the paper's model; 1e-7 and 1e-10 with a load, buffer or recuperator
    (pulses of hundreds of kN and the orifice's `v²/A²` need a tighter tolerance for the
    peaks to hold 1e-4)."""
    if options.rtol is not None and options.atol is not None:
        return options
    hardware = any(getattr(params, g) is not None for g in ("load", "buffer", "recuperator"))
    rtol, atol = (1e-7, 1e-10) if hardware else (1e-6, 1e-9)
    return dataclasses.replace(
        options,
        rtol=rtol if options.rtol is None else options.rtol,
        atol=atol if options.atol is None else options.atol,
    )


def end_time(params: RecoilParams, options: SolverOptions) -> Any:
    """The end time of a solve (s): `options.t1`, or the model's default.

    **Raises:** `ParameterError`, for concrete inputs, when the load does not fit
    (`check_load_fits`): the solve would be cut short or could not finish."""
    t1 = default_end_time(params) if options.t1 is None else options.t1
    t1 = jnp.asarray(t1, dtype=float)
    if is_concrete((params, t1)):
        check_load_fits(params, t1, options.max_steps)
    return t1


#: A gamma pulse has delivered all but 11 e^-10 (0.05 %) of its momentum after this many
#: `pulse_time`s: the pulse's length, for `check_load_fits`.
PULSE_LENGTHS = 10.0


def check_load_fits(params: RecoilParams, t1: Any, max_steps: int, labels: Any = None) -> None:
    """Refuse, before anything is compiled, a load that a solve to `t1` (s, scalar or per
    design) could not deliver or finish: a round fired after `t1`, a pulse (its
    `PULSE_LENGTHS` pulse times) or a force table that `t1` cuts short, or more load
    breakpoints (the later rounds' firings and every table point of every round, each
    of which ends a solver step) than `max_steps` steps. `labels`: each design's index
    for messages (default: its place in the batch)."""
    load = params.load
    if load is None:
        return
    t1 = np.asarray(t1, dtype=float)
    last = (load.shots - 1) * np.asarray(load.fire_interval, dtype=float)
    if load.table is not None:  # each design's own table (`ForceTable.stacked`) may end apart
        length, what = np.asarray(load.table.t, dtype=float)[..., -1], "the force table"
    else:
        length, what = PULSE_LENGTHS * np.asarray(load.pulse_time, dtype=float), "the pulse"
    last, length, t1 = np.broadcast_arrays(last, length, t1)
    ends = (last + length).reshape(-1)
    last, t1 = last.reshape(-1), t1.reshape(-1)
    short = ends > t1
    if np.any(short):
        i = int(np.argmax(short))
        label = i if labels is None else int(labels[i])
        if last[i] >= t1[i]:
            cause = f"the last of {load.shots} rounds fires at {last[i]:g} s"
        else:
            cause = f"{what} of the last round lasts until {ends[i]:g} s"
        raise ParameterError(
            f"the load does not fit in the solve{f' (design {label})' if ends.size > 1 else ''}: "
            f"{cause}, after t1 = {t1[i]:g} s, so the recoil would be cut short; give "
            f"t1 >= {ends[i]:g} s (or a shorter load)"
        )
    rows = 0 if load.table is None else int(np.shape(load.table.t)[-1])
    breakpoints = (load.shots - 1) + load.shots * rows
    if breakpoints >= max_steps:
        raise ParameterError(
            f"the load has {breakpoints:,} breakpoints ({load.shots} round{'s' * (load.shots > 1)}"
            + (f" x {rows:,} force-table points" if rows else "")
            + f"), each of which ends a solver step, but max_steps is {max_steps:,}: give "
            f"max_steps > {breakpoints:,} (command line: --max-steps), or fewer points"
        )


def _knots(names: dict[str, Any]) -> Any:
    """The orifice knots given by flat name, as one array `(..., K)`; holes are errors."""
    indices = sorted(PARAMETERS[n].index or 0 for n in names)
    missing = [i for i in range(len(indices)) if i not in indices]
    if missing:
        raise ParameterError(
            f"orifice knots must be numbered from 0 without holes: orifice_{missing[0]} is "
            f"missing (given: {', '.join(f'orifice_{i}' for i in indices)})"
        )
    if len(indices) < MIN_KNOTS:
        raise ParameterError(
            f"orifice_0 alone is not a profile: give at least {MIN_KNOTS} knots "
            "(orifice_0, orifice_1, ...)"
        )
    return jnp.stack(
        [jnp.asarray(names[f"orifice_{i}"], dtype=float) for i in range(len(indices))], axis=-1
    )


def params_from_values(values: Mapping[str, Any] | None = None, **kwargs: Any) -> RecoilParams:
    """Build `RecoilParams` from flat parameter names (`PARAMETERS`).

    **Arguments:**

    - `values`, `**kwargs`: flat name → value (scalars, or arrays for a batch); names not
      given take their defaults. `m = 0` gives the simplified model (no absorber). The
      load, buffer and recuperator are present when any of their parameters is given.

    **Returns:** the validated `RecoilParams`.

    **Raises:** `ParameterError` for an unknown name, a value outside its valid range,
    absorber parameters given with `m = 0`, orifice knots with a hole or without
    `piston_area`, or different `shots` in one batch.
    """
    values = {**(values or {}), **kwargs}
    grouped: dict[str, dict[str, Any]] = {g: {} for g in _GROUPS}
    for name, value in values.items():
        grouped[parameter(name).group][name] = value
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
    optional: dict[str, Any] = {}
    load = dict(grouped["load"])
    if load:
        if "shots" in load:
            shots = np.unique(np.asarray(load["shots"], dtype=float))
            if shots.size != 1:
                raise ParameterError(
                    f"shots differ within one RecoilParams ({', '.join(f'{x:g}' for x in shots)}):"
                    " shots is static; sweep() runs each value as its own group"
                )
            check_value("Load", "shots", shots[0], PARAMETERS["shots"])
            if shots[0] != int(shots[0]):
                raise ParameterError(
                    f"Load.shots = {shots[0]:g} is invalid: valid shots is an integer >= 1 "
                    "(rounds fired)"
                )
            load["shots"] = int(shots[0])
        optional["load"] = Load(**load)
    buffer = dict(grouped["buffer"])
    if buffer:
        knots = {n: buffer.pop(n) for n in list(buffer) if PARAMETERS[n].index is not None}
        if knots and "piston_area" not in buffer:
            first = min(knots, key=lambda n: PARAMETERS[n].index or 0)
            raise ParameterError(
                f"{first} is given without piston_area: the orifice throttles the buffer's "
                "oil, so give piston_area (m^2) too"
            )
        optional["buffer"] = Buffer(**buffer, orifice=_knots(knots) if knots else None)
    if grouped["recuperator"]:
        optional["recuperator"] = Recuperator(**grouped["recuperator"])
    return RecoilParams(
        barrel=Barrel(**grouped["barrel"]),
        absorber=absorber,
        contact=Contact(**grouped["contact"]),
        **optional,
    )


def params_to_values(params: RecoilParams) -> dict[str, Any]:
    """Inverse of `params_from_values`: the flat name → value mapping (m = 0 for the
    simplified model, whose other absorber parameters are absent; absent hardware groups
    give no names; the orifice knots come as `orifice_<i>`)."""
    out: dict[str, Any] = {}
    for name, p in PARAMETERS.items():
        module = getattr(params, p.group)
        if module is None:
            if name == "m":
                out[name] = 0.0
            continue
        out[name] = getattr(module, name)
    if params.buffer is not None and params.buffer.orifice is not None:
        for i in range(params.buffer.knots):
            out[f"orifice_{i}"] = params.buffer.orifice[..., i]
    return out


def _get(params: RecoilParams, p: Parameter) -> Any:
    value = getattr(getattr(params, p.group), p.attribute)
    return value if p.index is None else value[..., p.index]


def _check_present(params: RecoilParams, p: Parameter) -> None:
    module = getattr(params, p.group)
    if module is None or (p.index is not None and p.index >= module.knots):
        raise ParameterError(f"{p.name} is not part of this design (its {p.group} is absent)")
    if p.integer:
        raise ParameterError(f"{p.name} is an integer count: it cannot be set by value here")


def with_values(params: RecoilParams, names: Sequence[str], values: Any) -> RecoilParams:
    """`params` with the parameters `names` (flat names) set to `values` (shape
    `(len(names),)`). Concrete values are validated like the constructors do (tracers,
    inside transformations, are not)."""
    knots: dict[int, Any] = {}  # orifice index -> value
    for j, name in enumerate(names):
        p = parameter(name)
        _check_present(params, p)
        value = values[j]
        check_value(p.owner, name, value, p)
        value = jnp.asarray(value, dtype=float)
        if p.index is None:
            params = eqx.tree_at(
                lambda q, p=p: getattr(getattr(q, p.group), p.attribute), params, value
            )
        else:
            knots[p.index] = value
    if knots:
        # All knots in one update: this runs in every stage of a sensitivity solve, where
        # a scatter per knot made the 22-parameter program larger and slower.
        assert params.buffer is not None  # (_check_present)
        orifice = jnp.asarray(params.buffer.orifice, dtype=float)
        given = jnp.stack(jnp.broadcast_arrays(*knots.values()), axis=-1)
        if list(knots) == list(range(orifice.shape[-1])):
            orifice = jnp.broadcast_to(given, jnp.broadcast_shapes(given.shape, orifice.shape))
        else:
            orifice = orifice.at[..., np.asarray(list(knots))].set(given)
        params = eqx.tree_at(lambda q: q.buffer.orifice, params, orifice)
    return params


def values_of(params: RecoilParams, names: Sequence[str]) -> jax.Array:
    """The parameters `names` of `params` as one array, shape `(len(names),)`."""
    return jnp.stack([jnp.asarray(_get(params, parameter(n)), dtype=float) for n in names])
