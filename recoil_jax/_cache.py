"""JAX's persistent compilation cache, in the user's cache directory.

A compiled solve takes seconds to build and milliseconds to run; with the cache on, a
second process that runs the same program (the same `recoil-jax simulate`, `sweep` or
`optimise` again) loads it from disk instead of compiling it.
"""

from __future__ import annotations

import os
from pathlib import Path

import jax
from jax.experimental.compilation_cache import compilation_cache

__all__ = ["CACHE_ENVIRONMENT", "compilation_cache_dir", "enable_compilation_cache"]

#: Environment variable: a folder for the cache, or `off` (also `0`, `false`, `no`) to
#: keep it off.
CACHE_ENVIRONMENT = "RECOIL_JAX_CACHE"

_OFF = ("off", "0", "false", "no", "none")

# Programs that compile faster than this are not worth a disk write and a read.
_MIN_COMPILE_SECONDS = 0.0


def compilation_cache_dir() -> Path | None:
    """The cache folder: `$RECOIL_JAX_CACHE` if set (None if it says `off`), else
    `recoil-jax/jax` under `$XDG_CACHE_HOME` (default `~/.cache`)."""
    chosen = os.environ.get(CACHE_ENVIRONMENT, "").strip()
    if chosen.lower() in _OFF:
        return None
    if chosen:
        return Path(chosen).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "recoil-jax" / "jax"


def enable_compilation_cache(directory: str | os.PathLike | None = None) -> Path | None:
    """Turn on JAX's persistent compilation cache for this process, in `directory`
    (default `compilation_cache_dir()`). Call it before the first solve; the command
    line calls it for every command unless given `--no-cache` or `RECOIL_JAX_CACHE=off`.

    ```python
    import recoil_jax as rj
    rj.enable_compilation_cache()   # e.g. at the top of a notebook
    ```

    **Returns:** the folder used, or None when the environment turns the cache off.

    The cache is trusted code: keep it in a folder only you can write to.
    """
    path = Path(directory).expanduser() if directory is not None else compilation_cache_dir()
    if path is None:
        return None
    path.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", _MIN_COMPILE_SECONDS)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    # JAX settles the cache at its first compilation (importing this package already
    # compiled a few constants): start it afresh so that it reads the folder set here.
    compilation_cache.reset_cache()
    return path
