"""Time and memory of the fixed-interval Wiener smoother against Kalman filter + RTS, N = 10^3..10^6.

The system is the example of the Wiener paper (2 states, 1 output), float64 on the default device.
For each N it reports the best of ``--repeats`` wall times (after a compile run) and XLA's
memory analysis of the compiled function (argument + output + temporary bytes), for

- ``wiener``: eq 10 from given initial values, with the end term (the paper's recursion);
- ``wiener_with_optimal_start``: the same plus the steady-state smoother pass that gives the
  optimal initial values and the final innovations;
- ``rts``: the Joseph-form Kalman filter followed by the RTS smoother (covariances every step).

    PYTHONPATH=. python benchmarks/wiener.py --json wiener_bench.json
"""

from __future__ import annotations

import argparse
import json
import platform

import jax
import jax.numpy as jnp

from jaxest import Gaussian, run
from jaxest.filters.kalman import KalmanFilter
from jaxest.report import best_of, device_name, emit_json
from jaxest.smoothers.rts import rts_smooth
from jaxest.smoothers.wiener import WienerSmoother
from jaxest.systems.wiener_example import ARBITRARY_START, paper_model


def measure(fn, *args, repeats):
    compiled = jax.jit(fn).lower(*args).compile()
    jax.block_until_ready(compiled(*args))
    seconds = best_of(lambda: compiled(*args), repeats)[1]
    memory = compiled.memory_analysis()
    total = None
    if memory is not None:
        total = (
            memory.argument_size_in_bytes + memory.output_size_in_bytes + memory.temp_size_in_bytes
        )
    return seconds, total


def main(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--sizes", type=int, nargs="+", default=[10**3, 10**4, 10**5, 10**6])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--json", default=None, help="also write the results to this file")
    args = parser.parse_args(argv)
    jax.config.update("jax_enable_x64", True)

    model = paper_model()
    smoother = WienerSmoother.from_model(model)
    prior = Gaussian(jnp.zeros(2), jnp.eye(2))
    x0 = jnp.asarray(ARBITRARY_START)

    def wiener(ys, final):
        return smoother.smooth(ys, x0, final)

    def wiener_with_optimal_start(ys):
        optimal, final = smoother.optimal_start(ys, prior.mean)
        return smoother.smooth(ys, optimal, final)

    def rts(ys):
        return rts_smooth(model, run(KalmanFilter(), model, ys, prior=prior)).mean

    rows = []
    for n in args.sizes:
        ys = jax.random.normal(jax.random.key(n), (n, 1))
        final = ys[-2:]
        row = {"N": n}
        for name, fn, fn_args in (
            ("wiener", wiener, (ys, final)),
            ("wiener_with_optimal_start", wiener_with_optimal_start, (ys,)),
            ("rts", rts, (ys,)),
        ):
            seconds, nbytes = measure(fn, *fn_args, repeats=args.repeats)
            row[name] = {
                "seconds": seconds,
                "ns_per_step": 1e9 * seconds / n,
                "bytes": nbytes,
                "bytes_per_step": None if nbytes is None else nbytes / n,
            }
        rows.append(row)
        print(json.dumps(row), flush=True)
    result = {
        "benchmark": "wiener smoother vs Kalman filter + RTS",
        "device": device_name(),
        "jax": jax.__version__,
        "machine": platform.machine(),
        "results": rows,
    }
    emit_json(result, args.json)


if __name__ == "__main__":
    main()
