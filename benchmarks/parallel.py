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
    python benchmarks/parallel.py --lengths 100000 --states 20   # one corner of it

``--chunks`` overrides :data:`jaxest.scan.CHUNKS` (the lane width T / C of the parallel scans;
``benchmarks/scan_lanes.py`` measures which is fastest).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jaxest.scan  # noqa: E402
from jaxest.progress import Progress  # noqa: E402
from jaxest.report import device_name, emit_json, write_json  # noqa: E402
from jaxest.studies.parallel import GRID, QUICK_GRID, grid_weights, speed_rows  # noqa: E402


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", default=None, help="write the results here (default: stdout)")
    parser.add_argument("--quick", action="store_true", help="n = 4 and T <= 10^3 only")
    parser.add_argument("--states", type=int, nargs="+", help="state dimensions (default: grid's)")
    parser.add_argument("--lengths", type=int, nargs="+", help="values of T (default: grid's)")
    parser.add_argument("--dtypes", nargs="+", help="dtypes (default: float64 float32)")
    parser.add_argument("--chunks", type=int, help="T / C of the parallel scans")
    args = parser.parse_args(argv)
    grid = dict(QUICK_GRID if args.quick else GRID)
    for key in ("states", "lengths", "dtypes"):
        grid[key] = getattr(args, key) or grid[key]
    if args.chunks:
        jaxest.scan.CHUNKS = args.chunks
    rows = []

    def report():
        return {"device": device_name(), "chunks": jaxest.scan.CHUNKS, "rows": rows}

    weights = grid_weights(grid)
    with Progress("parallel", weights=weights) as progress:
        for label, new in speed_rows(**grid):
            rows += new
            progress.advance(label)
            if args.json:  # a run cut short keeps what it measured
                write_json(Path(args.json), report())
    for r in rows:
        print(f"n={r['n']} T={r['T']} {r['dtype']} {r['method']}: compile {r['compile_s']:.1f} s, "
              f"run {1e3 * r['run_s']:.2f} ms, rel loglik diff {r['loglik_rel_diff']}")  # fmt: skip
    emit_json(report(), args.json)


if __name__ == "__main__":
    main()
