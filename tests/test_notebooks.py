"""Every notebook in notebooks/ runs top to bottom without error."""

from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))


@pytest.mark.slow
@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_notebook_runs(path):
    notebook = nbformat.read(path, as_version=4)
    NotebookClient(
        notebook,
        timeout=900,
        kernel_name="python3",
        # the suite's garbage-collector thresholds in the kernel too (jaxest.gc_thresholds)
        extra_arguments=[
            "--IPKernelApp.exec_lines=from jaxest import gc_thresholds",
            "--IPKernelApp.exec_lines=gc_thresholds.collect_rarely()",
        ],
        resources={"metadata": {"path": str(path.parent)}},
    ).execute()
