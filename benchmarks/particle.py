"""jaxest's particle filter against cuthbert's, in one process (issue 13).

Problem: the pendulum of benchmarks/sigma_point.py (x = [angle, rate], y = sin x0 + v), T = 200,
float64. Filter: the bootstrap particle filter, N = 1000 particles, systematic resampling when
ESS < N/2, in both libraries: ``je.ParticleFilter(1000)`` (its defaults) and cuthbert's
``smc.particle_filter.build_filter`` with cuthbertlib's systematic resampling under
``ess_decorator(..., 0.5)``, run by ``cuthbert.filtering.filter``. Each returns the
log-likelihood estimate and the filtered means.

Conventions aligned: jaxest weights the prior's particles by y_0 (the prior is the belief at the
first measurement). cuthbert's ``init_prepare`` draws x_0 from the prior with equal weights and
log Z = 0 (no potential at time 0), and each later step resamples, propagates and weights. So
cuthbert starts from its ``init_prepare`` state reweighted by log g(y_0 | x_0^i) (log Z_0 =
logsumexp - log N) and filters y_1..y_{T-1}: both estimate log p(y_0..y_{T-1}), with the same
increments and the same resampling decisions (jaxest resamples at the end of step k, cuthbert at
the start of step k + 1, on the same weights).

Modes: one sequence, and 200 runs under ``vmap`` (own measurements and key per run). Per-step
time = wall time / (runs * T), best of 3 repeats after compilation; compile time apart. On CPU
cuthbert's inverse CDF is a numba ``pure_callback`` (``vmap_method="sequential"``), and under
``vmap`` its adaptive ``lax.cond`` runs both branches. Sanity check (reported, not asserted):
mean and std of the log-likelihood estimate over 50 keys on one sequence from each library, and
z = difference of the means / its standard error.

    python benchmarks/particle.py --json out.json
    python benchmarks/particle.py --quick   # T = 50, 20 runs, 10 keys
"""

from __future__ import annotations

import argparse
import json

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

from sigma_point import PRIOR, Q, R, f, h  # noqa: E402 - the sigma-point benchmark's pendulum

import jaxest as je  # noqa: E402
from jaxest.report import device_name, emit_json, timed  # noqa: E402

N, ESS_THRESHOLD = 1000, 0.5
MODEL = je.NonlinearGaussian(f, h, Q, R)


def jaxest_fn(key, ys):
    filt = je.ParticleFilter(N, resampling="systematic", ess_threshold=ESS_THRESHOLD)
    result = je.run(filt, MODEL, ys, prior=PRIOR, key=key, save=je.SaveAt(fields=("mean",)))
    return result.loglik, result.mean


def cuthbert_fn():
    from cuthbert.filtering import filter as cuthbert_filter
    from cuthbert.smc.particle_filter import build_filter
    from cuthbertlib.resampling import ess_decorator, systematic

    chol_prior, chol_Q = jnp.linalg.cholesky(PRIOR.cov), jnp.linalg.cholesky(Q)

    def log_g(x, y):
        return jax.scipy.stats.multivariate_normal.logpdf(y, h(x), R)

    pf = build_filter(
        init_sample=lambda key: PRIOR.mean + chol_prior @ jax.random.normal(key, (2,)),
        propagate_sample=lambda key, x, y: f(x) + chol_Q @ jax.random.normal(key, (2,)),
        log_potential=lambda x_prev, x, y: log_g(x, y),
        n_filter_particles=N,
        resampling_fn=ess_decorator(systematic.resampling, ESS_THRESHOLD),
    )

    def loglik(key, ys):
        init_key, first_key, key = jax.random.split(key, 3)
        state = pf.init_prepare(key=init_key)
        log_w = jax.vmap(log_g, (0, None))(state.particles, ys[0])
        # the first step draws from state.key: a fresh key, for split(init_key, N + 1) in that
        # step would repeat the N normal draws of the initial particles
        state = state._replace(
            key=first_key,
            log_weights=log_w,
            log_normalizing_constant=jax.nn.logsumexp(log_w) - jnp.log(N),
        )
        states = cuthbert_filter(pf, ys[1:], state, key=key)
        W = jax.nn.softmax(states.log_weights, axis=-1)
        return states.log_normalizing_constant[-1], jnp.einsum("tn,tni->ti", W, states.particles)

    return loglik


def main(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--json", help="write the results here as well as to stdout")
    parser.add_argument("--quick", action="store_true", help="T = 50, 20 runs, 10 keys")
    args = parser.parse_args(argv)
    steps, runs, num_keys = (50, 20, 10) if args.quick else (200, 200, 50)
    ys = jax.vmap(lambda k: je.simulate(MODEL, PRIOR, steps, k).y)(
        jax.random.split(jax.random.key(1), runs)
    )
    keys = jax.random.split(jax.random.key(2), runs)
    fns = {"jaxest": jaxest_fn, "cuthbert": cuthbert_fn()}
    rows = []
    for mode in ("single", f"vmap{runs}"):
        if mode == "single":
            call_args, per, wrap = (keys[0], ys[0]), steps, lambda fn: fn
        else:
            call_args, per, wrap = (keys, ys), steps * runs, jax.vmap
        row = {"mode": mode}
        for name, fn in fns.items():
            compile_s, t, _ = timed(wrap(fn), call_args, repeats=3)
            row[f"{name}_us_per_step"] = 1e6 * t / per
            row[f"{name}_compile_s"] = compile_s
        row["ratio"] = row["jaxest_us_per_step"] / row["cuthbert_us_per_step"]
        rows.append(row)
        print(json.dumps(row), flush=True)
    check = {"keys": num_keys}
    key_batch = jax.random.split(jax.random.key(3), num_keys)
    for name, fn in fns.items():
        logliks = np.asarray(jax.jit(jax.vmap(fn, (0, None)))(key_batch, ys[0])[0])
        check[f"{name}_loglik_mean"] = logliks.mean()
        check[f"{name}_loglik_std"] = logliks.std(ddof=1)
    check["z"] = (check["jaxest_loglik_mean"] - check["cuthbert_loglik_mean"]) / np.sqrt(
        (check["jaxest_loglik_std"] ** 2 + check["cuthbert_loglik_std"] ** 2) / num_keys
    )
    emit_json(
        {
            "device": device_name(),
            "steps": steps,
            "runs": runs,
            "particles": N,
            "rows": rows,
            "loglik_check": check,
        },
        args.json,
    )


if __name__ == "__main__":
    main()
