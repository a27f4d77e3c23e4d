"""je.fit_em against dynamax's LinearGaussianSSM.fit_em, its monotone log-likelihood with inputs
and held parameters, recovery of a simulated 4-state model's invariants, and argument errors."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.stats
from dynamax.linear_gaussian_ssm import LinearGaussianSSM

import jaxest as je
from jaxest import xla_flags

TRUE_F = np.array([[0.9, 0.2, 0, 0], [-0.2, 0.9, 0, 0], [0, 0, 0.6, 0.3], [0, 0, 0, -0.5]])


def system(seed, n, m, T, p=0):
    rng = np.random.default_rng(seed)
    F = TRUE_F if n == 4 else np.diag(np.linspace(0.9, -0.5, n))
    H = rng.normal(size=(m, n))
    B, D = rng.normal(size=(n, p)), rng.normal(size=(m, p))
    truth = je.LinearGaussian(*map(jnp.asarray, (F, H, 0.1 * np.eye(n), 0.2 * np.eye(m))),
                              B=jnp.asarray(B) if p else None, D=jnp.asarray(D) if p else None)  # fmt: skip
    prior = je.Gaussian(jnp.zeros(n), jnp.eye(n))
    inputs = jnp.asarray(rng.normal(size=(T, p))) if p else None
    ys = je.simulate(truth, prior, T, jax.random.PRNGKey(seed), inputs=inputs).y
    A0 = rng.normal(size=(n, n))
    init = je.LinearGaussian(
        jnp.asarray(0.8 * A0 / np.max(np.abs(np.linalg.eigvals(A0)))),
        jnp.asarray(rng.normal(size=(m, n))), 0.5 * jnp.eye(n), jnp.eye(m),
        B=jnp.zeros((n, p)) if p else None, D=jnp.zeros((m, p)) if p else None,
    )  # fmt: skip
    init_prior = je.Gaussian(jnp.asarray(rng.normal(size=n)), 2.0 * jnp.eye(n))
    return truth, ys, inputs, init, init_prior


@pytest.mark.parametrize("parallel", [False, True], ids=["sequential", "parallel"])
def test_matches_dynamax_fit_em(parallel):
    """Same data and initialisation; dynamax without its biases (jaxest's model has none) and
    without inputs (dynamax's dynamics input enters as B u_{k+1}, jaxest's as B u_k)."""
    _, ys, _, init, init_prior = system(0, 3, 2, 64)
    ours = je.fit_em(init, ys, prior=init_prior, num_iters=12, parallel=parallel)
    lgssm = LinearGaussianSSM(3, 2, has_dynamics_bias=False, has_emissions_bias=False)
    params, props = lgssm.initialize(
        initial_mean=init_prior.mean, initial_covariance=init_prior.cov,
        dynamics_weights=init.F, dynamics_covariance=init.Q,
        emission_weights=init.H, emission_covariance=init.R,
    )  # fmt: skip
    fitted, logliks = lgssm.fit_em(params, props, ys, num_iters=12, verbose=False)
    np.testing.assert_allclose(ours.logliks, logliks, rtol=1e-6)
    assert bool(ours.ok), je.EMStatus.describe(ours.any_status)
    for mine, theirs in [(ours.model.F, fitted.dynamics.weights), (ours.model.Q, fitted.dynamics.cov),
                         (ours.model.H, fitted.emissions.weights), (ours.model.R, fitted.emissions.cov),
                         (ours.prior.mean, fitted.initial.mean), (ours.prior.cov, fitted.initial.cov)]:  # fmt: skip
        np.testing.assert_allclose(mine, theirs, rtol=1e-6, atol=1e-8)


@pytest.mark.parametrize(
    "fixed", [(), ("H", "D"), ("F", "Q", "prior.mean"), ("B", "R", "prior.cov")]
)
def test_loglik_is_monotone_with_inputs_and_held_parameters(fixed):
    _, ys, inputs, init, init_prior = system(1, 3, 2, 150, p=1)
    res = je.fit_em(init, ys, prior=init_prior, num_iters=15, fixed=fixed, inputs=inputs)
    logliks = np.asarray(res.logliks)
    assert np.all(np.diff(logliks) >= -1e-9 * np.abs(logliks[1:]))
    assert logliks[-1] > logliks[0] + 1.0
    assert bool(res.ok), je.EMStatus.describe(res.any_status)
    fitted = {"F": res.model.F, "B": res.model.B, "Q": res.model.Q, "H": res.model.H,
              "D": res.model.D, "R": res.model.R, "prior.mean": res.prior.mean,
              "prior.cov": res.prior.cov}  # fmt: skip
    start = {"F": init.F, "B": init.B, "Q": init.Q, "H": init.H, "D": init.D, "R": init.R,
             "prior.mean": init_prior.mean, "prior.cov": init_prior.cov}  # fmt: skip
    for name in je.em.PARAMETERS:
        if name in fixed:
            np.testing.assert_array_equal(fitted[name], start[name])
        else:
            assert not np.allclose(fitted[name], start[name])


def markov_parameters(model, num=8):
    """H F^k K (K the steady-state Kalman gain) and the innovation covariance: invariant under
    x -> T x, so comparable between a fitted model and the truth."""
    gain = je.steady_state_gain(model)
    F = np.asarray(model.F)
    blocks = [np.asarray(model.H) @ np.linalg.matrix_power(F, k) @ np.asarray(gain.K)
              for k in range(num)]  # fmt: skip
    return np.stack(blocks), np.asarray(gain.innovation_cov)


def test_recovers_invariants_of_a_four_state_model():
    """T = 2000, EM from a random start. The fit is the maximum-likelihood estimate: its
    log-likelihood exceeds the truth's, by less than the 0.999 quantile of chi^2(d) / 2 for the
    d = 33 identifiable parameters (innovation form F, K, H, S less the n^2 of the similarity,
    19, and the prior's 14), as Wilks' theorem has it. Similarity invariants: the dominant
    eigenvalue pair of F (0.9 +- 0.2i), the Markov parameters H F^k K of the innovation form and
    its innovation covariance agree with the truth to within the sampling error of this T (the
    two weakly excited real modes, 0.6 and -0.5, are not resolved at this T and not compared)."""
    truth, ys, _, init, init_prior = system(2, 4, 2, 2000)
    # 400 iterations run far longer than they compile: optimised machine code (13.2 -> 9.4 s)
    fit = lambda init, ys, prior: je.fit_em(init, ys, prior=prior, num_iters=400)
    res = jax.jit(fit, compiler_options=xla_flags.OPTIMISED_MACHINE_CODE)(init, ys, init_prior)
    truth_loglik = je.run(je.KalmanFilter(), truth, ys, prior=init_prior).loglik
    excess = 2.0 * float(res.logliks[-1] - truth_loglik)
    assert 0.0 < excess < scipy.stats.chi2.ppf(0.999, 33)
    eig_true = np.sort_complex(np.linalg.eigvals(TRUE_F))
    eig_fit = np.sort_complex(np.linalg.eigvals(np.asarray(res.model.F)))
    np.testing.assert_allclose(eig_fit[-2:], eig_true[-2:], atol=0.05)
    markov_true, S_true = markov_parameters(truth)
    markov_fit, S_fit = markov_parameters(res.model)
    assert np.max(np.abs(markov_fit - markov_true)) < 0.25 * np.max(np.abs(markov_true))
    np.testing.assert_allclose(S_fit, S_true, atol=0.1 * np.max(np.abs(S_true)))


def degenerate_problem(seed):
    """Two steps with an input: the regressions have one or two samples for three regressors
    [x; u], so the first M-step's R is singular (eigenvalues 0 and 0.15-0.9, measured) and the
    next E-step's filter produces NaN."""
    rng = np.random.default_rng(seed)
    model = je.LinearGaussian(0.9 * jnp.eye(2), jnp.eye(2), jnp.eye(2), jnp.eye(2),
                              B=jnp.zeros((2, 1)), D=jnp.zeros((2, 1)))  # fmt: skip
    ys, inputs = (jnp.asarray(rng.normal(size=(2, k))) for k in (2, 1))
    return model, je.Gaussian(jnp.zeros(2), jnp.eye(2)), ys, inputs


def test_a_degenerate_fit_is_flagged_not_silent():
    """It used to return NaN parameters and log-likelihoods with nothing to say so. The singular
    R is flagged whether rounding leaves it a Cholesky factor or not (seed 1's had one, and
    its fit ran on with status OK, before the pivots were checked)."""
    flags = je.EMStatus
    for seed in range(1, 4):
        model, prior, ys, inputs = degenerate_problem(seed)
        res = je.fit_em(model, ys, prior=prior, num_iters=3, inputs=inputs)
        assert int(res.status[0]) == flags.DEGENERATE_COVARIANCE, seed  # the first M-step's R
    model, prior, ys, inputs = degenerate_problem(0)
    res = je.fit_em(model, ys, prior=prior, num_iters=3, inputs=inputs)
    assert np.isnan(res.logliks[1]) and np.all(np.isnan(res.model.Q))
    assert int(res.status[0]) == flags.DEGENERATE_COVARIANCE
    # the E-step's filter on that Q (only the filter raises NOT_POSITIVE_DEFINITE), then NaN
    assert int(res.status[1]) & flags.NOT_POSITIVE_DEFINITE
    assert all(int(s) & flags.NONFINITE for s in res.status[1:])
    assert not bool(res.ok)
    with pytest.raises(Exception, match="DEGENERATE_COVARIANCE: a fitted covariance"):
        je.fit_em(model, ys, prior=prior, num_iters=3, inputs=inputs, throw=True)
    # with the regressions held, R (two samples of two outputs plus H P(k|T) H^T) is PD
    held = je.fit_em(model, ys, prior=prior, num_iters=3, inputs=inputs,
                     fixed=("F", "B", "Q", "H", "D", "prior.cov"))  # fmt: skip
    assert bool(held.ok), flags.describe(held.any_status)


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_status_under_jit_and_vmap(dtype):
    """A batch of a sound and a degenerate fit under ``jit(vmap(...))``: each run keeps its
    own flags, and the sound run's results equal its fit alone."""
    _, ys, _, init, init_prior = system(0, 2, 2, 40)
    init, init_prior, ys = je.astype((init, init_prior, ys), dtype)
    # the second run: every measurement equal, so the fitted R collapses to 0
    batch = jnp.stack([ys, jnp.ones_like(ys)])
    fits = jax.jit(jax.vmap(lambda y: je.fit_em(init, y, prior=init_prior, num_iters=4)))(batch)
    alone = je.fit_em(init, ys, prior=init_prior, num_iters=4)
    assert fits.status.shape == (2, 4) and fits.status.dtype == jnp.int32
    np.testing.assert_allclose(
        fits.logliks[0], alone.logliks, rtol=1e-5 if dtype == jnp.float32 else 1e-12
    )
    np.testing.assert_array_equal(fits.status[0], alone.status)
    assert bool(fits.ok[0]) and not bool(fits.ok[1])


def test_a_fall_of_the_loglik_is_flagged_beyond_rounding_only():
    for dtype in (jnp.float64, jnp.float32):
        # a tenth of the tolerance sqrt(eps) (|l_i| + |l_i-1| + 1), well above the spacing
        small = 0.1 * float(jnp.sqrt(jnp.finfo(dtype).eps)) * 191
        logliks = jnp.asarray([-100.0, -90.0, -95.0, -95.0 - small, -94.0], dtype)
        assert logliks[3] < logliks[2]
        status = je.em.decrease_status(logliks)
        assert status.tolist() == [0, 0, je.EMStatus.LOGLIK_DECREASED, 0, 0]


def small_noise_problem(seed, q):
    """TRUE_F seen by two random sensors, Q = R = q I, the prior's spread 100 I, 200 steps;
    EM starts from the truth perturbed by 0.05 and from 3 q I."""
    rng = np.random.default_rng(seed)
    H = rng.normal(size=(2, 4))
    truth = je.LinearGaussian(jnp.asarray(TRUE_F), jnp.asarray(H), q * jnp.eye(4), q * jnp.eye(2))
    prior = je.Gaussian(jnp.zeros(4), 100.0 * jnp.eye(4))
    ys = je.simulate(truth, prior, 200, jax.random.PRNGKey(seed)).y
    init = je.LinearGaussian(jnp.asarray(TRUE_F + 0.05 * rng.normal(size=(4, 4))),
                             jnp.asarray(H + 0.05 * rng.normal(size=(2, 4))),
                             3 * q * jnp.eye(4), 3 * q * jnp.eye(2))  # fmt: skip
    return ys, init, prior


@pytest.mark.parametrize(
    "seed, q, parallel, square_root",
    [(4, 1e-4, False, False), (4, 1e-4, True, False), (0, 1e-6, False, True)],
)
def test_float32_fit_matches_float64_where_noise_is_far_below_the_prior(
    seed, q, parallel, square_root
):
    """60 iterations in float32 end where float64's do: both fits scored by the float64 Kalman
    filter within 0.05 nats, every iteration OK. With eqs (2)-(3) in the textbook form (sums of
    the signal's size) the float32 fits were flagged from iteration 32, 42 and 0 (the log-
    likelihood fell, or Q was singular) and went on to NaN. At q = 1e-6 the covariance-form
    E-step fails in float32 from the first iteration, hence ``square_root``; in float64 it gives
    the covariance form's log-likelihoods to within that form's own rounding (1.4e-9 relative
    at q = 1e-6, Q 1e-8 of the prior's spread)."""
    ys, init, prior = small_noise_problem(seed, q)
    fit = lambda *args, **kw: je.fit_em(*args, num_iters=60, parallel=parallel, **kw)
    reference = fit(init, ys, prior=prior)
    init32, ys32, prior32 = je.astype((init, ys, prior), jnp.float32)
    single = fit(init32, ys32, prior=prior32, square_root=square_root)
    assert bool(reference.ok) and bool(single.ok), je.EMStatus.describe(single.any_status)
    score = lambda res: je.run(je.KalmanFilter(), *je.astype((res.model, ys), jnp.float64),
                               prior=je.astype(res.prior, jnp.float64)).loglik  # fmt: skip
    assert abs(float(score(single) - score(reference))) < 0.05
    if square_root:
        root = fit(init, ys, prior=prior, square_root=True)
        np.testing.assert_allclose(root.logliks, reference.logliks, rtol=1e-8)
        covariance_form = fit(init32, ys32, prior=prior32)
        assert int(covariance_form.status[0]) & je.EMStatus.NOT_POSITIVE_DEFINITE


def test_errors_name_the_argument():
    _, ys, _, init, prior = system(0, 3, 2, 20)
    with pytest.raises(ValueError, match="fixed"):
        je.fit_em(init, ys, prior=prior, num_iters=2, fixed=("G",))
    # one name alone is that name (it was refused, "expected names from (..., 'Q', ...), got 'Q'")
    np.testing.assert_array_equal(je.fit_em(init, ys, prior=prior, num_iters=2, fixed="Q").model.Q,
                                  init.Q)  # fmt: skip
    with pytest.raises(ValueError, match="num_iters"):
        je.fit_em(init, ys, prior=prior, num_iters=0)
    with pytest.raises(ValueError, match="ys"):
        je.fit_em(init, ys.at[3, 0].set(jnp.nan), prior=prior, num_iters=2)
    with pytest.raises(ValueError, match="model.G"):
        je.fit_em(je.LinearGaussian(init.F, init.H, init.Q, init.R, G=jnp.eye(3)), ys, prior=prior,
                  num_iters=2)  # fmt: skip
    with pytest.raises(ValueError, match="inputs"):
        je.fit_em(init, ys, prior=prior, num_iters=2, inputs=jnp.ones((20, 1)))
    with pytest.raises(ValueError, match="prior"):
        je.fit_em(init, ys, prior=je.Gaussian(jnp.zeros(2), jnp.eye(2)), num_iters=2)
    # one step has no transition to estimate F and Q from: they came out NaN without a word
    with pytest.raises(ValueError, match=r"^ys: has 1 steps; estimating \['F', 'Q'\]"):
        je.fit_em(init, ys[:1], prior=prior, num_iters=2)
    with pytest.raises(ValueError, match="^num_iters: must be a positive integer, got True"):
        je.fit_em(init, ys, prior=prior, num_iters=True)
    # the square-root filters (parallel, square_root) factor Q: a singular one gave NaN (status 13)
    singular = eqx.tree_at(lambda m: m.Q, init, jnp.diag(jnp.asarray([1.0, 1.0, 0.0])))
    with pytest.raises(ValueError, match="^model.Q: must be positive definite"):
        je.fit_em(singular, ys, prior=prior, num_iters=2, parallel=True)
    with pytest.raises(ValueError, match="^model.Q: must be positive definite"):
        je.fit_em(singular, ys, prior=prior, num_iters=2, square_root=True)
    # an integer F was fitted as integers ([[0, 0], ...] with ok=True); an integer Q failed in
    # the scan
    for name in ("F", "Q"):
        integer = eqx.tree_at(lambda m, name=name: getattr(m, name), init,
                              jnp.eye(3, dtype=jnp.int32))  # fmt: skip
        with pytest.raises(ValueError, match=f"^model.{name}: is int32; fit_em updates"):
            je.fit_em(integer, ys, prior=prior, num_iters=2)
    # a float32 model (or a float32 F beside float64 matrices) came out of the first iteration
    # in float64, a TypeError from inside the scan (a filter run promotes, but EM updates them)
    float32 = je.astype(init, jnp.float32)
    with pytest.raises(ValueError, match=r"^model: is float32, narrower .*the prior float64"):
        je.fit_em(float32, ys.astype(jnp.float32), prior=prior, num_iters=2)
    with pytest.raises(ValueError, match="^model: fit_em updates its matrices in one dtype"):
        je.fit_em(eqx.tree_at(lambda m: m.F, init, float32.F), ys, prior=prior, num_iters=2)
