"""The README's Python example runs and prints what it says, and so do the guide's pages
that continue it (their blocks run in order, in one namespace)."""

import re
from pathlib import Path

import numpy as np
import pytest

import recoil_jax as rj
from recoil_jax._model.derivatives import SIGNAL_ALIASES, SIGNALS

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
#: The pages whose Python blocks continue the README's example, in order.
PAGES = [README, *(ROOT / "docs" / f"{page}.md" for page in ("python", "tuning", "sensitivity"))]


@pytest.mark.slow
def test_readme_python_example_runs(capsys):
    namespace = {}
    for page in PAGES:
        blocks = re.findall(r"```python\n(.*?)```", page.read_text(), flags=re.S)
        assert blocks, page
        for block in blocks:
            exec(compile(block, str(page), "exec"), namespace)
    printed = capsys.readouterr().out.split()
    assert float(printed[0]) == pytest.approx(5514.05, abs=0.01)
    assert float(printed[1]) == pytest.approx(0.183827, abs=1e-6)
    assert namespace["batch"].peak_anchoring_force.shape == (64,)


def test_every_signal_name_of_the_readme_and_of_traces_is_a_history_attribute():
    # The README's `simulate` line names the fields; a trace's columns (`read_trace`) may
    # use the paper's symbols or History's longer names: each one reads the same series.
    said = re.search(r"rj\.simulate\(.*#\s*(.*)", README.read_text())
    assert said, "the README's simulate line"
    names = [n.strip() for n in said.group(1).split(",")]
    assert set(names) == set(SIGNALS), names
    history = rj.simulate(ts=np.linspace(0.0, 0.5, 11))
    for name in [*names, *SIGNAL_ALIASES]:
        assert getattr(history, name).shape == (11,), name
    for field, symbol in SIGNAL_ALIASES.items():
        assert getattr(history, symbol) is getattr(history, field)
