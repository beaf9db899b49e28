"""Vectorised sweeps: many designs in vmapped, chunked, device-sharded batches."""

from __future__ import annotations

import dataclasses
import itertools
import os
import sys
import time
from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from ._gradients import GRADIENT_OPTIONS, _check_wrt, _peak_gradients_batch_jit
from ._params import (
    PARAMETER_NAMES,
    ParameterError,
    RecoilParams,
    Smoothing,
    SolverOptions,
    params_from_values,
    params_to_values,
)
from ._solve import PEAK_KEYS, Status, _peaks_batch_jit

_METRIC_FIELDS = {  # gradient key -> PeakGradients field
    "peak_displacement_m": "peak_displacement",
    "peak_anchoring_force_N": "peak_anchoring_force",
    "peak_contact_force_N": "peak_contact_force",
    "min_stroke_m": "min_stroke",
    "max_stroke_m": "max_stroke",
}


@dataclasses.dataclass
class SweepResult:
    """Results of a sweep, one entry per design, in input order (NumPy arrays, shape
    `(n,)`).

    - `values`: every parameter of every design, by flat name (`m = 0`: no absorber).
    - `peaks`: the peaks by `simulate --json` key (`peak_anchoring_force_N`, ...). Points
      whose solve failed hold NaN there, and say why in `status`.
    - `status`: `Status` codes; `messages()` gives the reasons.
    - `gradients`: with `wrt`, `{peak key: {parameter: (n,) derivative}}`, else None.
    - `swept`, `grid_shape`: for a cartesian grid, the swept names and the grid's shape
      (`reshape` the arrays to it, C order over `swept`).
    """

    values: dict[str, np.ndarray]
    peaks: dict[str, np.ndarray]
    status: np.ndarray
    gradients: dict[str, dict[str, np.ndarray]] | None = None
    swept: tuple[str, ...] = ()
    grid_shape: tuple[int, ...] | None = None
    seconds: float = 0.0

    def __len__(self) -> int:
        return int(self.status.shape[0])

    @property
    def ok(self) -> np.ndarray:
        return self.status == Status.OK

    def messages(self) -> list[str]:
        return [Status.message(code) for code in self.status]

    def failures(self) -> list[tuple[int, str]]:
        """`(index, reason)` of every failed point."""
        return [(int(i), Status.message(self.status[i])) for i in np.flatnonzero(~self.ok)]

    def records(self, model: str = "smoothed") -> list[dict]:
        """One dict per point, in input order, with the keys of `recoil-jax simulate
        --json`: the peaks (None where the solve failed), `status` ("ok" or the reason),
        `model`, `parameters`; with gradients also `gradients` ({peak: {param: d}})."""
        out = []
        for i in range(len(self)):
            ok = bool(self.ok[i])
            record = {key: None if not ok else (int(v[i]) if key == "num_steps"
                                                else float(v[i]))
                      for key, v in self.peaks.items()}
            record["status"] = Status.message(self.status[i])
            record["model"] = model
            record["parameters"] = {name: float(v[i]) for name, v in self.values.items()}
            if self.gradients:
                record["gradients"] = {
                    key: {name: float(v[i]) if ok else None for name, v in by.items()}
                    for key, by in self.gradients.items()}
            out.append(record)
        return out


def _as_columns(designs) -> dict[str, np.ndarray]:
    if isinstance(designs, Mapping):
        columns = {k: np.atleast_1d(np.asarray(v, dtype=float)) for k, v in designs.items()}
    else:
        designs = list(designs)
        if not designs:
            raise ParameterError("no designs to sweep")
        names = sorted({k for d in designs for k in d})
        defaults = params_to_values(RecoilParams())
        columns = {n: np.array([float(d.get(n, defaults[n])) for d in designs]) for n in names}
    lengths = {len(v) for v in columns.values()}
    if len(lengths) > 1:
        raise ParameterError(f"sweep columns have different lengths: {sorted(lengths)}")
    unknown = sorted(set(columns) - set(PARAMETER_NAMES))
    if unknown:
        raise ParameterError(
            f"unknown parameter(s) {', '.join(unknown)}; known: {', '.join(PARAMETER_NAMES)}")
    return columns


def batch_params(designs) -> tuple[RecoilParams, dict[str, np.ndarray]]:
    """Designs (a list of `{name: value}` dicts, or `name -> (n,)` columns) as one
    `RecoilParams` whose every leaf has shape `(n,)` (names not given take the paper's
    values), ready for `jax.vmap(..., in_axes=0)`; also returns the flat columns. Every
    value is validated (a bad one raises `ParameterError` naming its index). `m = 0` in
    every design is the simplified model; mixing it with `m > 0` is an error."""
    columns = _as_columns(designs)
    n = len(next(iter(columns.values())))
    simplified = "m" in columns and np.all(columns["m"] == 0)
    if "m" in columns and np.any(columns["m"] == 0) and not simplified:
        raise ParameterError(
            "m = 0 (simplified model) and m > 0 cannot be mixed in one sweep; sweep them "
            "separately")
    absorber_free = ("gap", "k_r", "c_r") if simplified else ()
    defaults = params_to_values(params_from_values({"m": 0.0} if simplified else {}))
    values = {k: np.full(n, float(np.asarray(v))) for k, v in defaults.items()}
    values.update(columns)
    values = {k: v for k, v in values.items() if k not in absorber_free}
    return params_from_values(values), values


def shard_batch(tree, devices: Sequence[jax.Device] | None = None):
    """Place a pytree whose leaves have a leading batch axis on `devices` (default: all
    local devices), split along that axis. The batch must divide evenly."""
    devices = list(devices) if devices is not None else jax.local_devices()
    mesh = Mesh(np.array(devices), ("batch",))
    return jax.device_put(tree, NamedSharding(mesh, PartitionSpec("batch")))


def grid(axes: Mapping[str, Sequence[float]], fixed: Mapping[str, float] | None = None):
    """Cartesian product of `axes` (name -> values), C order, plus `fixed` values:
    returns `(columns, shape)` for `sweep`."""
    names = list(axes)
    arrays = [np.asarray(axes[n], dtype=float).reshape(-1) for n in names]
    points = np.array(list(itertools.product(*arrays)), dtype=float).reshape(-1, len(names))
    columns = {n: points[:, j] for j, n in enumerate(names)}
    for name, value in (fixed or {}).items():
        if name in columns:
            raise ParameterError(f"{name} is both swept and fixed")
        columns[name] = np.full(points.shape[0], float(value))
    return columns, tuple(len(a) for a in arrays)


class _Progress:
    def __init__(self, total: int, enabled: bool, stream=None):
        self.total, self.enabled = total, enabled
        self.stream = stream or sys.stderr
        self.start = time.perf_counter()
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()

    def update(self, done: int) -> None:
        if not self.enabled:
            return
        elapsed = time.perf_counter() - self.start
        rate = done / elapsed if elapsed > 0 else 0.0
        left = (self.total - done) / rate if rate > 0 else float("nan")
        width = 30
        filled = int(width * done / self.total)
        line = (f"sweep [{'#' * filled}{'.' * (width - filled)}] {done}/{self.total} designs, "
                f"{elapsed:.1f} s, {rate:.0f}/s, ~{left:.0f} s left")
        end = "\r" if self.tty and done < self.total else "\n"
        print(line, end=end, file=self.stream, flush=True)


def default_workers(devices: Sequence[jax.Device]) -> int:
    """Parts a sweep chunk is split into: one per device, and on CPU at least one per
    core this process may use. One XLA CPU program keeps about one core busy, and
    programs called from different threads run at the same time."""
    if all(d.platform == "cpu" for d in devices):
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (
            os.cpu_count() or 1)
        return len(devices) * max(1, -(-cores // len(devices)))
    return len(devices)


def _run_chunk(batch: RecoilParams, smoothing, options, wrt, devices, lanes: int,
               workers: int):
    """Run one chunk: split along the batch into `workers` equal, interleaved parts
    (each with the same mix of designs), each through the queued stepping loop (`lanes`
    designs in flight) on device `i % len(devices)`, from its own thread."""
    size = jax.tree.leaves(batch)[0].shape[0] // workers
    # At least 16 designs per lane: the slowest designs take ~7x the mean number of
    # steps, and with fewer per lane the batch idles while they finish (measured: 4096
    # Jacobians ran 2.5x faster with 128 lanes per part than with 512).
    lanes = min(lanes, max(32, size // 16))

    def run(i):
        part = jax.device_put(jax.tree.map(lambda x: x[i::workers], batch),
                              devices[i % len(devices)])
        if wrt:
            out = _peak_gradients_batch_jit(part, smoothing, options, wrt, lanes)
        else:
            out = _peaks_batch_jit(part, smoothing, options, lanes)
        return jax.tree.map(np.asarray, out)

    with ThreadPoolExecutor(workers) as pool:
        outputs = list(pool.map(run, range(workers)))
    # Undo the interleaving: design j of part i is entry i + j * workers of the chunk.
    return jax.tree.map(
        lambda *xs: np.stack(xs, axis=1).reshape(-1, *xs[0].shape[1:]), *outputs)


def sweep(
    designs,
    *,
    smoothing: Smoothing = Smoothing(),
    options: SolverOptions | None = None,
    wrt: Sequence[str] | None = None,
    chunk_size: int = 16384,
    lanes: int = 1024,
    progress: bool | None = None,
    sort_by_gap: bool = True,
    devices: Sequence[jax.Device] | None = None,
    workers: int | None = None,
) -> SweepResult:
    """Peaks (and, with `wrt`, their gradients) of many designs.

    - `designs`: a list of `{name: value}` dicts, or a mapping `name -> (n,) array`
      (e.g. from `grid`). Names not given take the paper's values; `m = 0` (every point)
      is the simplified model.
    - Every value is validated before anything is compiled; a bad point raises
      `ParameterError` naming its index.
    - Designs run `chunk_size` at a time (the last chunk is padded, so nothing
      recompiles), split into `workers` equal, interleaved parts (default
      `default_workers`: one per device, and on CPU one per core), each run from its own
      thread on one of `devices` (default: all local devices).
    - In each part `lanes` designs (capped at 1/16 of the part, but at least 32) are in
      flight in one vmapped stepping loop, and a lane takes the next design as soon as
      its own has finished: a plain `vmap` runs every design for as many steps as the
      slowest in the batch needs. Designs are sorted by `gap` first, so the impact-heavy ones start
      early; results come back in input order.
    - Each point carries a status; a failed solve never aborts the sweep and its peaks
      are NaN, flagged in `status` (see `SweepResult.failures()`).
    - `progress`: a progress line on stderr (default: when there is more than one chunk).
    - `options`: default `SolverOptions()`, or `GRADIENT_OPTIONS` with `wrt`.
    """
    wrt = tuple(wrt) if wrt else None
    options = options or (GRADIENT_OPTIONS if wrt else SolverOptions())
    full, values = batch_params(designs)  # validates every point, before any compilation
    n = len(values["M"])
    simplified = full.absorber is None
    if wrt:
        _check_wrt(full, wrt)

    order = np.argsort(values["gap"], kind="stable") if (
        sort_by_gap and not simplified) else np.arange(n)
    devices = list(devices) if devices is not None else jax.local_devices()
    workers = workers or default_workers(devices)
    if workers < 1:
        raise ParameterError(f"workers = {workers} is invalid: valid >= 1")
    chunk = max(workers, chunk_size - chunk_size % workers)
    chunk = min(chunk, -(-n // workers) * workers)  # no bigger than needed
    show = progress if progress is not None else n > chunk
    bar = _Progress(n, show)

    outputs = []
    start = time.perf_counter()
    for begin in range(0, n, chunk):
        index = order[begin:begin + chunk]
        padded = np.concatenate([index, np.full(chunk - len(index), index[-1])])
        batch = jax.tree.map(lambda leaf, p=padded: np.asarray(leaf)[p], full)
        result = _run_chunk(batch, smoothing, options, wrt, devices, lanes, workers)
        result = jax.tree.map(lambda x, k=len(index): x[:k], result)
        outputs.append(result)
        bar.update(min(begin + chunk, n))
    seconds = time.perf_counter() - start

    inverse = np.empty(n, dtype=int)
    inverse[order] = np.arange(n)

    chunk_peaks = [o[0] if wrt else o for o in outputs]

    def gather(chunks, field):
        return np.concatenate([np.asarray(getattr(c, field)) for c in chunks])[inverse]

    status = gather(chunk_peaks, "status")
    failed = status != Status.OK
    peaks = {}
    for key, field in PEAK_KEYS.items():
        column = gather(chunk_peaks, field)
        if key != "num_steps":
            column = np.where(failed, np.nan, column)
        peaks[key] = column
    gradients = None
    if wrt:
        gradients = {}
        for key, field in _METRIC_FIELDS.items():
            matrix = gather([o[1] for o in outputs], field)
            gradients[key] = {name: np.where(failed, np.nan, matrix[:, j])
                              for j, name in enumerate(wrt)}
    if failed.any():
        reasons = {Status.message(c) for c in status[failed]}
        print(f"sweep: {int(failed.sum())} of {n} designs failed ({'; '.join(reasons)}); "
              "see SweepResult.failures()", file=sys.stderr)
    return SweepResult(values=values, peaks=peaks, status=status, gradients=gradients,
                       seconds=seconds)


def sweep_grid(axes: Mapping[str, Sequence[float]], fixed: Mapping[str, float] | None = None,
               **kwargs) -> SweepResult:
    """`sweep` over the cartesian product of `axes` (see `grid`); the result knows its
    `swept` names and `grid_shape`."""
    columns, shape = grid(axes, fixed)
    result = sweep(columns, **kwargs)
    result.swept = tuple(axes)
    result.grid_shape = shape
    return result
