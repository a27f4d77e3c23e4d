"""The adaptive study in quick mode writes summary.json of the required form and its figures."""

import json

import numpy as np
import pytest

from jaxest.studies.adaptive import settling_time

KEYS = {"theta_true", "theta_final", "theta_settling_time", "x_error_final", "pe_min_eigenvalue"}


def test_settling_time_definition():
    theta = np.array([2.0, 1.0])
    est = np.array([[1.0, 1.0], [1.95, 1.0], [2.05, 1.0], [2.01, 1.01], [1.99, 0.995]])
    assert settling_time(est, theta) == pytest.approx(3 * 0.01)  # last violation at index 2
    assert settling_time(est[:3], theta) == float("inf")
    assert settling_time(est[3:], theta) == 0.0


@pytest.mark.slow
def test_quick_study_writes_summary(tmp_path):
    from jaxest.cli import main

    assert main(["reproduce", "adaptive", "--quick", "--out", str(tmp_path)]) == 0
    out = tmp_path / "adaptive"
    summary = json.loads((out / "summary.json").read_text())
    for name, p in (("charlie", 1), ("b747", 2)):
        for group in (summary[name], summary[name]["noisy"]):
            for label in ("hand", "tuned"):
                record = group[label]
                assert KEYS <= set(record)
                assert len(record["theta_final"]) == p and len(record["theta_true"]) == p
                assert np.all(np.isfinite(record["theta_final"]))
                assert record["pe_min_eigenvalue"] > 0
        assert (out / f"{name}_errors.png").stat().st_size > 0
        assert (out / f"{name}_states_tuned.png").stat().st_size > 0
    assert (out / "summary.md").read_text().startswith("# Zhang adaptive observer")
