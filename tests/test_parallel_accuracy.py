"""benchmarks/parallel_accuracy.py (docs/parallel.md's accuracy tables) on a short record."""

import json

import jax.numpy as jnp
import numpy as np

from tests import benchmark_scripts

accuracy = benchmark_scripts.load("parallel_accuracy")


def test_rows_and_the_flag_agree_with_the_recomputed_discrepancy(tmp_path):
    """Where a parallel row's eq (5) discrepancy, recomputed from the prefixes, is well above
    sqrt(eps) the filter's status flagged a step, where well below it did not (near sqrt(eps)
    the two programs' rounding may differ); the sequential rows come at --detail."""
    out = tmp_path / "accuracy.json"
    accuracy.main(["--steps", "300", "--scales", "1e-1", "1e-4", "--json", str(out)])
    rows = json.loads(out.read_text())["rows"]
    assert {(r["R_scale"], r["dtype"], r["filter"]) for r in rows} == {
        (s, d, f) for s in (1e-1, 1e-4) for d in ("float32", "float64")
        for f in ("parallel_sqrt", "parallel_standard")
    } | {(1e-4, "float32", "KalmanFilter"), (1e-4, "float32", "SquareRootKF")}  # fmt: skip
    seen = set()
    for r in rows:
        if not r["filter"].startswith("parallel"):
            continue
        tolerance = float(np.sqrt(jnp.finfo(r["dtype"]).eps))
        flagged = "LOGLIK_INCONSISTENT" in r["status"]
        if r["eq5_discrepancy"] > 2 * tolerance or r["eq5_discrepancy"] < tolerance / 2:
            assert flagged == (r["eq5_discrepancy"] > tolerance), r
            seen.add(flagged)
        assert (r["flagged_steps"] > 0) == (r["status"] != "OK"), r
    assert seen == {True, False}  # both sides of the flag were checked
    float64 = [r for r in rows if r["dtype"] == "float64" and r["filter"] == "parallel_sqrt"]
    assert all(r["loglik_rel_err"] < 1e-12 and r["flagged_steps"] == 0 for r in float64)
