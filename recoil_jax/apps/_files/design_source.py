"""A design taken from a study, calibration or plan file (`simulate --from`), so that the
traces of a planned test come out of the file that planned or fits them, not retyped.

- A calibration file (`[[experiment]]`): its `[design]`, each fitted value's start (else
  the middle of its bounds), and one experiment's own values (`elevation`, `v0`, `t1`,
  ...), by number from 1 or by name or trace; what it records and its noise come too.
- A study file (`[tune]`): its `[design]` and one `[[condition]]`'s values, by number
  or name; the tuned values are the study's to find, so they must be given.
- A plan file (`[candidates]`): its `[design]` (the guess) and one candidate firing, by
  number in the plan's order (the first condition varying slowest); its sampling.
"""

from __future__ import annotations

import dataclasses
import itertools
from pathlib import Path

import recoil_jax as rj

from .inputs import read_toml

__all__ = ["DesignSource", "design_from_file"]


@dataclasses.dataclass(frozen=True)
class DesignSource:
    """What a file says of one firing: `values` (flat names, `t1` included where given),
    `label` (the file and the experiment or condition, for messages), the signals it
    records with their noise (`sigma`; empty where the file does not say) and its
    sampling (`rate`, `duration`; None where it does not say)."""

    values: dict[str, float]
    label: str
    sigma: dict[str, float] = dataclasses.field(default_factory=dict)
    rate: float | None = None
    duration: float | None = None
    #: Names the file leaves to be given (a study's tuned values).
    required: tuple[str, ...] = ()


def _numbers(table: dict, where: str, skip=()) -> dict[str, float]:
    values = {}
    for name, value in table.items():
        if name in skip:
            continue
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise rj.ParameterError(f"{where}: {name} = {value!r} is not a number")
        values[name] = float(value)
    return values


def _pick(entries: list[dict], which: str | None, where: str, kind: str, keys=("name",)) -> tuple:
    """`(index from 0, entry)`: by number from 1, or by one of the `keys`' values; the
    only one where `which` is None."""
    if not entries:
        raise rj.ParameterError(f"{where}: it has no {kind}")
    names = [
        " / ".join(str(e[k]) for k in keys if k in e) or f"{kind} {i}"
        for i, e in enumerate(entries, 1)
    ]
    listing = "; ".join(f"{i}: {n}" for i, n in enumerate(names, 1))
    if which is None:
        if len(entries) == 1:
            return 0, entries[0]
        raise rj.ParameterError(
            f"{where} has {len(entries)} {kind}s: choose one with --experiment ({listing})"
        )
    if which.isdigit() and 1 <= int(which) <= len(entries):
        return int(which) - 1, entries[int(which) - 1]
    for i, entry in enumerate(entries):
        if any(str(entry.get(k)) == which for k in keys) or (
            "trace" in keys and Path(str(entry.get("trace", ""))).stem == which
        ):
            return i, entry
    raise rj.ParameterError(f"--experiment {which}: {where} has no such {kind} ({listing})")


def design_from_file(path, which: str | None = None) -> DesignSource:
    """The design of one firing of the file at `path` (see the module's docstring).

    **Raises:** `ParameterError` (one line naming the file) for a file that is none of
    the three, an experiment or condition it does not have, or a study whose tuned
    values are not given (the caller adds the command line's).
    """
    path = Path(path)
    config = read_toml(path, "study, calibration or plan file")
    design = _numbers(config.get("design", {}), f"{path} [design]")
    if "experiment" in config:  # a calibration
        fitted = {}
        for name, spec in config.get("fit", {}).items():
            try:
                if isinstance(spec, dict) and "start" in spec:
                    fitted[name] = float(spec["start"])
                else:
                    lower, upper = spec.get("bounds", ()) if isinstance(spec, dict) else spec
                    fitted[name] = 0.5 * (float(lower) + float(upper))
            except (TypeError, ValueError):
                raise rj.ParameterError(
                    f"{path} [fit] {name} = {spec!r}: give [lower, upper] or "
                    "{ bounds = [lower, upper], start = x }"
                ) from None
        fitted.pop("t_shift", None)
        index, entry = _pick(config["experiment"], which, str(path), "experiment",
                             keys=("name", "trace"))  # fmt: skip
        own = _numbers(entry, f"{path} [[experiment]] {index + 1}",
                       skip=("trace", "sigma", "per_experiment", "window", "name",
                             "force_table", "t_shift"))  # fmt: skip
        sigma = _numbers(entry.get("sigma", {}), f"{path} [[experiment]] {index + 1} sigma")
        label = f"{path}, experiment {index + 1} ({entry.get('trace', entry.get('name', ''))})"
        return DesignSource(design | fitted | own, label, sigma)
    if "candidates" in config:  # a plan
        candidates = config["candidates"]
        names = list(candidates)
        rows = [dict(zip(names, row, strict=True))
                for row in itertools.product(*candidates.values())]  # fmt: skip
        index, row = _pick(rows, which, str(path), "candidate firing", keys=names)
        signals = config.get("signals", {})
        sigma = {s: float(v["sigma"]) for s, v in signals.items() if isinstance(v, dict)}
        sampling = config.get("sampling", {})
        label = f"{path}, candidate {index + 1} (" + ", ".join(
            f"{k} {v:g}" for k, v in row.items()) + ")"  # fmt: skip
        return DesignSource(
            design | _numbers(row, label), label, sigma,
            rate=sampling.get("rate", 1000.0), duration=sampling.get("duration", 1.0),
        )  # fmt: skip
    if "tune" in config:  # a study
        conditions = config.get("condition", [])
        values, label = design, str(path)
        if conditions:
            index, entry = _pick(conditions, which, str(path), "condition")
            values = design | _numbers(entry, f"{path} [[condition]] {index + 1}",
                                       skip=("name", "constraints", "weight"))  # fmt: skip
            label = f"{path}, condition {index + 1} ({entry.get('name', '')})"
        tuned = tuple(n for n in config["tune"] if n not in values)
        return DesignSource(values, label, required=tuned)
    raise rj.ParameterError(
        f"{path}: not a study ([tune]), calibration ([[experiment]]) or plan ([candidates]) file"
    )
