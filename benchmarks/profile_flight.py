"""Where the 23-state flight filters spend a step: each filter's share in library calls, from a
profile; prints JSON.

Profiles the svd-ekf study's Monte Carlo of each filter (benchmarks/flight.py's runs, rate and
data; one ``vmap``) once under ``jax.profiler`` and sums the trace's operations
(benchmarks/_xla_trace.py). ``library`` is the time in each kind of library kernel (LAPACK on the
CPU: ``lapack_dgesdd_ffi`` is an SVD), per step and run and as a share of the filter's operations.
``svd_over_ekf`` is the SVD filter's time in SVD kernels alone over the EKF's whole step: where
it reaches 2, the SVD filter cannot come within 2x of the EKF (issue 12's bar) with those
kernels, whatever the rest of its step costs. The profiler slows the run: read the shares and the
ratios; flight.py gives the times.

    python benchmarks/profile_flight.py [--runs 100] [--rate 32] [--dtype float64] [--json PATH]
"""

from __future__ import annotations

import argparse
import collections

import _xla_trace as xla_trace  # sets XLA_FLAGS, so before anything is computed
import jax

jax.config.update("jax_enable_x64", True)

from flight import monte_carlo_arguments  # noqa: E402

from jaxest.report import device_name, emit_json  # noqa: E402
from jaxest.studies import svd_ekf  # noqa: E402

#: XLA:CPU's library kernels (LAPACK through jaxlib), as :func:`_xla_trace.instructions` names them
LIBRARY = "lapack_"
#: LAPACK's SVDs (divide and conquer, QR iteration), in double and single precision
SVD_KERNELS = {f"lapack_{t}{kind}_ffi" for t in "ds" for kind in ("gesdd", "gesvd")}


def profile(runs: int, rate: int, dtype_name: str, top: int = 8) -> dict:
    arguments, T = monte_carlo_arguments(runs, rate, dtype_name)
    out = {}
    for name, args in arguments.items():
        compiled = svd_ekf._monte_carlo.lower(*args).compile()
        jax.block_until_ready(compiled(*args))  # warm up
        total, calls, runs_as = xla_trace.traced_operations(
            lambda: compiled(*args), compiled.compiled.as_text()
        )
        all_us = sum(total.values())
        by_kernel = collections.Counter()
        for operation, us in total.items():
            if runs_as[operation].startswith(LIBRARY):
                by_kernel[runs_as[operation]] += us
        out[name] = {
            "us_per_step_run": all_us / (T * runs),
            "library": {
                kernel: {"us_per_step_run": us / (T * runs), "share": us / all_us}
                for kernel, us in by_kernel.most_common()
            },
            "top": [
                {
                    "operation": op,
                    "runs_as": runs_as[op],
                    "calls": calls[op],
                    "share": us / all_us,
                }
                for op, us in total.most_common(top)
            ],
        }
    ekf_us = out["ekf"]["us_per_step_run"]
    for row in out.values():
        row["over_ekf"] = row["us_per_step_run"] / ekf_us
        svd_us = sum(
            k["us_per_step_run"] for kernel, k in row["library"].items() if kernel in SVD_KERNELS
        )
        row["svd_over_ekf"] = svd_us / ekf_us
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--runs", type=int, default=100, help="runs under vmap (default 100)")
    parser.add_argument("--rate", type=int, default=32, help="Hz (default 32)")
    parser.add_argument("--dtype", choices=["float64", "float32"], default="float64")
    parser.add_argument("--top", type=int, default=8, help="operations listed (default 8)")
    parser.add_argument("--json", help="write the result here as well as to stdout")
    args = parser.parse_args(argv)
    result = {
        "runs": args.runs,
        "rate_hz": args.rate,
        "dtype": args.dtype,
        "device": device_name(),
        "filters": profile(args.runs, args.rate, args.dtype, args.top),
    }
    emit_json(result, args.json)


if __name__ == "__main__":
    main()
