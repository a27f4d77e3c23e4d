"""The 'network' study in quick mode: summary keys and the facts it must show."""

import json

import numpy as np
import pytest
import scipy.linalg

from jaxest.cli import main
from jaxest.systems.chain import mass_chain


@pytest.mark.slow
def test_network_study_quick(tmp_path):
    assert main(["reproduce", "network", "--quick", "--out", str(tmp_path)]) == 0
    summary = json.loads((tmp_path / "network" / "summary.json").read_text())
    # the centralized Kalman-Bucy cost, recomputed with scipy's CARE
    A, H, W, R = (np.asarray(x) for x in mass_chain(summary["setup"]["N"]).centralized())
    J_kb = np.trace(scipy.linalg.solve_continuous_are(A.T, H.T, W, R))
    assert summary["centralized"]["J"] == pytest.approx(J_kb, rel=1e-8)
    structures = summary["structures"]
    assert {"none", "chain", "full"} <= set(structures)
    for name, r in structures.items():
        assert r["J_designed"] >= summary["centralized"]["J"], name  # Kalman-Bucy is a lower bound
        assert abs(r["J_empirical"] - r["J_designed"]) < 4 * r["J_empirical_se"], name
        assert r["step4_gradient_relative"] < 1e-8, name
        assert abs(r["discretisation_bias"]) < 0.5 * r["J_empirical_se"], name
    assert structures["none"]["links"] == 0
    assert structures["full"]["J_designed"] < structures["none"]["J_designed"]
    assert [row["N"] for row in summary["scaling"]] == sorted(
        row["N"] for row in summary["scaling"]
    )
    for row in summary["scaling"]:
        assert row["design_seconds"] > 0 and row["run_seconds"] > 0
    for name in ("cost_vs_links.png", "cost_transient.png", "scaling.png", "results.md"):
        assert (tmp_path / "network" / name).exists()
