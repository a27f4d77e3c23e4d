"""LAPACK for a single matrix against the unrolled kernels everywhere (issue 12), interleaved.

jaxest.linalg's ``cholesky`` and ``solve_triangular`` run LAPACK for one unbatched matrix of at
least ``LAPACK_ALONE_FROM`` rows and the unrolled kernels under ``vmap``; "unrolled" below swaps
the unrolled kernels back in everywhere (the behaviour before). The rows of benchmarks/speed.py
(jaxest only), both variants compiled in one process and timed alternately, best of 11, so that
the load of a shared machine falls on both alike. Prints one Markdown table row per line:
problem, mode, pass, µs/step unrolled, µs/step dispatched, compile s of each.

    python benchmarks/linalg_dispatch.py [linear_4x2 linear_6x3 duffing_ekf]
"""

from __future__ import annotations

import functools
import importlib.util
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp

jax.config.update("jax_enable_x64", True)

import jaxest as je  # noqa: E402
from jaxest import linalg  # noqa: E402

spec = importlib.util.spec_from_file_location("speed", Path(__file__).with_name("speed.py"))
speed = importlib.util.module_from_spec(spec)
spec.loader.exec_module(speed)

DISPATCHED = (linalg._small_cholesky, dict(linalg._small_solve))
UNROLLED = (
    linalg._cholesky_unrolled,
    {lower: functools.partial(linalg._solve_unrolled, lower=lower) for lower in (True, False)},
)
PROBLEMS = {
    "linear_4x2": speed.linear_problem,
    "linear_6x3": lambda: speed.linear_problem(6, 3),
    "duffing_ekf": speed.duffing_problem,
}


def use(kernels):
    linalg._small_cholesky, linalg._small_solve = kernels[0], dict(kernels[1])
    jax.clear_caches()


def main(names):
    for name in names or list(PROBLEMS):
        model, prior, ours, _ = PROBLEMS[name]()
        keys = jax.random.split(jax.random.PRNGKey(1), speed.RUNS)
        ys = jax.vmap(lambda k: je.simulate(model, prior, speed.T, k).y)(keys)
        scales = jnp.linspace(0.5, 2.0, speed.RUNS)
        for mode, wrap, args, per in speed.modes(ys, scales):
            for pass_name in ("forward", "value_and_grad"):
                compiled, compile_s, best = {}, {}, {}
                for tag, kernels in (("unrolled", UNROLLED), ("dispatched", DISPATCHED)):
                    use(kernels)
                    fn = speed.passes(ours)[pass_name]
                    start = time.perf_counter()
                    compiled[tag] = jax.jit(wrap(lambda *a, fn=fn: fn(*a))).lower(*args).compile()
                    compile_s[tag] = time.perf_counter() - start
                    jax.block_until_ready(compiled[tag](*args))
                    best[tag] = float("inf")
                for _ in range(11):
                    for tag, fn in compiled.items():
                        start = time.perf_counter()
                        jax.block_until_ready(fn(*args))
                        best[tag] = min(best[tag], time.perf_counter() - start)
                us = {tag: 1e6 * t / per for tag, t in best.items()}
                print(
                    f"| {name} | {mode} | {pass_name} | {us['unrolled']:.3g} | "
                    f"{us['dispatched']:.3g} | {compile_s['unrolled']:.1f} | "
                    f"{compile_s['dispatched']:.1f} |",
                    flush=True,
                )
        use(DISPATCHED)


if __name__ == "__main__":
    main(sys.argv[1:])
