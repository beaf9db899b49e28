"""The notebooks: each is a jupytext percent script (`notebooks/*.py`, the source, so
diffs stay readable) paired with an `.ipynb` committed with its outputs (the figures show
when browsing the repository). The pair must hold the same cells, and the scripts execute
top to bottom through a Jupyter kernel in their fast setting (RECOIL_JAX_FAST=1)."""

import os
from pathlib import Path

import jupytext
import pytest
from nbclient import NotebookClient

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.py"))
RENDER = "jupytext --to ipynb --execute notebooks/<name>.py"


def _cells(notebook):
    return [(cell.cell_type, cell.source) for cell in notebook.cells]


def test_there_is_a_notebook_for_each_main_use():
    assert [p.stem[:2] for p in NOTEBOOKS] == [
        "01",
        "02",
        "03",
        "04",
        "05",
        "06",
        "07",
        "08",
        "09",
        "10",
    ]


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_is_committed_with_its_outputs(path):
    """The `.ipynb` beside each script has the script's cells (it cannot drift from
    the code: re-render it with the command in `RENDER`), each code cell ran in order,
    none raised, and its figures are stored."""
    rendered_path = path.with_suffix(".ipynb")
    assert rendered_path.exists(), f"render it: {RENDER}"
    source, rendered = jupytext.read(path), jupytext.read(rendered_path)
    assert _cells(rendered) == _cells(source), f"out of date; re-render: {RENDER}"
    code = [cell for cell in rendered.cells if cell.cell_type == "code"]
    assert [cell.execution_count for cell in code] == list(range(1, len(code) + 1))
    outputs = [output for cell in code for output in cell.outputs]
    assert not [o for o in outputs if o.output_type == "error"]
    assert any("image/png" in o.get("data", {}) for o in outputs)


@pytest.mark.slow  # executes every notebook on a kernel
@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_executes(path, monkeypatch):
    monkeypatch.setenv("RECOIL_JAX_FAST", "1")
    notebook = jupytext.read(path)
    # The script holds code and markdown only; outputs live in the .ipynb.
    assert all(not cell.get("outputs") for cell in notebook.cells)
    assert notebook.cells[0].cell_type == "markdown"  # opens with the physics
    client = NotebookClient(
        notebook,
        timeout=600,
        kernel_name="python3",
        resources={"metadata": {"path": str(path.parent)}},
    )
    client.execute(env=dict(os.environ))
    errors = [
        output
        for cell in notebook.cells
        for output in cell.get("outputs", [])
        if output.get("output_type") == "error"
    ]
    assert not errors
