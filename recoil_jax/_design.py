"""Peak metrics as a differentiable function of a flat design vector.

`differentiable_peaks` wraps the forward-sensitivity solve (`_gradients`) in a custom
JVP: the primal solve also integrates the sensitivities, and the JVP is their Jacobian
times the tangent. So `jax.grad`, `jax.value_and_grad`, `jax.jacfwd` and `jax.jacrev`
of *any* function built on the metrics (an objective, a penalty, a worst case over a
batch) get the error-controlled gradients, not the derivative of the discrete solver.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp

from ._gradients import (
    GRADIENT_OPTIONS,
    SmoothMax,
    _check_wrt,
    _sensitivity_solve,
)
from ._params import RecoilParams, Smoothing, SolverOptions, values_of, with_values

#: The peak metrics `differentiable_peaks` returns (`Peaks` field names).
METRICS = ("peak_displacement", "peak_anchoring_force", "peak_contact_force", "max_stroke",
           "min_stroke")


def _solve(theta, params, wrt, smoothing, options, smooth_max):
    peaks, grads, smooth_values, smooth_grads = _sensitivity_solve(
        with_values(params, wrt, theta), smoothing, options, wrt, smooth_max)
    values = {name: getattr(peaks, name) for name in METRICS}
    jacobian = {name: getattr(grads, name) for name in METRICS}
    if smooth_max is not None:
        for j, name in enumerate(smooth_max.metrics):
            values["smooth_" + name] = smooth_values[j]
            jacobian["smooth_" + name] = smooth_grads[j]
    return values, jacobian, peaks.status


@eqx.filter_custom_jvp
def _metrics(theta, *, params, wrt, smoothing, options, smooth_max):
    values, _, status = _solve(theta, params, wrt, smoothing, options, smooth_max)
    return values, status


@_metrics.def_jvp
def _metrics_jvp(primals, tangents, *, params, wrt, smoothing, options, smooth_max):
    (theta,), (theta_dot,) = primals, tangents
    values, jacobian, status = _solve(theta, params, wrt, smoothing, options, smooth_max)
    if theta_dot is None:
        return (values, status), (jax.tree.map(jnp.zeros_like, values), None)
    return (values, status), ({k: j @ theta_dot for k, j in jacobian.items()}, None)


def differentiable_peaks(
    params: RecoilParams,
    wrt: Sequence[str],
    smoothing: Smoothing = Smoothing(),
    options: SolverOptions = GRADIENT_OPTIONS,
    smooth_max: SmoothMax | None = None,
) -> Callable[[jax.Array], tuple[dict[str, jax.Array], jax.Array]]:
    """`fn(theta) -> (metrics, status)`: the peaks of `params` with the parameters `wrt`
    set to `theta` (shape `(len(wrt),)`, SI units), as a function that JAX can
    differentiate in forward or reverse mode (gradients by forward sensitivities with
    error control, see `peak_gradients`).

    `metrics` maps each of `METRICS` (and `"smooth_<metric>"` for each metric of
    `smooth_max`) to a scalar; `status` is the solve's `Status` code. Unjitted; `jit` and
    `vmap` it as you need (`params` may be closed over, also inside `jit`).

    ```python
    fn = rj.differentiable_peaks(params, ("gap", "m"))
    force, grad = jax.value_and_grad(lambda th: fn(th)[0]["peak_anchoring_force"])(theta)
    ```
    """
    wrt = tuple(wrt)
    _check_wrt(params, wrt)

    def fn(theta):
        # The tuned leaves of `params` are replaced by `theta`: cut any tangent they carry.
        base = with_values(params, wrt, jax.lax.stop_gradient(values_of(params, wrt)))
        return _metrics(jnp.asarray(theta, dtype=float), params=base, wrt=wrt,
                        smoothing=smoothing, options=options, smooth_max=smooth_max)

    return fn
