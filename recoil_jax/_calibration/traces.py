"""Measured firing traces: reading them (`read_trace`) and what a calibration knows about
each firing (`Experiment`).

A trace is a CSV file with a header: `t` (s) and one column per measured signal, named
by the paper's symbols (`SIGNALS`) or `History`'s longer names (`SIGNAL_ALIASES`).
Samples may come at any times; an empty or NaN value is skipped (and counted), not read
as zero.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from .._model.derivatives import ABSORBER_SIGNALS, SIGNAL_ALIASES, SIGNALS
from .._model.parameter_table import parameter
from .._model.params import ForceTable, RecoilParams
from .._model.registry import Limits, ParameterError, check_value
from .._model.solve import History
from .._model.text_files import read_text, written

__all__ = [
    "TIME_COLUMNS",
    "T_SHIFT",
    "Experiment",
    "Trace",
    "known_values",
    "read_trace",
    "signal_name",
]

#: The names the time column may have.
TIME_COLUMNS = ("t", "t_s")

#: The trigger delay of a trace (s): the model's t = 0 is at the trace's `t = t_shift`.
#: A calibration may fit it (its documented range is the default bounds).
T_SHIFT = Limits(unit="s", lower=-1.0, upper=1.0, documented=(-0.01, 0.01), meaning="trigger delay")


def signal_name(column: str) -> str | None:
    """The signal (`SIGNALS`) a column header names, or None."""
    column = column.strip()
    if column in SIGNALS:
        return column
    return SIGNAL_ALIASES.get(column)


def _signal_list() -> str:
    return ", ".join([*SIGNALS, *SIGNAL_ALIASES])


@dataclasses.dataclass(frozen=True)
class Trace:
    """One measured firing: sample times `t` (s, shape `(n,)`, strictly increasing) and
    the measured `signals` by name (`SIGNALS`; shape `(n,)` each, NaN where a sample is
    missing). `skipped`: per signal, how many samples were empty or NaN; `source`: where
    it came from (a file, for messages)."""

    t: np.ndarray
    signals: Mapping[str, np.ndarray]
    source: str = "<arrays>"
    skipped: Mapping[str, int] = dataclasses.field(default_factory=dict)

    @classmethod
    def of(cls, t, source: str = "<arrays>", **signals) -> Trace:
        """A trace from arrays (`t` and signals by name, NaN for a missing sample),
        checked as a file is."""
        t = np.asarray(t, dtype=float)
        columns = {}
        for name, values in signals.items():
            signal = signal_name(name)
            if signal is None:
                raise ParameterError(
                    f"{source}: no signal {name!r}; the model has {_signal_list()}"
                )
            columns[signal] = np.asarray(values, dtype=float)
            if columns[signal].shape != t.shape:
                raise ParameterError(
                    f"{source}: {name} has {columns[signal].size} samples and t {t.size}"
                )
        skipped = {name: int(np.sum(~np.isfinite(v))) for name, v in columns.items()}
        return _checked(source, t, columns, skipped)

    @classmethod
    def of_history(
        cls, history: History, params: RecoilParams, source: str = "<simulated>"
    ) -> Trace:
        """The trace of a simulated `history` of `params` (`simulate`): its times, and
        every signal (`SIGNALS`) the design has (without an absorber, not those only an
        absorber has)."""
        names = [n for n in SIGNALS if params.absorber is not None or n not in ABSORBER_SIGNALS]
        return cls.of(history.ts, source, **{n: getattr(history, n) for n in names})

    def to_csv(self, path) -> Path:
        """Write the trace as `read_trace` reads it: the header `t` and the signals by the
        paper's symbols, every value as exactly as a float64 is written (a missing sample
        empty). Returns the path."""
        path = Path(path)
        names = list(self.signals)
        rows = zip(self.t.tolist(), *(self.signals[n].tolist() for n in names), strict=True)
        lines = [",".join(["t", *names])]
        lines += [",".join(repr(v) if math.isfinite(v) else "" for v in row) for row in rows]
        with written(path) as temporary:
            temporary.write_text("\n".join(lines) + "\n")
        return path

    def within(self, start: float, end: float) -> Trace:
        """The samples with `start <= t <= end` (s)."""
        keep = (self.t >= start) & (self.t <= end)
        if not keep.any():
            raise ParameterError(
                f"{self.source}: no sample within the window [{start:g}, {end:g}] s "
                f"(the trace spans {self.t[0]:g} to {self.t[-1]:g} s)"
            )
        signals = {k: v[keep] for k, v in self.signals.items()}
        return dataclasses.replace(self, t=self.t[keep], signals=signals)

    @property
    def samples(self) -> int:
        """The number of usable values over every signal."""
        return int(sum(np.isfinite(v).sum() for v in self.signals.values()))


def _checked(source: str, t: np.ndarray, columns: dict, skipped: dict, lines=None) -> Trace:
    """A checked `Trace`; `lines`: each sample's line in its file (for messages)."""

    def where(i: int) -> str:
        return f"line {lines[i]}" if lines is not None else f"sample {i + 1}"

    if t.ndim != 1 or t.size == 0:
        raise ParameterError(f"{source}: no samples")
    if not np.all(np.isfinite(t)):
        i = int(np.argmax(~np.isfinite(t)))
        raise ParameterError(f"{source}, {where(i)}: t is not a finite number")
    steps = np.diff(t)
    if np.any(steps <= 0):
        i = int(np.argmax(steps <= 0)) + 1
        raise ParameterError(
            f"{source}, {where(i)}: column t is not increasing "
            f"(t = {t[i]:g} s after {t[i - 1]:g} s)"
        )
    if not columns:
        raise ParameterError(f"{source}: no signal column; give one of {_signal_list()}")
    if not any(np.isfinite(v).any() for v in columns.values()):
        raise ParameterError(f"{source}: no usable sample (every value is empty or NaN)")
    return Trace(t, columns, source, skipped)


def read_trace(path) -> Trace:
    """Read a measured trace from a CSV file.

    The header names `t` (s; or `t_s`) and the measured signals: `x_M`, `x_m` (m), `v_M`,
    `v_m` (m/s), `F_AN`, `F_ct` (N), or `anchoring_force`, `contact_force`. Commas
    separate values; a byte-order mark, CRLF line ends, spaces around values, blank lines
    and lines starting with `#` are accepted. An empty or NaN value is skipped (counted
    in `Trace.skipped`); a row whose time is empty is skipped whole.

    **Raises:** `ParameterError` naming the file, the column and the line for a missing
    file, a header without `t`, an unknown or repeated column, a value that is not a
    number, a row of the wrong length, times that do not increase, or no usable sample.
    """
    source = str(path)
    text = read_text(Path(path), "trace")
    rows = [
        (number, line)
        for number, line in enumerate(text.splitlines(), start=1)
        if line.strip() and not line.lstrip().startswith("#")
    ]
    if not rows:
        raise ParameterError(f"{source}: empty (no header, no samples)")
    header_line, header = rows[0]
    names = [name.strip() for name in header.split(",")]
    while names and names[-1] == "":  # a spreadsheet's trailing commas
        names.pop()
    times = [i for i, name in enumerate(names) if name in TIME_COLUMNS]
    if len(times) != 1:
        raise ParameterError(
            f"{source}, line {header_line}: the header needs one time column t (s); "
            f"it has {', '.join(names)}"
        )
    signals: dict[int, str] = {}
    for i, name in enumerate(names):
        if i == times[0]:
            continue
        signal = signal_name(name)
        if signal is None:
            raise ParameterError(
                f"{source}, line {header_line}: no signal {name!r} in the model; columns "
                f"may be t and {_signal_list()}"
            )
        if signal in signals.values():
            raise ParameterError(f"{source}, line {header_line}: signal {signal} given twice")
        signals[i] = signal
    t: list[float] = []
    lines: list[int] = []
    values: dict[str, list[float]] = {name: [] for name in signals.values()}
    skipped = {name: 0 for name in signals.values()}
    for number, line in rows[1:]:
        fields = [field.strip() for field in line.split(",")]
        while len(fields) > len(names) and fields[-1] == "":
            fields.pop()
        if len(fields) != len(names):
            raise ParameterError(
                f"{source}, line {number}: {len(fields)} values for {len(names)} columns"
            )
        time = _value(source, number, names[times[0]], fields[times[0]])
        if math.isnan(time):
            for name in signals.values():
                skipped[name] += 1
            continue
        t.append(time)
        lines.append(number)
        for i, name in signals.items():
            value = _value(source, number, names[i], fields[i])
            skipped[name] += math.isnan(value)
            values[name].append(value)
    if not t:
        raise ParameterError(f"{source}: no samples below the header")
    columns = {name: np.asarray(v, dtype=float) for name, v in values.items()}
    return _checked(source, np.asarray(t, dtype=float), columns, skipped, lines)


def _value(source: str, line: int, column: str, field: str) -> float:
    if field == "" or field.lower() == "nan":
        return math.nan
    try:
        value = float(field)
    except ValueError:
        raise ParameterError(
            f"{source}, line {line}, column {column}: {field!r} is not a number"
        ) from None
    if math.isinf(value):
        raise ParameterError(f"{source}, line {line}, column {column}: {field!r} is not finite")
    return value


@dataclasses.dataclass(frozen=True)
class Experiment:
    """One firing test: its measured `trace` and what is known about it.

    - `design`: known values by flat name (`v0`, `pulse_time`, `shots`, any fixed design
      value; `t_shift`, the trigger delay, s, default 0), over the calibration's.
    - `sigma`: the noise of each measured signal by name (its unit); signals not given
      have theirs estimated from the residuals.
    - `per_experiment`: fitted parameters this firing has its own value of (its `v0` at
      another charge temperature, its `t_shift`); fitted as `name[i]`, `i` the
      experiment's number from 1.
    - `window`: `(start, end)` (s): only the samples within it are fitted.
    - `name`: for reports (default: the trace's file name).
    - `force_table`: this firing's measured breech force of one round (`ForceTable`, e.g.
      its chamber pressure times the bore area), over the calibration's; it replaces
      the impulse (`v0`) or pulse. Either every experiment has a table or none does.
    """

    trace: Trace
    design: Mapping[str, float] = dataclasses.field(default_factory=dict)
    sigma: Mapping[str, float] = dataclasses.field(default_factory=dict)
    per_experiment: tuple[str, ...] = ()
    window: tuple[float, float] | None = None
    name: str = ""
    force_table: ForceTable | None = None

    def __post_init__(self):
        where = self.label
        sigma = {signal_name(k) or k: v for k, v in self.sigma.items()}
        object.__setattr__(self, "sigma", sigma)
        for name, value in self.design.items():
            if name == "t_shift":
                check_value(where, name, value, T_SHIFT)
            elif name == "m" and value == 0:  # the simplified model, as `simulate m=0`
                continue
            elif name != "t1":  # each value alone: the design, merged with the shared
                # one, is checked whole as `simulate`'s is (`Calibration`)
                check_value(where, name, value, parameter(name))
        for name, value in self.sigma.items():
            if name not in self.trace.signals:
                raise ParameterError(
                    f"{where}: sigma of {name}, which the trace does not measure "
                    f"({', '.join(self.trace.signals)})"
                )
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ParameterError(f"{where}: sigma of {name} = {value!r}: valid > 0")
        if self.window is not None:
            start, end = self.window
            if not start < end:
                raise ParameterError(f"{where}: window [{start:g}, {end:g}] s is empty")
        if self.force_table is not None and not isinstance(self.force_table, ForceTable):
            raise ParameterError(f"{where}: force_table must be a ForceTable")

    @property
    def label(self) -> str:
        """The experiment's name for messages and reports."""
        return self.name or Path(self.trace.source).name

    @property
    def fitted_trace(self) -> Trace:
        """The trace within the window."""
        return self.trace if self.window is None else self.trace.within(*self.window)


def known_values(design: Mapping[str, Any]) -> dict[str, float]:
    """Model parameters only (`t_shift` and `t1` removed)."""
    return {k: float(v) for k, v in design.items() if k not in ("t_shift", "t1")}
