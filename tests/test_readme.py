"""The README's first example runs as written in a fresh interpreter."""

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_first_example_runs_in_a_fresh_interpreter():
    readme = (ROOT / "README.md").read_text()
    example = re.search(r"## A first look.*?```python\n(.*?)```", readme, re.S).group(1)
    done = subprocess.run(
        [sys.executable, "-c", example], cwd=ROOT, capture_output=True, text=True, timeout=600
    )
    assert done.returncode == 0, done.stderr
    loglik, ok = done.stdout.split()[:2]
    assert float(loglik) < 0 and ok == "True"
