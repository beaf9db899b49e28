"""`recoil-jax sweep`: command-line sweeps, their files and figures."""

from __future__ import annotations

import csv
import json
import sys
from pathlib import Path

import numpy as np

from ._params import PARAMETER_NAMES, ParameterError, SolverOptions
from ._solve import Status
from ._sweep import SweepResult, sweep, sweep_grid


def parse_axis(name: str, text: str) -> np.ndarray:
    """`a,b,c` (a list) or `start:stop:count` (inclusive linspace); one value is fixed."""
    try:
        if ":" in text:
            start, stop, count = text.split(":")
            if int(count) < 1:
                raise ValueError
            return np.linspace(float(start), float(stop), int(count))
        return np.array([float(v) for v in text.split(",")])
    except ValueError:
        raise ParameterError(
            f"{name}={text!r}: expected a number, a list a,b,c or a range start:stop:count"
        ) from None


def read_points(path) -> list[dict]:
    """Designs from a CSV file (header = parameter names) or a JSON list of objects."""
    path = Path(path)
    text = path.read_text()
    if path.suffix.lower() == ".json" or text.lstrip().startswith("["):
        points = json.loads(text)
        if not isinstance(points, list) or not all(isinstance(p, dict) for p in points):
            raise ParameterError(f"{path}: expected a JSON list of {{name: value}} objects")
    else:
        points = list(csv.DictReader(text.splitlines()))
    designs = []
    for row, point in enumerate(points):
        design = {}
        for name, value in point.items():
            if name not in PARAMETER_NAMES:
                raise ParameterError(
                    f"{path}, point {row}: unknown parameter {name!r}; known: "
                    f"{', '.join(PARAMETER_NAMES)}")
            try:
                design[name] = float(value)
            except (TypeError, ValueError):
                raise ParameterError(f"{path}, point {row}: {name} = {value!r} is not a "
                                     "number") from None
        designs.append(design)
    return designs


def write_results(result: SweepResult, out: Path, meta: dict) -> list[Path]:
    """`sweep.csv` (one row per design) and `sweep.npz` (every array, plus metadata as
    JSON in `metadata`)."""
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for record in result.records():
        row = dict(record.pop("parameters"))
        for key, by_param in record.pop("gradients", {}).items():
            row |= {f"d({key})/d({name})": v for name, v in by_param.items()}
        rows.append(row | record)
    with open(out / "sweep.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    arrays = {f"param_{k}": v for k, v in result.values.items()}
    arrays |= {k: v for k, v in result.peaks.items()}
    arrays["status"] = result.status
    for key, by_param in (result.gradients or {}).items():
        for name, v in by_param.items():
            arrays[f"grad_{key}__{name}"] = v
    metadata = meta | {"swept": list(result.swept), "grid_shape": result.grid_shape,
                       "n": len(result), "failed": len(result.failures()),
                       "status_codes": Status.MESSAGES}
    np.savez(out / "sweep.npz", metadata=json.dumps(metadata), **arrays)
    return [out / "sweep.csv", out / "sweep.npz"]


def write_figures(result: SweepResult, out: Path) -> list[Path]:
    """Fig. 6 / Fig. 10 style line plots (peak vs gap, one line per value of the other
    swept parameter), heatmaps over the first two swept parameters, and the map of
    ∂(peak anchoring force)/∂gap."""
    from ._plot import plot_heatmap, plot_series

    figures = []
    if not result.grid_shape or not result.swept:
        return figures
    shape, swept = result.grid_shape, result.swept
    grid_values = {n: result.values[n].reshape(shape) for n in swept}
    units = {"peak_displacement_m": ("peak barrel displacement (m)", 1.0),
             "peak_anchoring_force_N": ("peak anchoring force (N)", 1.0)}
    if "gap" in swept and len(swept) <= 2:
        other = [n for n in swept if n != "gap"]
        for key, (label, scale) in units.items():
            data = result.peaks[key].reshape(shape)
            series = {}
            if other:
                o_axis = swept.index(other[0])
                for k in range(shape[o_axis]):
                    row = np.take(data, k, axis=o_axis)
                    gaps = np.take(grid_values["gap"], k, axis=o_axis)
                    value = np.take(grid_values[other[0]], k, axis=o_axis).flat[0]
                    series[f"{other[0]} = {value:g}"] = (gaps, row)
            else:
                series["design"] = (grid_values["gap"], data)
            name = "fig6_peak_displacement_vs_gap" if key.startswith("peak_disp") else \
                "fig10_peak_anchoring_force_vs_gap"
            figures.append(plot_series(series, out / f"{name}.png", xlabel="gap (mm)",
                                       ylabel=label, xscale=1e3, yscale=scale,
                                       title=label + " vs gap"))
    if len(swept) >= 2:
        x_name, y_name = swept[1], swept[0]
        # Heatmaps over the first two swept parameters (others at their first value).
        index = tuple(slice(None) if i < 2 else 0 for i in range(len(shape)))
        for key, (label, _) in units.items():
            data = result.peaks[key].reshape(shape)[index]
            figures.append(plot_heatmap(
                grid_values[x_name][index][0], grid_values[y_name][index][:, 0], data,
                out / f"heatmap_{key}.png", xlabel=x_name, ylabel=y_name, label=label))
        if result.gradients and "gap" in result.gradients["peak_anchoring_force_N"]:
            data = result.gradients["peak_anchoring_force_N"]["gap"].reshape(shape)[index]
            figures.append(plot_heatmap(
                grid_values[x_name][index][0], grid_values[y_name][index][:, 0], data,
                out / "map_dF_AN_dgap.png", xlabel=x_name, ylabel=y_name,
                label="∂(peak anchoring force)/∂gap (N/m)", diverging=True))
    return figures


def run_sweep(args) -> int:
    axes, fixed = {}, {}
    for item in args.assignments:
        name, sep, text = item.partition("=")
        if not sep:
            raise ParameterError(f"expected name=value, got {item!r}")
        if name not in PARAMETER_NAMES and name != "t1":
            raise ParameterError(f"unknown parameter {name!r}; names: "
                                 f"{' '.join(PARAMETER_NAMES)} t1")
        values = parse_axis(name, text)
        if len(values) == 1:
            fixed[name] = float(values[0])
        else:
            axes[name] = values
    options = SolverOptions(t1=fixed.pop("t1")) if "t1" in fixed else None
    if args.points:
        if axes:
            raise ParameterError("with --points, other parameters can only be fixed "
                                 "(name=value), not swept")
        designs = [fixed | design for design in read_points(args.points)]
        result = sweep(designs, options=options, progress=not args.json)
    else:
        if not axes:
            raise ParameterError("nothing to sweep: give at least one list a,b,c or range "
                                 "start:stop:count, or --points FILE")
        wrt = ("gap",) if "gap" in axes else None
        result = sweep_grid(axes, fixed, options=options, wrt=wrt, progress=not args.json)
    if args.json:
        print(json.dumps(result.records()))
    else:
        ok = int(result.ok.sum())
        print(f"swept {len(result)} designs in {result.seconds:.1f} s "
              f"({len(result) / max(result.seconds, 1e-9):.0f}/s): {ok} ok, "
              f"{len(result) - ok} failed")
        best = int(np.nanargmin(np.where(result.ok, result.peaks["peak_anchoring_force_N"],
                                         np.nan))) if ok else None
        if best is not None:
            design = ", ".join(f"{k}={result.values[k][best]:g}" for k in
                               (result.swept or ("m", "gap")) if k in result.values)
            print(f"lowest peak anchoring force: "
                  f"{result.peaks['peak_anchoring_force_N'][best]:.2f} N at {design}")
    if args.out:
        out = Path(args.out)
        paths = write_results(result, out, {"command": " ".join(sys.argv)})
        paths += write_figures(result, out)
        for path in paths:
            print(f"wrote {path}", file=sys.stderr)
    return 0  # failed points are reported per point (status), not as a failed command
