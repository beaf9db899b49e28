"""The forces family: what a part of the gun is (`Part`: a group of parameters, its
fields) and what a force is (`Force`: a part that pushes on the barrel through the
recoil mechanism, into the mount). Each module of `_model/forces` defines its part as a
member; the equations sum the forces a design has, as diffrax's `MultiTerm` sums terms
(`system.forces`). A part defined outside the package joins the family by subclassing,
with its parameter rows (`Part.ROWS`) and its group (`Part.GROUP`): the parameter
registry, `params_from_values`, the sweeps and the studies take it by its flat names
(`docs/developers.md`, *Adding a force*).
"""

from __future__ import annotations

import abc
import dataclasses
import hashlib
import inspect
import threading
from typing import Any, ClassVar

import jax
import numpy as np

from ..._model.parameter_table import PARAMETERS
from ..._model.registry import (
    GROUPS,
    Group,
    Limits,
    Parameter,
    ParameterError,
    Validated,
    float_leaf,
)

__all__ = [
    "FAMILY",
    "Design",
    "Force",
    "Part",
    "forget_part",
    "group_limits",
    "outside_parts",
    "outside_source",
    "registered",
]

#: A design (`RecoilParams`), typed loosely here: the parts are defined before the
#: design that holds them.
Design = Any

#: Every part of the gun, by its group's name (`Group.name`). A design orders its parts
#: as the registry's `GROUPS` does (the built-in groups, then those added).
FAMILY: dict[str, type[Part]] = {}


def registered(name: str) -> Any:
    """A pytree field for the registered parameter `name`, with its default."""
    return float_leaf(PARAMETERS[name].default)


def group_limits(group: str) -> dict[str, Limits]:
    """The registry entries of `group` by name: the `LIMITS` of its pytree."""
    return {name: p for name, p in PARAMETERS.items() if p.group == group}


class Part(Validated):
    """A part of the gun: one group of the design's parameters, which are its fields
    (each a pytree leaf, validated against its registry entry, `LIMITS`).

    A subclass names its group (`GROUP`, a `Group`: its name, title, part of the gun and
    the switches that leave it out), and that makes it a member of the family
    (`FAMILY`); its `LIMITS` are its group's rows of the parameter table. A part defined
    outside the package gives its parameters' registry rows too (`ROWS`, each a
    `Parameter` of its group); its group and rows then join the registry (`GROUPS`,
    `PARAMETERS`), after the built-in ones. `forget_part` takes them out again.
    """

    GROUP: ClassVar[Group]
    ROWS: ClassVar[tuple[Parameter, ...]] = ()

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        group = cls.__dict__.get("GROUP")
        if group is None:  # an abstract kind (`Force`), not a part
            return
        if group.pytree != cls.__name__:
            raise ParameterError(f"{cls.__name__}.GROUP names the pytree {group.pytree!r}")
        if group.name in FAMILY:
            raise ParameterError(f"a part of group {group.name!r} exists already")
        if cls.ROWS:
            if group.name in GROUPS:
                raise ParameterError(f"group {group.name!r} exists already: give another name")
            strays = [row.name for row in cls.ROWS if row.group != group.name]
            fields = getattr(cls, "__annotations__", {})
            strays += [row.name for row in cls.ROWS if row.attribute not in fields]
            if strays:
                raise ParameterError(
                    f"{cls.__name__}.ROWS: {strays} are not fields of group {group.name}"
                )
            PARAMETERS.add(cls.ROWS)
            GROUPS[group.name] = group
            cls.LIMITS = {row.name: row for row in cls.ROWS}
        elif group.name not in GROUPS:
            raise ParameterError(f"{cls.__name__}: group {group.name!r} has no ROWS")
        elif "LIMITS" not in cls.__dict__:  # a built-in part's: its rows in the table
            cls.LIMITS = group_limits(group.name)
        FAMILY[group.name] = cls

    def __reduce_ex__(self, protocol):
        # A part defined outside the package travels as its class and its fields, and
        # is made whole where it lands (`_received_part`).
        if not type(self).ROWS:
            return super().__reduce_ex__(protocol)
        values = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        return _received_part, (type(self), values)


class Force(Part):
    """A part that pushes on the barrel through the recoil mechanism: what it adds to
    the anchoring force `F_AN` (and so, with the opposite sign, to the barrel's equation
    `M a_M = F_b − F_AN − ...`), by name (`anchoring`), and what the solve's early stops
    need of it (`potential`, `anchoring_bound`, `held_change`). Its smoothing width, if
    it switches, is its own to define (a field, or a `Smoothing` width it reads).

    The equations sum, in this order: the forces of the mechanism, the rails' friction
    (which takes what the others leave), then the reactions (`REACTION`: the battery
    stop); within each, in the order of the registry's groups (`GROUPS`). A member whose
    `potential` or `anchoring_bound` is None (the default) keeps the solve from stopping
    early by the energy; one whose `held_change` is None keeps a held barrel's solve
    from stopping before `t1`: slower, never wrong.
    """

    #: A reaction of the gun's limits (the battery stop): its `anchoring` is the force
    #: with which it pushes the barrel back, which `F_AN` loses (after the friction).
    REACTION: ClassVar[bool] = False

    @abc.abstractmethod
    def anchoring(self, y, t, design: Design, smoothing) -> dict[str, Any]:
        """Its shares of `F_AN` at state `y = (x_M, v_M, x_m, v_m)` (N, positive holding
        the barrel back), by name; `t` (s) may be None (the forces of a state alone)."""

    def potential(self, x_M, design: Design) -> Any:
        """The energy it holds at displacement `x_M` (J, >= 0; its work from battery),
        for a force that only stores (a spring) or dissipates; None if it may add
        energy or is not known."""
        return None

    def anchoring_bound(self, reach, two_energy, design: Design) -> Any:
        """An upper bound on its `F_AN` share (N) while `x_M <= reach` (m) and the
        mechanical energy is at most `two_energy / 2` (J); None if not known."""
        return None

    def held_change(self, design: Design) -> Any:
        """How much its `F_AN` share can still change (N) while the barrel is held still
        by its friction (the stick a mode: it does not creep), by time alone; None if not
        known."""
        return None


def forget_part(part: type[Part]) -> None:
    """Take a part defined outside the package out of the family and the registry (its
    group and rows): for a test, or a notebook that redefines it."""
    if not part.ROWS:
        raise ParameterError(f"{part.__name__} is built in: it cannot be forgotten")
    name = part.GROUP.name
    FAMILY.pop(name, None)
    GROUPS.pop(name, None)
    PARAMETERS.remove([row.name for row in part.ROWS])


#: What making a class adds to its body (dataclass, equinox, abc and `Part` itself):
#: left out when a class is made again from its body (`_remade`).
_MADE = frozenset({
    "__dict__", "__weakref__", "__dataclass_fields__", "__dataclass_params__",
    "__match_args__", "__abstractclassvars__", "__abstractmethods__", "__abstractvars__",
    "_abc_impl", "__slotnames__", "LIMITS",
})  # fmt: skip
#: Each outside part's class as received, and the class its parts are made of here
#: (made under the lock: a Dask worker may unpickle on two threads at once).
_RECEIVED: dict[type, type] = {}
_RECEIVING = threading.Lock()


def _received_part(cls: type[Part], values: dict[str, Any]) -> Part:
    """A part defined outside the package, unpickled (`Part.__reduce_ex__`): `values`
    (its fields by name) on its class made whole (`_whole`)."""
    part = object.__new__(_whole(cls))
    for name, value in values.items():
        object.__setattr__(part, name, value)
    return part


def _whole(cls: type[Part]) -> type[Part]:
    """`cls`, or where it came without its pytree's fields, the class made again from its
    body. A class sent by value (cloudpickle: one defined in a notebook or a script's
    `__main__`, sent to a Dask worker) is made empty and filled in after, and equinox
    registers a module's pytree fields when its class is made: its parts would flatten
    to nothing, and a solve would see each field's default instead of its value."""
    with _RECEIVING:
        if cls not in _RECEIVED:
            _RECEIVED[cls] = cls if _flattens_its_fields(cls) else _remade(cls)
        return _RECEIVED[cls]


def _flattens_its_fields(cls: type[Part]) -> bool:
    """Whether a part of `cls` flattens to one leaf a field (its static fields aside)."""
    fields = dataclasses.fields(cls)
    probe = object.__new__(cls)
    for field in fields:
        object.__setattr__(probe, field.name, np.zeros(()))
    dynamic = [f for f in fields if not f.metadata.get("static", False)]
    return jax.tree.structure(probe).num_leaves == len(dynamic)


def _remade(cls: type[Part]) -> type[Part]:
    """`cls` made again from its body, its fields as declared: it joins the family here
    (`Part.__init_subclass__`), in place of any class of its group made before. Its
    methods' references to the class as received (`super()`'s cell, its name among
    their globals) are pointed at the class made."""
    body = {name: value for name, value in vars(cls).items() if name not in _MADE}
    if cls.__dataclass_params__.init:  # pyright: ignore[reportAttributeAccessIssue]
        body.pop("__init__", None)  # the dataclass's own, made again from the fields
    fields = dataclasses.fields(cls)
    # The fields alone, annotated by objects: a string annotation (`from __future__
    # import annotations`) would be read in this process's module of that name.
    body["__annotations__"] = {f.name: Any if isinstance(f.type, str) else f.type for f in fields}
    for f in fields:
        default, factory = (_declared(x) for x in (f.default, f.default_factory))
        body[f.name] = dataclasses.field(
            default=default, default_factory=factory, init=f.init, repr=f.repr,
            hash=f.hash, compare=f.compare, metadata=f.metadata, kw_only=_declared(f.kw_only),
        )  # fmt: skip
    body["__qualname__"] = cls.__qualname__
    earlier = FAMILY.get(cls.GROUP.name)
    if earlier is not None and earlier.ROWS:
        # Its group's class made before in this process: one made again for an earlier
        # version, or a worker's own copy of the sender's script (a process started by
        # `spawn` runs its `__main__` again). The design received says what it is.
        forget_part(earlier)
    metaclass: Any = type(cls)  # equinox's: it registers the pytree's fields
    made = metaclass(cls.__name__, cls.__bases__, body)
    for value in body.values():
        for function in _functions(value):
            cells = zip(function.__code__.co_freevars, function.__closure__ or (), strict=True)
            for name, cell in cells:
                if name == "__class__" and cell.cell_contents is cls:
                    cell.cell_contents = made
            for name in function.__code__.co_names:
                if function.__globals__.get(name) is cls:
                    function.__globals__[name] = made
    return made


def _functions(value: Any) -> list[Any]:
    """The plain functions a class attribute holds (a method, a property's accessors, a
    class or static method's function)."""
    if isinstance(value, property):
        candidates = [value.fget, value.fset, value.fdel]
    else:
        candidates = [getattr(value, "__func__", value)]
    return [f for f in candidates if inspect.isfunction(f)]


def _declared(value: Any) -> Any:
    """`value`, or `dataclasses.MISSING` for a copy of it (sent by value with its
    class, it is another object, which `dataclasses` would take for a value)."""
    return dataclasses.MISSING if type(value).__name__ == "_MISSING_TYPE" else value


def outside_parts(tree: Any) -> list[Part]:
    """The parts defined outside the package (`Part.ROWS`) that the pytree `tree` holds
    (a design's `added`), in its order."""
    found = jax.tree.leaves(tree, is_leaf=lambda x: isinstance(x, Part))
    return [p for p in found if isinstance(p, Part) and type(p).ROWS]


def outside_source(tree: Any) -> str:
    """A digest of the code of every part defined outside the package that `tree` holds
    (its class's source, or its qualified name where the source is not to be had), or ""
    where there is none: a part whose law is edited is another model, to a store's
    identity as to a kept program."""
    classes = sorted({type(p) for p in outside_parts(tree)}, key=lambda c: c.__qualname__)
    if not classes:
        return ""
    digest = hashlib.sha256()
    for cls in classes:
        try:
            text = inspect.getsource(cls)
        except (OSError, TypeError):
            text = f"{cls.__module__}.{cls.__qualname__}"
        digest.update(text.encode())
    return digest.hexdigest()
