"""The explorer's envelope view (issue 62): a design with the firing envelope solved at
each of its firing conditions (elevations), its histories side by side, each metric held
against its limit at each condition, and the hazards each condition has, named unasked
(`rj.peaks_hazards`). It follows every change of the explorer's fields, as its other
views do; one program per model structure (`rj.simulate`), whatever the elevations."""

from __future__ import annotations

import html
from typing import Any

import numpy as np

import recoil_jax as rj
import recoil_jax.extend as rjx

from .._files.inputs import parse_assignments

__all__ = ["EnvelopeView", "parse_elevations"]

#: The metrics the view holds at each condition, with each limit's field label, kind and
#: start value (None: shown without a limit). The barrel's travel takes the explorer's
#: own limit (its "barrel travel limit").
_METRICS: dict[str, tuple[str, str, float] | None] = {
    "peak_mount_load": None,
    "peak_anchoring_force": None,
    "peak_pull_force": None,
    "peak_displacement": None,
    "return_time": ("return time limit (s)", "max", 2.5),
    "battery_speed": ("battery speed limit (m/s)", "max", 0.5),
    "residual_displacement": ("distance from rest at t1, limit (m)", "max", 1e-3),
    "stability_margin": ("least stability margin", "min", 0.1),
}

#: The elevations (degrees) the view starts with: the shipped envelope study's.
_START = "0, 35, 70"
#: The most conditions the view solves at once.
_MAX_CONDITIONS = 6


def parse_elevations(text: str) -> list[float]:
    """The elevations (degrees) of the view's field: numbers separated by commas, each
    in the valid range of `elevation` (`ParameterError` naming the field otherwise)."""
    items = [item.strip() for item in str(text).split(",") if item.strip()]
    if not items or len(items) > _MAX_CONDITIONS:
        raise rj.ParameterError(
            f"elevations: give 1 to {_MAX_CONDITIONS} elevations in degrees, separated by "
            f"commas (got {text!r})"
        )
    values = [parse_assignments([f"elevation={item}"])["elevation"] for item in items]
    for value in values:
        rj.params_from_values({"elevation": value})  # its valid range, named
    return values


class EnvelopeView:
    """The view's widgets, plots and panes. `update(values, duration)` solves the design
    `values` (flat names, as the explorer's fields give them) at each elevation and
    shows it; `clear(note)` empties it."""

    def __init__(self, pn, watched, travel_limit):
        from bokeh.models import ColumnDataSource

        self.pn = pn
        self.travel_limit = travel_limit
        self.elevations = watched(
            pn.widgets.TextInput(
                name="elevations", value=_START, sizing_mode="stretch_width",
            )
        )  # fmt: skip
        self.elevations.css_classes = ["field-elevations"]
        self.limits = {
            name: watched(
                pn.widgets.FloatInput(name=label, value=value, sizing_mode="stretch_width")
            )
            for name, limit in _METRICS.items()
            if limit is not None
            for label, _, value in [limit]
        }
        self.sources = [
            ColumnDataSource({"t": [], "x_M": [], "F_AN": []}) for _ in range(_MAX_CONDITIONS)
        ]
        self.force_plots = []
        self.motion_plots = []
        for source in self.sources:
            force = _small_plot("F_AN (kN)")
            force.line("t", "F_AN", source=source, color="black", line_width=2)
            motion = _small_plot("x_M from rest (mm)", force.x_range)
            motion.line("t", "x_M", source=source, color="steelblue", line_width=2)
            self.force_plots.append(force)
            self.motion_plots.append(motion)
        self.forces = pn.Row(sizing_mode="stretch_width")
        self.motions = pn.Row(sizing_mode="stretch_width")
        self.table = pn.pane.HTML("", css_classes=["envelope-metrics"], sizing_mode="stretch_width")
        self.hazards = pn.pane.HTML("", css_classes=["envelope-hazards"])
        self.message = pn.pane.HTML("", css_classes=["envelope-message"])
        self.panel = pn.Card(
            self.message,
            self.table,
            self.hazards,
            self.forces,
            self.motions,
            title="Firing envelope: the design at each elevation",
            sizing_mode="stretch_width",
            css_classes=["envelope-view"],
        )

    def sidebar(self) -> list:
        """The view's fields: the elevations, then the limits."""
        return [self.elevations, *self.limits.values()]

    def clear(self, note: str = "") -> None:
        """No results: `note` says why (HTML-escaped), or nothing."""
        self.message.object = (
            f'<div class="envelope-note">{html.escape(note)}</div>' if note else ""
        )
        self.table.object = ""
        self.hazards.object = ""
        self.forces.objects = []
        self.motions.objects = []
        for source in self.sources:
            source.data = {"t": [], "x_M": [], "F_AN": []}

    def update(self, values: dict[str, float], duration: float) -> None:
        """Solve `values` at each elevation and show it (the view's note says why not)."""
        if not any(rj.PARAMETERS[name].envelope for name in values):
            self.clear(
                "no firing envelope: give an elevation, rail friction, a battery stop, a "
                "counter-recoil buffer or a mount to see the design at each elevation"
            )
            return
        try:
            elevations = parse_elevations(self.elevations.value)
            designs = [rj.params_from_values(values | {"elevation": e}) for e in elevations]
        except rj.ParameterError as error:
            self.clear(str(error))
            self.message.object = (
                f'<div class="error" style="color:#b00020">{html.escape(str(error))}</div>'
            )
            return
        ts = np.linspace(0.0, float(duration), 400)
        solved = [rj.simulate(params, ts=ts, throw=False) for params in designs]
        self.message.object = ""
        self.forces.objects = self.force_plots[: len(designs)]
        self.motions.objects = self.motion_plots[: len(designs)]
        rows: dict[str, list[str]] = {name: [] for name in _METRICS}
        hazards = []
        for k, (elevation, params, history) in enumerate(
            zip(elevations, designs, solved, strict=True)
        ):
            x = np.asarray(history.x_M)
            self.sources[k].data = {
                "t": np.asarray(history.ts),
                "x_M": 1e3 * (x - x[0]),
                "F_AN": 1e-3 * np.asarray(history.anchoring_force),
            }
            self.force_plots[k].title.text = f"{elevation:g}°: force on the mount"
            self.motion_plots[k].title.text = f"{elevation:g}°: recoil"
            peaks = history.peaks
            if not bool(np.all(peaks.status == rj.Status.ok)):
                note = rjx.status_messages(peaks.status)[0]
                for name in _METRICS:
                    rows[name].append(f'<td class="failed">{html.escape(note)}</td>')
                continue
            report = peaks.to_dict()
            for name in _METRICS:
                rows[name].append(self._cell(name, k, report))
            found = rj.peaks_hazards(params, peaks)
            hazards.append(_hazard_lines(k, elevation, found))
        header = "".join(f"<th>{e:g}°</th>" for e in elevations)
        body = "".join(
            f"<tr><td>{rj.METRICS[name].label}</td>{''.join(cells)}</tr>"
            for name, cells in rows.items()
        )
        self.table.object = f"<table><tr><th></th>{header}</tr>{body}</table>"
        self.hazards.object = "".join(hazards)

    def _cell(self, name: str, k: int, report: dict) -> str:
        """One metric at condition `k`, held against its limit (within / over)."""
        metric = rj.METRICS[name]
        value = report[metric.key]
        if value is None:
            text, state = "none", ""
            if name == "return_time" and report["returned"] is False:
                text, state = "never", "over"
        else:
            text, state = f"{value:.6g}", ""
            limit = self._limit(name)
            if limit is not None:
                kind, bound = limit
                ok = value <= bound if kind == "max" else value >= bound
                state = "within" if ok else "over"
        style = ' style="color:#b00020"' if state == "over" else ""
        return f'<td id="env-{name}-{k}" class="{state}"{style}>{text}</td>'

    def _limit(self, name: str) -> tuple[str, float] | None:
        """A metric's limit as `(kind, value)`, None without one (or an empty field)."""
        if name == "peak_displacement":
            value = self.travel_limit.value
            return None if value is None else ("max", value)
        limit = _METRICS[name]
        if limit is None or self.limits[name].value is None:
            return None
        return limit[1], self.limits[name].value


def _hazard_lines(k: int, elevation: float, hazards: list[dict[str, str]]) -> str:
    """The hazards of condition `k`, one line each (or "none")."""
    if not hazards:
        return f'<div id="env-hazards-{k}">{elevation:g}°: no hazard</div>'
    lines = "".join(
        f'<li class="hazard" id="env-hazard-{k}-{h["name"]}"><b>{h["name"]}</b>: '
        f"{html.escape(h['sentence'])}</li>"
        for h in hazards
    )
    return (
        f'<div id="env-hazards-{k}" style="color:#b35900">{elevation:g}°: hazards'
        f"<ul>{lines}</ul></div>"
    )


def _small_plot(y_axis_label: str, x_range=None) -> Any:
    from bokeh.plotting import figure

    shared = {} if x_range is None else {"x_range": x_range}
    return figure(
        x_axis_label="time (s)",
        y_axis_label=y_axis_label,
        height=200,
        width=260,
        tools="pan,wheel_zoom,reset",
        **shared,
    )
