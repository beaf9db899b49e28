"""The memory a sweep may use (`check_memory`: a refusal, before anything is allocated,
of arrays that would not fit: Linux's free memory, or a container's limit) and the
threads it runs on (`default_workers`)."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from .._model.registry import ParameterError

__all__ = ["check_memory", "cores", "default_workers"]


def _available_memory() -> int | None:
    """Bytes of memory this process may still use: Linux's MemAvailable, or less where an
    address-space limit or a container's memory limit (cgroup v2) leaves less; None
    where none is known."""
    free = []
    try:
        with open("/proc/meminfo") as meminfo:
            for line in meminfo:
                if line.startswith("MemAvailable:"):
                    free.append(int(line.split()[1]) * 1024)
    except (OSError, ValueError, IndexError):
        pass
    try:  # an address-space limit (`ulimit -v`), less what the process has mapped
        import resource

        soft, _ = resource.getrlimit(resource.RLIMIT_AS)
        if soft != resource.RLIM_INFINITY:
            with open("/proc/self/status") as status:
                mapped = next(int(line.split()[1]) * 1024 for line in status
                              if line.startswith("VmSize:"))  # fmt: skip
            free.append(max(0, soft - mapped))
    except (ImportError, OSError, ValueError, StopIteration):
        pass
    try:
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        used = Path("/sys/fs/cgroup/memory.current").read_text().strip()
        if limit != "max":
            free.append(max(0, int(limit) - int(used)))
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
        return len(devices) * max(1, -(-cores() // len(devices)))
    return len(devices)


def cores() -> int:
    """The cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
