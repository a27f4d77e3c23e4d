"""Sequential against parallel-in-time Kalman filter + RTS smoother (issue 14): the crossover.

For n = 4 and n = 20 states (m = 2 measurements, random stable model), T = 10^2 .. 10^5,
float64 and float32: compile time, wall time per run (best of 3 after compiling, of 1 at T = 10^5)
and the relative log-likelihood difference from the float64 sequential filter, for the sequential
filter and smoother, and the parallel ones in square-root and standard form: the speed grid of
``python -m jaxest reproduce parallel`` (:func:`jaxest.studies.parallel.speed_grid`), without its
EM part. The JSON names the device, so a run on a GPU is
recorded beside the CPU one.

    python benchmarks/parallel.py --json parallel.json           # the whole grid
    python benchmarks/parallel.py --quick --json parallel.json   # n = 4, T <= 10^3
"""

from __future__ import annotations

import argparse

import jax

jax.config.update("jax_enable_x64", True)

from jaxest.progress import Progress  # noqa: E402
from jaxest.report import device_name, emit_json  # noqa: E402
from jaxest.studies.parallel import GRID, QUICK_GRID, grid_points, speed_grid  # noqa: E402


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", default=None, help="write the results here (default: stdout)")
    parser.add_argument("--quick", action="store_true", help="n = 4 and T <= 10^3 only")
    parser.add_argument("--max-T", type=int, default=100_000, help="largest T (default 10^5)")
    args = parser.parse_args(argv)
    grid = dict(QUICK_GRID if args.quick else GRID)
    grid["lengths"] = [T for T in grid["lengths"] if T <= args.max_T]
    with Progress("parallel", total=grid_points(grid)) as progress:
        rows = speed_grid(**grid, progress=progress)
    for r in rows:
        print(f"n={r['n']} T={r['T']} {r['dtype']} {r['method']}: compile {r['compile_s']:.1f} s, "
              f"run {1e3 * r['run_s']:.2f} ms, rel loglik diff {r['loglik_rel_diff']}")  # fmt: skip
    emit_json({"device": device_name(), "rows": rows}, args.json)


if __name__ == "__main__":
    main()
