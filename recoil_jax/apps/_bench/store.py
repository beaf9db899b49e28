"""`recoil-jax bench-store`: what a store, streaming and a 2-worker Dask cluster cost a
sweep (time, memory, disk), each way measured in its own fresh process in one run."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

import recoil_jax as rj

from .._files.options import Commands, add_json

__all__ = ["add_command", "format_store_bench", "main_store_bench", "run_store_bench"]

#: One measurement, in a fresh process: the program is compiled on one chunk of the
#: designs first (not timed), then the whole sweep is timed, with or without a store.
_CHILD = textwrap.dedent(
    """
    import json, resource, sys, time
    import recoil_jax as rj
    from recoil_jax.apps._bench.speed import bench_designs
    from recoil_jax.apps._files.cluster import dask_client

    count, store, workers = int(sys.argv[1]), sys.argv[2] or None, int(sys.argv[3]) or None
    stream = sys.argv[4] == "stream"
    designs = bench_designs(count, seed=0)
    with dask_client(workers, None) as client:
        first = {k: v[:16384] for k, v in designs.items()}
        rj.sweep(first, progress=False, client=client)  # compile (on every worker)
        if client is not None:
            rj.sweep(first, progress=False, client=client)
        start = time.perf_counter()
        if stream:
            result = rj.sweep_to_store(designs, store, progress=False, client=client)
            ok = result.designs - result.failed
        else:
            result = rj.sweep(designs, store=store, progress=False, client=client)
            ok = int(result.ok.sum())
        seconds = time.perf_counter() - start
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # kB on Linux
    print(json.dumps({"seconds": seconds, "ok": ok, "peak_rss_mb": peak}))
    """
)

#: The ways, by name: (store file, Dask workers, results kept in memory or streamed).
WAYS = {
    "plain": ("", 0, "memory"),
    "store": ("bench.sqlite", 0, "memory"),
    "stream": ("stream.sqlite", 0, "stream"),
    "cluster": ("cluster.sqlite", 2, "stream"),
}
LABELS = {
    "plain": "without a store",
    "store": "with a store",
    "stream": "streamed to a store",
    "cluster": "streamed, on 2 Dask workers",
}


def _measure(count: int, store: str, workers: int, keep: str, label: str, log) -> dict:
    """Run `_CHILD`; its figures: seconds, designs ok, peak resident memory (MB) of the
    process that runs the sweep (not of its Dask workers)."""
    process = subprocess.Popen(
        [sys.executable, "-c", _CHILD, str(count), store, str(workers), keep],
        stdout=subprocess.PIPE,
        text=True,
        env=os.environ | {"RECOIL_JAX_CACHE": "off"},
    )
    output, _ = process.communicate()
    if process.returncode:
        raise RuntimeError(f"bench-store: the measuring process failed ({process.returncode})")
    figures = json.loads(output.strip().splitlines()[-1])
    log(f"  {label}: {figures['seconds']:.1f} s, peak memory {figures['peak_rss_mb']:.0f} MB")
    return figures


def run_store_bench(count: int, ways=tuple(WAYS), log=None) -> dict:
    """Sweep `count` random absorber designs (`bench_designs`) in each of `ways`
    (`WAYS`), each in a fresh process: without a store (`plain`), with a store and the
    results kept in memory (`store`, `rj.sweep(store=)`), streamed to a store
    (`stream`, `rj.sweep_to_store`), and streamed on a local Dask cluster of 2 worker
    processes (`cluster`). Returns, per way, seconds, designs/s and peak memory (MB), the
    overheads (%) against `plain` (when measured), and the store's size (MB)."""
    log = log or (lambda message: None)
    unknown = set(ways) - set(WAYS)
    if unknown or not ways:
        raise rj.ParameterError(f"bench-store: ways {sorted(unknown)}; known: {', '.join(WAYS)}")
    result: dict = {"designs": count, "ways": list(ways)}
    with tempfile.TemporaryDirectory() as folder:
        log(f"bench-store: {count} designs, each way in a fresh process")
        for way in ways:
            name, workers, keep = WAYS[way]
            store = str(Path(folder) / name) if name else ""
            figures = _measure(count, store, workers, keep, LABELS[way], log)
            result[f"{way}_seconds"] = figures["seconds"]
            result[f"{way}_designs_per_second"] = count / figures["seconds"]
            result[f"{way}_peak_rss_mb"] = figures["peak_rss_mb"]
            if name:
                result["store_mb"] = (Path(folder) / name).stat().st_size / 1e6
    if "plain" in ways:
        for way in ways:
            if way != "plain":
                ratio = result[f"{way}_seconds"] / result["plain_seconds"]
                result[f"{way}_overhead_percent"] = 100 * (ratio - 1)
    return result


def format_store_bench(result: dict) -> str:
    lines = [f"{result['designs']} designs, each way in a fresh process:"]
    for way in result["ways"]:
        line = (
            f"  {LABELS[way]:30s} {result[f'{way}_seconds']:8.1f} s "
            f"{result[f'{way}_designs_per_second']:8.0f}/s  "
            f"peak memory {result[f'{way}_peak_rss_mb']:6.0f} MB"
        )
        if f"{way}_overhead_percent" in result:
            line += f"  overhead {result[f'{way}_overhead_percent']:+.1f} %"
        lines.append(line)
    if "store_mb" in result:
        lines.append(f"  a store on disk: {result['store_mb']:.0f} MB")
    return "\n".join(lines)


def main_store_bench(args) -> int:
    ways = tuple(args.ways.split(",")) if args.ways else tuple(WAYS)
    result = run_store_bench(args.designs, ways, log=lambda m: print(m, file=sys.stderr))
    print(json.dumps(result) if args.json else format_store_bench(result))
    return 0


def add_command(commands: Commands) -> None:
    """`recoil-jax bench-store`'s arguments."""
    store_bench = commands.add(
        "bench-store",
        main_store_bench,
        help="what a store and a Dask cluster cost a sweep: time, memory, disk",
        description="Sweep random absorber designs in several ways, each in a fresh process "
        "(compiled on one chunk first, not timed): plain (no store), store (results kept "
        "in memory and stored), stream (results only in the store: rj.sweep_to_store) and "
        "cluster (streamed, on a local Dask cluster of 2 workers). Prints seconds, "
        "designs/s, the peak memory of the process that sweeps, the overheads against "
        "plain and a store's size on disk.",
    )
    store_bench.add_argument(
        "--ways",
        metavar="W,W",
        help="which ways, comma-separated (default plain,store,stream,cluster)",
    )
    store_bench.add_argument(
        "--designs", type=int, default=1_000_000, metavar="N", help="designs (default 1000000)"
    )
    add_json(store_bench, "one JSON object")
