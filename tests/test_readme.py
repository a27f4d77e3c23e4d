"""The README's first example, and the documentation's getting-started example after it, run as
written in a fresh interpreter, without jaxest's deprecation warnings."""

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_first_example_runs_in_a_fresh_interpreter():
    readme = (ROOT / "README.md").read_text()
    example = re.search(r"## A first look.*?```python\n(.*?)```", readme, re.S).group(1)
    getting_started = (ROOT / "docs" / "index.md").read_text()
    first_filter = re.search(r"```python\n(.*?)```", getting_started, re.S).group(1)
    done = subprocess.run(
        [sys.executable, "-W", "error:jaxest:DeprecationWarning", "-c", example + first_filter],
        cwd=ROOT, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    loglik, ok = lines[0].split()[:2]
    assert float(loglik) < 0 and ok == "True"
    loglik, status = lines[-1].split()
    assert float(loglik) < 0 and status == "OK"
