"""The iterated extended Kalman smoother: exact for linear models, its fixed point the minimiser
of the negative log-posterior (checked against scipy's), parallel = sequential with missing
data, jit/vmap/grad in float64 and float32 (gradient against central differences), and
argument errors."""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize

import jaxest as je
from tests.test_parallel import assert_close, problem

DT = 0.05


def pendulum_model(dtype=jnp.float64, r_scale=1.0):
    """The pendulum of Särkkä's book (Bayesian Filtering and Smoothing, Example 5.1):
    x = [angle, rate], Euler-discretised, measurement sin(angle)."""

    def f(x):
        return jnp.stack([x[0] + x[1] * DT, x[1] - 9.81 * jnp.sin(x[0]) * DT])

    Q = 0.5 * jnp.array([[DT**3 / 3, DT**2 / 2], [DT**2 / 2, DT]], dtype)
    R = r_scale * jnp.array([[0.1**2]], dtype)
    return je.NonlinearGaussian(f, lambda x: jnp.sin(x[:1]), Q, R)


@functools.cache
def pendulum(T=100, seed=0):
    """The model, its prior, measurements (y_10 and y_11 missing) and the EKF + RTS means."""
    model = pendulum_model()
    prior = je.Gaussian(jnp.array([1.2, 0.0]), 0.1 * jnp.eye(2))
    ys = np.array(je.simulate(model, prior, T, jax.random.PRNGKey(seed)).y)
    ys[10:12] = np.nan
    ys = jnp.asarray(ys)
    eks = je.rts_smooth(model, je.run(je.EKF(), model, ys, prior=prior)).mean
    return model, prior, ys, eks


def neg_log_posterior(model, prior, ys):
    """Eq (2) of jaxest.smoothers.iterated for additive noise, written out (NaN rows left out)."""
    Q_inv, R_inv, P0_inv = (np.linalg.inv(a) for a in (model.Q, model.R, prior.cov))
    observed = jnp.asarray(~np.isnan(np.asarray(ys)))
    y = jnp.where(observed, ys, 0.0)

    def J(flat):
        x = flat.reshape(ys.shape[0], -1)
        d0 = x[0] - prior.mean
        w = x[1:] - jax.vmap(model.f)(x[:-1])
        v = jnp.where(observed, y - jax.vmap(model.h)(x), 0.0)
        return 0.5 * (
            d0 @ P0_inv @ d0
            + jnp.einsum("ki,ij,kj->", w, Q_inv, w)
            + jnp.einsum("ki,ij,kj->", v, R_inv, v)
        )

    return J


@pytest.mark.parametrize("parallel", [True, False], ids=["parallel", "sequential"])
def test_linear_model_one_iteration_is_the_rts_smoother(parallel):
    """Linearising a linear model changes nothing: one iteration is the Kalman filter and RTS
    smoother (rank-deficient noise gain, inputs, missing data)."""
    model, prior, inputs, _, ys = problem()
    rts = je.rts_smooth(model, je.run(je.KalmanFilter(), model, ys, prior=prior, inputs=inputs),
                        inputs=inputs)  # fmt: skip
    res = je.iterated_smooth(model, ys, prior=prior, inputs=inputs, num_iters=2, parallel=parallel)
    assert_close(res.mean, rts.mean)
    assert_close(res.cov, rts.cov)
    assert_close(res.smoothed.cross_cov, rts.cross_cov)
    assert bool(res.ok) and float(res.changes[1]) < 1e-9


def test_fixed_point_is_scipys_map_trajectory():
    """From the EKF + RTS means, the iterations converge to the minimiser of the negative
    log-posterior that scipy's L-BFGS finds from the same start; there its gradient vanishes."""
    model, prior, ys, eks = pendulum()
    res = je.iterated_smooth(model, ys, prior=prior, num_iters=25, initial=eks)
    assert bool(res.ok)
    assert float(res.changes[-1]) < 1e-9 < float(res.changes[0])
    J = jax.jit(neg_log_posterior(model, prior, ys))
    value_and_grad = jax.jit(jax.value_and_grad(J))
    grad = lambda x: value_and_grad(x)[1]
    fun = lambda x: jax.tree.map(np.asarray, value_and_grad(jnp.asarray(x)))
    opt = scipy.optimize.minimize(fun, np.asarray(eks).ravel(), jac=True, method="L-BFGS-B",
                                  options={"gtol": 1e-10, "ftol": 1e-15, "maxiter": 5000})  # fmt: skip
    sd = np.sqrt(np.diagonal(np.asarray(res.cov), axis1=1, axis2=2))
    assert np.max(np.abs(opt.x.reshape(eks.shape) - res.mean) / sd) < 1e-4
    assert float(J(res.mean.ravel())) <= opt.fun + 1e-9 * abs(opt.fun)
    g_start, g_end = (np.max(np.abs(grad(x.ravel()))) for x in (eks, res.mean))
    assert g_end < 1e-8 * g_start


def test_parallel_equals_sequential_with_missing_data():
    model, prior, ys, eks = pendulum()
    runs = [je.iterated_smooth(model, ys, prior=prior, num_iters=6, initial=eks, parallel=p)
            for p in (True, False)]  # fmt: skip
    for field in ("mean", "cov"):
        assert_close(getattr(runs[0], field), getattr(runs[1], field))
    assert_close(runs[0].loglik, runs[1].loglik)
    assert_close(runs[0].changes, runs[1].changes)


def test_jit_vmap_grad_in_float64_and_float32():
    """A batch of three runs under vmap in float32 matches float64; the gradient of log p(y)
    of the last linearisation in the measurement variance matches central differences."""
    model, prior = pendulum_model(), je.Gaussian(jnp.array([0.6, 0.0]), 0.1 * jnp.eye(2))
    ys = je.monte_carlo(lambda k: je.simulate(model, prior, 60, k), jax.random.PRNGKey(3), 3).y

    def smooth(model, prior, ys):
        return je.iterated_smooth(model, ys, prior=prior, num_iters=8)

    batch = eqx.filter_jit(eqx.filter_vmap(smooth, in_axes=(None, None, 0)))
    f64 = batch(model, prior, ys)
    f32 = batch(pendulum_model(jnp.float32),
                *je.astype((prior, ys), jnp.float32))  # fmt: skip
    assert f32.mean.dtype == jnp.float32 and bool(jnp.all(f32.ok))
    sd = jnp.sqrt(jnp.diagonal(f64.cov, axis1=-2, axis2=-1))
    assert float(jnp.max(jnp.abs(f32.mean - f64.mean) / sd)) < 1e-3

    loglik = lambda scale: smooth(pendulum_model(r_scale=scale), prior, ys[0]).loglik
    grad = jax.jit(jax.grad(loglik))(1.0)
    h = 1e-5
    central = (loglik(1.0 + h) - loglik(1.0 - h)) / (2 * h)
    np.testing.assert_allclose(grad, central, rtol=1e-6)


def test_argument_errors():
    model, prior, ys, eks = pendulum()
    with pytest.raises(ValueError, match="num_iters"):
        je.iterated_smooth(model, ys, prior=prior, num_iters=0)
    with pytest.raises(ValueError, match="initial"):
        je.iterated_smooth(model, ys, prior=prior, initial=eks[:-1])
    with pytest.raises(ValueError, match="initial"):
        je.iterated_smooth(model, ys, prior=prior, initial=eks.at[3, 0].set(jnp.inf))
    with pytest.raises(ValueError, match="ys"):
        je.iterated_smooth(model, ys[:, None], prior=prior)
    with pytest.raises(ValueError, match="prior"):
        je.iterated_smooth(model, ys, prior=(prior.mean, prior.cov))
    singular_Q = eqx.tree_at(lambda m: m.Q, model, jnp.zeros_like(model.Q))
    with pytest.raises(ValueError, match="factors Q: .*, or pass parallel=False$"):
        je.iterated_smooth(singular_Q, ys, prior=prior)  # it advised filters it does not take
    with pytest.raises(ValueError, match="^ys: has no steps"):  # a TypeError from the trace
        je.iterated_smooth(model, ys[:0], prior=prior)
