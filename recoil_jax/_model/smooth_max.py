"""What a gradient solve can integrate beside the state: the smooth maxima over time of
peak metrics (`SmoothMax`), and the signals whose maxima are metrics at save times
(`MetricSeries`), each with the key it has in results."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from .._model.metrics import METRICS
from .._model.registry import ParameterError, is_concrete

__all__ = ["MetricSeries", "SmoothMax", "series_name", "smooth_name"]


def smooth_name(metric: str) -> str:
    """The key of a metric's smooth maximum in results: `smooth_<metric>`."""
    return "smooth_" + metric


class SmoothMax(eqx.Module):
    """Smooth maxima over time of peak metrics: `T · log((1/t1) ∫_0^t1 exp(g(t)/T) dt)`
    for each metric `g` named in `metrics` (static; metrics of `METRICS` with a smooth
    maximum) with temperature `T` in the metric's unit (`temperatures`, shape
    `(len(metrics),)`).

    As `T → 0` this tends to `max_t g`, from below by about `T · log(t1 / w)` where `w`
    is the width of the peak. Unlike the peak, it is smooth where the maximum jumps
    from one local maximum to another: both contribute, weighted by `exp(g/T)`.
    It is integrated as one extra state per metric, `L = log((1/t1) ∫ exp(g/T))`, with
    `dL/dt = exp(g/T − L) / t1`, under the same error control as the rest.
    """

    metrics: tuple[str, ...] = eqx.field(static=True)
    temperatures: jax.Array = eqx.field(converter=lambda x: jnp.asarray(x, dtype=float))

    def __check_init__(self):
        smoothable = [name for name, m in METRICS.items() if m.smoothable]
        for name in self.metrics:
            if name not in smoothable:
                raise ParameterError(
                    f"no smooth maximum of {name!r}; choose from {', '.join(smoothable)}"
                )
        if jnp.shape(self.temperatures)[-1:] != (len(self.metrics),):
            raise ParameterError("SmoothMax needs one temperature per metric")
        if is_concrete(self.temperatures) and not bool(jnp.all(self.temperatures > 0)):
            raise ParameterError(
                f"SmoothMax.temperatures = {self.temperatures} is invalid: valid > 0 "
                "(in the metric's unit)"
            )


def series_name(metric: str) -> str:
    """The key of a metric's signal on the save times of a `MetricSeries`:
    `series_<metric>`."""
    return "series_" + metric


class MetricSeries(eqx.Module):
    """The signals whose maxima are metrics (`metrics`, static; those with a maximum over
    time, as `SmoothMax`), at the save times `ts` (s, shape `(n,)`, sorted), with their
    gradients: a minimax over time as many smooth constraints (`search`'s local phase).

    Values are `sign · signal` (the quantity whose maximum is the metric). Save times
    after the solve stopped (its peaks were certain) hold NaN."""

    metrics: tuple[str, ...] = eqx.field(static=True)
    ts: jax.Array = eqx.field(converter=lambda x: jnp.asarray(x, dtype=float))

    def __check_init__(self):
        SmoothMax(self.metrics, jnp.ones(len(self.metrics)))  # the same metrics qualify
        if jnp.ndim(self.ts) != 1:
            raise ParameterError("MetricSeries.ts must be one sorted vector of save times")
