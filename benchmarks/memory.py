"""A log-likelihood-only Monte Carlo study holds no per-step covariances (Core v2 acceptance).

10^4 runs x 10^4 steps of a 4-state / 2-measurement linear model through the Kalman filter with
``SaveAt(fields=())``: each run keeps only its total log-likelihood (carried in the filter
state), runs go through ``je.monte_carlo`` in chunks. Reports wall time, the process's peak
resident memory, and what the per-step covariances alone would have taken had they been kept
(runs * steps * n^2 * 8 bytes for one float64 covariance per step).

    python benchmarks/memory.py --json out.json [--runs 10000 --steps 10000 --chunk 500]
"""

from __future__ import annotations

import argparse
import resource
import time

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

from speed import linear_model  # noqa: E402 - the speed benchmark's 4x2 model

import jaxest as je  # noqa: E402
from jaxest.report import device_name, emit_json  # noqa: E402


def peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--json", help="write the results here as well as to stdout")
    parser.add_argument("--runs", type=int, default=10_000)
    parser.add_argument("--steps", type=int, default=10_000)
    parser.add_argument("--chunk", type=int, default=500)
    args = parser.parse_args(argv)
    model, prior = linear_model()
    save = je.SaveAt(fields=())

    def one_run(key):
        ys = je.simulate(model, prior, args.steps, key).y
        return je.run(je.KalmanFilter(), model, ys, prior=prior, save=save).loglik

    rss_before = peak_rss_mib()
    start = time.perf_counter()
    logliks = np.asarray(
        je.monte_carlo(one_run, jax.random.key(0), args.runs, chunk_size=args.chunk)
    )
    wall = time.perf_counter() - start
    n = 4
    emit_json(
        {
            "device": device_name(),
            "runs": args.runs,
            "steps": args.steps,
            "chunk": args.chunk,
            "wall_s": wall,
            "us_per_step_run": 1e6 * wall / (args.runs * args.steps),
            "peak_rss_mib": peak_rss_mib(),
            "peak_rss_before_mib": rss_before,
            "dense_covariances_would_need_mib": args.runs * args.steps * n * n * 8 / 2**20,
            "all_finite": bool(np.all(np.isfinite(logliks))),
            "mean_loglik_per_step": float(np.mean(logliks) / args.steps),
        },
        args.json,
    )


if __name__ == "__main__":
    main()
