"""The notebooks execute from top to bottom (with nbclient, on the ``python3`` kernel)."""

from __future__ import annotations

from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")

pytestmark = pytest.mark.usefixtures("kernel_imports_this_checkout")

NOTEBOOKS = Path(__file__).resolve().parents[2] / "notebooks"


def _run(path: Path):
    nb = nbformat.read(path, as_version=4)
    client = nbclient.NotebookClient(
        nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(path.parent)}}
    )
    client.execute()  # raises CellExecutionError on the first failing cell
    return nb


def _stdout(nb) -> str:
    return "".join(
        out.get("text", "")
        for cell in nb.cells
        if cell.cell_type == "code"
        for out in cell.get("outputs", [])
        if out.get("output_type") == "stream" and out.get("name") == "stdout"
    )


def test_quickstart_runs():
    nb = _run(NOTEBOOKS / "quickstart.ipynb")
    text = _stdout(nb)
    assert "same free run: True" in text
    assert "same smoothed states: True" in text
    errors = [
        out for cell in nb.cells if cell.cell_type == "code"
        for out in cell.get("outputs", []) if out.get("output_type") == "error"
    ]
    assert not errors
    # the fit recovers the paper's parameters (a = 0.9, b = 1, c = 1)
    values = {
        line.split("=")[0].strip(): float(line.split("=")[1].split()[0])
        for line in text.splitlines()
        if line[:2] in ("a ", "b ", "c ")
    }
    assert values["a"] == pytest.approx(0.9, abs=0.1)
    assert values["b"] == pytest.approx(1.0, abs=0.15)
    assert values["c"] == pytest.approx(1.0, abs=0.15)


def test_stored_notebook_has_outputs():
    """The notebook is stored with the outputs of a run (readable on GitHub without running)."""
    nb = nbformat.read(NOTEBOOKS / "quickstart.ipynb", as_version=4)
    code = [c for c in nb.cells if c.cell_type == "code"]
    assert code and all(c.get("execution_count") for c in code)
    assert any(o.get("output_type") == "display_data" for c in code for o in c.outputs)


# The reproduction notebooks (one per experiment of the paper's Section 4) are tested in
# tests/applications/test_notebooks_reproduction.py.
