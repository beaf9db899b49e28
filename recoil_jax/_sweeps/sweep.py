"""Vectorised sweeps: many designs in chunked batches, split over threads and devices,
each through the lane scheduler, with a status per point."""

from __future__ import annotations

import dataclasses
import inspect
import itertools
import json
import math
import os
import sys
import time
from collections.abc import Iterator, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, NamedTuple

import equinox as eqx
import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from .._campaigns.progress import Progress
from .._campaigns.store import (
    SweepStore,
    campaign_identity,
    lowest_row,
    read_sweep_store,
    store_failures,
)
from .._model.derivatives import GRADIENT_OPTIONS, check_wrt, peak_gradients_batch
from .._model.metrics import METRICS, PEAK_FIELDS, gradient_key
from .._model.parameter_table import PARAMETERS
from .._model.params import ForceTable, Load, RecoilParams, params_from_values, params_to_values
from .._model.programs import avx2_codegen_set
from .._model.registry import ParameterError, check_value
from .._model.settings import (
    T1_LIMITS,
    Smoothing,
    SolverOptions,
    check_load_fits,
    default_end_time,
    with_default_tolerances,
)
from .._model.solve import peaks_batch
from .._model.status import Status, status_codes, status_item, status_messages

__all__ = [
    "CHUNK_SIZE",
    "Grid",
    "StoredSweep",
    "SweepResult",
    "batch_params",
    "default_workers",
    "grid",
    "load_sweep",
    "shard_batch",
    "sweep",
    "sweep_grid",
    "sweep_to_store",
    "with_table",
]

#: Names a design may carry besides the parameters: the end time, per point.
_SETTINGS = ("t1",)
_ABSORBER = tuple(name for name, p in PARAMETERS.items() if p.group == "absorber")


@dataclasses.dataclass
class SweepResult:
    """Results of a sweep, one entry per design, in input order (NumPy arrays, shape
    `(n,)`).

    - `values`: every parameter of every design by flat name, as requested (`m = 0`: no
      absorber, whose other parameters then have no effect), and `t1` if given per point.
    - `peaks`: the reported `Peaks` fields by name (`peak_anchoring_force`,
      `peak_anchoring_force_time`, ..., `num_steps`). Points whose solve failed hold NaN
      there, and say why in `status`.
    - `status`: a `Status` item of shape `(n,)`; `ok`, `messages()` and `failures()` read
      it.
    - `gradients`: with `wrt`, `{metric: {parameter: (n,) derivative}}`, else None. For the
      simplified model (`m = 0`) the derivatives with respect to absorber parameters are 0.
    - `swept`, `grid_shape`: for a cartesian grid, the swept names and the grid's shape
      (`reshape` the arrays to it, C order over `swept`).
    - `seconds`: the wall time of this run; `stored`: how many of the designs were read
      from the store (a resumed sweep) rather than solved in it.
    """

    values: dict[str, np.ndarray]
    peaks: dict[str, np.ndarray]
    status: Any
    gradients: dict[str, dict[str, np.ndarray]] | None = None
    swept: tuple[str, ...] = ()
    grid_shape: tuple[int, ...] | None = None
    seconds: float = 0.0
    stored: int = 0

    def __len__(self) -> int:
        return int(status_codes(self.status).shape[0])

    @property
    def ok(self) -> np.ndarray:
        return np.asarray(self.status == Status.ok)

    @property
    def codes(self) -> np.ndarray:
        """`(n,)`: each point's integer `Status` code."""
        return status_codes(self.status)

    def messages(self) -> list[str]:
        return status_messages(self.status)

    def failures(self) -> list[tuple[int, str]]:
        """`(index, reason)` of every failed point."""
        messages = self.messages()
        return [(int(i), messages[i]) for i in np.flatnonzero(~self.ok)]

    def parameters(self, index: int) -> dict[str, float]:
        """The parameters of point `index`, as `simulate --json` reports them (no
        absorber parameters for the simplified model, no knots it does not have)."""
        simplified = "m" in self.values and self.values["m"][index] == 0
        return {
            name: float(v[index])
            for name, v in self.values.items()
            if not (simplified and name in _ABSORBER and name != "m") and not np.isnan(v[index])
        }

    def records(self, model: str = "smoothed") -> list[dict]:
        """One dict per point, in input order, with the keys of `recoil-jax simulate
        --json` (`PEAK_FIELDS`): the peaks (None where the solve failed), `status` ("ok" or
        the reason), `model`, `parameters`; with gradients also `gradients`
        ({metric key: {parameter: derivative}})."""
        out = []
        messages = self.messages()
        for i in range(len(self)):
            ok = bool(self.ok[i])
            record: dict[str, Any] = {
                key: None
                if not ok
                else (int if field == "num_steps" else float)(self.peaks[field][i])
                for field, key in PEAK_FIELDS.items()
            }
            record["status"] = messages[i]
            record["model"] = model
            record["parameters"] = self.parameters(i)
            if self.gradients:
                record["gradients"] = {
                    METRICS[name].key: {p: float(v[i]) if ok else None for p, v in by.items()}
                    for name, by in self.gradients.items()
                }
            out.append(record)
        return out


def _as_columns(designs) -> dict[str, np.ndarray]:
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


def _is_knot(name: str) -> bool:
    return name in PARAMETERS and PARAMETERS[name].index is not None


def _structure_groups(columns: dict[str, np.ndarray], labels=None) -> list[tuple[np.ndarray, dict]]:
    """The designs split by the structure of their pytree, which one compiled program
    serves: with or without an absorber (`m = 0`), the number of rounds (`shots`, static)
    and the number of orifice knots. Returns `(indices, columns)` per group, in order of
    first appearance; a knot column is kept only in the groups that have that knot."""
    n = len(next(iter(columns.values())))
    simplified = columns["m"] == 0 if "m" in columns else np.zeros(n, dtype=bool)
    shots = columns.get("shots", np.ones(n))
    knots = sorted((PARAMETERS[c].index or 0, c) for c in columns if _is_knot(c))
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
            if not (_is_knot(c) and (PARAMETERS[c].index or 0) >= knots_here)
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
    columns = _as_columns(designs)
    columns.pop("t1", None)
    if len(_structure_groups(columns)) > 1:
        raise ParameterError(
            "these designs differ in structure (m = 0 beside m > 0, different shots or "
            "numbers of orifice knots) and cannot share one RecoilParams; sweep() runs "
            "them as separate groups"
        )
    values = _group_values(columns)
    return params_from_values(values), values


def _group_values(columns: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The flat columns of designs of one structure (validated), with a full column of
    defaults for every parameter of every group they have (`batch_params`)."""
    n = len(next(iter(columns.values())))
    simplified = "m" in columns and np.all(columns["m"] == 0)
    # Every parameter of every group the designs have gets a full column of defaults.
    seed = {"m": 0.0} if simplified else {}
    for name in columns:
        p = PARAMETERS[name]
        if p.group in ("load", "buffer", "recuperator") and p.index is None:
            seed.setdefault(name, p.default)
    defaults = params_to_values(params_from_values(seed))
    values = {k: np.full(n, float(np.asarray(v))) for k, v in defaults.items()}
    values.update(columns)
    if simplified:
        values = {k: v for k, v in values.items() if k == "m" or k not in _ABSORBER}
    return values


def shard_batch(tree, devices: Sequence[Any] | None = None):
    """Place a pytree whose leaves have a leading batch axis on `devices` (default: all
    local devices), split along that axis. The batch must divide evenly."""
    devices = list(devices) if devices is not None else jax.local_devices()
    mesh = Mesh(np.array(devices), ("batch",))
    return jax.device_put(tree, NamedSharding(mesh, PartitionSpec("batch")))


class Grid:
    """The cartesian product of `axes` (name -> values; C order, as `itertools.product`
    gives it) plus `fixed` values (name -> value), without its columns made: `sweep` and
    `sweep_to_store` make them a chunk at a time, so a streamed grid's memory does not
    grow with it (`docs/campaigns.md`); `grid` makes them all.

    - `shape`: the axes' lengths; `len(grid)`: the number of designs;
    - `columns(rows)`: `name -> (len(rows),)` values of the designs at flat indices `rows`
      (a slice or an integer array; None: every design).

    **Raises:** `ParameterError` for an axis without values, or a name both swept and
    fixed. The values are checked by `sweep`, before anything is compiled."""

    def __init__(
        self, axes: Mapping[str, Sequence[float]], fixed: Mapping[str, float] | None = None
    ):
        self.axes = {n: np.asarray(v, dtype=float).reshape(-1) for n, v in axes.items()}
        self.fixed = {n: float(v) for n, v in (fixed or {}).items()}
        for name, values in self.axes.items():
            if not len(values):
                raise ParameterError(f"the grid's axis {name} has no values")
            if name in self.fixed:
                raise ParameterError(f"{name} is both swept and fixed")
        if not self.axes and not self.fixed:
            raise ParameterError("a grid needs at least one axis or fixed value")
        self.shape = tuple(len(a) for a in self.axes.values())

    def __len__(self) -> int:
        return math.prod(self.shape)

    @property
    def names(self) -> list[str]:
        return [*self.axes, *self.fixed]

    def columns(self, rows: slice | np.ndarray | None = None) -> dict[str, np.ndarray]:
        n = len(self)
        if rows is None:  # every design, by broadcasting (no index arrays)
            shape, d = self.shape, len(self.shape)
            out = {
                name: np.broadcast_to(a.reshape([-1 if i == j else 1 for i in range(d)]), shape)
                .reshape(-1)
                .copy()
                for j, (name, a) in enumerate(self.axes.items())
            }
            count = n
        else:
            flat = np.arange(*rows.indices(n)) if isinstance(rows, slice) else np.asarray(rows)
            index = np.unravel_index(flat, self.shape) if self.shape else ()
            out = {name: a[i] for (name, a), i in zip(self.axes.items(), index, strict=True)}
            count = len(flat)
        return out | {name: np.full(count, value) for name, value in self.fixed.items()}

    def probe(self) -> tuple[Grid, np.ndarray]:
        """The small grid that meets every check that involves more than one value of a
        design (its structure, its load against its end time, the orifice a piston
        needs): each of those axes reduced to its extremes, its zero and its NaN (those
        checks are monotone in each value), an orifice knot's to one value present and
        one absent, every other axis to its first value (its values are checked one by
        one); and the index in this grid of each of its designs (for messages)."""
        reduced, positions = {}, []
        for name, values in self.axes.items():
            kept = [0]  # positions on the axis
            missing = np.isnan(values)
            if _is_knot(name):  # its checks ask only whether it is there
                kept += [int(np.argmax(missing))] * bool(missing.any())
                kept += [int(np.argmax(~missing))] * bool(not missing.all())
            elif name in _CROSS_CHECKED:
                if not missing.all():
                    kept = [int(np.nanargmin(values)), int(np.nanargmax(values))]
                kept += [int(np.argmax(values == 0))] * bool(np.any(values == 0))
                kept += [int(np.argmax(missing))] * bool(missing.any())
            # One position per distinct value (NaN once).
            distinct = dict.fromkeys(kept)
            by_value = {("nan" if np.isnan(values[i]) else values[i]): i for i in distinct}
            positions.append(np.array(sorted(by_value.values())))
            reduced[name] = values[positions[-1]]
        probe = Grid(reduced, self.fixed)
        index = np.unravel_index(np.arange(len(probe)), probe.shape) if probe.shape else ()
        where = [kept[i] for kept, i in zip(positions, index, strict=True)]
        flat = np.ravel_multi_index(where, self.shape) if self.shape else np.zeros(1, int)
        return probe, np.asarray(flat).reshape(-1)


#: Names whose checks involve other values of the same design: the structure (`m = 0`,
#: `shots`), the load against the end time, and the piston area against the orifice.
_CROSS_CHECKED = ("m", "shots", "fire_interval", "pulse_time", "t1", "piston_area")


def grid(axes: Mapping[str, Sequence[float]], fixed: Mapping[str, float] | None = None):
    """Cartesian product of `axes` (name -> values), C order, plus `fixed` values:
    returns `(columns, shape)` for `sweep`, made in memory (`Grid` makes them on demand)."""
    designs = Grid(axes, fixed)
    check_memory(
        len(designs), 8 * len(designs.names), "a grid",
        "give a smaller grid, or sweep Grid(axes, fixed) to a store (its columns are made "
        "a chunk at a time)",
    )  # fmt: skip
    return designs.columns(), designs.shape


def _available_memory() -> int | None:
    """Bytes of memory this process may still use: Linux's MemAvailable, or less where a
    container's memory limit (cgroup v2) leaves less; None where neither is known."""
    free = []
    try:
        with open("/proc/meminfo") as meminfo:
            for line in meminfo:
                if line.startswith("MemAvailable:"):
                    free.append(int(line.split()[1]) * 1024)
    except (OSError, ValueError, IndexError):
        pass
    try:
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        used = Path("/sys/fs/cgroup/memory.current").read_text().strip()
        if limit != "max":
            free.append(int(limit) - int(used))
    except (OSError, ValueError):
        pass
    return min(free) if free else None


def check_memory(
    designs: int, bytes_per_design: int, what: str, advice: str, unit: str = "designs"
) -> None:
    """Refuse, before anything is allocated, `what` of `designs` designs (or other
    `unit`s) whose arrays (`bytes_per_design` each) would take more than half of the free
    memory."""
    available = _available_memory()
    need = designs * bytes_per_design
    if available is not None and need > available // 2:
        raise ParameterError(
            f"{what} of {designs:,} {unit} needs about {need / 1e9:,.1f} GB in memory, more "
            f"than half of the {available / 1e9:.1f} GB free here: {advice}"
        )


def default_workers(devices: Sequence[Any]) -> int:
    """Parts a sweep chunk is split into: one per device, and on CPU at least one per
    core this process may use. One XLA CPU program keeps about one core busy, and
    programs called from different threads run at the same time."""
    if all(d.platform == "cpu" for d in devices):
        cores = (
            len(os.sched_getaffinity(0))
            if hasattr(os, "sched_getaffinity")
            else (os.cpu_count() or 1)
        )
        return len(devices) * max(1, -(-cores // len(devices)))
    return len(devices)


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


def _has(params: RecoilParams, name: str) -> bool:
    """Whether `params` has the real-valued parameter `name` (its group, its knot)."""
    p = PARAMETERS[name] if name in PARAMETERS else None
    if p is None or p.integer:
        return False
    module = getattr(params, p.group)
    return module is not None and (p.index is None or p.index < module.knots)


#: Sweeps of up to this many designs run in one chunk of this size (per structure, the
#: same compiled program); only the real designs are solved.
SHARED_CHUNK = 1024

#: The most designs per compiled call of a sweep, unless the caller says.
CHUNK_SIZE = 16384

#: Designs in flight per part. On XLA:CPU a loop step's cost per lane grows once the
#: lanes' working set leaves the core's cache: measured at 16,384 designs (2 cores), 128
#: lanes ran the paper model 1.14x, the hardware designs 1.19x and 4-parameter Jacobians
#: 2.15x faster than 1024 (capped to 512 there), and 64 lanes no faster (docs/speed.md).
DEFAULT_LANES = 128


def _run_chunk(
    batch: RecoilParams, t1, count: int, smoothing, options, wrt, devices, lanes: int, workers: int
):
    """Run one chunk: split along the batch into `workers` equal, interleaved parts
    (each with the same mix of designs), each through the queued stepping loop (`lanes`
    designs in flight) on device `i % len(devices)`, from its own thread. Only the first
    `count` designs of the chunk are solved; the rest pad it to its compiled shape."""
    size = jax.tree.leaves(batch)[0].shape[0] // workers
    # At least 16 designs per lane: the slowest designs take ~7x the mean number of
    # steps, and with fewer per lane the batch idles while they finish (measured: 4096
    # Jacobians ran 2.5x faster with 128 lanes per part than with 512).
    lanes = min(lanes, max(32, size // 16))
    # Tolerances as values, also the defaults: one program for any tolerances (the
    # smoothed and the hard-switch model of a structure share it too).
    options = with_default_tolerances(batch, options)

    def run(i):
        part, end = jax.device_put(
            jax.tree.map(lambda x: x[i::workers], (batch, t1)), devices[i % len(devices)]
        )
        solved = np.asarray(len(range(i, count, workers)))  # this part's real designs
        if wrt:
            out = peak_gradients_batch(part, end, smoothing, options, wrt, lanes, solved)
        else:
            out = peaks_batch(part, end, smoothing, options, lanes, solved)
        return jax.tree.map(np.asarray, out)

    with ThreadPoolExecutor(workers) as pool:
        outputs = list(pool.map(run, range(workers)))
    # Undo the interleaving: design j of part i is entry i + j * workers of the chunk.
    return jax.tree.map(lambda *xs: np.stack(xs, axis=1).reshape(-1, *xs[0].shape[1:]), *outputs)


def _chunk_columns(result, wrt, all_wrt) -> dict[str, np.ndarray]:
    """One chunk's results by column (`sweep.csv`'s and the store's names): the reported
    peaks (NaN where the solve failed), `status_code`, and the derivative of every metric
    with respect to each of `all_wrt` (0 for a parameter this group does not have)."""
    peaks, grads = result if wrt else (result, None)
    codes = status_codes(peaks.status)
    failed = codes != status_codes(Status.ok)
    out = {}
    for field, key in PEAK_FIELDS.items():
        value = np.asarray(getattr(peaks, field), dtype=float)
        out[key] = value if field == "num_steps" else np.where(failed, np.nan, value)
    for name in METRICS if all_wrt else ():
        matrix = getattr(grads, name) if grads is not None else None
        for w in all_wrt:
            column = np.zeros(len(codes))
            if grads is not None and w in grads.wrt:
                column = np.where(failed, np.nan, np.asarray(matrix)[:, grads.wrt.index(w)])
            out[gradient_key(name, w)] = column
    out["status_code"] = codes
    return out


class _Group(NamedTuple):
    """The designs of one structure (one compiled program): `indices` into the sweep's
    input, their given `columns` (the rest take defaults when a chunk is built, so that
    a sweep never holds every parameter of every design), end times `t1`, the `wrt` they
    have, whether they have an `absorber`, and the `force_table` of every design."""

    indices: np.ndarray
    columns: dict[str, np.ndarray]
    t1: np.ndarray
    wrt: tuple[str, ...] | None
    absorber: bool
    force_table: ForceTable | None

    def params(self, rows) -> RecoilParams:
        """The `RecoilParams` of the group's designs at positions `rows`."""
        values = _group_values({k: v[rows] for k, v in self.columns.items()})
        params = params_from_values(values)
        return params if self.force_table is None else with_table(params, self.force_table)


#: Designs per slice when a group's end times and loads are checked: the checks never
#: hold every parameter of every design at once.
_CHECK_SLICE = 65536


def _groups(
    columns, options: SolverOptions, wrt, force_table, labels=None, every_wrt: bool = True
) -> list[_Group]:
    """The designs by structure (`_structure_groups`), each with its end times, its loads
    checked to fit them and the `wrt` it has; raises `ParameterError` before anything is
    compiled. `labels`: the designs' indices in the sweep (default: their positions; a
    grid's block or probe gives its own); `every_wrt`: check that each of `wrt` is a
    parameter of some group (a grid checks this once, on its `Grid.probe`)."""
    groups = []
    for indices, given in _structure_groups(columns, labels):
        indices = indices if labels is None else np.asarray(labels)[indices]
        given = dict(given)
        t1 = given.pop("t1", None)
        group = _Group(indices, given, np.zeros(0), None, True, force_table)
        probe = group.params(slice(0, 1))
        ends = []
        for begin in range(0, len(indices), _CHECK_SLICE):
            rows = slice(begin, begin + _CHECK_SLICE)
            params = group.params(rows)
            if t1 is not None:
                end = t1[rows]
            elif options.t1 is not None:
                end = np.full(len(indices[rows]), float(options.t1))
            else:
                end = np.asarray(default_end_time(params))
            check_load_fits(params, end, options.max_steps, labels=indices[rows])
            ends.append(end)
        group_wrt = None
        if wrt:
            # Parameters this group does not have (an absorber's for m = 0, knots beyond
            # its orifice) change nothing: their derivatives are 0.
            group_wrt = tuple(w for w in wrt if _has(probe, w)) or None
        absorber = probe.absorber is not None
        groups.append(group._replace(t1=np.concatenate(ends), wrt=group_wrt, absorber=absorber))
    for w in wrt if every_wrt and wrt else ():
        if not any(w in (g.wrt or ()) for g in groups):
            check_wrt(groups[0].params(slice(0, 1)), (w,))  # raises, naming why
    for g in groups:
        if g.wrt:
            check_wrt(g.params(slice(0, 1)), g.wrt)
    return groups


class _Chunk(NamedTuple):
    """One compiled call's worth of a group's designs: `key` (in the store), the group,
    `rows` (positions in the group, in solving order) and `size` (the padded batch the
    program is compiled for)."""

    key: str
    group: _Group
    rows: np.ndarray
    size: int

    @property
    def points(self) -> np.ndarray:
        """The chunk's designs' indices into the sweep's input."""
        return self.group.indices[self.rows]


def _per_chunk(plan: dict) -> int:
    """The most designs per chunk: `chunk_size`, a multiple of the workers."""
    workers = plan["workers"]
    return max(workers, plan["chunk_size"] - plan["chunk_size"] % workers)


def _chunks(groups, plan: dict, prefix: str = "", full: bool = False) -> list[_Chunk]:
    """The designs cut into chunks, group by group, in solving order (the gap ascending,
    with `sort_by_gap`, so that the impact-heavy designs start early). `prefix` starts
    each key; `full`: every chunk of `_per_chunk`'s size (a grid's chunks, which would
    otherwise come in many sizes, each compiled)."""
    workers = plan["workers"]
    out = []
    for number, group in enumerate(groups):
        n = len(group.indices)
        # Without a gap column every design has the default gap: no order to take.
        sort = plan["sort_by_gap"] and group.absorber and "gap" in group.columns
        order = np.argsort(group.columns["gap"], kind="stable") if sort else np.arange(n)
        chunk = _per_chunk(plan)
        if not full:
            # No bigger than needed, rounded up to a power of two per part and to at
            # least `SHARED_CHUNK`: the padding is never solved, and every sweep of up to
            # that many designs (a study's samples and its checks) runs one program per
            # structure.
            per_part = -(-n // workers)
            needed = max(workers * (1 << (per_part - 1).bit_length()), SHARED_CHUNK)
            chunk = min(chunk, needed - needed % workers)
        for begin in range(0, n, chunk):
            rows = order[begin : begin + chunk]
            out.append(_Chunk(f"{prefix}{number}:{begin}", group, rows, chunk))
    return out


def _chunk_batch(chunk: _Chunk):
    """The chunk's designs and end times, padded to its compiled size with its last."""
    rows = chunk.rows
    padded = np.concatenate([rows, np.full(chunk.size - len(rows), rows[-1])])
    return jax.tree.map(np.asarray, chunk.group.params(padded)), chunk.group.t1[padded]


def _solve_chunk(batch, t1, count, smoothing, options, wrt, all_wrt, devices, plan):
    """Solve the first `count` designs of a padded batch: `(columns, seconds)`, their
    columns (`_chunk_columns`) and the wall time it took."""
    start = time.perf_counter()
    result = _run_chunk(
        batch, t1, count, smoothing, options, wrt, devices, plan["lanes"], plan["workers"]
    )
    result = jax.tree.map(lambda x: x[:count], result)
    return _chunk_columns(result, wrt, all_wrt), time.perf_counter() - start


def _cache_dir() -> str | None:
    """The folder of this process's persistent compilation cache (None: off)."""
    return jax.config.values.get("jax_compilation_cache_dir")


def _solve_chunk_on_worker(
    batch, t1, count, smoothing, options, wrt, all_wrt, plan, cache, avx2: bool
):
    """`_solve_chunk` as a Dask task, on the worker's own devices, with the persistent
    compilation cache of the process that made the sweep (so each structure compiles
    once for all workers), and its AVX2 code if it has it (`use_avx2_codegen`; a worker
    that has computed already keeps its own)."""
    from .._model.programs import enable_compilation_cache, use_avx2_codegen

    if avx2:
        use_avx2_codegen()
    if cache and _cache_dir() != cache:
        enable_compilation_cache(cache)
    return _solve_chunk(
        batch, t1, count, smoothing, options, wrt, all_wrt, jax.local_devices(), plan
    )


def _solved_chunks(todo, smoothing, options, all_wrt, devices, plan, client):
    """`(chunk, columns, seconds)` for each chunk of `todo` (an iterable, made as it is
    taken) as it finishes: one after the other here, or as Dask tasks on `client`'s
    workers (a chunk whose worker dies is run again elsewhere by Dask)."""
    if client is None:
        for chunk in todo:
            batch, t1 = _chunk_batch(chunk)
            wrt = chunk.group.wrt
            yield (
                chunk,
                *_solve_chunk(
                    batch, t1, len(chunk.points), smoothing, options, wrt, all_wrt, devices, plan
                ),
            )
        return
    from distributed import as_completed

    cache = _cache_dir()
    avx2 = avx2_codegen_set()
    futures = {}
    done = as_completed()
    waiting = iter(todo)

    def submit(chunk: _Chunk) -> None:
        batch, t1 = _chunk_batch(chunk)
        future = client.submit(
            _solve_chunk_on_worker,
            batch,
            t1,
            len(chunk.points),
            smoothing,
            options,
            chunk.group.wrt,
            all_wrt,
            plan,
            cache,
            avx2,
            pure=False,
            retries=2,
        )
        futures[future] = chunk
        done.add(future)

    # Two chunks per worker thread in flight: the workers never wait, and the designs
    # waiting to be solved stay here, not in the cluster's memory.
    for chunk in itertools.islice(waiting, 2 * max(1, sum(client.nthreads().values()))):
        submit(chunk)
    try:
        for future in done:
            chunk = futures.pop(future)
            yield chunk, *future.result()
            following = next(waiting, None)
            if following is not None:
                submit(following)
    finally:
        for future in futures:
            future.cancel()


class _Columns:
    """A sweep's designs given as columns, all in memory (`_as_columns`): grouped by
    structure and checked as a whole, chunked group by group."""

    def __init__(self, columns: dict[str, np.ndarray], options, wrt, force_table):
        self.columns = columns
        self.names = list(columns)
        self.count = len(next(iter(columns.values())))
        self.groups = _groups(columns, options, wrt, force_table)

    def identity(self) -> Any:
        return self.columns

    def chunks(self, plan: dict, done: Mapping[str, int]) -> Iterator[_Chunk]:
        """The chunks, those in `done` (key -> designs, from the store) left out."""
        return (c for c in _chunks(self.groups, plan) if c.key not in done)

    def given(self, points: np.ndarray) -> dict[str, np.ndarray]:
        return {name: values[points] for name, values in self.columns.items()}

    def all_columns(self) -> dict[str, np.ndarray]:
        return self.columns

    def structures(self, columns) -> list[tuple[np.ndarray, dict[str, np.ndarray]]]:
        """`(indices, given columns)` per structure (the groups it was chunked by)."""
        return [(g.indices, g.columns) for g in self.groups]


class _GridColumns:
    """A sweep of a `Grid`: its values checked on its axes and on its `Grid.probe` (before
    anything is compiled), its columns made a block of `_per_chunk` designs at a time,
    each block grouped and chunked on its own (so that memory does not grow with the
    grid), in input order."""

    def __init__(self, designs: Grid, options, wrt, force_table):
        for name, values in designs.axes.items():
            _as_columns({name: values})  # each value on its own: the checks are elementwise
        probe, labels = designs.probe()  # the fixed values too
        _groups(_as_columns(probe.columns()), options, wrt, force_table, labels)
        self.grid, self.names, self.count = designs, designs.names, len(designs)
        self.options, self.wrt, self.force_table = options, wrt, force_table

    def identity(self) -> Any:
        # The axes in their order (it sets which design each index is): a dict's keys
        # are sorted when it is flattened.
        axes = self.grid.axes
        return ("grid", tuple(axes), tuple(axes.values()), self.grid.fixed)

    def chunks(self, plan: dict, done: Mapping[str, int]) -> Iterator[_Chunk]:
        """The chunks, block by block, those in `done` (key -> designs, from the store)
        left out; a block whose every design is stored is not made at all (a resumed
        campaign near its end does not rebuild what it has)."""
        block = _per_chunk(plan)
        stored: dict[str, int] = {}
        for key, designs in done.items():
            prefix = key.split("/", 1)[0]
            stored[prefix] = stored.get(prefix, 0) + int(designs)
        for number, begin in enumerate(range(0, self.count, block)):
            if stored.get(str(number), 0) >= min(block, self.count - begin):
                continue
            columns = self.grid.columns(slice(begin, begin + block))
            labels = np.arange(begin, min(begin + block, self.count))
            groups = _groups(
                columns, self.options, self.wrt, self.force_table, labels, every_wrt=False
            )
            # One block: chunks as for columns; more: all of one size (one program).
            for chunk in _chunks(groups, plan, f"{number}/", full=self.count > block):
                if chunk.key not in done:
                    yield chunk

    def given(self, points: np.ndarray) -> dict[str, np.ndarray]:
        return self.grid.columns(points)

    def all_columns(self) -> dict[str, np.ndarray]:
        return self.grid.columns()

    def structures(self, columns) -> list[tuple[np.ndarray, dict[str, np.ndarray]]]:
        """`(indices, given columns)` per structure of `all_columns` (`t1` left out)."""
        return [
            (indices, {name: c for name, c in given.items() if name != "t1"})
            for indices, given in _structure_groups(columns)
        ]


def _plan(workers, lanes, chunk_size, sort_by_gap) -> dict:
    if workers < 1:
        raise ParameterError(f"workers = {workers} is invalid: valid >= 1")
    return {
        "workers": int(workers),
        "lanes": int(lanes),
        "chunk_size": int(chunk_size),
        "sort_by_gap": bool(sort_by_gap),
    }


def _open_store(path, designs, smoothing, options, wrt, force_table, plan, bar_enabled):
    """The store at `path` for this sweep (created, or checked to be this sweep's); its
    plan replaces `plan`, so that the chunks are those of the run that made it."""
    identity = campaign_identity(
        "sweep", designs.identity(), smoothing, options, wrt or (), force_table
    )
    names = [*designs.names, *PEAK_FIELDS.values()]
    names += [gradient_key(m, w) for m in METRICS for w in wrt or ()]
    n = designs.count
    store = SweepStore(
        path,
        identity=identity,
        total=n,
        plan=plan,
        columns=names,
        description={
            "designs": n,
            "names": sorted(designs.names),
            "wrt": list(wrt or ()),
            "created": time.strftime("%Y-%m-%d %H:%M:%S"),
        },
    )
    if store.plan != plan and bar_enabled is not False:
        print(
            f"sweep: resuming with the plan of the run that made {path} ({store.plan}), "
            f"not {plan}: the same chunks give the same results",
            file=sys.stderr,
        )
    return store


def sweep(
    designs,
    *,
    smoothing: Smoothing = Smoothing(),
    options: SolverOptions | None = None,
    wrt: Sequence[str] | None = None,
    chunk_size: int = CHUNK_SIZE,
    lanes: int = DEFAULT_LANES,
    progress: bool | None = None,
    sort_by_gap: bool = True,
    devices: Sequence[Any] | None = None,
    workers: int | None = None,
    force_table: ForceTable | None = None,
    store: str | os.PathLike | None = None,
    client: Any = None,
) -> SweepResult:
    """Peaks (and, with `wrt`, their gradients) of many designs.

    **Arguments:**

    - `designs`: a list of `{name: value}` dicts, a mapping `name -> (n,) array` (e.g.
      from `grid`), or a `Grid` (its columns made a chunk at a time, in input order).
      Names are flat parameter names, plus `t1` (the end time, per point); names not
      given take the paper's values. `m = 0` is the simplified model, and may be
      mixed with absorbers: the two groups run apart and merge in input order.
    - `smoothing`: the switch widths, shared by every point.
    - `options`: default `SolverOptions()`, or `GRADIENT_OPTIONS` with `wrt`; its `t1`
      applies where the designs do not give one.
    - `wrt`: parameters to differentiate with respect to (forward sensitivities).
    - `chunk_size`: the most designs per compiled call. A sweep of fewer designs runs in
      one chunk of the next power of two (per worker), at least `SHARED_CHUNK` (1024),
      so that sweeps of different sizes reuse one program; the last chunk is padded to
      the same shape, and padding is never solved.
    - `lanes`: designs in flight per part in the vmapped stepping loop (default
      `DEFAULT_LANES`, 128; capped at 1/16 of the part, at least 32); a lane takes the
      next design as soon as its own has finished. A plain `vmap` would run every design
      for as many steps as the slowest.
    - `progress`: a progress line on stderr (default: when there is more than one chunk),
      and a line saying how many designs failed; `False`: nothing is printed.
    - `sort_by_gap`: run designs in order of `gap`, so that the impact-heavy ones start
      early; results come back in input order regardless.
    - `force_table`: a `ForceTable` of one round, the breech force of every design
      (replacing the impulse or pulse).
    - `devices`, `workers`: each chunk is split into `workers` interleaved parts (default
      `default_workers`: one per device, and on CPU one per core), each run from its own
      thread on one of `devices` (default: all local devices).
    - `store`: the path of an SQLite file that keeps the results (`docs/campaigns.md`).
      Each chunk is committed as it finishes; running the same sweep with the same store
      again resumes it (finished chunks are read, not solved again; the results equal
      an uninterrupted run's, bit for bit, since the chunks are cut as when the store was
      made). A store made by another sweep or a study is refused with `ParameterError`.
    - `client`: a `dask.distributed.Client`: each chunk is a task on its cluster's
      workers (each solving it on its own devices, in `workers` parts), and the results
      come back here (and into the store) as each finishes. A chunk whose worker dies is
      run again on another; the results equal those of a run in this process.

    **Returns:** `SweepResult`. A failed solve never aborts the sweep: its peaks are NaN
    and `status` says why (`SweepResult.failures()`).

    **Raises:** `ParameterError` for an unknown name or a bad value (naming the point's
    index) before anything is compiled.
    """
    # Every argument, by name, as `_sweep` takes them (nothing else is defined yet).
    return _sweep(True, **locals())


class StoredSweep(NamedTuple):
    """What `sweep_to_store` returns: the sweep's results are in its store, not in memory.

    - `path`: the store; `designs`: how many designs the sweep has, `stored` of them read
      from the store (a resumed sweep) rather than solved in this run, `failed` of them
      failed (their peaks NULL, their `status` says why); `seconds`: this run's wall time.
    """

    path: Path
    designs: int
    stored: int
    failed: int
    seconds: float

    def load(self) -> SweepResult:
        """The results as a `SweepResult` (`load_sweep`): every design in memory."""
        return load_sweep(self.path)

    def lowest(self, metric: str = "peak_anchoring_force") -> dict[str, float] | None:
        """The design with the lowest `metric` (a `PEAK_FIELDS` name) of those whose solve
        succeeded, as its store row by column name (None if none did), found by SQLite."""
        if metric not in PEAK_FIELDS:
            raise ParameterError(
                f"lowest: unknown peak {metric!r}; known: {', '.join(PEAK_FIELDS)}"
            )
        return lowest_row(self.path, PEAK_FIELDS[metric], int(status_codes(Status.ok)))


def sweep_to_store(designs, store: str | os.PathLike, **kwargs: Any) -> StoredSweep:
    """`sweep(designs, store=store, **kwargs)`, streamed: each chunk's results go to the
    store and are not kept here, so the sweep's memory does not grow with its results
    (only with the designs given). For campaigns too big to hold (`docs/campaigns.md`);
    `StoredSweep.load()` or `load_sweep` reads the results back, and pandas or any
    SQLite reader reads the store without this project. Resumes as `sweep` does.

    **Arguments:** `designs` and the keyword arguments of `sweep`; `store` is required.

    **Returns:** `StoredSweep`.
    """
    # `sweep`'s defaults, and its refusal of an unknown or repeated argument.
    arguments = inspect.signature(sweep).bind(designs, store=store, **kwargs)
    arguments.apply_defaults()
    return _sweep(False, **arguments.arguments)


def load_sweep(store: str | os.PathLike) -> SweepResult:
    """The results of a finished sweep, read from its store (`sweep --store`,
    `sweep_to_store`), in input order. `values` holds the parameters the sweep was given
    (not the defaults of the others); `stored` is every design.

    **Raises:** `ParameterError` for a file that is not a sweep's store, or a sweep that
    has not finished (run it again with its store to finish it)."""
    meta, points, data = read_sweep_store(store)
    order = np.argsort(points)
    data = {name: column[order] for name, column in data.items()}
    description = json.loads(meta["description"])
    wrt = description.get("wrt") or []
    gradients = None
    if wrt:
        gradients = {m: {w: data[gradient_key(m, w)] for w in wrt} for m in METRICS}
    return SweepResult(
        values={name: data[name] for name in description["names"]},
        peaks={field: data[key] for field, key in PEAK_FIELDS.items()},
        status=status_item(data["status_code"]),
        gradients=gradients,
        seconds=float(meta["seconds"]),
        stored=len(points),
    )


def _sweep(
    in_memory: bool,
    designs,
    *,
    smoothing: Smoothing,
    options: SolverOptions | None,
    wrt: Sequence[str] | None,
    chunk_size: int,
    lanes: int,
    progress: bool | None,
    sort_by_gap: bool,
    devices: Sequence[Any] | None,
    workers: int | None,
    force_table: ForceTable | None,
    store: str | os.PathLike | None,
    client: Any,
) -> Any:
    """`sweep` (`in_memory`), or `sweep_to_store`: the results in the store only."""
    if not in_memory and store is None:
        raise ParameterError("a sweep whose results are not kept in memory needs a store")
    wrt = tuple(wrt) if wrt else None
    options = options or (GRADIENT_OPTIONS if wrt else SolverOptions())
    columns = None if isinstance(designs, Grid) else _as_columns(designs)  # validated
    if columns is None:
        names, n = designs.names, len(designs)
    else:
        names, n = list(columns), len(next(iter(columns.values())))
    if in_memory:  # the results of every design, and their copies on the way
        outputs = len(PEAK_FIELDS) + 1 + len(METRICS) * len(wrt or ())
        check_memory(
            n, 8 * 3 * (len(names) + outputs), "a sweep in memory",
            "keep the results in a store instead (--store FILE.sqlite on the command line "
            "without --out and --json, rj.sweep_to_store in Python), or sweep fewer designs",
        )  # fmt: skip
    if columns is None:
        source = _GridColumns(designs, options, wrt, force_table)
    else:
        source = _Columns(columns, options, wrt, force_table)

    devices = list(devices) if devices is not None else jax.local_devices()
    plan = _plan(workers or default_workers(devices), lanes, chunk_size, sort_by_gap)
    # By default a progress line for more than one chunk, and for every campaign (store).
    shown = progress if progress is not None else (n > _per_chunk(plan) or store is not None)
    store_ = None
    if store is not None:
        store_ = _open_store(store, source, smoothing, options, wrt, force_table, plan, progress)
    try:  # the store (and its writer lock) is closed whatever happens from here
        return _run_sweep(
            in_memory, source, store, store_, plan, smoothing, options, wrt, devices, client,
            progress, shown,
        )  # fmt: skip
    finally:
        if store_ is not None:
            store_.close()


def _run_sweep(
    in_memory, designs, store, store_, plan, smoothing, options, wrt, devices, client,
    progress, shown,
):  # fmt: skip
    """`_sweep` once its store is open: resume from it, solve the rest, return."""
    n = designs.count
    if store_ is not None:
        plan = store_.plan
        if (dropped := store_.drop_incomplete()) and progress is not False:
            print(
                f"sweep: {store} had chunks with rows missing or doubled ({dropped} designs "
                "dropped): those chunks are solved again",
                file=sys.stderr,
            )

    names = list(PEAK_FIELDS.values()) + [gradient_key(m, w) for m in METRICS for w in wrt or ()]
    out: dict[str, np.ndarray] = {}
    if in_memory:
        out = {name: np.zeros(n) for name in names}
        out["status_code"] = np.zeros(n, dtype=np.int32)
    stored = store_.done() if store_ is not None else {}
    already = sum(stored.values())
    if store_ is not None:
        if in_memory:
            points, data = store_.read(stored)
            for name in out:
                out[name][points] = data[name]
        if already and progress is not False:
            print(
                f"sweep: resuming from {store}: {already} of {n} designs "
                f"({len(stored)} chunk{'s' * (len(stored) != 1)}) already done",
                file=sys.stderr,
            )
    bar = Progress("sweep", n, "designs", shown, already=already)
    todo = designs.chunks(plan, stored)
    solved = _solved_chunks(todo, smoothing, options, wrt, devices, plan, client)
    for chunk, chunk_columns, chunk_seconds in solved:
        for name, column in chunk_columns.items() if in_memory else ():
            out[name][chunk.points] = column
        if store_ is not None:
            # About 0.1 s per 16,384 designs, against about 1.4 s to solve them.
            given = designs.given(chunk.points)
            messages = status_messages(status_item(chunk_columns["status_code"]))
            store_.commit(chunk.key, chunk.points, chunk_columns | given, messages, chunk_seconds)
        bar.update(bar.done + len(chunk.points))
    if store_ is not None:
        store_.close()  # before the store is read back below
    if not in_memory:
        assert store is not None
        failures = store_failures(store)
        failed = sum(failures.values())
        if failed and progress is not False:
            print(
                f"sweep: {failed} of {n} designs failed ({'; '.join(sorted(failures))}): "
                f"their peaks are NULL in {store} and their status says why",
                file=sys.stderr,
            )
        return StoredSweep(Path(store), n, already, failed, bar.elapsed)
    columns = designs.all_columns()
    values: dict[str, np.ndarray] = {}
    for indices, given in designs.structures(columns):
        for name, column in _group_values(given).items():
            values.setdefault(name, np.full(n, np.nan))[indices] = column
    seconds = bar.elapsed
    # Every requested value as given (absorber parameters of m = 0 points included).
    values = {name: v for name, v in values.items() if not np.all(np.isnan(v))}
    values |= columns

    codes = out["status_code"]
    peaks = {field: out[key] for field, key in PEAK_FIELDS.items()}
    gradients = None
    if wrt:
        gradients = {name: {w: out[gradient_key(name, w)] for w in wrt} for name in METRICS}
    status = status_item(codes)
    failed = codes != status_codes(Status.ok)
    if failed.any() and progress is not False:  # progress=False: the caller reports
        reasons = sorted(set(status_messages(status_item(codes[failed]))))
        print(
            f"sweep: {int(failed.sum())} of {n} designs failed ({'; '.join(reasons)}): "
            "their peaks are NaN and their status says why",
            file=sys.stderr,
        )
    return SweepResult(
        values=values,
        peaks=peaks,
        status=status,
        gradients=gradients,
        seconds=seconds,
        stored=already,
    )


def sweep_grid(
    axes: Mapping[str, Sequence[float]], fixed: Mapping[str, float] | None = None, **kwargs
) -> SweepResult:
    """`sweep` over the cartesian product of `axes` (a `Grid`); the result knows its
    `swept` names and `grid_shape`."""
    designs = Grid(axes, fixed)
    result = sweep(designs, **kwargs)
    result.swept = tuple(axes)
    result.grid_shape = designs.shape
    return result
