"""Accuracy of the parallel Kalman filter as R shrinks: docs/parallel.md's two tables.

A random stable 4-state model (spectral radius 0.99) with 2 measurements, R = s x a random SPD
matrix, prior N(0, 10 I), T = 10^4 measurements simulated in float64. For each s and dtype, the
parallel filter in square-root and standard form against the float64 sequential
``KalmanFilter``:

- the total log-likelihood's relative error (the sum of the steps' terms, eq (6) of
  :mod:`jaxest.filters.parallel`) and the steps its status flags
  (``ParallelStatus.LOGLIK_INCONSISTENT``), and that of the combined log-likelihood of the last
  prefix (eq (3)'s c; what the filter reported as the total before eq (6));
- the largest discrepancy of eq (5) over the steps,
  |loglik(prefix) - loglik(previous) - term| / (|loglik(prefix)| + |loglik(previous)| + |term| + 1),
  which the flag compares with sqrt(eps), and its ratio to the combined log-likelihood's error;
  and that of eq (5') over the whole run, which the flag compares with sqrt(eps) too;
- the errors of the filtered means and covariances (relative to the largest entry of the float64
  array), and the means' largest error in posterior standard deviations (those of the float64
  filter, sqrt of its P(k|k)'s diagonal): whether an error is large for what the filter claims
  to know.

At ``--detail`` s (default 1e-4) the float32 sequential ``KalmanFilter`` and ``SquareRootKF``
are reported too.

    python benchmarks/parallel_accuracy.py --json parallel_accuracy.json
"""

from __future__ import annotations

import argparse

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxest as je  # noqa: E402
from jaxest._estimator import associative_prefixes  # noqa: E402
from jaxest.filters.parallel import loglik_discrepancy, run_loglik_discrepancy  # noqa: E402
from jaxest.report import emit_json  # noqa: E402

SCALES = (1e-1, 1e-2, 1e-3, 1e-4, 1e-5, 1e-6)
FIELDS = ("mean", "cov", "loglik", "status")


def problem(scale: float, T: int, seed: int = 2):
    """The model with R = ``scale`` x SPD, its prior and T measurements (float64)."""
    rng = np.random.default_rng(seed)
    n, m = 4, 2
    F = 0.99 * np.linalg.qr(rng.normal(size=(n, n)))[0]
    H = rng.normal(size=(m, n))
    A, B = rng.normal(size=(n, n)), rng.normal(size=(m, m))
    Q = A @ A.T / n + 0.1 * np.eye(n)
    R = scale * (B @ B.T / m + 0.2 * np.eye(m))
    model = je.LinearGaussian(*map(jnp.asarray, (F, H, Q, R)))
    prior = je.Gaussian(jnp.zeros(n), 10.0 * jnp.eye(n))
    return model, prior, je.simulate(model, prior, T, jax.random.PRNGKey(seed)).y


@jax.jit
def eq5_discrepancies(filt, model, prior, ys):
    """The largest relative discrepancy of eq (5) over the steps, that of eq (5') over the run,
    and the last prefix's combined log-likelihood: every prefix by the associative scan, each
    step's term from ``output`` (as ``je.run`` computes them)."""
    ks = jnp.arange(ys.shape[0])
    previous, prefixes = associative_prefixes(filt, model, prior, ks, ys, None)
    loglik = jax.vmap(lambda prefix: prefix.element.loglik)  # a property of one prefix
    term = jax.vmap(lambda p, q, k: filt.output(model, p, q, k))(previous, prefixes, ks).loglik
    discrepancy, scale = loglik_discrepancy(loglik(prefixes), loglik(previous), term)
    whole, whole_scale = run_loglik_discrepancy(loglik(previous)[0], loglik(prefixes)[-1], term)
    return jnp.max(discrepancy / scale), whole / whole_scale, loglik(prefixes)[-1]


def relative(a, b) -> float:
    """max |a - b| over the largest |b|."""
    a, b = np.asarray(a, np.float64), np.asarray(b)
    return float(np.max(np.abs(a - b)) / np.max(np.abs(b)))


def relative_loglik_error(loglik, reference) -> float:
    return abs(float(loglik) / float(reference.loglik) - 1)


def in_standard_deviations(mean, reference) -> float:
    """max over steps and states of |mean - reference.mean| / sqrt(diag reference.cov)."""
    sd = np.sqrt(np.diagonal(np.asarray(reference.cov), axis1=-2, axis2=-1))
    return float(np.max(np.abs(np.asarray(mean, np.float64) - np.asarray(reference.mean)) / sd))


def errors(result, reference) -> dict:
    return {
        "loglik": float(result.loglik),
        "loglik_rel_err": relative_loglik_error(result.loglik, reference),
        "mean_rel_err": relative(result.mean, reference.mean),
        "mean_err_sd": in_standard_deviations(result.mean, reference),
        "cov_rel_err": relative(result.cov, reference.cov),
        "flagged_steps": int(np.sum(np.asarray(result.status) != 0)),
        "status": je.ParallelStatus.describe(result.any_status),
    }


def rows_at(scale: float, T: int, detail: bool) -> list[dict]:
    model64, prior64, ys64 = problem(scale, T)
    save = je.SaveAt(fields=FIELDS)
    reference = je.run(je.KalmanFilter(), model64, ys64, prior=prior64, save=save)
    rows = []
    for dtype in ("float32", "float64"):
        model, prior, ys = je.astype((model64, prior64, ys64), dtype)
        filters = {"parallel_sqrt": je.ParallelKalmanFilter(),
                   "parallel_standard": je.ParallelKalmanFilter(square_root=False)}  # fmt: skip
        if detail and dtype == "float32":
            filters |= {"KalmanFilter": je.KalmanFilter(), "SquareRootKF": je.SquareRootKF()}
        for name, filt in filters.items():
            row = {"R_scale": scale, "dtype": dtype, "filter": name}
            row |= errors(je.run(filt, model, ys, prior=prior, save=save), reference)
            if isinstance(filt, je.ParallelKalmanFilter):
                step, whole, combined = eq5_discrepancies(filt, model, prior, ys)
                row["eq5_discrepancy"], row["eq5_run_discrepancy"] = float(step), float(whole)
                row["combined_loglik_rel_err"] = relative_loglik_error(combined, reference)
                row["discrepancy_over_error"] = (
                    row["eq5_discrepancy"] / row["combined_loglik_rel_err"]
                    if row["combined_loglik_rel_err"] else None
                )  # fmt: skip
            rows.append(row)
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", default=None, help="write the results here (default: stdout)")
    parser.add_argument("--scales", type=float, nargs="+", default=SCALES, help="values of s")
    parser.add_argument("--detail", type=float, default=1e-4, help="s of the sequential rows")
    parser.add_argument("--steps", type=int, default=10_000, help="T")
    args = parser.parse_args(argv)
    rows = []
    for scale in args.scales:
        rows += rows_at(scale, args.steps, detail=scale == args.detail)
    for r in rows:
        combined = r.get("combined_loglik_rel_err")
        print(f"R = {r['R_scale']:g} x SPD {r['dtype']} {r['filter']}: loglik rel err "
              f"{r['loglik_rel_err']:.1e}"
              + ("" if combined is None else f" (combined {combined:.1e})")
              + f", {r['flagged_steps']} steps flagged")  # fmt: skip
    emit_json({"T": args.steps, "rows": rows}, args.json)


if __name__ == "__main__":
    main()
