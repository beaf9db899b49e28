"""Peak metrics as a differentiable function of a flat design vector.

`differentiable_peaks` wraps the forward-sensitivity solve (`tangent_solve`) in a
custom JVP: the primal solve also integrates the forward sensitivities, and the JVP is
their Jacobian times the tangent. So `jax.grad`, `jax.value_and_grad`, `jax.jacfwd` and `jax.jacrev`
of *any* function built on the metrics (an objective, a penalty, a worst case over a
batch) get the error-controlled gradients, not the derivative of the discrete solver.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp

from .._model.derivatives import GRADIENT_OPTIONS, check_wrt, tangent_solve
from .._model.metrics import METRICS
from .._model.params import RecoilParams, values_of, with_values
from .._model.settings import Smoothing, SolverOptions
from .._model.smooth_max import SmoothMax, series_name, smooth_name
from .._model.status import status_item

__all__ = ["design_metrics", "differentiable_peaks"]


def _solve(theta, params, wrt, smoothing, options, smooth_max, series):
    solved = tangent_solve(
        with_values(params, wrt, theta), smoothing, options, wrt, smooth_max, series
    )
    values = {name: getattr(solved.peaks, name) for name in METRICS}
    jacobian = {name: getattr(solved.gradients, name) for name in METRICS}
    if smooth_max is not None:
        assert solved.smooth_values is not None and solved.smooth_gradients is not None
        for j, name in enumerate(smooth_max.metrics):
            values[smooth_name(name)] = solved.smooth_values[j]
            jacobian[smooth_name(name)] = solved.smooth_gradients[j]
    if series is not None:
        assert solved.series_values is not None and solved.series_gradients is not None
        for j, name in enumerate(series.metrics):
            values[series_name(name)] = solved.series_values[j]
            jacobian[series_name(name)] = solved.series_gradients[j]
    # The integer code: custom JVPs take arrays.
    (code,) = jax.tree.leaves(solved.peaks.status)
    return values, jacobian, code


@eqx.filter_custom_jvp
def design_metrics(theta, *, params, wrt, smoothing, options, smooth_max, series=None):
    """`(metrics, code)` of `params` with the parameters `wrt` set to `theta`: the
    metrics of `METRICS` by name (and `smooth_<metric>` for each of `smooth_max`,
    `series_<metric>` of shape `(n,)` for each of a `MetricSeries`) and the
    integer `Status` code, with a custom JVP on the forward sensitivities. The keyword
    arguments are closed over (not differentiated); see `differentiable_peaks`."""
    values, _, status = _solve(theta, params, wrt, smoothing, options, smooth_max, series)
    return values, status


@design_metrics.def_jvp
def _design_metrics_jvp(
    primals, tangents, *, params, wrt, smoothing, options, smooth_max, series=None
):
    (theta,), (theta_dot,) = primals, tangents
    values, jacobian, status = _solve(theta, params, wrt, smoothing, options, smooth_max, series)
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
    """The peaks as a function of the tuned parameters that JAX can differentiate in
    forward or reverse mode, with gradients by forward sensitivities with error control
    (see `peak_gradients`), not the derivative of the discrete solver.

    ```python
    fn = rj.differentiable_peaks(params, ("gap", "m"))
    force, grad = jax.value_and_grad(lambda th: fn(th)[0]["peak_anchoring_force"])(theta)
    ```

    **Arguments:**

    - `params`: the design; the parameters `wrt` are replaced by `theta`, the others are
      held (closed over, also inside `jit`).
    - `wrt`: flat names of the tuned parameters (static).
    - `smoothing`, `options`: as `peak_gradients` (default `GRADIENT_OPTIONS`).
    - `smooth_max`: optional `SmoothMax`: also return `"smooth_<metric>"` entries.

    **Returns:** `fn(theta) -> (metrics, status)`, `theta` of shape `(len(wrt),)` in SI
    units: `metrics` maps each metric of `METRICS` by name (and the smooth maxima) to a
    scalar, `status` is the solve's `Status`. Unjitted; `jit` and `vmap` it as you need.

    **Raises:** `ParameterError` for a bad `wrt`.
    """
    wrt = tuple(wrt)
    check_wrt(params, wrt)

    def fn(theta):
        # The tuned leaves of `params` are replaced by `theta`: cut any tangent they carry.
        base = with_values(params, wrt, jax.lax.stop_gradient(values_of(params, wrt)))
        metrics, code = design_metrics(
            jnp.asarray(theta, dtype=float),
            params=base,
            wrt=wrt,
            smoothing=smoothing,
            options=options,
            smooth_max=smooth_max,
        )
        return metrics, status_item(code)

    return fn
