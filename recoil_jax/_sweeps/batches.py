"""Designs as columns and as batches: `name -> (n,)` columns checked value by value,
split by the structure of their pytree (one compiled program each), made into one
`RecoilParams` with a leading batch axis (`batch_params`), given a breech force table
(`with_table`) and placed on devices (`shard_batch`)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import equinox as eqx
import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from .._model.parameter_table import PARAMETERS
from .._model.params import ForceTable, Load, RecoilParams, params_from_values, params_to_values
from .._model.registry import PAPER_GROUPS, ParameterError, check_value
from .._model.settings import T1_LIMITS

__all__ = [
    "ABSORBER",
    "as_columns",
    "batch_params",
    "group_values",
    "is_knot",
    "shard_batch",
    "structure_groups",
    "with_table",
]

#: Names a design may carry besides the parameters: the end time, per point.
_SETTINGS = ("t1",)
#: The absorber's parameters, which a design without one (`m = 0`) does not have.
ABSORBER = tuple(name for name, p in PARAMETERS.items() if p.group == "absorber")


def as_columns(designs) -> dict[str, np.ndarray]:
    """Designs as `name -> (n,)` float columns (names checked; missing values in a list of
    dicts take the defaults; a missing orifice knot is NaN, i.e. absent)."""
    if isinstance(designs, Mapping):
        columns = {k: np.atleast_1d(np.asarray(v, dtype=float)) for k, v in designs.items()}
    else:
        designs = list(designs)
        if not designs:
            raise ParameterError("no designs to sweep")
        names = sorted({k for d in designs for k in d})
        for name in names:
            if name not in PARAMETERS and name not in _SETTINGS:
                _unknown(name)
        if "t1" in names and not all("t1" in d for d in designs):
            raise ParameterError(
                "t1 is given for some points but not all: give it for every point, or for none"
            )

        def default(name):
            return PARAMETERS[name].default if name in PARAMETERS else np.nan

        columns = {n: np.array([float(d.get(n, default(n))) for d in designs]) for n in names}
    lengths = {len(v) for v in columns.values()}
    if len(lengths) > 1:
        raise ParameterError(f"sweep columns have different lengths: {sorted(lengths)}")
    for name, column in columns.items():
        if name in _SETTINGS:
            check_value("SolverOptions", name, column, T1_LIMITS)
        elif name in PARAMETERS:
            p = PARAMETERS[name]
            if name == "m":  # m = 0 is the simplified model: check the others in place
                column = np.where(column == 0, p.default, column)
            if p.index is not None:  # NaN: this point has fewer knots
                column = np.where(np.isnan(column), p.lower + 1.0, column)
            check_value(p.owner, name, column, p)
            if p.integer and np.any(column != np.round(column)):
                i = int(np.argmax(column != np.round(column)))
                raise ParameterError(
                    f"{p.owner}.{name}[{i}] = {column[i]:g} is invalid: valid {name} is an "
                    f"integer >= {p.lower:g} ({p.meaning})"
                )
        else:
            _unknown(name)
    return columns


def _unknown(name: str):
    raise ParameterError(
        f"unknown parameter(s) {name}; known: {PARAMETERS.names()} and {', '.join(_SETTINGS)}"
    )


def is_knot(name: str) -> bool:
    """Whether `name` is an orifice knot's (`orifice_<i>`): a design may lack it (NaN)."""
    return name in PARAMETERS and PARAMETERS[name].index is not None


def structure_groups(columns: dict[str, np.ndarray], labels=None) -> list[tuple[np.ndarray, dict]]:
    """The designs split by the structure of their pytree, which one compiled program
    serves: with or without an absorber (`m = 0`), the number of rounds (`shots`, static)
    and the number of orifice knots. Returns `(indices, columns)` per group, in order of
    first appearance; a knot column is kept only in the groups that have that knot."""
    n = len(next(iter(columns.values())))
    simplified = columns["m"] == 0 if "m" in columns else np.zeros(n, dtype=bool)
    shots = columns.get("shots", np.ones(n))
    knots = sorted((PARAMETERS[c].index or 0, c) for c in columns if is_knot(c))
    present = np.array([~np.isnan(columns[c]) for _, c in knots], dtype=bool).reshape(len(knots), n)
    # Knots per design: the leading ones present (a missing knot is NaN).
    count = np.argmin(np.vstack([present, np.zeros((1, n), bool)]), axis=0)
    # A knot present after the first missing one is a hole.
    holes = np.any(present & (np.arange(len(knots))[:, None] >= count[None, :]), axis=0)
    if holes.any():
        i = int(np.argmax(holes))
        label = i if labels is None else int(np.asarray(labels)[i])
        raise ParameterError(
            f"design {label}: orifice knots must be numbered from 0 without holes: "
            f"{knots[count[i]][1]} is missing"
        )
    # One integer per design, no Python object per design (a sweep may have millions):
    # the knots (at most 32) in the low bits, then the rounds, then the absorber.
    keys = count.astype(np.int64) + (np.asarray(shots, dtype=np.int64) << 6)
    keys += simplified.astype(np.int64) << 40
    if n and np.all(keys == keys[0]):  # one structure: no sorting
        unique, first, inverse = keys[:1], np.zeros(1, int), np.zeros(0, int)
    else:
        unique, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
        inverse = inverse.reshape(-1)
    groups = []
    for number in np.argsort(first):  # in order of first appearance
        knots_here = int(unique[number] & 63)
        indices = np.arange(n) if len(unique) == 1 else np.flatnonzero(inverse == number)
        group = {
            c: v if len(unique) == 1 else v[indices]
            for c, v in columns.items()
            if not (is_knot(c) and (PARAMETERS[c].index or 0) >= knots_here)
        }
        groups.append((indices, group))
    return groups


def batch_params(designs) -> tuple[RecoilParams, dict[str, np.ndarray]]:
    """Designs (a list of `{name: value}` dicts, or `name -> (n,)` columns) as one
    `RecoilParams` whose every leaf has shape `(n,)` (names not given take the paper's
    values), ready for `jax.vmap(..., in_axes=0)`; also returns the flat columns. Every
    value is validated (a bad one raises `ParameterError` naming its index). The designs
    must share one structure: all with or all without an absorber (`m = 0`), one number
    of rounds and of orifice knots (`sweep` runs mixed designs as separate groups)."""
    columns = as_columns(designs)
    columns.pop("t1", None)
    if len(structure_groups(columns)) > 1:
        raise ParameterError(
            "these designs differ in structure (m = 0 beside m > 0, different shots or "
            "numbers of orifice knots) and cannot share one RecoilParams; sweep() runs "
            "them as separate groups"
        )
    values = group_values(columns)
    return params_from_values(values), values


def group_values(columns: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The flat columns of designs of one structure (validated), with a full column of
    defaults for every parameter of every group they have (`batch_params`)."""
    n = len(next(iter(columns.values())))
    simplified = "m" in columns and np.all(columns["m"] == 0)
    # Every parameter of every group the designs have gets a full column of defaults.
    seed = {"m": 0.0} if simplified else {}
    for name in columns:
        p = PARAMETERS[name]
        if p.group not in PAPER_GROUPS and p.index is None:
            seed.setdefault(name, p.default)
    defaults = params_to_values(params_from_values(seed))
    values = {k: np.full(n, float(np.asarray(v))) for k, v in defaults.items()}
    values.update(columns)
    if simplified:
        values = {k: v for k, v in values.items() if k == "m" or k not in ABSORBER}
    return values


def shard_batch(tree, devices: Sequence[Any] | None = None):
    """Place a pytree whose leaves have a leading batch axis on `devices` (default: all
    local devices), split along that axis. The batch must divide evenly."""
    devices = list(devices) if devices is not None else jax.local_devices()
    mesh = Mesh(np.array(devices), ("batch",))
    return jax.device_put(tree, NamedSharding(mesh, PartitionSpec("batch")))


def with_table(params: RecoilParams, table: ForceTable) -> RecoilParams:
    """`params` (one design, or a batch with a leading axis on every leaf) with the
    breech force `table` (one round) for every design, or each design's own (a batched
    table `(B, n)`, `ForceTable.stacked`); a load with the default rhythm is added where
    there is none."""
    batch = np.shape(params.barrel.v0)
    load = params.load
    if load is None:
        load = Load(
            pulse_time=np.full(batch, PARAMETERS["pulse_time"].default),
            fire_interval=np.full(batch, PARAMETERS["fire_interval"].default),
        )
    points = np.shape(table.t)[-1]
    batched = ForceTable(
        t=np.broadcast_to(np.asarray(table.t), (*batch, points)),
        F=np.broadcast_to(np.asarray(table.F), (*batch, points)),
    )
    load = eqx.tree_at(lambda q: q.table, load, batched, is_leaf=lambda x: x is None)
    return eqx.tree_at(lambda p: p.load, params, load, is_leaf=lambda x: x is None)
