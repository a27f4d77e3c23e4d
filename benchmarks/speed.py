"""jaxest against dynamax in one process, on the same problems (issue: core, acceptance).

Problems: ``linear_4x2`` (n = 4, m = 2 random stable system) and ``duffing_ekf`` (the Duffing map
of docs/papers/smf.md with Gaussian noise), T = 1000. Modes: one sequence, and 200 runs under
``vmap`` with a different process covariance per run. Passes: forward (log-likelihood and
filtered means) and ``value_and_grad`` of the log-likelihood with respect to the Q scale.
Per-step time = wall time / (runs * T), best of several repeats after compilation.

    python benchmarks/speed.py --json out.json
"""

from __future__ import annotations

import argparse
import json

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

import jaxest as je  # noqa: E402
from jaxest.filters import KalmanFilter  # noqa: E402
from jaxest.report import emit_json, timed  # noqa: E402
from jaxest.systems.duffing import Duffing  # noqa: E402

T, RUNS = 1000, 200


def linear_model():
    """The random stable 4-state / 2-measurement model (seed 0) and its prior."""
    rng = np.random.default_rng(0)
    F = 0.95 * np.linalg.qr(rng.normal(size=(4, 4)))[0]
    H = rng.normal(size=(2, 4))
    A = rng.normal(size=(4, 4))
    Q = A @ A.T / 4 + 0.1 * np.eye(4)
    R = np.array([[0.5, 0.1], [0.1, 0.3]])
    model = je.LinearGaussian(*(jnp.asarray(a) for a in (F, H, Q, R)))
    return model, je.Gaussian(jnp.zeros(4), jnp.eye(4))


def linear_problem():
    model, prior = linear_model()

    def jaxest_loglik(q_scale, ys):
        mdl = je.LinearGaussian(model.F, model.H, q_scale * model.Q, model.R)
        res = je.run(KalmanFilter(), mdl, ys, prior=prior)
        return res.loglik, res.mean

    from dynamax.linear_gaussian_ssm import LinearGaussianSSM, lgssm_filter

    params, _ = LinearGaussianSSM(4, 2).initialize(
        jax.random.PRNGKey(0),
        initial_mean=prior.mean, initial_covariance=prior.cov,
        dynamics_weights=model.F, dynamics_covariance=model.Q,
        emission_weights=model.H, emission_covariance=model.R,
    )  # fmt: skip

    def dynamax_loglik(q_scale, ys):
        p = params._replace(dynamics=params.dynamics._replace(cov=q_scale * model.Q))
        post = lgssm_filter(p, ys)
        return post.marginal_loglik, post.filtered_means

    return model, prior, jaxest_loglik, dynamax_loglik


def duffing_problem():
    f = Duffing()
    h = lambda x, u=None: x
    Q, R = 1e-5 * jnp.eye(2), 1e-4 * jnp.eye(2)
    model = je.NonlinearGaussian(f, h, Q, R)
    prior = je.Gaussian(jnp.asarray([0.2, 0.3]), 0.01 * jnp.eye(2))

    def jaxest_loglik(q_scale, ys):
        mdl = je.NonlinearGaussian(f, h, q_scale * Q, R)
        res = je.run(KalmanFilter(), mdl, ys, prior=prior)
        return res.loglik, res.mean

    from dynamax.nonlinear_gaussian_ssm import ParamsNLGSSM, extended_kalman_filter

    def dynamax_loglik(q_scale, ys):
        p = ParamsNLGSSM(prior.mean, prior.cov, lambda x: f(x), q_scale * Q, lambda x: x, R)
        post = extended_kalman_filter(p, ys, output_fields=["filtered_means"])
        return post.marginal_loglik, post.filtered_means

    return model, prior, jaxest_loglik, dynamax_loglik


def passes(loglik):
    """forward and value_and_grad versions of a (q_scale, ys) -> (loglik, means) function."""
    value_and_grad = jax.value_and_grad(lambda q, ys: loglik(q, ys)[0])
    return {"forward": loglik, "value_and_grad": value_and_grad}


def main(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--json", help="write the results here as well as to stdout")
    parser.add_argument("--steps", type=int, default=T, help="time steps per run (default 1000)")
    parser.add_argument("--runs", type=int, default=RUNS, help="runs under vmap (default 200)")
    args = parser.parse_args(argv)
    rows = []
    for name, build in (("linear_4x2", linear_problem), ("duffing_ekf", duffing_problem)):
        model, prior, ours, theirs = build()
        keys = jax.random.split(jax.random.PRNGKey(1), args.runs)
        ys = jax.vmap(lambda k: je.simulate(model, prior, args.steps, k).y)(keys)
        scales = jnp.linspace(0.5, 2.0, args.runs)  # a different Q per run
        a, b = ours(1.0, ys[0])[0], theirs(1.0, ys[0])[0]
        if not np.isclose(a, b, rtol=1e-6):  # Joseph vs plain update differ in rounding
            raise RuntimeError(
                f"{name}: the two libraries disagree ({a} vs {b}): not the same problem"
            )
        for mode in ("single", "vmap200"):
            for pass_name in ("forward", "value_and_grad"):
                fns = [passes(ours)[pass_name], passes(theirs)[pass_name]]
                if mode == "single":
                    call_args, per = (jnp.asarray(1.0), ys[0]), args.steps
                else:
                    fns = [jax.vmap(fn) for fn in fns]
                    call_args, per = (scales, ys), args.steps * args.runs
                (c_ours, t_ours, _), (_, t_theirs, _) = (
                    timed(fns[0], call_args),
                    timed(fns[1], call_args),
                )
                rows.append(
                    {
                        "problem": name,
                        "mode": mode,
                        "pass": pass_name,
                        "jaxest_us_per_step": 1e6 * t_ours / per,
                        "dynamax_us_per_step": 1e6 * t_theirs / per,
                        "ratio": t_ours / t_theirs,
                        "jaxest_compile_s": c_ours,
                    }
                )
                print(json.dumps(rows[-1]), flush=True)
    forward = {
        (r["problem"], r["mode"]): r["jaxest_us_per_step"] for r in rows if r["pass"] == "forward"
    }
    for r in rows:
        if r["pass"] == "value_and_grad":
            r["grad_over_forward"] = r["jaxest_us_per_step"] / forward[(r["problem"], r["mode"])]
    emit_json({"device": str(jax.devices()[0]), "rows": rows}, args.json)


if __name__ == "__main__":
    main()
