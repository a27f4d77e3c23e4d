"""Where one row of benchmarks/speed.py spends its time: XLA's operations per step, from a profile.

Runs jaxest's compiled function of the row (speed.py's problem, data, mode and pass) once under
``jax.profiler`` and sums the trace's events by operation name. On the CPU each event is one
thunk: a fusion, a copy, a library call. ``per_step`` is an operation run once per time step, or
once per step of the reverse pass. The profiler itself slows the run (benchmarks/_xla_trace.py),
so read the shares, not the absolute times; speed.py gives those.

    python benchmarks/profile_step.py linear_6x3 vmap200 forward [--top 12] [--json out.json]
"""

from __future__ import annotations

import argparse

import _xla_trace as xla_trace  # sets XLA_FLAGS, so before anything is computed
import jax
from speed import PROBLEMS, RUNS, T, jaxest_case, modes, passes

from jaxest.report import emit_json


def profile(problem: str, mode: str, pass_name: str, runs: int, steps: int, top: int) -> dict:
    fn, ys, scales = jaxest_case(problem, runs, steps)
    batching = next(m for m in modes(ys, scales) if m.name == mode)
    args = batching.args
    compiled = (
        jax.jit(batching.wrap(passes(fn)[pass_name]))
        .lower(*args)
        .compile(batching.compiler_options)
    )
    jax.block_until_ready(compiled(*args))  # warm up
    total, calls, _ = xla_trace.traced_operations(lambda: compiled(*args), compiled.as_text())
    time_steps = ys.shape[1]
    per_step = [name for name in calls if calls[name] >= time_steps]
    all_us = sum(total.values())
    return {
        "problem": problem,
        "mode": mode,
        "pass": pass_name,
        "time_steps": time_steps,
        "operations_per_step": sum(calls[name] for name in per_step) / time_steps,
        "per_step_share": sum(total[name] for name in per_step) / all_us,
        "top": [
            {"operation": name, "calls": calls[name], "share": us / all_us}
            for name, us in total.most_common(top)
        ],
    }


def main(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("problem", choices=list(PROBLEMS))
    parser.add_argument("mode", choices=["single", "vmap200", "minor200"])
    parser.add_argument("pass_name", metavar="pass", choices=["forward", "value_and_grad"])
    parser.add_argument("--top", type=int, default=12, help="operations listed (default 12)")
    parser.add_argument("--steps", type=int, default=T, help="time steps per run (default 1000)")
    parser.add_argument("--runs", type=int, default=RUNS, help="runs under vmap (default 200)")
    parser.add_argument("--json", help="write the result here as well as to stdout")
    args = parser.parse_args(argv)
    result = profile(args.problem, args.mode, args.pass_name, args.runs, args.steps, args.top)
    emit_json(result, args.json)


if __name__ == "__main__":
    main()
