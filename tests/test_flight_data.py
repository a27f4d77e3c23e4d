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
    # beyond its limit a delay repeated the last sample instead of marking it missing
    for delays in ([0.0, 0.5], [0.0, -0.3]):
        with pytest.raises(ValueError, match=r"^delays: must lie in \[0, max_delays\]"):
            flight_data.advance_channels(np.zeros((5, 2)), 0.1, delays, [0.0, 0.2])


def test_attas_record_rejects_a_table_without_the_45_channels():
    with pytest.raises(ValueError, match="table"):
        flight_data.attas_record(np.zeros((10, 20)), "short")
    record = flight_data.attas_record(np.arange(90.0).reshape(2, 45), "two rows", "ft")
    np.testing.assert_array_equal(record.t, [0.0, 45.0])
    assert record.outputs[1, 5] == 60.0 * flight_data.FOOT  # pressure altitude, column 16
    with pytest.raises(ValueError, match="^altitude_unit: expected 'ft' or 'm'"):
        flight_data.attas_record(np.arange(90.0).reshape(2, 45), "two rows", "km")


def synthetic_attas(rows=50, altitude=16000.0, pressure_hpa=549.2):
    """An ATTAS table of 45 channels at 25 Hz: time, a pressure altitude and a static pressure
    (549.2 hPa: 4 876 m in the standard atmosphere, 16 000 ft)."""
    table = np.zeros((rows, 45))
    table[:, 0] = 0.04 * np.arange(rows)
    table[:, 15], table[:, 32] = altitude, pressure_hpa
    return table


def test_the_altitude_unit_is_told_by_the_static_pressure():
    """The README gives HQNH in ft; the stall records give it in metres (their header says M):
    read as ft, 5 300 m became 1 600 m with status OK. Feet and metres are told apart by the
    static pressure's standard-atmosphere altitude, in hPa or Pa."""
    infer = flight_data.infer_altitude_unit
    assert infer(synthetic_attas()) == "ft"
    assert infer(synthetic_attas(altitude=4876.0)) == "m"
    assert infer(synthetic_attas(altitude=5350.0, pressure_hpa=51801.7)) == "m"  # qst01, Pa
    with pytest.raises(ValueError, match="^altitude_unit: cannot tell"):
        infer(synthetic_attas(altitude=100.0, pressure_hpa=1005.0))  # near the ground: both fit
    with pytest.raises(ValueError, match="^altitude_unit: cannot tell"):
        infer(synthetic_attas(altitude=30000.0))  # neither
    record = flight_data.attas_record(synthetic_attas(altitude=4876.0), "metres")
    np.testing.assert_allclose(record.outputs[:, 5], 4876.0)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda t: t[::-1], r"time \(column 1\) does not increase"),
        (
            lambda t: np.delete(t, 20, axis=0),
            r"goes from 0.76 to 0.84 at row 20, where the record steps by 0.04",
        ),
        (lambda t: t.__setitem__((5, 0), np.nan) or t, r"time \(column 1\) is not finite at row 5"),
        (lambda t: t[:, :44], r"50 rows of 44 columns, expected 45 or 48 columns"),
        (lambda t: t[:1], r"has 1 row, and a record needs at least 2"),
    ],
    ids=["reversed", "gap", "nan_time", "column_dropped", "one_row"],
)
def test_a_file_that_is_not_a_uniformly_sampled_record_is_named(tmp_path, edit, message):
    """Each of these loaded before, and the filters ran on it with status OK (a reversed or
    gapped time axis under one dt, a dropped column shifting every channel)."""
    np.savetxt(tmp_path / "record.asc", edit(synthetic_attas()))
    with pytest.raises(ValueError, match=f"^data: .*record.asc.*{message}"):
        flight_data.load_attas("record.asc", tmp_path)


def test_files_that_are_not_headerless_tables_are_named(tmp_path):
    """The _withHeader copies (rates and attitude angles in rad under DEG headings), MATLAB
    files, an empty or ragged file, and a file of the other aircraft: a UnicodeDecodeError, a
    message from numpy or a record loaded in the wrong units before."""
    np.savetxt(tmp_path / "header.asc", synthetic_attas(), header="T AXCG AYCG\ns M/S**2 M/S**2")
    (tmp_path / "record.mat").write_bytes(b"MATLAB 5.0 MAT-file")
    (tmp_path / "empty.asc").write_text("")
    (tmp_path / "ragged.asc").write_text("0 1 2\n0.04 1\n")
    for name, message in [
        ("header.asc", "has a text header"),
        ("record.mat", "is a MATLAB file"),
        ("empty.asc", "has no row of numbers"),
        ("ragged.asc", "is not a table of numbers"),
    ]:
        with pytest.raises(ValueError, match=f"^data: .*{name} {message}"):
            flight_data.load_attas(name, tmp_path)
    np.savetxt(tmp_path / "hfb320_1_10.asc", synthetic_attas())  # ATTAS where the HFB-320 is read
    with pytest.raises(ValueError, match="expected 20 columns .*other aircraft"):
        flight_data.load_hfb320(tmp_path)


@needs_data
def test_the_stall_records_altitude_is_in_metres():
    """fAttas_qst01/02.asc give HQNH in metres (the _withHeader copy says M, and PSTAT in Pa puts
    them at 5 290 m); read as feet they were at 1 600 m."""
    for name in ("fAttas_qst01.asc", "fAttas_qst02.asc"):
        assert 5000 < np.median(flight_data.load_attas(name, DATA).outputs[:, 5]) < 5600
    with pytest.raises(ValueError, match="has a text header"):
        flight_data.load_attas("fAttas_qst01_withHeader.asc", DATA)
