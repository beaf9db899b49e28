"""The design (`RecoilParams`, which holds one of each part of the gun) and the
flat-name conversions.

The parts are the forces family's members (`forces.family`), each defined in its module
of `_model/forces` (`Barrel`, `Absorber`, `Contact`, `Load` with its `ForceTable`,
`Buffer`, `Recuperator`, the firing envelope's `Rails`, `BatteryStop`,
`CounterRecoilBuffer` and `Mount`) and re-exported here; a part defined outside the
package joins a design as `RecoilParams(added=...)`. Their validation, the flat-name
conversions (`params_from_values`, `params_to_values`, `with_values`, `values_of`) and
every error message derive from the registry (`PARAMETERS`, `parameter_table`).

Every physical parameter is a pytree leaf (so `jax.grad`, `jax.jacfwd` and `jax.vmap`
apply to it); configuration that changes the compiled program (`Load.shots`) is static.
Values are validated in `__check_init__` whenever they are concrete (Python numbers,
NumPy or JAX arrays), i.e. before anything is compiled. Tracers (values inside
`jit`/`grad`/`vmap`) are not checked: they were checked when the concrete inputs were
built.
"""

from __future__ import annotations

import dataclasses
import importlib
import pkgutil
from collections.abc import Mapping, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._model import forces
from .._model.forces.absorber import Absorber, Contact
from .._model.forces.barrel import Barrel
from .._model.forces.counter_recoil import CounterRecoilBuffer
from .._model.forces.family import FAMILY, Force, Part
from .._model.forces.loads import ForceTable, Load
from .._model.forces.mount import Mount
from .._model.forces.orifice import Buffer
from .._model.forces.rails import Rails
from .._model.forces.recuperator import Recuperator
from .._model.forces.stop import BatteryStop
from .._model.parameter_table import PARAMETERS, parameter
from .._model.registry import (
    GROUPS,
    MIN_KNOTS,
    Parameter,
    ParameterError,
    check_value,
    element_label,
    is_concrete,
)

__all__ = [
    "Absorber",
    "Barrel",
    "BatteryStop",
    "Buffer",
    "Contact",
    "CounterRecoilBuffer",
    "ForceTable",
    "Load",
    "Mount",
    "Rails",
    "RecoilParams",
    "Recuperator",
    "check_design",
    "check_present",
    "params_from_values",
    "params_to_values",
    "values_of",
    "with_values",
]


class RecoilParams(eqx.Module):
    """All physical parameters of one design. `absorber=None` is the simplified model
    (barrel, spring and damper only). The hardware beyond the paper is optional:
    `load=None` is one impulse of `v0`, `buffer=None` no hydraulic buffer,
    `recuperator=None` no gas recuperator, each as in the paper; so is the firing
    envelope: `rails=None` is level frictionless rails, `battery_stop=None` no stop,
    `counter_recoil_buffer=None` no counter-recoil buffer and `mount=None` no mount.
    `added`: parts defined outside the package (`Part`, `Force`), one of each group.

    Checked across the groups (when the values are concrete): a recuperator preload
    needs the battery stop, and a mount is at least as heavy as its recoiling parts."""

    barrel: Barrel = Barrel()
    absorber: Absorber | None = Absorber()
    contact: Contact = Contact()
    load: Load | None = None
    buffer: Buffer | None = None
    recuperator: Recuperator | None = None
    rails: Rails | None = None
    battery_stop: BatteryStop | None = None
    counter_recoil_buffer: CounterRecoilBuffer | None = None
    mount: Mount | None = None
    added: tuple[Part, ...] = ()

    def __check_init__(self):
        check_added(self.added)
        check_design(self)

    def part(self, group: str) -> Any:
        """The part of group `group` (`Group.name`), or None where the design has none."""
        if group in _BUILT_IN:
            return getattr(self, group)
        return next((p for p in self.added if p.GROUP.name == group), None)

    def parts(self) -> dict[str, Part]:
        """The parts the design has, by group: the built-in ones in the registry's order
        (`GROUPS`), then those added outside the package, in `added`'s order (read from
        the design itself: a process it is sent to need not know their groups)."""
        built_in = {g: getattr(self, g) for g in _BUILT_IN}
        added = {p.GROUP.name: p for p in self.added}
        return {g: p for g, p in (built_in | added).items() if p is not None}

    def forces(self) -> list[Force]:
        """The forces the design has (`Force`), in the registry's order (`parts`)."""
        return [p for p in self.parts().values() if isinstance(p, Force)]


# Every module of `_model/forces` joins the family as it is imported: a part added to
# the package beyond the built-in fields below is found there, with no list to edit.
for _module in pkgutil.iter_modules(forces.__path__):
    importlib.import_module(f"{forces.__name__}.{_module.name}")

#: The built-in groups: the fields of `RecoilParams` that hold a part.
_BUILT_IN = tuple(f.name for f in dataclasses.fields(RecoilParams) if f.name != "added")


def check_added(added: Any) -> None:
    """Refuse (`ParameterError`) `RecoilParams.added` unless a tuple of parts of the
    family (`Part`) defined outside the package, one a group."""
    if not isinstance(added, tuple) or not all(isinstance(p, Part) for p in added):
        raise ParameterError(
            f"RecoilParams.added must be a tuple of parts (rjx.Part, rjx.Force); got {added!r}"
        )
    groups = [p.GROUP.name for p in added]
    doubled = sorted({g for g in groups if groups.count(g) > 1} | set(groups) & set(_BUILT_IN))
    if doubled:
        raise ParameterError(
            f"RecoilParams.added: {', '.join(doubled)} given twice (or as a built-in part)"
        )


def _first_bad(*arrays: Any, bad) -> tuple[str, tuple[float, ...]] | None:
    """Where `bad(*arrays)` (broadcast) is first true, and the arrays' values there; None
    if nowhere or if a value is not concrete."""
    if not is_concrete(arrays):
        return None
    try:
        values = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in arrays))
    except (TypeError, ValueError):
        return None  # the range checks report a value that is not a number
    mask = np.asarray(bad(*values)).reshape(-1)
    if not mask.any():
        return None
    index = int(np.argmax(mask))
    return element_label(values[0], index), tuple(float(v.reshape(-1)[index]) for v in values)


def check_design(params: RecoilParams) -> None:
    """The checks that span parameter groups, on concrete values (`ParameterError`, one
    line each): a recuperator preload needs the battery stop (`stop_stiffness > 0`) stiff
    enough to hold it within `recuperator_length` by itself (`stop_stiffness ≥
    P·2^−γ/L^n_s`), and a mount (`mount_mass > 0`) is at least as heavy as its recoiling
    parts, `M + m`."""
    if params.recuperator is not None:
        stop = 0.0 if params.battery_stop is None else params.battery_stop.stop_stiffness
        found = _first_bad(
            params.recuperator.recuperator_preload, stop, bad=lambda p, k: (p > 0) & ~(k > 0)
        )
        if found is not None:
            where, (preload, _) = found
            raise ParameterError(
                f"Recuperator.recuperator_preload{where} = {preload:g} N is invalid: a preload "
                "needs the battery stop to hold the barrel in battery against it; valid "
                "recuperator_preload 0 without a stop, >= 0 N with stop_stiffness > 0"
            )
        if params.battery_stop is not None:
            _check_stop_holds(params.recuperator, params.battery_stop)
    if params.mount is not None:
        absorber = 0.0 if params.absorber is None else params.absorber.m
        found = _first_bad(
            params.mount.mount_mass,
            params.barrel.M,
            absorber,
            bad=lambda mg, M, m: (mg != 0) & (mg < M + m),
        )
        if found is not None:
            where, (mass, M, m) = found
            raise ParameterError(
                f"Mount.mount_mass{where} = {mass:g} kg is invalid: a mount lighter than its "
                f"recoiling parts cannot carry them; valid mount_mass 0 (no mount) or >= M + m "
                f"= {M + m:g} kg (the whole gun on the ground, recoiling parts included)"
            )


def _check_stop_holds(recuperator: Recuperator, stop: BatteryStop) -> None:
    """A stop too soft to hold the preload by itself is refused: at `recuperator_length`
    `L` into it, the stop pushes back `k_s·L^n_s` and the gas forward `P·2^−γ` (its
    force falls as it expands, `P·(L/(L − x))^γ` at `x = −L`), so a stop at least that
    stiff holds the preload within `L` on its own. (The recoil spring, the gas spring
    and the axial weight at a positive elevation help it; at a negative one the weight
    pushes too.)"""
    found = _first_bad(
        recuperator.recuperator_preload,
        stop.stop_stiffness,
        recuperator.recuperator_length,
        stop.stop_exponent,
        recuperator.polytropic_index,
        bad=lambda p, k, length, n, gamma: (p > 0) & (k > 0) & (k * length**n < p * 2.0**-gamma),
    )
    if found is not None:
        where, (preload, stiffness, length, exponent, gamma) = found
        least = preload * 2.0**-gamma / length**exponent
        raise ParameterError(
            f"BatteryStop.stop_stiffness{where} = {stiffness:g} N/m^n_s is invalid: too soft "
            f"to hold recuperator_preload = {preload:g} N (recuperator_length = {length:g} m "
            f"into the stop, it pushes back {stiffness * length**exponent:.3g} N, the gas "
            f"{preload * 2.0**-gamma:.3g} N); valid stop_stiffness >= {least:.3g} N/m^n_s "
            "for this preload (P 2^-gamma / L^n_s)"
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
    grouped: dict[str, dict[str, Any]] = {g: {} for g in GROUPS}
    for name, value in values.items():
        grouped[parameter(name).group][name] = value
    given_barrel, given_contact = grouped.pop("barrel"), grouped.pop("contact")
    given_absorber = grouped.pop("absorber")
    m = given_absorber.get("m", None)
    simplified = m is not None and is_concrete(m) and bool(np.all(np.asarray(m) == 0))
    if simplified:
        extra = sorted(set(given_absorber) - {"m"})
        if extra:
            raise ParameterError(
                f"m = 0 selects the simplified model (no absorber), so {', '.join(extra)} "
                "cannot be set; give m > 0 to use them"
            )
        absorber = None
    else:
        absorber = Absorber(**given_absorber)
    optional: dict[str, Any] = {}
    load = grouped.pop("load")
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
    buffer = grouped.pop("buffer")
    if buffer:
        knots = {n: buffer.pop(n) for n in list(buffer) if PARAMETERS[n].index is not None}
        if knots and "piston_area" not in buffer:
            first = min(knots, key=lambda n: PARAMETERS[n].index or 0)
            raise ParameterError(
                f"{first} is given without piston_area: the orifice throttles the buffer's "
                "oil, so give piston_area (m^2) too"
            )
        optional["buffer"] = Buffer(**buffer, orifice=_knots(knots) if knots else None)
    # Every other part (the recuperator's, the envelope's, any added outside the
    # package) is present when any of its parameters is given.
    added = []
    for group, given in grouped.items():
        if given:
            part = FAMILY[group](**given)
            if group in _BUILT_IN:
                optional[group] = part
            else:
                added.append(part)
    return RecoilParams(
        barrel=Barrel(**given_barrel),
        absorber=absorber,
        contact=Contact(**given_contact),
        **optional,
        added=tuple(added),
    )


def params_to_values(params: RecoilParams) -> dict[str, Any]:
    """Inverse of `params_from_values`: the flat name → value mapping (m = 0 for the
    simplified model, whose other absorber parameters are absent; absent hardware groups
    give no names; the orifice knots come as `orifice_<i>`)."""
    out: dict[str, Any] = {}
    for name, p in PARAMETERS.items():
        module = params.part(p.group)
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
    value = getattr(params.part(p.group), p.attribute)
    return value if p.index is None else value[..., p.index]


def check_present(params: RecoilParams, p: Parameter) -> None:
    """Raise `ParameterError` unless parameter `p` is part of `params` and set by value
    (not an integer count)."""
    module = params.part(p.group)
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
        check_present(params, p)
        value = values[j]
        check_value(p.owner, name, value, p)
        value = jnp.asarray(value, dtype=float)
        if p.index is None:
            params = eqx.tree_at(
                lambda q, p=p: getattr(q.part(p.group), p.attribute), params, value
            )
        else:
            knots[p.index] = value
    if knots:
        # All knots in one update: this runs in every stage of a tangent solve, where
        # a scatter per knot made the 22-parameter program larger and slower.
        assert params.buffer is not None  # (check_present)
        orifice = jnp.asarray(params.buffer.orifice, dtype=float)
        given = jnp.stack(jnp.broadcast_arrays(*knots.values()), axis=-1)
        if list(knots) == list(range(orifice.shape[-1])):
            orifice = jnp.broadcast_to(given, jnp.broadcast_shapes(given.shape, orifice.shape))
        else:
            orifice = orifice.at[..., np.asarray(list(knots))].set(given)
        params = eqx.tree_at(lambda q: q.buffer.orifice, params, orifice)
    check_design(params)  # the checks across groups (`tree_at` does not run them)
    return params


def values_of(params: RecoilParams, names: Sequence[str]) -> jax.Array:
    """The parameters `names` of `params` as one array, shape `(len(names),)`."""
    return jnp.stack([jnp.asarray(_get(params, parameter(n)), dtype=float) for n in names])
