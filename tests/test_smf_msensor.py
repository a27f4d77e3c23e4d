"""Guaranteed fault detection and isolation with m >= 3 sensors: the filter bank built for any m,
and the three-sensor pendulum example (notebooks/02_smf_fault_diagnosis.ipynb) run as a Monte
Carlo under jit and vmap."""

import jax
import numpy as np
import pytest

from jaxest.setmembership import SetMembershipFilter, fdi
from jaxest.studies import smf_fdi
from jaxest.systems import pendulum


def test_filter_bank_for_two_and_three_sensors():
    two = smf_fdi.filter_bank(2)
    # the paper's study: method 2's filter i (every sensor but i) is method 1's other filter
    np.testing.assert_array_equal(two.masks, [[True, True], [True, False], [False, True]])
    np.testing.assert_array_equal(two.isolation[2], two.isolation[1][::-1])
    assert two.names == ("all sensors", "sensor 1", "sensor 2")
    three = smf_fdi.filter_bank(3)
    assert len(three.masks) == 7 and len(set(map(bytes, three.masks))) == 7
    assert three.masks[three.detection].all()
    for method in (1, 2):
        np.testing.assert_array_equal(
            three.masks[three.isolation[method]], fdi.bank_masks(3, method)
        )
    assert three.names[three.isolation[2][0]] == "all but sensor 1"
    for bad in (1, 2.0):
        with pytest.raises(ValueError, match="^m:"):
            smf_fdi.filter_bank(bad)
    with pytest.raises(ValueError, match="^sensor:"):
        pendulum.sensor_bias(0.03, sensor=3)
    with pytest.raises(ValueError, match="^faulty:"):
        smf_fdi.isolation_score(np.zeros((1, 7, 4), bool), three, 1, faulty=3, fault_start=2)


def test_three_sensor_pendulum_monte_carlo():
    """Fault-free runs: the truth in every filter's set at every step and no alarm from any
    method; faulty runs (bias on the angle sensor): no alarm before the fault and none naming a
    healthy sensor, the fault detected, and method 2's "by_step" reading isolating the faulty
    sensor in every run the "same_step" reading does."""
    bank = smf_fdi.filter_bank(pendulum.NUM_SENSORS)
    model = pendulum.model()
    prior = SetMembershipFilter().predict(model, pendulum.prior())
    monte_carlo = smf_fdi.bank_monte_carlo_function(
        model, prior, pendulum.simulate, pendulum.sensor_bias(), bank
    )
    inconsistent, contains = (
        np.asarray(a) for a in monte_carlo(jax.random.split(jax.random.key(5), 50))
    )
    assert inconsistent.shape == contains.shape == (50, 2, 7, pendulum.NUM_STEPS)
    assert contains[:, 0].all()
    assert not inconsistent[:, 0].any()
    before = slice(0, pendulum.FAULT_START - 1)  # same noise draws: identical runs before the fault
    np.testing.assert_array_equal(inconsistent[:, 1, :, before], inconsistent[:, 0, :, before])

    rates = smf_fdi.bank_rates(inconsistent, bank, pendulum.FAULTY_SENSOR, pendulum.FAULT_START)
    assert set(rates) == {
        "detection",
        "isolation_method1",
        "isolation_method2_same_step",
        "isolation_method2_by_step",
    }
    for entry in rates.values():
        assert entry["false_alarm_rate"] == 0.0 and entry["fault_free_alarm_rate"] == 0.0
    assert rates["detection"]["rate"] > 0.5

    method2 = inconsistent[:, 1][:, bank.isolation[2]]
    isolated = {
        reading: np.asarray(fdi.isolation_decisions(method2, 2, reading))[
            ..., pendulum.FAULTY_SENSOR
        ].any(axis=-1)
        for reading in ("same_step", "by_step")
    }
    for reading, runs in isolated.items():
        assert rates[f"isolation_method2_{reading}"]["rate"] == pytest.approx(runs.mean())
    # so "by_step" isolates at least as often as "same_step"
    assert np.all(isolated["by_step"][isolated["same_step"]])
