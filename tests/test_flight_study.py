"""The svd-ekf study end to end in its --quick form."""

import json

import jax
import numpy as np
import pytest

from jaxest.studies import svd_ekf
from jaxest.systems import flight_data


@pytest.mark.slow
def test_quick_study_writes_the_summary(tmp_path):
    data = flight_data.find_data_dir()
    with jax.enable_x64(True):
        svd_ekf.run(tmp_path, runs=3, seed=0, quick=True, options={"data": data})
    out = tmp_path / "svd-ekf"
    summary = json.loads((out / "summary.json").read_text())
    assert summary["conditions"]
    for cond in summary["conditions"].values():
        assert cond["rate_hz"] in (10, 32) and cond["dtype"] in ("float64", "float32")
        for f in ("ekf", "svd_ekf", "svd_improved"):
            F = cond[f]
            assert set(F) >= {"rmse", "param_error", "diverged_runs", "runs", "all", "nis"}
            assert F["runs"] == 3 and set(F["rmse"]) == set(svd_ekf.KINEMATIC_STATES)
            assert F["rmse"]["theta"] < 0.5  # deg: the filters track the attitude
    own = summary["own_model_simulation"]["elevator_10hz_float64"]["ekf"]
    assert own["runs"] == 3 and own["rmse"]["theta"] < 0.5 and own["all"]["expected"] == 23
    if data is None:
        assert "real_data" not in summary and "flt_data.zip" in summary["real_data_note"]
    else:
        real = summary["real_data"]
        assert set(real["residual_rms"]) == {"V", "beta", "alpha", "theta", "phi", "h"}
        assert set(real["parameters"]) == set(svd_ekf.PARAMETERS)
        assert list(out.glob("*.png"))
    assert (out / "tables.md").exists()


@pytest.mark.slow
def test_delay_estimate_recovers_a_simulated_vane_lag():
    """A simulated 25 Hz elevator maneuver whose alpha vane lags by 2 samples (0.08 s) and whose
    beta vane does not: the likelihood profile finds both delays."""
    import jax.numpy as jnp

    from jaxest.systems import flight, flight_sim as sim

    with jax.enable_x64(True):
        truth = sim.true_flight("elevator", 25, duration=12.0)
        params = sim.draw_parameters(jax.random.key(0))
        record = sim.corrupt(truth, params, jax.random.key(1), lever_arms=flight.AT_CG)
        ys = np.asarray(record.measurements).copy()
        ys[2:, 2] = ys[:-2, 2]  # alpha measured 2 samples late
        data = flight_data.FlightData(
            "lagged", np.asarray(truth.t), np.asarray(record.measured_inputs), ys
        )
        delays, profiles, best = svd_ekf.estimate_delays(
            {"sim": data}, sim.INPUT_STD, svd_ekf.REAL_OUTPUT_STD
        )
    alpha, beta = (delays[svd_ekf.OUTPUTS.index(c)] for c in ("alpha", "beta"))
    assert abs(alpha - 0.08) < 1e-9 and beta == 0.0
    assert best["alpha"]["sim"] == alpha and np.all(np.isfinite(profiles["alpha"]["sim"]))
    assert jnp.argmax(jnp.asarray(profiles["alpha"]["sim"])) > 0


def test_nees_groups_and_band_against_numpy_and_scipy():
    """Each group's NEES uses its marginal covariance (NumPy solves on the blocks); the band is
    scipy's chi-square quantiles of runs * dof, divided by runs."""
    import scipy.stats

    rng = np.random.default_rng(0)
    n, n_kin = svd_ekf.N_STATE, svd_ekf.N_KIN
    A = rng.normal(size=(n, n))
    P = A @ A.T + n * np.eye(n)
    e = rng.normal(size=n)
    with jax.enable_x64(True):
        ours = np.asarray(svd_ekf.nees_by_group(jax.numpy.asarray(e), jax.numpy.asarray(P)))
    kin, par = slice(0, n_kin), slice(n_kin, n)
    expect = [
        e @ np.linalg.solve(P, e),
        e[kin] @ np.linalg.solve(P[kin, kin], e[kin]),
        e[par] @ np.linalg.solve(P[par, par], e[par]),
    ]
    np.testing.assert_allclose(ours, expect, rtol=1e-10)
    low, high = svd_ekf.nees_band(100, 23)
    np.testing.assert_allclose(
        [low, high], scipy.stats.chi2.ppf([0.025, 0.975], 2300) / 100, rtol=1e-9
    )


def test_identifiability_finds_the_uninformed_combinations():
    """A posterior that leaves b_h at its prior and (b_ax + b_theta)/sqrt 2 at 0.8 of its prior
    std, and every other direction at 0.1: those two come first, with their loadings."""
    from jaxest.systems.flight import N_KIN, PARAMETERS

    rng = np.random.default_rng(0)
    std = np.concatenate([np.ones(N_KIN), rng.uniform(0.01, 3.0, len(PARAMETERS))])
    pair = np.zeros(len(PARAMETERS))
    pair[[PARAMETERS.index("b_ax"), PARAMETERS.index("b_theta")]] = 1 / np.sqrt(2)
    single = np.eye(len(PARAMETERS))[PARAMETERS.index("b_h")]
    C = (
        0.01 * np.eye(len(PARAMETERS))
        + 0.63 * np.outer(pair, pair)
        + 0.99 * np.outer(single, single)
    )
    P = np.eye(N_KIN + len(PARAMETERS))
    P[N_KIN:, N_KIN:] = C * np.outer(std[N_KIN:], std[N_KIN:])
    first, second, third = svd_ekf.identifiability(P, np.diag(std**2))
    assert first["std_ratio"] == pytest.approx(1.0) and first["loadings"] == pytest.approx(
        {"b_h": 1.0}
    )
    assert second["std_ratio"] == pytest.approx(0.8)
    assert second["loadings"] == pytest.approx({"b_ax": 2**-0.5, "b_theta": 2**-0.5})
    assert third["std_ratio"] == pytest.approx(0.1)
