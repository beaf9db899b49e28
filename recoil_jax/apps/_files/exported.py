"""`recoil-jax simulate`'s solve as an exported program kept on disk.

JAX's compilation cache saves the compilation of a repeated command, but each process
still traces and lowers the Python of the solve (about half a second) to find its cache
key. For the command line's most repeated call, one design's peaks, the traced program
is exported (`jax.export`) to the compilation cache's folder once; later processes load
it and call it, which skips tracing, and its compilation comes from JAX's cache.

An exported program is found by a key of everything it depends on: the package's source
files, the JAX version, and the structure (static settings, shapes and dtypes) of the
design, smoothing and solver options. Values are arguments, so every design with the
same structure shares it.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib.util
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import recoil_jax as rj

__all__ = ["exported_peaks"]


def _source_digest() -> str:
    package = Path(rj.__file__).parent
    digest = hashlib.sha256()
    for path in sorted(package.rglob("*.py")):
        digest.update(path.read_bytes())
    return digest.hexdigest()


def _key(treedef, leaves) -> str:
    text = "|".join(
        [
            _source_digest(),
            jax.__version__,
            str(treedef),
            *(f"{np.shape(x)}:{np.asarray(x).dtype}" for x in leaves),
        ]
    )
    return hashlib.sha256(text.encode()).hexdigest()[:32]


def _peaks_structure():
    fields = {f.name: jnp.zeros(()) for f in dataclasses.fields(rj.Peaks) if f.name != "status"}
    return jax.tree.structure(rj.Peaks(**fields, status=rj.Status.ok))


def _folder() -> str | None:
    """The compilation cache's folder, where exported programs are kept (None: off)."""
    return getattr(jax.config, "jax_compilation_cache_dir")  # noqa: B009 (untyped flag)


def exported_peaks(
    params: rj.RecoilParams, smoothing: rj.Smoothing, options: rj.SolverOptions
) -> rj.Peaks:
    """`rj.peaks(params, smoothing, options, throw=False)` through a program exported to
    the compilation cache's folder (exported on first use). Without a cache folder
    (the cache not enabled in this process), without flatbuffers or for a design with a
    part defined outside the package, a plain `rj.peaks`."""
    folder = _folder()
    if not folder or importlib.util.find_spec("flatbuffers") is None or params.added:
        # No cache, or no flatbuffers (the `apps` extra) to write jax.export's files;
        # or a part defined outside the package, whose code the key does not name.
        return rj.peaks(params, smoothing, options, throw=False)
    leaves, treedef = jax.tree.flatten((params, smoothing, options))
    leaves = [np.asarray(x) for x in leaves]
    path = Path(folder) / "exported" / f"peaks-{_key(treedef, leaves)}"
    if path.exists():
        exported = jax.export.deserialize(bytearray(path.read_bytes()))
    else:

        def program(leaves):
            return jax.tree.leaves(rj.peak_metrics(*jax.tree.unflatten(treedef, leaves)))

        shapes = [jax.ShapeDtypeStruct(x.shape, x.dtype) for x in leaves]
        exported = jax.export.export(jax.jit(program))(shapes)
        path.parent.mkdir(parents=True, exist_ok=True)
        partial = path.with_suffix(".partial")
        partial.write_bytes(exported.serialize())
        partial.replace(path)  # whole or absent, also with two processes at once
    return jax.tree.unflatten(_peaks_structure(), exported.call(leaves))
