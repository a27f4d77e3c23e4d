"""jaxest.ScaledState: the estimate in other units of the state is the same estimate (every
Gaussian filter, the smoother, gradients, vmap, float32), and its arguments are checked as the
model's. What it is for, a float32 filter on the real flight records, is tested in
tests/test_flight_float32.py."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxest as je
from tests.registry import GAUSSIAN_FILTER_IDS, GAUSSIAN_FILTERS

#: the sizes of the three states: a position in metres, a velocity, an angle in radians
SIZES = np.array([1e3, 10.0, 1e-3])


def tracking_model(dtype=jnp.float64) -> tuple[je.NonlinearGaussian, je.Gaussian]:
    """Position, velocity driven by an input, and a slowly drifting sensor angle; a range-like
    measurement of the position and one of the angle mixed with the velocity (nonlinear, an
    analytic Jacobian for h), and the process noise through a gain G(x) of two sources."""
    dt = 0.1

    def f(x, u):
        return jnp.stack([x[0] + dt * x[1], x[1] + dt * u[0], x[2]])

    def h(x):
        return jnp.stack([jnp.sqrt(x[0] ** 2 + 1e4), x[1] * jnp.cos(x[2]) + 1e3 * x[2]])

    def jac_h(x):
        r = jnp.sqrt(x[0] ** 2 + 1e4)
        zero = jnp.zeros_like(x[0])
        return jnp.stack([
            jnp.stack([x[0] / r, zero, zero]),
            jnp.stack([zero, jnp.cos(x[2]), 1e3 - x[1] * jnp.sin(x[2])]),
        ])  # fmt: skip

    def gain(x):
        return jnp.array([[0.5 * dt**2, 0.0], [dt, 0.0], [0.0, 1e-4]], x.dtype)

    model = je.NonlinearGaussian(
        f, h, jnp.eye(2, dtype=dtype), jnp.diag(jnp.array([4.0, 0.01], dtype)),
        noise_gain=gain, jac_h=jac_h,
    )  # fmt: skip
    prior = je.Gaussian(
        jnp.asarray([2e3, 5.0, 2e-3], dtype), jnp.diag(jnp.asarray(SIZES**2, dtype))
    )
    return model, prior


def inputs(steps=30):
    return jnp.sin(0.1 * jnp.arange(steps))[:, None]


def measurements(model, prior, key=0, steps=30):
    return je.simulate(model, prior.mean, steps, jax.random.key(key), inputs=inputs(steps)).y


def in_standard_deviations(mean, reference: je.FilterResult) -> float:
    sd = jnp.sqrt(jnp.diagonal(reference.cov, axis1=-2, axis2=-1))
    return float(jnp.max(jnp.abs(mean - reference.mean) / sd))


@pytest.mark.parametrize("Filter", GAUSSIAN_FILTERS + [je.UKF], ids=GAUSSIAN_FILTER_IDS + ["UKF"])
def test_every_filter_gives_the_same_estimate_in_scaled_units(Filter):
    model, prior = tracking_model()
    ys = measurements(model, prior)
    scaled, scaled_prior = je.scale_state(model, prior)
    assert np.allclose(jnp.diag(scaled_prior.cov), 1.0)  # the prior's standard deviations
    run = lambda m, p: je.run(Filter(), m, ys, inputs=inputs(), prior=p)
    reference, result = run(model, prior), run(scaled, scaled_prior)
    assert int(reference.any_status) == int(result.any_status) == 0
    assert in_standard_deviations(scaled.state_mean(result.mean), reference) < 1e-8
    cov = scaled.state_cov(result.cov)
    scale = jnp.sqrt(jnp.diagonal(reference.cov, axis1=-2, axis2=-1))
    assert (
        float(jnp.max(jnp.abs(cov - reference.cov) / (scale[:, :, None] * scale[:, None]))) < 1e-8
    )
    assert np.allclose(result.innovation, reference.innovation, rtol=1e-9, atol=1e-9)
    assert abs(float(result.loglik - reference.loglik)) < 1e-8


def test_the_smoother_gradient_and_vmap_match_the_unscaled_model():
    """A simulation and the RTS smoother in scaled units; the log-likelihood's gradient in R
    through the wrapper equals the model's own (the Kalman filter, autodiff on both); a vmap
    over runs equals the runs one by one."""
    model, prior = tracking_model()
    ys = jnp.stack([measurements(model, prior, key) for key in range(3)])
    scaled, scaled_prior = je.scale_state(model, prior)
    simulate = lambda m, x0: je.simulate(m, x0, 30, jax.random.key(0), inputs=inputs())
    sim, truth = simulate(scaled, scaled_prior.mean), simulate(model, prior.mean)
    np.testing.assert_allclose(scaled.state_mean(sim.states), truth.states, rtol=1e-12)
    np.testing.assert_allclose(sim.y, truth.y, rtol=1e-12)
    run = lambda m, p, y: je.run(je.KalmanFilter(), m, y, inputs=inputs(), prior=p)
    smooth = lambda m, p, y: je.rts_smooth(m, run(m, p, y), inputs=inputs())
    reference, result = smooth(model, prior, ys[0]), smooth(scaled, scaled_prior, ys[0])
    assert in_standard_deviations(scaled.state_mean(result.mean), reference) < 1e-8

    def loglik_in_R(R, wrap):
        m = eqx.tree_at(lambda m: m.R, model, R)
        m, p = (je.scale_state(m, prior)) if wrap else (m, prior)
        return jax.vmap(lambda y: run(m, p, y).loglik)(ys)

    per_run = [float(run(scaled, scaled_prior, y).loglik) for y in ys]
    assert np.allclose(loglik_in_R(model.R, True), per_run, rtol=1e-10)
    grads = [jax.grad(lambda R, w=w: jnp.sum(loglik_in_R(R, w)))(model.R) for w in (False, True)]
    assert np.all(np.isfinite(grads[0])) and np.allclose(grads[1], grads[0], rtol=1e-7)


def test_float32_runs_in_float32_in_scaled_units():
    """A float32 model and prior give a float32 scale, and the run stays float32 (its carry
    keeps its dtype) and ends as close to the float64 run as the unscaled float32 run does.
    That scaling helps a float32 filter on a state of very different sizes is tested on the
    real HFB-320 record (tests/test_flight_float32.py)."""
    model, prior = tracking_model()
    ys = measurements(model, prior, steps=60)
    run = lambda m, y, p: je.run(je.ImprovedSVDKF(), m, y, inputs=inputs(60), prior=p)
    reference = run(model, ys, prior)
    single = lambda tree: jax.tree.map(
        lambda a: a.astype(jnp.float32) if eqx.is_inexact_array(a) else a, tree
    )
    scaled, scaled_prior = je.scale_state(single(model), single(prior))
    assert scaled.scale.dtype == scaled_prior.mean.dtype == jnp.float32
    result = run(scaled, single(ys), scaled_prior)
    assert int(result.any_status) == 0
    assert scaled.state_mean(result.mean).dtype == scaled.state_cov(result.cov).dtype == jnp.float32
    assert in_standard_deviations(scaled.state_mean(result.mean), reference) < 0.05


def test_arguments_are_checked_as_the_models_and_the_scale_is_named():
    model, prior = tracking_model()
    ys = measurements(model, prior, steps=5)
    scaled, scaled_prior = je.scale_state(model, prior)
    with pytest.raises(ValueError, match="scale: every entry must be positive"):
        je.ScaledState(model, jnp.array([1.0, -1.0, 1.0]))
    with pytest.raises(ValueError, match=r"scale: expected a vector"):
        je.ScaledState(model, jnp.ones((3, 1)))
    with pytest.raises(ValueError, match=r"scale: has shape \(2,\)"):
        je.scale_state(model, prior, jnp.ones(2))
    with pytest.raises(ValueError, match="prior: its variances"):
        je.scale_state(model, je.Gaussian(prior.mean, jnp.diag(jnp.array([1.0, 0.0, 1.0]))))
    with pytest.raises(ValueError, match=r"model.scale: has shape \(3,\), expected \(2,\)"):
        je.run(
            je.KalmanFilter(),
            scaled,
            ys,
            inputs=inputs(5),
            prior=je.Gaussian(jnp.zeros(2), jnp.eye(2)),
        )
    bad_R = je.ScaledState(eqx.tree_at(lambda m: m.R, model, -model.R), scaled.scale)
    with pytest.raises(ValueError, match="model.R"):
        je.run(je.KalmanFilter(), bad_R, ys, inputs=inputs(5), prior=scaled_prior)
    short_R = eqx.tree_at(lambda m: m.R, model, jnp.stack([model.R] * 3))  # 3 steps of 5
    with pytest.raises(ValueError, match="model.R: time-varying with 3 steps"):
        je.run(
            je.KalmanFilter(),
            je.ScaledState(short_R, scaled.scale),
            ys,
            inputs=inputs(5),
            prior=scaled_prior,
        )
    narrow = je.astype(scaled_prior, jnp.float32)
    with pytest.raises(ValueError, match="prior: is float32, narrower"):
        je.run(
            je.KalmanFilter(),
            scaled,
            ys.astype(jnp.float32),
            inputs=inputs(5).astype(jnp.float32),
            prior=narrow,
        )
    on_input = je.NonlinearGaussian(
        lambda x, u: x + u, lambda x: x, jnp.eye(3), jnp.eye(3), noise_on_input=True
    )
    zeros = jnp.zeros((5, 3))
    with pytest.raises(ValueError, match="noise_on_input"):
        je.ParticleFilter(10).check(
            je.ScaledState(on_input, scaled.scale), zeros, zeros, scaled_prior
        )
