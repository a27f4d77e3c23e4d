"""The sigma-point study: the bearings-only system, and the study end to end in --quick form."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxest as je
from jaxest.systems import bearings


def test_bearings_model_is_the_papers():
    """Noise-free, the target moves on a straight line and the measurement is its bearing;
    the simulated noise has the paper's standard deviations."""
    model, prior = bearings.model(), bearings.prior()
    x0 = jnp.asarray(bearings.X0)
    x1 = model.f(x0)
    np.testing.assert_allclose(x1, [-0.049, 0.001, 0.645, -0.055], rtol=1e-12)
    np.testing.assert_allclose(model.h(x1), [np.arctan2(0.645, -0.049)], rtol=1e-12)
    G, Q = model.process_noise(x0, None, 0)
    np.testing.assert_allclose(G @ Q @ G.T, 1e-6 * np.kron(np.eye(2), [[0.25, 0.5], [0.5, 1]]))
    runs = je.monte_carlo(lambda k: je.simulate(model, prior, 24, k), jax.random.PRNGKey(0), 400)
    noise = runs.y[..., 0] - jax.vmap(jax.vmap(lambda x: bearings.bearing(x)[0]))(runs.states)
    assert abs(float(jnp.std(noise)) / bearings.BEARING_STD - 1) < 0.03


@pytest.mark.slow
def test_quick_study_writes_the_summary(tmp_path):
    from jaxest.studies import sigma_point

    summary = sigma_point.run(tmp_path, runs=6, seed=0, quick=True, options={})
    out = tmp_path / "sigma-point"
    on_disk = json.loads((out / "summary.json").read_text())
    assert set(on_disk["problems"]) == {"duffing", "bearings"}
    for problem in ("duffing", "bearings"):
        for dtype in ("float64", "float32"):
            block = summary["problems"][problem][dtype]
            assert set(block["filters"]) == set(sigma_point.QUICK_FILTERS)
            for r in block["filters"].values():
                assert 0 <= r["diverged"] <= 6 and r["us_per_step"] > 0
        f64 = summary["problems"][problem]["float64"]["filters"]
        # the square-root form is the covariance form in other arithmetic
        assert f64["ukf_sqrt"]["rmse"] == pytest.approx(f64["ukf_covariance"]["rmse"], rel=1e-8)
    duffing = summary["problems"]["duffing"]["float64"]["filters"]
    assert all(r["diverged"] == 0 for r in duffing.values())
    for r in duffing.values():  # a nearly linear problem: every filter close to the EKF
        assert r["rmse"] == pytest.approx(duffing["ekf"]["rmse"], rel=0.1)
    assert summary["svd_form_difference"]["duffing"]["ukf"] < 1e-3
    tuning = summary["tuning"]
    assert tuning["loss_last"] < tuning["loss_first"]
    assert np.all(np.abs(tuning["z_scores"]) < 4)
    assert (out / "filters.png").stat().st_size > 0
    assert "## bearings" in (out / "tables.md").read_text()
    conv = summary["pf_loglik"]["by_particles"]
    assert conv[1000]["std"] < conv[100]["std"] / 2  # 1/sqrt(N) would give 3.2
