"""Loader of the real flight data (skipped where the data directory is absent)."""

import numpy as np
import pytest

from jaxest.systems import flight_data

DATA = flight_data.find_data_dir()
needs_data = pytest.mark.skipif(
    DATA is None, reason="flight data not found (../shared/data/flight)"
)


def test_missing_directory_explains_the_download(tmp_path):
    with pytest.raises(ValueError, match="data: .*flt_data.zip"):
        flight_data.find_data_dir(tmp_path / "nowhere")
    with pytest.raises(ValueError, match="not found.*flt_data.zip"):
        flight_data.load_attas("elevator", tmp_path)


@needs_data
@pytest.mark.parametrize("maneuver", list(flight_data.ATTAS_FILES))
def test_attas_channels_in_si_units(maneuver):
    d = flight_data.load_attas(maneuver, DATA)
    assert d.inputs.shape == d.outputs.shape == (d.t.shape[0], 6)
    np.testing.assert_allclose(np.diff(d.t), 0.04, atol=1e-6)  # 25 Hz
    speed, beta, alpha, theta, phi, h = d.outputs.T
    assert 100 < speed.mean() < 160  # m/s
    assert np.all(np.abs(alpha) < 0.3) and np.all(np.abs(beta) < 0.2)  # rad, not deg
    assert 4000 < h.mean() < 6000  # 16000 ft in metres
    a_z = d.inputs[:, 2]
    assert -12 < a_z.mean() < -8  # specific force at 1 g, z down
    assert np.all(np.abs(d.inputs[:, 3:]) < 1.0)  # rad/s


@needs_data
def test_hfb320_has_no_altitude():
    d = flight_data.load_hfb320(DATA)
    assert d.t.shape == (601,)
    np.testing.assert_allclose(d.rate_hz, 10.0, rtol=1e-6)
    assert np.all(np.isnan(d.outputs[:, 5]))
    assert 100 < np.mean(d.outputs[:, 0]) < 115
    assert -10.5 < np.mean(d.inputs[:, 2]) < -9.0  # AZCG is column 11 whatever README says


def test_advance_channels_shifts_by_whole_and_half_samples():
    rng = np.random.default_rng(0)
    y = rng.normal(size=(30, 3))
    out = np.asarray(flight_data.advance_channels(y, 0.04, [0.0, 0.08, 0.06], [0.0, 0.1, 0.1]))
    np.testing.assert_allclose(out[:, 0], y[:, 0], rtol=1e-6)  # no delay, no limit: untouched
    np.testing.assert_allclose(out[:27, 1], y[2:29, 1], rtol=1e-6)  # two samples later
    np.testing.assert_allclose(out[:27, 2], 0.5 * (y[1:28, 2] + y[2:29, 2]), rtol=1e-5)
    # the last ceil(0.1 / 0.04) = 3 samples are missing for every delay up to the limit
    assert np.all(np.isnan(out[27:, 1:])) and np.all(np.isfinite(out[:27]))


def test_advance_channels_derivative_matches_finite_differences():
    import jax

    with jax.enable_x64(True):
        y = np.sin(np.linspace(0.0, 3.0, 40))[:, None]
        f = lambda d: jax.numpy.nansum(flight_data.advance_channels(y, 0.1, d, [0.5]) ** 3)
        d = np.array([0.123])
        fd = (f(d + 1e-6) - f(d - 1e-6)) / 2e-6
        np.testing.assert_allclose(jax.grad(f)(d)[0], fd, rtol=1e-6)


def test_advance_channels_rejects_bad_limits():
    with pytest.raises(ValueError, match="max_delays"):
        flight_data.advance_channels(np.zeros((5, 2)), 0.1, [0.0, 0.1], [0.1])
    with pytest.raises(ValueError, match="max_delays"):
        flight_data.advance_channels(np.zeros((5, 2)), 0.1, [0.0, 0.1], [0.0, -0.1])


def test_attas_record_rejects_a_table_without_the_45_channels():
    with pytest.raises(ValueError, match="table"):
        flight_data.attas_record(np.zeros((10, 20)), "short")
    record = flight_data.attas_record(np.arange(90.0).reshape(2, 45), "two rows")
    np.testing.assert_array_equal(record.t, [0.0, 45.0])
    assert record.outputs[1, 5] == 60.0 * flight_data.FOOT  # pressure altitude, column 16
