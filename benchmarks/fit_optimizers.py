"""The studies' L-BFGS fits with optax's L-BFGS against optimistix's, each in a fresh process.

    python benchmarks/fit_optimizers.py [--json out.json] [--fits filters sigma-point ...]

Prints, per fit and optimiser, ``{"fit", "optimizer", "wall_s", "compile_s", "reached"}``: the
wall time of the study's fitting function at its published size (simulation, fit and what the
study computes from the fit), the seconds XLA spent compiling in it, and the number the fit is
judged by: the final loss (``filters``: the ML fit's minus log-likelihood per step; ``sigma-point``:
its loss) or log-likelihood (``svd-ekf``, ``parallel``). Both optimisers take the same number of
steps; optimistix's ``LBFGS`` evaluates the loss once per step and holds one copy of its gradient
in the program, optax's ``lbfgs()`` three (docs/performance.md).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time

FITS = ("filters", "sigma-point", "svd-ekf", "parallel")
OPTIMIZERS = ("optax", "optimistix")


def one(fit: str, optimizer_name: str) -> dict:
    """Run one fit in this process (a fresh one: no program compiled before)."""
    import jax
    import optax

    from jaxest import xla_flags

    xla_flags.add(xla_flags.FASTER_COMPILATION)  # as the studies compile
    jax.config.update("jax_enable_x64", True)
    from jaxest.studies import filters, parallel, sigma_point, svd_ekf
    from jaxest.systems import flight_sim
    from jaxest.tune import FIXED_STEPS_LBFGS

    compile_s = []
    jax.monitoring.register_event_duration_secs_listener(
        lambda name, secs, **_: (
            compile_s.append(secs) if name == "/jax/core/compile/backend_compile_duration" else None
        )
    )
    optimizer = {"optax": optax.lbfgs(), "optimistix": FIXED_STEPS_LBFGS}[optimizer_name]
    start = time.perf_counter()
    if fit == "filters":  # as in the study: 20 runs of 400 steps, 60 fitting steps
        reached = filters.tuning(20, 400, 0, 60, optimizer=optimizer)["ml"]["loss_last"]
    elif fit == "sigma-point":
        reached = sigma_point.tune_duffing(20, 100, 7, 40, optimizer=optimizer)["loss_last"]
    elif fit == "svd-ekf":
        truth = flight_sim.true_flight("elevator", 32, flight_sim.DURATION)
        tuned = svd_ekf.tune_simulated(jax.random.key(0), truth, 40, optimizer=optimizer)
        reached = tuned["loglik_tuned"]
    else:
        reached = parallel.em_versus_gradient(1000, 500, 200, 0, optimizer)["gradient"]["loglik"]
    return {"fit": fit, "optimizer": optimizer_name, "wall_s": time.perf_counter() - start,
            "compile_s": sum(compile_s), "reached": float(reached)}  # fmt: skip


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", help="also write the rows here")
    parser.add_argument("--fits", nargs="+", choices=FITS, default=FITS)
    parser.add_argument("--one", nargs=2, metavar=("FIT", "OPTIMIZER"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.one:
        print(json.dumps(one(*args.one)))
        return
    from jaxest.report import device_name, emit_json

    rows = []
    for fit in args.fits:
        for name in OPTIMIZERS:
            done = subprocess.run([sys.executable, __file__, "--one", fit, name],
                                  capture_output=True, text=True, check=True)  # fmt: skip
            rows.append(json.loads(done.stdout.splitlines()[-1]))
            print(rows[-1], file=sys.stderr)
    emit_json({"device": device_name(), "rows": rows}, args.json)


if __name__ == "__main__":
    main()
