"""Sigma-point filters and the iterated EKF against dynamax's UKF, in one process (issue 13).

Problem: the pendulum x = [angle, rate], x_{k+1} = [x0 + dt x1, x1 - g dt sin x0] + w,
y = sin x0 + v (dynamax's UKF example), T = 1000. Filters: jaxest's UKF (alpha = 1, beta = 2,
kappa = 0; covariance, sqrt and svd forms; additive and augmented noise), CubatureKF,
GaussHermiteKF(order=3), IteratedEKF(iterations=3), the EKF (KalmanFilter) and dynamax's
``unscented_kalman_filter`` with the same alpha, beta, kappa. Modes: one sequence, and 200 runs
under ``vmap`` with a different Q scale per run. Pass: forward (log-likelihood and filtered means).
Per-step time = wall time / (runs * T), best of several repeats after compilation.

cuthbert (0.1.1) has no sigma-point filter (only quadrature linearisation primitives in
cuthbertlib), so it has no row here.

    python benchmarks/sigma_point.py --json out.json
"""

from __future__ import annotations

import argparse
import json

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

import jaxest as je  # noqa: E402
from jaxest.report import device_name, emit_json, timed  # noqa: E402

T, RUNS, DT, GRAVITY = 1000, 200, 0.0125, 9.81
ALPHA, BETA, KAPPA = 1.0, 2.0, 0.0


def f(x):
    return jnp.stack([x[0] + DT * x[1], x[1] - GRAVITY * DT * jnp.sin(x[0])])


def h(x):
    return jnp.sin(x[:1])


Q = 0.1 * jnp.array([[DT**3 / 3, DT**2 / 2], [DT**2 / 2, DT]])
R = jnp.array([[0.3**2]])
PRIOR = je.Gaussian(jnp.array([1.5, 0.0]), 0.1 * jnp.eye(2))

FILTERS = {
    "UKF": je.UKF(alpha=ALPHA, beta=BETA, kappa=KAPPA),
    "UKF-sqrt": je.UKF(alpha=ALPHA, beta=BETA, kappa=KAPPA, form="sqrt"),
    "UKF-svd": je.UKF(alpha=ALPHA, beta=BETA, kappa=KAPPA, form="svd"),
    "UKF-augmented": je.UKF(alpha=ALPHA, beta=BETA, kappa=KAPPA, noise="augmented"),
    "CubatureKF": je.CubatureKF(),
    "CubatureKF-sqrt": je.CubatureKF(form="sqrt"),
    "GaussHermiteKF3": je.GaussHermiteKF(order=3),
    "IteratedEKF3": je.IteratedEKF(iterations=3),
    "EKF": je.KalmanFilter(),
}


def jaxest_fn(filt):
    def loglik(q_scale, ys):
        result = je.run(filt, je.NonlinearGaussian(f, h, q_scale * Q, R), ys, prior=PRIOR)
        return result.loglik, result.mean

    return loglik


def dynamax_fn():
    from dynamax.nonlinear_gaussian_ssm import (
        ParamsNLGSSM,
        UKFHyperParams,
        unscented_kalman_filter,
    )

    hyper = UKFHyperParams(alpha=ALPHA, beta=BETA, kappa=KAPPA)

    def loglik(q_scale, ys):
        params = ParamsNLGSSM(PRIOR.mean, PRIOR.cov, f, q_scale * Q, h, R)
        post = unscented_kalman_filter(params, ys, hyper, output_fields=["filtered_means"])
        return post.marginal_loglik, post.filtered_means

    return loglik


def main(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--json", help="write the results here as well as to stdout")
    parser.add_argument("--steps", type=int, default=T, help="time steps per run (default 1000)")
    parser.add_argument("--runs", type=int, default=RUNS, help="runs under vmap (default 200)")
    args = parser.parse_args(argv)
    model = je.NonlinearGaussian(f, h, Q, R)
    keys = jax.random.split(jax.random.PRNGKey(1), args.runs)
    ys = jax.vmap(lambda k: je.simulate(model, PRIOR, args.steps, k).y)(keys)
    scales = jnp.linspace(0.5, 2.0, args.runs)
    theirs = dynamax_fn()
    ours = jaxest_fn(FILTERS["UKF"])
    a, b = ours(1.0, ys[0])[0], theirs(1.0, ys[0])[0]
    if not np.isclose(a, b, rtol=1e-8):
        raise RuntimeError(f"jaxest's and dynamax's UKF disagree ({a} vs {b}): not the same")
    rows = []
    for mode in ("single", "vmap200"):
        if mode == "single":
            call_args, per, wrap = (jnp.asarray(1.0), ys[0]), args.steps, lambda fn: fn
        else:
            call_args, per, wrap = (scales, ys), args.steps * args.runs, jax.vmap
        _, t_dynamax, _ = timed(wrap(theirs), call_args)
        for name, filt in FILTERS.items():
            compile_s, t, _ = timed(wrap(jaxest_fn(filt)), call_args)
            rows.append(
                {
                    "filter": name,
                    "mode": mode,
                    "jaxest_us_per_step": 1e6 * t / per,
                    "dynamax_ukf_us_per_step": 1e6 * t_dynamax / per,
                    "ratio_to_dynamax_ukf": t / t_dynamax,
                    "jaxest_compile_s": compile_s,
                }
            )
            print(json.dumps(rows[-1]), flush=True)
    emit_json(
        {"device": device_name(), "steps": args.steps, "runs": args.runs, "rows": rows},
        args.json,
    )


if __name__ == "__main__":
    main()
