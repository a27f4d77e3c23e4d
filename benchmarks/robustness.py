"""Ill-conditioned measurement update (Dyer-McReynolds / Grewal-Andrews, docs/papers/svd_ekf.md).

P0 = I3, H = [[1, 1, 1], [1, 1, 1 + d]], R = d^2 I2, one update; relative error (Frobenius) of
P+ against the closed form, P+'s variance along the direction the two measurements pin down over
the exact one (``smallest_variance_ratio``) and the update's status, for every filter ("kf" =
conventional covariance KF, "svd_ekf" = the paper's SVD filter, ...) in float64 and float32 and
d = 1e-1 ... 1e-16 (null where not finite).

    python benchmarks/robustness.py --json out.json
"""

from __future__ import annotations

import argparse

import jax

from jaxest.report import emit_json
from jaxest.studies.filters import robustness


def main(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--json", help="write the results here as well as to stdout")
    args = parser.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    emit_json({"results": robustness()}, args.json)


if __name__ == "__main__":
    main()
