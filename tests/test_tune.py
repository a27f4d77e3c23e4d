"""SPD parametrisations and gradient fitting."""

import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import optimistix as optx
import pytest

import jaxest as je
from jaxest import tune
from jaxest.filters import EKF, KalmanFilter
from jaxest.montecarlo import monte_carlo
from jaxest.tune import (
    FIXED_STEPS_LBFGS,
    fit,
    from_unconstrained,
    neg_loglik,
    supervised_mse,
    to_unconstrained,
)
from tests.lowering import programs_compiled


@pytest.mark.parametrize("kind", ["cholesky", "log_diagonal"])
def test_parametrisations_round_trip(kind):
    P = (
        jnp.asarray([[2.0, 0.3], [0.3, 1.0]])
        if kind == "cholesky"
        else jnp.diag(jnp.asarray([2.0, 0.5]))
    )
    np.testing.assert_allclose(from_unconstrained(to_unconstrained(P, kind), kind), P, rtol=1e-12)
    theta = jax.random.normal(jax.random.PRNGKey(0), to_unconstrained(P, kind).shape)
    assert np.all(np.linalg.eigvalsh(np.asarray(from_unconstrained(theta, kind))) > 0)


def scalar_problem(runs=6, T=200):
    truth = je.LinearGaussian(
        jnp.asarray([[0.95]]), jnp.asarray([[1.0]]), jnp.asarray([[0.1]]), jnp.asarray([[0.5]])
    )
    prior = je.Gaussian(jnp.zeros(1), jnp.eye(1))
    sims = monte_carlo(lambda k: je.simulate(truth, prior, T, k), jax.random.PRNGKey(0), runs)
    return truth, prior, sims


def test_unconstrained_transition_fit_finds_the_likelihood_maximum():
    truth, prior, sims = scalar_problem()
    loss = neg_loglik(KalmanFilter(), sims.y, prior=prior)
    start = je.LinearGaussian(jnp.asarray([[0.5]]), truth.H, truth.Q, truth.R)
    result = fit(start, loss, {"F": "unconstrained"}, optimizer=optax.lbfgs(), num_steps=30)
    grid = jnp.linspace(0.85, 1.0, 301)
    nll = jax.jit(jax.vmap(lambda f: loss(eqx.tree_at(lambda m: m.F, start, f[None, None]))))(grid)
    best = float(grid[np.argmin(nll)])
    assert abs(float(result.model.F[0, 0]) - best) <= float(grid[1] - grid[0])
    np.testing.assert_array_equal(result.model.Q, start.Q)  # only F moved
    with pytest.raises(ValueError, match="cholesky needs a square matrix"):
        fit(
            je.LinearGaussian(truth.F, jnp.ones((2, 1)), truth.Q, jnp.eye(2)),
            loss,
            {"H": "cholesky"},
        )


def test_maximum_likelihood_recovers_q_and_r_from_tenfold_error():
    truth, prior, sims = scalar_problem()
    wrong = je.LinearGaussian(truth.F, truth.H, 10 * truth.Q, truth.R / 10)
    result = fit(
        wrong,
        neg_loglik(KalmanFilter(), sims.y, prior=prior),
        {"Q": "cholesky", "R": "log_diagonal"},
        optimizer=optax.adam(0.05),
        num_steps=400,
    )
    assert result.losses[-1] < result.losses[0]
    assert_at_grid_maximum(result.model, truth, prior, sims)


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_optimistix_minimiser_reaches_the_maximum_with_one_copy_of_the_gradient(dtype):
    truth64, prior64, sims = scalar_problem()
    truth, prior, ys = je.astype((truth64, prior64, sims.y), dtype)
    wrong = je.LinearGaussian(truth.F, truth.H, 10 * truth.Q, truth.R / 10)
    traces = []
    nll = neg_loglik(KalmanFilter(), ys, prior=prior)

    def loss(model):  # counts the times fit traces it
        traces.append(1)
        return nll(model)

    params = {"Q": "cholesky", "R": "log_diagonal"}
    result = fit(wrong, loss, params, optimizer=optx.LBFGS(rtol=1e-6, atol=1e-6), num_steps=60)
    assert len(traces) == 1  # one evaluation per step, its gradient in the accepted branch
    assert result.losses.dtype == dtype and result.model.Q.dtype == dtype
    assert result.losses[0] == pytest.approx(float(nll(wrong)), rel=1e-5)  # the start
    assert np.all(np.diff(np.asarray(result.losses)) <= 0)  # accepted points only
    assert_at_grid_maximum(result.model, truth64, prior64, sims)
    traces.clear()
    # optax's line search steps float32 parameters in float64 (under x64): the model was
    # float64 in its trials, and the loss refused the float32 prior
    result = fit(wrong, loss, params, optimizer=optax.lbfgs(), num_steps=5)
    assert len(traces) == 3  # the first step and the zoom line search's two branches
    assert result.losses.dtype == dtype and result.model.Q.dtype == dtype


def test_minimiser_fits_a_batch_of_data_sets_in_one_vmap():
    """A Monte Carlo study of the tuning itself: one fit per data set under ``jax.vmap`` gives
    each data set's own fit. (``optax.lbfgs()`` under the same ``vmap`` of 8 data sets did not
    finish in 100 s, where each alone takes 2 s: docs/performance.md.)"""
    truth, prior, sims = scalar_problem(runs=4, T=100)
    wrong = je.LinearGaussian(truth.F, truth.H, 10 * truth.Q, truth.R / 10)
    params = {"Q": "log_diagonal", "R": "log_diagonal"}

    def fitted_variances(ys):
        loss = neg_loglik(KalmanFilter(), ys[None], prior=prior)
        model = fit(wrong, loss, params, optimizer=FIXED_STEPS_LBFGS, num_steps=30).model
        return jnp.stack([model.Q[0, 0], model.R[0, 0]])

    batched = jax.vmap(fitted_variances)(sims.y)
    one_by_one = jax.jit(fitted_variances)
    for ys, variances in zip(sims.y, batched, strict=True):
        np.testing.assert_allclose(variances, one_by_one(ys), rtol=1e-6)
    assert len({float(v) for v in batched[:, 0]}) == 4  # four data sets, four fits


@pytest.mark.skipif(
    not tune._line_search_miscompiled_here(),
    reason="the warning is for jaxlib 0.10's CPU, where the hang was seen",
)
def test_optax_line_search_under_vmap_warns_as_it_is_traced():
    """optax.lbfgs() under ``jax.vmap`` over data sets can loop forever on jaxlib 0.10's CPU
    (docs/performance.md): the user is told while the program is traced (``eval_shape``: it is
    never run), and only for a line search whose losses differ across the batch."""
    truth, prior, sims = scalar_problem(runs=2, T=20)
    wrong = je.LinearGaussian(truth.F, truth.H, 10 * truth.Q, truth.R / 10)
    params = {"Q": "log_diagonal", "R": "log_diagonal"}

    def fitted_q(ys, optimizer):
        loss = neg_loglik(KalmanFilter(), ys[None], prior=prior)
        return fit(wrong, loss, params, optimizer=optimizer, num_steps=3).model.Q

    with pytest.warns(RuntimeWarning, match="optimistix minimiser under vmap"):
        jax.eval_shape(jax.vmap(lambda ys: fitted_q(ys, optax.lbfgs())), sims.y)
    one_data_set = sims.y[0]
    quiet = [
        lambda: jax.eval_shape(lambda ys: fitted_q(ys, optax.lbfgs()), one_data_set),
        lambda: jax.eval_shape(jax.vmap(lambda ys: fitted_q(ys, optax.adam(0.1))), sims.y),
        lambda: jax.eval_shape(jax.vmap(lambda ys: fitted_q(ys, FIXED_STEPS_LBFGS)), sims.y),
        # batched over something the losses do not depend on
        lambda: jax.eval_shape(jax.vmap(lambda _: fitted_q(one_data_set, optax.lbfgs())), sims.y),
    ]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for trace in quiet:
            trace()
    # the alarm on the loss keeps its derivative (a custom_vmap alone has none)
    alarmed = lambda x: tune._warn_if_batched(3.0 * x) ** 2
    assert jax.grad(alarmed)(2.0) == 36.0 and jax.jvp(alarmed, (2.0,), (1.0,))[1] == 36.0


def test_minimiser_stops_at_its_tolerances():
    """A quartic, which BFGS approaches slowly: with loose tolerances the minimiser stops, as
    ``optimistix.minimise`` would, and the remaining steps hold its point."""
    model = je.LinearGaussian(jnp.eye(2), jnp.eye(2), jnp.eye(2), jnp.eye(2))
    target = jnp.asarray([[2.0, 0.5], [-1.0, 3.0]])
    loss = lambda m: jnp.sum((m.F - target) ** 4)
    params = {"F": "unconstrained"}
    loose = fit(model, loss, params, optimizer=optx.BFGS(rtol=1e-2, atol=1e-2), num_steps=60)
    losses = np.asarray(loose.losses)
    stopped = int(np.argmax(losses == losses[-1]))
    assert 0 < stopped < 30 and losses[-1] < 1e-2 * losses[0]
    tight = fit(model, loss, params, optimizer=optx.BFGS(rtol=1e-9, atol=1e-9), num_steps=60)
    assert tight.losses[-1] < 1e-3 * losses[-1]  # it would have gone on
    with pytest.raises(ValueError, match="^optimizer: expected an optax"):
        fit(model, loss, params, optimizer="lbfgs")
    with pytest.raises(ValueError, match="^optimizer: NelderMead keeps no accepted point's loss"):
        fit(model, loss, params, optimizer=optx.NelderMead(rtol=1e-3, atol=1e-3))


@pytest.mark.parametrize(
    "optimizer", [optax.sgd(0.1), optx.GradientDescent(0.1, rtol=1e-9, atol=1e-9)],
    ids=["optax", "optimistix"],
)  # fmt: skip
def test_a_loss_that_turns_nan_is_flagged_and_the_last_finite_iterate_kept(optimizer):
    """Descent on (F - 3)^2 from F = 1, with the loss NaN from F = 2 on (where a filter's
    likelihood can turn NaN): fit returned the NaN iterate, with nothing to say so."""
    model = je.LinearGaussian(jnp.eye(1), jnp.eye(1), jnp.eye(1), jnp.eye(1))
    loss = lambda m: jnp.where(m.F[0, 0] < 2.0, (m.F[0, 0] - 3.0) ** 2, jnp.nan)
    result = fit(model, loss, {"F": "unconstrained"}, optimizer=optimizer, num_steps=20)
    assert int(result.status) == je.Status.NONFINITE
    assert np.any(np.isnan(np.asarray(result.losses)))
    assert 1.0 < float(result.model.F[0, 0]) < 2.0
    fine = fit(model, loss, {"F": "unconstrained"}, optimizer=optimizer, num_steps=1)
    assert int(fine.status) == je.Status.OK


def assert_at_grid_maximum(fitted, truth, prior, sims):
    """``fitted``'s Q and R are the likelihood's maximiser found by a fine grid over
    (log q, log r), within its spacing."""
    grid = jnp.linspace(-1.2, 1.2, 61)
    nll = jax.jit(
        jax.vmap(
            jax.vmap(
                lambda a, b: neg_loglik(KalmanFilter(), sims.y, prior=prior)(
                    je.LinearGaussian(truth.F, truth.H, truth.Q * jnp.exp(a), truth.R * jnp.exp(b))
                ),
                (None, 0),
            ),
            (0, None),
        )
    )(grid, grid)
    i, j = np.unravel_index(np.argmin(nll), nll.shape)
    np.testing.assert_allclose(np.log(fitted.Q[0, 0] / truth.Q[0, 0]), grid[i], atol=0.05)
    np.testing.assert_allclose(np.log(fitted.R[0, 0] / truth.R[0, 0]), grid[j], atol=0.05)


def test_free_mask_holds_entries_fixed_and_supervised_loss_lowers_error():
    truth, prior, sims = scalar_problem(runs=4, T=100)
    wrong = je.LinearGaussian(truth.F, truth.H, 10 * truth.Q, truth.R / 10)
    loss = supervised_mse(KalmanFilter(), sims.y, sims.states, prior=prior)
    result = fit(
        wrong,
        loss,
        {"Q": "log_diagonal", "R": "log_diagonal"},
        free={"R": jnp.zeros(1)},
        num_steps=150,
    )
    assert float(result.model.R[0, 0]) == pytest.approx(float(wrong.R[0, 0]), rel=1e-12)
    assert loss(result.model) < loss(wrong)


def test_fit_compiles_one_program():
    """Parametrisations, steps and fitted matrices in one program: outside ``jit`` the
    parametrisations and the final matrices ran op by op (26 programs for this fit)."""
    rng = np.random.default_rng(5)
    n = 7
    model = je.LinearGaussian(0.9 * jnp.eye(n), jnp.asarray(rng.normal(size=(3, n))),
                              0.1 * jnp.eye(n), 0.5 * jnp.eye(3))  # fmt: skip
    prior = je.Gaussian(jnp.zeros(n), jnp.eye(n))
    ys = jnp.asarray(rng.normal(size=(20, 3)))
    loss = lambda m: -je.run(EKF(), m, ys, prior=prior).loglik
    fits = []

    def fitting():
        fits.append(fit(model, loss, {"Q": "log_diagonal", "R": "cholesky"}, num_steps=3))
        return fits[-1].losses

    assert programs_compiled(fitting) == 1
    assert fits[0].losses[-1] < fits[0].losses[0]


def test_fit_rejects_unknown_parameters():
    truth, prior, sims = scalar_problem(runs=2, T=10)
    with pytest.raises(ValueError, match="params"):
        fit(truth, lambda m: 0.0, ["S"])
    with pytest.raises(ValueError, match="params\\['Q'\\]"):
        fit(truth, lambda m: 0.0, {"Q": "eigen"})


def test_losses_and_fit_name_bad_arguments():
    """These raised a misleading ys error from inside run, TypeErrors from broadcasting, an
    MLIRError or a LinAlgError, or (a mask for a parameter not fitted) nothing at all."""
    truth, prior, sims = scalar_problem(runs=2, T=10)
    loss = neg_loglik(KalmanFilter(), sims.y, prior=prior)
    cases = [
        ("^ys: expected a batch", lambda: neg_loglik(KalmanFilter(), sims.y[0], prior=prior)),
        ("^states: expected shape", lambda: supervised_mse(KalmanFilter(), sims.y, sims.states[..., :0], prior=prior)(truth)),
        (r"^free\['Q'\]: expected a mask of shape \(1, 1\)", lambda: fit(truth, loss, ["Q"], free={"Q": jnp.ones(2)})),
        ("^free: 'R' is not one of the fitted", lambda: fit(truth, loss, ["Q"], free={"R": jnp.ones((1, 1))})),
        ("^num_steps", lambda: fit(truth, loss, ["Q"], num_steps=-1)),
        # an integer matrix reached optax's grad, which raised a TypeError
        (r"^params\['F'\]: expected a floating-point matrix to fit, got int32", lambda: fit(eqx.tree_at(lambda m: m.F, truth, jnp.ones((1, 1), jnp.int32)), loss, {"F": "unconstrained"})),
        ("^loss: expected a function, got int", lambda: fit(truth, 3, ["Q"])),  # a TypeError
        ("^loss: must return a scalar, got shape \\(1, 1\\)", lambda: fit(truth, lambda m: m.Q, ["Q"])),
        ("^estimator: expected a jaxest estimator", lambda: neg_loglik("kalman", sims.y, prior=prior)),
        (r"^params\['Q'\]: expected a floating-point", lambda: fit(eqx.tree_at(lambda m: m.Q, truth, jnp.ones((1, 1), jnp.int32)), loss, ["Q"])),
        ("^count", lambda: je.log_variance_standard_errors(truth, loss, 0)),
        # the runs are traced under the losses' vmap: an infinite entry gave a NaN loss
        ("^ys: contains \\+-inf", lambda: neg_loglik(KalmanFilter(), sims.y.at[1, 3, 0].set(jnp.inf), prior=prior)),
    ]  # fmt: skip
    for message, call in cases:
        with pytest.raises(ValueError, match=message):
            call()
    assert fit(truth, loss, ["Q"], num_steps=0).losses.shape == (0,)  # the start, unchanged
    # one path, not its letters ("prior.cov" was read as "p", "r", ...)
    start = ModelAndPrior(truth, prior)
    one = fit(start, lambda mp: jnp.sum((mp.prior.cov - 2.0) ** 2), "prior.cov", num_steps=3)
    assert 1.0 < float(one.model.prior.cov[0, 0]) < 2.0


class ModelAndPrior(eqx.Module):
    model: je.LinearGaussian
    prior: je.Gaussian


@pytest.mark.parametrize(
    "Q, kind, message",
    [
        ([[0.1, 0.05], [0.05, 0.1]], "log_diagonal", "off-diagonal entries up to 0.05"),
        ([[0.1, 0.0], [0.0, 0.0]], "log_diagonal", "positive diagonal entries"),
        ([[0.1, 0.0], [0.0, 0.0]], "cholesky", "positive definite"),
        ([[0.1, 0.2], [0.2, 0.1]], "cholesky", "positive definite"),
        ([[0.1, 0.05], [0.0, 0.1]], "cholesky", "symmetric"),
    ],
)
def test_fit_rejects_a_start_its_parametrisation_cannot_represent(Q, kind, message):
    # these started from NaN (singular, indefinite, zero variance) or silently from another
    # matrix (log_diagonal dropped the off-diagonal, cholesky read the lower triangle)
    model = je.LinearGaussian(0.9 * jnp.eye(2), jnp.eye(2)[:1], jnp.asarray(Q), jnp.eye(1))
    with pytest.raises(ValueError, match=rf"^params\['Q'\]: .*{message}"):
        fit(model, lambda m: 0.0, {"Q": kind})


def test_log_variance_standard_errors_from_a_finite_difference_hessian():
    """The observed information of [log diag Q, log diag R] against central differences of the
    total negative log-likelihood (second differences, step 1e-3), on a 2-state model."""
    jax.config.update("jax_enable_x64", True)
    F = jnp.array([[0.9, 0.1], [0.0, 0.8]])
    H = jnp.array([[1.0, 0.0], [0.5, 1.0]])
    model = je.LinearGaussian(
        F, H, jnp.diag(jnp.array([0.04, 0.09])), jnp.diag(jnp.array([0.25, 0.16]))
    )
    prior = je.Gaussian(jnp.zeros(2), jnp.eye(2))
    ys = monte_carlo(lambda k: je.simulate(model, prior, 60, k), jax.random.key(4), 5).y
    loss = neg_loglik(KalmanFilter(), ys, prior=prior)
    count = ys.shape[0] * ys.shape[1]
    se = je.log_variance_standard_errors(model, loss, count)
    theta = np.asarray(je.log_variances(model))
    np.testing.assert_allclose(theta, np.log([0.04, 0.09, 0.25, 0.16]), rtol=1e-14)

    def total(t):
        Q, R = jnp.diag(jnp.exp(t[:2])), jnp.diag(jnp.exp(t[2:]))
        return float(count * loss(je.LinearGaussian(F, H, Q, R)))

    h, n = 1e-3, theta.size
    step = lambda i, s: s * h * np.eye(n)[i]
    hessian = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            hessian[i, j] = (
                total(theta + step(i, 1) + step(j, 1)) - total(theta + step(i, 1) - step(j, 1))
                - total(theta - step(i, 1) + step(j, 1)) + total(theta - step(i, 1) - step(j, 1))
            ) / (4 * h * h)  # fmt: skip
    np.testing.assert_allclose(se, np.sqrt(np.diag(np.linalg.inv(hessian))), rtol=1e-4)


def test_losses_pass_checkpoint_to_run():
    """``checkpoint=True`` reaches ``run``: the compiled gradient keeps a fraction of the
    intermediates (it recomputes the steps) and equals the one that stores them."""
    truth, prior, sims = scalar_problem(runs=3, T=200)
    for make in (
        lambda ck: neg_loglik(EKF(), sims.y, prior=prior, checkpoint=ck),
        lambda ck: supervised_mse(EKF(), sims.y, sims.states, prior=prior, checkpoint=ck),
    ):
        grads, temp = {}, {}
        for ck in (False, True):
            loss = make(ck)
            grad = jax.jit(
                jax.grad(lambda q, loss=loss: loss(eqx.tree_at(lambda m: m.Q, truth, q)))
            )
            temp[ck] = grad.lower(truth.Q).compile().memory_analysis().temp_size_in_bytes
            grads[ck] = grad(truth.Q)
        np.testing.assert_allclose(grads[True], grads[False], rtol=1e-12)
        assert temp[True] < temp[False] / 2
