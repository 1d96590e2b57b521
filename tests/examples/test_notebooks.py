"""The example notebooks run top to bottom in a kernel of this interpreter, as a reader would run
them (examples/notebooks; issue 61): a cell that raises fails the test."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("ipykernel")
pytest.importorskip("arviz")

NOTEBOOKS = sorted((Path(__file__).resolve().parents[2] / "examples" / "notebooks").glob("*.ipynb"))


def test_there_are_notebooks():
    assert [p.name for p in NOTEBOOKS] == ["where_did_the_mug_come_from.ipynb"]


@pytest.fixture
def kernel(tmp_path, monkeypatch) -> str:
    """A kernel spec running this interpreter (a user's own ``python3`` spec may name another),
    found first on JUPYTER_PATH."""
    spec = tmp_path / "jupyter" / "kernels" / "dejaview-test"
    spec.mkdir(parents=True)
    argv = [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"]
    (spec / "kernel.json").write_text(json.dumps({"argv": argv, "display_name": "dejaview test",
                                                  "language": "python"}))
    monkeypatch.setenv("JUPYTER_PATH", str(tmp_path / "jupyter"))
    return "dejaview-test"


def run(nb, where: Path, kernel: str) -> None:
    """Execute nb in place, in the folder ``where`` (CellExecutionError where a cell raises)."""
    nbclient.NotebookClient(nb, timeout=600, kernel_name=kernel, resources={"metadata": {"path": str(where)}}).execute()


def test_a_cell_that_raises_fails_the_run(tmp_path, kernel):
    nb = nbformat.v4.new_notebook(cells=[nbformat.v4.new_code_cell("import sys\nprint(sys.executable)"),
                                         nbformat.v4.new_code_cell("raise ValueError('in the notebook')")])
    with pytest.raises(nbclient.exceptions.CellExecutionError, match="in the notebook"):
        run(nb, tmp_path, kernel)
    assert nb.cells[0].outputs[0].text.strip() == sys.executable  # the kernel is this interpreter


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_notebook_runs_top_to_bottom(path, tmp_path, kernel):
    nb = nbformat.read(path, as_version=4)
    assert all(not c.get("outputs") for c in nb.cells if c.cell_type == "code"), "commit notebooks without outputs"
    run(nb, path.parent, kernel)
    code = [c for c in nb.cells if c.cell_type == "code"]
    assert all(c.execution_count for c in code)
    errors = [o for c in code for o in c.outputs if o.output_type == "error"]
    assert not errors
    images = [o for c in code for o in c.outputs if "image/png" in o.get("data", {})]
    assert len(images) >= 4  # rank, posterior, pair plots and the heatmap were drawn
    nbformat.write(nb, tmp_path / path.name)  # the executed notebook, for a look when it fails
