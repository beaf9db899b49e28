"""The Fisher information of candidate firings, before any is fired: for each candidate
condition and each signal, `Jᵀ J / σ²` over the sampled times, `J` the exact,
error-controlled sensitivities of the signal (`signal_sensitivities`), in the box
coordinates the calibration reports in. All candidates, at every truth, in one vmapped
program.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._model.derivatives import signal_sensitivities
from .._model.params import RecoilParams, values_of, with_values
from .._model.settings import Smoothing, SolverOptions
from .._sweeps.space import SearchSpace

__all__ = ["candidate_information"]


def candidate_information(
    params: RecoilParams,
    fit: Sequence[str],
    space: SearchSpace,
    candidates: Mapping[str, Any],
    signals: Sequence[str],
    sigma: Sequence[float],
    ts,
    smoothing: Smoothing = Smoothing(),
    options: SolverOptions = SolverOptions(),
    truths=None,
) -> tuple[np.ndarray, np.ndarray]:
    """The information of each candidate firing and signal, and each solve's status.

    **Arguments:**

    - `params`: the design; `fit`: the parameters the test must determine (flat names),
      `space` their box (`SearchSpace`).
    - `candidates`: condition name → values `(C,)`, one column per condition parameter.
    - `signals`: signal names (`SIGNALS`), `sigma (S,)` their noise (SI units).
    - `ts (T,)`: the sample times, from the firing (s); the solve runs to `ts[-1]`.
    - `truths (R, P)`: the fitted values to compute it at (default: `params`' own).

    **Returns:** `information (R, C, S, P, P)` in box coordinates (each bound range [0,
    1], logarithmic where the space is), and `status (R, C)` codes. All in one program.
    """
    fit, signals = tuple(fit), tuple(signals)
    names = tuple(candidates)
    columns = jnp.stack([jnp.asarray(candidates[n], dtype=float) for n in names], axis=1)
    if truths is None:
        truths = values_of(params, fit)[None]
    truths = jnp.asarray(truths, dtype=float)
    z = jnp.asarray(space.z(np.asarray(truths)))
    # dθ/dz per parameter: the chain rule into box coordinates.
    dtheta_dz = jax.vmap(lambda z: jax.jvp(space.theta, (z,), (jnp.ones_like(z),))[1])(z)
    weights = 1.0 / jnp.asarray(sigma, dtype=float) ** 2
    information, codes = _program(
        params, fit, names, signals, weights, jnp.asarray(ts, dtype=float),
        smoothing, options, truths, dtheta_dz, columns,
    )  # fmt: skip
    return np.asarray(information), np.asarray(codes)


@eqx.filter_jit
def _program(
    params, fit, names, signals, weights, ts, smoothing, options, truths, dtheta_dz, columns
):
    def at_truth(theta, dtheta_dz):
        truth = with_values(params, fit, theta)

        def one(values):
            p = with_values(truth, names, values)
            s = signal_sensitivities(p, smoothing, options, fit, ts, ts[-1], signals)
            J = s.gradients * dtheta_dz  # (S, T, P)
            info = jnp.einsum("stp,stq->spq", J, J) * weights[:, None, None]
            (code,) = jax.tree.leaves(s.status)
            return info, code

        return jax.vmap(one)(columns)

    return jax.vmap(at_truth)(truths, dtheta_dz)
