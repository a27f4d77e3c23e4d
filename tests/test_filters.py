"""Every Gaussian filter against a NumPy Kalman filter, against each other, and under jit, vmap
and grad in float32 and float64."""

import functools
import logging

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxest as je
from jaxest.filters import EKF, SVDEKF, ImprovedSVDKF, KalmanFilter
from jaxest.systems.ill_conditioned import posterior_error, problem
from tests.lowering import programs_compiled
from tests.reference import kalman_filter, random_system
from tests.registry import GAUSSIAN_FILTER_IDS as IDS, GAUSSIAN_FILTERS as FILTERS


def linear_problem(seed=0, n=4, m=2, T=40, correlated_R=True, dtype=jnp.float64):
    rng = np.random.default_rng(seed)
    F, H, Q, R = random_system(rng, n, m, correlated_R)
    model = je.LinearGaussian(*(jnp.asarray(a, dtype) for a in (F, H, Q, R)))
    prior = je.Gaussian(jnp.asarray(rng.normal(size=n), dtype), jnp.asarray(np.eye(n) * 2.0, dtype))
    sim = je.simulate(model, prior, T, jax.random.PRNGKey(seed))
    return model, prior, sim


@pytest.mark.parametrize("Filter", FILTERS, ids=IDS)
def test_matches_numpy_kalman_filter(Filter):
    model, prior, sim = linear_problem(seed=1)
    ys = np.array(sim.y)
    ys[3, 0] = np.nan  # a single missing entry
    ys[7, :] = np.nan  # a whole missing vector
    res = je.run(Filter(), model, jnp.asarray(ys), prior=prior)
    means, covs, pmeans, pcovs, loglik = kalman_filter(
        np.asarray(model.F), np.asarray(model.H), np.asarray(model.Q), np.asarray(model.R),
        np.asarray(prior.mean), np.asarray(prior.cov), ys,
    )  # fmt: skip
    np.testing.assert_allclose(res.mean, means, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(res.cov, covs, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(res.predicted_mean, pmeans, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(res.predicted_cov, pcovs, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(res.loglik, loglik, rtol=1e-9)
    assert np.all(np.asarray(res.status) == je.Status.OK)


@pytest.mark.parametrize("seed", [2, 3, 4])
def test_factored_filters_agree_with_kf_on_random_systems(seed):
    model, prior, sim = linear_problem(seed=seed, n=5, m=3, T=30)
    ref = je.run(KalmanFilter(), model, sim.y, prior=prior)
    for Filter in FILTERS[1:]:
        res = je.run(Filter(), model, sim.y, prior=prior)
        for name in ("mean", "cov", "innovation", "innovation_cov", "loglik_terms"):
            np.testing.assert_allclose(
                getattr(res, name),
                getattr(ref, name),
                rtol=1e-9,
                atol=1e-11,
                err_msg=f"{Filter.__name__}.{name}",
            )


def test_kalman_filter_matches_dynamax():
    dynamax = pytest.importorskip("dynamax.linear_gaussian_ssm")
    model, prior, sim = linear_problem(seed=5, n=4, m=2, T=50)
    params, _ = dynamax.LinearGaussianSSM(4, 2).initialize(
        jax.random.PRNGKey(0),
        initial_mean=prior.mean, initial_covariance=prior.cov,
        dynamics_weights=model.F, dynamics_covariance=model.Q,
        emission_weights=model.H, emission_covariance=model.R,
    )  # fmt: skip
    post = dynamax.lgssm_filter(params, sim.y)
    res = je.run(KalmanFilter(), model, sim.y, prior=prior)
    np.testing.assert_allclose(res.mean, post.filtered_means, rtol=1e-8, atol=1e-9)
    np.testing.assert_allclose(res.cov, post.filtered_covariances, rtol=1e-8, atol=1e-9)
    np.testing.assert_allclose(res.loglik, post.marginal_loglik, rtol=1e-9)


def test_time_varying_model_matches_numpy():
    rng = np.random.default_rng(6)
    T, n, m = 25, 3, 2
    F = np.stack([random_system(rng, n, m)[0] for _ in range(T)])
    H = rng.normal(size=(T, m, n))
    _, _, Q, R = random_system(rng, n, m)
    model = je.LinearGaussian(jnp.asarray(F), jnp.asarray(H), jnp.asarray(Q), jnp.asarray(R))
    prior = je.Gaussian(jnp.zeros(n), jnp.eye(n))
    sim = je.simulate(model, prior, T, jax.random.PRNGKey(0))
    means, covs, *_, loglik = kalman_filter(F, H, Q, R, np.zeros(n), np.eye(n), np.asarray(sim.y))
    for Filter in (KalmanFilter, SVDEKF):
        res = je.run(Filter(), model, sim.y, prior=prior)
        np.testing.assert_allclose(res.mean, means, rtol=1e-9, atol=1e-10)
        np.testing.assert_allclose(res.loglik, loglik, rtol=1e-9)


def pendulum_model(dtype=jnp.float64):
    dt = 0.05

    def f(x, u):
        return jnp.stack([x[0] + dt * x[1], x[1] - dt * 9.81 * jnp.sin(x[0])])

    def h(x, u):
        return jnp.stack([jnp.sin(x[0]), x[1] ** 2 / 10])

    Q = jnp.diag(jnp.asarray([1e-4, 1e-3], dtype))
    R = jnp.asarray([[0.01, 0.002], [0.002, 0.02]], dtype)
    return je.NonlinearGaussian(f, h, Q, R)


def numpy_ekf(f, jf, h, jh, Q, R, m0, P0, ys):
    x, P, means, loglik = np.array(m0), np.array(P0), [], 0.0
    for y in ys:
        H = jh(x)
        S = H @ P @ H.T + R
        K = P @ H.T @ np.linalg.inv(S)
        e = y - h(x)
        x, P = x + K @ e, P - K @ S @ K.T
        loglik += -0.5 * (
            len(y) * np.log(2 * np.pi) + np.linalg.slogdet(S)[1] + e @ np.linalg.solve(S, e)
        )
        means.append(x)
        Fj = jf(x)
        x, P = f(x), Fj @ P @ Fj.T + Q
    return np.array(means), loglik


@pytest.mark.parametrize("Filter", FILTERS, ids=IDS)
def test_ekf_matches_numpy_ekf(Filter):
    model = pendulum_model()
    prior = je.Gaussian(jnp.asarray([0.5, 0.0]), 0.1 * jnp.eye(2))
    sim = je.simulate(model, prior, 60, jax.random.PRNGKey(3))
    dt = 0.05
    f = lambda x: np.array([x[0] + dt * x[1], x[1] - dt * 9.81 * np.sin(x[0])])
    jf = lambda x: np.array([[1.0, dt], [-dt * 9.81 * np.cos(x[0]), 1.0]])
    h = lambda x: np.array([np.sin(x[0]), x[1] ** 2 / 10])
    jh = lambda x: np.array([[np.cos(x[0]), 0.0], [0.0, x[1] / 5]])
    means, loglik = numpy_ekf(
        f,
        jf,
        h,
        jh,
        np.asarray(model.Q),
        np.asarray(model.R),
        [0.5, 0.0],
        0.1 * np.eye(2),
        np.asarray(sim.y),
    )
    res = je.run(Filter(), model, sim.y, prior=prior)
    np.testing.assert_allclose(res.mean, means, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(res.loglik, loglik, rtol=1e-9)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64], ids=["float32", "float64"])
@pytest.mark.parametrize("Filter", FILTERS, ids=IDS)
def test_jit_vmap_grad(Filter, dtype):
    model, prior, sim = linear_problem(seed=7, n=3, m=2, T=20, dtype=dtype)
    ys = jnp.stack([sim.y, sim.y * 0.5, sim.y + 0.1])

    def loglik(q_scale, r_scale, y):
        mdl = je.LinearGaussian(model.F, model.H, q_scale * model.Q, r_scale * model.R)
        return je.run(Filter(), mdl, y, prior=prior).loglik

    one = jax.jit(loglik)(dtype(1.0), dtype(1.0), sim.y)
    batch = jax.vmap(loglik, in_axes=(None, None, 0))(dtype(1.0), dtype(1.0), ys)
    grads = jax.jit(jax.vmap(jax.grad(loglik, argnums=(0, 1)), in_axes=(None, None, 0)))(
        dtype(1.0), dtype(1.0), ys
    )
    ref, ref_grad = _kalman_loglik_and_q_gradient(dtype)
    assert one.dtype == dtype and batch.dtype == dtype and grads[0].dtype == dtype
    tol = 1e-4 if dtype == jnp.float32 else 1e-10
    np.testing.assert_allclose(one, ref, rtol=tol)
    np.testing.assert_allclose(batch[0], one, rtol=tol)
    assert np.all(np.isfinite(np.asarray(grads)))
    np.testing.assert_allclose(grads[0][0], ref_grad, rtol=10 * tol)


@functools.cache  # one reference per dtype for every filter of test_jit_vmap_grad
def _kalman_loglik_and_q_gradient(dtype):
    """log p(y) of test_jit_vmap_grad's problem and its derivative in the Q scale, autodiff
    through the Kalman recursion (not the closed form)."""
    model, prior, sim = linear_problem(seed=7, n=3, m=2, T=20, dtype=dtype)

    def loglik(q):
        scaled = je.LinearGaussian(model.F, model.H, q * model.Q, model.R)
        return je.run(KalmanFilter(closed_form_gradient=False), scaled, sim.y, prior=prior).loglik

    return jax.jit(jax.value_and_grad(loglik))(dtype(1.0))


@pytest.mark.parametrize("Filter", FILTERS, ids=IDS)
def test_gradients_match_finite_differences(Filter):
    model, prior, sim = linear_problem(seed=8, n=3, m=2, T=25)

    def loss(params):
        a, q, r, p0 = params
        F = model.F.at[0, 1].add(a)
        mdl = je.LinearGaussian(F, model.H, model.Q + q * jnp.eye(3), model.R * r)
        res = je.run(Filter(), mdl, sim.y, prior=je.Gaussian(prior.mean, prior.cov * p0))
        return res.loglik + jnp.sum(res.mean[-1] ** 2)  # likelihood and a loss on the outputs

    x0 = jnp.asarray([0.0, 0.05, 1.2, 1.5])
    grad = jax.jit(jax.grad(loss))(x0)
    eps = 1e-6
    shifts = jnp.concatenate([jnp.eye(4), -jnp.eye(4)]) * eps
    values = jax.jit(jax.vmap(loss))(x0 + shifts)
    fd = (values[:4] - values[4:]) / (2 * eps)
    np.testing.assert_allclose(grad, fd, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("Filter", [SVDEKF, ImprovedSVDKF], ids=["SVDEKF", "ImprovedSVDKF"])
def test_svd_gradients_finite_with_repeated_singular_values(Filter):
    """P0 = c I and isotropic Q: jnp.linalg.svd's own derivative is NaN there (docs/papers/svd_ekf.md)."""
    model, _, sim = linear_problem(seed=9, n=3, m=2, T=20)

    def loglik(Filter, q, c):
        mdl = je.LinearGaussian(model.F, model.H, q * jnp.eye(3), model.R)
        return je.run(Filter(), mdl, sim.y, prior=je.Gaussian(jnp.zeros(3), c * jnp.eye(3))).loglik

    ours = jax.grad(loglik, argnums=(1, 2))(Filter, 0.2, 3.0)
    ekf = jax.grad(loglik, argnums=(1, 2))(EKF, 0.2, 3.0)
    assert np.all(np.isfinite(ours))
    np.testing.assert_allclose(ours, ekf, rtol=1e-6)

    # jnp.linalg.svd's own derivative is not finite at such a point: the custom rule is needed.
    naive = jax.grad(lambda c: jnp.sum(jnp.linalg.svd(c * jnp.eye(3))[0] ** 3))(1.0)
    assert not np.isfinite(naive)


@pytest.mark.parametrize("Filter", [SVDEKF, ImprovedSVDKF], ids=lambda f: f.__name__)
def test_second_derivatives_match_central_differences_of_the_gradient(Filter):
    """The Hessian of log p(y) in (log q, log r, log c), Q = q I and P0 = c I (repeated singular
    values), by forward over reverse (``jax.hessian``), forward over forward and reverse over
    forward, against central differences of the Kalman filter's gradient. The SVD filters'
    forward-over-forward Hessians were wrong (factor tangents with U in place of U^-T, see
    docs/papers/svd_ekf.md) and reverse over forward failed to trace (``linalg.mm``'s rule)."""
    model, _, sim = linear_problem(seed=9, n=3, m=2, T=20)

    def loglik(Filter, theta):
        q, r, c = jnp.exp(theta)
        mdl = je.LinearGaussian(model.F, model.H, q * jnp.eye(3), r * model.R)
        return je.run(Filter(), mdl, sim.y, prior=je.Gaussian(jnp.zeros(3), c * jnp.eye(3))).loglik

    theta, h = jnp.asarray([np.log(0.2), 0.1, np.log(3.0)]), 1e-5
    kf_grad = jax.jit(jax.grad(functools.partial(loglik, KalmanFilter)))
    central = np.stack(
        [(kf_grad(theta + h * e) - kf_grad(theta - h * e)) / (2 * h) for e in np.eye(3)]
    )
    ours = functools.partial(loglik, Filter)
    for second_derivative in (jax.hessian, lambda f: jax.jacfwd(jax.jacfwd(f)),
                              lambda f: jax.jacrev(jax.jacfwd(f))):  # fmt: skip
        np.testing.assert_allclose(jax.jit(second_derivative(ours))(theta), central, rtol=1e-6)


def test_svd_filters_survive_where_kf_fails():
    """The Dyer-McReynolds test of docs/papers/svd_ekf.md at d = 1e-9 (float64)."""
    for Filter in (SVDEKF, ImprovedSVDKF):
        assert posterior_error(Filter, 1e-9) < 1e-5
    assert not posterior_error(KalmanFilter, 1e-9) < 1e-2  # NaN or O(1) error
    model, prior, ys = problem(1e-9)
    assert je.run(KalmanFilter(), model, ys, prior=prior).status[0] != je.Status.OK  # and says so


def test_status_flags_nonfinite_inside_jit():
    model, prior, sim = linear_problem(seed=10, n=2, m=1, T=10)
    bad = je.LinearGaussian(
        model.F, model.H, model.Q, -model.R
    )  # indefinite, hidden from checks by jit
    res = jax.jit(lambda m: je.run(KalmanFilter(), m, sim.y, prior=prior))(bad)
    assert np.all(np.asarray(res.status) != je.Status.OK)
    assert "NONFINITE" in je.Status.describe(int(res.status[0]))


SVD_FORMS = [SVDEKF(), ImprovedSVDKF(), je.UKF(form="svd"), je.CubatureKF(form="svd")]


def test_a_non_symmetric_covariance_under_jit_is_read_as_its_symmetric_part_by_every_filter():
    """Traced, a non-symmetric Q or R passes the argument checks. The filters that factor it
    read its lower triangle, the Kalman filter the symmetric part of S: three answers, each with
    status OK. The models now hand every filter the symmetric part."""
    model, prior, sim = linear_problem(seed=5, n=3, m=2, T=8)
    skew = lambda a: a - a.T
    rng = np.random.default_rng(5)
    tilted = je.LinearGaussian(
        model.F,
        model.H,
        model.Q + 0.05 * skew(jnp.asarray(rng.normal(size=(3, 3)))),
        model.R + 0.05 * skew(jnp.asarray(rng.normal(size=(2, 2)))),
    )
    estimators = (je.KalmanFilter(), je.SquareRootKF(), je.SVDEKF(), je.UKF(),
                  je.SteadyStateKalmanFilter())  # fmt: skip
    for estimator in estimators:
        run = jax.jit(lambda m, estimator=estimator: je.run(estimator, m, sim.y, prior=prior))
        want, got = run(model), run(tilted)
        assert int(got.any_status) == 0
        np.testing.assert_allclose(got.mean, want.mean, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize(
    "estimator", SVD_FORMS, ids=["SVDEKF", "ImprovedSVDKF", "UKF-svd", "CKF-svd"]
)
def test_indefinite_covariances_inside_jit_are_flagged_not_repaired(estimator):
    """R, Q or P0 with a negative eigenvalue, traced (the argument checks cannot see it): the
    filters that factor them by a symmetric SVD say so in the status from the first step, where
    they used to clip the eigenvalue to 0 and run on another model with status OK (the SVD
    filters, and until 2026-11-30 the sigma-point filters' SVD form, whose log-likelihood was the
    same for R = diag(r, -0.1) and diag(r, -2)). A positive semidefinite Q of rank one, formed
    with rounding, still runs cleanly."""
    model, prior, sim = linear_problem(seed=11, n=3, m=2, T=10)
    flip = jnp.diag(jnp.asarray([1.0, 1.0, -1.0]))
    run = jax.jit(lambda m, p: je.run(estimator, m, sim.y, prior=p))
    for bad_model, bad_prior in (
        (je.LinearGaussian(model.F, model.H, model.Q, model.R * jnp.asarray([1.0, -1.0])), prior),
        (je.LinearGaussian(model.F, model.H, flip @ model.Q @ flip - 0.5 * jnp.eye(3), model.R), prior),
        (model, je.Gaussian(prior.mean, flip * prior.cov)),
    ):  # fmt: skip
        status = np.asarray(run(bad_model, bad_prior).status)
        assert status[0] != je.Status.OK
    v = jnp.asarray([0.3, -0.1, 0.7])
    rank_one = je.LinearGaussian(model.F, model.H, 0.1 * jnp.outer(v, v), model.R)
    assert int(run(rank_one, prior).any_status) == 0


@pytest.mark.parametrize(
    "estimator",
    [F() for F in FILTERS] + [je.UKF(form="sqrt"), je.ParallelKalmanFilter()],
    ids=[*IDS, "UKF-sqrt", "ParallelKalmanFilter"],
)
def test_status_flags_every_step_whose_outputs_overflow(estimator):
    # two unobserved states growing 3^k: in float32 a Cholesky factor 3^k stays finite up to
    # k = 80 while its covariance 9^k overflows from k = 41 (the factored filters' own checks
    # passed those steps with status OK)
    dtype = jnp.float32
    model = je.LinearGaussian(
        3.0 * jnp.eye(3, dtype=dtype), jnp.eye(3, dtype=dtype)[:1], 0.1 * jnp.eye(3, dtype=dtype),
        0.1 * jnp.eye(1, dtype=dtype),
    )  # fmt: skip
    prior = je.Gaussian(jnp.zeros(3, dtype), jnp.eye(3, dtype=dtype))
    result = je.run(estimator, model, jnp.zeros((100, 1), dtype), prior=prior)
    finite = [
        np.all(np.isfinite(np.asarray(getattr(result, name))), axis=tuple(range(1, ndim)))
        for name, ndim in (("predicted_mean", 2), ("predicted_cov", 3), ("mean", 2), ("cov", 3))
    ]
    overflowed = ~np.logical_and.reduce(finite)
    assert overflowed.sum() > 20
    flagged = (np.asarray(result.status) & je.Status.NONFINITE) != 0
    np.testing.assert_array_equal(flagged[overflowed], True)


def test_a_first_kalman_run_compiles_its_check_and_its_run_only():
    """Outside ``jit`` the Kalman filter checks that P0 and Q have densities for its closed-form
    gradient: one compiled program besides the run's own. Run under
    ``jax.ensure_compile_time_eval``, the check's trace ran and compiled every constant of the
    unrolled Cholesky op by op (23 programs on a first run of a new shape)."""
    model, prior, sim = linear_problem(seed=3, n=7, m=3, T=20)
    run = lambda: je.run(KalmanFilter(), model, sim.y, prior=prior).loglik
    assert programs_compiled(run) <= 2


def test_simulate_compiles_once_per_shape(caplog):
    """``je.simulate`` is one compiled program: a second draw with another key compiles
    nothing (it compiled its scan anew on every call before)."""
    model, prior, first = linear_problem(seed=2, T=50)
    key = jax.random.PRNGKey(7)
    with jax.log_compiles(), caplog.at_level(logging.WARNING):
        second = jax.block_until_ready(je.simulate(model, prior, 50, key))
    assert [r.getMessage() for r in caplog.records if "Compiling" in r.getMessage()] == []
    assert second.y.shape == first.y.shape and not np.allclose(second.y, first.y)
