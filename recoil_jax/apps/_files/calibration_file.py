"""A calibration file (TOML), read (`load_calibration`) and written for a planned test
(`calibration_skeleton`): the one home of its keys and limits, for `recoil-jax calibrate`,
which reads it, and `recoil-jax plan`, which writes it (`docs/calibration.md` describes
the file)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import recoil_jax as rj
import recoil_jax.extend as rjx

from .inputs import (
    check_keys,
    file_error as _error,
    file_integer,
    file_number as _number,
    read_toml,
)

__all__ = [
    "MAX_EXPERIMENTS",
    "MAX_FIT_STEPS",
    "MAX_SIGNAL",
    "MAX_STARTS",
    "calibration_skeleton",
    "check_experiments",
    "load_calibration",
    "toml_string",
]

#: The most starts a calibration may have (`--starts`, `starts`): each is a fit.
MAX_STARTS = 1024
#: The most Levenberg–Marquardt steps per fit (`fit_steps`; the default is 200, and a
#: fit converges in under 50).
MAX_FIT_STEPS = 10_000
#: The most experiments, fitted and validation together (each has its panels in the
#: figures).
MAX_EXPERIMENTS = 50
#: The largest magnitude a measured value may have: beyond it the squares of the
#: residuals overflow (a unit mistake, or a broken export).
MAX_SIGNAL = 1e150

#: The keys of a calibration file, and of one `[[experiment]]` besides design values.
_FILE_KEYS = {"description", "design", "fit", "experiment", "validation", "loss", "f_scale",
              "starts", "seed", "fit_steps", "force_table", "posterior"}  # fmt: skip
#: The keys of `[posterior]` (`recoil-jax calibrate --posterior`), and of each prior.
_POSTERIOR_KEYS = {"draws", "warmup", "chains", "parallel_chains", "seed", "dense_mass",
                   "target_acceptance", "prior", "sample_noise", "noise_scale"}  # fmt: skip
_EXPERIMENT_KEYS = {"trace", "sigma", "per_experiment", "window", "name", "force_table"}


def _force_table(where: str, value: Any, folder: Path) -> rj.ForceTable | None:
    """`force_table = "file.csv"` (relative to the calibration file), or None."""
    if value is None:
        return None
    if not isinstance(value, str):
        raise _error(where, 'give force_table = "file.csv" (header t_s,F_N)')
    return rj.ForceTable.from_csv(folder / value)


def _bounds(where: str, value: Any) -> tuple[tuple[float, float], float | None]:
    """`[lo, hi]` or `{bounds = [lo, hi], start = x}`."""
    start = None
    if isinstance(value, dict):
        unknown = set(value) - {"bounds", "start"}
        if unknown or "bounds" not in value:
            raise _error(where, "give [lower, upper] or { bounds = [lower, upper], start = x }")
        if "start" in value:
            start = _number(f"{where}.start", value["start"])
        value = value["bounds"]
    if not isinstance(value, list) or len(value) != 2:
        raise _error(where, f"{value!r}: give bounds as [lower, upper]")
    return (_number(where, value[0]), _number(where, value[1])), start


def _experiment(where: str, entry: Any, folder: Path) -> rjx.Experiment:
    if not isinstance(entry, dict):
        raise _error(where, 'each experiment is a table with a trace = "file.csv"')
    if "trace" not in entry or not isinstance(entry["trace"], str):
        raise _error(where, 'names no trace (trace = "file.csv", relative to the file)')
    trace = rj.read_trace(folder / entry["trace"])
    design = {}
    for name, value in entry.items():
        if name in _EXPERIMENT_KEYS:
            continue
        if name not in rj.PARAMETERS and name not in ("t_shift", "t1"):
            raise rj.PARAMETERS.unknown(name, also=("t_shift", "t1", *_EXPERIMENT_KEYS))
        design[name] = _number(f"{where}.{name}", value)
    sigma = entry.get("sigma", {})
    if not isinstance(sigma, dict):
        raise _error(f"{where}.sigma", "give { signal = noise, ... }")
    window = entry.get("window")
    if window is not None:
        window = _bounds(f"{where}.window", window)[0]
    per = entry.get("per_experiment", [])
    if not isinstance(per, list) or not all(isinstance(n, str) for n in per):
        raise _error(f"{where}.per_experiment", "give a list of parameter names")
    twice = sorted({n for n in per if per.count(n) > 1})
    if twice:
        raise _error(f"{where}.per_experiment", f"{twice[0]} is given twice")
    return rjx.Experiment(
        trace,
        design=design,
        sigma={k: _number(f"{where}.sigma.{k}", v) for k, v in sigma.items()},
        per_experiment=tuple(per),
        window=window,
        name=str(entry.get("name", "")),
        force_table=_force_table(f"{where}.force_table", entry.get("force_table"), folder),
    )


def load_calibration(path) -> tuple[rj.Calibration, dict[str, Any]]:
    """A calibration file as a `Calibration`, and its settings (`starts`, `seed`,
    `description`). Every fault is a `ParameterError` naming the file and the key."""
    path = Path(path)
    config = read_toml(path, "calibration file")
    check_keys(path, "", config, _FILE_KEYS)
    description = config.get("description", "")
    if not isinstance(description, str):
        raise _error(str(path), f"description = {description!r}: give a string")
    design = config.get("design", {})
    for name in design:
        if name not in rj.PARAMETERS and name != "t1":
            raise rj.PARAMETERS.unknown(name, also=("t1",))
    design = {k: _number(f"[design] {k}", v) for k, v in design.items()}
    fit, start = {}, {}
    for name, value in config.get("fit", {}).items():
        fit[name], s = _bounds(f"[fit] {name}", value)
        if s is not None:
            start[name] = s
        if name in design:
            raise _error(str(path), f"{name} is given both in [design] ({name} = "
                         f"{design[name]:g}) and in [fit]: give it in one place")  # fmt: skip
    experiments = config.get("experiment", [])
    if not isinstance(experiments, list):
        raise _error(str(path), "write each experiment as [[experiment]]")
    validations = config.get("validation", [])
    if not isinstance(validations, list):
        raise _error(str(path), "write each validation experiment as [[validation]]")
    check_experiments(len(experiments) + len(validations), str(path))
    for key, least, most in (("starts", 1, MAX_STARTS), ("seed", 0, 2**63 - 1),
                             ("fit_steps", 1, MAX_FIT_STEPS)):  # fmt: skip
        file_integer(path, key, config.get(key, least), least, most)
    folder = path.parent
    fitted = [_experiment(f"[[experiment]] {i}", e, folder) for i, e in enumerate(experiments, 1)]
    validation = [
        _experiment(f"[[validation]] {i}", e, folder) for i, e in enumerate(validations, 1)
    ]
    for kind, entries in (("experiment", fitted), ("validation", validation)):
        for i, e in enumerate(entries, 1):
            held = [n for n in e.design if n in fit and n not in e.per_experiment]
            if held:
                name = held[0]
                raise _error(
                    str(path),
                    f"[[{kind}]] {i}: {name} = {e.design[name]:g} is fitted ([fit]), so it "
                    f"would not be held there: give a start in [fit] ({name} = {{ bounds = "
                    f"[..], start = .. }}), or fit it in each experiment (per_experiment)",
                )
    calibration = rj.Calibration(
        fitted,
        fit=fit,
        start=start,
        design=design,
        loss=config.get("loss", "linear"),
        f_scale=_number("f_scale", config.get("f_scale", 3.0)),
        validation=validation,
        force_table=_force_table("force_table", config.get("force_table"), folder),
    )
    settings = {
        "posterior": _posterior(path, config.get("posterior", {})),
        "starts": config.get("starts", rjx.DEFAULT_STARTS),
        "seed": config.get("seed", 0),
        "fit_steps": config.get("fit_steps", 200),
        "description": description,
    }
    return calibration, settings


def _posterior(path: Path, table: Any) -> dict[str, Any]:
    """`[posterior]`: `sample_posterior`'s settings by name (checked against the
    calibration by `rjx.check_posterior_settings` before the fit), its priors under
    `[posterior.prior]` as `name = { kind = "normal", mean = .., sd = .. }`."""
    if not isinstance(table, dict):
        raise _error(str(path), "write the sampler's settings as a [posterior] table")
    check_keys(path, "posterior", table, _POSTERIOR_KEYS)
    settings: dict[str, Any] = {}
    for key in ("draws", "warmup", "chains", "parallel_chains", "seed"):
        if key in table:
            settings[key] = table[key]
    for key in ("dense_mass", "sample_noise"):
        if key in table:
            if not isinstance(table[key], bool):
                raise _error(str(path), f"[posterior] {key} = {table[key]!r}: give true or false")
            settings[key] = table[key]
    if "target_acceptance" in table:
        settings["target_acceptance"] = _number(
            "[posterior] target_acceptance", table["target_acceptance"]
        )
    if "noise_scale" in table:
        scales = table["noise_scale"]
        if not isinstance(scales, dict):
            raise _error(str(path), "write each noise's prior scale under "
                                    "[posterior.noise_scale] as signal = number")  # fmt: skip
        settings["noise_scale"] = {name: _number(f"[posterior.noise_scale] {name}", value)
                                   for name, value in scales.items()}  # fmt: skip
    priors = table.get("prior", {})
    if not isinstance(priors, dict):
        raise _error(str(path), "write each prior under [posterior.prior] as name = { .. }")
    settings["priors"] = {}
    for name, spec in priors.items():
        try:
            settings["priors"][name] = rjx.Prior.of(spec)
        except rj.ParameterError as error:
            raise _error(str(path), f"[posterior.prior] {name}: {error}") from None
    return settings


def check_experiments(count: int, where: str) -> None:
    if count > MAX_EXPERIMENTS:
        raise _error(where, f"{count:,} experiments (fitted and validation), more than "
                     f"{MAX_EXPERIMENTS}: fit fewer at a time")  # fmt: skip


def calibration_skeleton(plan: rj.FiringPlan, description: str = "") -> str:
    """A calibration file for the plan (`recoil-jax calibrate` reads it once the
    traces exist): the known values, the fitted bounds starting from the guess, and one
    `[[experiment]]` per firing with its condition values, `t1` and signals' noise."""
    problem = plan.problem
    guess = problem.guess
    lines = [
        f"description = {toml_string('calibration of the planned test: ' + description)}",
        "# Written by `recoil-jax plan`. Record each firing's traces as a CSV file (a t",
        "# column and one per signal) under the name below, then run",
        "#   recoil-jax calibrate calibration.toml",
        "",
        "[design]",
        *(f"{k} = {float(v)!r}" for k, v in guess.items() if k not in problem.fit),
        "",
        "[fit]",
        *(
            f"{k} = {{ bounds = [{float(lo)!r}, {float(hi)!r}], start = {float(guess[k])!r} }}"
            for k, (lo, hi) in problem.fit.items()
        ),
    ]
    for i, (c, signals) in enumerate(plan.plan.firings, 1):
        noise = ", ".join(f"{s} = {float(problem.signals[s].sigma)!r}" for s in signals)
        lines += [
            "",
            "[[experiment]]",
            f'trace = "firing_{i}.csv"          # record: {", ".join(signals)}',
            *(f"{k} = {float(v)!r}" for k, v in plan.conditions[c].items()),
            f"t1 = {float(problem.duration)!r}",
            f"sigma = {{ {noise} }}",
        ]
    return "\n".join(lines) + "\n"


def toml_string(text: str) -> str:
    """`text` as a TOML basic string: JSON's escapes (quotes, backslashes, every control
    character) are TOML's, but for DEL, which TOML does not take raw."""
    return json.dumps(text, ensure_ascii=False).replace("\x7f", "\\u007f")
