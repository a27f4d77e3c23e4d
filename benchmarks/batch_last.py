"""Would the runs on the minor axis make the batched Kalman filter twice as fast as dynamax?

Under ``vmap`` every array of jaxest's filter step carries the runs on its leading axis (``lax.scan``
and the batching rules put them there), so the unrolled small-matrix code reads strided slices of
(runs, n, n) arrays. docs/performance.md ("What bounds linear_6x3 under `vmap`") left open whether
that layout is what keeps the linear 6 x 3 rows of ``speed.py`` from a ratio of 0.5. This writes
the filter by hand with the runs on the last axis: states and covariances (n, runs) and
(n, n, runs), every product written out entry by entry, element-wise over the runs, the m x m
innovation covariance factored by unrolled Cholesky, and jaxest's Joseph-form update (dynamax uses
the cheaper P - K H P). It has no status checks and no missing data: about what a batch-last
jaxest filter would cost, not a filter to use.

On speed.py's problem and data (200 runs with their own Q scale, T = 1000, forward: the
log-likelihoods and the filtered means), it times the prototype, ``vmap`` of jaxest's
``KalmanFilter`` and dynamax, interleaved for ``--rounds`` rounds, each best of 5 after compiling,
and reports each one's best, the ratios and the compile times (XLA's own cache serves the rounds
after the first). The prototype's results are checked against jaxest's.

    python benchmarks/batch_last.py --states 6 --measurements 3 --json batch_last.json
"""

from __future__ import annotations

import argparse

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
from speed import RUNS, T, gaussian_data, linear_problem  # noqa: E402

from jaxest.report import emit_json, timed  # noqa: E402


def products(A, B):
    """(i, j, ...) x (j, k, ...) -> (i, k, ...) written out entry by entry, each entry a sum of
    products of (runs,) vectors (or of a shared scalar and a vector): XLA fuses them into loops
    over the contiguous runs. (A multiply-and-sum over an (i, j, k, runs) broadcast took about
    twice as long, docs/performance.md.)"""
    inner, columns = A.shape[1], B.shape[1]
    return jnp.stack(
        [
            jnp.stack([sum(A[i, j] * B[j, c] for j in range(inner)) for c in range(columns)])
            for i in range(A.shape[0])
        ]
    )


def cholesky_rows(S):
    """The lower Cholesky factor of S (m, m, runs) as nested lists of (runs,) entries."""
    m = S.shape[0]
    L = [[None] * m for _ in range(m)]
    for j in range(m):
        L[j][j] = jnp.sqrt(S[j, j] - sum(L[j][p] ** 2 for p in range(j)))
        for i in range(j + 1, m):
            L[i][j] = (S[i, j] - sum(L[i][p] * L[j][p] for p in range(j))) / L[j][j]
    return L


def substitution(L, b, transposed=False):
    """x with L x = b (``transposed``: L^T x = b), b a list of m rows (each (..., runs))."""
    m = len(L)
    entry = (lambda i, p: L[p][i]) if transposed else (lambda i, p: L[i][p])
    x = [None] * m
    for i in reversed(range(m)) if transposed else range(m):
        done = range(i + 1, m) if transposed else range(i)
        x[i] = (b[i] - sum(entry(i, p) * x[p] for p in done)) / L[i][i]
    return x


def batch_last_filter(model, prior):
    """(q_scales (runs,), ys (runs, T, m)) -> (log-likelihoods (runs,), filtered means
    (T, n, runs)) of the model with Q scaled per run."""
    F, H, R = model.F, model.H, model.R
    n, m = H.shape[1], H.shape[0]

    def run(q_scales, ys):
        runs = q_scales.shape[0]
        Q = model.Q[:, :, None] * q_scales
        mean = jnp.broadcast_to(prior.mean[:, None], (n, runs))
        cov = jnp.broadcast_to(prior.cov[:, :, None], (n, n, runs))

        def step(carry, y):
            x, P, loglik = carry
            HP = products(H[:, :, None], P)  # (m, n, runs)
            S = products(HP, H.T[:, :, None]) + R[:, :, None]
            innovation = y - H @ x
            L = cholesky_rows(S)
            gain_t = jnp.stack(substitution(L, substitution(L, list(HP)), transposed=True))
            whitened = substitution(L, list(innovation))
            loglik = loglik - 0.5 * (
                sum(w**2 for w in whitened)
                + 2 * sum(jnp.log(L[i][i]) for i in range(m))
                + m * jnp.log(2 * jnp.pi)
            )
            gain = jnp.swapaxes(gain_t, 0, 1)  # (n, m, runs)
            x = x + jnp.sum(gain * innovation[None, :, :], axis=1)
            # Joseph form, as jaxest: (I - K H) P (I - K H)^T + K R K^T
            A = jnp.eye(n)[:, :, None] - products(gain, H[:, :, None])
            P = products(products(A, P), jnp.swapaxes(A, 0, 1))
            P = P + products(products(gain, R[:, :, None]), gain_t)
            P = 0.5 * (P + jnp.swapaxes(P, 0, 1))
            P_next = products(products(F[:, :, None], P), F.T[:, :, None]) + Q
            return (F @ x, P_next, loglik), x

        carry = (mean, cov, jnp.zeros(runs, mean.dtype))
        (_, _, loglik), means = jax.lax.scan(step, carry, jnp.moveaxis(ys, 0, -1))
        return loglik, means

    return run


def measure(states: int, measurements: int, rounds: int) -> dict:
    model, prior, ours, theirs = linear_problem(states, measurements)
    ys, scales = gaussian_data(model, prior, RUNS, T)
    candidates = {
        "batch_last": jax.jit(batch_last_filter(model, prior)),
        "jaxest_vmap": jax.jit(jax.vmap(ours)),
        "dynamax_vmap": jax.jit(jax.vmap(theirs)),
    }
    loglik, means = candidates["batch_last"](scales, ys)
    loglik_ref, means_ref = candidates["jaxest_vmap"](scales, ys)
    agreement = {
        "loglik_max_rel_error": float(jnp.max(jnp.abs(loglik - loglik_ref) / jnp.abs(loglik_ref))),
        "mean_max_abs_error": float(jnp.max(jnp.abs(jnp.moveaxis(means, -1, 0) - means_ref))),
    }
    if agreement["loglik_max_rel_error"] > 1e-10 or agreement["mean_max_abs_error"] > 1e-9:
        raise RuntimeError(f"the prototype does not compute jaxest's filter: {agreement}")
    times = {name: [] for name in candidates}
    compile_s = {name: [] for name in candidates}
    for _ in range(rounds):
        for name, fn in candidates.items():
            compiling, run_s, _ = timed(fn, (scales, ys))
            times[name].append(run_s / (RUNS * T) * 1e6)
            compile_s[name].append(compiling)
    best = {name: min(values) for name, values in times.items()}
    return {
        "problem": f"linear_{states}x{measurements}",
        "runs": RUNS,
        "time_steps": T,
        "us_per_step_and_run": times,
        "best_us_per_step_and_run": best,
        "compile_s": compile_s,
        "batch_last_over_dynamax": best["batch_last"] / best["dynamax_vmap"],
        "jaxest_over_dynamax": best["jaxest_vmap"] / best["dynamax_vmap"],
        "batch_last_over_jaxest": best["batch_last"] / best["jaxest_vmap"],
        **agreement,
    }


def main(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--states", type=int, default=6)
    parser.add_argument("--measurements", type=int, default=3)
    parser.add_argument("--rounds", type=int, default=5, help="interleaved rounds (default 5)")
    parser.add_argument("--json", help="write the result here as well as to stdout")
    args = parser.parse_args(argv)
    emit_json(measure(args.states, args.measurements, args.rounds), args.json)


if __name__ == "__main__":
    main()
