"""The metric registry, and the containers that carry metrics by name.

`METRICS` is the one registry of what a solve reports: each metric's name (used in
Python, TOML study files, objectives and constraints), its unit, the model signal it is
the extreme of, and whether its time is reported. The JSON and CSV keys
(`peak_anchoring_force_N`, `peak_displacement_time_s`, ...) derive from it, as do the
fields of `Peaks` and `PeakGradients`, which are checked against it when built.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, Literal

import equinox as eqx
import jax
import numpy as np

from .._model.registry import ParameterError
from .._model.status import Status

__all__ = [
    "ENVELOPE_FIELDS",
    "EXTREMES",
    "METRICS",
    "PEAK_FIELDS",
    "Metric",
    "PeakGradients",
    "Peaks",
    "gradient_key",
    "is_return_field",
    "metric",
    "reported_value",
    "worst_case",
]


@dataclasses.dataclass(frozen=True, kw_only=True)
class Metric:
    """One reported metric, in `unit`. Of `kind`:

    - `"extreme"`: the `extreme` (`"max"` or `"min"`) over `[0, t1]` of the model signal
      `signal` (see `tracked_metrics`);
    - `"return"`: taken where the barrel comes back into battery after the last round
      (`return_time`, `battery_speed`; the firing envelope's designs only);
    - `"final"`: taken at `t1` (`residual_displacement`; likewise);
    - `"either"`: the larger of the push and the pull, `max(peak_anchoring_force,
      peak_pull_force) = max |F_AN|`, with its time and gradient (`peak_mount_load`; not
      tracked on its own: each tracked quantity costs every step its share).

    `extreme` is also the direction in which it is worst (`worst_case`)."""

    name: str
    unit: str
    signal: str | None
    extreme: Literal["max", "min"]
    timed: bool  # the time of the extreme is reported too
    smoothable: bool  # has a smooth maximum over time (`SmoothMax`)
    meaning: str
    kind: Literal["extreme", "return", "final", "either"] = "extreme"
    envelope: bool = False  # reported for the firing envelope's designs only (else null)

    @property
    def key(self) -> str:
        """The JSON / CSV key: the name with its unit (`peak_anchoring_force_N`,
        `battery_speed_m_per_s`; the name alone for a ratio)."""
        if not self.unit:
            return self.name
        return f"{self.name}_{self.unit.replace('/', '_per_')}"

    @property
    def time_field(self) -> str:
        return f"{self.name}_time"

    @property
    def time_key(self) -> str:
        return f"{self.name}_time_s"

    @property
    def sign(self) -> float:
        """+1 for a maximum, −1 for a minimum: the loop tracks maxima of `sign · signal`."""
        return 1.0 if self.extreme == "max" else -1.0

    @property
    def label(self) -> str:
        """`meaning (unit)`, for axis labels."""
        return f"{self.meaning} ({self.unit})" if self.unit else self.meaning


#: The metrics by name, in the order they are reported.
METRICS: dict[str, Metric] = {
    m.name: m
    for m in (
        Metric(
            name="peak_displacement",
            unit="m",
            signal="recoil",
            extreme="max",
            timed=True,
            smoothable=True,
            meaning="peak barrel displacement from its rest",
        ),
        Metric(
            name="peak_anchoring_force",
            unit="N",
            signal="F_AN",
            extreme="max",
            timed=True,
            smoothable=True,
            meaning="peak anchoring force",
        ),
        Metric(
            name="peak_contact_force",
            unit="N",
            signal="F_ct",
            extreme="max",
            timed=True,
            smoothable=False,
            meaning="peak contact force",
        ),
        Metric(
            name="min_stroke",
            unit="m",
            signal="stroke",
            extreme="min",
            timed=False,
            smoothable=False,
            meaning="least absorber travel x_m - x_M",
        ),
        Metric(
            name="max_stroke",
            unit="m",
            signal="stroke",
            extreme="max",
            timed=False,
            smoothable=False,
            meaning="largest absorber travel x_m - x_M",
        ),
        Metric(
            name="return_time",
            unit="s",
            signal=None,
            extreme="max",
            timed=False,
            smoothable=False,
            meaning="time from the last round back into battery (x_M = x_r + 1 mm)",
            kind="return",
            envelope=True,
        ),
        Metric(
            name="battery_speed",
            unit="m/s",
            signal=None,
            extreme="max",
            timed=False,
            smoothable=False,
            meaning="speed of the barrel arriving in battery",
            kind="return",
            envelope=True,
        ),
        Metric(
            name="residual_displacement",
            unit="m",
            signal=None,
            extreme="max",
            timed=False,
            smoothable=False,
            meaning="barrel displacement from its rest at the end, x_M(t1) - x_r",
            kind="final",
            envelope=True,
        ),
        Metric(
            name="stability_margin",
            unit="",
            signal="margin",
            extreme="min",
            timed=True,
            smoothable=False,
            meaning="least stability margin of the mount",
            envelope=True,
        ),
        Metric(
            name="peak_pull_force",
            unit="N",
            signal="pull",
            extreme="max",
            timed=True,
            smoothable=True,
            meaning="peak forward pull on the mount, max(0, -F_AN)",
            envelope=True,
        ),
        Metric(
            name="peak_mount_load",
            unit="N",
            signal=None,
            extreme="max",
            timed=True,
            smoothable=False,
            meaning="peak load on the mount either way, max |F_AN|",
            kind="either",
            envelope=True,
        ),
    )
}

#: The metrics that are extremes of a signal over the solve, the peak loop's tracked
#: quantities.
EXTREMES: dict[str, Metric] = {n: m for n, m in METRICS.items() if m.kind == "extreme"}

#: The `Peaks` fields of the firing envelope: NaN (`returned` False) for a design without
#: it, whose solve stops at its last peak; `stability_margin` also without a mount.
ENVELOPE_FIELDS: tuple[str, ...] = (
    *(n for n, m in METRICS.items() if m.envelope),
    *(m.time_field for m in METRICS.values() if m.envelope and m.timed),
    "returned",
)


def worst_case(
    values: Mapping[str, Any], xp: Any = np, quantile: float | None = None
) -> dict[str, Any]:
    """The worst case of each quantity over a scatter of designs (`values`: name →
    values, the scatter along every axis): a metric's own extreme (the least stroke, the
    greatest peak); any other quantity (a smooth maximum) its greatest. With `quantile`
    q, the q-quantile towards the worst instead (q of the scatter is no worse; the
    `1 - q` quantile of a metric whose extreme is its least; linear interpolation, as
    `numpy.quantile`; q = 1 is the worst case). `xp`: `numpy` or `jax.numpy`."""
    out = {}
    for name, v in values.items():
        least = name in METRICS and METRICS[name].extreme == "min"
        if quantile is None:
            out[name] = xp.min(v) if least else xp.max(v)
        else:
            out[name] = xp.quantile(v, 1.0 - quantile if least else quantile)
    return out


def metric(name: str) -> Metric:
    """The registry entry of metric `name`; a `ParameterError` listing the metrics if
    there is none."""
    try:
        return METRICS[name]
    except KeyError:
        raise ParameterError(f"unknown metric {name!r}; choose from {', '.join(METRICS)}") from None


def _reported_fields() -> dict[str, str]:
    fields = {}
    for m in METRICS.values():
        fields[m.name] = m.key
        if m.timed:
            fields[m.time_field] = m.time_key
    fields["returned"] = "returned"
    fields["num_steps"] = "num_steps"
    return fields


#: `Peaks` field → JSON / CSV key, for every reported field, in output order.
PEAK_FIELDS: dict[str, str] = _reported_fields()


def gradient_key(metric_name: str, parameter: str) -> str:
    """The CSV (and store) column of the derivative of metric `metric_name` with respect
    to the flat parameter `parameter`: `d(peak_anchoring_force_N)/d(gap)`."""
    return f"d({METRICS[metric_name].key})/d({parameter})"


class Peaks(eqx.Module):
    """Peak metrics of one solve (scalars; leading batch axes under `vmap`).

    Peaks are located between solver steps, not on a save grid (`docs/model.md`).

    - `peak_displacement` (m), `peak_displacement_time` (s): max of x_M.
    - `peak_anchoring_force` (N), `peak_anchoring_force_time` (s): max of F_AN.
    - `peak_contact_force` (N), `peak_contact_force_time` (s): max of F_ct (0, at t = 0,
      when there is no contact or no absorber).
    - `min_stroke`, `max_stroke` (m): min and max of the absorber's travel relative to the
      barrel, x_m − x_M (both 0 for the simplified model).
    - The firing envelope's metrics (`docs/model.md`), for designs with any part of it
      (rails, the battery stop, the counter-recoil buffer, a mount; NaN for the others,
      whose solve stops once the peaks are certain): `return_time` (s), from the last
      round's firing until the barrel comes forward through `x_M = x_r + 1 mm`, and
      `battery_speed` (m/s), `−v_M` then; `returned`, whether it did before `t1` (if
      not, `return_time` is the time observed, `t1` less the last firing, a lower bound,
      and `battery_speed` 0: neither is reported, `to_dict`); `residual_displacement`
      (m), `x_M(t1) − x_r`; `stability_margin`, `stability_margin_time` (s), the mount's
      least margin (NaN without a mount, `mount_mass = 0`); `peak_pull_force` (N), the
      largest forward pull `max(0, −F_AN)`, with the time `F_AN` is least, and
      `peak_mount_load` (N), `max |F_AN|`, with its time.
    - Displacements are measured from the gun's static rest `x_r` (`static_rest`; 0
      without a battery stop), where it starts.
    - `num_steps`: accepted steps; `num_attempts`: accepted + rejected. The solve stops
      before `t1` once the mechanical energy left shows that no metric can exceed its
      peak again (`future_metric_bounds`); the peaks are those over all of `[0, t1]`.
    - `status`: a `Status`; anything but `Status.ok` means the other fields are not to be
      trusted.

    The fields are those of `METRICS` (and their times); `Peaks.of` builds it by name.
    """

    peak_displacement: jax.Array
    peak_displacement_time: jax.Array
    peak_anchoring_force: jax.Array
    peak_anchoring_force_time: jax.Array
    peak_contact_force: jax.Array
    peak_contact_force_time: jax.Array
    min_stroke: jax.Array
    max_stroke: jax.Array
    return_time: jax.Array
    battery_speed: jax.Array
    residual_displacement: jax.Array
    stability_margin: jax.Array
    stability_margin_time: jax.Array
    peak_pull_force: jax.Array
    peak_pull_force_time: jax.Array
    peak_mount_load: jax.Array
    peak_mount_load_time: jax.Array
    returned: jax.Array
    num_steps: jax.Array
    num_attempts: jax.Array
    status: Any

    @classmethod
    def of(
        cls,
        values: dict[str, Any],
        times: dict[str, Any],
        num_steps,
        num_attempts,
        status,
        returned,
    ) -> Peaks:
        """Build from `values` and `times` keyed by metric name (every metric of
        `METRICS`; times of the timed ones)."""
        fields = {name: values[name] for name in METRICS}
        fields |= {m.time_field: times[m.name] for m in METRICS.values() if m.timed}
        return cls(
            **fields,
            returned=returned,
            num_steps=num_steps,
            num_attempts=num_attempts,
            status=status,
        )

    def metrics(self) -> dict[str, Any]:
        """The metric values by name (`METRICS`), as in objectives and constraints."""
        return {name: getattr(self, name) for name in METRICS}

    def to_dict(self) -> dict:
        """JSON-ready dict of one (unbatched) solve; the keys of `recoil-jax simulate
        --json` (`PEAK_FIELDS`, then `status`: `"ok"` or why the solve failed)."""
        out: dict[str, Any] = {
            key: reported_value(field, getattr(self, field), self.returned)
            for field, key in PEAK_FIELDS.items()
        }
        if np.isnan(float(self.residual_displacement)):
            out["returned"] = None
        return out | {"status": Status[self.status]}


def reported_value(field: str, value: Any, returned: Any) -> Any:
    """A `Peaks` field's value as reported (`PEAK_FIELDS`): a float, an int
    (`num_steps`), a bool (`returned`), or None where there is none: an envelope metric
    a design has not got (NaN), and the return's metrics of a barrel that did not come
    back."""
    if field == "num_steps":
        return int(value)
    if field == "returned":  # NaN in a sweep's arrays where there is no envelope
        return None if np.isnan(float(value)) else bool(value)
    value = float(value)
    name = field if field in METRICS else field.removesuffix("_time")
    if name in METRICS and METRICS[name].envelope:
        if np.isnan(value) or (is_return_field(field) and not bool(returned)):
            return None
    return value


def is_return_field(field: str) -> bool:
    """Whether a `Peaks` field (a metric or its time) is the return's: none is reported
    for a barrel that has not returned."""
    name = field if field in METRICS else field.removesuffix("_time")
    return name in METRICS and METRICS[name].kind == "return"


class PeakGradients(eqx.Module):
    """Derivatives of the peak metrics with respect to the parameters `wrt` (flat names,
    static). One field per metric of `METRICS`, each of shape `(..., len(wrt))`; units:
    metric unit per parameter unit.

    There is no gradient of the peak *times*: a peak can jump from one local maximum to
    another, and its time with it.
    """

    peak_displacement: jax.Array
    peak_anchoring_force: jax.Array
    peak_contact_force: jax.Array
    min_stroke: jax.Array
    max_stroke: jax.Array
    return_time: jax.Array
    battery_speed: jax.Array
    residual_displacement: jax.Array
    stability_margin: jax.Array
    peak_pull_force: jax.Array
    peak_mount_load: jax.Array
    wrt: tuple[str, ...] = eqx.field(static=True)

    @classmethod
    def of(cls, gradients: dict[str, Any], wrt: tuple[str, ...]) -> PeakGradients:
        """Build from gradients keyed by metric name (every metric of `METRICS`)."""
        return cls(**{name: gradients[name] for name in METRICS}, wrt=wrt)

    def to_dict(self) -> dict[str, dict[str, float]]:
        """`{metric key: {parameter: derivative}}` for one (unbatched) design, with the
        JSON keys of `METRICS` (`peak_anchoring_force_N`, ...)."""
        return {
            m.key: {n: float(getattr(self, m.name)[j]) for j, n in enumerate(self.wrt)}
            for m in METRICS.values()
        }
