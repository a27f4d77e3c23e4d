"""Sigma-point filters (UKF, CubatureKF, GaussHermiteKF in covariance, sqrt and SVD forms, additive
and augmented noise) against filterpy, the Kalman filter, a plain-NumPy sigma-point filter and
finite differences."""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

import jaxest as je
from jaxest.filters.sigma_points import CubaturePoints, GaussHermitePoints, UnscentedPoints
from tests.gradients import check_grad_float64_and_float32

DT, GRAVITY, T = 0.1, 9.81, 25
FORMS = ("covariance", "sqrt", "svd")
POINT_SETS = {
    "UKF": je.UKF,
    "UKF-alpha0.5": functools.partial(je.UKF, alpha=0.5),  # negative Wc_0: Cholesky downdates
    "CKF": je.CubatureKF,
    "GHKF3": functools.partial(je.GaussHermiteKF, order=3),
}


def pendulum_f(x):
    return jnp.stack([x[0] + DT * x[1], x[1] - GRAVITY * DT * jnp.sin(x[0])])


def pendulum_h(x):
    return jnp.stack([jnp.sin(x[0]), 0.5 * x[1] ** 2])


def pendulum(dtype=jnp.float64):
    """The pendulum, its prior and measurements (simulated in float64, then cast)."""
    if dtype != jnp.float64:
        model, prior, ys = pendulum()
        cast = lambda a: a.astype(dtype) if isinstance(a, jax.Array) else a  # noqa: E731
        return jax.tree.map(cast, (model, prior, ys))
    Q = jnp.array([[DT**3 / 3, DT**2 / 2], [DT**2 / 2, DT]], dtype) * 0.5
    R = jnp.array([[0.05, 0.01], [0.01, 0.08]], dtype)
    model = je.NonlinearGaussian(pendulum_f, pendulum_h, Q, R)
    prior = je.Gaussian(jnp.array([1.0, 0.0], dtype), jnp.diag(jnp.array([0.3, 0.5], dtype)))
    ys = je.simulate(model, jnp.array([1.2, 0.0], dtype), T, jax.random.key(1)).y
    return model, prior, ys.at[4, 1].set(jnp.nan)


def random_linear(dtype=jnp.float64, n=3, m=2):
    rng = np.random.default_rng(0)
    A, B = rng.normal(size=(n, n)), rng.normal(size=(m, m))
    model = je.LinearGaussian(
        F=jnp.asarray(0.4 * rng.normal(size=(n, n)), dtype),
        H=jnp.asarray(rng.normal(size=(m, n)), dtype),
        Q=jnp.asarray(A @ A.T / n + 0.1 * np.eye(n), dtype),
        R=jnp.asarray(B @ B.T / m + 0.2 * np.eye(m), dtype),
    )
    prior = je.Gaussian(jnp.zeros(n, dtype), jnp.eye(n, dtype=dtype))
    ys = je.simulate(model, jnp.zeros(n, dtype), T, jax.random.key(0)).y
    return model, prior, ys.at[3, 0].set(jnp.nan)


FIELDS = ("predicted_mean", "predicted_cov", "mean", "cov", "innovation", "innovation_cov")


def assert_results_close(result, reference, rtol):
    for name in FIELDS + ("loglik_terms",):
        np.testing.assert_allclose(
            getattr(result, name), getattr(reference, name), rtol=rtol, atol=rtol, err_msg=name
        )


# ---------------------------------------------------------------------------------------------
# filterpy


def filterpy_ukf(model, prior, ys, fx, hx, alpha, beta, kappa):
    """filterpy's UKF with the measurement-update points redrawn from the predicted x, P."""
    n, m = prior.mean.shape[0], ys.shape[1]
    points = MerweScaledSigmaPoints(n, alpha=alpha, beta=beta, kappa=kappa)
    ukf = UnscentedKalmanFilter(n, m, DT, hx=hx, fx=lambda x, dt: fx(x), points=points)
    ukf.x, ukf.P = np.array(prior.mean), np.array(prior.cov)
    ukf.Q, ukf.R = np.array(model.Q), np.array(model.R)
    out = {name: [] for name in FIELDS + ("loglik_terms",)}
    for y in np.asarray(ys):
        out["predicted_mean"].append(ukf.x.copy())
        out["predicted_cov"].append(ukf.P.copy())
        ukf.sigmas_f = ukf.points_fn.sigma_points(ukf.x, ukf.P)
        ukf.update(y)
        out["mean"].append(ukf.x.copy())
        out["cov"].append(ukf.P.copy())
        out["innovation"].append(ukf.y.copy())
        out["innovation_cov"].append(ukf.S.copy())
        out["loglik_terms"].append(ukf.log_likelihood)
        ukf.predict()
    return type("FilterpyResult", (), {k: np.array(v) for k, v in out.items()})


@pytest.mark.parametrize("alpha, beta, kappa", [(1.0, 2.0, 0.0), (0.5, 2.0, 1.0)])
def test_ukf_equals_filterpy_on_pendulum(alpha, beta, kappa):
    model, prior, ys = pendulum()
    ys = ys.at[4, 1].set(0.1)  # filterpy has no missing data
    ref = filterpy_ukf(
        model, prior, ys, lambda x: np.asarray(pendulum_f(jnp.asarray(x))),
        lambda x: np.asarray(pendulum_h(jnp.asarray(x))), alpha, beta, kappa,
    )  # fmt: skip
    result = je.run(je.UKF(alpha=alpha, beta=beta, kappa=kappa), model, ys, prior=prior)
    assert_results_close(result, ref, rtol=1e-9)


def test_ukf_equals_filterpy_on_random_linear_system():
    model, prior, ys = random_linear()
    ys = ys.at[3, 0].set(0.3)
    F, H = np.asarray(model.F), np.asarray(model.H)
    ref = filterpy_ukf(model, prior, ys, lambda x: F @ x, lambda x: H @ x, 0.5, 2.0, 0.0)
    result = je.run(je.UKF(alpha=0.5), model, ys, prior=prior)
    assert_results_close(result, ref, rtol=1e-9)


# ---------------------------------------------------------------------------------------------
# Linear systems: every point set, form and noise mode is the Kalman filter


@pytest.mark.parametrize("noise", ["additive", "augmented"])
@pytest.mark.parametrize("form", FORMS)
@pytest.mark.parametrize("name", ["UKF-alpha0.5", "CKF", "GHKF3"])
def test_linear_system_equals_kalman_filter(name, form, noise):
    model, prior, ys = random_linear()
    ref = je.run(je.KalmanFilter(), model, ys, prior=prior)
    result = je.run(POINT_SETS[name](form=form, noise=noise), model, ys, prior=prior)
    assert_results_close(result, ref, rtol=1e-9)
    np.testing.assert_allclose(result.loglik, ref.loglik, rtol=1e-9)
    assert int(result.any_status) == 0


# ---------------------------------------------------------------------------------------------
# Nonlinear: forms against one another and against an independent NumPy filter


@pytest.mark.parametrize(
    "name, noise",
    [("UKF-alpha0.5", "additive"), ("UKF-alpha0.5", "augmented"), ("CKF", "augmented"),
     ("GHKF3", "additive")],
)  # fmt: skip
def test_sqrt_form_equals_covariance_form_on_pendulum(name, noise):
    model, prior, ys = pendulum()
    ref = je.run(POINT_SETS[name](noise=noise), model, ys, prior=prior)
    result = je.run(POINT_SETS[name](form="sqrt", noise=noise), model, ys, prior=prior)
    assert_results_close(result, ref, rtol=1e-9)


def numpy_sigma_point_filter(points, sqrt, f, h, Q, R, prior, ys):
    """Plain-NumPy additive-noise sigma-point filter (eqs 1-5 of jaxest.filters.sigma_point)
    with the matrix square root ``sqrt``; missing (NaN) entries dropped from y, yhat and S."""
    x, P = np.array(prior.mean), np.array(prior.cov)
    xi, Wm, Wc = points.unit_points(x.shape[0])
    out = {name: [] for name in FIELDS + ("loglik_terms",)}
    for y in np.asarray(ys):
        out["predicted_mean"].append(x)
        out["predicted_cov"].append(P)
        X = x + xi @ sqrt(P).T
        Y = np.array([h(s) for s in X])
        yhat = Wm @ Y
        obs = ~np.isnan(y)
        dX, dY = X - Wm @ X, (Y - yhat)[:, obs]
        S = dY.T @ (Wc[:, None] * dY) + R[np.ix_(obs, obs)]
        K = dX.T @ (Wc[:, None] * dY) @ np.linalg.inv(S)
        e = y[obs] - yhat[obs]
        x, P = x + K @ e, P - K @ S @ K.T
        e_full, S_full = np.zeros_like(y), np.eye(y.shape[0])
        e_full[obs], S_full[np.ix_(obs, obs)] = e, S
        loglik = -0.5 * (obs.sum() * np.log(2 * np.pi) + np.linalg.slogdet(S)[1])
        out["loglik_terms"].append(loglik - 0.5 * e @ np.linalg.solve(S, e))
        out["mean"].append(x)
        out["cov"].append(P)
        out["innovation"].append(e_full)
        out["innovation_cov"].append(S_full)
        FX = np.array([f(s) for s in x + xi @ sqrt(P).T])
        x = Wm @ FX
        P = (FX - x).T @ (Wc[:, None] * (FX - x)) + Q
    return type("NumpyResult", (), {k: np.array(v) for k, v in out.items()})


def numpy_pendulum(points, sqrt):
    model, prior, ys = pendulum()
    f = lambda x: np.asarray(pendulum_f(jnp.asarray(x)))  # noqa: E731
    h = lambda x: np.asarray(pendulum_h(jnp.asarray(x)))  # noqa: E731
    return numpy_sigma_point_filter(
        points, sqrt, f, h, np.asarray(model.Q), np.asarray(model.R), prior, ys
    )


@pytest.mark.parametrize(
    "name, points",
    [("UKF-alpha0.5", UnscentedPoints(0.5, 2.0, 0.0)), ("GHKF3", GaussHermitePoints(3))],
)
@pytest.mark.parametrize("form", ["covariance", "svd"])
def test_nonlinear_equals_numpy_reference(name, points, form):
    """Both forms draw their points with chol(P) (the SVD form through the QR of (U D)^T): each
    equals the NumPy filter with Cholesky points, including a missing entry."""
    model, prior, ys = pendulum()
    ref = numpy_pendulum(points, np.linalg.cholesky)
    result = je.run(POINT_SETS[name](form=form), model, ys, prior=prior)
    assert_results_close(result, ref, rtol=1e-9)


@pytest.mark.parametrize("name", ["UKF-alpha0.5", "CKF", "GHKF3"])
def test_svd_form_is_the_covariance_form_on_a_nonlinear_model(name):
    """Same points, other arithmetic: on the pendulum (nonlinear) the SVD form's means and
    covariances equal the covariance form's to rounding, not only on linear models."""
    model, prior, ys = pendulum()
    assert_results_close(
        je.run(POINT_SETS[name](form="svd"), model, ys, prior=prior),
        je.run(POINT_SETS[name](), model, ys, prior=prior),
        rtol=1e-9,
    )


def test_cubature_equals_ukf_alpha1_beta0_kappa0():
    model, prior, ys = pendulum()
    ref = je.run(je.UKF(alpha=1.0, beta=0.0, kappa=0.0), model, ys, prior=prior)
    for form in FORMS:
        assert_results_close(
            je.run(je.CubatureKF(form=form), model, ys, prior=prior),
            je.run(je.UKF(alpha=1.0, beta=0.0, kappa=0.0, form=form), model, ys, prior=prior),
            rtol=1e-12,
        )
    assert_results_close(je.run(je.CubatureKF(), model, ys, prior=prior), ref, rtol=1e-12)


def test_point_sets_are_exact_to_second_order():
    for points, n in [
        (UnscentedPoints(0.3, 2.0, 1.0), 4), (CubaturePoints(), 3), (GaussHermitePoints(4), 2)
    ]:  # fmt: skip
        xi, Wm, Wc = points.unit_points(n)
        np.testing.assert_allclose(Wm.sum(), 1.0, rtol=1e-14)
        np.testing.assert_allclose(Wm @ xi, np.zeros(n), atol=1e-14)
        np.testing.assert_allclose(xi.T @ (Wc[:, None] * xi), np.eye(n), atol=1e-13)
    xi, W, _ = GaussHermitePoints(3).unit_points(1)  # E x^4 = 3
    np.testing.assert_allclose(W @ xi[:, 0] ** 4, 3.0, rtol=1e-13)


# ---------------------------------------------------------------------------------------------
# jit, vmap, grad in float64 and float32; finite gradients at repeated eigenvalues


@pytest.mark.parametrize(
    "name, form, noise",
    [("UKF-alpha0.5", "covariance", "additive"), ("UKF-alpha0.5", "sqrt", "additive"),
     ("UKF-alpha0.5", "svd", "augmented"), ("CKF", "svd", "additive"),
     ("GHKF3", "sqrt", "augmented")],
)  # fmt: skip
def test_jit_vmap_grad_float64_and_float32(name, form, noise):
    """Finite-difference gradient in float64; float32 under jit and vmap follows float64."""
    check_grad_float64_and_float32(POINT_SETS[name](form=form, noise=noise), pendulum)


@pytest.mark.parametrize("name", ["UKF-alpha0.5", "GHKF3"])
def test_svd_form_gradient_finite_at_repeated_eigenvalues(name):
    """P0 = I and Q = q I (repeated eigenvalues): the SVD form's gradient with respect to q is
    finite and equals the covariance form's on a linear model, and the finite difference on the
    pendulum."""
    import equinox as eqx

    model, _, ys = random_linear()
    model = eqx.tree_at(lambda m: m.Q, model, jnp.eye(3))
    prior = je.Gaussian(jnp.zeros(3), jnp.eye(3))

    def loss(filt, model, q):
        return je.run(filt, eqx.tree_at(lambda m: m.Q, model, q * model.Q), ys, prior=prior).loglik

    g_svd = jax.jit(jax.grad(functools.partial(loss, POINT_SETS[name](form="svd"), model)))(0.5)
    g_cov = jax.jit(jax.grad(functools.partial(loss, POINT_SETS[name](), model)))(0.5)
    np.testing.assert_allclose(g_svd, g_cov, rtol=1e-9)

    pend, _, ys = pendulum()
    pend = eqx.tree_at(lambda m: m.Q, pend, 0.01 * jnp.eye(2))
    prior = je.Gaussian(jnp.array([1.0, 0.0]), jnp.eye(2))
    svd_loss = jax.jit(functools.partial(loss, POINT_SETS[name](form="svd"), pend))
    grad = jax.grad(svd_loss)(1.0)
    fd = (svd_loss(1.0 + 1e-5) - svd_loss(1.0 - 1e-5)) / 2e-5
    assert np.isfinite(grad)
    np.testing.assert_allclose(grad, fd, rtol=1e-6)


# ---------------------------------------------------------------------------------------------
# status and argument checks


def test_nonfinite_measurement_sets_status():
    """Inside jit the checks cannot see +-inf in ys; the step's status says NONFINITE."""
    model, prior, ys = pendulum()
    for form in FORMS:
        run = jax.jit(lambda ys, form=form: je.run(je.UKF(form=form), model, ys, prior=prior))
        result = run(ys.at[5, 0].set(jnp.inf))
        assert int(result.status[5]) & je.Status.NONFINITE
        assert int(result.status[4]) == 0


@pytest.mark.parametrize("form", FORMS)
def test_lost_definiteness_sets_status(form):
    """beta = -1 with alpha = 0.3 makes Wc_0 so negative that the sigma-point S of h(x) = x^4
    is negative: every form flags NOT_POSITIVE_DEFINITE instead of returning a silent NaN."""
    model = je.NonlinearGaussian(lambda x: x, lambda x: x**4, 0.01 * jnp.eye(1), 1e-3 * jnp.eye(1))
    prior = je.Gaussian(jnp.zeros(1), jnp.eye(1))
    result = je.run(je.UKF(alpha=0.3, beta=-1.0, form=form), model, jnp.ones((3, 1)), prior=prior)
    assert int(result.status[0]) & je.Status.NOT_POSITIVE_DEFINITE


@pytest.mark.parametrize(
    "make, argument",
    [
        (lambda: je.UKF(alpha=0.0), "alpha"),
        (lambda: je.UKF(alpha=-1.0), "alpha"),
        (lambda: je.UKF(beta=float("nan")), "beta"),
        (lambda: je.UKF(form="cholesky"), "form"),
        (lambda: je.CubatureKF(noise="multiplicative"), "noise"),
        (lambda: je.GaussHermiteKF(order=0), "order"),
        (lambda: je.GaussHermiteKF(order=1), "order"),
        (lambda: je.GaussHermiteKF(order=2.5), "order"),
    ],
)
def test_bad_arguments_name_the_argument(make, argument):
    with pytest.raises(ValueError, match=f"^{argument}:"):
        make()


def test_kappa_checked_against_dimension_before_tracing():
    model, prior, ys = pendulum()
    with pytest.raises(ValueError, match="^kappa:"):
        je.run(je.UKF(kappa=-2.0), model, ys, prior=prior)


def test_sqrt_form_requires_positive_definite_Q():
    import equinox as eqx

    model, prior, ys = pendulum()
    singular = eqx.tree_at(lambda m: m.Q, model, jnp.zeros((2, 2)))
    with pytest.raises(ValueError, match="Q"):
        je.run(je.UKF(form="sqrt"), singular, ys, prior=prior)
    assert int(je.run(je.UKF(form="svd"), singular, ys, prior=prior).any_status) == 0


# ---------------------------------------------------------------------------------------------
# sigma-point RTS smoother


@pytest.mark.parametrize(
    "filt",
    [je.UKF(alpha=0.5), je.UKF(alpha=0.5, form="sqrt", noise="augmented"),
     je.CubatureKF(form="svd"), je.GaussHermiteKF(order=3, form="svd", noise="augmented")],
    ids=lambda f: f"{type(f).__name__}-{f.form}-{f.noise}",
)  # fmt: skip
def test_sigma_point_rts_equals_rts_on_linear_model(filt):
    model, prior, ys = random_linear()
    ref = je.rts_smooth(model, je.run(je.KalmanFilter(), model, ys, prior=prior))
    smoothed = je.sigma_point_rts_smooth(model, je.run(filt, model, ys, prior=prior), filt)
    np.testing.assert_allclose(smoothed.mean, ref.mean, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(smoothed.cov, ref.cov, rtol=1e-9, atol=1e-12)
    assert bool(smoothed.ok)


def test_smoothers_read_a_time_varying_model_from_k0():
    """A run resumed at k0 = 3 on a model with a time axis on F: every RTS smoother given that k0
    equals the same smoother on the model cut at step 3 from k0 = 0 (they read F_0, F_1, ...
    whatever the run's k0, and had no k0); a k0 past the time axis is refused."""
    model, prior, ys = random_linear()
    T = ys.shape[0]
    scales = np.linspace(0.7, 1.1, T + 3)[:, None, None]
    varying = eqx.tree_at(lambda m: m.F, model, jnp.asarray(scales * np.asarray(model.F)))
    cut = eqx.tree_at(lambda m: m.F, model, varying.F[3:])
    for filt, smooth in (
        (je.KalmanFilter(), je.rts_smooth),
        (je.KalmanFilter(), lambda *a, **k: je.rts_smooth(*a, **k, parallel=True)),
        (je.UKF(alpha=0.5), lambda m, r, **k: je.sigma_point_rts_smooth(m, r, je.UKF(alpha=0.5), **k)),
    ):  # fmt: skip
        resumed = smooth(varying, je.run(filt, varying, ys, prior=prior, k0=3), k0=3)
        reference = smooth(cut, je.run(filt, cut, ys, prior=prior))
        np.testing.assert_allclose(resumed.mean, reference.mean, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(resumed.cov, reference.cov, rtol=1e-12, atol=1e-14)
    result = je.run(je.KalmanFilter(), varying, ys, prior=prior, k0=3)
    with pytest.raises(ValueError, match="^model.F: time-varying with"):
        je.rts_smooth(varying, result, k0=4)
    with pytest.raises(ValueError, match="^k0: expected a non-negative integer"):
        je.rts_smooth(varying, result, k0=-1)


def numpy_urts(points, f, Q, filtered):
    """Plain-NumPy unscented RTS smoother (Särkkä 2008, eqs 15-17) with Cholesky points."""
    means, covs = [filtered.mean[-1]], [filtered.cov[-1]]
    xi, Wm, Wc = points.unit_points(filtered.mean.shape[1])
    for m, P in zip(filtered.mean[-2::-1], filtered.cov[-2::-1], strict=True):
        X = m + xi @ np.linalg.cholesky(P).T
        FX = np.array([f(s) for s in X])
        m_pred = Wm @ FX
        P_pred = (FX - m_pred).T @ (Wc[:, None] * (FX - m_pred)) + Q
        D = (X - m).T @ (Wc[:, None] * (FX - m_pred))
        C = D @ np.linalg.inv(P_pred)
        means.append(m + C @ (means[-1] - m_pred))
        covs.append(P + C @ (covs[-1] - P_pred) @ C.T)
    return np.array(means[::-1]), np.array(covs[::-1])


def test_sigma_point_rts_equals_numpy_urts_on_pendulum():
    model, prior, ys = pendulum()
    filt = je.UKF(alpha=0.5)
    result = je.run(filt, model, ys, prior=prior)
    smoothed = je.sigma_point_rts_smooth(model, result, filt)
    f = lambda x: np.asarray(pendulum_f(jnp.asarray(x)))  # noqa: E731
    filtered = jax.tree.map(np.asarray, result)
    means, covs = numpy_urts(UnscentedPoints(0.5, 2.0, 0.0), f, np.asarray(model.Q), filtered)
    np.testing.assert_allclose(smoothed.mean, means, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(smoothed.cov, covs, rtol=1e-9, atol=1e-12)


def test_sigma_point_rts_checks_its_arguments():
    model, prior, ys = random_linear()
    result = je.run(je.KalmanFilter(), model, ys, prior=prior)
    with pytest.raises(ValueError, match="^filter:"):
        je.sigma_point_rts_smooth(model, result, je.KalmanFilter())
    partial = je.run(je.UKF(), model, ys, prior=prior, save=je.SaveAt(fields=("mean",)))
    with pytest.raises(ValueError, match="^result:"):
        je.sigma_point_rts_smooth(model, partial, je.UKF())
