"""The parallel-in-time Kalman filter and RTS smoother against the sequential ones and a NumPy
Kalman filter: values, log-likelihood and its gradient, missing data, float32 at T = 10^4,
jit/vmap/grad, and argument errors."""

import functools
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxest as je
from tests.reference import kalman_filter, random_system

FORMS = [True, False]
FORM_IDS = ["square_root", "standard"]
FIELDS = ("mean", "cov", "predicted_mean", "predicted_cov", "innovation", "innovation_cov",
          "loglik_terms")  # fmt: skip


def assert_close(actual, desired, rtol=1e-9):
    """rtol relative to each array's largest entry (means cross zero)."""
    desired = np.asarray(desired)
    scale = np.max(np.abs(desired))
    np.testing.assert_allclose(actual, desired, rtol=rtol, atol=rtol * scale)


@functools.cache
def problem(seed=0, n=4, m=2, q=2, p=1, T=40):
    """A random system with a rank-q noise gain G (n x q, so G Q G^T is singular), inputs,
    and measurements with a missing entry and two wholly missing vectors."""
    rng = np.random.default_rng(seed)
    F, H, Q, R = random_system(rng, n, m)
    G = rng.normal(size=(n, q))
    B, D = rng.normal(size=(n, p)), rng.normal(size=(m, p))
    Qq = np.eye(q) * 0.3 + 0.1
    model = je.LinearGaussian(*map(jnp.asarray, (F, H, Qq, R, G, B, D)))
    prior = je.Gaussian(jnp.asarray(rng.normal(size=n)), jnp.asarray(2.0 * np.eye(n)))
    inputs = jnp.asarray(rng.normal(size=(T, p)))
    ys = np.array(je.simulate(model, prior, T, jax.random.PRNGKey(seed), inputs=inputs).y)
    full = ys.copy()
    ys[3, 0] = np.nan
    ys[7, :] = np.nan
    ys[T - 1, :] = np.nan
    return model, prior, inputs, jnp.asarray(full), jnp.asarray(ys)


@pytest.mark.parametrize("square_root", FORMS, ids=FORM_IDS)
def test_equals_sequential_kalman_filter_with_and_without_missing_data(square_root):
    model, prior, inputs, full, missing = problem()
    parallel = je.ParallelKalmanFilter(square_root=square_root)
    for ys in (full, missing):
        seq = je.run(je.KalmanFilter(), model, ys, prior=prior, inputs=inputs)
        par = je.run(parallel, model, ys, prior=prior, inputs=inputs)
        for field in FIELDS:
            assert_close(getattr(par, field), getattr(seq, field))
        assert_close(par.loglik, seq.loglik)
        assert_close(par.final_state.mean, seq.final_state.mean)
        assert_close(par.final_state.factor.cov, seq.final_state.factor.cov)
        assert int(par.any_status) == 0
        # the same pieces run sequentially (init/step) give the same numbers
        one_by_one = je.run(parallel, model, ys, prior=prior, inputs=inputs, parallel=False)
        assert_close(one_by_one.loglik, seq.loglik)
        assert_close(one_by_one.cov, seq.cov)


def test_matches_numpy_kalman_filter():
    """The default (square-root) form against NumPy; the standard form equals KalmanFilter
    (above), which equals NumPy (tests/test_filters.py)."""
    rng = np.random.default_rng(5)
    F, H, Q, R = random_system(rng, 3, 2)
    model = je.LinearGaussian(*map(jnp.asarray, (F, H, Q, R)))
    prior = je.Gaussian(jnp.asarray(rng.normal(size=3)), jnp.eye(3))
    ys = np.array(je.simulate(model, prior, 40, jax.random.PRNGKey(5)).y)
    ys[0, :], ys[11, 1] = np.nan, np.nan  # the first vector missing too
    res = je.run(je.ParallelKalmanFilter(), model, jnp.asarray(ys), prior=prior)
    means, covs, pmeans, pcovs, loglik = kalman_filter(F, H, Q, R, np.asarray(prior.mean),
                                                       np.asarray(prior.cov), ys)  # fmt: skip
    for actual, desired in zip((res.mean, res.cov, res.predicted_mean, res.predicted_cov),
                               (means, covs, pmeans, pcovs), strict=True):  # fmt: skip
        assert_close(actual, desired)
    assert_close(res.loglik, loglik)


def loglik_and_grad(filt, model, prior, ys, inputs):
    """log p(y) and its gradient in (F, H, B, D, noise factors, prior), Q = Lq Lq^T etc. (a
    symmetric parametrisation), at the parameters given."""

    @jax.jit
    def fn(params):
        F, H, B, D, Lq, Lr, m0, L0 = params
        m = je.LinearGaussian(F, H, Lq @ Lq.T, Lr @ Lr.T, model.G, B, D)
        return je.run(filt, m, ys, prior=je.Gaussian(m0, L0 @ L0.T), inputs=inputs).loglik

    chol = jnp.linalg.cholesky
    params = (model.F, model.H, model.B, model.D, chol(model.Q), chol(model.R), prior.mean,
              chol(prior.cov))  # fmt: skip
    return fn, params


@pytest.mark.parametrize("square_root", FORMS, ids=FORM_IDS)
def test_loglik_gradient_equals_sequential(square_root):
    model, prior, inputs, _, ys = problem()
    ys, inputs = ys[:8], inputs[:8]  # with the missing entry and the missing vector
    seq_fn, params = loglik_and_grad(je.KalmanFilter(), model, prior, ys, inputs)
    par = je.ParallelKalmanFilter(square_root=square_root)
    fn, _ = loglik_and_grad(par, model, prior, ys, inputs)
    value, grad = jax.value_and_grad(fn)(params)
    seq_value, seq_grad = jax.value_and_grad(seq_fn)(params)
    assert_close(value, seq_value)
    for g, g_seq in zip(grad, seq_grad, strict=True):
        assert_close(g, g_seq)
    # and against a central finite difference of the parallel filter along a random direction
    rng = np.random.default_rng(1)
    direction = jax.tree.map(lambda a: jnp.asarray(rng.normal(size=a.shape)), params)
    shifted = lambda t: jax.tree.map(lambda a, d: a + t * d, params, direction)
    h = 1e-5
    fd = (fn(shifted(h)) - fn(shifted(-h))) / (2 * h)
    exact = sum(jnp.vdot(g, d) for g, d in zip(grad, direction, strict=True))
    np.testing.assert_allclose(fd, exact, rtol=1e-6)


@pytest.mark.parametrize("square_root", FORMS, ids=FORM_IDS)
def test_parallel_smoother_equals_sequential_rts(square_root):
    model, prior, inputs, _, ys = problem()
    filtered = je.run(je.ParallelKalmanFilter(square_root=square_root), model, ys, prior=prior,
                      inputs=inputs)  # fmt: skip
    seq = je.rts_smooth(model, je.run(je.KalmanFilter(), model, ys, prior=prior, inputs=inputs),
                        inputs=inputs)  # fmt: skip
    par = je.rts_smooth(model, filtered, inputs=inputs, parallel=True)
    assert_close(par.mean, seq.mean)
    assert_close(par.cov, seq.cov)
    assert_close(par.cross_cov, seq.cross_cov)
    assert bool(par.ok)


@pytest.mark.parametrize("parallel", [False, True], ids=["sequential", "parallel"])
def test_a_float32_smoothed_covariance_that_lost_definiteness_is_flagged(parallel):
    """A rotation with Q = 1e-6, R = 3e-5 and P0 = 300 I in float32: the square-root filters are
    accurate (0.01 posterior standard deviations), but the smoother's P(k+1|T) - P(k+1|k) loses
    P(k|T), which came out indefinite (smallest eigenvalue -3.7e-5 where the float64 one's is
    3.1e-6) with status OK at every step. Every indefinite P(k|T) is now flagged."""
    c, s = np.cos(0.3), np.sin(0.3)
    cast = lambda a: jnp.asarray(a, jnp.float32)
    model = je.LinearGaussian(
        cast([[c, -s], [s, c]]), cast([[1.0, 0.5]]), cast(1e-6 * np.array([[1.0, 0.3], [0.3, 0.5]])),
        cast([[3e-5]]),
    )  # fmt: skip
    prior = je.Gaussian(cast(np.zeros(2)), cast(300.0 * np.eye(2)))
    ys = cast(np.random.default_rng(0).normal(size=(30, 1)))
    filt = je.ParallelKalmanFilter() if parallel else je.SquareRootKF()
    filtered = je.run(filt, model, ys, prior=prior)
    smoothed = je.rts_smooth(model, filtered, parallel=parallel)
    indefinite = np.linalg.eigvalsh(np.asarray(smoothed.cov, np.float64))[:, 0] <= 0
    flagged = (np.asarray(smoothed.status) & je.Status.NOT_POSITIVE_DEFINITE) != 0
    assert int(filtered.any_status) == 0 and np.any(indefinite)
    assert np.all(flagged[indefinite])


def precise_measurements(T=10_000):
    """A 4-state model with R = 10^-4 x SPD (P+ much smaller than P-), a prior, T measurements
    and the float64 sequential filter's log-likelihood."""
    rng = np.random.default_rng(2)
    F, H, Q, R = random_system(rng, 4, 2, stable=0.99)
    model = je.LinearGaussian(*map(jnp.asarray, (F, H, Q, R * 1e-4)))
    prior = je.Gaussian(jnp.zeros(4), jnp.eye(4) * 10.0)
    ys = je.simulate(model, prior, T, jax.random.PRNGKey(2)).y
    ref = je.run(je.KalmanFilter(), model, ys, prior=prior, save=je.SaveAt(fields=())).loglik
    return model, prior, ys, float(ref)


def test_float32_at_ten_thousand_steps():
    """float32 at T = 10^4: the square-root form is finite with its log-likelihood within 1e-3
    relative of float64 and status OK; the standard form, whose combined log-likelihood is a
    difference of large terms, loses digits in the combinations, and its status says so
    (LOGLIK_INCONSISTENT, eq (5)): its filtered means are off by per cents. Its total, the sum
    of the sequential update's terms (eq (6)), stays within 1e-3 (the combined one was +5.6e5
    for -3.2e4)."""
    model, prior, ys, ref = precise_measurements()
    save = je.SaveAt(fields=("mean", "cov", "status"))
    results = {
        square_root: je.run(je.ParallelKalmanFilter(square_root=square_root), je.astype(model, jnp.float32),
                            ys.astype(jnp.float32), prior=je.astype(prior, jnp.float32), save=save)
        for square_root in (True, False)
    }  # fmt: skip
    res = results[True]
    assert res.loglik.dtype == jnp.float32
    assert np.all(np.isfinite(res.mean)) and np.all(np.isfinite(res.cov))
    assert int(res.any_status) == 0
    assert abs(float(res.loglik) / ref - 1.0) < 1e-3
    standard = results[False]
    assert je.ParallelStatus.describe(standard.any_status) == "LOGLIK_INCONSISTENT"
    sequential = je.run(je.KalmanFilter(), model, ys, prior=prior, save=je.SaveAt(fields=("mean",)))
    scale = np.max(np.abs(sequential.mean))
    assert np.max(np.abs(standard.mean - sequential.mean)) > 1e-2 * scale  # what the flag is for
    assert abs(float(standard.loglik) / ref - 1.0) < 1e-3
    assert isinstance(standard, je.ParallelFilterResult)
    with pytest.raises(Exception, match="LOGLIK_INCONSISTENT"):
        je.run(je.ParallelKalmanFilter(square_root=False), je.astype(model, jnp.float32), ys.astype(jnp.float32),
               prior=je.astype(prior, jnp.float32), save=je.SaveAt(fields=()), throw=True)  # fmt: skip


@pytest.mark.parametrize("dtype", [jnp.float32])
def test_jit_vmap_grad_through_fit(dtype):
    """je.fit (jit, grad of a vmapped neg_loglik) with the parallel filter follows the same
    losses as with the sequential one. (float64: jit and grad in the gradient test above, vmap
    in the Monte Carlo test below.)"""
    model, prior, inputs, full, _ = problem()
    model, prior = je.astype((model, prior), dtype)
    batch, us = je.astype((jnp.stack([full[:8], full[8:16]]), jnp.stack([inputs[:8]] * 2)), dtype)
    losses = {}
    for filt in (je.ParallelKalmanFilter(), je.KalmanFilter()):
        loss = je.neg_loglik(filt, batch, prior=prior, inputs=us)
        fitted = je.fit(model, loss, ("R",), num_steps=3)
        assert fitted.losses.dtype == dtype and fitted.model.R.dtype == dtype
        losses[type(filt)] = fitted.losses
    assert_close(losses[je.ParallelKalmanFilter], losses[je.KalmanFilter],
                 1e-5 if dtype == jnp.float32 else 1e-9)  # fmt: skip


def test_resumes_and_runs_in_monte_carlo():
    model, prior, inputs, full, _ = problem()
    filt = je.ParallelKalmanFilter()
    whole = je.run(filt, model, full, prior=prior, inputs=inputs)
    head = je.run(filt, model, full[:25], prior=prior, inputs=inputs[:25])
    tail = je.run(filt, model, full[25:], state=head.final_state, k0=25, inputs=inputs[25:])
    assert_close(tail.loglik, whole.loglik)
    assert_close(tail.mean, whole.mean[25:])

    def one(key):
        ys = je.simulate(model, prior, 8, key, inputs=inputs[:8]).y
        seq = je.run(je.KalmanFilter(), model, ys, prior=prior, inputs=inputs[:8]).loglik
        return je.run(filt, model, ys, prior=prior, inputs=inputs[:8]).loglik - seq

    diffs = je.monte_carlo(one, jax.random.PRNGKey(0), 3)
    assert np.max(np.abs(diffs)) < 1e-9


def test_errors_name_the_argument():
    model, prior, _, full, _ = problem()
    nonlinear = je.NonlinearGaussian(lambda x: x, lambda x: x[:2], jnp.eye(4), jnp.eye(2))
    with pytest.raises(ValueError, match="model"):
        je.run(je.ParallelKalmanFilter(), nonlinear, full, prior=prior)
    plain = je.LinearGaussian(model.F, model.H, jnp.eye(4), model.R)
    singular = je.LinearGaussian(model.F, model.H, jnp.zeros((4, 4)), model.R)
    with pytest.raises(ValueError, match="Q"):
        je.run(je.ParallelKalmanFilter(), singular, full, prior=prior)
    with pytest.raises(ValueError, match="prior"):
        je.run(je.ParallelKalmanFilter(), plain, full, prior=None)
    lean = je.run(je.KalmanFilter(), plain, full, prior=prior, save=je.SaveAt(fields=("mean",)))
    with pytest.raises(ValueError, match="result"):
        je.rts_smooth(plain, lean, parallel=True)
    with pytest.raises(ValueError, match=r"^ys: has no steps"):  # an IndexError inside the scan
        je.run(je.ParallelKalmanFilter(), plain, full[:0], prior=prior)


def test_twenty_states_square_root_filter_and_parallel_smoother_finish():
    """n = 20 > SMALL_FACTOR: the square-root filter's batched QR and the smoother's batched
    Cholesky are LAPACK calls that jaxlib 0.10 on CPU deadlocked when run at once (hung at the
    first call before jaxest.linalg.after ordered them). Twenty calls in a subprocess that must
    finish, smoothing equal to the sequential RTS smoother's."""
    code = textwrap.dedent(
        """
        import jax, numpy as np
        jax.config.update("jax_enable_x64", True)
        import jaxest as je
        from jaxest.studies.parallel import random_model
        model, prior = random_model(20)
        ys = je.simulate(model, prior, 100, jax.random.PRNGKey(0)).y
        def smooth(m, p, y, parallel):
            result = je.run(je.ParallelKalmanFilter(), m, y, prior=p)
            return je.rts_smooth(m, result, parallel=parallel).mean
        parallel = jax.jit(lambda m, p, y: smooth(m, p, y, True))
        for _ in range(20):
            means = jax.block_until_ready(parallel(model, prior, ys))
        np.testing.assert_allclose(means, smooth(model, prior, ys, False), rtol=1e-9, atol=1e-12)
        """
    )
    subprocess.run([sys.executable, "-c", code], timeout=240, check=True)


def test_study_speed_grid_rows_figure_and_crossover(tmp_path):
    """The study's speed grid at its smallest size: every method finite, status OK and close to
    the float64 sequential log-likelihood, and a figure written."""
    from jaxest.studies import parallel as study

    rows = study.speed_grid(states=(4,), lengths=(100,), dtypes=("float64", "float32"))
    assert [(r["dtype"], r["method"]) for r in rows] == [
        (dtype, method) for dtype in ("float64", "float32") for method in study.METHODS
    ]
    for r in rows:
        assert r["finite"] and r["status"] == "OK" and r["compile_s"] > 0 and r["run_s"] > 0
        assert r["loglik_rel_diff"] < (1e-12 if r["dtype"] == "float64" else 1e-5)
    assert study.speed_figure(rows, tmp_path / "speed.png").stat().st_size > 10_000
    assert len(study.crossover(rows)) == 4  # two dtypes, two parallel forms


def test_study_crossover_is_the_first_length_where_parallel_is_faster():
    def row(T, method, run_s):
        return {"n": 4, "T": T, "dtype": "float64", "method": method, "run_s": run_s}

    rows = [row(100, "sequential", 1.0), row(100, "parallel_sqrt", 3.0),
            row(100, "parallel_standard", 2.0), row(1000, "sequential", 10.0),
            row(1000, "parallel_sqrt", 5.0), row(1000, "parallel_standard", 20.0)]  # fmt: skip
    from jaxest.studies.parallel import crossover

    assert crossover(rows) == [
        {"n": 4, "dtype": "float64", "method": "parallel_sqrt", "crossover_T": 1000,
         "min_ratio": 0.5, "max_ratio": 3.0},
        {"n": 4, "dtype": "float64", "method": "parallel_standard", "crossover_T": None,
         "min_ratio": 2.0, "max_ratio": 2.0},
    ]  # fmt: skip
