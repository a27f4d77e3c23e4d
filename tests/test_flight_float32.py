"""benchmarks/flight_float32.py's pieces (docs/robustness.md, "The 23-state flight model in
float32"): the change of state units it runs the filters in, and the condition number it reports.
The script itself filters the real records (about 90 s) and is run by hand."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxest as je
from tests import benchmark_scripts

flight_float32 = benchmark_scripts.load("flight_float32")


def test_largest_condition_number_is_the_worst_steps_eigenvalue_ratio():
    rotation = jnp.array([[0.6, -0.8], [0.8, 0.6]])
    covs = jnp.stack(
        [
            jnp.diag(jnp.array([2.0, 200.0])),
            rotation @ jnp.diag(jnp.array([3.0, 1e-3])) @ rotation.T,
        ]
    )
    assert flight_float32.largest_condition_number(covs) == pytest.approx(3e3, rel=1e-12)
    indefinite = jnp.concatenate([covs, jnp.diag(jnp.array([1.0, -1e-9]))[None]])
    assert flight_float32.largest_condition_number(indefinite) == np.inf


@pytest.mark.parametrize("Filter", [je.SVDEKF, je.ImprovedSVDKF, je.EKF])
def test_the_scaled_state_filters_to_the_same_means_and_likelihood(Filter):
    # metres beside radians, as in the flight model: in float64 the change of units is exact up to
    # rounding, so the scaled run's means mapped back are the run's own
    f = lambda x, u: jnp.array(
        [x[0] + 50.0 * x[1] + u[0], 0.95 * x[1] + 1e-3 * jnp.tanh(x[0] / 1e3)]
    )
    h = lambda x, u: jnp.array([x[0], jnp.sin(x[1])])
    G = lambda x, u: jnp.eye(2) * (1.0 + 0.1 * jnp.cos(x[1]))
    model = je.NonlinearGaussian(
        f, h, jnp.diag(jnp.array([1.0, 1e-8])), jnp.diag(jnp.array([4.0, 1e-6])), noise_gain=G
    )
    prior = je.Gaussian(jnp.array([1e3, 0.01]), jnp.diag(jnp.array([100.0, 1e-4])))
    inputs = jnp.full((60, 1), 0.5)
    sim = je.simulate(model, prior, 60, jax.random.key(3), inputs=inputs)
    s = jnp.sqrt(jnp.diag(prior.cov))
    given = je.run(Filter(), model, sim.y, inputs=inputs, prior=prior)
    scaled_model, scaled_prior = flight_float32.scaled(model, prior, s)
    scaled = je.run(Filter(), scaled_model, sim.y, inputs=inputs, prior=scaled_prior)
    assert int(given.any_status) == 0 and int(scaled.any_status) == 0
    # compared in the scaled units, where both states are of order one
    np.testing.assert_allclose(scaled.mean, given.mean / s, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(scaled.cov, given.cov / jnp.outer(s, s), rtol=1e-7, atol=1e-9)
    assert float(scaled.loglik) == pytest.approx(float(given.loglik), rel=1e-10)
