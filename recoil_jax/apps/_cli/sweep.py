"""`recoil-jax sweep`: command-line sweeps, their files and figures."""

from __future__ import annotations

import csv
import dataclasses
import json
import sys
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

import recoil_jax as rj
import recoil_jax.extend as rjx

from .._files.cluster import dask_client
from .._files.inputs import (
    design_warnings,
    known,
    names,
    number,
    output_folder,
    read_text,
    split_assignment,
    unknown_name,
    warn,
)
from .._files.json_writer import dumps as json_dumps
from .._files.options import (
    Commands,
    add_cluster,
    add_force_table,
    add_json,
    add_max_steps,
    add_store,
)

__all__ = [
    "MAX_AXIS",
    "add_command",
    "parse_axis",
    "read_points",
    "run_sweep",
    "write_results",
]


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
        record["hazards"] = ";".join(record["hazards"])  # one CSV cell: names, ;-separated
        for metric, by_param in (result.gradients or {}).items():
            row |= {
                rjx.gradient_key(metric, name): float(v[i]) if result.ok[i] else None
                for name, v in by_param.items()
            }
        rows.append(row | record)
    with rjx.written(out / "sweep.csv") as temporary, open(temporary, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    arrays: dict[str, Any] = {f"param_{k}": v for k, v in result.values.items()}
    arrays |= {rjx.PEAK_FIELDS[field]: v for field, v in result.reported_peaks().items()}
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
    with rjx.written(out / "sweep.npz") as temporary, open(temporary, "wb") as f:
        np.savez(f, **arrays)
    return [out / "sweep.csv", out / "sweep.npz"]


class _Designs(NamedTuple):
    """What a sweep's command line asks for: the swept `axes` and `fixed` values (as
    given, `given`), and either the `--points` designs or the `grid` (its `shape`), the
    `columns` of either for the warnings, and the gradients to take (`wrt`)."""

    axes: dict[str, np.ndarray]
    fixed: dict[str, float]
    points: list[dict] | None
    grid: Any
    shape: tuple[int, ...]
    columns: dict[str, Any]
    wrt: tuple[str, ...] | None

    @property
    def designs(self):
        """The points, or the grid: what `rj.sweep` takes."""
        return self.points if self.points is not None else self.grid


def _read_assignments(args) -> tuple[dict[str, np.ndarray], dict[str, float], dict[str, str]]:
    """The `name=values` items: the swept axes, the fixed values, and each as given."""
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
    return axes, fixed, given


def _read_designs(args, axes, fixed, given) -> _Designs:
    """The designs `args` name: the items' axes and fixed values, or `--points`."""
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
        columns = {n: [d.get(n, np.nan) for d in designs] for n in set().union(*designs)}
        return _Designs(axes, fixed, designs, None, (), columns, None)
    if not axes:
        raise rj.ParameterError(
            "nothing to sweep: give at least one list a,b,c or "
            "range start:stop:count, or --points FILE"
        )
    # Its columns made a chunk at a time as it is swept: a streamed grid's memory
    # does not grow with it.
    grid = rjx.Grid(axes, fixed)
    columns = grid.axes | {name: np.array([value]) for name, value in fixed.items()}
    wrt = ("gap",) if "gap" in axes else None
    return _Designs(axes, fixed, None, grid, grid.shape, columns, wrt)


def run_sweep(args) -> int:
    """Run `recoil-jax sweep` with the parsed `args`; its exit status (failed points are
    reported per point, not as a failed command)."""
    axes, fixed, given = _read_assignments(args)
    table = rj.ForceTable.from_csv(args.force_table) if args.force_table else None
    asked = _read_designs(args, axes, fixed, given)
    warn(design_warnings({n: _given(c) for n, c in asked.columns.items()}, table))
    # The sweep's own options (tighter with gradients), with the step limit asked for.
    options = rj.GRADIENT_OPTIONS if asked.wrt else rj.SolverOptions()
    options = dataclasses.replace(options, max_steps=args.max_steps)
    if args.out is not None:
        output_folder(args.out)  # once the input is known good, before any solve
    if args.store and args.out is None and not args.json:
        # Nothing asks for the results here: they stream to the store, not into memory.
        return _sweep_to_store(args, asked.axes, asked.designs, asked.wrt, options, table)
    with dask_client(args.workers, args.scheduler) as client:
        result = rj.sweep(
            asked.designs,
            wrt=asked.wrt,  # None for points
            options=options,
            progress=not args.json,
            force_table=table,
            store=args.store,
            client=client,
        )
    if asked.points is None:
        result.swept, result.grid_shape = tuple(asked.axes), asked.shape
    if args.out is not None:  # the files first: a failing standard output leaves them whole
        _write_out(result, Path(args.out))
    if args.json:
        print(json_dumps(result.records()))
    else:
        _print_summary(result)
    return 0


def _print_summary(result: rj.SweepResult) -> None:
    """How many designs were solved, how fast, how many failed, and the lowest peak
    anchoring force."""
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


def _write_out(result: rj.SweepResult, out: Path) -> None:
    """The sweep's files and figures in `out`, each named on stderr."""
    from .._figures.sweeps import sweep_figures

    paths = write_results(result, out, {"command": " ".join(sys.argv)})
    figures = sweep_figures(result, out)
    for path in paths + figures:
        print(f"wrote {path}", file=sys.stderr)
    if not figures:
        print(
            "sweep: no figures for a list of points (--points); a grid "
            "(name=a,b,c or start:stop:count) draws them",
            file=sys.stderr,
        )


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


def add_command(commands: Commands) -> None:
    """`recoil-jax sweep`'s arguments."""
    swp = commands.add(
        "sweep",
        run_sweep,
        help="peaks over a grid or a list of designs",
        description="Sweep designs: name=a,b,c (a list), name=start:stop:count (a range, "
        "inclusive) or name=value (fixed), over the cartesian grid of the swept names; "
        "or --points FILE (CSV with a header of names, or a JSON list of objects). "
        "Names: " + names() + ". m=0 (no absorber) may be mixed with m > 0. "
        "Writes sweep.csv, sweep.npz (arrays + metadata) and figures to --out.",
    )
    swp.add_argument("assignments", nargs="*", metavar="name=values")
    swp.add_argument("--points", metavar="FILE", help="designs from CSV or JSON")
    add_json(swp, "a JSON list, in input order (keys as simulate --json + status)")
    swp.add_argument("--out", metavar="DIR", help="folder for sweep.csv, sweep.npz, figures")
    add_force_table(swp)
    add_store(swp, "commit each finished chunk", "sweep")
    add_cluster(swp, "the chunks")
    add_max_steps(swp)
