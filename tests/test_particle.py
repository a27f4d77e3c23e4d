"""The particle filter: resampling schemes against their definitions, the likelihood estimate
against the Kalman filter, the gradient estimate against the Kalman filter's exact derivative,
a fit of R, a user proposal, missing data, degenerate weights, bad input, jit/vmap/grad."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from jax import export

import jaxest as je
from jaxest import xla_flags
from jaxest.filters.particle import (
    AbstractProposal,
    GaussianTransition,
    _search_sorted,
    resample,
)

PRIOR = je.Gaussian(jnp.zeros(1), jnp.eye(1))
SAVE_NONE = je.SaveAt(fields=())


def scalar_model(R=0.5, dtype=jnp.float64):
    """x_{k+1} = 0.9 x_k + w, y_k = x_k + v, Q = 1."""
    a = lambda v: jnp.asarray([[v]], dtype)
    return je.LinearGaussian(a(0.9), a(1.0), a(1.0), a(R))


def two_by_two():
    """A 2-state, 2-sensor linear Gaussian model with correlated R."""
    F = jnp.asarray([[0.9, 0.2], [-0.1, 0.8]])
    H = jnp.asarray([[1.0, 0.0], [0.5, 1.0]])
    Q = jnp.asarray([[0.5, 0.1], [0.1, 0.3]])
    R = jnp.asarray([[0.4, 0.1], [0.1, 0.6]])
    return je.LinearGaussian(F, H, Q, R), je.Gaussian(jnp.zeros(2), jnp.eye(2))


def loglik_draws(estimator, model, ys, prior, keys):
    one = lambda key: je.run(estimator, model, ys, prior=prior, key=key, save=SAVE_NONE).loglik
    return np.asarray(jax.jit(jax.vmap(one))(keys))


# --- resampling ------------------------------------------------------------------------------


WEIGHTS = np.random.default_rng(0).dirichlet(0.3 * np.ones(40))


def test_systematic_counts_are_floor_or_ceil_of_N_w():
    N = WEIGHTS.size
    for seed in range(20):
        counts = np.bincount(resample(jax.random.PRNGKey(seed), jnp.asarray(WEIGHTS)), minlength=N)
        assert counts.sum() == N
        assert np.all(counts >= np.floor(N * WEIGHTS) - 1e-9)
        assert np.all(counts <= np.ceil(N * WEIGHTS) + 1e-9)


@pytest.mark.parametrize("scheme", ["multinomial", "stratified", "systematic"])
def test_resampling_counts_are_unbiased(scheme):
    """E[count_j] = N W_j; the bound uses the multinomial variance N W (1 - W), which bounds the
    stratified and systematic ones (Douc, Cappe & Moulines 2005)."""
    N, draws = WEIGHTS.size, 4000
    keys = jax.random.split(jax.random.PRNGKey(1), draws)
    idx = jax.vmap(lambda k: resample(k, jnp.asarray(WEIGHTS), scheme))(keys)
    counts = np.asarray(jax.vmap(lambda i: jnp.bincount(i, length=N))(idx))
    se = np.sqrt(N * WEIGHTS * (1 - WEIGHTS) / draws)
    assert np.all(np.abs(counts.mean(0) - N * WEIGHTS) <= 5 * se + 1e-12)
    if scheme == "multinomial":  # independent draws: the variance is the multinomial one
        np.testing.assert_allclose(counts.var(0), N * WEIGHTS * (1 - WEIGHTS), rtol=0.2, atol=0.02)


def test_zero_weights_are_never_resampled():
    w = jnp.asarray([0.0, 0.5, 0.0, 0.5, 0.0])
    for scheme in ("multinomial", "stratified", "systematic"):
        idx = jax.vmap(lambda k, s=scheme: resample(k, w, s))(
            jax.random.split(jax.random.PRNGKey(2), 200)
        )
        assert set(np.unique(np.asarray(idx))) <= {1, 3}


@pytest.mark.parametrize(
    "weights, match",
    [
        ([1.0, -1.0, 3.0, 0.0], "non-negative"),  # picked the negative one: [1, 1, 3, 3]
        ([0.0, 0.0, 0.0, 0.0], "positive sum"),
        ([1.0, np.nan, 1.0, 1.0], "NaN"),
        ([[0.5, 0.5], [0.5, 0.5]], "a vector"),
    ],
)
def test_resample_names_weights_that_are_not_weights(weights, match):
    with pytest.raises(ValueError, match=f"^weights: .*{match}"):
        resample(jax.random.key(0), jnp.asarray(weights))


def test_resampling_searches_by_a_loop_on_the_cpu_and_by_a_sort_on_gpus():
    """The platform switch of the inverse-CDF search: the CUDA program sorts and the CPU program
    loops (both lowered here, on the CPU), and the sort finds the same indices as the binary
    search, with zero weights (equal CDF values) and u on the CDF's values included."""
    w = jnp.concatenate([jnp.zeros(3), jax.random.uniform(jax.random.PRNGKey(0), (997,))])
    cdf = jnp.cumsum(w.at[500:510].set(0.0))
    cdf = cdf / cdf[-1]
    u = jnp.concatenate([jax.random.uniform(jax.random.PRNGKey(1), (1000,)), cdf[::7]])
    for platform, sorts in (("cpu", False), ("cuda", True)):
        program = export.export(jax.jit(_search_sorted), platforms=[platform])(cdf, u)
        text = program.mlir_module()
        assert ("stablehlo.sort" in text) == sorts and ("stablehlo.while" in text) != sorts
    by_sort = jnp.searchsorted(cdf, u, side="right", method="sort")
    np.testing.assert_array_equal(jax.jit(_search_sorted)(cdf, u), by_sort)


@pytest.mark.parametrize("scheme", ["stratified", "systematic"])
def test_sorted_schemes_count_on_the_cpu_with_the_searchs_indices(scheme):
    """Stratified and systematic ancestors come from counting on the CPU (no loop, no sort in the
    program) and from the sort on GPUs; the counting gives the binary search's indices for 200
    keys at N = 10^3 and 20 at N = 10^5, with runs of zero weights and tiny ones."""
    for N, num_keys in ((1_000, 200), (100_000, 20)):
        w = jax.random.exponential(jax.random.PRNGKey(N), (N,), jnp.float64) ** 4
        w = w.at[: N // 10].set(0.0).at[N // 2 : N // 2 + 7].set(1e-300)

        def both(key, w, N=N):
            ancestors = resample(key, w, scheme)
            offsets = jax.random.uniform(key, () if scheme == "systematic" else (N,), w.dtype)
            cdf = jnp.cumsum(w) / jnp.sum(w)
            by_search = jnp.searchsorted(cdf, (jnp.arange(N) + offsets) / N, side="right")
            return ancestors, jnp.minimum(by_search, N - 1)

        keys = jax.random.split(jax.random.PRNGKey(7), num_keys)
        ancestors, by_search = jax.jit(jax.vmap(both, (0, None)))(keys, w)
        np.testing.assert_array_equal(ancestors, by_search)
    lower = lambda fn, platform: export.export(jax.jit(fn), platforms=[platform])(
        jax.random.PRNGKey(0)
    ).mlir_module()  # fmt: skip
    shape = () if scheme == "systematic" else w.shape
    offsets_only = lower(lambda key: jax.random.uniform(key, shape, w.dtype), "cpu")
    on_cpu, on_gpu = (lower(lambda key: resample(key, w, scheme), p) for p in ("cpu", "cuda"))
    # the CPU program loops only where drawing the offsets does (the PRNG's rounds)
    assert on_cpu.count("stablehlo.while") == offsets_only.count("stablehlo.while")
    assert "stablehlo.sort" not in on_cpu and "stablehlo.sort" in on_gpu


# --- likelihood against the Kalman filter ----------------------------------------------------


def test_loglik_converges_to_the_kalman_filter_with_missing_data():
    """Bias and spread shrink with N; at N = 1000 the mean over keys agrees with the KF's exact
    log-likelihood within 4 standard errors plus the Jensen bias sigma^2/2 of a log of an
    unbiased estimate. One fully and one partly missing measurement are skipped by both."""
    model, prior = two_by_two()
    ys = je.simulate(model, prior, 15, jax.random.PRNGKey(0)).y
    ys = ys.at[3].set(jnp.nan).at[7, 1].set(jnp.nan)
    exact = float(je.run(je.KalmanFilter(), model, ys, prior=prior).loglik)
    keys = jax.random.split(jax.random.PRNGKey(1), 40)
    small = loglik_draws(je.ParticleFilter(100), model, ys, prior, keys)
    large = loglik_draws(je.ParticleFilter(1000), model, ys, prior, keys)
    sd = large.std()
    assert abs(large.mean() - exact) < 4 * sd / np.sqrt(keys.shape[0]) + sd**2
    assert sd < small.std() / 2  # 1/sqrt(N) would give 3.2
    assert abs(large.mean() - exact) < abs(small.mean() - exact)


def test_fully_missing_step_adds_nothing():
    model = scalar_model()
    ys = jnp.asarray([[0.3], [jnp.nan], [-0.2]])
    r = je.run(je.ParticleFilter(50), model, ys, prior=PRIOR, key=jax.random.PRNGKey(0))
    assert float(r.loglik_terms[1]) == 0.0
    assert int(r.any_status) == 0


class OptimalLinearProposal(AbstractProposal):
    """p(x_k | x_{k-1}, y_k) for y = H x + v: N(m + K (y - H m), (I - K H) S), K = S H^T
    (H S H^T + R)^-1 with (m, S) the particle's transition (Doucet, Godsill & Andrieu 2000)."""

    def moments(self, model, t, k):
        S = t.factor @ t.factor.T
        H, R = model.H, model.R
        K = jnp.linalg.solve(H @ S @ H.T + R, H @ S).T
        return K, S - K @ H @ S

    def sample(self, model, t, k, y, u, key):
        K, P = self.moments(model, t, k)
        mean = t.mean + K @ (y - model.H @ t.mean)
        return GaussianTransition(mean, jnp.linalg.cholesky(P)).sample(key)

    def log_prob(self, model, x, t, k, y, u):
        K, P = self.moments(model, t, k)
        mean = t.mean + K @ (y - model.H @ t.mean)
        return GaussianTransition(mean, jnp.linalg.cholesky(P)).log_prob(x)


def test_user_proposal_is_consistent_and_beats_the_bootstrap():
    """With the optimal proposal every weight is p(y_k | x_{k-1}): a far smaller spread of the
    log-likelihood than the bootstrap's at the same N, around the KF's value."""
    model, prior = two_by_two()
    ys = je.simulate(model, prior, 15, jax.random.PRNGKey(3)).y
    exact = float(je.run(je.KalmanFilter(), model, ys, prior=prior).loglik)
    keys = jax.random.split(jax.random.PRNGKey(4), 40)
    boot = loglik_draws(je.ParticleFilter(100), model, ys, prior, keys)
    opt = loglik_draws(je.ParticleFilter(100, proposal=OptimalLinearProposal()), model, ys, prior,
                       keys)  # fmt: skip
    assert opt.std() < boot.std() / 2
    assert abs(opt.mean() - exact) < 4 * opt.std() / np.sqrt(keys.shape[0]) + opt.std() ** 2


def test_moments_match_the_kalman_filter():
    model, prior = two_by_two()
    ys = je.simulate(model, prior, 10, jax.random.PRNGKey(5)).y
    kf = je.run(je.KalmanFilter(), model, ys, prior=prior)
    pf = je.run(je.ParticleFilter(5000), model, ys, prior=prior, key=jax.random.PRNGKey(6))
    sd = np.sqrt(np.diagonal(np.asarray(kf.cov), axis1=1, axis2=2))
    assert np.all(np.abs(np.asarray(pf.mean - kf.mean)) < 0.1 * sd)
    np.testing.assert_allclose(pf.cov, kf.cov, rtol=0.15, atol=0.02)
    assert np.all((pf.ess > 0) & (pf.ess <= 5000 * (1 + 1e-9)))


# --- gradients -------------------------------------------------------------------------------


def test_gradient_agrees_with_the_kalman_filter_within_monte_carlo_error():
    """d loglik / d log R averaged over keys (multinomial, resampling every step) agrees with
    the KF's exact derivative; without the resampling correction it is off by many standard
    errors."""
    ys = je.simulate(scalar_model(), PRIOR, 20, jax.random.PRNGKey(0)).y

    def loglik(estimator, log_r, key=None):
        model = scalar_model(jnp.exp(log_r))
        return je.run(estimator, model, ys, prior=PRIOR, key=key, save=SAVE_NONE).loglik

    exact = float(jax.grad(lambda r: loglik(je.KalmanFilter(), r))(jnp.log(0.5)))
    keys = jax.random.split(jax.random.PRNGKey(1), 100)
    grads = {}
    for corrected in (True, False):
        pf = je.ParticleFilter(200, "multinomial", 1.0, differentiable=corrected)
        g = jax.jit(jax.vmap(jax.grad(lambda r, key, pf=pf: loglik(pf, r, key)), (None, 0)))
        grads[corrected] = np.asarray(g(jnp.log(0.5), keys))
    se = grads[True].std() / np.sqrt(keys.shape[0])
    assert abs(grads[True].mean() - exact) < 4 * se
    se_plain = grads[False].std() / np.sqrt(keys.shape[0])
    assert abs(grads[False].mean() - exact) > 10 * se_plain


def test_fit_recovers_R_within_its_standard_error():
    """Stochastic gradient (Adam, a fresh key per step, Polyak average of the second half) on the
    PF's log-likelihood from R x 5 reaches the KF's maximum-likelihood R within a quarter of its
    standard error (from the observed Fisher information), and the truth within one."""
    true_r = 0.5
    runs = je.monte_carlo(
        lambda key: je.simulate(scalar_model(true_r), PRIOR, 40, key), jax.random.PRNGKey(7), 8
    )
    ys = runs.y

    def nll(estimator, log_r, key=None):
        model = scalar_model(jnp.exp(log_r))
        one = lambda y: je.run(estimator, model, y, prior=PRIOR, key=key, save=SAVE_NONE).loglik
        return -jnp.sum(jax.vmap(one)(ys))

    pf, optimizer, steps = je.ParticleFilter(1000, "multinomial", 1.0), optax.adam(0.05), 100

    @functools.partial(jax.jit, compiler_options=xla_flags.OPTIMISED_MACHINE_CODE)
    def sgd(log_r, key):
        def body(carry, key):
            log_r, opt_state = carry
            grad = jax.grad(lambda t: nll(pf, t, key) / ys.size)(log_r)
            updates, opt_state = optimizer.update(grad, opt_state)
            log_r = optax.apply_updates(log_r, updates)
            return (log_r, opt_state), log_r

        init = (log_r, optimizer.init(log_r))
        return jax.lax.scan(body, init, jax.random.split(key, steps))[1]

    fitted = float(jnp.mean(sgd(jnp.log(5 * true_r), jax.random.PRNGKey(8))[steps // 2 :]))
    kf_nll = lambda t: nll(je.KalmanFilter(), t)
    kf_fit = je.fit(
        scalar_model(5 * true_r),
        lambda model: kf_nll(jnp.log(model.R[0, 0])),
        {"R": "log_diagonal"},
        optimizer=optax.lbfgs(),
        num_steps=30,
    )
    kf_mle = jnp.log(kf_fit.model.R[0, 0])
    se = 1.0 / np.sqrt(float(jax.hessian(kf_nll)(kf_mle)))
    assert abs(fitted - float(kf_mle)) < se / 4
    assert abs(fitted - np.log(true_r)) < se


# --- transforms, dtypes, status, bad input ---------------------------------------------------


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_jit_vmap_grad_in_each_dtype(dtype):
    prior = je.Gaussian(jnp.zeros(1, dtype), jnp.eye(1, dtype=dtype))
    ys = je.simulate(scalar_model(dtype=dtype), prior, 10, jax.random.PRNGKey(0)).y

    def loglik(log_r, key):
        model = scalar_model(jnp.exp(log_r), dtype)
        return je.run(je.ParticleFilter(64), model, ys, prior=prior, key=key).loglik

    keys = jax.random.split(jax.random.PRNGKey(1), 4)
    values, grads = jax.jit(jax.vmap(jax.value_and_grad(loglik), (None, 0)))(
        jnp.asarray(np.log(0.5), dtype), keys
    )
    assert values.dtype == dtype and grads.dtype == dtype
    assert np.all(np.isfinite(values)) and np.all(np.isfinite(grads))
    r = je.run(je.ParticleFilter(64), scalar_model(dtype=dtype), ys, prior=prior, key=keys[0])
    assert r.mean.dtype == dtype and r.cov.dtype == dtype and int(r.any_status) == 0


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_all_weights_underflow_sets_the_status_bit_with_finite_outputs(dtype):
    """A measurement so far out that every Gaussian log-density overflows to -inf."""
    prior = je.Gaussian(jnp.zeros(1, dtype), jnp.eye(1, dtype=dtype))
    big = 1e30 if dtype == jnp.float32 else 1e200
    ys = jnp.asarray([[0.1], [big], [0.2]], dtype)
    r = je.run(
        je.ParticleFilter(32),
        scalar_model(dtype=dtype),
        ys,
        prior=prior,
        key=jax.random.PRNGKey(0),
        save=je.SaveAt(fields=("mean", "cov", "ess", "loglik", "status", "particles")),
    )
    flag = int(je.ParticleStatus.WEIGHTS_DEGENERATE)
    assert [int(s) & flag for s in r.status] == [0, flag, 0]
    for a in (r.mean, r.cov, r.ess, r.loglik_terms, r.particles, r.loglik):
        assert np.all(np.isfinite(np.asarray(a)))
    assert "WEIGHTS_DEGENERATE" in je.ParticleStatus.describe(r.any_status)


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_weights_sum_to_one_where_huge_log_weights_tie_by_rounding(dtype):
    """A measurement far out but finite in the log-densities (1e20 in float64, 1e8 in float32):
    the log-weights are about -1e40 (-1e16) and many tie by rounding. Normalised by
    log w - logsumexp(log w) each tied one had W = 1: the weights summed to up to N, the ESS fell
    below one and the "mean" was a sum of particles (float64: 407.9 at N = 500), status OK."""
    prior = je.Gaussian(jnp.zeros(1, dtype), jnp.eye(1, dtype=dtype))
    big = 1e8 if dtype == jnp.float32 else 1e20
    ys = jnp.asarray([[0.1], [big], [0.2]], dtype)
    N = 64
    r = je.run(
        je.ParticleFilter(N),
        scalar_model(dtype=dtype),
        ys,
        prior=prior,
        key=jax.random.key(1),
        save=je.SaveAt(fields=("mean", "ess", "particles", "log_weights")),
    )
    W = np.exp(np.asarray(r.log_weights, np.float64))
    np.testing.assert_allclose(W.sum(axis=1), 1.0, rtol=N * float(jnp.finfo(dtype).eps))
    assert np.all((np.asarray(r.ess) >= 1 - 1e-3) & (np.asarray(r.ess) <= N * (1 + 1e-3)))
    particles, mean = np.asarray(r.particles)[..., 0], np.asarray(r.mean)[:, 0]
    assert np.all((particles.min(axis=1) <= mean) & (mean <= particles.max(axis=1)))


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"num_particles": 0}, "num_particles"),
        ({"num_particles": 10.0}, "num_particles"),
        ({"resampling": "residual"}, "resampling"),
        ({"ess_threshold": 0.0}, "ess_threshold"),
        ({"ess_threshold": 1.5}, "ess_threshold"),
        ({"proposal": "optimal"}, "proposal"),
    ],
)
def test_bad_arguments_raise_naming_them(kwargs, name):
    with pytest.raises(ValueError, match=f"^{name}"):
        je.ParticleFilter(**kwargs)


def test_run_requires_a_key_and_checks_the_model():
    ys = jnp.zeros((3, 1))
    with pytest.raises(ValueError, match="^key"):
        je.run(je.ParticleFilter(10), scalar_model(), ys, prior=PRIOR)
    with pytest.raises(ValueError, match="^prior"):
        je.run(je.ParticleFilter(10), scalar_model(), ys, prior=None, key=jax.random.PRNGKey(0))
    # noise on the input: it sampled the linearised N(f, G Q G^T), status OK (log-likelihood
    # -113.3 where a bootstrap filter of the true transition gives -98.1)
    on_input = je.NonlinearGaussian(
        lambda x, u: 0.5 * x + 3.0 * jnp.sin(u), lambda x: x, jnp.eye(1), jnp.eye(1),
        noise_on_input=True,
    )  # fmt: skip
    with pytest.raises(ValueError, match=r"^model: has its noise on the input"):
        je.run(je.ParticleFilter(10), on_input, ys, prior=PRIOR, inputs=jnp.zeros((3, 1)),
               key=jax.random.PRNGKey(0))  # fmt: skip


def test_the_losses_take_a_key_for_a_filter_that_samples():
    """neg_loglik and supervised_mse had no key=, so no particle filter could be tuned with them
    (the README says every entry point takes key=): run i draws with split(key, runs)[i], the
    same at every evaluation."""
    model = scalar_model()
    sims = je.monte_carlo(lambda k: je.simulate(model, PRIOR, 6, k), jax.random.key(0), 2)
    pf, key = je.ParticleFilter(32), jax.random.key(1)
    loss = je.neg_loglik(pf, sims.y, prior=PRIOR, key=key)
    by_hand = [
        je.run(pf, model, y, prior=PRIOR, key=k, save=SAVE_NONE).loglik
        for y, k in zip(sims.y, jax.random.split(key, 2), strict=True)
    ]
    value, grad = jax.jit(jax.value_and_grad(loss))(model)
    np.testing.assert_allclose(value, -np.mean(by_hand) / 6, rtol=1e-12)
    assert np.isfinite(float(grad.R[0, 0]))
    np.testing.assert_allclose(loss(model), value, rtol=1e-12)  # the same draws again
    mse = je.supervised_mse(pf, sims.y, sims.states, prior=PRIOR, key=key)
    assert np.isfinite(float(mse(model)))
    with pytest.raises(ValueError, match="^key: ParticleFilter samples"):
        je.neg_loglik(pf, sims.y, prior=PRIOR)(model)


def test_particles_are_saved_on_request_and_resume():
    model = scalar_model()
    ys = je.simulate(model, PRIOR, 8, jax.random.PRNGKey(0)).y
    key = jax.random.PRNGKey(1)
    save = je.SaveAt(fields=("particles", "log_weights", "loglik", "status"))
    r = je.run(je.ParticleFilter(16), model, ys, prior=PRIOR, key=key, save=save)
    assert r.particles.shape == (8, 16, 1) and r.log_weights.shape == (8, 16)
    np.testing.assert_allclose(jax.nn.logsumexp(r.log_weights, axis=1), 0.0, atol=1e-12)
    assert r.mean is None
    np.testing.assert_allclose(r.loglik, jnp.sum(r.loglik_terms), rtol=1e-12)
    head = je.run(je.ParticleFilter(16), model, ys[:5], prior=PRIOR, key=key, save=save)
    tail = je.run(je.ParticleFilter(16), model, ys[5:], state=head.final_state, k0=5, key=key,
                  save=save)  # fmt: skip
    np.testing.assert_allclose(tail.particles, r.particles[5:], rtol=1e-12)
    np.testing.assert_allclose(tail.loglik, r.loglik, rtol=1e-12)
