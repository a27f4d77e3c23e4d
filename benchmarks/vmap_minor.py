"""Every Gaussian filter under ``jax.vmap`` and under ``je.vmap_minor`` (the runs on the minor axis).

On speed.py's ``linear_6x3`` problem and data (200 runs, each with its own Q scale, T = 1000):
the forward pass (log-likelihood and filtered means), compiled once per filter and batching, then
``--rounds`` rounds alternating the two, each the best of 3. Prints per filter the µs per step
and run of each batching (best of the rounds), their compile seconds, the primitives that fall
back to ``jax.vmap`` under ``vmap_minor`` (``je.vmap_minor_fallbacks``) and whether the two agree
(log-likelihoods to 1e-9 relative).

    python benchmarks/vmap_minor.py [--rounds 2] [--json out.json]
"""

from __future__ import annotations

import argparse

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
from speed import RUNS, T, gaussian_data, linear_model, modes, scaled_q_run  # noqa: E402

import jaxest as je  # noqa: E402
from jaxest.report import device_name, emit_json  # noqa: E402

FILTERS = [je.KalmanFilter, je.EKF, je.InformationFilter, je.SquareRootKF, je.SVDEKF, je.UKF]


def measure(rounds: int) -> list[dict]:
    model, prior = linear_model(6, 3)
    ys, scales = gaussian_data(model, prior, RUNS, T)
    by_name = {mode.name: mode for mode in modes(ys, scales)}  # speed.py's batched modes
    batchings = {"vmap": by_name["vmap200"], "vmap_minor": by_name["minor200"]}
    rows = []
    for filter_type in FILTERS:
        run = scaled_q_run(filter_type(), model, prior, save=je.SaveAt(fields=("mean",)))
        times = {name: [] for name in batchings}
        compile_s, outputs = {}, {}
        for _ in range(rounds):
            for name, mode in batchings.items():
                compiling, seconds, outputs[name] = mode.timed(run, repeats=3)
                compile_s.setdefault(name, compiling)
                times[name].append(seconds / (RUNS * T) * 1e6)
        a, b = outputs["vmap"][0], outputs["vmap_minor"][0]
        rows.append(
            {
                "filter": filter_type.__name__,
                "vmap_us_per_step": min(times["vmap"]),
                "vmap_minor_us_per_step": min(times["vmap_minor"]),
                "minor_over_vmap": min(times["vmap_minor"]) / min(times["vmap"]),
                "compile_s": compile_s,
                "fallbacks": je.vmap_minor_fallbacks(run, scales, ys),
                "agree": bool(jnp.allclose(a, b, rtol=1e-9)),
            }
        )
        print(rows[-1], flush=True)
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--rounds", type=int, default=2, help="alternating rounds (default 2)")
    parser.add_argument("--json", help="write the results here as well as to stdout")
    args = parser.parse_args(argv)
    rows = measure(args.rounds)
    emit_json({"device": device_name(), "runs": RUNS, "steps": T, "rows": rows}, args.json)


if __name__ == "__main__":
    main()
