"""The svd-ekf study end to end in its --quick form."""

import json

import jax
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
            assert set(F) >= {"rmse", "param_error", "diverged_runs", "runs", "nees"}
            assert F["runs"] == 3 and set(F["rmse"]) == set(svd_ekf.KINEMATIC_STATES)
            assert F["rmse"]["theta"] < 0.5  # deg: the filters track the attitude
    if data is None:
        assert "real_data" not in summary and "flt_data.zip" in summary["real_data_note"]
    else:
        real = summary["real_data"]
        assert set(real["residual_rms"]) == {"V", "beta", "alpha", "theta", "phi", "h"}
        assert set(real["parameters"]) == set(svd_ekf.PARAMETERS)
        assert list(out.glob("*.png"))
    assert (out / "tables.md").exists()
