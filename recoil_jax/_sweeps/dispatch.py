"""Where a sweep's chunks are solved: each chunk split into interleaved parts, each part
from its own thread on one of the devices (`solved_chunks`), here or as tasks on the
workers of a Dask cluster; and one chunk's results as columns."""

from __future__ import annotations

import dataclasses
import importlib
import itertools
import sys
import time
from collections.abc import Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import jax
import numpy as np

from .._model.derivatives import peak_gradients_batch
from .._model.forces.family import Part, outside_parts
from .._model.metrics import METRICS, PEAK_FIELDS, gradient_key
from .._model.params import RecoilParams
from .._model.programs import avx2_codegen_set
from .._model.settings import with_default_tolerances
from .._model.solve import peaks_batch
from .._model.status import Status, status_codes
from .chunks import Chunk
from .settings import SweepSettings

__all__ = ["solved_chunks"]


def _run_chunk(batch: RecoilParams, t1, count: int, wrt, settings: SweepSettings):
    """Run one chunk: split along the batch into the plan's `workers` equal, interleaved
    parts (each with the same mix of designs), each through the queued stepping loop
    (the plan's `lanes` designs in flight) on device `i % len(devices)`, from its own
    thread. Only the first `count` designs of the chunk are solved; the rest pad it to
    its compiled shape. `wrt`: the chunk's group's (None: peaks only)."""
    workers, devices = settings.plan["workers"], settings.devices
    size = jax.tree.leaves(batch)[0].shape[0] // workers
    # At least 16 designs per lane: the slowest designs take ~7x the mean number of
    # steps, and with fewer per lane the batch idles while they finish (measured: 4096
    # Jacobians ran 2.5x faster with 128 lanes per part than with 512).
    lanes = min(settings.plan["lanes"], max(32, size // 16))
    # Tolerances as values, also the defaults: one program for any tolerances (the
    # smoothed and the hard-switch model of a structure share it too).
    options = with_default_tolerances(batch, settings.options)
    smoothing = settings.smoothing

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
    # A design without the firing envelope has none of its metrics (NaN), nor a return.
    unsolved = np.isnan(np.asarray(peaks.residual_displacement, dtype=float))
    for field, key in PEAK_FIELDS.items():
        value = np.asarray(getattr(peaks, field), dtype=float)
        if field == "returned":
            value = np.where(unsolved, np.nan, value)
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


def _solve_chunk(batch, t1, count: int, wrt, settings: SweepSettings):
    """Solve the first `count` designs of a padded batch (`wrt`: its group's): `(columns,
    seconds)`, their columns (`_chunk_columns`, with the derivatives of every one of the
    sweep's `wrt`) and the wall time it took."""
    start = time.perf_counter()
    result = _run_chunk(batch, t1, count, wrt, settings)
    result = jax.tree.map(lambda x: x[:count], result)
    return _chunk_columns(result, wrt, settings.wrt), time.perf_counter() - start


def _cache_dir() -> str | None:
    """The folder of this process's persistent compilation cache (None: off)."""
    return jax.config.values.get("jax_compilation_cache_dir")


def _solve_chunk_on_worker(
    batch, t1, count: int, wrt, settings: SweepSettings, cache: str | None, avx2: bool
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
    here = dataclasses.replace(settings, devices=tuple(jax.local_devices()))
    return _solve_chunk(batch, t1, count, wrt, here)


def solved_chunks(
    todo: Iterable[Chunk], settings: SweepSettings
) -> Iterator[tuple[Chunk, dict[str, np.ndarray], float]]:
    """`(chunk, columns, seconds)` for each chunk of `todo` (an iterable, made as it is
    taken) as it finishes: one after the other here, or as Dask tasks on the workers of
    `settings.client` (a chunk whose worker dies is run again elsewhere by Dask)."""
    if settings.client is None:
        for chunk in todo:
            batch, t1 = chunk.batch()
            yield chunk, *_solve_chunk(batch, t1, len(chunk.points), chunk.group.wrt, settings)
        return
    yield from _solved_on_cluster(todo, settings)


def _solved_on_cluster(
    todo: Iterable[Chunk], settings: SweepSettings
) -> Iterator[tuple[Chunk, dict[str, np.ndarray], float]]:
    """`solved_chunks` on a Dask cluster: two chunks per worker thread in flight, the
    rest made here as chunks finish."""
    from distributed import as_completed

    client: Any = settings.client
    shipped = settings.shipped()
    cache = _cache_dir()
    avx2 = avx2_codegen_set()
    futures = {}
    done = as_completed()
    waiting = iter(todo)
    verified: dict[tuple[str, str], set[str]] = {}

    def submit(chunk: Chunk) -> None:
        batch, t1 = chunk.batch()
        _check_importable_on_workers(client, batch, verified)
        future = client.submit(
            _solve_chunk_on_worker, batch, t1, len(chunk.points), chunk.group.wrt, shipped,
            cache, avx2, pure=False, retries=2,
        )  # fmt: skip
        futures[future] = chunk
        done.add(future)

    try:
        # Two chunks per worker thread in flight: the workers never wait, and the designs
        # waiting to be solved stay here, not in the cluster's memory.
        for chunk in itertools.islice(waiting, 2 * max(1, sum(client.nthreads().values()))):
            submit(chunk)
        for future in done:
            chunk = futures.pop(future)
            yield chunk, *future.result()
            following = next(waiting, None)
            if following is not None:
                submit(following)
    finally:
        for future in futures:
            future.cancel()


def _sent_by_reference(cls: type) -> bool:
    """Whether cloudpickle sends the class `cls` by reference (its module's name and its
    qualified name, which the receiver imports) rather than by value: where its module
    is imported here, is not `__main__` nor registered by value (it or a package above
    it), and holds `cls` under its qualified name (not a class made in a function)."""
    import cloudpickle

    module = cls.__module__
    by_value = cloudpickle.list_registry_pickle_by_value()
    packages = {".".join(module.split(".")[: i + 1]) for i in range(module.count(".") + 1)}
    if module == "__main__" or packages & by_value or module not in sys.modules:
        return False
    found: Any = sys.modules[module]
    for name in cls.__qualname__.split("."):
        found = getattr(found, name, None)
    return found is cls


def _classes_by_reference(batch) -> dict[tuple[str, str], str]:
    """The classes that a worker imports to unpickle the outside parts of `batch` (a
    design's `added`): each part's class and its bases sent by reference, as `(module,
    qualified name)`, each with the part's class that needs it. Not Python's classes,
    nor those of the package or of its parts' bases (equinox): a worker runs them."""
    has = {*sys.stdlib_module_names, *(c.__module__.split(".")[0] for c in Part.__mro__)}
    needed = {}
    for part in outside_parts(batch):
        for cls in type(part).__mro__:
            if cls.__module__.split(".")[0] not in has and _sent_by_reference(cls):
                needed.setdefault((cls.__module__, cls.__qualname__), type(part).__qualname__)
    return needed


def _unimportable(classes: list[tuple[str, str]]) -> dict[tuple[str, str], str]:
    """Of `classes` (`(module, qualified name)`), those this process cannot import, each
    with why (run on each Dask worker)."""
    missing = {}
    for module, qualname in classes:
        try:
            found: Any = importlib.import_module(module)
            for name in qualname.split("."):
                found = getattr(found, name)
        except Exception as error:  # reported, with its cause
            missing[module, qualname] = f"{type(error).__name__}: {error}"
    return missing


def _check_importable_on_workers(
    client: Any, batch, verified: dict[tuple[str, str], set[str]]
) -> None:
    """Raise `ImportError` before the chunk `batch` is sent where a worker of `client`
    cannot import a class that its outside parts are sent by reference with: a worker
    that cannot unpickle a task leaves the sweep waiting for ever. `verified`: for each
    class, the workers found to import it (added to; a worker that joins later is asked
    before the next chunk)."""
    needed = _classes_by_reference(batch)
    if not needed:
        return
    workers = set(client.nthreads())  # every worker, by address
    asked = {key: workers - verified.get(key, set()) for key in needed}
    ask = set().union(*asked.values())
    if not ask:
        return
    missing = client.run(_unimportable, sorted(needed), workers=sorted(ask))
    for key, part in needed.items():
        module, qualname = key
        failed = sorted(w for w in asked[key] if key in missing.get(w, {}))
        if failed:
            why = missing[failed[0]][key]
            raise ImportError(
                f"the Dask worker{'s' if len(failed) > 1 else ''} {', '.join(failed)} cannot "
                f"import {module}.{qualname}, which the added part {part} needs ({why}): "
                "make its module importable there (installed, or on the workers' "
                "PYTHONPATH), or define the part in the script or notebook that runs the "
                "sweep, so that it is sent with the sweep",
                name=module,
            )
        verified.setdefault(key, set()).update(asked[key] & set(missing))
