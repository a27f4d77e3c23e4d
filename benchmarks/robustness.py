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

from jaxest.filters import EKF, SVDEKF, ImprovedSVDKF, InformationFilter, KalmanFilter, SquareRootKF  # noqa: E402
from jaxest.systems.ill_conditioned import posterior_error  # noqa: E402

FILTERS = {
    "kf": KalmanFilter,
    "ekf": EKF,
    "information": InformationFilter,
    "sqrt_kf": SquareRootKF,
    "svd_ekf": SVDEKF,
    "svd_improved": ImprovedSVDKF,
}
DELTAS = [10.0**-e for e in range(1, 17)]


def main(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--json", help="write the results here as well as to stdout")
    args = parser.parse_args(argv)
    results = []
    for name, Filter in FILTERS.items():
        for dtype in (jnp.float64, jnp.float32):
            for d in DELTAS:
                err = posterior_error(Filter, d, dtype)
                results.append(
                    {
                        "filter": name,
                        "dtype": jnp.dtype(dtype).name,
                        "delta": d,
                        "rel_error": float(err) if np.isfinite(err) else None,
                    }
                )
    text = json.dumps({"results": results}, indent=1)
    if args.json:
        with open(args.json, "w") as fh:
            fh.write(text)
    print(text)
    return results


if __name__ == "__main__":
    main()
