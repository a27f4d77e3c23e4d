"""benchmarks/parallel_accuracy.py (docs/parallel.md's accuracy tables) on a short record."""

import json

import jax
import jax.numpy as jnp
import numpy as np

import jaxest as je
from tests import benchmark_scripts

accuracy = benchmark_scripts.load("parallel_accuracy")


def test_rows_and_the_flag_agree_with_the_recomputed_discrepancy(tmp_path):
    """Where a parallel row's eq (5) or (5') discrepancy, recomputed from the prefixes, is well above
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
        largest = max(r["eq5_discrepancy"], r["eq5_run_discrepancy"])  # a step's, the run's
        if largest > 2 * tolerance or largest < tolerance / 2:
            assert flagged == (largest > tolerance), r
            seen.add(flagged)
        assert (r["flagged_steps"] > 0) == (r["status"] != "OK"), r
    assert seen == {True, False}  # both sides of the flag were checked
    # what the filters return unflagged is off by a small part of what they claim to know
    unflagged = [r for r in rows if r["status"] == "OK"]
    assert unflagged and all(r["mean_err_sd"] < 0.1 for r in unflagged), unflagged
    float64 = [r for r in rows if r["dtype"] == "float64" and r["filter"] == "parallel_sqrt"]
    assert all(r["loglik_rel_err"] < 1e-12 and r["flagged_steps"] == 0 for r in float64)


def test_a_drift_spread_over_the_steps_is_flagged_on_the_last():
    """Float32 standard form, 6 states, 3 measurements (R from 10^-2 to 1), T = 500, 5 % of the
    entries missing: the combined log-likelihood drifts 3.6 nats (1.3e-3 relative), each step's
    discrepancy within its tolerance (0.015 nats a step in the audit's like system), and was
    reported with status OK. Eq (5') over the run flags the last step, and the total reported
    since, the sum of the sequential update's terms (eq (6)), is within 0.05 nats; the
    square-root form on the same data agrees with float64 and is not flagged. The sequential path
    (``parallel=False``) reports the same sum."""
    rng = np.random.default_rng(3)
    n, m, T = 6, 3, 500
    U, V = (np.linalg.qr(rng.normal(size=(n, n)))[0] for _ in range(2))
    F = U @ np.diag(rng.uniform(0.85, 1.0, n) * rng.choice([-1, 1], n)) @ U.T
    F = F + 0.2 * np.triu(rng.normal(size=(n, n)), 1)
    F = F * min(1.0, 0.999 / max(abs(np.linalg.eigvals(F))))
    Q = V @ np.diag(np.logspace(-4, 0, n)[rng.permutation(n)]) @ V.T
    H, R = rng.normal(size=(m, n)), np.diag(np.logspace(-2, 0, m))
    model = je.LinearGaussian(*map(jnp.asarray, (F, H, Q, R)))
    prior = je.Gaussian(jnp.asarray(rng.normal(size=n)), 3.0 * jnp.eye(n))
    ys = np.array(je.simulate(model, prior, T, jax.random.key(3)).y)
    ys[rng.random(ys.shape) < 0.05] = np.nan
    reference = float(je.run(je.KalmanFilter(), model, jnp.asarray(ys), prior=prior).loglik)
    single = lambda tree: jax.tree.map(lambda a: jnp.asarray(a, jnp.float32), tree)
    for square_root in (False, True):
        result = je.run(je.ParallelKalmanFilter(square_root=square_root), single(model),
                        single(ys), prior=single(prior))  # fmt: skip
        nats = abs(float(result.loglik) - reference)
        flagged = np.asarray(result.status) & je.ParallelStatus.LOGLIK_INCONSISTENT != 0
        assert nats < 0.05
        assert flagged[-1] == (not square_root) and not flagged[:-1].any()
    # the sequential path carries the same total: the terms, not the combined log-likelihood
    result = je.run(je.ParallelKalmanFilter(square_root=False), single(model), single(ys),
                    prior=single(prior), parallel=False)  # fmt: skip
    assert abs(float(result.loglik) - reference) < 0.05
