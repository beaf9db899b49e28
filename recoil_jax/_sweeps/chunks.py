"""A sweep's designs as the chunks it solves: by structure (`Group`: one compiled program
each, checked before anything is compiled), cut into chunks of one compiled size
(`Chunk`), from designs given as columns (`ColumnDesigns`) or as a grid made a block at a
time (`GridDesigns`)."""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from typing import Any, NamedTuple

import jax
import numpy as np

from .._model.derivatives import check_wrt
from .._model.parameter_table import PARAMETERS
from .._model.params import ForceTable, RecoilParams, params_from_values
from .._model.settings import SolverOptions, check_load_fits, default_end_time
from .batches import as_columns, group_values, structure_groups, with_table
from .grid import Grid

__all__ = ["SHARED_CHUNK", "Chunk", "ColumnDesigns", "GridDesigns", "Group", "per_chunk"]

#: Sweeps of up to this many designs run in one chunk of this size (per structure, the
#: same compiled program); only the real designs are solved.
SHARED_CHUNK = 1024


class Group(NamedTuple):
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
        values = group_values({k: v[rows] for k, v in self.columns.items()})
        params = params_from_values(values)
        return params if self.force_table is None else with_table(params, self.force_table)


#: Designs per slice when a group's end times and loads are checked: the checks never
#: hold every parameter of every design at once.
_CHECK_SLICE = 65536


def _groups(
    columns, options: SolverOptions, wrt, force_table, labels=None, every_wrt: bool = True
) -> list[Group]:
    """The designs by structure (`structure_groups`), each with its end times, its loads
    checked to fit them and the `wrt` it has; raises `ParameterError` before anything is
    compiled. `labels`: the designs' indices in the sweep (default: their positions; a
    grid's block or probe gives its own); `every_wrt`: check that each of `wrt` is a
    parameter of some group (a grid checks this once, on its `Grid.probe`)."""
    groups = []
    for indices, given in structure_groups(columns, labels):
        indices = indices if labels is None else np.asarray(labels)[indices]
        given = dict(given)
        t1 = given.pop("t1", None)
        group = Group(indices, given, np.zeros(0), None, True, force_table)
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


def _has(params: RecoilParams, name: str) -> bool:
    """Whether `params` has the real-valued parameter `name` (its group, its knot)."""
    p = PARAMETERS[name] if name in PARAMETERS else None
    if p is None or p.integer:
        return False
    module = params.part(p.group)
    return module is not None and (p.index is None or p.index < module.knots)


class Chunk(NamedTuple):
    """One compiled call's worth of a group's designs: `key` (in the store), the group,
    `rows` (positions in the group, in solving order) and `size` (the padded batch the
    program is compiled for)."""

    key: str
    group: Group
    rows: np.ndarray
    size: int

    @property
    def points(self) -> np.ndarray:
        """The chunk's designs' indices into the sweep's input."""
        return self.group.indices[self.rows]

    def batch(self) -> tuple[RecoilParams, np.ndarray]:
        """The chunk's designs (NumPy leaves, leading axis `size`) and their end times
        `(size,)`, padded to its compiled size with its last design."""
        rows = self.rows
        padded = np.concatenate([rows, np.full(self.size - len(rows), rows[-1])])
        return jax.tree.map(np.asarray, self.group.params(padded)), self.group.t1[padded]


def per_chunk(plan: dict) -> int:
    """The most designs per chunk: `chunk_size`, a multiple of the workers."""
    workers = plan["workers"]
    return max(workers, plan["chunk_size"] - plan["chunk_size"] % workers)


def _chunks(groups, plan: dict, prefix: str = "", full: bool = False) -> list[Chunk]:
    """The designs cut into chunks, group by group, in solving order (the gap ascending,
    with `sort_by_gap`, so that the impact-heavy designs start early). `prefix` starts
    each key; `full`: every chunk of `per_chunk`'s size (a grid's chunks, which would
    otherwise come in many sizes, each compiled)."""
    workers = plan["workers"]
    out = []
    for number, group in enumerate(groups):
        n = len(group.indices)
        # Without a gap column every design has the default gap: no order to take.
        sort = plan["sort_by_gap"] and group.absorber and "gap" in group.columns
        order = np.argsort(group.columns["gap"], kind="stable") if sort else np.arange(n)
        chunk = per_chunk(plan)
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
            out.append(Chunk(f"{prefix}{number}:{begin}", group, rows, chunk))
    return out


class ColumnDesigns:
    """A sweep's designs given as columns, all in memory (`as_columns`): grouped by
    structure and checked as a whole, chunked group by group."""

    def __init__(self, columns: dict[str, np.ndarray], options, wrt, force_table):
        self.columns = columns
        self.names = list(columns)
        self.count = len(next(iter(columns.values())))
        self.groups = _groups(columns, options, wrt, force_table)

    def identity(self) -> Any:
        """What a store's identity holds of these designs (`campaign_identity`)."""
        return self.columns

    def chunks(self, plan: dict, done: Mapping[str, int]) -> Iterator[Chunk]:
        """The chunks, those in `done` (key -> designs, from the store) left out."""
        return (c for c in _chunks(self.groups, plan) if c.key not in done)

    def given(self, points: np.ndarray) -> dict[str, np.ndarray]:
        """The given columns of the designs at `points` (indices into the sweep)."""
        return {name: values[points] for name, values in self.columns.items()}

    def all_columns(self) -> dict[str, np.ndarray]:
        """Every design's given columns."""
        return self.columns

    def structures(self, columns) -> list[tuple[np.ndarray, dict[str, np.ndarray]]]:
        """`(indices, given columns)` per structure (the groups it was chunked by)."""
        return [(g.indices, g.columns) for g in self.groups]


class GridDesigns:
    """A sweep of a `Grid`: its values checked on its axes and on its `Grid.probe` (before
    anything is compiled), its columns made a block of `per_chunk` designs at a time,
    each block grouped and chunked on its own (so that memory does not grow with the
    grid), in input order."""

    def __init__(self, designs: Grid, options, wrt, force_table):
        for name, values in designs.axes.items():
            as_columns({name: values})  # each value on its own: the checks are elementwise
        probe, labels = designs.probe()  # the fixed values too
        _groups(as_columns(probe.columns()), options, wrt, force_table, labels)
        self.grid, self.names, self.count = designs, designs.names, len(designs)
        self.options, self.wrt, self.force_table = options, wrt, force_table

    def identity(self) -> Any:
        """What a store's identity holds of this grid (`campaign_identity`): its axes in
        their order (it sets which design each index is; a dict's keys are sorted when
        it is flattened) and its fixed values."""
        axes = self.grid.axes
        return ("grid", tuple(axes), tuple(axes.values()), self.grid.fixed)

    def chunks(self, plan: dict, done: Mapping[str, int]) -> Iterator[Chunk]:
        """The chunks, block by block, those in `done` (key -> designs, from the store)
        left out; a block whose every design is stored is not made at all (a resumed
        campaign near its end does not rebuild what it has)."""
        block = per_chunk(plan)
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
        """The columns of the designs at `points` (flat indices into the grid)."""
        return self.grid.columns(points)

    def all_columns(self) -> dict[str, np.ndarray]:
        """Every design's columns, made at once."""
        return self.grid.columns()

    def structures(self, columns) -> list[tuple[np.ndarray, dict[str, np.ndarray]]]:
        """`(indices, given columns)` per structure of `all_columns` (`t1` left out)."""
        return [
            (indices, {name: c for name, c in given.items() if name != "t1"})
            for indices, given in structure_groups(columns)
        ]
