"""Every notebook in notebooks/ runs top to bottom without error.

The code cells run in the test's own process, in order and in one namespace, as a script made
from the notebook would: a Jupyter kernel per notebook cost 2.7 s of CPU each to start and to
import jax, jaxest and matplotlib again (seven notebooks: 59 s in kernels, 41 s in one
process). ``make docs`` executes every notebook in a kernel, and the build fails on a cell that
raises there (``allow_errors: false`` in mkdocs.yml)."""

import linecache
from pathlib import Path

import matplotlib.pyplot as plt
import nbformat
import pytest

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))


@pytest.mark.slow
@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_notebook_runs(path, monkeypatch):
    monkeypatch.chdir(path.parent)  # where a kernel started by Jupyter would run it
    namespace = {"__name__": "__main__"}
    try:
        for index, cell in enumerate(nbformat.read(path, as_version=4).cells):
            if cell.cell_type == "code":
                name = f"{path.name}, cell {index}"
                # the cell's lines in tracebacks
                linecache.cache[name] = (len(cell.source), None, cell.source.splitlines(True), name)
                exec(compile(cell.source, name, "exec"), namespace)
    finally:
        plt.close("all")
