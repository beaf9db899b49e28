"""The one JSON writer of the command line: every `result.json` (calibrate, sensitivity,
optimise) and every `--json` print goes through `dumps` or `write`.

JSON has no NaN or infinity (Python's `json` writes the bare words `NaN` and `Infinity`,
which other readers refuse). A number that is not finite is written `null`, with the
reason beside it: `"aic": null, "aic_null": "inf (not a finite number; JSON has none)"`
(for the values of a list, one note on its key: how many, and which). The text is then
made with `allow_nan=False`, so that nothing non-finite can slip through.
"""

from __future__ import annotations

import json as _json
import math
from pathlib import Path
from typing import Any

import numpy as np

import recoil_jax.extend as rjx

__all__ = ["dumps", "finite", "loads", "write", "write_text"]

#: What is said beside a value written `null`.
_REASON = "{} (not a finite number; JSON has none)"

loads = _json.loads


def _bad(value: Any) -> str | None:
    """`"nan"`, `"inf"` or `"-inf"` for a float that is not finite, else None."""
    if isinstance(value, float | np.floating) and not math.isfinite(value):
        return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf")
    return None


def _clean(value: Any, found: list[str]) -> Any:
    """`value` with every non-finite float as None (each one's word appended to
    `found`), numpy scalars and arrays as Python's, dict notes added at each level."""
    if isinstance(value, np.ndarray):
        value = value.tolist()
    elif isinstance(value, np.generic):
        value = value.item()
    word = _bad(value)
    if word is not None:
        found.append(word)
        return None
    if isinstance(value, dict):
        cleaned: dict = {}
        for key, item in value.items():
            inner: list[str] = []
            cleaned[key] = _clean(item, inner)
            note = f"{key}_null"
            if not inner or isinstance(item, dict) or note in value:
                continue
            if len(inner) == 1 and cleaned[key] is None:
                cleaned[note] = _REASON.format(inner[0])  # beside the value
            else:
                kinds = ", ".join(sorted(set(inner)))
                cleaned[note] = (
                    f"{len(inner)} values written null: {kinds} (not finite; JSON has none)"
                )
        return cleaned
    if isinstance(value, list | tuple):
        return [_clean(item, found) for item in value]
    return value


def finite(value: Any) -> Any:
    """`value` (dicts, lists, numbers) as strict JSON can hold it: see the module."""
    return _clean(value, [])


def dumps(value: Any, **options: Any) -> str:
    """`json.dumps` of `finite(value)`, refusing anything non-finite left."""
    options.pop("allow_nan", None)
    return _json.dumps(finite(value), allow_nan=False, **options)


def write(path, value: Any) -> Path:
    """Write `value` as indented JSON to `path`, whole or not at all: into a temporary
    file beside it, renamed over `path` once complete (a full disk leaves no truncated
    file). A failed write is an `OSError` naming `path`."""
    return write_text(path, dumps(value, indent=2) + "\n")


def write_text(path, text: str) -> Path:
    """Write `text` to `path` whole or not at all (`rjx.written`); a failure names
    `path`."""
    path = Path(path)
    with rjx.written(path) as temporary, open(temporary, "w", encoding="utf-8", newline="") as f:
        f.write(text)
    return path
