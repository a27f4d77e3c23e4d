"""Bad input raises ValueError naming the argument, before anything is traced."""

import jax.numpy as jnp
import numpy as np
import pytest

import jaxest as je
from jaxest.filters import SVDEKF, KalmanFilter


def good():
    model = je.LinearGaussian(0.9 * jnp.eye(2), jnp.ones((1, 2)), 0.1 * jnp.eye(2), jnp.eye(1))
    return model, jnp.zeros((10, 1)), je.Gaussian(jnp.zeros(2), jnp.eye(2))


def test_good_arguments_pass():
    model, ys, prior = good()
    assert je.run(KalmanFilter(), model, ys, prior=prior).mean.shape == (10, 2)


@pytest.mark.parametrize(
    "change, match",
    [
        (lambda m, y, p: (m, y[:, :, None], p), "ys"),
        (lambda m, y, p: (m, jnp.zeros((10, 3)), p), "model.R"),
        (lambda m, y, p: (je.LinearGaussian(jnp.eye(3), m.H, m.Q, m.R), y, p), "model.F"),
        (lambda m, y, p: (je.LinearGaussian(m.F, jnp.ones((1, 3)), m.Q, m.R), y, p), "model.H"),
        (lambda m, y, p: (je.LinearGaussian(m.F, m.H, jnp.ones((2, 3)), m.R), y, p), "model.Q"),
        (
            lambda m, y, p: (
                je.LinearGaussian(m.F, m.H, jnp.asarray([[1.0, 0.5], [0.0, 1.0]]), m.R),
                y,
                p,
            ),
            "model.Q: must be symmetric",
        ),
        (
            lambda m, y, p: (
                je.LinearGaussian(m.F, m.H, jnp.asarray([[1.0, 2.0], [2.0, 1.0]]), m.R),
                y,
                p,
            ),
            "model.Q: must be positive semidefinite",
        ),
        (
            lambda m, y, p: (je.LinearGaussian(m.F, m.H, m.Q, -m.R), y, p),
            "model.R: must be positive definite",
        ),
        (
            lambda m, y, p: (je.LinearGaussian(m.F, m.H, m.Q.at[0, 0].set(jnp.nan), m.R), y, p),
            "model.Q: contains NaN",
        ),
        (
            lambda m, y, p: (
                m,
                y,
                je.Gaussian(jnp.zeros(2), jnp.asarray([[1.0, 0.0], [0.0, jnp.nan]])),
            ),
            "init.cov: contains NaN",
        ),
        (lambda m, y, p: (m, y, je.Gaussian(jnp.zeros(2), jnp.ones((2, 3)))), "init.cov"),
        (lambda m, y, p: (m, y, je.Gaussian(jnp.zeros(3), jnp.eye(3))), "model"),
        (lambda m, y, p: (m, y, (p.mean, p.cov)), "init"),
        (
            lambda m, y, p: (je.LinearGaussian(jnp.stack([m.F] * 5), m.H, m.Q, m.R), y, p),
            "model.F: time-varying",
        ),
    ],
)
def test_bad_arguments_name_the_argument(change, match):
    model, ys, prior = change(*good())
    with pytest.raises(ValueError, match=match):
        je.run(SVDEKF(), model, ys, prior=prior)


def test_mismatched_input_length():
    model, ys, prior = good()
    model = je.LinearGaussian(model.F, model.H, model.Q, model.R, B=jnp.ones((2, 1)))
    with pytest.raises(ValueError, match="inputs: has 4 time steps but the measurements have 10"):
        je.run(KalmanFilter(), model, ys, inputs=jnp.zeros((4, 1)), prior=prior)


def test_nonlinear_model_shapes_checked():
    model = je.NonlinearGaussian(lambda x, u: x[:1], lambda x, u: x, jnp.eye(2), jnp.eye(2))
    with pytest.raises(ValueError, match="model transition mean"):
        je.run(
            KalmanFilter(), model, jnp.zeros((5, 2)), prior=je.Gaussian(jnp.zeros(2), jnp.eye(2))
        )
    with pytest.raises(ValueError, match="noise_gain"):
        je.NonlinearGaussian(
            lambda x, u: x,
            lambda x, u: x,
            jnp.eye(2),
            jnp.eye(2),
            noise_gain=lambda x, u: jnp.eye(2),
            noise_on_input=True,
        )


def test_missing_rows_are_skipped_exactly():
    """A NaN entry gives the same result as a model without that measurement row."""
    model, _, prior = good()
    full = je.LinearGaussian(
        model.F,
        jnp.asarray([[1.0, 0.0], [0.0, 1.0]]),
        model.Q,
        jnp.asarray([[1.0, 0.3], [0.3, 2.0]]),
    )
    ys = np.random.default_rng(0).normal(size=(10, 2))
    ys[:, 1] = np.nan
    only_first = je.LinearGaussian(
        model.F, jnp.asarray([[1.0, 0.0]]), model.Q, jnp.asarray([[1.0]])
    )
    a = je.run(SVDEKF(), full, jnp.asarray(ys), prior=prior)
    b = je.run(SVDEKF(), only_first, jnp.asarray(ys[:, :1]), prior=prior)
    np.testing.assert_allclose(a.mean, b.mean, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(a.loglik, b.loglik, rtol=1e-12)
