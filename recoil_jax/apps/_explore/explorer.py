"""`recoil-jax explore`: a live design explorer (Panel, Bokeh plots).

A field for every parameter, grouped by part (the barrel, the absorber and its contact,
the breech load, the throttling orifice, the gas recuperator; a part is off at its "none"
value: m = 0, piston_area = 0, recuperator_force = 0), limits on the travels, and views
that follow every change: the displacements x_M and x_m, the anchoring and the contact
force against time (each on its axis), the peaks against their limits, and the gradient
of the peak anchoring force as bars ("which knob matters here"). One compiled program per model
structure (which parts are on) computes the history, the peaks and the gradient; after
its first run an update takes milliseconds. It runs in a notebook (`explorer()`) and as
a page (`recoil-jax explore`).
"""

from __future__ import annotations

import html
import re
import socket
import time
from typing import Any

import jax.numpy as jnp
import numpy as np

import recoil_jax as rj
import recoil_jax.extend as rjx

from .._files.inputs import parse_assignments
from .envelope_view import EnvelopeView

__all__ = ["EXPLORER_KNOTS", "Explorer", "check_listen", "explorer", "main_explore"]

#: Orifice knots the explorer offers (when `piston_area > 0`).
EXPLORER_KNOTS = 4

#: The sidebar's width (px): every card takes all of it.
_SIDEBAR = 330

# Drawn points per history: enough for the plots, few enough to send at once.
_POINTS = 800

#: The travel limits the peaks are held against: each one's field label and start value.
_LIMITS = {
    "peak_displacement": ("barrel travel limit (m)", 0.25),
    "max_stroke": ("absorber travel limit (m)", 0.15),
}

#: The size and tools of each plot against time.
_TIME_PLOT: dict[str, Any] = dict(
    height=230, sizing_mode="stretch_width", tools="pan,wheel_zoom,reset"
)


@rjx.structure_jit
def _compute(params, ts, wrt):
    """The history at `ts`, the peaks and the peak anchoring force's gradient with
    respect to `wrt`: one program per model structure."""
    history = rj.simulate(params, ts=ts, throw=False)
    # The peaks as `simulate` reports them (default solver options); the gradient from
    # forward sensitivities at their own, tighter, tolerance.
    peaks = rj.peak_metrics(params)
    _, gradients = rj.peak_jacobian(params, wrt=wrt, throw=False)
    return history, peaks, gradients.peak_anchoring_force


def _start_values(values: dict[str, float] | None) -> dict[str, float]:
    """Every field's start value by flat name: the parameters' defaults (and the offered
    orifice knots) overridden by the design `values` (validated, as `simulate` reads
    them)."""
    start = rj.params_to_values(rj.params_from_values(values or {}))
    defaults = {name: float(p.default) for name, p in rj.PARAMETERS.items()}
    defaults |= {f"orifice_{i}": 4e-4 for i in range(EXPLORER_KNOTS)}
    defaults |= {k: float(np.asarray(v)) for k, v in start.items()}
    return {k: v for k, v in defaults.items() if rj.PARAMETERS[k].group in rjx.GROUPS}


def _time_plot(title: str, y_axis_label: str, x_range=None):
    """An empty plot against time (s), on the time axis `x_range` where given (to pan and
    zoom with the plot it comes from)."""
    from bokeh.plotting import figure

    shared = {} if x_range is None else {"x_range": x_range}
    return figure(
        title=title, x_axis_label="time (s)", y_axis_label=y_axis_label, **shared, **_TIME_PLOT
    )


def _tuned(values: dict[str, float]) -> tuple[str, ...]:
    """The parameters whose gradient the bars show: every continuous parameter of the
    parts that are on (`values` holds only those; counts such as `shots` are not
    differentiable, and `m = 0` means no absorber)."""
    return tuple(
        name for name in values if name != "shots" and not (name == "m" and not values[name])
    )


class Explorer:
    """The explorer's state and views. `panel()` is the layout; `set(name, value)` and
    `update()` drive it from code (the tests do).

    Each field is text, read as the command line reads `name=value` (so `abc` and `nan`
    are refused with the command line's message); an invalid field shows its message
    right under it, in its card, and the views are cleared until it is fixed. A failed
    solve (a bottomed-out recuperator) shows why instead of peaks and gradient bars. While
    a new structure compiles (about 20 s the first time), the views show a spinner."""

    def __init__(
        self,
        values: dict[str, float] | None = None,
        duration: float = 2.0,
        trace: rjx.Trace | None = None,
    ):
        import panel as pn

        self.pn = pn
        self.fields: dict[str, Any] = {}
        self.field_errors: dict[str, Any] = {}
        for name, value in _start_values(values).items():
            self._add_field(name, value)
        self.duration = self._watched(
            pn.widgets.FloatInput(
                label="shown time (s)", value=duration, start=0.01, sizing_mode="stretch_width"
            )
        )
        self.limits = {
            name: self._watched(
                pn.widgets.FloatInput(label=label, value=value, sizing_mode="stretch_width")
            )
            for name, (label, value) in _LIMITS.items()
        }
        self._add_history_plots()
        self.measured = None if trace is None else self._overlay(trace)
        self._add_bar_plot()
        self.envelope = EnvelopeView(pn, self._watched, self.limits["peak_displacement"])
        self.peaks_pane = pn.pane.HTML("", css_classes=["peaks"])
        self.message = pn.pane.HTML("", css_classes=["message"])
        self.timing = pn.pane.HTML("", css_classes=["timing"])
        self.update_ms: float | None = None
        self.cards = self._cards()
        self.views = pn.Column(
            self.message,
            self.peaks_pane,
            self.timing,
            self.motion_plot,
            self.force_plot,
            self.contact_plot,
            self.bar_plot,
            self.envelope.panel,
            sizing_mode="stretch_width",
        )
        self._structure: tuple | None = None
        self._update(time.perf_counter())

    def _watched(self, widget):
        """`widget`, which now updates the views whenever its value changes."""
        widget.param.watch(lambda event: self.update(), "value")
        return widget

    def _add_field(self, name: str, value: float) -> None:
        """A parameter's text field (its unit in the label, its meaning and documented
        range in the description) and the pane under it for its message."""
        parameter = rj.PARAMETERS[name]
        unit = f" ({parameter.unit})" if parameter.unit else ""
        low, high = parameter.documented or (None, None)
        text = f"{int(value)}" if parameter.integer else f"{value:.8g}"
        widget = self.pn.widgets.TextInput(
            label=name + unit, value=text, sizing_mode="stretch_width"
        )
        widget.description = f"{parameter.meaning}; documented {low:g} to {high:g}"
        widget.css_classes = [f"field-{name}"]
        self.fields[name] = self._watched(widget)
        self.field_errors[name] = self.pn.pane.HTML(
            "", css_classes=[f"error-{name}"], sizing_mode="stretch_width", margin=(0, 10)
        )

    def _add_history_plots(self) -> None:
        """The histories' sources (and the bars'), and the plots against time: the
        displacements, then the anchoring force (kN) and the contact force (tens of kN),
        each on its axis, all three sharing the time axis."""
        from bokeh.models import ColumnDataSource

        self.motion = ColumnDataSource({"t": [], "x_M": [], "x_m": []})
        self.force = ColumnDataSource({"t": [], "F_AN": [], "F_ct": []})
        self.bars = ColumnDataSource({"name": [], "change": []})
        self.motion_plot = _time_plot("displacements", "displacement (mm)")
        self.motion_plot.line(
            "t", "x_M", source=self.motion, legend_label="barrel x_M", line_width=2
        )
        self.motion_plot.line(
            "t",
            "x_m",
            source=self.motion,
            legend_label="absorber x_m",
            color="darkorange",
            line_width=2,
        )
        shared = self.motion_plot.x_range
        self.force_plot = _time_plot("anchoring force into the mounting", "F_AN (kN)", shared)
        self.force_plot.line("t", "F_AN", source=self.force, color="black", line_width=2)
        self.contact_plot = _time_plot(
            "contact force between barrel and absorber", "F_ct (kN)", shared
        )
        self.contact_plot.line("t", "F_ct", source=self.force, color="firebrick", line_width=2)

    def _add_bar_plot(self) -> None:
        """The gradient bars: the peak anchoring force's change for +1 % of each
        parameter, one bar a parameter (their names the plot's range)."""
        from bokeh.models import FactorRange
        from bokeh.plotting import figure

        self.bar_range = FactorRange()
        self.bar_plot = figure(
            title="peak anchoring force: change for +1 % of each parameter",
            y_range=self.bar_range,
            x_axis_label="change (N)",
            height=320,
            sizing_mode="stretch_width",
            tools="",
        )
        self.bar_plot.hbar(
            y="name", right="change", height=0.7, source=self.bars, color="steelblue"
        )

    def _cards(self) -> dict[str, Any]:
        """One card a part, holding its fields (each with its message pane); the parts a
        designer sets first open (`rjx.Group.first`: the barrel's and the absorber's), the
        others collapsed."""
        groups: dict[str, list] = {}
        for name, widget in self.fields.items():
            groups.setdefault(rj.PARAMETERS[name].group, []).extend(
                [widget, self.field_errors[name]]
            )
        return {
            group: self.pn.Card(
                *widgets,
                title=rjx.GROUPS[group].title,
                collapsed=not rjx.GROUPS[group].first,
                sizing_mode="stretch_width",
            )
            for group, widgets in groups.items()
        }

    def _overlay(self, trace: rjx.Trace):
        """A measured trace's signals as points over the live histories (the same units:
        mm and kN), so a design can be matched to a firing test by hand."""
        from bokeh.models import ColumnDataSource

        scale = {"x_M": 1e3, "x_m": 1e3, "F_AN": 1e-3, "F_ct": 1e-3}
        plots = {"x_M": self.motion_plot, "x_m": self.motion_plot, "F_AN": self.force_plot,
                 "F_ct": self.contact_plot}  # fmt: skip
        columns: dict[str, Any] = {"t": trace.t.tolist()} | {
            name: (trace.signals[name] * scale[name]).tolist()
            for name in scale
            if name in trace.signals
        }
        source = ColumnDataSource(columns)
        for name in columns:
            if name != "t":
                plots[name].scatter("t", name, source=source, size=3, color="gray", alpha=0.5,
                                    legend_label=f"measured {name}")  # fmt: skip
        return source

    def values(self) -> dict[str, float]:
        """The design the fields describe, by flat name, without the parts that are off
        (so that it is the design `simulate` builds from the same items). Raises
        `ParameterError` (naming the field) for a field that is not a number."""
        values = parse_assignments([f"{name}={w.value}" for name, w in self.fields.items()])
        return {
            name: value
            for name, value in values.items()
            if name == "m" or not _off(values).get(rj.PARAMETERS[name].group, False)
        }

    def set(self, name: str, value: float | str) -> None:
        """Set one field (and so update the views)."""
        self.fields[name].value = str(value)

    def update(self) -> None:
        """Recompute and redraw. On a page, a design of a new structure first shows a
        spinner (sent at once), then compiles."""
        start = time.perf_counter()
        document = self.pn.state.curdoc
        served = document is not None and document.session_context is not None
        if served and document is not None and self._new_structure():
            # After a pause, so that the page has the spinner before the compilation
            # holds the server's event loop (a next-tick callback runs before the send).
            self.views.loading = True
            self.message.object = (
                '<div class="busy">compiling the program of this structure (once per '
                "structure, seconds)...</div>"
            )
            document.add_timeout_callback(lambda: self._update(start), 100)
        else:
            self._update(start)

    def _new_structure(self) -> bool:
        """Whether the fields describe a design of another structure than the one shown
        (False while a field is invalid: nothing will compile)."""
        try:
            return _structure(self.values()) != self._structure
        except rj.ParameterError:
            return False

    def _update(self, start: float) -> None:
        """Compute and show, then take the spinner away."""
        # One message to the page for all the views' changes.
        with self.pn.io.hold():
            try:
                self._compute_and_show(start)
            finally:
                self.views.loading = False

    def _compute_and_show(self, start: float) -> None:
        """Solve the fields' design and show its histories, peaks and gradient bars (or
        why not); the time since `start` is the update's."""
        for pane in self.field_errors.values():
            pane.object = ""
        self.message.object = ""
        try:
            values = self.values()
            self._titles(values)
            params = rj.params_from_values(values)
            duration = self.duration.value
            if not duration or duration <= 0:
                raise rj.ParameterError("shown time must be > 0 s")
            wrt = _tuned(values)
            ts = jnp.linspace(0.0, float(duration), _POINTS)
            history, peaks, gradient = _compute(params, ts, wrt)
            self._structure = _structure(values)
        except rj.ParameterError as error:
            self._show_error(str(error))
            return
        t = np.asarray(history.ts)
        self.motion.data = {
            "t": t,
            "x_M": 1e3 * np.asarray(history.x_M),
            "x_m": 1e3 * np.asarray(history.x_m),
        }
        self.force.data = {
            "t": t,
            "F_AN": 1e-3 * np.asarray(history.anchoring_force),
            "F_ct": 1e-3 * np.asarray(history.contact_force),
        }
        if not bool(np.all(peaks.status == rj.Status.ok)):
            # No peaks, limits or gradient of a solve that did not finish.
            note = html.escape(rjx.status_messages(peaks.status)[0])
            self.message.object = f'<div class="error" style="color:#b00020">solver: {note}</div>'
            # The reason is in the message above: said once.
            self.peaks_pane.object = '<div class="failed">no peaks: the solve failed</div>'
            self.bar_range.factors = []
            self.bars.data = {"name": [], "change": []}
        else:
            change = np.asarray(gradient) * np.asarray([values[name] for name in wrt]) * 0.01
            order = np.argsort(np.abs(change))
            names = [wrt[i] for i in order]
            self.bar_range.factors = names
            self.bars.data = {"name": names, "change": change[order]}
            hazards = rj.peaks_hazards(params, peaks)
            self.peaks_pane.object = self._peaks_html(peaks.to_dict()) + _hazards_html(hazards)
        self.envelope.update(values, duration)
        self.update_ms = 1e3 * (time.perf_counter() - start)
        self.timing.object = f'<span class="update-ms">updated in {self.update_ms:.1f} ms</span>'

    def _show_error(self, message: str) -> None:
        """The message under the field it names (its card opened), else above the views;
        the views are cleared: they would show a design the fields no longer describe."""
        text = f'<div class="error" style="color:#b00020">{html.escape(message)}</div>'
        named = [
            (found.start(), name)
            for name in self.fields
            if (found := re.search(rf"(?<![\w<])({re.escape(name)})(?![\w>])", message))
        ]
        if named:
            name = min(named)[1]
            self.field_errors[name].object = text
            self.cards[rj.PARAMETERS[name].group].collapsed = False
        else:
            self.message.object = text
        self.motion.data = {"t": [], "x_M": [], "x_m": []}
        self.force.data = {"t": [], "F_AN": [], "F_ct": []}
        self.bar_range.factors = []
        self.bars.data = {"name": [], "change": []}
        self.peaks_pane.object = '<div class="failed">no results until the design is valid</div>'
        self.envelope.clear()
        self.timing.object = ""

    def _titles(self, values: dict[str, float]) -> None:
        """Each card says whether its part is on, and what turns it off."""
        off = _off(values)
        for group, card in self.cards.items():
            title, switches = rjx.GROUPS[group].title, rjx.GROUPS[group].off
            if switches:
                switch = " = ".join((*switches, "0"))
                title += f" (off: {switch})" if off[group] else " (on)"
            card.title = title

    def _peaks_html(self, peaks: dict) -> str:
        """The peaks as an HTML table, each travel held against its limit."""
        rows = []
        for name in (
            "peak_displacement",
            "peak_anchoring_force",
            "peak_contact_force",
            "max_stroke",
        ):
            metric = rj.METRICS[name]
            value = peaks[metric.key]
            limit = self.limits.get(name)
            state = ""
            if limit is not None and limit.value is not None:
                ok = value <= limit.value
                state = f" {'within' if ok else 'over'} the limit {limit.value:g} {metric.unit}"
            rows.append(
                f'<tr><td>{metric.meaning}</td><td id="{name}" style="text-align:right">'
                f"{value:.6g}</td><td>{metric.unit}{state}</td></tr>"
            )
        return "<table>" + "".join(rows) + f"</table><small>status: {peaks['status']}</small>"

    def panel(self):
        """The layout: a heading; fields on the left (one card per part, each as wide as
        the sidebar), views on the right."""
        pn = self.pn
        sidebar = pn.Column(
            self.duration,
            *self.limits.values(),
            *self.cards.values(),
            pn.Card(*self.envelope.sidebar(), title="Firing envelope: elevations and limits",
                    collapsed=False, sizing_mode="stretch_width"),
            width=_SIDEBAR,
        )  # fmt: skip
        heading = pn.pane.Markdown(
            "## recoil-jax design explorer\n"
            "Type a value and press Enter: the histories, the peaks and the gradient follow.",
            sizing_mode="stretch_width",
        )
        return pn.Column(
            heading, pn.Row(sidebar, self.views, sizing_mode="stretch_width"),
            sizing_mode="stretch_width",
        )  # fmt: skip


def _hazards_html(hazards: list[dict[str, str]]) -> str:
    """The design's hazards (`rj.peaks_hazards`), named unasked, one line each."""
    if not hazards:
        return '<div class="hazards">hazards: none</div>'
    lines = "".join(
        f'<li class="hazard" id="hazard-{h["name"]}"><b>{h["name"]}</b>: '
        f"{html.escape(h['sentence'])}</li>"
        for h in hazards
    )
    return f'<div class="hazards" style="color:#b35900">hazards:<ul>{lines}</ul></div>'


def _off(values: dict[str, float]) -> dict[str, bool]:
    """Which parts the values turn off: those whose switches (`rjx.Group.off`) are all
    0, and the load at the paper's one impulse."""
    off = {
        name: not any(values.get(switch) for switch in group.off)
        for name, group in rjx.GROUPS.items()
        if group.off
    }
    return off | {"load": values.get("pulse_time") == 0 and values.get("shots") == 1}


def _structure(values: dict[str, float]) -> tuple:
    """What decides the compiled program: which parts are on, and the counts."""
    off = _off(values)
    return (*sorted(k for k, v in off.items() if not v), values.get("shots"))


def explorer(values: dict[str, float] | None = None, duration: float = 2.0, trace=None):
    """The design explorer as a Panel layout, for a notebook cell (after
    `import panel as pn; pn.extension()`), starting from the design `values` (flat
    names; default the paper's best absorber) and showing `duration` seconds; with a
    measured `trace` (`rj.read_trace`), its signals as points over the histories."""
    return Explorer(values, duration, trace).panel()


def main_explore(args, values: dict[str, float]) -> int:
    """Serve the explorer (`recoil-jax explore`), one session per browser tab."""
    import panel as pn

    check_listen(args.address, args.port)
    trace = rj.read_trace(args.trace) if args.trace else None
    Explorer(values, trace=trace)  # bad input fails here, before the server starts
    pn.extension()
    print(f"recoil-jax explore: http://{_host(args.address)}:{args.port}/", flush=True)
    origins = {f"{host}:{args.port}" for host in ("localhost", "127.0.0.1", args.address)}
    pn.serve(
        lambda: Explorer(values, trace=trace).panel(),
        port=args.port,
        address=args.address,
        show=not args.no_browser,
        title="recoil-jax explorer",
        websocket_origin=sorted(origins),
        verbose=False,
    )
    return 0


def _host(address: str) -> str:
    """An address as it goes in a URL (an IPv6 one in brackets)."""
    return f"[{address}]" if ":" in address else address


def check_listen(address: str, port: int) -> None:
    """That the server can listen on `address:port` (before it starts, which would
    otherwise print its URL and then fail with a traceback): one line if not."""
    if not 1 <= port <= 65535:
        raise rj.ParameterError(f"--port {port} is invalid: valid is 1 to 65535")
    try:
        infos = socket.getaddrinfo(address, port, type=socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError) as error:
        raise rj.ParameterError(
            f"--address {address!r} is not an address of this machine ({error}): give a "
            "host name or IP address, e.g. localhost or 0.0.0.0"
        ) from None
    family, kind, protocol, _, where = infos[0]
    with socket.socket(family, kind, protocol) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind(where)
        except OSError as error:
            raise rj.ParameterError(
                f"cannot listen on {address}:{port} ({error.strerror}): give another "
                "--port, or an --address of this machine"
            ) from None
