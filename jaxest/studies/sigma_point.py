"""Study ``sigma-point``: every nonlinear filter on three problems, and ML tuning through the UKF.

Filters: the EKF, the SVD-EKF, the iterated EKF (5 Gauss-Newton iterations), the UKF (alpha = 1, beta = 2, kappa = 0), the cubature and the
third-order Gauss-Hermite filters, each sigma-point filter in its covariance, square-root and
SVD forms, and the bootstrap particle filter with 10^3 particles (systematic resampling at
ESS < N/2). Problems:

(a) ``duffing``: the Duffing oscillator of :mod:`jaxest.systems.duffing` with Gaussian noise of
    the paper's box half-widths as standard deviations (Q = 0.005^2 I, R = 0.01^2 I), prior
    N([0.2, 0.3], 0.01 I), T = 100;
(b) ``flight``: the 23-state flight model of the svd-ekf study (:mod:`jaxest.studies.svd_ekf`),
    elevator 3-2-1-1 maneuver at 10 Hz, its simulator, 6 s (60 steps); small, it is expensive.
    Skipped there (``SKIPPED``): the Gauss-Hermite filter (3^23 ~ 9.4e10 points), the particle
    filter (16 of the 23 states are constant sensor parameters without process noise: the
    particles never rejuvenate them, so 10^3 particles in 23 dimensions collapse onto a few
    values);
(c) ``bearings``: bearings-only tracking of Gordon, Salmond & Smith (:mod:`jaxest.systems.bearings`),
    T = 24, the true initial state drawn from the prior.

For each problem, filter and dtype (float64, float32): RMSE over the runs no filter lost (the
states of ``RMSE_STATES``), mean NEES (time average per run, then over those runs; its expected
value is n), the number of diverged runs (a status flag, a non-finite value, or a time-averaged
NEES above ``NEES_FACTOR`` n) and the run time per step and run of the ``vmap``ped batch (compiled
beforehand). Also: by how much the SVD form's filtered means differ from the covariance form's
(max |difference| / prior std over the first runs, float64) -- the same points in other
arithmetic, so a rounding difference -- and an ML fit of diag Q, diag R on the Duffing problem through the UKF from a
10x wrong start (L-BFGS), with standard errors from the observed Fisher information.

Finally the particle filter's log-likelihood estimate against the Kalman filter's exact value on
a linear-Gaussian model (:func:`pf_loglik_convergence`): its bias and standard deviation over
independent keys at 10^2 ... 10^5 particles.

Default: 100 runs on every problem; the flight runs go through the filters in ``vmap``ped chunks
of ``CHUNK`` runs (:data:`CHUNK`). ``--quick``: 10 runs, T = 50 on (a), no (b), and
only the filters of ``QUICK_FILTERS`` (compilation, not the runs, dominates the time).
"""

from __future__ import annotations

from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import jaxest as je
from jaxest.filters import (
    EKF,
    SVDEKF,
    UKF,
    CubatureKF,
    GaussHermiteKF,
    IteratedEKF,
    KalmanFilter,
    ParticleFilter,
)
from jaxest.linalg import cholesky, solve_triangular
from jaxest.plot import save, subplots
from jaxest.progress import Progress
from jaxest.report import markdown_table, timed_call, write_json
from jaxest.studies import svd_ekf
from jaxest.systems import bearings, duffing, flight_sim
from jaxest.tune import (
    FIXED_STEPS_LBFGS,
    fit,
    log_variance_standard_errors,
    log_variances,
    neg_loglik,
)

NAME = "sigma-point"
DESCRIPTION = "sigma-point, iterated and particle filters on Duffing, flight and bearings-only"

FILTERS = {
    "ekf": EKF(),
    "svd_ekf": SVDEKF(),
    "iekf": IteratedEKF(iterations=5),
    **{f"ukf_{f}": UKF(form=f) for f in ("covariance", "sqrt", "svd")},
    **{f"ckf_{f}": CubatureKF(form=f) for f in ("covariance", "sqrt", "svd")},
    **{f"ghkf_{f}": GaussHermiteKF(order=3, form=f) for f in ("covariance", "sqrt", "svd")},
    "pf_1000": ParticleFilter(1000),
}
#: filters left out of a problem, with the reason (reported in the summary)
SKIPPED = {
    "flight": {
        **{
            f"ghkf_{f}": "3^23 Gauss-Hermite points in 23 dimensions"
            for f in ("covariance", "sqrt", "svd")
        },
        "pf_1000": "16 constant parameters without process noise: 1000 particles in 23 "
        "dimensions collapse onto a few values (no rejuvenation)",
    }
}
#: ``--quick``: these filters, on Duffing and bearings only
QUICK_FILTERS = ("ekf", "svd_ekf", "ukf_covariance", "ukf_sqrt", "ukf_svd", "pf_1000")
#: a run diverged when its time-averaged NEES exceeds NEES_FACTOR times the state dimension
NEES_FACTOR = 20.0
DTYPES = ("float64", "float32")
#: runs per ``vmap``ped batch (the runs of a problem not named here: all at once). jaxlib 0.10's
#: CPU thread pool can deadlock when two batched LAPACK calls of more than about 2e5 flops each
#: run at once (:mod:`jaxest.montecarlo`); 10 flight runs keep a batched 23 x 23 factorisation at
#: 10 * 23^3 ~ 1.2e5 flops. All 100 flight runs in one ``vmap`` hung once here (every thread
#: asleep); in chunks of 10 they cost about the same.
CHUNK = {"flight": 10}


class Problem(eqx.Module):
    """A batch of runs: model, prior per run, measurements, inputs and true states."""

    model: eqx.Module
    mean0: jax.Array  # (runs, n)
    cov0: jax.Array  # (n, n)
    ys: jax.Array  # (runs, T, m)
    inputs: jax.Array | None  # (runs, T, p)
    truth: jax.Array  # (runs, T, n)
    rmse_states: tuple[int, ...] = eqx.field(static=True)


def duffing_model(dtype, q_scale=1.0, r_scale=1.0):
    Q = q_scale * duffing.PROCESS_BOUND**2 * jnp.eye(2, dtype=dtype)
    R = r_scale * duffing.MEASUREMENT_BOUND**2 * jnp.eye(2, dtype=dtype)
    return je.NonlinearGaussian(duffing.Duffing(), duffing.observe, Q, R)


def duffing_prior(dtype):
    return je.Gaussian(jnp.asarray(duffing.X0, dtype), duffing.P0_SCALE * jnp.eye(2, dtype=dtype))


def make_problems(name, dtypes, runs, T, key) -> dict[str, Problem]:
    """``name``'s runs, simulated once in float64 (duffing, bearings: x_0 ~ the prior), as the
    problem of the filters in each of ``dtypes``."""
    if name == "flight":
        truth = flight_sim.true_flight("elevator", 10, T / 10.0, dtype=jnp.float64)
        batch = svd_ekf.simulated_batch(truth, runs, key, jnp.float64)

        def problem(dt):
            ys, inputs, mean0, states = (a.astype(dt) for a in batch)
            model, cov0 = svd_ekf.model_for(10, dt), svd_ekf.prior_cov(dt)
            return Problem(model, mean0, cov0, ys, inputs, states, (0, 1, 2))

    else:
        model, prior, rmse_states = {
            "duffing": (duffing_model, duffing_prior, (0, 1)),
            "bearings": (bearings.model, bearings.prior, (0, 2)),
        }[name]
        model64, prior64 = model(jnp.float64), prior(jnp.float64)
        sims = je.monte_carlo(lambda k: je.simulate(model64, prior64, T, k), key, runs)

        def problem(dt):
            prior_dt = prior(dt)
            mean0 = jnp.broadcast_to(prior_dt.mean, (runs, prior_dt.mean.shape[0]))
            ys, states = sims.y.astype(dt), sims.states.astype(dt)
            return Problem(model(dt), mean0, prior_dt.cov, ys, None, states, rmse_states)

    return {dtype: problem(jnp.dtype(dtype)) for dtype in dtypes}


def nees(err, cov):
    """e^T P^-1 e per step, through the Cholesky factor (NaN where P is not positive definite)."""
    L = cholesky(cov)
    w = jax.vmap(lambda L, e: solve_triangular(L, e, lower=True))(L, err)
    return jnp.sum(w**2, axis=-1)


def one_run(estimator, problem: Problem, mean0, ys, inputs, truth, key):
    prior = je.Gaussian(mean0, problem.cov0)
    save = je.SaveAt(fields=("mean", "cov", "status"))
    kwargs = {"key": key} if estimator.needs_key else {}
    r = je.run(estimator, problem.model, ys, prior=prior, inputs=inputs, save=save, **kwargs)
    err = (r.mean - truth).astype(jnp.float64)
    idx = jnp.asarray(problem.rmse_states)
    return {
        "sq_err": jnp.mean(err[:, idx] ** 2),
        "nees": jnp.mean(nees(err, r.cov.astype(jnp.float64))),
        "status": r.any_status,
        "finite": jnp.all(jnp.isfinite(r.mean)) & jnp.all(jnp.isfinite(r.cov)),
        "mean": r.mean,
    }


@eqx.filter_jit
def batch_metrics(estimator, problem: Problem, keys, chunk: int | None = None):
    """:func:`one_run` over the runs of ``problem``: one ``vmap``, or ``vmap``s of ``chunk`` runs
    in a ``lax.map``."""

    def one(args):
        mean0, ys, inputs, truth, key = args
        return one_run(estimator, problem, mean0, ys, inputs, truth, key)

    args = (problem.mean0, problem.ys, problem.inputs, problem.truth, keys)
    if chunk is None or chunk >= keys.shape[0]:
        return jax.vmap(one)(args)
    return jax.lax.map(one, args, batch_size=chunk)


def timed_metrics(estimator, problem: Problem, keys, chunk: int | None = None):
    """Metrics of every run (NumPy) and the run time per step and run, compilation excluded."""
    compiled = batch_metrics.lower(estimator, problem, keys, chunk).compile()
    metrics, elapsed = timed_call(lambda: compiled(estimator, problem, keys, chunk))
    runs, T = problem.ys.shape[:2]
    return jax.tree.map(np.asarray, metrics), elapsed / (runs * T)


def diverged(metrics, n):
    bad = (metrics["status"] != 0) | ~metrics["finite"] | ~np.isfinite(metrics["nees"])
    return bad | (metrics["nees"] > NEES_FACTOR * n)


def evaluate(name, problem: Problem, seed, filters=tuple(FILTERS)) -> tuple[dict, dict]:
    """Every filter on ``problem``: {filter: metrics and per-step time}, then RMSE and NEES over
    the runs no filter lost; and {filter: its filtered means of every run}."""
    runs, n = problem.truth.shape[0], problem.truth.shape[-1]
    keys = jax.random.split(jax.random.key(seed), runs)
    raw = {}
    for fname in filters:
        if fname not in SKIPPED.get(name, {}):
            raw[fname] = timed_metrics(FILTERS[fname], problem, keys, CHUNK.get(name))
    bad = {f: diverged(m, n) for f, (m, _) in raw.items()}
    common = ~np.any(np.stack(list(bad.values())), axis=0)
    out = {}
    for fname, (m, seconds) in raw.items():
        use = common if np.any(common) else ~bad[fname]
        out[fname] = {
            "rmse": float(np.sqrt(np.mean(m["sq_err"][use]))) if np.any(use) else None,
            "nees": float(np.mean(m["nees"][use])) if np.any(use) else None,
            "diverged": int(np.sum(bad[fname])),
            "status_runs": int(np.sum(m["status"] != 0)),
            "us_per_step": 1e6 * seconds,
        }
    means = {fname: m["mean"] for fname, (m, _) in raw.items()}
    return {"filters": out, "runs": runs, "compared_runs": int(np.sum(common)), "n": n}, means


def svd_form_difference(means: dict, cov0, runs: int = 5) -> dict:
    """max |mean_svd - mean_covariance| / prior std of the UKF and the CKF over the first
    ``runs`` runs, from :func:`evaluate`'s filtered means (where both forms of a family ran)."""
    sd = np.sqrt(np.diag(np.asarray(cov0)))
    out = {}
    for family in ("ukf", "ckf"):
        svd, covariance = means.get(f"{family}_svd"), means.get(f"{family}_covariance")
        if svd is not None and covariance is not None:
            out[family] = float(np.max(np.abs(svd[:runs] - covariance[:runs]) / sd))
    return out


def tune_duffing(runs: int, T: int, seed: int, steps: int, optimizer=FIXED_STEPS_LBFGS) -> dict:
    """ML fit of diag Q, diag R through the UKF from Q x 10, R / 10; z-scores of the fitted
    log-variances against the truth with standard errors from the observed Fisher information."""
    truth, prior = duffing_model(jnp.float64), duffing_prior(jnp.float64)
    ys = je.monte_carlo(lambda k: je.simulate(truth, prior, T, k), jax.random.key(seed), runs).y
    start = duffing_model(jnp.float64, q_scale=10.0, r_scale=0.1)
    params = {"Q": "log_diagonal", "R": "log_diagonal"}
    loss = neg_loglik(UKF(), ys, prior=prior)
    result = fit(start, loss, params, optimizer=optimizer, num_steps=steps)
    se = log_variance_standard_errors(result.model, loss, ys.shape[0] * ys.shape[1])
    return {
        "runs": runs,
        "steps": T,
        "true": {"Q_diag": np.diag(truth.Q), "R_diag": np.diag(truth.R)},
        "start": {"Q_diag": np.diag(start.Q), "R_diag": np.diag(start.R)},
        "fitted": {"Q_diag": np.diag(result.model.Q), "R_diag": np.diag(result.model.R)},
        "standard_errors_log": se,
        "z_scores": np.asarray(log_variances(result.model) - log_variances(truth)) / se,
        "loss_first": float(result.losses[0]),
        "loss_last": float(result.losses[-1]),
    }


#: the particle counts of :func:`pf_loglik_convergence`
PARTICLE_COUNTS = (100, 1_000, 10_000, 100_000)


def tracking_model():
    """A 2-D constant-velocity target in one axis, position measured: the linear-Gaussian model
    of the particle filter's likelihood check (dt = 1, q = 0.1, r = 1)."""
    F = jnp.asarray([[1.0, 1.0], [0.0, 1.0]])
    Q = 0.1 * jnp.asarray([[1 / 3, 1 / 2], [1 / 2, 1.0]])
    H, R = jnp.asarray([[1.0, 0.0]]), jnp.eye(1)
    return je.LinearGaussian(F, H, Q, R), je.Gaussian(jnp.zeros(2), jnp.eye(2))


def pf_loglik_convergence(T: int, keys_per_count: int, seed: int, counts=PARTICLE_COUNTS):
    """Bootstrap particle filter (systematic resampling at ESS < N/2) log-likelihood minus the
    Kalman filter's on one simulated sequence of ``tracking_model``: mean (bias), standard
    deviation and standard error of the mean over ``keys_per_count`` keys, per particle count.
    The estimate of the likelihood is unbiased, so that of its log is biased low by about
    var / 2 (Jensen); both shrink as 1/N."""
    model, prior = tracking_model()
    ys = je.simulate(model, prior, T, jax.random.key(seed)).y
    exact = float(je.run(KalmanFilter(), model, ys, prior=prior).loglik)
    keys = jax.random.split(jax.random.key(seed + 1), keys_per_count)
    rows = {}
    for N in counts:
        loglik = eqx.filter_jit(
            lambda keys, N=N: jax.lax.map(
                lambda k: je.run(ParticleFilter(N), model, ys, prior=prior, key=k).loglik, keys
            )
        )
        errors = np.asarray(loglik(keys)) - exact
        rows[N] = {
            "bias": float(np.mean(errors)),
            "std": float(np.std(errors, ddof=1)),
            "standard_error": float(np.std(errors, ddof=1) / np.sqrt(len(errors))),
        }
    return {"steps": T, "keys": keys_per_count, "exact_loglik": exact, "by_particles": rows}


def figure(results: dict, path: Path):
    names = list(results)
    fig, axes = subplots(2, len(names), width=4.6, height=3.2)
    for j, problem in enumerate(names):
        filters = list(results[problem]["float64"]["filters"])
        x = np.arange(len(filters))
        for off, dtype in ((-0.2, "float64"), (0.2, "float32")):
            block = results[problem][dtype]["filters"]
            rmse = [np.nan if block[f]["rmse"] is None else block[f]["rmse"] for f in filters]
            axes[0, j].bar(x + off, rmse, width=0.4, label=dtype)
            axes[1, j].bar(x + off, [block[f]["diverged"] for f in filters], width=0.4)
        axes[0, j].set_title(f"{problem}: RMSE (compared runs)")
        axes[0, j].set_yscale("log")
        axes[1, j].set_title(f"{problem}: diverged runs of {results[problem]['float64']['runs']}")
        for ax in axes[:, j]:
            ax.set_xticks(x, filters, rotation=70, fontsize=7)
    axes[0, 0].legend(fontsize=8)
    save(fig, path)


def write_tables(out_dir: Path, summary: dict):
    text = ""
    for problem, by_dtype in summary["problems"].items():
        rows = []
        for dtype, block in by_dtype.items():
            for fname, r in block["filters"].items():
                fmt = lambda v: "n/a" if v is None else f"{v:.4g}"
                rows.append(
                    [fname, dtype, fmt(r["rmse"]), fmt(r["nees"]), r["diverged"],
                     f"{r['us_per_step']:.1f}"]
                )  # fmt: skip
        text += f"## {problem} (n = {by_dtype['float64']['n']}, runs = "
        text += f"{by_dtype['float64']['runs']})\n\n"
        text += markdown_table(["filter", "dtype", "RMSE", "NEES", "diverged", "us/step/run"], rows)
        for fname, why in SKIPPED.get(problem, {}).items():
            text += f"\nSkipped {fname}: {why}."
        text += "\n\n"
    tune = summary["tuning"]
    text += "## ML tuning of Q, R on Duffing through the UKF\n\n" + markdown_table(
        ["", "Q11", "Q22", "R11", "R22"],
        [[k, *tune[k]["Q_diag"], *tune[k]["R_diag"]] for k in ("true", "start", "fitted")]
        + [["z-score", *tune["z_scores"]]],
    )
    conv = summary["pf_loglik"]
    text += (
        f"\n\n## Particle filter log-likelihood minus the Kalman filter's ({conv['steps']} steps, "
        f"{conv['keys']} keys, exact {conv['exact_loglik']:.4f})\n\n"
    )
    text += markdown_table(
        ["particles", "bias", "std", "standard error"],
        [
            [N, f"{r['bias']:.4g}", f"{r['std']:.4g}", f"{r['standard_error']:.2g}"]
            for N, r in conv["by_particles"].items()
        ],
    )
    (out_dir / "tables.md").write_text(text)


def run(out: Path, *, runs: int | None, seed: int, quick: bool, options: dict) -> dict:
    out_dir = Path(out) / "sigma-point"
    runs = runs or (10 if quick else 100)
    settings = {"duffing": (runs, 50 if quick else 100), "bearings": (runs, bearings.NUM_STEPS)}
    if not quick:
        settings["flight"] = (runs, 60)
    filters = QUICK_FILTERS if quick else tuple(FILTERS)
    summary: dict = {
        "settings": {
            "runs": {p: r for p, (r, _) in settings.items()},
            "steps": {p: T for p, (_, T) in settings.items()},
            "seed": seed,
            "nees_factor": NEES_FACTOR,
            "filters": filters,
            "skipped": SKIPPED,
        },
        "problems": {},
        "svd_form_difference": {},
    }
    with Progress(NAME, total=len(settings) * len(DTYPES) + 3) as progress:
        for i, (name, (n_runs, T)) in enumerate(settings.items()):
            summary["problems"][name] = {}
            problems = make_problems(name, DTYPES, n_runs, T, jax.random.key(seed + 100 * i))
            for dtype, problem in problems.items():
                result, means = evaluate(name, problem, seed + 1, filters)
                summary["problems"][name][dtype] = result
                if dtype == "float64":
                    summary["svd_form_difference"][name] = svd_form_difference(means, problem.cov0)
                progress.advance(f"{name} {dtype}")
        summary["tuning"] = tune_duffing(5 if quick else 20, 100, seed + 7, 30 if quick else 40)
        progress.advance("tuning")
        counts = PARTICLE_COUNTS[:2] if quick else PARTICLE_COUNTS
        summary["pf_loglik"] = pf_loglik_convergence(50, 10 if quick else 40, seed + 9, counts)
        progress.advance("particle log-likelihood")
        figure(summary["problems"], out_dir / "filters.png")
        write_tables(out_dir, summary)
        write_json(out_dir / "summary.json", summary)
        progress.advance("written")
    return summary
