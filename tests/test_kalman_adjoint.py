"""The Kalman log-likelihood's closed-form (Fisher identity) derivative, jaxest.filters.fisher,
against autodiff through the recursion (``closed_form_gradient=False``) and central differences:
every parameter, inputs, missing data, time-varying matrices, jit, vmap, float32, forward mode and
Hessians, and the autodiff gradients of the other outputs."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxest as je
from jaxest.filters import KalmanFilter

CLOSED_FORM, AUTODIFF = KalmanFilter(), KalmanFilter(closed_form_gradient=False)
T = 40


def problem(time_varying: bool, dtype=jnp.float64):
    """A random 3-state, 2-measurement, 1-input model with B and D, its prior, inputs and
    simulated measurements with one entry and one whole row missing."""
    rng = np.random.default_rng(1)
    n, m, p = 3, 2, 1
    F = 0.9 * np.linalg.qr(rng.normal(size=(n, n)))[0]
    A, C = rng.normal(size=(n, n)), rng.normal(size=(m, m))
    Q, R = A @ A.T / n + 0.1 * np.eye(n), C @ C.T / m + 0.2 * np.eye(m)
    H = rng.normal(size=(m, n))
    if time_varying:  # a leading time axis on F and R
        F = F * np.linspace(0.8, 1.0, T)[:, None, None]
        R = R * np.linspace(0.5, 1.5, T)[:, None, None]
    cast = lambda a: jnp.asarray(a, dtype)
    model = je.LinearGaussian(
        cast(F), cast(H), cast(Q), cast(R), B=cast(rng.normal(size=(n, p))),
        D=cast(rng.normal(size=(m, p))),
    )  # fmt: skip
    B0 = rng.normal(size=(n, n))
    prior = je.Gaussian(cast(rng.normal(size=n)), cast(B0 @ B0.T / n + 0.5 * np.eye(n)))
    inputs = cast(rng.normal(size=(T, p)))
    ys = je.simulate(model, prior, T, jax.random.PRNGKey(2), inputs=inputs).y
    return model, prior, ys.at[3, 0].set(jnp.nan).at[7].set(jnp.nan), inputs


def loglik(filt, save=None):
    """(model, prior, ys, inputs) -> log p(y) by ``filt``."""
    return lambda model, prior, ys, inputs: (
        je.run(filt, model, ys, prior=prior, inputs=inputs, save=save).loglik
    )


def grad_all(filt, args, save=None):
    return jax.jit(jax.grad(loglik(filt, save), argnums=(0, 1, 2, 3)))(*args)


def assert_same_gradient(closed, auto, rtol):
    """Leaf by leaf; the prior covariance's gradients compared by their symmetric parts (the
    filter reads P0 unsymmetrised; the closed form is the symmetric gradient)."""
    paths = jax.tree_util.tree_leaves_with_path(auto)
    for (path, a), c in zip(paths, jax.tree.leaves(closed), strict=True):
        name = jax.tree_util.keystr(path)
        if name == "[1].cov":
            a, c = 0.5 * (a + a.T), 0.5 * (c + c.T)
        scale = np.max(np.abs(np.asarray(a)))
        np.testing.assert_allclose(c, a, rtol=rtol, atol=rtol * scale, err_msg=name)


@pytest.mark.parametrize("time_varying", [False, True], ids=["time_invariant", "time_varying"])
def test_equals_autodiff_for_every_parameter(time_varying):
    """F, H, Q, R, B, D, m0, P0, ys and inputs, with missing data, in float64 to rtol 1e-9; the
    same when the caller saves nothing (run keeps the fields the rule needs)."""
    args = problem(time_varying)
    auto = grad_all(AUTODIFF, args)
    assert_same_gradient(grad_all(CLOSED_FORM, args), auto, 1e-9)
    assert_same_gradient(grad_all(CLOSED_FORM, args, je.SaveAt(fields=())), auto, 1e-9)
    assert np.all(np.asarray(auto[2])[7] == 0)  # the missing row has no gradient


def test_central_differences_forward_mode_and_hessian():
    """The closed-form gradient along a random direction of every parameter (symmetric for the
    covariances) equals the central difference of log p(y) and the forward-mode (jvp) derivative; the Hessian in the log noise
    scales (forward over reverse through the rule) equals autodiff's."""
    model, prior, ys, inputs = problem(False)
    params = (model, prior)
    flat, unravel = jax.flatten_util.ravel_pytree(params)
    model_dir, prior_dir = unravel(jax.random.normal(jax.random.PRNGKey(3), flat.shape))
    sym = lambda a: 0.5 * (a + a.T)  # covariances move along symmetric directions
    model_dir = eqx.tree_at(lambda m: (m.Q, m.R), model_dir, (sym(model_dir.Q), sym(model_dir.R)))
    direction, _ = jax.flatten_util.ravel_pytree(
        (model_dir, je.Gaussian(prior_dir.mean, sym(prior_dir.cov)))
    )
    f = jax.jit(lambda z: loglik(CLOSED_FORM)(*unravel(z), ys, inputs))
    slope = jnp.vdot(jax.jit(jax.grad(f))(flat), direction)
    h = 1e-5
    fd = (f(flat + h * direction) - f(flat - h * direction)) / (2 * h)
    np.testing.assert_allclose(slope, fd, rtol=1e-6)
    _, tangent = jax.jit(lambda z: jax.jvp(f, (z,), (direction,)))(flat)
    np.testing.assert_allclose(tangent, slope, rtol=1e-9)

    def of_scales(filt):
        def fn(log_scales):
            scaled = eqx.tree_at(
                lambda m: (m.Q, m.R), model,
                (jnp.exp(log_scales[0]) * model.Q, jnp.exp(log_scales[1]) * model.R),
            )  # fmt: skip
            return loglik(filt)(scaled, prior, ys, inputs)

        return jax.jit(jax.hessian(fn))(jnp.zeros(2))

    np.testing.assert_allclose(of_scales(CLOSED_FORM), of_scales(AUTODIFF), rtol=1e-8)


def test_vmap_and_float32():
    """Under jit and vmap over runs and Q scales, float64 and float32: the closed form equals
    autodiff (float32: to float32 accuracy, and the float64 value). In float64 nothing is saved,
    as in je.neg_loglik."""
    model, prior, _, inputs = problem(False)
    keys = jax.random.split(jax.random.PRNGKey(4), 3)
    ys = jax.vmap(lambda k: je.simulate(model, prior, T, k, inputs=inputs).y)(keys)
    scales = jnp.array([0.5, 1.0, 2.0])

    def batched(filt, dtype, save=None):
        mdl, pr, u = je.astype((model, prior, inputs), dtype)

        def one(scale, y):
            scaled = eqx.tree_at(lambda m: m.Q, mdl, scale * mdl.Q)
            return loglik(filt, save)(scaled, pr, y, u)

        return jax.jit(jax.vmap(jax.value_and_grad(one)))(scales.astype(dtype), ys.astype(dtype))

    v64, g64 = batched(CLOSED_FORM, jnp.float64, je.SaveAt(fields=()))
    g_auto = batched(AUTODIFF, jnp.float64)[1]
    np.testing.assert_allclose(g64, g_auto, rtol=1e-9)
    v32, g32 = batched(CLOSED_FORM, jnp.float32)
    assert v32.dtype == g32.dtype == jnp.float32
    np.testing.assert_allclose(g32, batched(AUTODIFF, jnp.float32)[1], rtol=1e-3, atol=1e-2)
    np.testing.assert_allclose(g32, g64, rtol=1e-3, atol=1e-2)
    np.testing.assert_allclose(v32, v64, rtol=1e-5)


@pytest.mark.parametrize("singular", ["zero_variance", "rank_one"])
def test_a_singular_Q_gives_autodiffs_gradient_also_traced(singular):
    """A singular Q (a noise that drives some states only): the rule inverts no Q, so the
    gradient in every parameter is autodiff's also where Q is traced. The form with Q^-1 gave NaN
    there (and autodiff was run instead where Q's values were known)."""
    model, prior, ys, inputs = problem(False)
    Q = np.diag([0.0, 0.3, 0.2]) if singular == "zero_variance" else np.full((3, 3), 0.1)
    args = (eqx.tree_at(lambda m: m.Q, model, jnp.asarray(Q)), prior, ys, inputs)
    assert_same_gradient(grad_all(CLOSED_FORM, args), grad_all(AUTODIFF, args), 1e-9)


def test_noise_far_below_the_state_uncertainty_keeps_the_gradient_accurate():
    """Q and R down to 1e-7 of the state's prior variance, float32 against float64 autodiff; Q
    = 1e-12 in float64. Formed with Q^-1 (R^-1) twice around a difference of covariances of the
    state's size, the rule was off by 17 % in H at R = 1e-7 (float32) and by half in Q at
    Q = 1e-12 (float64) here (benchmarks/fisher_rule.py has the grid)."""
    F, H = jnp.array([[1.0, 0.1], [0.0, 1.0]]), jnp.array([[1.0, 0.0]])
    prior = je.Gaussian(jnp.zeros(2), jnp.eye(2))
    truth = je.LinearGaussian(F, H, 1e-2 * jnp.eye(2), jnp.array([[0.1]]))
    ys = je.simulate(truth, prior, 200, jax.random.PRNGKey(1)).y
    scales = jnp.array([[1e-2, 1e-1], [1e-6, 1e-1], [1e-2, 1e-7], [1e-6, 1e-5], [1e-12, 1e-1]])

    def gradients(filt, dtype, rows):
        def one(scale):
            model = je.LinearGaussian(F, H, scale[0] * jnp.eye(2), scale[1] * jnp.eye(1))
            return jax.grad(
                lambda m: loglik(filt)(m, je.astype(prior, dtype), je.astype(ys, dtype), None)
            )(je.astype(model, dtype))

        return jax.jit(jax.vmap(one))(je.astype(scales[rows], dtype))

    reference = gradients(AUTODIFF, jnp.float64, slice(None))
    for dtype, rows, rtol in [(jnp.float64, slice(None), 1e-8), (jnp.float32, slice(4), 1e-3)]:
        closed = gradients(CLOSED_FORM, dtype, rows)
        for name in ("F", "H", "Q", "R"):
            got, want = getattr(closed, name), getattr(reference, name)[rows]
            scale = np.max(np.abs(np.asarray(want)), axis=(1, 2), keepdims=True)
            relative = np.abs(np.asarray(got, np.float64) - want) / scale
            assert np.all(relative < rtol), (name, np.dtype(dtype).name, relative.max(axis=(1, 2)))


def test_a_run_resumed_at_k0_on_a_time_varying_model():
    """From k0 = 5 the filter reads F_5, R_5, ...; so must the rule's smoother (it read F_0, ...:
    the closed form was off by up to 18 against autodiff while the values were right)."""
    model, prior, ys, inputs = problem(True)
    grads = [
        jax.jit(jax.grad(
            lambda m, p, y, u, filt=filt: je.run(filt, m, y, prior=p, inputs=u, k0=5).loglik,
            argnums=(0, 1, 2, 3),
        ))(model, prior, ys[: T - 5], inputs[: T - 5])
        for filt in (CLOSED_FORM, AUTODIFF)
    ]  # fmt: skip
    assert_same_gradient(*grads, 1e-9)


def test_saving_nothing_runs_the_filter_once():
    """With ``SaveAt(fields=())`` (as ``neg_loglik`` runs it) the result holds no per-step
    arrays, and the gradient runs two scans, the filter's and the smoother's: ``run`` keeps
    the fields the rule needs instead of the rule running the filter again."""
    model, prior, ys, inputs = problem(False)
    nothing = je.SaveAt(fields=())
    result = je.run(CLOSED_FORM, model, ys, prior=prior, inputs=inputs, save=nothing)
    assert all(getattr(result, f) is None for f in ("mean", "cov", "predicted_cov", "status"))
    jaxpr = jax.make_jaxpr(jax.grad(loglik(CLOSED_FORM, nothing)))(model, prior, ys, inputs)
    assert str(jaxpr).count(" scan[") == 2  # nested jaxprs print inline


def test_other_outputs_keep_autodiff():
    """A loss of the filtered means and the log-likelihood together: the means' part is
    differentiated by autodiff, the sum matches autodiff throughout."""
    args = problem(False)

    def loss(filt):
        def fn(model, prior, ys, inputs):
            result = je.run(filt, model, ys, prior=prior, inputs=inputs)
            return result.loglik + jnp.sum(result.mean**2) + jnp.sum(result.loglik_terms)

        return jax.jit(jax.grad(fn, argnums=(0, 1, 2, 3)))(*args)

    assert_same_gradient(loss(CLOSED_FORM), loss(AUTODIFF), 1e-9)
