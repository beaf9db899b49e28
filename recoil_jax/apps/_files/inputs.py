"""What a user types or loads: `name=value` items, the files the commands read, and the
warnings about values the model accepts but were probably not meant.

Every command reads its input here, so that each bad input gets the same one-line
`ParameterError` (exit status 2) naming the parameter or the file, before anything is
solved or compiled.
"""

from __future__ import annotations

import contextlib
import math
import os
import sys
from collections.abc import Mapping
from pathlib import Path

import numpy as np

import recoil_jax as rj
import recoil_jax.extend as rjx

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib  # pyright: ignore[reportMissingImports]

__all__ = [
    "MADE_FOLDERS",
    "SETTINGS",
    "TooLarge",
    "check_figure_path",
    "check_keys",
    "check_not_input",
    "check_output_file",
    "design_warnings",
    "file_error",
    "file_integer",
    "file_number",
    "known",
    "names",
    "number",
    "output_folder",
    "parse_assignments",
    "read_calibration_section",
    "read_text",
    "read_toml",
    "remove_unused_folders",
    "resolve_shipped",
    "results_folder",
    "split_assignment",
    "unknown_name",
    "values_taken",
    "warn",
]

#: A text file's contents, or one line saying why not (the library's reader).
read_text = rjx.read_text


def read_toml(path, what: str) -> dict:
    """A TOML file (a study, a calibration, a sensitivity analysis) as a dict, or one line
    naming the file: missing, not text, or not valid TOML."""
    try:
        return tomllib.loads(read_text(path, what))
    except tomllib.TOMLDecodeError as error:
        raise file_error(path, f"not valid TOML ({error})") from None


def file_error(where, message: str) -> rj.ParameterError:
    """A fault in a file the command loads: `where` (the file, and the key) first."""
    return rj.ParameterError(f"{where}: {message}")


def check_keys(where, section: str, table: Mapping, known_keys, *, kind: str = "key") -> None:
    """The one refusal of keys a section does not take: `{where}: [section] unknown
    key 'x'; known: a, b` (`section` empty: the file's top level; `kind`: what a key
    is, "key" or "section")."""
    unknown = sorted(set(table) - set(known_keys))
    if unknown:
        label = f"[{section}] " if section else ""
        plural = "s" if len(unknown) > 1 else ""
        raise file_error(
            where,
            f"{label}unknown {kind}{plural} {', '.join(map(repr, unknown))}; known: "
            f"{', '.join(sorted(known_keys))}",
        )


def file_integer(where, key: str, value, least: int, most: int | None = None) -> int:
    """An integer setting from a loaded file, at least `least` (at most `most`), or the
    one refusal: `{where}: key = value: valid an integer >= least` (`from least to
    most`; `where` None: no file to name)."""
    try:
        return rjx.check_integer(key, value, least, most)
    except rj.ParameterError as refused:
        raise refused if where is None else file_error(where, str(refused)) from None


def read_calibration_section(
    path, section, known_keys, taken: Mapping[str, str]
) -> rjx.FittedParameters:
    """A `[calibration]` section (of a study or a sensitivity file): `from = "result.json"`
    (a calibration's result, relative to the file at `path`) read as the fitted values
    and their covariance, its keys among `known_keys` (`from` and the file's own), and
    each fitted name in none of `taken` (`{name: "[design]", ...}`: where the file gives
    it). A result whose model does not explain its traces, or leaves a value
    undetermined, is refused. Every refusal names the file and `[calibration]`."""
    if not isinstance(section, dict) or not isinstance(section.get("from"), str):
        raise file_error(path, '[calibration] needs from = "result.json" (a calibration result)')
    check_keys(path, "calibration", section, known_keys)
    try:
        fitted = rjx.FittedParameters.from_json(Path(path).parent / section["from"])
        fitted.check_determined()
    except rj.ParameterError as error:
        raise file_error(path, f"[calibration] {error}") from None
    for name in fitted.names:
        if name in taken:
            raise file_error(path, f"{taken[name]} {name} is fitted by the calibration: leave "
                             "it out")  # fmt: skip
    return fitted


def file_number(where, value) -> float:
    """A finite number from a loaded file (TOML), or one line naming `where`."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise file_error(where, f"{value!r} is not a number")
    if not math.isfinite(value):
        raise file_error(where, f"{value!r} is not finite")
    return float(value)


def resolve_shipped(source, folder: Path, what: str, shipped_as: str) -> Path:
    """The file `source` names: an existing path, or the name of a file shipped in
    `folder` (`name` or `name.toml`, whatever the working directory). `what` names the
    kind of file and `shipped_as` the shipped ones, for the message."""
    path = Path(source)
    if path.exists():
        return path
    shipped = folder / (path.name if path.suffix == ".toml" else f"{path.name}.toml")
    if path.parent == Path(".") and shipped.exists():
        return shipped
    names = sorted(p.stem for p in folder.glob("*.toml"))
    raise rj.ParameterError(
        f"{what} file {source} not found; shipped {shipped_as}: {', '.join(names) or 'none'}"
    )


#: Names `name=value` items may use besides the parameters (`rj.PARAMETERS`).
SETTINGS = ("t1",)


def known(name: str) -> bool:
    """Whether `name=value` may use `name`: a parameter (orifice knots included) or `t1`."""
    return name in rj.PARAMETERS or name in SETTINGS


def names() -> str:
    """Every name, for messages."""
    return f"{rj.PARAMETERS.names()}, {', '.join(SETTINGS)}"


def unknown_name(name: str) -> rj.ParameterError:
    """The error for a name that is not `known`."""
    return rj.PARAMETERS.unknown(name, also=SETTINGS)


def split_assignment(item: str, given: Mapping[str, object]) -> tuple[str, str]:
    """`name=text` → `(name, text)`; the name must be `known` and not already `given`."""
    name, sep, text = item.partition("=")
    if not sep:
        raise rj.ParameterError(f"expected name=value, got {item!r}; names: {names()}")
    if not known(name):
        raise unknown_name(name)
    if name in given:
        raise rj.ParameterError(f"{name} is given twice ({name}={given[name]} and {item})")
    return name, text


def parse_assignments(items: list[str]) -> dict[str, float]:
    """`name=value` items as a dict of numbers; names must be `known`, each given once."""
    values: dict[str, float] = {}
    texts: dict[str, str] = {}
    for item in items:
        name, text = split_assignment(item, texts)
        texts[name] = text
        try:
            values[name] = number(text)
        except ValueError as error:
            why = str(error) if isinstance(error, TooLarge) else ""
            raise rj.ParameterError(f"{name} = {text!r} is not a number{why}") from None
    return values


class TooLarge(ValueError):
    """A number beyond the largest float64: its message (from ": ") says so."""


def number(text: str) -> float:
    """A number as typed; `ValueError` for none, and `TooLarge` (a `ValueError`) for one
    beyond the largest float64 (which `float` would read as inf), its message saying so."""
    value = float(text)
    if math.isinf(value) and "inf" not in text.lower():
        raise TooLarge(": beyond the largest float64 (about 1.8e308)")
    return value


#: The output folders this process made (`output_folder`), first made first: the
#: command line removes those still empty when a command is refused or interrupted.
MADE_FOLDERS: list[Path] = []


def output_folder(path, option: str = "--out") -> Path:
    """`path` as a folder to write into, made if missing (before any solve): a path that
    is a file, passes through one, or cannot be made or written is one line naming
    `option`; so is an empty name (which would be the current folder: say `.`)."""
    if isinstance(path, str) and not path.strip():
        raise rj.ParameterError(f"{option} {path!r} is empty: give a folder (. for this one)")
    path = Path(path)
    missing = [p for p in (path, *path.parents) if not p.exists()]
    if path.exists() and not path.is_dir():
        raise rj.ParameterError(f"{option} {path} is a file, not a folder: give a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        raise rj.ParameterError(
            f"{option} {path}: a part of the path is a file, not a folder"
        ) from None
    except OSError as error:
        raise rj.ParameterError(f"{option} {path} cannot be made: {error.strerror}") from None
    MADE_FOLDERS.extend(reversed(missing))
    if not os.access(path, os.W_OK | os.X_OK):
        raise rj.ParameterError(f"{option} {path} cannot be written (permission denied)")
    return path


def check_not_input(out: Path, names, *inputs) -> None:
    """Refuse an output folder `out` where a file the command writes (`names`) is one of
    its `inputs` (`plan DIR/calibration.toml --out DIR`): it would be overwritten."""
    for name in names:
        target = (out / name).resolve()
        for given in inputs:
            if given is not None and Path(given).resolve() == target:
                raise rj.ParameterError(
                    f"--out {out} would overwrite the input {given} with the {name} it "
                    "writes: give another folder"
                )


def results_folder(out, command: str, source) -> Path:
    """A command's output folder: `out` (its `--out`) if given, else
    `results/<command>/<name>`, `name` the stem of `source` (a file, or a shipped
    example's name): each input its own folder, so that no run replaces the results of
    a run on another input."""
    if out is not None:
        return output_folder(out) if not str(out).strip() else Path(out)  # ('' refused)
    return Path("results") / command / Path(source).stem


def remove_unused_folders() -> None:
    """Remove the folders `output_folder` made that are still empty (innermost first)."""
    while MADE_FOLDERS:
        folder = MADE_FOLDERS.pop()
        with contextlib.suppress(OSError):  # not empty, or gone: leave it
            folder.rmdir()


def check_figure_path(path) -> Path:
    """`path` if matplotlib can write a figure of its suffix into its folder (made if
    missing; checked before any solve)."""
    from matplotlib.figure import Figure

    path = Path(path)
    formats = Figure().canvas.get_supported_filetypes()
    if path.suffix.lstrip(".").lower() not in formats:
        raise rj.ParameterError(
            f"cannot write a figure to {path}: give a file ending in one of "
            + ", ".join(f".{f}" for f in sorted(formats))
        )
    return check_output_file(path, "--plot")


def check_output_file(path, option: str) -> Path:
    """`path` as a file the command will write (`option` names it in messages): not a
    folder, its folder made if missing and writable; checked before any solve."""
    path = Path(path)
    if path.is_dir():
        raise rj.ParameterError(f"{option} {path} is a folder: give a file")
    output_folder(path.parent, option=f"{option}'s folder")  # made if missing, and writable
    return path


def design_warnings(values: Mapping[str, object], table: rj.ForceTable | None = None) -> list[str]:
    """One line per value the model accepts but a user probably did not mean: outside its
    documented range (where accuracy is tested), or set where it has no effect. `values`:
    flat name → number or array (a sweep's columns)."""
    lines = []
    knots = sorted(n for n in values if n.startswith("orifice_"))
    no_buffer = bool(knots) and _all_zero(values.get("piston_area"))
    recuperator = {"recuperator_length", "polytropic_index"} & set(values)
    no_recuperator = (
        bool(recuperator)
        and _all_zero(values.get("recuperator_force", 0.0))
        and _all_zero(values.get("recuperator_preload", 0.0))
    )
    mount = {"cg_distance", "trunnion_height", "spade_distance"} & set(values)
    no_mount = bool(mount) and _all_zero(values.get("mount_mass", 0.0))
    unused = (set(knots) if no_buffer else set()) | (recuperator if no_recuperator else set())
    unused |= mount if no_mount else set()
    for name, value in values.items():
        ranged = name in rj.PARAMETERS or name == "t1"  # every documented range, t1's too
        if not ranged or name in unused or value is None:
            continue
        p = rjx.T1_LIMITS if name == "t1" else rj.PARAMETERS[name]
        array = np.asarray(value, dtype=float).reshape(-1)
        if p.zero_means:  # m = 0 is the simplified model, k = 0 no spring: not values
            array = array[array != 0]
        # A value the model refuses is refused (one line), not also warned about.
        lower_ok = array > p.lower if p.lower_open else array >= p.lower
        array = array[np.isfinite(array) & lower_ok & (array <= p.ceiling)]
        if p.documented is None or not array.size:
            continue
        lo, hi = p.documented
        outside = (array < lo) | (array > hi)
        if outside.any():
            which = f"{name}={array[outside][0]:g} is"
            if array.size > 1:
                which = (
                    f"{name}: {int(outside.sum())} of {array.size} values (e.g. {which[:-3]}) are"
                )
            unit = f" {p.unit}" if p.unit else ""
            lines.append(
                f"{which} outside the documented range {lo:g} to {hi:g}{unit}, where the "
                "model's accuracy is tested"
            )
    if no_buffer:
        lines.append(
            f"piston_area = 0 is no hydraulic buffer: the orifice ({', '.join(knots)}) "
            "has no effect"
        )
    if no_recuperator:
        lines.append(
            "recuperator_force = 0 is no gas recuperator: "
            f"{', '.join(sorted(recuperator))} has no effect"
        )
    if no_mount:
        lines.append(
            f"mount_mass = 0 is no mount: {', '.join(sorted(mount))} "
            f"{'has' if len(mount) == 1 else 'have'} no effect"
        )
    if table is not None:
        F = np.asarray(table.F)
        if np.any(F < 0):
            i = int(np.argmin(F))
            lines.append(
                f"the force table pulls the barrel forward: F = {F[i]:g} N < 0 at "
                f"t = {float(np.asarray(table.t)[i]):g} s"
            )
    return lines


def values_taken(*tables: Mapping[str, object]) -> dict[str, np.ndarray]:
    """Every value each name takes over `tables` (a design, tuned or fitted bounds,
    conditions, candidates: flat name → a number or numbers), as one array per name:
    what `design_warnings` checks for a file that gives more than one design."""
    taken: dict[str, list[np.ndarray]] = {}
    for table in tables:
        for name, value in table.items():
            if value is not None:
                taken.setdefault(name, []).append(np.asarray(value, dtype=float).reshape(-1))
    return {name: np.concatenate(parts) for name, parts in taken.items()}


def warn(lines: list[str]) -> None:
    """Print `design_warnings` on stderr, one line each."""
    for line in lines:
        print(f"recoil-jax: warning: {line}", file=sys.stderr)


def _all_zero(value) -> bool:
    return value is not None and bool(np.all(np.asarray(value, dtype=float) == 0.0))
