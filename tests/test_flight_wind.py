"""``jaxest.systems.flight_wind``: the wind states against scipy's rotations, the pinned flight
model they wrap, and their own generic linearisation."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import jaxest as je
from jaxest import EKF, Gaussian, run
from jaxest.studies import svd_ekf
from jaxest.systems import flight_wind
from tests.flight_model_functions import DT, INPUT_STD, OUTPUT_STD, functions_at


def pinned():
    return svd_ekf.pinned_model(DT, INPUT_STD, OUTPUT_STD)


@pytest.fixture(scope="module")
def point():
    """A reduced (pinned) state banked, pitched and turned, with non-zero sensor parameters."""
    with jax.enable_x64(True):
        _, names = pinned()
        rng = np.random.default_rng(1)
        z = np.zeros(len(names))
        z[:7] = [120.0, 2.0, 5.0, 0.4, 0.1, 0.7, 1000.0]  # u, v, w, phi, theta, psi, h
        z[7:] = rng.normal(scale=0.02, size=len(names) - 7)
        rates = np.array([0.5, -0.2, 9.0, 0.4, 0.05, -0.3])  # a_x, a_y, a_z, p, q, r
        yield jnp.asarray(z), jnp.asarray(np.concatenate([rates, rates * 1.1])), names


def test_body_from_earth_is_the_transpose_of_the_yaw_pitch_roll_rotation():
    phi, theta, psi = 0.4, -0.2, 2.5
    body_to_earth = Rotation.from_euler("ZYX", [psi, theta, phi]).as_matrix()
    with jax.enable_x64(True):
        ours = np.asarray(flight_wind.body_from_earth(phi, theta, psi))
    np.testing.assert_allclose(ours, body_to_earth.T, atol=1e-15)


def test_flow_sensors_see_the_velocity_relative_to_the_air(point):
    z, u, names = point
    wind = np.array([8.0, -5.0, 1.5])  # north, east, down (m/s)
    phi, theta, psi = (float(z[names.index(s)]) for s in ("phi", "theta", "psi"))
    body_wind = Rotation.from_euler("ZYX", [psi, theta, phi]).inv().apply(wind)
    air = np.asarray(z).copy()
    air[:3] -= body_wind
    with jax.enable_x64(True):
        plain, _ = pinned()
        model, _ = flight_wind.with_wind(plain, names, 0.05)
        ours = model.observation_fn(jnp.concatenate([z, jnp.asarray(wind)]), u)
        expected, still = plain.observation_fn(jnp.asarray(air), u), plain.observation_fn(z, u)
        calm = model.observation_fn(jnp.concatenate([z, jnp.zeros(3)]), u)
    np.testing.assert_allclose(ours, expected, rtol=1e-13)
    np.testing.assert_allclose(calm, still, rtol=1e-15)
    assert abs(float(ours[1] - still[1])) > 1e-2  # rad: this wind moves the sideslip
    np.testing.assert_allclose(ours[5], still[5], rtol=1e-15)  # the altitude does not see it


def test_wind_states_are_random_walks_beside_the_wrapped_model(point):
    z, u, names = point
    step = 0.05
    x = jnp.concatenate([z, jnp.array([3.0, -1.0, 0.5])])
    with jax.enable_x64(True):
        plain, _ = pinned()
        model, wind_names = flight_wind.with_wind(plain, names, step)
        _, f, G = functions_at(model, x, u)
        _, f_plain, G_plain = functions_at(plain, z, u)
        mean, F, G_update, Q = eqx.filter_jit(lambda m, x, u: m.transition(x, u, 0))(model, x, u)
        F_generic = eqx.filter_jit(lambda m, x, u: jax.jacfwd(m.transition_fn)(x, u))(model, x, u)
    assert wind_names == names + flight_wind.WIND_STATES
    np.testing.assert_allclose(f[:-3], f_plain, rtol=1e-15)
    np.testing.assert_array_equal(f[-3:], x[-3:])
    q = G_plain.shape[1]
    np.testing.assert_allclose(G[:-3, :q], G_plain, rtol=1e-15)
    np.testing.assert_array_equal(G[-3:, q:], np.eye(3))
    np.testing.assert_array_equal(G[:-3, q:], 0.0)
    np.testing.assert_array_equal(G[-3:, :q], 0.0)
    np.testing.assert_allclose(np.diag(model.Q)[q:], step**2)
    np.testing.assert_allclose(model.Q[:q, :q], plain.Q)
    # the time update's one linearisation is the generic one of f and G
    np.testing.assert_allclose(mean, f, rtol=1e-15)
    np.testing.assert_allclose(F, F_generic, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(G_update, G, rtol=1e-10, atol=1e-12)
    np.testing.assert_array_equal(Q, model.Q)


def test_bad_arguments_are_named():
    plain, names = pinned()
    with pytest.raises(ValueError, match="names: .*'psi'"):
        flight_wind.with_wind(plain, tuple(s for s in names if s != "psi"), 0.05)
    with pytest.raises(ValueError, match="wind_step"):
        flight_wind.with_wind(plain, names, 0.0)


def test_prior_with_wind_appends_independent_zero_mean_wind_states():
    prior = Gaussian(jnp.array([1.0, 2.0]), jnp.array([[2.0, 0.5], [0.5, 1.0]]))
    wind = flight_wind.prior_with_wind(prior, 0.1)
    np.testing.assert_array_equal(wind.mean, [1.0, 2.0, 0.0, 0.0, 0.0])
    expected = np.zeros((5, 5))
    expected[:2, :2] = prior.cov
    expected[2:, 2:] = 0.01 * np.eye(3)
    np.testing.assert_allclose(wind.cov, expected, rtol=1e-6)
    with pytest.raises(ValueError, match="start_std"):
        flight_wind.prior_with_wind(prior, -1.0)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_wind_step_is_tuned_by_gradient_through_the_ekf(point, dtype):
    """The EKF's log-likelihood on a short banked record under jit and vmap over the wind step,
    and its derivative in log(wind_step) against central differences (float64)."""
    z, u, names = point
    with jax.enable_x64(dtype == jnp.float64):
        z, u = np.asarray(z).astype(dtype), np.asarray(u).astype(dtype)
        plain, _ = pinned()
        steps = 15
        inputs = jnp.tile(u, (steps, 1)).astype(dtype)
        truth, _ = flight_wind.with_wind(plain, names, 0.05)
        x0 = jnp.concatenate([z, jnp.array([1.0, -2.0, 0.5])])
        ys = jax.vmap(lambda k: truth.observation_fn(x0.at[-3].add(0.05 * k), u))(
            jnp.arange(steps)
        ).astype(dtype)
        prior = flight_wind.prior_with_wind(
            Gaussian(z.astype(dtype), jnp.diag(jnp.full(z.shape[0], 1e-2, dtype))), 1.0
        )

        @jax.jit
        def loglik(log_step):
            model, _ = flight_wind.with_wind(plain, names, jnp.exp(log_step))
            model = je.astype(model, dtype)
            return run(EKF(), model, ys, inputs=inputs, prior=prior).loglik

        log_steps = jnp.log(jnp.array([0.02, 0.1], dtype))
        values = jax.vmap(loglik)(log_steps)
        grad = jax.grad(loglik)(log_steps[0])
        assert values.dtype == dtype and bool(jnp.all(jnp.isfinite(values)))
        assert bool(jnp.isfinite(grad)) and float(values[0]) != float(values[1])
        if dtype == jnp.float64:
            h = 1e-5
            central = (loglik(log_steps[0] + h) - loglik(log_steps[0] - h)) / (2 * h)
            np.testing.assert_allclose(grad, central, rtol=1e-5)
