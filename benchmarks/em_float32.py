"""``fit_em`` in float32 on random systems whose noise is far below the prior's spread, each
E-step (sequential in covariance or square-root form, parallel) against a float64 fit; prints
JSON (docs/robustness.md, "EM in float32").

Each system: ``smoother_float32``'s random system (F a random rotation times ``--decay``, H
random, Q and R random SPD scaled to ``--q``), P0 = ``--p0`` I, T steps simulated in float64.
EM starts from the truth with F and H perturbed by 0.05 and Q, R three times too large, and
runs ``--iters`` iterations in float32 and, as the reference, in float64 (sequential, covariance
form). Per run: the float32 fit's status, and its parameters scored by the float64 Kalman filter
against the reference's score (nats; positive where the float32 fit is worse). The summary
counts the flagged runs and the unflagged ones more than ``--tolerance`` nats worse (a better
score is EM's path through the iterations, not an error: at 100 iterations a float32 fit may be
further along than float64's, which it later meets), and times
one fit of each E-step (the best of three, compiled beforehand) against the covariance form's.

    python benchmarks/em_float32.py [--systems 20] [--q 1e-4] [--json out.json]
"""

from __future__ import annotations

import argparse

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from smoother_float32 import random_system  # noqa: E402

import jaxest as je  # noqa: E402
from jaxest.report import emit_json, timed  # noqa: E402

#: fit_em's (parallel, square_root) for each E-step
E_STEPS = {
    "covariance": (False, False),
    "square_root": (False, True),
    "parallel": (True, False),
}


def problem(seed: int, args):
    """The data, the initial model and the prior of one system (module docstring)."""
    rng = np.random.default_rng(seed)
    F, H, Q, R = random_system(rng, args.states, args.sensors, args.decay, args.q, args.q)
    truth = je.LinearGaussian(*map(jnp.asarray, (F, H, Q, R)))
    prior = je.Gaussian(jnp.zeros(args.states), args.p0 * jnp.eye(args.states))
    ys = je.simulate(truth, prior, args.steps, jax.random.key(seed)).y
    perturb = lambda M: jnp.asarray(M + 0.05 * rng.normal(size=M.shape))
    init = je.LinearGaussian(perturb(F), perturb(H), 3 * truth.Q, 3 * truth.R)
    return ys, init, prior


def fitter(args, parallel, square_root):
    fit = lambda init, ys, prior: je.fit_em(init, ys, prior=prior, num_iters=args.iters,
                                            parallel=parallel, square_root=square_root)  # fmt: skip
    return jax.jit(fit)


def score(result, ys) -> float:
    """log p(y) of the fitted model and prior, by the float64 Kalman filter; NaN where they are
    not a model (not finite, or a covariance not positive definite: ``run`` refuses them)."""
    model, prior = je.astype((result.model, result.prior), jnp.float64)
    try:
        return float(je.run(je.KalmanFilter(), model, ys, prior=prior).loglik)
    except ValueError:
        return float("nan")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--systems", type=int, default=20)
    parser.add_argument("--states", type=int, default=4)
    parser.add_argument("--sensors", type=int, default=2)
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--iters", type=int, default=100)
    parser.add_argument("--decay", type=float, default=0.95)
    parser.add_argument("--q", type=float, default=1e-4, help="noise scale (Q and R)")
    parser.add_argument("--p0", type=float, default=100.0, help="prior variance")
    parser.add_argument("--tolerance", type=float, default=0.5, help="nats")
    parser.add_argument("--json", default=None, help="write the results here (default: stdout)")
    args = parser.parse_args(argv)
    reference = fitter(args, False, False)
    fits = {name: fitter(args, *options) for name, options in E_STEPS.items()}
    rows = []
    for seed in range(args.systems):
        ys, init, prior = problem(seed, args)
        ref = reference(init, ys, prior)
        row = {"seed": seed, "reference_status": je.EMStatus.describe(ref.any_status)}
        single = je.astype((init, ys, prior), jnp.float32)
        for name, fit in fits.items():
            result = fit(*single)
            row[name] = {
                "worse_by_nats": score(ref, ys) - score(result, ys),
                "status": je.EMStatus.describe(result.any_status),
            }
        rows.append(row)
    summary = {}
    ys, init, prior = problem(0, args)
    for dtype in (jnp.float32, jnp.float64):
        data = je.astype((init, ys, prior), dtype)
        seconds = {name: timed(fit, data, repeats=3)[1] for name, fit in fits.items()}
        for name in fits:
            entry = summary.setdefault(name, {})
            entry[f"time_ratio_{jnp.dtype(dtype).name}"] = seconds[name] / seconds["covariance"]
    for name in fits:
        runs = [r[name] for r in rows]
        unflagged = [r["worse_by_nats"] for r in runs if r["status"] == "OK"]
        summary[name] |= {
            "flagged": sum(r["status"] != "OK" for r in runs),
            "unflagged_worse": sum(not w <= args.tolerance for w in unflagged),
            "most_worse_by_nats_unflagged": float(np.max(unflagged)) if unflagged else None,
        }
    emit_json({"arguments": vars(args), "summary": summary, "rows": rows}, args.json)


if __name__ == "__main__":
    main()
