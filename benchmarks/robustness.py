"""Ill-conditioned measurement update (Dyer-McReynolds / Grewal-Andrews, NOTES.md section 1).

P0 = I3, H = [[1, 1, 1], [1, 1, 1 + d]], R = d^2 I2, one update; relative error (Frobenius) of
P+ against the closed form, for every filter in float64 and float32 and d = 1e-1 ... 1e-16.

    python benchmarks/robustness.py --json out.json
"""

from __future__ import annotations

import argparse
import json

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

import jaxest as je  # noqa: E402
from jaxest.filters import EKF, SVDEKF, ImprovedSVDKF, InformationFilter, KalmanFilter, SquareRootKF  # noqa: E402

FILTERS = {
    "kf": KalmanFilter,
    "ekf": EKF,
    "information": InformationFilter,
    "sqrt_kf": SquareRootKF,
    "svd_ekf": SVDEKF,
    "svd_improved": ImprovedSVDKF,
}
DELTAS = [10.0**-e for e in range(1, 17)]


def exact_posterior(d: float) -> np.ndarray:
    """Closed form of P+ (NOTES.md section 1), evaluated in extended precision."""
    d = np.longdouble(d)
    a, b = 5 + 2 * d * (1 + d), -2 - d
    P = np.array([[a, -3, b], [-3, a, b], [b, b, 4 + d**2]], dtype=np.longdouble)
    return (P / (8 + 2 * d * (1 + d))).astype(np.float64)


def posterior(Filter, d: float, dtype) -> np.ndarray:
    H = jnp.asarray([[1.0, 1.0, 1.0], [1.0, 1.0, 1.0 + d]], dtype)
    model = je.LinearGaussian(jnp.eye(3, dtype=dtype), H, jnp.zeros((3, 3), dtype), jnp.asarray(d, dtype) ** 2 * jnp.eye(2, dtype=dtype))
    prior = je.Gaussian(jnp.zeros(3, dtype), jnp.eye(3, dtype=dtype))
    return np.asarray(je.run(Filter(), model, jnp.zeros((1, 2), dtype), None, prior).cov[0], np.float64)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--json", help="write the results here as well as to stdout")
    args = parser.parse_args(argv)
    results = []
    for name, Filter in FILTERS.items():
        for dtype in (jnp.float64, jnp.float32):
            for d in DELTAS:
                exact = exact_posterior(d)
                err = np.linalg.norm(posterior(Filter, d, dtype) - exact) / np.linalg.norm(exact)
                results.append(
                    {"filter": name, "dtype": jnp.dtype(dtype).name, "delta": d, "rel_error": float(err) if np.isfinite(err) else None}
                )
    text = json.dumps({"results": results}, indent=1)
    if args.json:
        with open(args.json, "w") as fh:
            fh.write(text)
    print(text)
    return results


if __name__ == "__main__":
    main()
