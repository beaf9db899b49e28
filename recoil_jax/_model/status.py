"""How a solve ended: the `Status` enumeration, and raising on failure under `jit`."""

from __future__ import annotations

import functools
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._model.registry import is_concrete

__all__ = [
    "OK_CODE",
    "SolveError",
    "Status",
    "failure_message",
    "raise_on_failure",
    "status_codes",
    "status_item",
    "status_messages",
    "status_table",
]


class Status(eqx.Enumeration):
    """How a solve ended (an `equinox.Enumeration`; `Peaks.status`, `History.status`).

    Compare with `==` (`peaks.status == rj.Status.ok`, elementwise under `vmap`); the
    message of one item is `rj.Status[item]`, of a batch `status_messages(item)`.
    """

    ok = "ok"
    max_steps = (
        "max_steps reached before t1: increase max_steps (SolverOptions.max_steps; on the "
        "command line --max-steps) or loosen the tolerances"
    )
    nonfinite = "the state became NaN or inf"
    step_underflow = "the step size underflowed (t + dt == t) before t1"
    bottomed_out = (
        "the barrel bottomed out the gas recuperator: x_M reached 0.95 recuperator_length"
    )


#: What `peaks`, `simulate` and `peak_jacobian` raise when a solve fails and
#: `throw=True` (`raise_on_failure`): equinox's runtime error, raised after the compiled
#: program ran or, inside a user's `jit`, by `equinox.error_if` within it. Its message
#: holds the `Status` message.
SolveError = eqx.EquinoxRuntimeError


def raise_on_failure(token: Any, status: Any) -> Any:
    """`token`, raising `SolveError` if any element of `status` is not `Status.ok`, with
    that status's message (for a batch, the largest code's).

    A concrete `status` (a compiled program's output) is checked here, on the host. A
    traced one (inside a user's `jit` or `vmap`) gets the error attached with
    `equinox.error_if`, which fires when that program runs. Called on a program's
    outputs rather than inside it, the program holds no host callback, and JAX keeps
    it in the persistent compilation cache."""
    (codes,) = jax.tree.leaves(status)
    ok = status_codes(Status.ok)
    if is_concrete(codes):
        host = np.asarray(codes)
        failed = host != ok
        if np.any(failed):
            raise SolveError(_messages()[int(np.max(np.where(failed, host, ok)))])
        return token
    failed = codes != ok
    worst = jax.tree.map(lambda _: jnp.max(jnp.where(failed, codes, ok)), Status.ok)
    return worst.error_if(token, jnp.any(failed))


def status_codes(status: Any) -> np.ndarray:
    """The integer codes of a (possibly batched) `Status` item, on the host."""
    (codes,) = jax.tree.leaves(status)
    return np.asarray(codes)


#: The integer code of `Status.ok`: a solve that succeeded.
OK_CODE = int(status_codes(Status.ok))


def status_messages(status: Any) -> list[str]:
    """The message of each element of a (possibly batched) `Status` item, flattened."""
    table = _messages()
    return [table[code] for code in status_codes(status).reshape(-1).tolist()]


@functools.cache
def _messages() -> dict[int, str]:
    # Looked up by code: `Status[item]` costs about 80 µs, 80 s for a million designs.
    return {code: Status[status_item(np.int32(code))] for code in range(len(Status))}


def status_item(codes: Any) -> Any:
    """A `Status` item holding the integer `codes` (host arrays gathered from several
    batches, or traced codes)."""
    as_array = jnp.asarray if isinstance(codes, jax.Array) else np.asarray
    return jax.tree.map(lambda _: as_array(codes, dtype=np.int32), Status.ok)


def status_table() -> dict[int, str]:
    """Every `Status` code with its message (for files that store the codes)."""
    return dict(_messages())


def failure_message(error: BaseException) -> str:
    """The `Status` message a `SolveError` carries, without equinox's debugging notes (or
    the error's first line, for any other error)."""
    text = str(error)
    ok = int(status_codes(Status.ok))
    for code, message in status_table().items():
        if code != ok and message in text:
            return message
    return text.strip().splitlines()[0] if text.strip() else type(error).__name__
