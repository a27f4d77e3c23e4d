"""A diffuse prior: every Gaussian filter's error against a float64 NumPy Kalman filter
(docs/robustness.md, "A diffuse prior in float32").

A random linear system with more sensors than states (correlated R), the prior P0 = s I for
s = 1e2, 1e4, 1e6, each filter in float32 and float64 on the same float32-rounded data. Per
filter, dtype and s: the largest error of the filtered means in the reference's standard
deviations at the first update, over the whole run and at the last step, and the first
step's status flags.

    python benchmarks/diffuse_prior.py [--states 3] [--sensors 5] [--seed 0] [--json out.json]
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import numpy as np

import jaxest as je
from jaxest.report import emit_json

FILTERS = {
    "KalmanFilter": je.KalmanFilter(),
    "SquareRootKF": je.SquareRootKF(),
    "EKF": je.EKF(),
    "InformationFilter": je.InformationFilter(),
    "SVDEKF": je.SVDEKF(),
    "ImprovedSVDKF": je.ImprovedSVDKF(),
    "UKF": je.UKF(),
    "UKF svd": je.UKF(form="svd"),
}
SCALES = (1e2, 1e4, 1e6)


def random_system(rng, n, m):
    """Stable F, full H, SPD Q and a correlated SPD R."""
    F = 0.95 * np.linalg.qr(rng.normal(size=(n, n)))[0]
    H = rng.normal(size=(m, n))
    A, B = rng.normal(size=(n, n)), rng.normal(size=(m, m))
    return F, H, A @ A.T / n + 0.1 * np.eye(n), B @ B.T / m + 0.1 * np.eye(m)


def numpy_filtered_means(F, H, Q, R, m0, P0, ys):
    """Filtered means and standard deviations of the textbook Kalman filter, in float64."""
    x, P, means, sds = m0.copy(), P0.copy(), [], []
    for y in ys:
        S = H @ P @ H.T + R
        K = np.linalg.solve(S, H @ P).T
        x = x + K @ (y - H @ x)
        IKH = np.eye(len(x)) - K @ H
        P = IKH @ P @ IKH.T + K @ R @ K.T
        means.append(x.copy())
        sds.append(np.sqrt(np.diag(P)))
        x, P = F @ x, F @ P @ F.T + Q
    return np.array(means), np.array(sds)


def main(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--states", type=int, default=3)
    parser.add_argument("--sensors", type=int, default=5)
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", help="write the results here as well as to stdout")
    args = parser.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    rng = np.random.default_rng(args.seed)
    n, m = args.states, args.sensors
    system = [np.float32(a).astype(np.float64) for a in random_system(rng, n, m)]
    F, H, Q, R = system
    m0 = np.float32(rng.normal(size=n)).astype(np.float64)
    rows = []
    for scale in SCALES:
        P0 = scale * np.eye(n)
        x, ys = rng.multivariate_normal(m0, P0), []
        for _ in range(args.steps):
            ys.append(H @ x + rng.multivariate_normal(np.zeros(m), R))
            x = F @ x + rng.multivariate_normal(np.zeros(n), Q)
        ys = np.float32(ys).astype(np.float64)
        reference, sd = numpy_filtered_means(F, H, Q, R, m0, P0, ys)
        for dtype in (jnp.float32, jnp.float64):
            cast = lambda a, dtype=dtype: jnp.asarray(a, dtype)
            model = je.LinearGaussian(*map(cast, system))
            prior = je.Gaussian(cast(m0), cast(P0))
            for name, estimator in FILTERS.items():
                result = je.run(estimator, model, cast(ys), prior=prior)
                error = np.max(np.abs(np.asarray(result.mean, np.float64) - reference) / sd, 1)
                rows.append(
                    {
                        "filter": name,
                        "dtype": jnp.dtype(dtype).name,
                        "prior_scale": scale,
                        "first_update_error_sd": float(error[0]),
                        "max_error_sd": float(np.max(error)),
                        "last_error_sd": float(error[-1]),
                        "first_status": type(result).flags.describe(int(result.status[0])),
                    }
                )
    emit_json({"R_eigenvalues": np.linalg.eigvalsh(R).tolist(), "rows": rows}, args.json)


if __name__ == "__main__":
    main()
