"""Where the first call of each benchmarks/speed.py row goes: tracing, lowering, compiling.

speed.py's ``jaxest_compile_s`` is the whole ahead-of-time compile of a row's program
(``jax.jit(fn).lower(*args).compile()``). This script splits it, for jaxest's function of every
row (the same problems, data, modes and passes), into

- ``trace_s``: Python running the function on tracers (``jax.jit(fn).trace``), custom
  derivative rules and ``vmap`` included;
- ``lower_s``: the jaxpr lowered to StableHLO;
- ``compile_s``: XLA compiling it, with the row's compiler options;

with JAX's in-memory caches cleared before each, the best of ``--repeats``, and the size of the
traced program: ``equations``, counting those inside ``scan``, ``cond``, ``jit`` and custom
derivative rules. XLA's share depends on ``XLA_FLAGS`` (recorded in the JSON;
:mod:`jaxest.xla_flags`), so run it with and without
``XLA_FLAGS=--xla_cpu_use_fusion_emitters=false``.

    python benchmarks/compile_phases.py [--problems linear_4x2 ...] [--json out.json]
"""

from __future__ import annotations

import argparse
import time

import jax
from speed import PROBLEMS, jaxest_case, modes, passes

from jaxest._jaxpr import inner_jaxprs
from jaxest.report import device_name, emit_json


def equations(jaxpr) -> int:
    """Equations of ``jaxpr`` and of every jaxpr in their parameters, recursively."""
    return sum(1 + sum(map(equations, inner_jaxprs(eqn))) for eqn in jaxpr.eqns)


def phases(fn, args, compiler_options, repeats: int) -> dict:
    """Seconds of tracing, lowering and compiling ``jax.jit(fn)(*args)`` from cold caches (the
    repeat with the smallest total), and the traced program's equation count."""
    best = None
    for _ in range(repeats):
        jax.clear_caches()
        start = time.perf_counter()
        traced = jax.jit(fn).trace(*args)
        traced_at = time.perf_counter()
        lowered = traced.lower()
        lowered_at = time.perf_counter()
        lowered.compile(compiler_options)
        seconds = (traced_at - start, lowered_at - traced_at, time.perf_counter() - lowered_at)
        if best is None or sum(seconds) < sum(best):
            best = seconds
    return {
        "trace_s": best[0], "lower_s": best[1], "compile_s": best[2],
        "equations": equations(traced.jaxpr.jaxpr),
    }  # fmt: skip


def main(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--json", help="write the results here as well as to stdout")
    parser.add_argument(
        "--problems", nargs="+", choices=list(PROBLEMS), default=list(PROBLEMS),
        help="which of speed.py's problems (default: all)",
    )  # fmt: skip
    parser.add_argument("--repeats", type=int, default=2, help="cold compiles per row (best)")
    args = parser.parse_args(argv)
    rows = []
    for problem in args.problems:
        ours, ys, scales = jaxest_case(problem)
        for mode in modes(ys, scales):
            for pass_name, fn in passes(ours).items():
                row = {"problem": problem, "mode": mode.name, "pass": pass_name}
                rows.append(
                    row | phases(mode.wrap(fn), mode.args, mode.compiler_options, args.repeats)
                )
    emit_json({"device": device_name(), "rows": rows}, args.json)


if __name__ == "__main__":
    main()
