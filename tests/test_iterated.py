"""The iterated EKF against the EKF / Kalman filter (one iteration) and an independent NumPy
Gauss-Newton / Levenberg-Marquardt implementation (normal equations, not the Kalman form)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxest as je
from tests.gradients import check_grad_float64_and_float32

DT, T = 0.1, 20


def range_f(x):
    return jnp.stack([x[0] + DT * x[2], x[1] + DT * x[3], x[2], 0.98 * x[3]])


def range_h(x):
    """Range and bearing from the origin: strongly nonlinear near it."""
    return jnp.stack([jnp.sqrt(x[0] ** 2 + x[1] ** 2), jnp.arctan2(x[1], x[0])])


def tracking(dtype=jnp.float64):
    model = je.NonlinearGaussian(
        range_f, range_h, 0.01 * jnp.eye(4), jnp.diag(jnp.array([0.05, 0.002]))
    )
    prior = je.Gaussian(jnp.array([1.0, 1.0, 0.2, -0.1]), jnp.diag(jnp.array([0.5, 0.5, 0.1, 0.1])))
    ys = je.simulate(model, jnp.array([1.3, 0.7, 0.3, -0.2]), T, jax.random.key(3)).y
    ys = ys.at[6, 1].set(jnp.nan)
    cast = lambda a: a.astype(dtype) if isinstance(a, jax.Array) else a  # noqa: E731
    return jax.tree.map(cast, (model, prior, ys))


def numpy_h(x):
    return np.array([np.hypot(x[0], x[1]), np.arctan2(x[1], x[0])])


def numpy_jacobian_h(x):
    r2 = x[0] ** 2 + x[1] ** 2
    r = np.sqrt(r2)
    return np.array([[x[0] / r, x[1] / r, 0, 0], [-x[1] / r2, x[0] / r2, 0, 0]])


def numpy_iekf(model, prior, ys, iterations, damping):
    """Gauss-Newton / Levenberg-Marquardt on J(x) in normal-equation form:
    x <- x + (H^T R^-1 H + P^-1 + lambda I)^-1 (H^T R^-1 (y - h(x)) - P^-1 (x - x-))."""
    F = np.eye(4) + DT * np.eye(4, k=2)
    F[3, 3] = 0.98
    Q, R_full = np.asarray(model.Q), np.asarray(model.R)
    x_prior, P = np.array(prior.mean), np.array(prior.cov)
    means, covs, logliks = [], [], []
    for y in np.asarray(ys):
        obs = ~np.isnan(y)
        R = R_full[np.ix_(obs, obs)]
        P_inv = np.linalg.inv(P)
        H0 = numpy_jacobian_h(x_prior)[obs]
        S0 = H0 @ P @ H0.T + R
        e0 = y[obs] - numpy_h(x_prior)[obs]
        logliks.append(
            -0.5 * (obs.sum() * np.log(2 * np.pi) + np.linalg.slogdet(S0)[1])
            - 0.5 * e0 @ np.linalg.solve(S0, e0)
        )
        x = x_lin = x_prior.copy()
        for _ in range(iterations):
            x_lin = x
            H = numpy_jacobian_h(x)[obs]
            A = H.T @ np.linalg.solve(R, H) + P_inv + damping * np.eye(4)
            g = H.T @ np.linalg.solve(R, y[obs] - numpy_h(x)[obs]) - P_inv @ (x - x_prior)
            x = x + np.linalg.solve(A, g)
        H = numpy_jacobian_h(x_lin)[obs]
        S = H @ P @ H.T + R
        K = P @ H.T @ np.linalg.inv(S)
        P_post = P - K @ S @ K.T
        means.append(x)
        covs.append(P_post)
        x_prior, P = F @ x, F @ P_post @ F.T + Q
    return np.array(means), np.array(covs), np.array(logliks)


@pytest.mark.parametrize("iterations, damping", [(4, 0.0), (3, 2.0)])
def test_iterations_equal_numpy_gauss_newton(iterations, damping):
    model, prior, ys = tracking()
    result = je.run(je.IteratedEKF(iterations=iterations, damping=damping), model, ys, prior=prior)
    means, covs, logliks = numpy_iekf(model, prior, ys, iterations, damping)
    np.testing.assert_allclose(result.mean, means, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(result.cov, covs, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(result.loglik_terms, logliks, rtol=1e-9)
    ekf = je.run(je.EKF(), model, ys, prior=prior)
    assert float(jnp.max(jnp.abs(result.mean - ekf.mean))) > 1e-4  # the iterations matter


def test_one_iteration_is_the_ekf():
    model, prior, ys = tracking()
    result = je.run(je.IteratedEKF(iterations=1), model, ys, prior=prior)
    for Reference in (je.KalmanFilter, je.EKF):
        ref = je.run(Reference(), model, ys, prior=prior)
        for name in ("mean", "cov", "predicted_mean", "predicted_cov", "innovation",
                     "innovation_cov", "loglik_terms"):  # fmt: skip
            np.testing.assert_allclose(
                getattr(result, name), getattr(ref, name), rtol=1e-9, atol=1e-12, err_msg=name
            )


def test_linear_model_undamped_iterations_are_the_kalman_filter():
    """Gauss-Newton is exact for linear h after one step; later steps stay there."""
    rng = np.random.default_rng(1)
    model = je.LinearGaussian(
        F=jnp.asarray(0.5 * rng.normal(size=(3, 3))), H=jnp.asarray(rng.normal(size=(2, 3))),
        Q=0.1 * jnp.eye(3), R=0.2 * jnp.eye(2),
    )  # fmt: skip
    prior = je.Gaussian(jnp.zeros(3), jnp.eye(3))
    ys = je.simulate(model, jnp.zeros(3), T, jax.random.key(0)).y
    ref = je.run(je.KalmanFilter(), model, ys, prior=prior)
    result = je.run(je.IteratedEKF(iterations=3), model, ys, prior=prior)
    np.testing.assert_allclose(result.mean, ref.mean, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(result.cov, ref.cov, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(result.loglik, ref.loglik, rtol=1e-9)


@pytest.mark.parametrize("damping", [0.0, 1.0])
def test_jit_vmap_grad_float64_and_float32(damping):
    """Finite-difference gradient in float64; float32 under jit and vmap follows float64."""
    check_grad_float64_and_float32(je.IteratedEKF(iterations=3, damping=damping), tracking)


@pytest.mark.parametrize(
    "kwargs, argument",
    [({"iterations": 0}, "iterations"), ({"iterations": 2.0}, "iterations"),
     ({"damping": -1.0}, "damping"), ({"damping": float("nan")}, "damping")],
)  # fmt: skip
def test_bad_arguments_name_the_argument(kwargs, argument):
    with pytest.raises(ValueError, match=f"^{argument}:"):
        je.IteratedEKF(**kwargs)
