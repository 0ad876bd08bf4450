"""Every notebook in notebooks/ runs top to bottom at small size (LAGRAX_SMALL=1)."""

import hashlib
import os
import pathlib

import pytest


nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")

ROOT = pathlib.Path(__file__).parent.parent
NOTEBOOKS = sorted((ROOT / "notebooks").glob("*.ipynb"))
# Each notebook compiles many sweep configurations even at small size: the first
# tutorial runs every time, the others with `-m slow` (the gradient through the sweep
# that the tautochrone notebook uses is checked every time in tests/test_gradients.py).
_SLOW = {
    "speed_vs_accuracy",
    "isochronism",
    "design_a_tautochrone",
    "particles_and_constraints",
}
_CASES = [
    pytest.param(p, id=p.stem, marks=[pytest.mark.slow] if p.stem in _SLOW else [])
    for p in NOTEBOOKS
]


def _figures():
    """The digest of every PNG of the repository (the README's figures among them)."""
    return {
        p: hashlib.sha256(p.read_bytes()).hexdigest()
        for folder in ("notebooks", "benchmarks")
        for p in (ROOT / folder).rglob("*.png")
    }


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
    figures = _figures()
    client.execute()
    assert _figures() == figures  # (a small run rewrites none of them)
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
    assert os.path.isdir(ROOT / "notebooks")
