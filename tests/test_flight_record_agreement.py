"""``benchmarks/flight_record_agreement.py`` (issue 16): the six ATTAS slices against the study's
records, the deweighted altitude and the figure (the wind states: test_flight_wind.py)."""

import numpy as np
import pytest

from jaxest.studies import svd_ekf
from jaxest.systems import flight, flight_data
from tests import benchmark_scripts
from tests.flight_model_functions import OUTPUT_STD

agreement = benchmark_scripts.load("flight_record_agreement")


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
