"""``benchmarks/flight_record_agreement.py`` (issue 16): the wind-state model against the flight
model and scipy's rotations, and the six ATTAS slices against the study's records."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jaxest.studies import svd_ekf
from jaxest.systems import flight, flight_data
from tests import benchmark_scripts
from tests.flight_model_functions import DT, INPUT_STD, OUTPUT_STD, functions_at

agreement = benchmark_scripts.load("flight_record_agreement")


@pytest.fixture(scope="module")
def point():
    """A reduced (pinned) state banked, pitched and turned, with non-zero sensor parameters."""
    _, names = agreement.pinned_model(DT, INPUT_STD, OUTPUT_STD)
    rng = np.random.default_rng(1)
    z = np.zeros(len(names))
    z[:7] = [120.0, 2.0, 5.0, 0.4, 0.1, 0.7, 1000.0]  # u, v, w, phi, theta, psi, h
    z[7:] = rng.normal(scale=0.02, size=len(names) - 7)
    rates = np.array([0.5, -0.2, 9.0, 0.4, 0.05, -0.3])  # a_x, a_y, a_z, p, q, r
    with jax.enable_x64(True):
        yield jnp.asarray(z), jnp.asarray(np.concatenate([rates, rates * 1.1])), names


def test_body_from_earth_is_the_transpose_of_the_yaw_pitch_roll_rotation():
    phi, theta, psi = 0.4, -0.2, 2.5
    body_to_earth = Rotation.from_euler("ZYX", [psi, theta, phi]).as_matrix()
    with jax.enable_x64(True):
        ours = np.asarray(agreement.body_from_earth(phi, theta, psi))
    np.testing.assert_allclose(ours, body_to_earth.T, atol=1e-15)


def test_flow_sensors_see_the_velocity_relative_to_the_air(point):
    z, u, names = point
    wind = np.array([8.0, -5.0, 1.5])  # north, east, down (m/s)
    phi, theta, psi = (float(z[names.index(s)]) for s in ("phi", "theta", "psi"))
    body_wind = Rotation.from_euler("ZYX", [psi, theta, phi]).inv().apply(wind)
    air = np.asarray(z).copy()
    air[:3] -= body_wind
    with jax.enable_x64(True):
        model, _ = agreement.wind_model(DT, INPUT_STD, OUTPUT_STD, 0.05)
        plain, _ = agreement.pinned_model(DT, INPUT_STD, OUTPUT_STD)
        ours = model.observation_fn(jnp.concatenate([z, jnp.asarray(wind)]), u)
        expected, still = plain.observation_fn(jnp.asarray(air), u), plain.observation_fn(z, u)
        calm = model.observation_fn(jnp.concatenate([z, jnp.zeros(3)]), u)
    np.testing.assert_allclose(ours, expected, rtol=1e-13)
    np.testing.assert_allclose(calm, still, rtol=1e-15)
    assert abs(float(ours[1] - still[1])) > 1e-2  # rad: this wind moves the sideslip
    np.testing.assert_allclose(ours[5], still[5], rtol=1e-15)  # the altitude does not see it


def test_wind_states_are_random_walks_beside_the_pinned_model(point):
    z, u, names = point
    step = 0.05
    x = jnp.concatenate([z, jnp.array([3.0, -1.0, 0.5])])
    with jax.enable_x64(True):
        model, wind_names = agreement.wind_model(DT, INPUT_STD, OUTPUT_STD, step)
        plain, _ = agreement.pinned_model(DT, INPUT_STD, OUTPUT_STD)
        _, f, G = functions_at(model, x, u)
        _, f_plain, G_plain = functions_at(plain, z, u)
    assert wind_names == names + agreement.WIND_STATES
    np.testing.assert_allclose(f[:-3], f_plain, rtol=1e-15)
    np.testing.assert_array_equal(f[-3:], x[-3:])
    q = G_plain.shape[1]
    np.testing.assert_allclose(G[:-3, :q], G_plain, rtol=1e-15)
    np.testing.assert_array_equal(G[-3:, q:], np.eye(3))
    np.testing.assert_array_equal(G[:-3, q:], 0.0)
    np.testing.assert_array_equal(G[-3:, :q], 0.0)
    np.testing.assert_allclose(np.diag(model.Q)[q:], step**2)
    np.testing.assert_allclose(model.Q[:q, :q], plain.Q)


def test_the_six_slices_are_one_flight_and_hold_the_study_records():
    if flight_data.find_data_dir() is None:
        pytest.skip("no flight data")
    raw = agreement.read_slices()
    assert list(raw) == list(agreement.SLICES)
    starts = [t0 for t0, _ in raw.values()]
    ends = [t0 + float(d.t[-1]) for t0, d in raw.values()]
    np.testing.assert_allclose(np.array(starts[1:]) - np.array(ends[:-1]), 0.04, atol=1e-9)
    for maneuver in agreement.STUDY_SLICES:
        record = flight_data.load_attas(maneuver)
        np.testing.assert_array_equal(raw[maneuver][1].inputs, record.inputs)
        np.testing.assert_array_equal(raw[maneuver][1].outputs, record.outputs)
    # each maneuver twice: the pitch, roll and yaw rate dominate in turn (their std)
    dominant = [int(np.argmax(np.std(d.inputs[:, 3:6], axis=0))) for _, d in raw.values()]
    assert dominant == [1, 1, 0, 0, 2, 2]


def test_the_altitude_is_deweighted_in_one_model_only():
    h = svd_ekf.OUTPUTS.index("h")
    deweighted = agreement.output_std_of("altitude_deweighted")
    assert deweighted[h] == agreement.DEWEIGHTED_ALTITUDE_STD
    np.testing.assert_array_equal(np.delete(deweighted, h), np.delete(OUTPUT_STD, h))
    np.testing.assert_array_equal(agreement.output_std_of("study"), OUTPUT_STD)
    assert flight.OUTPUTS[h] == "h"


def test_figure_draws_every_slice_of_every_model(tmp_path):
    entry = {"value": 0.1, "std": 0.05, "identified": True}
    slices = {s: {"parameters": dict.fromkeys(agreement.FIGURE_PARAMETERS, entry)}
              for s in agreement.SLICES}  # fmt: skip
    models = {m: {"by_slice": slices} for m in ("study", "altitude_deweighted", "wind_states")}
    path = agreement.figure(models, tmp_path / "agreement.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
