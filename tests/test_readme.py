"""The README's Python example runs and prints what it says, and so do the guide's pages
that continue it (their blocks run in order, in one namespace)."""

import re
from pathlib import Path

import pytest

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
