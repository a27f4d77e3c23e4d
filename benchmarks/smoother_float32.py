"""The RTS smoother in float32, covariance form against square-root form, on random systems whose
noise is far below the prior's spread; prints JSON (docs/robustness.md, "The RTS smoother in
float32").

Each system: F a random rotation times ``--decay``, H random (m x n), Q and R random SPD scaled
to ``--q`` and ``--r``, P0 = ``--p0`` I, T steps simulated in float64 and rounded to float32.
The reference is a NumPy Kalman filter and RTS smoother in float64 on the same rounded numbers.
Each smoother (sequential and parallel, covariance and square-root form) runs after
``SquareRootKF`` and the square-root ``ParallelKalmanFilter`` in float32 (their Cholesky factors
saved) and after ``KalmanFilter`` (the square-root smoother from the Cholesky factors of its
covariances); per run: the largest error of the smoothed means in the
reference's smoothed standard deviations, the largest relative error of the smoothed variances,
whether every P(k|T) is finite and whether some is indefinite, and the status flags. The summary
counts the systems with a mean over one standard deviation off or a variance off by 100 % or more
(or not finite), and those of them whose status is OK.

    python benchmarks/smoother_float32.py [--systems 40] [--states 4] [--sensors 2] [--json out.json]
"""

from __future__ import annotations

import argparse

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxest as je  # noqa: E402
from jaxest.report import emit_json  # noqa: E402

#: (filter, whether its result keeps its Cholesky factors, which the square-root smoother reads)
RUNS = {
    "SquareRootKF": (je.SquareRootKF, True),
    "ParallelKalmanFilter": (je.ParallelKalmanFilter, True),
    "KalmanFilter": (je.KalmanFilter, False),
}
#: the smoothers: rts_smooth's (parallel, square_root)
FORMS = {
    "covariance": (False, False),
    "square_root": (False, True),
    "parallel covariance": (True, False),
    "parallel square_root": (True, True),
}


def random_system(rng, n, m, decay, q, r):
    """F = decay x a random rotation, H random, Q and R random SPD with unit mean variance times
    ``q`` and ``r``."""
    F = decay * np.linalg.qr(rng.normal(size=(n, n)))[0]
    spd = lambda k: (lambda A: A @ A.T / k + 0.1 * np.eye(k))(rng.normal(size=(k, k)))
    return F, rng.normal(size=(m, n)), q * spd(n), r * spd(m)


def numpy_smoother(F, H, Q, R, m0, P0, ys):
    """Smoothed means and covariances of the textbook Kalman filter and RTS smoother, float64."""
    x, P, filtered, predicted = m0, P0, [], []
    for y in ys:
        predicted.append((x, P))
        K = np.linalg.solve(H @ P @ H.T + R, H @ P).T
        IKH = np.eye(len(x)) - K @ H
        x, P = x + K @ (y - H @ x), IKH @ P @ IKH.T + K @ R @ K.T
        filtered.append((x, P))
        x, P = F @ x, F @ P @ F.T + Q
    means, covs = [filtered[-1][0]], [filtered[-1][1]]
    for k in range(len(ys) - 2, -1, -1):
        (x, P), (x_pred, P_pred) = filtered[k], predicted[k + 1]
        C = np.linalg.solve(P_pred, F @ P).T
        means.insert(0, x + C @ (means[0] - x_pred))
        covs.insert(0, P + C @ (covs[0] - P_pred) @ C.T)
    return np.array(means), np.array(covs)


def errors(smoothed: je.SmootherResult, means, covs, flags) -> dict:
    """The run's errors against the reference ``means`` and ``covs``; its status named by the
    filter's ``flags`` (the smoother's status holds the filter's bits)."""
    sd = np.sqrt(np.diagonal(covs, axis1=1, axis2=2))
    cov = np.asarray(smoothed.cov, np.float64)
    variances = np.diagonal(cov, axis1=1, axis2=2)
    return {
        "mean_err_sd": float(np.max(np.abs(np.asarray(smoothed.mean, np.float64) - means) / sd)),
        "var_rel_err": float(np.max(np.abs(variances / sd**2 - 1))),
        "finite": bool(np.all(np.isfinite(cov))),
        "indefinite": bool(np.all(np.isfinite(cov)) and np.any(np.linalg.eigvalsh(cov)[:, 0] <= 0)),
        "status": flags.describe(jnp.bitwise_or.reduce(smoothed.status)),
    }


def one_system(seed: int, args) -> dict:
    rng = np.random.default_rng(seed)
    F, H, Q, R = random_system(rng, args.states, args.sensors, args.decay, args.q, args.r)
    model = je.LinearGaussian(*map(jnp.asarray, (F, H, Q, R)))
    prior = je.Gaussian(jnp.zeros(args.states), args.p0 * jnp.eye(args.states))
    ys = je.simulate(model, prior, args.steps, jax.random.key(seed)).y
    model, prior, ys = je.astype((model, prior, ys), jnp.float32)
    rounded = [np.asarray(a, np.float64) for a in (model.F, model.H, model.Q, model.R)]
    means, covs = numpy_smoother(*rounded, np.zeros(args.states), args.p0 * np.eye(args.states),
                                 np.asarray(ys, np.float64))  # fmt: skip
    row = {"seed": seed}
    for name, (Filter, factors) in RUNS.items():
        save = je.SaveAt(fields=Filter.default_fields + (("factor",) if factors else ()))
        filtered = je.run(Filter(), model, ys, prior=prior, save=save)
        for form, (parallel, square_root) in FORMS.items():
            smoothed = je.rts_smooth(model, filtered, parallel=parallel, square_root=square_root)
            row[f"{name}, {form}"] = errors(smoothed, means, covs, filtered.flags)
    return row


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--systems", type=int, default=40)
    parser.add_argument("--states", type=int, default=4)
    parser.add_argument("--sensors", type=int, default=2)
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--decay", type=float, default=0.99)
    parser.add_argument("--q", type=float, default=1e-6, help="process noise scale")
    parser.add_argument("--r", type=float, default=3e-5, help="measurement noise scale")
    parser.add_argument("--p0", type=float, default=300.0, help="prior variance")
    parser.add_argument("--json", default=None, help="write the results here (default: stdout)")
    args = parser.parse_args(argv)
    rows = [one_system(seed, args) for seed in range(args.systems)]
    summary = {}
    for key in (k for k in rows[0] if k != "seed"):
        bad = [not r[key]["mean_err_sd"] <= 1 or not r[key]["var_rel_err"] < 1 for r in rows]
        summary[key] = {
            "systems_off": int(sum(bad)),
            "indefinite": int(sum(r[key]["indefinite"] for r in rows)),
            "flagged": int(sum(r[key]["status"] != "OK" for r in rows)),
            "off_and_unflagged": int(
                sum(b and r[key]["status"] == "OK" for b, r in zip(bad, rows, strict=True))
            ),
            "median_mean_err_sd": float(np.median([r[key]["mean_err_sd"] for r in rows])),
            "max_mean_err_sd": float(np.max([r[key]["mean_err_sd"] for r in rows])),
            "max_var_rel_err": float(np.max([r[key]["var_rel_err"] for r in rows])),
        }
    emit_json({"arguments": vars(args), "summary": summary, "rows": rows}, args.json)


if __name__ == "__main__":
    main()
