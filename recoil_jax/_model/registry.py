"""The types of the parameter registry and the validation of a value: `ParameterError`,
`Limits` (a unit, a valid and a documented range) and the check of a value against them
(`check_value`), `Validated` (a pytree whose fields are checked against their limits),
`Parameter` (one registry entry) and `ParameterRegistry` (the flat names, with the family
of orifice knots). The registry's data is in `parameter_table`.

Values are validated whenever they are concrete (Python numbers, NumPy or JAX arrays),
i.e. before anything is compiled. Tracers (values inside `jit`/`grad`/`vmap`) are not
checked: they were checked when the concrete inputs were built.
"""

from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.core
import numpy as np

__all__ = [
    "GROUPS",
    "MAX_KNOTS",
    "MIN_KNOTS",
    "PAPER_GROUPS",
    "Group",
    "Limits",
    "Parameter",
    "ParameterError",
    "ParameterRegistry",
    "Validated",
    "as_float_array",
    "check_integer",
    "check_value",
    "element_label",
    "float_leaf",
    "is_concrete",
]


class ParameterError(ValueError):
    """An invalid parameter value. The message names the parameter, its value and the
    valid range."""


def check_integer(key: str, value: Any, least: int, most: int | None = None) -> int:
    """`value`, an integer setting `key` (a count, a seed, a number of draws) of at
    least `least` and at most `most`; else the one refusal, `key = value: valid an
    integer >= least` (`from least to most`). A bool is not an integer here."""
    if (
        isinstance(value, bool)
        or not isinstance(value, int | np.integer)
        or value < least
        or (most is not None and value > most)
    ):
        valid = f">= {least}" if most is None else f"from {least} to {most:,}"
        raise ParameterError(f"{key} = {value!r}: valid an integer {valid}")
    return int(value)


#: How far above its documented range a value without an upper bound stays valid.
CEILING_FACTOR = 1e6


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
    # What 0 means where it is a part left out, not a value (`m`: no absorber; `k`: no
    # spring): no warning for 0 outside the documented range, which is the part's.
    zero_means: str = ""

    @property
    def ceiling(self) -> float:
        """The largest valid value: `upper`, or where that is unbounded `CEILING_FACTOR`
        times the documented range's top (a value past it means no gun, and the model's
        products, `(M + m)·g·d` or `k_c·δ^n_c`, would overflow before it did)."""
        if math.isinf(self.upper) and self.documented is not None and self.documented[1] > 0:
            return CEILING_FACTOR * self.documented[1]
        return self.upper

    def describe(self) -> str:
        low = f"> {self.lower:g}" if self.lower_open else f">= {self.lower:g}"
        unit = f" {self.unit}" if self.unit else ""
        if math.isinf(self.upper):
            ceiling = "" if math.isinf(self.ceiling) else f", at most {self.ceiling:g}{unit}"
            return f"{low}{unit}{ceiling}"
        return f"{low} and <= {self.upper:g}{unit}"


@dataclasses.dataclass(frozen=True)
class Group:
    """A group of parameters (`Parameter.group`), one part of the gun:

    - `name`: its name (a built-in group's is the field of `RecoilParams` that holds
      it; a part defined outside the package is in `RecoilParams.added`);
    - `pytree`: the class of its part (`forces.family.Part`, in its module of
      `_model/forces`, or outside the package);
    - `title`: what the part is, for people (the explorer's cards);
    - `part`: `"paper"` (the paper's model: always there, `absorber` aside),
      `"hardware"` (the recoil hardware beyond the paper) or `"envelope"` (the firing
      envelope: a design with any such group is solved to `t1`, its return and rest
      being metrics, and has the envelope's metrics);
    - `off`: the parameters that leave the part out when they are all 0 (none: it is
      always there);
    - `first`: one of the parts a designer sets first (the explorer opens its card)."""

    name: str
    pytree: str
    title: str
    part: str
    off: tuple[str, ...] = ()
    first: bool = False

    @property
    def envelope(self) -> bool:
        return self.part == "envelope"


#: Every group of parameters, in the order of `RecoilParams`'s fields: the one list of
#: them; every other form (`PAPER_GROUPS`, a design's `Structure`, the explorer's cards)
#: derives from it. A part defined outside the package adds its group after them
#: (`forces.family.Part`).
GROUPS: dict[str, Group] = {
    group.name: group
    for group in (
        Group("barrel", "Barrel", "Barrel and recoil system", "paper", first=True),
        Group("absorber", "Absorber", "Absorber", "paper", ("m",), first=True),
        Group("contact", "Contact", "Contact", "paper", ("m",)),
        Group("load", "Load", "Breech load", "hardware"),
        Group("buffer", "Buffer", "Throttling orifice", "hardware", ("piston_area",)),
        Group(
            "recuperator",
            "Recuperator",
            "Gas recuperator",
            "hardware",
            ("recuperator_force", "recuperator_preload"),
        ),
        Group(
            "rails",
            "Rails",
            "Rails: elevation and friction",
            "envelope",
            ("elevation", "friction_force", "friction_coefficient"),
        ),
        Group("battery_stop", "BatteryStop", "Battery stop", "envelope", ("stop_stiffness",)),
        Group(
            "counter_recoil_buffer",
            "CounterRecoilBuffer",
            "Counter-recoil buffer",
            "envelope",
            ("buffer_damping",),
        ),
        Group("mount", "Mount", "Mount", "envelope", ("mount_mass",)),
    )
}
#: The groups of the paper's model (`Group.part`), in `GROUPS`' order.
PAPER_GROUPS = tuple(name for name, g in GROUPS.items() if g.part == "paper")


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
    # A change of typical size, scaling the parameter's tangent in the gradients' error
    # norm (default: the documented range's width; kept where that range grew later, so
    # that the solver's steps, and the gradients to the bit, stay as they were).
    tangent_scale: float | None = None

    @property
    def attribute(self) -> str:
        return self.field or self.name

    @property
    def owner(self) -> str:
        """The class holding it (its group's, `Group.pytree`: `Barrel`, `Absorber`, ...),
        for messages."""
        return GROUPS[self.group].pytree

    @property
    def envelope(self) -> bool:
        """Whether it is a parameter of the firing envelope (its group's, `Group`)."""
        return GROUPS[self.group].envelope

    @property
    def label(self) -> str:
        """`name (unit)`, for axis labels."""
        return f"{self.name} ({self.unit})" if self.unit else self.name

    def check(self, value: Any) -> None:
        """Raise `ParameterError` if `value` is not a valid value of this parameter by
        itself (`check_value`: a finite number in range, or 0 where 0 leaves its part
        out, `zero_means`; what it needs of the others is the whole design's to check)."""
        if self.zero_means and is_concrete(value) and np.all(np.asarray(value) == 0):
            return
        check_value(self.owner, self.name, value, self)
        if self.integer and is_concrete(value) and np.any(np.asarray(value) % 1 != 0):
            raise ParameterError(
                f"{self.owner}.{self.name} = {value!r} is invalid: valid {self.name} is an "
                f"integer {self.describe()}" + (f" ({self.meaning})" if self.meaning else "")
            )


#: Orifice knots: at least 2, at most this many (`orifice_0` ... `orifice_31`).
MAX_KNOTS = 32
MIN_KNOTS = 2
#: The flat name of an orifice knot, `orifice_<i>` (its index without leading zeros).
_KNOT_NAME = re.compile(r"orifice_(0|[1-9][0-9]?)")


class ParameterRegistry(Mapping[str, Parameter]):
    """The design parameters by flat name, from the entries `scalars` and the entry `knot`
    of the orifice knots. Iterating gives the scalar parameters in the order of `scalars`
    (the order the command line lists them); the orifice knots `orifice_0` ...
    `orifice_31` (`orifice_<i>`, each a copy of `knot` with its `index`) are looked up by
    name like the others."""

    def __init__(self, scalars: Sequence[Parameter], knot: Parameter):
        self._scalars = {p.name: p for p in scalars}
        self._knot = knot

    def __getitem__(self, name: str) -> Parameter:
        if name in self._scalars:
            return self._scalars[name]
        match = _KNOT_NAME.fullmatch(name) if isinstance(name, str) else None
        if match and int(match.group(1)) < MAX_KNOTS:
            return dataclasses.replace(self._knot, name=name, index=int(match.group(1)))
        raise KeyError(name)

    def __iter__(self):
        return iter(self._scalars)

    def __len__(self) -> int:
        return len(self._scalars)

    def add(self, rows: Sequence[Parameter]) -> None:
        """Take the entries `rows` of a part defined outside the package (`Part.ROWS`),
        after the others; a name taken already is refused."""
        names = [row.name for row in rows]
        for name in names:
            if name in self or _KNOT_NAME.fullmatch(name) or names.count(name) > 1:
                raise ParameterError(f"parameter {name!r} exists already: give another name")
        self._scalars = self._scalars | {row.name: row for row in rows}

    def remove(self, names: Sequence[str]) -> None:
        """Drop the entries `names` (a part defined outside the package, forgotten)."""
        self._scalars = {n: p for n, p in self._scalars.items() if n not in set(names)}

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
    bad_range |= flat > limits.ceiling
    bad = bad_finite | bad_range
    if not bad.any():
        return
    index = int(np.argmax(bad))
    where = element_label(array, index)
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


def element_label(array: np.ndarray, index: int) -> str:
    """How a message names the element at flat `index` of `array`: `[i, j]`, or nothing
    for a scalar."""
    if not array.ndim:
        return ""
    return "[" + ", ".join(str(int(i)) for i in np.unravel_index(index, array.shape)) + "]"


def as_float_array(value: Any) -> Any:
    """Leaves become float64 arrays so that `eqx.filter_jit` traces them (it would hold
    Python floats static and recompile for every new value). Tracers and JAX arrays pass."""
    if value is None or isinstance(value, jax.Array):
        return value
    try:
        return np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        return value  # left for __check_init__ to report with the parameter's name


def float_leaf(default: Any) -> Any:
    """A pytree field of float64 values (`as_float_array`) with its `default`."""
    return eqx.field(default=default, converter=as_float_array)


class Validated(eqx.Module):
    """Base class of the parameter and settings pytrees: checks every field listed in
    `LIMITS` when values are concrete (`check_value`)."""

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
