"""Speed of the svd-ekf study and of the 23-state augmented filters under vmap; prints JSON.

    python benchmarks/flight.py [--runs 100] [--rate 32] [--study quick|full|none] [--json PATH]

Per-step times are wall-clock seconds of one compiled, vmapped Monte Carlo batch divided by the
number of steps (and by the number of runs for the per-run figure), best of three after a warm-up
call; ``over_ekf`` is that time over the EKF's. ``lower_s`` and ``compile_s`` are tracing and
XLA compilation of the batch (the study's metrics included), timed apart from any run.
"""

from __future__ import annotations

import argparse
import platform
import tempfile
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402

from jaxest.report import best_of, device_name, emit_json  # noqa: E402
from jaxest.studies import svd_ekf  # noqa: E402
from jaxest.systems import flight_data, flight_sim as sim  # noqa: E402


def monte_carlo_arguments(runs: int, rate: int, dtype_name: str) -> tuple[dict, int]:
    """({filter: arguments of the svd-ekf study's Monte Carlo}, time steps): ``runs`` simulated
    elevator flights at ``rate`` Hz, all runs in one ``vmap`` (chunk = runs)."""
    dtype = jnp.dtype(dtype_name)
    truth = sim.true_flight("elevator", rate)
    batch = svd_ekf.simulated_batch(truth, runs, jax.random.key(0), dtype)
    model, P0 = svd_ekf.model_for(rate, dtype), svd_ekf.prior_cov(dtype)
    settle = int(svd_ekf.SETTLE_S * rate)
    arguments = {
        name: (est, model, batch, P0, settle, runs) for name, est in svd_ekf.FILTERS.items()
    }
    return arguments, truth.t.shape[0]


def per_step_times(runs: int, rate: int, dtype_name: str, repeats: int = 3) -> dict:
    arguments, T = monte_carlo_arguments(runs, rate, dtype_name)
    out = {}
    for name, args in arguments.items():
        start = time.perf_counter()
        lowered = svd_ekf._monte_carlo.lower(*args)
        lowered_at = time.perf_counter()
        compiled = lowered.compile()
        compiled_at = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        best = best_of(lambda: compiled(*args), repeats)[1]
        out[name] = {
            "lower_s": lowered_at - start,
            "compile_s": compiled_at - lowered_at,
            "batch_s": best,
            "step_s_batch": best / T,
            "step_s_per_run": best / (T * runs),
        }
    for name in out:
        out[name]["over_ekf"] = out[name]["step_s_per_run"] / out["ekf"]["step_s_per_run"]
    return out


def study_time(quick: bool) -> float:
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        svd_ekf.run(Path(tmp), runs=None, seed=0, quick=quick,
                    options={"data": flight_data.find_data_dir()})  # fmt: skip
        return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=100)
    parser.add_argument("--rate", type=int, default=32)
    parser.add_argument("--study", choices=["quick", "full", "none"], default="quick")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    result = {
        "machine": {
            "platform": platform.platform(),
            "device": device_name(),
            "jax": jax.__version__,
        },  # fmt: skip
        "state_dim": 23,
        "runs": args.runs,
        "rate_hz": args.rate,
        "per_step": {d: per_step_times(args.runs, args.rate, d) for d in ("float64", "float32")},
    }
    if args.study != "none":
        result[f"study_{args.study}_s"] = study_time(args.study == "quick")
    emit_json(result, args.json)


if __name__ == "__main__":
    main()
