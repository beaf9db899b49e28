"""The documentation site builds without a warning (`mkdocs build --strict`): every API
page resolves its objects, every link and notebook is found, and the generated pages
(command-line reference, studies, notebooks) come from the sources."""

import os
import subprocess
import sys
from pathlib import Path

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
