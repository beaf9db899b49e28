"""The figures of a grid sweep: lines against the gap (the paper's Fig. 6 and 10), lines
against one parameter, heatmaps."""

from __future__ import annotations

from pathlib import Path

import numpy as np

import recoil_jax as rj

from .designs import plot_heatmap
from .histories import LEGEND_LINES, plot_series

__all__ = ["sweep_figures"]


def sweep_figures(result: rj.SweepResult, out: Path) -> list[Path]:
    """The figures of a grid sweep (none for a list of points):

    - gap swept (with at most one other parameter): Fig. 6 / Fig. 10 style lines of each
      peak against the gap, one per value of the other parameter (a colour scale from
      `LEGEND_LINES` values on), the lowest point of each marked;
    - one parameter swept, not the gap: both peaks against it;
    - two or more swept: heatmaps of both peaks over the first two (the others at their
      first value), and the map of ∂(peak anchoring force)/∂gap when the gap is swept.

    The gap is drawn in mm in every figure."""
    if not result.grid_shape or not result.swept:
        return []
    swept = result.swept
    if "gap" in swept and len(swept) <= 2:
        figures = _lines_against_gap(result, out)
    elif len(swept) == 1:
        figures = _lines_against_one(result, out)
    else:
        figures = []
    if len(swept) >= 2:
        figures += _heatmaps(result, out)
    return figures


def _unit(name: str) -> str:
    """A swept name's unit (a parameter's, else seconds: `t1`)."""
    return rj.PARAMETERS[name].unit if name in rj.PARAMETERS else "s"


def _axis(name: str) -> tuple[str, float]:
    """A swept name's axis label and the factor from SI units to it (the gap in mm)."""
    if name == "gap":
        return "gap (mm)", 1e3
    return (rj.PARAMETERS[name].label if name in rj.PARAMETERS else f"{name} (s)"), 1.0


#: The peaks drawn, and the file of each against the gap (the paper's figure numbers).
_PLOTTED = {
    "peak_displacement": "fig6_peak_displacement_vs_gap",
    "peak_anchoring_force": "fig10_peak_anchoring_force_vs_gap",
}


def _shape(result: rj.SweepResult) -> tuple[int, ...]:
    """The grid's shape (`sweep_figures` draws grids only)."""
    assert result.grid_shape is not None
    return tuple(result.grid_shape)


def _grid_values(result: rj.SweepResult) -> dict[str, np.ndarray]:
    """Each swept parameter's values, shaped as the grid."""
    return {n: result.values[n].reshape(_shape(result)) for n in result.swept}


def _lines_against_gap(result: rj.SweepResult, out: Path) -> list[Path]:
    """Each peak against the gap, one line per value of the other swept parameter."""
    figures = []
    shape, swept, grid_values = _shape(result), result.swept, _grid_values(result)
    other = [n for n in swept if n != "gap"]
    for name, filename in _PLOTTED.items():
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
    return figures


def _lines_against_one(result: rj.SweepResult, out: Path) -> list[Path]:
    """Both peaks against the one swept parameter (not the gap)."""
    figures = []
    swept = result.swept
    (name,) = swept
    label, scale = _axis(name)
    for metric in _PLOTTED:
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
    return figures


def _heatmaps(result: rj.SweepResult, out: Path) -> list[Path]:
    """Heatmaps of both peaks over the first two swept parameters (the others at their
    first value), and of ∂(peak anchoring force)/∂gap when the gap is swept."""
    figures = []
    shape, swept, grid_values = _shape(result), result.swept, _grid_values(result)
    x_name, y_name = swept[1], swept[0]
    (xlabel, xscale), (ylabel, yscale) = _axis(x_name), _axis(y_name)
    # Heatmaps over the first two swept parameters (others at their first value).
    index = tuple(slice(None) if i < 2 else 0 for i in range(len(shape)))
    x = xscale * grid_values[x_name][index][0]
    y = yscale * grid_values[y_name][index][:, 0]
    maps: dict[str, tuple[str, str | None, bool]] = {
        f"heatmap_{rj.METRICS[name].key}": (rj.METRICS[name].label, name, False)
        for name in _PLOTTED
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
