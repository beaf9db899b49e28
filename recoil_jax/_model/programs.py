"""Compiled programs: JAX's persistent compilation cache, in the user's cache directory,
and the bounded set of programs a process keeps in memory.

A compiled solve takes seconds to build and milliseconds to run; with the cache on, a
second process that runs the same program (the same `recoil-jax simulate`, `sweep` or
`optimise` again) loads it from disk instead of compiling it.
"""

from __future__ import annotations

import collections
import contextlib
import functools
import hashlib
import importlib.metadata
import importlib.util
import os
import platform
import re
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
from jax.experimental.compilation_cache import compilation_cache

from .._model.forces.family import outside_parts
from .._model.registry import check_integer, is_concrete

__all__ = [
    "CACHE_ENVIRONMENT",
    "avx2_codegen_set",
    "compilation_cache_dir",
    "compiled_ahead",
    "enable_compilation_cache",
    "live_programs",
    "program_builds",
    "set_max_programs",
    "structure_jit",
    "use_avx2_codegen",
]

#: Environment variable: a folder for the cache, or `off` (also `0`, `false`, `no`) to
#: keep it off.
CACHE_ENVIRONMENT = "RECOIL_JAX_CACHE"

_OFF = ("off", "0", "false", "no", "none")

# Programs that compile faster than this are not worth a disk write and a read.
_MIN_COMPILE_SECONDS = 0.0


#: The XLA flag that caps the instruction set of XLA:CPU's generated code.
AVX2_FLAG = "--xla_cpu_max_isa=AVX2"

# XLA aborts on a flag it does not know: `xla_cpu_max_isa` came in late 2024 (jax and
# jaxlib share their version number).
_MAX_ISA_SINCE = (0, 4, 36)


def _isa_cap(flags: str) -> str | None:
    """The `xla_cpu_max_isa` value in `flags` (upper case), or None."""
    found = re.findall(r"--xla_cpu_max_isa=(\S+)", flags)
    return found[-1].upper() if found else None


def avx2_codegen_set() -> bool:
    """Whether this process's `XLA_FLAGS` caps XLA:CPU's code at AVX2."""
    return _isa_cap(os.environ.get("XLA_FLAGS", "")) == "AVX2"


def use_avx2_codegen() -> bool:
    """Have XLA:CPU generate AVX2 code for this process: on x86-64 with a jaxlib that
    knows the flag, unless `XLA_FLAGS` already sets `xla_cpu_max_isa`, and only before
    JAX's first computation (the flag is read when the CPU backend starts). Returns
    whether the code is now capped at AVX2.

    On the 2-core AMD EPYC development machine (AVX-512 with BF16), `recoil-jax bench`
    ran 1.16× the sims/s with it (30,840 against 26,484) and 1.05–1.17× the
    Jacobians/s, with every peak and step count the same to the bit. Capped at `AVX512`
    or `AVX512_VNNI` the batched solves ran as fast as at `AVX2`; from `AVX512_BF16` up
    (the default there) about 1.2× slower, for a reason not found. The command line
    calls it for every command (and its Dask workers follow); a CPU without those
    instructions is unaffected.

    ```python
    import recoil_jax as rj
    rj.use_avx2_codegen()  # first, before any solve
    ```
    """
    from jax._src import xla_bridge  # the one place that says whether a backend started

    flags = os.environ.get("XLA_FLAGS", "")
    if _isa_cap(flags) is not None:
        return avx2_codegen_set()
    version = tuple(int(part) for part in re.findall(r"\d+", jax.__version__)[:3])
    started = getattr(xla_bridge, "backends_are_initialized", None)
    if (
        platform.machine().lower() not in ("x86_64", "amd64")
        or version < _MAX_ISA_SINCE
        or (started() if started is not None else bool(getattr(xla_bridge, "_backends", 1)))
    ):
        return False
    os.environ["XLA_FLAGS"] = f"{flags} {AVX2_FLAG}".strip()
    return True


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


#: Compiled programs a process keeps, over every `structure_jit` function together.
_DEFAULT_MAX_PROGRAMS = 32
_programs: collections.OrderedDict = collections.OrderedDict()  # key -> jitted, LRU last
_limit = [_DEFAULT_MAX_PROGRAMS]
_lock = threading.RLock()  # (a program built while another is: no deadlock)
_builds: collections.Counter = collections.Counter()  # fn -> programs built for it


def set_max_programs(count: int) -> int:
    """Keep at most `count` compiled programs in this process (default 32), over every
    entry point of recoil-jax together (`peaks`, `simulate`, sweeps, gradients, the
    explorer, the optimiser); past it, the least recently used is dropped and its memory
    freed (it is compiled again, or loaded from the persistent cache, if used again).
    Returns the previous limit.

    Each program maps several hundred memory regions, and Linux allows a process about
    65,000: without a bound, a notebook or the explorer that visits a few hundred model
    structures would fail to compile the next one."""
    count = check_integer("max programs", count, 1)
    with _lock:
        previous, _limit[0] = _limit[0], count
        while len(_programs) > count:
            _programs.popitem(last=False)
    return previous


def live_programs() -> int:
    """How many compiled programs (`structure_jit` entries) this process holds now."""
    return len(_programs)


def program_builds(fn) -> int:
    """How many programs this process has built for the `structure_jit` function `fn`
    (traced and compiled, or loaded exported): one per structure it was called with,
    and again for one dropped from the bounded cache and called again."""
    return _builds[fn]


def compiled_ahead(fn, *args) -> tuple[Callable, float]:
    """`fn` compiled ahead of time for the structure of `args` (as `structure_jit`
    selects a program), kept in the same bounded cache, and the seconds spent compiling
    it now (next to none when it was there): for a job that times its compilation apart from its
    work (the posterior's sampler). Returns a callable of arguments of that structure
    (their arrays may differ; everything else must be as given)."""
    dynamic, static = eqx.partition(args, eqx.is_array)
    key = (fn, "ahead", _structure_key(dynamic, static))
    clock = time.perf_counter()
    with _lock:
        program = _programs.pop(key, None)
        if program is None:
            lowered = jax.jit(lambda d: fn(*eqx.combine(d, static))).lower(dynamic)
            program = lowered.compile()
        _programs[key] = program
        while len(_programs) > _limit[0]:
            _programs.popitem(last=False)
    seconds = time.perf_counter() - clock

    def run(*args_):
        dynamic_, static_ = eqx.partition(args_, eqx.is_array)
        if _structure_key(dynamic_, static_) != key[2]:
            raise ValueError(f"{fn.__name__}: called with arguments of another structure than "
                             "it was compiled for")  # fmt: skip
        return program(dynamic_)

    return run, seconds


def _structure_key(dynamic, static) -> tuple:
    """What selects a program: the static part (structure and values, as
    `eqx.filter_jit` treats them) and every array's shape and dtype."""
    leaves, treedef = jax.tree.flatten(static)
    arrays, array_def = jax.tree.flatten(dynamic)
    shapes = tuple((tuple(a.shape), str(a.dtype), getattr(a, "weak_type", False)) for a in arrays)
    return treedef, tuple(leaves), array_def, shapes


def structure_jit(fn, *, exported=None):
    """`eqx.filter_jit(fn)`, with its compiled programs in this process's bounded cache
    (`set_max_programs`): one program per structure of the arguments (the arrays' shapes
    and dtypes, and every non-array argument by value), the least recently used dropped
    past the limit. Called while tracing another program, `fn` is traced inline.

    `exported`: a function that rebuilds `fn`'s output from its array leaves (an output
    of arrays only). With the compilation cache on, the traced program is then also kept
    in the cache's folder (`jax.export`), keyed by the package's source, JAX's version
    and the arguments' structure, so that another process skips tracing it too. Only
    for the package's own functions, with static arguments that have a value's repr; a
    program JAX cannot export (a host callback, such as `equinox.error_if`'s) is marked
    so, and compiled as usual from then on."""

    @functools.wraps(fn)
    def call(*args, **kwargs):
        dynamic, static = eqx.partition((args, kwargs), eqx.is_array)
        if not is_concrete(dynamic):
            return fn(*args, **kwargs)
        key = (fn, _structure_key(dynamic, static))
        with _lock:
            program = _programs.pop(key, None)
            if program is None:
                program = (exported and _exported(fn, dynamic, static, exported)) or _compile(
                    fn, static
                )
                _builds[fn] += 1
            _programs[key] = program  # the most recently used last
            while len(_programs) > _limit[0]:
                _programs.popitem(last=False)
        return program(dynamic)

    return call


def _source_digest() -> str:
    digest = hashlib.sha256()
    for path in sorted(Path(__file__).parents[1].rglob("*.py")):  # the whole package
        digest.update(path.read_bytes())
    return digest.hexdigest()


def _version(distribution: str) -> str:
    try:
        return importlib.metadata.version(distribution)
    except importlib.metadata.PackageNotFoundError:
        return "absent"


#: What an exported program's key names besides its arguments: the package's source as
#: imported (read now: a file edited later is not the code this process runs) and the
#: versions of the libraries whose code it traced.
_CODE = "|".join([
    _source_digest(),
    *(f"{name} {_version(name)}"
      for name in ("jax", "jaxlib", "equinox", "diffrax", "lineax", "optimistix")),
])  # fmt: skip


def _export(jitted, shapes, platform: str):
    """`jax.export` for `platform`, allowing LAPACK's custom calls (a QR in a
    least-squares solve): they carry no guarantee across JAX versions, and none is
    needed, since an exported program is keyed by the JAX version it was made with."""
    try:
        return jax.export.export(jitted, platforms=(platform,))(shapes)
    except ValueError as error:
        targets = sorted(set(re.findall(r"custom_call @(\w+)\(", str(error))))
        if not targets:
            raise
        checks = [jax.export.DisabledSafetyCheck.custom_call(t) for t in targets]
        return jax.export.export(jitted, platforms=(platform,), disabled_checks=checks)(shapes)


#: Where the types of an exported program's arguments may come from: a type defined
#: elsewhere (a user's subclass) is named in the key by its name, not its code.
_KNOWN_MODULES = ("builtins", "numpy", "jax", "jaxlib", "equinox", "diffrax", "optax")


def _known_types(*trees) -> bool:
    """Whether every pytree node and static leaf of `trees` is of a type of the package
    or of the libraries it builds on."""

    def known(kind) -> bool:
        module = getattr(kind, "__module__", "") or ""
        return module.split(".")[0] in (*_KNOWN_MODULES, _PACKAGE.rstrip("."))

    def nodes(treedef):
        data = treedef.node_data()
        if data is not None:
            yield data[0]
        for child in treedef.children():
            yield from nodes(child)

    for tree in trees:
        leaves, treedef = jax.tree.flatten(tree)
        if not all(known(kind) for kind in nodes(treedef)):
            return False
        if not all(known(type(leaf)) for leaf in leaves):
            return False
    return True


def _export_folder() -> str | None:
    """The compilation cache's folder, where exported programs are kept (None: off)."""
    return getattr(jax.config, "jax_compilation_cache_dir")  # noqa: B009 (untyped flag)


_PACKAGE = __name__.split(".")[0] + "."  # the package's modules' names start with it

#: A repr that names an object by its address (a function defined outside the package,
#: an object without a value repr): not a key that says what the program computes.
_ADDRESS = re.compile(r" at 0x[0-9a-fA-F]+")


def _exported(fn, dynamic, static, rebuild):
    """A program for `fn` at this structure, exported to (or loaded from) the
    compilation cache's folder; None without a cache folder or flatbuffers, or where
    JAX cannot export it (the caller then compiles as usual)."""
    folder = _export_folder()
    if folder is None or importlib.util.find_spec("flatbuffers") is None:
        return None
    # Its key names the package's code: not a function, or a part, defined outside it.
    if not fn.__module__.startswith(_PACKAGE) or outside_parts(dynamic):
        return None
    if not _known_types(dynamic, static):
        return None
    leaves, treedef = jax.tree.flatten(dynamic)
    devices = [d for x in leaves if isinstance(x, jax.Array) for d in x.devices()]
    platform = devices[0].platform if devices else jax.default_backend()
    text = "|".join([
        _CODE, platform, f"{fn.__module__}.{fn.__qualname__}", str(treedef),
        str(jax.tree.structure(static)), repr(jax.tree.leaves(static)),
        *(f"{tuple(x.shape)}:{x.dtype}" for x in leaves),
    ])  # fmt: skip
    if _ADDRESS.search(text):  # an object named by its address, not its value
        return None
    path = (
        Path(folder)
        / "exported"
        / f"{fn.__name__}-{hashlib.sha256(text.encode()).hexdigest()[:32]}"
    )
    refused = path.with_suffix(".refused")
    if refused.exists():  # JAX could not export it before: compile, do not trace twice
        return None
    try:
        if path.exists():
            program = jax.export.deserialize(bytearray(path.read_bytes()))
        else:

            def flat(leaves):
                args, kwargs = eqx.combine(jax.tree.unflatten(treedef, leaves), static)
                return jax.tree.leaves(fn(*args, **kwargs))

            shapes = [jax.ShapeDtypeStruct(x.shape, x.dtype) for x in leaves]
            try:
                program = _export(jax.jit(flat), shapes, platform)
                serialized = program.serialize()
            except (NotImplementedError, ValueError):  # JAX cannot export it (a callback)
                with contextlib.suppress(OSError):
                    refused.parent.mkdir(parents=True, exist_ok=True)
                    refused.touch()
                return None
            path.parent.mkdir(parents=True, exist_ok=True)
            partial = path.with_suffix(f".{os.getpid()}-{threading.get_ident()}.partial")
            try:
                partial.write_bytes(serialized)
                partial.replace(path)  # whole or absent, also with two processes at once
            finally:
                partial.unlink(missing_ok=True)
    except Exception:
        return None

    def imported(leaves):
        return program.call(leaves)

    imported.__name__ = imported.__qualname__ = fn.__name__  # in JAX's logs, as `_compile`'s
    jitted = jax.jit(imported)

    def run(dynamic):
        return rebuild(jax.block_until_ready(jitted(jax.tree.leaves(dynamic))))

    return run


def _compile(fn, static):
    """A fresh `jax.jit` closure over the static arguments: when the cache drops it,
    nothing else refers to it and JAX frees its executable (with `eqx.filter_jit` the
    function would be a static argument of one long-lived jitted function, and its
    programs would never be freed)."""
    outputs: dict[str, Any] = {}

    def program(dynamic):
        args, kwargs = eqx.combine(dynamic, static)
        out_dynamic, outputs["static"] = eqx.partition(fn(*args, **kwargs), eqx.is_array)
        return out_dynamic

    program.__name__, program.__qualname__ = fn.__name__, fn.__qualname__  # in JAX's logs
    jitted = jax.jit(program)

    def run(dynamic):
        try:
            # Waited for here, so that a runtime error (an `eqx.error_if` in `fn`) is
            # raised by this call, as `eqx.filter_jit` does.
            out_dynamic = jax.block_until_ready(jitted(dynamic))
        # A callback's error comes as a JaxRuntimeError, or in some processes (seen in
        # the test suite, under xdist) as a ValueError("INTERNAL: CpuCallback error").
        except (jax.errors.JaxRuntimeError, ValueError) as error:
            marker = "_EquinoxRuntimeError: "
            text = str(error)
            if marker not in text:
                raise
            message = text.split(marker, 1)[1].split("\n", 1)[0]
            raise eqx.EquinoxRuntimeError(message) from None
        return eqx.combine(out_dynamic, outputs["static"])

    return run
