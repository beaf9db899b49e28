"""Vectorised sweeps: many designs in chunked batches, split over threads and devices,
each through the lane scheduler, with a status per point."""

from __future__ import annotations

import dataclasses
import itertools
import os
import sys
from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from ._gradients import GRADIENT_OPTIONS, check_wrt, peak_gradients_batch
from ._metrics import METRICS, PEAK_FIELDS
from ._params import (
    PARAMETERS,
    T1_LIMITS,
    ParameterError,
    RecoilParams,
    Smoothing,
    SolverOptions,
    check_value,
    default_end_time,
    params_from_values,
    params_to_values,
)
from ._progress import Progress
from ._solve import peaks_batch
from ._status import Status, status_codes, status_item, status_messages

__all__ = [
    "SweepResult",
    "batch_params",
    "default_workers",
    "grid",
    "shard_batch",
    "sweep",
    "sweep_grid",
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
    """

    values: dict[str, np.ndarray]
    peaks: dict[str, np.ndarray]
    status: Any
    gradients: dict[str, dict[str, np.ndarray]] | None = None
    swept: tuple[str, ...] = ()
    grid_shape: tuple[int, ...] | None = None
    seconds: float = 0.0

    def __len__(self) -> int:
        return int(status_codes(self.status).shape[0])

    @property
    def ok(self) -> np.ndarray:
        return np.asarray(self.status == Status.ok)

    def messages(self) -> list[str]:
        return status_messages(self.status)

    def failures(self) -> list[tuple[int, str]]:
        """`(index, reason)` of every failed point."""
        messages = self.messages()
        return [(int(i), messages[i]) for i in np.flatnonzero(~self.ok)]

    def parameters(self, index: int) -> dict[str, float]:
        """The parameters of point `index`, as `simulate --json` reports them (no
        absorber parameters for the simplified model)."""
        simplified = self.values["m"][index] == 0
        return {
            name: float(v[index])
            for name, v in self.values.items()
            if not (simplified and name in _ABSORBER and name != "m")
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
    dicts take the defaults)."""
    if isinstance(designs, Mapping):
        columns = {k: np.atleast_1d(np.asarray(v, dtype=float)) for k, v in designs.items()}
    else:
        designs = list(designs)
        if not designs:
            raise ParameterError("no designs to sweep")
        names = sorted({k for d in designs for k in d})
        defaults = {name: p.default for name, p in PARAMETERS.items()}
        for name in names:
            if name not in defaults and name not in _SETTINGS:
                _unknown(name)
        if "t1" in names and not all("t1" in d for d in designs):
            raise ParameterError(
                "t1 is given for some points but not all: give it for every point, or for none"
            )
        columns = {
            n: np.array([float(d.get(n, defaults.get(n, np.nan))) for d in designs]) for n in names
        }
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
            check_value(p.owner, name, column, p)
        else:
            _unknown(name)
    return columns


def _unknown(name: str):
    raise ParameterError(
        f"unknown parameter(s) {name}; known: {', '.join(PARAMETERS)} and {', '.join(_SETTINGS)}"
    )


def batch_params(designs) -> tuple[RecoilParams, dict[str, np.ndarray]]:
    """Designs (a list of `{name: value}` dicts, or `name -> (n,)` columns) as one
    `RecoilParams` whose every leaf has shape `(n,)` (names not given take the paper's
    values), ready for `jax.vmap(..., in_axes=0)`; also returns the flat columns. Every
    value is validated (a bad one raises `ParameterError` naming its index). `m = 0` in
    every design is the simplified model; mixing it with `m > 0` in one `RecoilParams` is
    an error (`sweep` runs such designs as two groups)."""
    columns = _as_columns(designs)
    columns.pop("t1", None)
    n = len(next(iter(columns.values())))
    simplified = "m" in columns and np.all(columns["m"] == 0)
    if "m" in columns and np.any(columns["m"] == 0) and not simplified:
        raise ParameterError(
            "m = 0 (simplified model) and m > 0 cannot be mixed in one RecoilParams; "
            "sweep() runs them as two groups"
        )
    defaults = params_to_values(params_from_values({"m": 0.0} if simplified else {}))
    values = {k: np.full(n, float(np.asarray(v))) for k, v in defaults.items()}
    values.update(columns)
    if simplified:
        values = {k: v for k, v in values.items() if k == "m" or k not in _ABSORBER}
    return params_from_values(values), values


def shard_batch(tree, devices: Sequence[Any] | None = None):
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


def _run_chunk(batch: RecoilParams, t1, smoothing, options, wrt, devices, lanes: int, workers: int):
    """Run one chunk: split along the batch into `workers` equal, interleaved parts
    (each with the same mix of designs), each through the queued stepping loop (`lanes`
    designs in flight) on device `i % len(devices)`, from its own thread."""
    size = jax.tree.leaves(batch)[0].shape[0] // workers
    # At least 16 designs per lane: the slowest designs take ~7x the mean number of
    # steps, and with fewer per lane the batch idles while they finish (measured: 4096
    # Jacobians ran 2.5x faster with 128 lanes per part than with 512).
    lanes = min(lanes, max(32, size // 16))

    def run(i):
        part, end = jax.device_put(
            jax.tree.map(lambda x: x[i::workers], (batch, t1)), devices[i % len(devices)]
        )
        if wrt:
            out = peak_gradients_batch(part, end, smoothing, options, wrt, lanes)
        else:
            out = peaks_batch(part, end, smoothing, options, lanes)
        return jax.tree.map(np.asarray, out)

    with ThreadPoolExecutor(workers) as pool:
        outputs = list(pool.map(run, range(workers)))
    # Undo the interleaving: design j of part i is entry i + j * workers of the chunk.
    return jax.tree.map(lambda *xs: np.stack(xs, axis=1).reshape(-1, *xs[0].shape[1:]), *outputs)


def _run_group(
    params: RecoilParams,
    t1: np.ndarray,
    order: np.ndarray,
    smoothing,
    options,
    wrt,
    devices,
    lanes,
    workers,
    chunk_size,
    bar: Progress,
    done: int,
):
    """Solve one group of designs (all with, or all without, an absorber) in the order
    `order`, chunk by chunk; returns `(peaks, gradients)` in the group's input order."""
    n = len(order)
    chunk = max(workers, chunk_size - chunk_size % workers)
    chunk = min(chunk, -(-n // workers) * workers)  # no bigger than needed
    outputs = []
    for begin in range(0, n, chunk):
        index = order[begin : begin + chunk]
        padded = np.concatenate([index, np.full(chunk - len(index), index[-1])])
        batch = jax.tree.map(lambda leaf, p=padded: np.asarray(leaf)[p], params)
        result = _run_chunk(batch, t1[padded], smoothing, options, wrt, devices, lanes, workers)
        outputs.append(jax.tree.map(lambda x, k=len(index): x[:k], result))
        bar.update(done + min(begin + chunk, n))
    inverse = np.empty(n, dtype=int)
    inverse[order] = np.arange(n)
    gathered = jax.tree.map(lambda *xs: np.concatenate(xs)[inverse], *outputs)
    return gathered if wrt else (gathered, None)


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
    devices: Sequence[Any] | None = None,
    workers: int | None = None,
) -> SweepResult:
    """Peaks (and, with `wrt`, their gradients) of many designs.

    **Arguments:**

    - `designs`: a list of `{name: value}` dicts, or a mapping `name -> (n,) array` (e.g.
      from `grid`). Names are flat parameter names, plus `t1` (the end time, per point);
      names not given take the paper's values. `m = 0` is the simplified model, and may be
      mixed with absorbers: the two groups run apart and merge in input order.
    - `smoothing`: the switch widths, shared by every point.
    - `options`: default `SolverOptions()`, or `GRADIENT_OPTIONS` with `wrt`; its `t1`
      applies where the designs do not give one.
    - `wrt`: parameters to differentiate with respect to (forward sensitivities).
    - `chunk_size`: designs per compiled call (the last chunk is padded to the same shape,
      so nothing recompiles).
    - `lanes`: designs in flight per part in the vmapped stepping loop (capped at 1/16 of
      the part, at least 32); a lane takes the next design as soon as its own has
      finished. A plain `vmap` would run every design for as many steps as the slowest.
    - `progress`: a progress line on stderr (default: when there is more than one chunk).
    - `sort_by_gap`: run designs in order of `gap`, so that the impact-heavy ones start
      early; results come back in input order regardless.
    - `devices`, `workers`: each chunk is split into `workers` interleaved parts (default
      `default_workers`: one per device, and on CPU one per core), each run from its own
      thread on one of `devices` (default: all local devices).

    **Returns:** `SweepResult`. A failed solve never aborts the sweep: its peaks are NaN
    and `status` says why (`SweepResult.failures()`).

    **Raises:** `ParameterError` for an unknown name or a bad value (naming the point's
    index) before anything is compiled.
    """
    wrt = tuple(wrt) if wrt else None
    options = options or (GRADIENT_OPTIONS if wrt else SolverOptions())
    columns = _as_columns(designs)  # validates every point, before any compilation
    n = len(next(iter(columns.values())))
    simplified = columns["m"] == 0 if "m" in columns else np.zeros(n, dtype=bool)
    groups = []  # (indices into the input, params, values, end times, wrt)
    for mask in (~simplified, simplified):
        if not mask.any():
            continue
        indices = np.flatnonzero(mask)
        group = {k: v[indices] for k, v in columns.items()}
        params, values = batch_params(group)
        if "t1" in group:
            t1 = group["t1"]
        elif options.t1 is not None:
            t1 = np.full(len(indices), float(options.t1))
        else:
            t1 = np.asarray(default_end_time(params))
        group_wrt = wrt
        if wrt and params.absorber is None:
            group_wrt = tuple(w for w in wrt if w not in _ABSORBER) or None
        elif wrt:
            check_wrt(params, wrt)
        groups.append((indices, params, values, t1, group_wrt))

    devices = list(devices) if devices is not None else jax.local_devices()
    workers = workers or default_workers(devices)
    if workers < 1:
        raise ParameterError(f"workers = {workers} is invalid: valid >= 1")
    bar = Progress(
        "sweep",
        n,
        "designs",
        progress if progress is not None else n > max(workers, chunk_size - chunk_size % workers),
    )

    codes = np.zeros(n, dtype=np.int32)
    peaks = {field: np.zeros(n) for field in PEAK_FIELDS}
    gradients = {name: {w: np.zeros(n) for w in wrt} for name in METRICS} if wrt else None
    values = {name: np.full(n, np.nan) for name in PARAMETERS}
    done = 0
    for indices, params, group_values, t1, group_wrt in groups:
        sort = sort_by_gap and params.absorber is not None
        order = np.argsort(group_values["gap"], kind="stable") if sort else np.arange(len(indices))
        result, grads = _run_group(
            params,
            t1,
            order,
            smoothing,
            options,
            group_wrt,
            devices,
            lanes,
            workers,
            chunk_size,
            bar,
            done,
        )
        done += len(indices)
        codes[indices] = status_codes(result.status)
        for field in PEAK_FIELDS:
            peaks[field][indices] = getattr(result, field)
        if gradients is not None and grads is not None:
            for name in METRICS:
                matrix = getattr(grads, name)
                for j, w in enumerate(grads.wrt):
                    gradients[name][w][indices] = matrix[:, j]
        for name, column in group_values.items():
            values[name][indices] = column
    seconds = bar.elapsed
    # Every requested value as given (absorber parameters of m = 0 points included).
    values = {name: v for name, v in values.items() if not np.all(np.isnan(v))}
    values |= {name: columns[name] for name in columns}

    failed = codes != status_codes(Status.ok)
    for field in PEAK_FIELDS:
        if field != "num_steps":
            peaks[field] = np.where(failed, np.nan, peaks[field])
    if gradients is not None:
        gradients = {
            name: {w: np.where(failed, np.nan, v) for w, v in by.items()}
            for name, by in gradients.items()
        }
    status = status_item(codes)
    if failed.any():
        reasons = sorted(set(status_messages(status_item(codes[failed]))))
        print(
            f"sweep: {int(failed.sum())} of {n} designs failed ({'; '.join(reasons)}); "
            "see SweepResult.failures()",
            file=sys.stderr,
        )
    return SweepResult(
        values=values, peaks=peaks, status=status, gradients=gradients, seconds=seconds
    )


def sweep_grid(
    axes: Mapping[str, Sequence[float]], fixed: Mapping[str, float] | None = None, **kwargs
) -> SweepResult:
    """`sweep` over the cartesian product of `axes` (see `grid`); the result knows its
    `swept` names and `grid_shape`."""
    columns, shape = grid(axes, fixed)
    result = sweep(columns, **kwargs)
    result.swept = tuple(axes)
    result.grid_shape = shape
    return result
