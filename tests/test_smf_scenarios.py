"""The fault-diagnosis Monte Carlo computes each distinct filter run once: scenarios that differ
only by sensor biases share every filter's steps before the first bias it sees, and a filter
that never sees a scenario's bias shares that whole run (``smf_fdi.scenario_plan``). Checked
against every (scenario, filter) pair run alone."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxest.setmembership import SetMembershipFilter
from jaxest.studies import smf_fdi
from jaxest.systems import duffing

STEPS = 30


def _bias(sensor: int, start: int, size: float) -> np.ndarray:
    """(STEPS, 2): ``size`` on ``sensor`` from step index ``start`` on."""
    bias = np.zeros((STEPS, 2))
    bias[start:, sensor] = size
    return bias


def test_plan_of_the_paper_study():
    """Sensor 1 faulty from paper step 50 at three levels: every filter shares steps 1-49; then
    the detection and sensor-1 filters run four times each, the sensor-2 filter once."""
    plan = smf_fdi.scenario_plan(smf_fdi.scenario_biases(), smf_fdi.BANK.masks)
    assert plan.split == duffing.FAULT_START - 1
    names = smf_fdi.BANK.names
    runs = {name: len(set(plan.index[:, f])) for f, name in enumerate(names)}
    assert runs == {"all sensors": 4, "sensor 1": 4, "sensor 2": 1}
    assert len(plan.pairs) == 9
    for s, f in np.ndindex(plan.index.shape):
        assert plan.pairs[plan.index[s, f], 0] == f  # each run is its own filter's
    fault_free = np.zeros((3, STEPS, 2))
    assert smf_fdi.scenario_plan(fault_free, smf_fdi.BANK.masks).split == STEPS


CASES = {
    # fault-free, sensor 1 biased from index 10 at two sizes: shared steps 0-9
    "late_fault": [np.zeros((STEPS, 2)), _bias(0, 10, 0.04), _bias(0, 10, 0.06)],
    # sensor 2 biased from the first step: nothing shared by all, but the sensor-1 filter's runs
    # of scenarios 0 and 1 are one run
    "first_step": [np.zeros((STEPS, 2)), _bias(1, 0, 0.05), _bias(0, 5, 0.05)],
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_scenarios_equal_every_pair_run_alone(case):
    """Flags identical (bit for bit) to running every filter over every scenario (``run_bank``,
    ``bank_contains``), under jit and vmap over runs."""
    biases = np.stack(CASES[case])
    model = duffing.model(closed_form_bound=True)
    prior = SetMembershipFilter().predict(model, duffing.prior())
    masks = smf_fdi.BANK.masks

    def shared(key):
        states, ys = jax.vmap(duffing.simulate, (None, 0))(key, jnp.asarray(biases))
        return smf_fdi.run_bank_scenarios(model, prior, states, ys, biases, masks)

    def every_pair(key):
        def scenario(bias):
            states, ys = duffing.simulate(key, bias)
            bank = smf_fdi.run_bank(model, prior, ys, masks)
            return bank.inconsistent, smf_fdi.bank_contains(bank, states), bank.unbounded

        return jax.vmap(scenario)(jnp.asarray(biases))

    keys = jax.random.split(jax.random.key(3), 4)
    got, expected = (jax.jit(jax.vmap(fn))(keys) for fn in (shared, every_pair))
    for a, b in zip(got, expected, strict=True):
        assert a.shape == b.shape == (4, len(biases), len(masks), STEPS)
        np.testing.assert_array_equal(a, b)
    assert np.asarray(expected[0]).any()  # a bias that the sets notice
