"""Every notebook in notebooks/ runs top to bottom at small size (LAGRAX_SMALL=1)."""

import os
import pathlib

import pytest


nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")

NOTEBOOKS = sorted((pathlib.Path(__file__).parent.parent / "notebooks").glob("*.ipynb"))
# The two longest at small size (40-50 s each on the CI's 2 cores, mostly compiling
# many sweep configurations) run with `-m slow`; the tautochrone notebook (the
# gradient through the sweep) and the two tutorials run every time.
_SLOW = {"speed_vs_accuracy", "isochronism"}
_CASES = [
    pytest.param(p, id=p.stem, marks=[pytest.mark.slow] if p.stem in _SLOW else [])
    for p in NOTEBOOKS
]


@pytest.mark.parametrize("path", _CASES)
def test_notebook_runs(path, monkeypatch, tmp_path):
    monkeypatch.setenv("LAGRAX_SMALL", "1")
    monkeypatch.setenv("MPLBACKEND", "Agg")
    # The kernel is a subprocess: without this, `patch = ["subprocess"]` in the
    # coverage settings measures it too, ~30% slower; notebooks are not coverage.
    monkeypatch.delenv("COVERAGE_PROCESS_CONFIG", raising=False)
    monkeypatch.delenv("COVERAGE_PROCESS_START", raising=False)
    nb = nbformat.read(path, as_version=4)
    assert nb.cells[0].cell_type == "markdown" and nb.cells[0].source.startswith("#")
    client = nbclient.NotebookClient(
        nb,
        timeout=600,
        kernel_name="python3",
        resources={"metadata": {"path": tmp_path}},
    )
    client.execute()
    errors = [
        out
        for cell in nb.cells
        if cell.cell_type == "code"
        for out in cell.get("outputs", [])
        if out.get("output_type") == "error"
    ]
    assert not errors


def test_notebooks_exist():
    names = {p.name for p in NOTEBOOKS}
    assert names, "notebooks/ has no notebooks"
    assert os.path.isdir(pathlib.Path(__file__).parent.parent / "notebooks")
