"""The svd-ekf study end to end in its --quick form."""

import json
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxest.studies import svd_ekf
from jaxest.systems import flight_data, flight_sim as sim
from jaxest.systems.flight import N_KIN


@pytest.mark.slow
def test_quick_study_writes_the_summary(tmp_path, capsys):
    data = flight_data.find_data_dir()
    with jax.enable_x64(True):
        svd_ekf.run(tmp_path, runs=3, seed=0, quick=True, options={"data": data})
    # the progress display's weights (step_weights) are one per step the study takes
    done = [line.split("] ")[2].split()[0] for line in capsys.readouterr().err.splitlines()
            if line.startswith("[svd-ekf]")]  # fmt: skip
    total = len(done) - 1
    assert done == [f"{k}/{total}" for k in range(total + 1)]
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
    air_data = summary["air_data_start"]["elevator_10hz_float64"]["ekf"]
    assert air_data["runs"] == 3 and air_data["all"]["expected"] == 23
    assert summary["settings"]["kinematic_std"] == pytest.approx(svd_ekf.INS_KINEMATIC_STD)
    assert own["nis_band_95"][0] < 1 < own["nis_band_95"][1]
    assert set(own["nis_fraction_in_band"]) == set(svd_ekf.OUTPUTS)
    assert (out / "fig_nees_elevator.png").stat().st_size > 0
    assert (out / "fig_nis_elevator.png").stat().st_size > 0
    if data is None:
        assert "real_data" not in summary and "flt_data.zip" in summary["real_data_note"]
    else:
        real = summary["real_data"]
        assert set(real["residual_rms"]) == {"V", "beta", "alpha", "theta", "phi", "h"}
        est = real["estimation"]["by_maneuver"]["elevator"]
        free = set(svd_ekf.PARAMETERS) - set(svd_ekf.PINNED) - {"b_alpha"} | {"b_alpha_trim"}
        assert set(est["parameters"]) == free and all(k >= 1 for k in est["colour_factor"].values())
        assert est["smoothed_minus_last_filtered"] < 1e-3  # constant parameters: x(0|T) = x(T|T)
        info = real["least_informed_full_model"]["elevator"]
        assert info[0]["loadings"] == pytest.approx({"psi": 1.0})  # no heading measurement
        assert list(out.glob("*.png"))
    assert (out / "tables.md").exists()


def test_ins_start_differs_from_the_air_data_start_only_in_the_kinematic_error():
    """The conditions' INS start and the air-data block fly the same flights: the same draws, the
    initial kinematic error and prior std scaled by a tenth and nothing else changed."""
    truth = sim.true_flight("elevator", 10, 2.0)
    key = jax.random.key(5)
    air_data = svd_ekf.simulated_batch(truth, 4, key, jnp.float64)
    std = svd_ekf.INS_KINEMATIC_STD
    ins = svd_ekf.simulated_batch(truth, 4, key, jnp.float64, kinematic_std=std)
    for i in (0, 1, 3):  # measurements, inputs, true states
        np.testing.assert_array_equal(air_data[i], ins[i])
    error = lambda batch: np.asarray(batch[2] - batch[3][:, 0])  # initial guess - truth
    np.testing.assert_allclose(error(ins)[:, :N_KIN], 0.1 * error(air_data)[:, :N_KIN],
                               rtol=1e-12, atol=1e-12)  # fmt: skip
    np.testing.assert_array_equal(error(ins)[:, N_KIN:], error(air_data)[:, N_KIN:])
    assert std[:3] == pytest.approx(0.1) and std[6] == pytest.approx(1.0)  # m/s, m
    P0 = np.diag(svd_ekf.prior_cov(jnp.float64, std))
    np.testing.assert_allclose(np.sqrt(P0[:N_KIN]), std, rtol=1e-15)
    np.testing.assert_allclose(np.sqrt(P0[N_KIN:]), sim.PARAMETER_STD, rtol=1e-15)


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


@pytest.mark.parametrize("n", [svd_ekf.N_STATE, svd_ekf.N_STATE - 1])
def test_nees_groups_and_band_against_numpy_and_scipy(n):
    """Each group's NEES uses its marginal covariance (NumPy solves on the blocks), with all 23
    states or one parameter pinned (22); the band is scipy's chi-square quantiles of runs * dof,
    divided by runs."""
    import scipy.stats

    rng = np.random.default_rng(0)
    n_kin = svd_ekf.N_KIN
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


def test_nis_per_channel_its_bands_and_time_in_band_against_numpy_and_scipy():
    """Per channel: the NIS averaged over time and runs; the band of that average is scipy's
    chi-square(runs * steps) quantiles over runs * steps; the fraction of steps in band counts the
    run average at each step against chi-square(runs) / runs (NumPy, computed here)."""
    import scipy.stats

    rng = np.random.default_rng(1)
    runs, steps, m = 40, 30, len(svd_ekf.OUTPUTS)
    scale = np.linspace(0.7, 1.4, m)  # channels from overconfident to underconfident
    nis_t = rng.chisquare(1, size=(runs + 3, steps, m)) * scale
    use = np.ones(runs + 3, bool)
    use[[0, 5, 9]] = False  # runs left out
    metrics = {"nees_t": np.ones((runs + 3, steps, 3)), "nis_t": nis_t}
    out = svd_ekf.consistency(metrics, use)
    kept = nis_t[use]
    for i, o in enumerate(svd_ekf.OUTPUTS):
        assert out["nis"][o] == pytest.approx(kept[..., i].mean(), rel=1e-12)
        low, high = scipy.stats.chi2.ppf([0.025, 0.975], runs) / runs
        average = kept[..., i].mean(axis=0)
        expected = np.mean((average >= low) & (average <= high))
        assert out["nis_fraction_in_band"][o] == pytest.approx(expected, abs=1e-12)
    np.testing.assert_allclose(
        out["nis_band_95"], scipy.stats.chi2.ppf([0.025, 0.975], runs * steps) / (runs * steps),
        rtol=1e-9,
    )  # fmt: skip
    assert out["nis_fraction_in_band"]["h"] < out["nis_fraction_in_band"]["alpha"]


def test_record_information_is_the_observability_gramian_of_a_linear_model():
    """Without process noise the RTS smoother's P(0|T) gives I = P(0|T)^-1 - P0^-1 = sum_k
    Phi_k^T H^T R^-1 H Phi_k (computed here by the matrix powers): the eigen-pairs match, and a
    state the measurements never see has information 0 and std ratio 1."""
    import jax.numpy as jnp

    from jaxest import LinearGaussian, rts_smooth
    from jaxest._priors import Gaussian
    from jaxest._run import run as run_filter
    from jaxest.filters import EKF

    rng = np.random.default_rng(1)
    F = np.array([[1.0, 0.1, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.9]])
    H = np.array([[1.0, 0.0, 0.0]])  # the third state is never measured
    R, P0, T = np.array([[0.2]]), np.diag([4.0, 1.0, 9.0]), 40
    with jax.enable_x64(True):
        model = LinearGaussian(jnp.asarray(F), jnp.asarray(H), jnp.zeros((3, 3)), jnp.asarray(R))
        ys = jnp.asarray(rng.normal(size=(T, 1)))
        prior = Gaussian(jnp.zeros(3), jnp.asarray(P0))
        smooth = rts_smooth(model, run_filter(EKF(), model, ys, prior=prior))
        info = svd_ekf.record_information(P0, smooth.cov[0], ("x", "v", "z"), count=3)
    powers = [np.linalg.matrix_power(F, k) for k in range(T)]
    gramian = sum(Phi.T @ H.T @ np.linalg.inv(R) @ H @ Phi for Phi in powers)
    S = np.sqrt(np.diag(P0))
    expect = np.sort(np.linalg.eigvalsh(np.outer(S, S) * gramian))
    np.testing.assert_allclose([c["information"] for c in info], expect, rtol=1e-6, atol=1e-9)
    assert info[0]["loadings"] == pytest.approx({"z": 1.0}) and info[0]["std_ratio"] == 1.0
    np.testing.assert_allclose(info[1]["std_ratio"], 1 / np.sqrt(1 + expect[1]))


def test_long_run_variance_ratio_of_an_ar1_series():
    """kappa -> (1 + a) / (1 - a) for AR(1) noise with coefficient a (Bartlett bias
    2 a / ((1 - a)^2 (L + 1)) subtracted), 1 for white noise; bad lags raise ValueError."""
    rng = np.random.default_rng(2)
    n, a, lag = 400_000, 0.6, 100
    white = rng.normal(size=(n, 2))
    ar = np.empty(n)
    ar[0] = white[0, 0]
    for k in range(1, n):
        ar[k] = a * ar[k - 1] + white[k, 0]
    kappa = svd_ekf.long_run_variance_ratio(np.stack([ar, white[:, 1]], axis=1), lag)
    bartlett = (1 + a) / (1 - a) - 2 * a / ((1 - a) ** 2 * (lag + 1))
    assert kappa[0] == pytest.approx(bartlett, rel=0.05)
    assert kappa[1] == pytest.approx(1.0, abs=0.05)
    with pytest.raises(ValueError, match="max_lag"):
        svd_ekf.long_run_variance_ratio(white[:10], 10)


def test_colour_factors_whiten_by_the_innovation_variance_and_floor_at_one():
    """The factor of a channel is (C1) of innovation / sqrt(S_jj) over the rows where every channel
    was measured: scaling a channel's innovations and S together leaves it; an anti-correlated
    channel gets 1."""
    from types import SimpleNamespace

    rng = np.random.default_rng(4)
    T, rate = 2000, 25.0
    e = rng.normal(size=(T, 2))
    smooth = np.convolve(e[:, 0], np.ones(5) / 5, mode="same")  # positively correlated
    alternating = e[:, 1] - np.roll(e[:, 1], 1)  # negatively correlated: kappa < 1
    innovation = np.stack([10.0 * smooth, alternating], axis=1)
    S = np.broadcast_to(np.diag([100.0, 1.0]), (T, 2, 2))
    ys = np.zeros((T, 2))
    ys[-3:, 1] = np.nan  # the last rows are left out
    result = SimpleNamespace(innovation=innovation, innovation_cov=S)
    kappa = svd_ekf.colour_factors(result, ys, rate)
    expect = svd_ekf.long_run_variance_ratio(smooth[:-3, None], int(svd_ekf.RESIDUAL_LAG_S * rate))
    np.testing.assert_allclose(kappa, [expect[0], 1.0])
    assert kappa[0] > 3


def test_joint_estimate_is_the_batch_posterior_of_a_linear_case():
    """Two records y_mk = x_m + k theta + v_mk (x_m each record's own constant, theta shared):
    running the filter through them in turn gives the Gaussian posterior of theta given both,
    computed here by batch least squares on (x_1, x_2, theta) with their prior."""
    import jax.numpy as jnp

    from jaxest import LinearGaussian
    from jaxest._priors import Gaussian

    rng = np.random.default_rng(5)
    F, H, r = np.array([[1.0, 1.0], [0.0, 1.0]]), np.array([[1.0, 0.0]]), 0.3
    prior_std = np.array([2.0, 0.5])  # x_m, theta
    lengths, theta = (30, 20), 0.2
    starts = (1.0, -2.0)
    ys = [
        x0 + theta * np.arange(n) + r * rng.normal(size=n)
        for x0, n in zip(starts, lengths, strict=True)
    ]
    with jax.enable_x64(True):
        model = LinearGaussian(jnp.asarray(F), jnp.asarray(H), jnp.zeros((2, 2)), jnp.eye(1) * r**2)
        prior = Gaussian(jnp.zeros(2), jnp.diag(jnp.asarray(prior_std) ** 2))
        runs = [(model, jnp.asarray(y)[:, None], None, prior) for y in ys]
        mean, cov = svd_ekf.joint_estimate(runs, 1)
    A = np.zeros((sum(lengths), 3))  # columns x_1, x_2, theta
    A[: lengths[0], 0] = 1.0
    A[lengths[0] :, 1] = 1.0
    A[:, 2] = np.concatenate([np.arange(n) for n in lengths])
    info = A.T @ A / r**2 + np.diag(1 / np.array([2.0, 2.0, 0.5]) ** 2)
    post_cov = np.linalg.inv(info)
    post_mean = post_cov @ A.T @ np.concatenate(ys) / r**2
    np.testing.assert_allclose(float(mean[0]), post_mean[2], rtol=1e-6)
    np.testing.assert_allclose(float(cov[0, 0]), post_cov[2, 2], rtol=1e-6)


def test_trim_reparametrisation_moves_the_alpha_offset_to_the_trim_angle():
    """b_alpha_trim = b_alpha + lam_alpha alpha_trim with variance var_b + a^2 var_lam +
    2 a cov(b, lam), written out; the other entries are unchanged."""
    rng = np.random.default_rng(6)
    names = ("u", "b_alpha", "lam_alpha", "b_q")
    A = rng.normal(size=(4, 4))
    cov, mean = A @ A.T, rng.normal(size=4)
    new_mean, new_cov, new_names = svd_ekf.trim_reparametrised(mean, cov, names)
    a = svd_ekf.ALPHA_TRIM
    assert new_names == ("u", "b_alpha_trim", "lam_alpha", "b_q")
    assert new_mean[1] == pytest.approx(mean[1] + a * mean[2])
    assert new_cov[1, 1] == pytest.approx(cov[1, 1] + a**2 * cov[2, 2] + 2 * a * cov[1, 2])
    keep = [0, 2, 3]
    np.testing.assert_allclose(new_mean[keep], mean[keep])
    np.testing.assert_allclose(new_cov[np.ix_(keep, keep)], cov[np.ix_(keep, keep)])


def test_channel_rms_skips_missing_samples_and_channels_without_a_warning():
    """Per channel over the measured samples after the settle window; a channel with no sample
    (HFB-320's altitude) is NaN, and numpy's "Mean of empty slice" warning is not raised."""
    residuals = np.full((5, len(svd_ekf.OUTPUTS)), np.nan)
    residuals[:, 0] = [9.0, 3.0, np.nan, 4.0, 0.0]  # settle = 1 drops the 9
    residuals[2:, 1] = 2.0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rms = svd_ekf.channel_rms(residuals, settle=1)
    units = np.asarray(svd_ekf.OUTPUT_UNITS)
    np.testing.assert_allclose(rms[:2], np.array([np.sqrt(25.0 / 3), 2.0]) * units[:2])
    assert np.all(np.isnan(rms[2:]))


def test_real_data_settings_read_back_the_delays_and_the_tuned_input_noise():
    tuned = {"a_x": 1.9, "a_y": 0.007, "a_z": 3.3, "p": 0.07, "q": 0.2, "r": 0.14, "V": 0.13}
    summary = {"real_data": {"sensor_delays_s": {"beta": 0.08, "alpha": 0.12}},
               "tuning": {"real": {"tuned_noise": tuned}}}  # fmt: skip
    delays, input_std = svd_ekf.real_data_settings(summary)
    expected = np.zeros(6)
    expected[[svd_ekf.OUTPUTS.index("beta"), svd_ekf.OUTPUTS.index("alpha")]] = [0.08, 0.12]
    np.testing.assert_array_equal(delays, expected)
    deg = np.pi / 180.0  # rates are reported in deg/s
    np.testing.assert_allclose(input_std, [1.9, 0.007, 3.3, 0.07 * deg, 0.2 * deg, 0.14 * deg])
