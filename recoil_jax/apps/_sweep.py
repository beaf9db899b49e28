"""`recoil-jax sweep`: command-line sweeps, their files and figures."""

from __future__ import annotations

import csv
import dataclasses
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

import recoil_jax as rj
import recoil_jax.extend as rjx

from ._cluster import dask_client
from ._inputs import (
    design_warnings,
    known,
    number,
    output_folder,
    read_text,
    split_assignment,
    unknown_name,
    warn,
)
from ._json import dumps as json_dumps

__all__ = ["MAX_AXIS", "parse_axis", "read_points", "run_sweep", "write_figures", "write_results"]


#: The most values one axis `start:stop:count` may have (800 MB of them).
MAX_AXIS = 100_000_000


def parse_axis(name: str, text: str) -> np.ndarray:
    """`a,b,c` (a list) or `start:stop:count` (inclusive linspace); one value is fixed."""
    try:
        if ":" not in text:
            return np.array([number(v) for v in text.split(",")])
        start, stop, count = text.split(":")
        first, last, count = number(start), number(stop), int(count)
        if count < 1:
            raise ValueError
    except ValueError as error:
        raise rj.ParameterError(
            f"{name}={text!r}: expected a number, a list a,b,c or a range start:stop:count"
            f"{error if str(error).startswith(':') else ''}"
        ) from None
    if count > MAX_AXIS:
        raise rj.ParameterError(
            f"{name}={text}: {count:,} values on one axis, more than {MAX_AXIS:,}: give a "
            "smaller count"
        )
    return np.linspace(first, last, count)


def read_points(path) -> list[dict]:
    """Designs from a CSV file (header = names) or a JSON list of objects; the names are
    those of `name=value` items (parameters and `t1`)."""
    path = Path(path)
    text = read_text(path, "points file")
    if path.suffix.lower() == ".json" or text.lstrip().startswith("["):
        try:
            points = json.loads(text, object_pairs_hook=_once_each)
        except json.JSONDecodeError as error:
            raise rj.ParameterError(f"{path}: not valid JSON: {error}") from None
        if not isinstance(points, list) or not all(isinstance(p, dict) for p in points):
            raise rj.ParameterError(f"{path}: expected a JSON list of {{name: value}} objects")
    else:
        reader = csv.reader(text.splitlines())
        header = next(reader, [])
        for name in header:
            if header.count(name) > 1:
                raise rj.ParameterError(f"{path}: the column {name!r} is given twice")
        points = []
        for row in reader:
            if not row:  # a blank line
                continue
            if len(row) != len(header):
                raise rj.ParameterError(
                    f"{path}, point {len(points)}: {len(row)} values for the "
                    f"{len(header)} columns {','.join(header)}"
                )
            points.append(dict(zip(header, row, strict=True)))
    if not points:
        raise rj.ParameterError(f"{path}: no designs in the file")
    designs = []
    for row, point in enumerate(points):
        design = {}
        for name, value in point.items():
            if not known(name):
                error = unknown_name(name)
                raise rj.ParameterError(f"{path}, point {row}: {error}") from None
            try:
                design[name] = float(value)
            except (TypeError, ValueError):
                raise rj.ParameterError(
                    f"{path}, point {row}: {name} = {value!r} is not a number"
                ) from None
        designs.append(design)
    return designs


def _given(column) -> np.ndarray:
    """A column's values where they were given (NaN: a point that does not set it)."""
    column = np.asarray(column, dtype=float)
    return column[~np.isnan(column)]


def _once_each(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """A JSON object whose keys are each given once."""
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise rj.ParameterError(f"{key} is given twice in one design")
        out[key] = value
    return out


def write_results(result: rj.SweepResult, out: Path, meta: dict) -> list[Path]:
    """`sweep.csv` (one row per design) and `sweep.npz` (every array, plus metadata as
    JSON in `metadata`); both keyed as `simulate --json` (`PEAK_FIELDS`)."""
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    names = list(result.values)
    for i, record in enumerate(result.records()):
        parameters = record.pop("parameters")
        row = {name: parameters.get(name, "") for name in names}
        record.pop("gradients", None)
        for metric, by_param in (result.gradients or {}).items():
            row |= {
                rjx.gradient_key(metric, name): float(v[i]) if result.ok[i] else None
                for name, v in by_param.items()
            }
        rows.append(row | record)
    with open(out / "sweep.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    arrays: dict[str, Any] = {f"param_{k}": v for k, v in result.values.items()}
    arrays |= {rjx.PEAK_FIELDS[field]: v for field, v in result.peaks.items()}
    arrays["status"] = rjx.status_codes(result.status)
    for name, by_param in (result.gradients or {}).items():
        for parameter, v in by_param.items():
            arrays[f"grad_{rj.METRICS[name].key}__{parameter}"] = v
    metadata = meta | {
        "swept": list(result.swept),
        "grid_shape": result.grid_shape,
        "n": len(result),
        "failed": len(result.failures()),
        "status_codes": rjx.status_table(),
    }
    arrays["metadata"] = np.asarray(json.dumps(metadata))
    np.savez(out / "sweep.npz", **arrays)
    return [out / "sweep.csv", out / "sweep.npz"]


def write_figures(result: rj.SweepResult, out: Path) -> list[Path]:
    """The figures of a grid sweep (none for a list of points):

    - gap swept (with at most one other parameter): Fig. 6 / Fig. 10 style lines of each
      peak against the gap, one per value of the other parameter (a colour scale from
      `LEGEND_LINES` values on), the lowest point of each marked;
    - one parameter swept, not the gap: both peaks against it;
    - two or more swept: heatmaps of both peaks over the first two (the others at their
      first value), and the map of ∂(peak anchoring force)/∂gap when the gap is swept.

    The gap is drawn in mm in every figure."""
    from ._figures import LEGEND_LINES, plot_heatmap, plot_series

    figures = []
    if not result.grid_shape or not result.swept:
        return figures
    shape, swept = result.grid_shape, result.swept
    grid_values = {n: result.values[n].reshape(shape) for n in swept}
    plotted = {
        "peak_displacement": "fig6_peak_displacement_vs_gap",
        "peak_anchoring_force": "fig10_peak_anchoring_force_vs_gap",
    }
    if "gap" in swept and len(swept) <= 2:
        other = [n for n in swept if n != "gap"]
        for name, filename in plotted.items():
            label = rj.METRICS[name].label
            data = result.peaks[name].reshape(shape)
            series, values = {}, []
            if other:
                o_axis = swept.index(other[0])
                for k in range(shape[o_axis]):
                    row = np.take(data, k, axis=o_axis)
                    gaps = np.take(grid_values["gap"], k, axis=o_axis)
                    value = np.take(grid_values[other[0]], k, axis=o_axis).flat[0]
                    unit = _unit(other[0])
                    series[f"{other[0]} = {value:g}{unit and ' ' + unit}"] = (gaps, row)
                    values.append(float(value))
            else:
                series["design"] = (grid_values["gap"], data)
            many = len(series) >= LEGEND_LINES
            figures.append(
                plot_series(
                    series,
                    out / f"{filename}.png",
                    xlabel="gap (mm)",
                    ylabel=label,
                    xscale=1e3,
                    title=label + " vs gap (▼ lowest of each line, gap in mm)",
                    minima=rj.METRICS[name].unit,  # in the legend, or just marked
                    colour_by=(_axis(other[0])[0], values) if many else None,
                )
            )
    elif len(swept) == 1:
        (name,) = swept
        label, scale = _axis(name)
        for metric in plotted:
            figures.append(
                plot_series(
                    {f"{name} swept": (result.values[name], result.peaks[metric])},
                    out / f"{rj.METRICS[metric].key}_vs_{name}.png",
                    xlabel=label,
                    ylabel=rj.METRICS[metric].label,
                    xscale=scale,
                    title=f"{rj.METRICS[metric].label} vs {name} (▼ lowest)",
                    minima=rj.METRICS[metric].unit,
                )
            )
    if len(swept) >= 2:
        x_name, y_name = swept[1], swept[0]
        (xlabel, xscale), (ylabel, yscale) = _axis(x_name), _axis(y_name)
        # Heatmaps over the first two swept parameters (others at their first value).
        index = tuple(slice(None) if i < 2 else 0 for i in range(len(shape)))
        x = xscale * grid_values[x_name][index][0]
        y = yscale * grid_values[y_name][index][:, 0]
        maps: dict[str, tuple[str, str | None, bool]] = {
            f"heatmap_{rj.METRICS[name].key}": (rj.METRICS[name].label, name, False)
            for name in plotted
        }
        gradients = (result.gradients or {}).get("peak_anchoring_force", {})
        if "gap" in gradients:
            maps["map_dF_AN_dgap"] = ("∂(peak anchoring force)/∂gap (N/m)", None, True)
        for filename, (label, name, diverging) in maps.items():
            data = result.peaks[name] if name else gradients["gap"]
            figures.append(
                plot_heatmap(
                    x,
                    y,
                    data.reshape(shape)[index],
                    out / f"{filename}.png",
                    xlabel=xlabel,
                    ylabel=ylabel,
                    label=label,
                    diverging=diverging,
                )
            )
    return figures


def _unit(name: str) -> str:
    return rj.PARAMETERS[name].unit if name in rj.PARAMETERS else "s"


def _axis(name: str) -> tuple[str, float]:
    """A swept name's axis label and the factor from SI units to it (the gap in mm)."""
    if name == "gap":
        return "gap (mm)", 1e3
    return (rj.PARAMETERS[name].label if name in rj.PARAMETERS else f"{name} (s)"), 1.0


def run_sweep(args) -> int:
    axes, fixed = {}, {}
    given: dict[str, str] = {}
    for item in args.assignments:
        name, text = split_assignment(item, given)
        given[name] = text
        values = parse_axis(name, text)
        if len(values) == 1:
            fixed[name] = float(values[0])
        else:
            axes[name] = values
    table = rj.ForceTable.from_csv(args.force_table) if args.force_table else None
    designs: list[dict] = []  # from --points
    grid = None  # or the grid
    shape: tuple[int, ...] = ()  # the grid's
    if args.points:
        if axes:
            raise rj.ParameterError(
                "with --points, other parameters can only be fixed (name=value), not swept"
            )
        points = read_points(args.points)
        both = sorted(set(fixed) & set().union(*points))
        if both:
            name = both[0]
            raise rj.ParameterError(
                f"{name} is given both on the command line ({name}={given[name]}) and as a "
                f"column of {args.points}: give it in one place"
            )
        designs = [fixed | design for design in points]
        wrt = None
        columns = {n: [d.get(n, np.nan) for d in designs] for n in set().union(*designs)}
    else:
        if not axes:
            raise rj.ParameterError(
                "nothing to sweep: give at least one list a,b,c or "
                "range start:stop:count, or --points FILE"
            )
        wrt = ("gap",) if "gap" in axes else None
        # Its columns made a chunk at a time as it is swept: a streamed grid's memory
        # does not grow with it.
        grid = rjx.Grid(axes, fixed)
        shape = grid.shape
        columns = grid.axes | {name: np.array([value]) for name, value in fixed.items()}
    warn(design_warnings({n: _given(c) for n, c in columns.items()}, table))
    # The sweep's own options (tighter with gradients), with the step limit asked for.
    options = rj.GRADIENT_OPTIONS if wrt else rj.SolverOptions()
    options = dataclasses.replace(options, max_steps=args.max_steps)
    progress = not args.json
    if args.out:
        output_folder(args.out)  # once the input is known good, before any solve
    if args.store and not args.out and not args.json:
        # Nothing asks for the results here: they stream to the store, not into memory.
        return _sweep_to_store(args, axes, designs or grid, wrt, options, table)
    with dask_client(args.workers, args.scheduler) as client:
        if args.points:
            result = rj.sweep(
                designs,
                options=options,
                progress=progress,
                force_table=table,
                store=args.store,
                client=client,
            )
        else:
            result = rj.sweep(
                grid,
                wrt=wrt,
                options=options,
                progress=progress,
                force_table=table,
                store=args.store,
                client=client,
            )
            result.swept, result.grid_shape = tuple(axes), shape
    if args.json:
        print(json_dumps(result.records()))
    else:
        ok, solved = int(result.ok.sum()), len(result) - result.stored
        read = f" ({result.stored} read from the store)" if result.stored else ""
        print(
            f"swept {len(result)} designs{read}: {solved} solved in {result.seconds:.1f} s "
            f"({solved / max(result.seconds, 1e-9):.0f}/s); {ok} ok, {len(result) - ok} failed"
        )
        force = result.peaks["peak_anchoring_force"]
        best = int(np.nanargmin(np.where(result.ok, force, np.nan))) if ok else None
        if best is not None:
            design = ", ".join(
                f"{k}={result.values[k][best]:g}"
                for k in (result.swept or ("m", "gap"))
                if k in result.values
            )
            print(f"lowest peak anchoring force: {force[best]:.2f} N at {design}")
    if args.out:
        out = Path(args.out)
        paths = write_results(result, out, {"command": " ".join(sys.argv)})
        figures = write_figures(result, out)
        for path in paths + figures:
            print(f"wrote {path}", file=sys.stderr)
        if not figures:
            print(
                "sweep: no figures for a list of points (--points); a grid "
                "(name=a,b,c or start:stop:count) draws them",
                file=sys.stderr,
            )
    return 0  # failed points are reported per point (status), not as a failed command


def _sweep_to_store(args, axes, designs, wrt, options, table) -> int:
    """`sweep --store` with neither `--out` nor `--json`: `rj.sweep_to_store` of the
    points or the grid (`designs`), and a summary read from the store."""
    with dask_client(args.workers, args.scheduler) as client:
        stored = rj.sweep_to_store(
            designs, args.store, wrt=wrt, options=options, force_table=table, client=client
        )
    solved = stored.designs - stored.stored
    read = f" ({stored.stored} read from the store)" if stored.stored else ""
    print(
        f"swept {stored.designs} designs{read}: {solved} solved in {stored.seconds:.1f} s "
        f"({solved / max(stored.seconds, 1e-9):.0f}/s); {stored.designs - stored.failed} ok, "
        f"{stored.failed} failed; the results are in {stored.path} (docs/campaigns.md)"
    )
    best = stored.lowest("peak_anchoring_force")
    if best is not None:
        names = [k for k in (tuple(axes) or ("m", "gap")) if best.get(k) is not None]
        design = ", ".join(f"{k}={best[k]:g}" for k in names)
        print(
            f"lowest peak anchoring force: {best[rjx.PEAK_FIELDS['peak_anchoring_force']]:.2f} N"
            f" at {design}"
        )
    return 0
