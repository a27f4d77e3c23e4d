"""Every benchmark script loads and parses its options: most are run by hand, not by a test,
and a renamed function in jaxest (``parallel.grid_points``) breaks them unseen."""

import os
import sys

import pytest

from tests import benchmark_scripts

SCRIPTS = sorted(path.stem for path in benchmark_scripts.BENCHMARKS.glob("*.py"))


@pytest.mark.parametrize("name", SCRIPTS)
def test_script_loads_and_prints_its_help(name, monkeypatch, capsys):
    # scripts may set XLA_FLAGS for what they start (profile_step): restored after the test
    monkeypatch.setenv("XLA_FLAGS", os.environ.get("XLA_FLAGS", ""))
    monkeypatch.syspath_prepend(benchmark_scripts.BENCHMARKS)  # as run: siblings import by name
    module = benchmark_scripts.load(name)
    monkeypatch.setattr(sys, "argv", [f"{name}.py", "--help"])
    with pytest.raises(SystemExit) as exit_:
        module.main()
    assert exit_.value.code == 0
    assert capsys.readouterr().out.startswith("usage:")
