"""The sweep's entry points: `sweep` (the results in memory), `sweep_to_store` (in its
store only) and `sweep_grid`. Each checks its designs, makes its settings once
(`SweepSettings`), opens its store (`open_campaign`), solves the chunks the store does
not hold, and says how many designs failed and why."""

from __future__ import annotations

import contextlib
import dataclasses
import inspect
import os
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import jax
import numpy as np

from .._campaigns.opener import open_campaign
from .._campaigns.progress import Progress
from .._campaigns.store import SweepStore, campaign_identity
from .._campaigns.sweep_reader import store_failures
from .._model.derivatives import GRADIENT_OPTIONS
from .._model.metrics import METRICS, PEAK_FIELDS, gradient_key
from .._model.params import ForceTable
from .._model.registry import ParameterError
from .._model.settings import Smoothing, SolverOptions
from .._model.status import Status, status_codes, status_item, status_messages
from .batches import as_columns, group_values
from .chunks import ColumnDesigns, GridDesigns, per_chunk
from .dispatch import solved_chunks
from .grid import Grid
from .memory import check_memory, default_workers
from .result import StoredSweep, SweepResult
from .settings import CHUNK_SIZE, DEFAULT_LANES, SweepSettings, make_plan

__all__ = ["sweep", "sweep_grid", "sweep_to_store"]


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
    index) before anything is compiled; with `client`, `ImportError` naming the module
    and the workers where a worker cannot import the module an added part (its `ROWS`)
    is sent by name from, before it is sent a chunk that needs it (a part defined in a
    notebook, a script's `__main__` or a function is sent with the sweep).
    """
    # Every argument, by name, as `_sweep` takes them (nothing else is defined yet).
    return _sweep(True, **locals())


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
    """`sweep` (`in_memory`), or `sweep_to_store`: the results in the store only. The
    designs are checked first, then the settings made, once, and handed down."""
    if not in_memory and store is None:
        raise ParameterError("a sweep whose results are not kept in memory needs a store")
    wrt = tuple(wrt) if wrt else None
    options = options or (GRADIENT_OPTIONS if wrt else SolverOptions())
    source = _designs(designs, in_memory, options, wrt, force_table)
    devices = tuple(devices) if devices is not None else tuple(jax.local_devices())
    settings = SweepSettings(
        smoothing=smoothing, options=options, wrt=wrt, force_table=force_table,
        plan=make_plan(workers or default_workers(devices), lanes, chunk_size, sort_by_gap),
        devices=devices, client=client, progress=progress, store=store, in_memory=in_memory,
    )  # fmt: skip
    # By default a progress line for more than one chunk, and for every campaign (store).
    many = source.count > per_chunk(settings.plan)
    shown = progress if progress is not None else (many or store is not None)
    with _open_store(source, settings) as store_:  # closed whatever happens
        return _run_sweep(source, settings, store_, shown)


def _designs(designs, in_memory: bool, options, wrt, force_table) -> ColumnDesigns | GridDesigns:
    """The sweep's designs (columns, or a `Grid` made a block at a time), checked before
    anything is compiled; for a sweep in memory, with room for its results.

    **Raises:** `ParameterError` for an unknown name, a bad value (naming the point's
    index), or results that would not fit in memory."""
    columns = None if isinstance(designs, Grid) else as_columns(designs)  # validated
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
        return GridDesigns(designs, options, wrt, force_table)
    return ColumnDesigns(columns, options, wrt, force_table)


def _open_store(
    designs: ColumnDesigns | GridDesigns, settings: SweepSettings
) -> contextlib.AbstractContextManager[SweepStore | None]:
    """The store of this sweep (`open_campaign`; None without one): made, or checked to
    be this sweep's, whose plan then replaces the sweep's, so that the chunks are those
    of the run that made it."""
    wrt = settings.wrt or ()
    names = [*designs.names, *PEAK_FIELDS.values()]
    names += [gradient_key(m, w) for m in METRICS for w in wrt]

    def identity() -> str:  # the parts and their order of every store made before
        return campaign_identity(
            "sweep", designs.identity(), settings.smoothing, settings.options, wrt,
            settings.force_table,
        )  # fmt: skip

    return open_campaign(
        SweepStore, settings.store, label="sweep", identity=identity, total=designs.count,
        plan=settings.plan, columns=names, progress=settings.progress,
        description={"designs": designs.count, "names": sorted(designs.names), "wrt": list(wrt)},
    )  # fmt: skip


def _run_sweep(
    designs: ColumnDesigns | GridDesigns,
    settings: SweepSettings,
    store_: SweepStore | None,
    shown: bool | None,
) -> SweepResult | StoredSweep:
    """`_sweep` once its store is open: resume from it, solve the rest, return."""
    if store_ is not None:  # the chunks of the run that made the store
        settings = dataclasses.replace(settings, plan=store_.plan)
    stored = store_.done() if store_ is not None else {}
    already = sum(stored.values())
    out = _outputs(designs.count, settings.wrt, store_, stored) if settings.in_memory else {}
    bar = Progress("sweep", designs.count, "designs", shown, already=already)
    for chunk, columns, seconds in solved_chunks(designs.chunks(settings.plan, stored), settings):
        for name, column in columns.items() if settings.in_memory else ():
            out[name][chunk.points] = column
        if store_ is not None:
            # About 0.1 s per 16,384 designs, against about 1.4 s to solve them.
            given = designs.given(chunk.points)
            messages = status_messages(status_item(columns["status_code"]))
            store_.commit(chunk.key, chunk.points, columns | given, messages, seconds)
        bar.update(bar.done + len(chunk.points))
    if store_ is not None:
        store_.close()  # before the store is read back below
    if not settings.in_memory:
        return _stored_sweep(designs.count, settings, already, bar)
    return _sweep_result(designs, settings, out, already, bar)


def _outputs(n: int, wrt, store_: SweepStore | None, stored) -> dict[str, np.ndarray]:
    """A sweep's results in memory, `(n,)` per column of `sweep.csv` (and `status_code`),
    with the rows of the `stored` chunks read from the store."""
    names = [*PEAK_FIELDS.values(), *(gradient_key(m, w) for m in METRICS for w in wrt or ())]
    out: dict[str, np.ndarray] = {name: np.zeros(n) for name in names}
    out["status_code"] = np.zeros(n, dtype=np.int32)
    if store_ is not None:
        points, data = store_.read(stored)
        for name in out:
            out[name][points] = data[name]
    return out


def _stored_sweep(n: int, settings: SweepSettings, already: int, bar: Progress) -> StoredSweep:
    """A finished `sweep_to_store`: what its store holds, and a line on stderr saying how
    many designs failed and why (unless `progress` is False)."""
    store = settings.store
    assert store is not None
    failures = store_failures(store)
    failed = sum(failures.values())
    if failed and settings.progress is not False:
        print(
            f"sweep: {failed} of {n} designs failed ({'; '.join(sorted(failures))}): "
            f"their peaks are NULL in {store} and their status says why",
            file=sys.stderr,
        )
    return StoredSweep(Path(store), n, already, failed, bar.elapsed)


def _sweep_result(
    designs: ColumnDesigns | GridDesigns,
    settings: SweepSettings,
    out: dict[str, np.ndarray],
    already: int,
    bar: Progress,
) -> SweepResult:
    """A finished `sweep`'s `SweepResult` from its results `out` (`_outputs`), and a line
    on stderr saying how many designs failed and why (unless `progress` is False: the
    caller reports)."""
    n = designs.count
    values = _given_values(designs)
    seconds = bar.elapsed
    codes = out["status_code"]
    peaks = {field: out[key] for field, key in PEAK_FIELDS.items()}
    gradients = None
    if settings.wrt:
        gradients = {m: {w: out[gradient_key(m, w)] for w in settings.wrt} for m in METRICS}
    status = status_item(codes)
    failed = codes != status_codes(Status.ok)
    if failed.any() and settings.progress is not False:
        reasons = sorted(set(status_messages(status_item(codes[failed]))))
        print(
            f"sweep: {int(failed.sum())} of {n} designs failed ({'; '.join(reasons)}): "
            "their peaks are NaN and their status says why",
            file=sys.stderr,
        )
    return SweepResult(values, peaks, status, gradients, seconds=seconds, stored=already)


def _given_values(designs: ColumnDesigns | GridDesigns) -> dict[str, np.ndarray]:
    """Every parameter of the designs' groups, `(n,)` each (NaN where a design's group
    lacks it; a parameter no design has is left out), and every value as given
    (absorber parameters of `m = 0` points included)."""
    n = designs.count
    columns = designs.all_columns()
    values: dict[str, np.ndarray] = {}
    for indices, given in designs.structures(columns):
        for name, column in group_values(given).items():
            values.setdefault(name, np.full(n, np.nan))[indices] = column
    values = {name: v for name, v in values.items() if not np.all(np.isnan(v))}
    return values | columns
