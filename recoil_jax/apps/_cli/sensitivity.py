"""`recoil-jax sensitivity`: a sensitivity file (`_studies/sensitivity_file`) run through
`rj.sensitivity`, its samples, result.json and figures written, a summary printed."""

from __future__ import annotations

import csv
import dataclasses
import io
import sys
from pathlib import Path

import recoil_jax as rj

from .._files.cluster import dask_client
from .._files.inputs import (
    output_folder,
    results_folder,
)
from .._files.json_writer import dumps as json_dumps, write as write_json, write_text
from .._files.options import Commands, add_cluster, add_json, add_max_steps, add_store
from .._studies.sensitivity_file import load_sensitivity

__all__ = ["add_command", "run_sensitivity", "summary", "write_samples"]


def write_samples(result: rj.SensitivityResult, path: Path) -> Path:
    """Every design's ranged values and metrics (empty where its solve failed), and
    whether its solve succeeded; written whole or not at all (a full disk leaves no
    truncated file)."""
    with io.StringIO(newline="") as file:
        writer = csv.writer(file)
        writer.writerow([*result.parameters, *result.metrics, "ok"])
        outputs = [result.outputs[m] for m in result.metrics]
        for i, row in enumerate(result.samples):
            ok = bool(result.ok[i])
            values = [f"{v:.10g}" if ok else "" for v in (o[i] for o in outputs)]
            writer.writerow([*(f"{v:.10g}" for v in row), *values, int(ok)])
        return write_text(path, file.getvalue())


def summary(result: rj.SensitivityResult) -> str:
    """Per metric, the parameters ranked by the method's main index, with intervals."""
    main = result.main
    conf = f"{main}_conf"
    lines = [
        f"sensitivity ({result.method}): {len(result.parameters)} parameters, "
        f"{len(result.ok):,} designs ({result.used:,} used, {int((~result.ok).sum())} "
        f"failed), {result.seconds:.1f} s"
    ]
    for metric in result.metrics:
        note = " (constant over the box)" if metric in result.constant else ""
        lines.append(f"  {metric}, by {main}{note}:")
        for name in result.ranking(metric):
            entry = result.indices[metric][name]
            extra = f"  S1 {entry['S1']:.3f} ± {entry['S1_conf']:.3f}" if "S1" in entry else ""
            lines.append(f"    {name:<22} {entry[main]:.4g} ± {entry[conf]:.2g}{extra}")
    return "\n".join(lines)


def run_sensitivity(args) -> int:
    """The `sensitivity` command."""
    arguments, description = load_sensitivity(args.source)
    out = output_folder(results_folder(args.out, "sensitivity", args.source))
    # The sweep's defaults (tighter with gradients), with the command's step limit.
    options = rj.GRADIENT_OPTIONS if arguments["method"].gradients else rj.SolverOptions()
    options = dataclasses.replace(options, max_steps=args.max_steps)
    with dask_client(args.workers, args.scheduler) as client:
        result = rj.sensitivity(
            **arguments, options=options, store=args.store, client=client, progress=True
        )
    report = {"source": str(args.source), "description": description, **result.to_json()}
    write_samples(result, out / "samples.csv")
    from .._figures.sensitivity import sensitivity_figures

    report["figures"] = [str(p) for p in sensitivity_figures(result, out)]
    write_json(out / "result.json", report)
    if args.json:
        print(json_dumps(report))
    else:
        print(summary(result))
        print(f"  wrote {out / 'result.json'}, samples.csv and {len(report['figures'])} figures")
    if result.failures:
        reasons = "; ".join(f"{n} × {r}" for r, n in result.failures.items())
        print(
            f"recoil-jax: {int((~result.ok).sum())} of {len(result.ok)} solves failed "
            f"({reasons}); the indices rest on the other {result.used} designs",
            file=sys.stderr,
        )
    return 0


def add_command(commands: Commands) -> None:
    """`recoil-jax sensitivity`'s arguments."""
    sens = commands.add(
        "sensitivity",
        run_sensitivity,
        help="global sensitivity: which tolerances move the peaks",
        description="Sample the parameters over their ranges (a TOML file: [design], "
        "[ranges], [metrics], [method]; or a shipped example's name: "
        "paper_absorber, throttling), solve every design through the sweep and rank "
        "the parameters: Sobol first-order and total indices (SALib), Morris "
        "elementary effects, or DGSM from exact gradients, each with bootstrap 95% "
        "intervals. Writes result.json, samples.csv, indices.png, scatter.png (and "
        "morris.png). Failed solves are counted, and the indices say how many designs "
        "they rest on. Exit 0 done, 1 no design group solved, 2 bad input.",
    )
    sens.add_argument("source", help="a sensitivity file (.toml) or a shipped example's name")
    sens.add_argument(
        "--out", help="output folder (default results/sensitivity/<example or file name>)"
    )
    add_json(sens)
    add_store(sens, "commit every design's result", "run")
    add_cluster(sens, "the solves")
    add_max_steps(sens)
