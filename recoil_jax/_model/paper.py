"""The paper's numbers (Table 2 and text), shipped with the package, beside the
high-accuracy hard-switch reference values of the model in `docs/model.md`."""

from __future__ import annotations

import json
from importlib import resources
from typing import Any

from .._model.params import params_from_values

__all__ = ["case_params", "paper_cases"]


def paper_cases() -> list[dict[str, Any]]:
    """The cases: each a dict with `case` (name), `params` (flat names: `m`, `gap`; m = 0
    is the simplified model), `paper` and `reference` (JSON keys, as `simulate --json`)."""
    text = resources.files("recoil_jax").joinpath("data/paper_cases.json").read_text()
    return json.loads(text)["cases"]


def case_params(case: dict[str, Any]):
    """`RecoilParams` of one paper case (defaults elsewhere)."""
    values = dict(case["params"])
    if values.get("m", 0.0) == 0.0:
        values = {"m": 0.0}
    return params_from_values(values)
