"""The documentation site builds without a warning (`mkdocs build --strict`): every API
page resolves its objects, every link and notebook is found, and the generated pages
(command-line reference, studies, notebooks) come from the sources."""

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_documentation_site_builds_strictly(tmp_path):
    site = tmp_path / "site"
    done = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(site)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        env=os.environ | {"NO_MKDOCS_2_WARNING": "1"},
    )
    assert done.returncode == 0, done.stderr[-4000:]
    # The API reference rendered the docstrings of the public API.
    solving = (site / "api" / "solving" / "index.html").read_text()
    assert "Returns:" in solving or "Returns" in solving
    assert "peak_anchoring_force" in solving
    # The command-line reference lists every command with its options.
    cli = (site / "cli" / "index.html").read_text()
    for command in ("simulate", "sweep", "optimise", "bench-tuning", "--no-cache"):
        assert command in cli
    # The notebooks carry their figures.
    notebook = (site / "notebooks" / "05_throttling_design" / "index.html").read_text()
    assert "image/png" in notebook or "data:image/png" in notebook


def test_every_public_name_has_its_api_entry():
    # The top level and `recoil_jax.extend`, each name once, where `mkdocs` renders it.
    import recoil_jax as rj

    text = "".join(p.read_text() for p in (ROOT / "docs" / "api").glob("*.md"))
    top = set(re.findall(r":::\s*recoil_jax\.(\w+)\s", text)) - {"extend"}
    extended = set(re.findall(r":::\s*recoil_jax\.extend\.(\w+)", text))
    assert top == set(rj.__all__), top ^ set(rj.__all__)
    assert extended == set(rj.extend.__all__), extended ^ set(rj.extend.__all__)


def _number(text: str) -> float:
    return float(text.replace("−", "-").strip())


def test_the_ranges_table_is_the_registry():
    """`docs/numerics.md`'s documented ranges are the registry's, row for row, and every
    parameter with a documented range has its row (the orifice knots as `orifice_<i>`)."""
    import recoil_jax as rj

    text = (ROOT / "docs" / "numerics.md").read_text()
    table = text[text.index("## Valid and documented ranges") :]
    seen = set()
    for row in re.findall(r"^\| (`.+?) \| .+? \| (.+?) \|$", table, flags=re.M):
        names = [n for n in re.findall(r"`([^`]+)`", row[0]) if n in rj.PARAMETERS]
        if not names or row[1].startswith("damping"):
            continue
        low, high = (_number(part) for part in row[1].split("–"))
        for name in names:
            assert rj.PARAMETERS[name].documented == pytest.approx((low, high)), name
            seen.add(name)
    documented = {n for n, p in rj.PARAMETERS.items() if p.documented is not None}
    assert documented - seen <= {n for n in documented if n.startswith("orifice_")}
    assert "v0" in seen and "elevation" in seen
