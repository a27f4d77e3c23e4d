"""The extended models of ``benchmarks/flight_sensor_terms.py`` (issue 16) against the flight
model built independently: the vane rate terms are the beta vane's lever arms of eq 28
(``flight.LeverArms``), the roll gyro scale factor is the measured roll rate scaled before the
model sees it, and with every extra state at zero the model is the study's pinned one."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxest.studies import svd_ekf
from jaxest.systems import flight
from tests import benchmark_scripts
from tests.flight_model_functions import DT, INPUT_STD, OUTPUT_STD, functions_at

sensor_terms = benchmark_scripts.load("flight_sensor_terms")


@pytest.fixture(scope="module")
def point():
    """A reduced (pinned) state near trim with non-zero sensor parameters, and an input with
    large rates, so that every extra term matters."""
    _, names = svd_ekf.pinned_model(DT, INPUT_STD, OUTPUT_STD)
    rng = np.random.default_rng(0)
    z = np.zeros(len(names))
    z[:7] = [120.0, 2.0, 5.0, 0.3, 0.05, 0.1, 1000.0]
    z[7:] = rng.normal(scale=0.02, size=len(names) - 7)
    rates = np.array([0.5, -0.2, 9.0, 0.4, 0.05, -0.3])  # a_x, a_y, a_z, p, q, r
    u = np.concatenate([rates, rates * 1.1])
    with jax.enable_x64(True):
        yield jnp.asarray(z), jnp.asarray(u), names


def test_vane_rate_terms_are_the_beta_vane_lever_arms(point):
    z, u, _ = point
    x_beta, z_beta = 6.5, -0.8
    with jax.enable_x64(True):
        model, _ = sensor_terms.model_with(DT, INPUT_STD, OUTPUT_STD, ("k_p", "k_r"))
        arms = flight.LeverArms(x_beta=x_beta, z_beta=z_beta)
        full = flight.flight_model(DT, jnp.asarray(INPUT_STD), jnp.asarray(OUTPUT_STD), arms)
        reference, _ = flight.pin_parameters(full, svd_ekf.PINNED)
        plain, _ = sensor_terms.model_with(DT, INPUT_STD, OUTPUT_STD, ())
        ours = model.observation_fn(jnp.concatenate([z, jnp.array([z_beta, x_beta])]), u)
        expected, at_cg = reference.observation_fn(z, u), plain.observation_fn(z, u)
    np.testing.assert_allclose(ours, expected, rtol=1e-13, atol=1e-15)
    assert abs(float(ours[1] - at_cg[1])) > 1e-3  # rad: the arms matter at these rates


def test_bank_angle_scale_multiplies_the_bank_angle_channel(point):
    z, u, names = point
    lam_phi = -0.028
    with jax.enable_x64(True):
        model, _ = sensor_terms.model_with(DT, INPUT_STD, OUTPUT_STD, ("lam_phi",))
        plain, _ = sensor_terms.model_with(DT, INPUT_STD, OUTPUT_STD, ())
        ours = model.observation_fn(jnp.concatenate([z, jnp.array([lam_phi])]), u)
        expected = plain.observation_fn(z, u)
    phi = float(z[names.index("phi")])
    np.testing.assert_allclose(ours[4], expected[4] + lam_phi * phi, rtol=1e-14)
    np.testing.assert_array_equal(np.delete(ours, 4), np.delete(expected, 4))


def test_roll_gyro_scale_is_the_roll_rate_read_larger(point):
    z, u, _ = point
    lam_p = -0.028
    scaled = np.asarray(u).copy()
    scaled[[3, 3 + flight.N_IN]] *= 1.0 + lam_p
    with jax.enable_x64(True):
        model, _ = sensor_terms.model_with(DT, INPUT_STD, OUTPUT_STD, ("lam_p",))
        plain, _ = sensor_terms.model_with(DT, INPUT_STD, OUTPUT_STD, ())
        x = jnp.concatenate([z, jnp.array([lam_p])])
        _, f_ours, G_ours = functions_at(model, x, u)
        _, f_ref, G_ref = functions_at(plain, z, jnp.asarray(scaled))
        _, f_unscaled, _ = functions_at(plain, z, u)
    np.testing.assert_allclose(f_ours[:-1], f_ref, rtol=1e-14)
    assert f_ours[-1] == lam_p  # a constant
    np.testing.assert_allclose(G_ours[:-1], G_ref, rtol=1e-13, atol=1e-16)
    np.testing.assert_array_equal(G_ours[-1], 0.0)
    assert float(jnp.max(jnp.abs(f_ours[:-1] - f_unscaled))) > 1e-6


@pytest.mark.parametrize("variant", ["vane_rate_terms", "bank_angle_scale", "roll_gyro_scale"])
def test_extra_states_at_zero_give_the_pinned_model(point, variant):
    z, u, _ = point
    extra = sensor_terms.VARIANTS[variant]
    with jax.enable_x64(True):
        model, names = sensor_terms.model_with(DT, INPUT_STD, OUTPUT_STD, extra)
        plain, plain_names = sensor_terms.model_with(DT, INPUT_STD, OUTPUT_STD, ())
        x = jnp.concatenate([z, jnp.zeros(len(extra))])
        ours, expected = functions_at(model, x, u), functions_at(plain, z, u)
    assert names == plain_names + extra
    for a, b in zip(ours, expected, strict=True):  # h, f, G
        np.testing.assert_allclose(a[: len(b)], b, rtol=1e-15)
