"""The flight filters in float32 on the real records, as given and with the state in units of its
prior standard deviations; prints JSON (docs/robustness.md, "The 23-state flight model in
float32").

    python benchmarks/flight_float32.py [--data DIR] [--json PATH]

Each record the svd-ekf study reconstructs (HFB-320 and the ATTAS elevator, aileron and rudder
manoeuvres) is filtered with the study's prior (``real_prior``) and output noise, the
simulator's input noise, by the SVD-EKF, the improved SVD filter and the EKF, in float64 and in
float32. Each float32 run is measured against its filter's float64 run: the largest error of the
filtered means over steps and states in the float64 posterior standard deviations (sqrt of the
diagonal of P(k|k)), the log-likelihood's difference in nats, and the status; and the largest
condition number of the float32 run's P(k|k) over its steps (``cond_max``, its eigenvalues taken
in float64), to set beside 1 / eps(float32) = 8.4e6.

``scaled`` runs the same filter on the same model with the state x = s * x~, s the prior's
standard deviations (``jaxest.scale_state``, in float32): f~(x~, u) = f(s x~, u) / s,
G~ = G(s x~, u) / s (row-wise), h~(x~, u) = h(s x~, u), the prior's mean / s and covariance /
(s s^T); the means are mapped back by s before they are compared. The model's states span h
near 5 000 m to gyro biases of 1e-3 rad/s, and a covariance of such spread has directions that
float32 factors do not resolve unless the state is scaled.
"""

from __future__ import annotations

import argparse

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
from parallel_accuracy import in_standard_deviations  # noqa: E402

import jaxest as je  # noqa: E402
from jaxest.report import emit_json  # noqa: E402
from jaxest.setmembership.ellipsoid import condition_number  # noqa: E402
from jaxest.studies import svd_ekf as study  # noqa: E402
from jaxest.systems import flight_data  # noqa: E402

FILTERS = {"SVDEKF": je.SVDEKF, "ImprovedSVDKF": je.ImprovedSVDKF, "EKF": je.EKF}


def records(data_dir) -> dict[str, flight_data.FlightData]:
    """The four records of the svd-ekf study."""
    attas = {
        maneuver: flight_data.load_attas(maneuver, data_dir) for maneuver in flight_data.ATTAS_FILES
    }
    return {"hfb320": flight_data.load_hfb320(data_dir), **attas}


def largest_condition_number(covs) -> float:
    """max over steps of :func:`~jaxest.setmembership.ellipsoid.condition_number` of the
    covariances ``covs`` (T, n, n), in float64: infinite where one is singular or indefinite."""
    return float(jnp.max(jax.vmap(condition_number)(jnp.asarray(covs, jnp.float64))))


def float32_errors(Filter, data: flight_data.FlightData) -> dict:
    """The float32 runs of ``Filter`` on ``data``, as given and scaled, against its float64 run
    (the svd-ekf study's ``reconstruct``)."""
    reference, model, inputs = study.reconstruct(
        data, study.sim.INPUT_STD, study.REAL_OUTPUT_STD, Filter()
    )
    single = lambda tree: je.astype(tree, jnp.float32)
    model, prior = single(model), single(study.real_prior(data))
    scaled_model, scaled_prior = je.scale_state(model, prior)  # in float32
    # (model, prior, what maps the run's means back to the state's units)
    forms = {
        "as_given": (model, prior, lambda mean: mean),
        "scaled": (scaled_model, scaled_prior, scaled_model.state_mean),
    }
    row = {}
    for form, (m, p, back) in forms.items():
        result = je.run(Filter(), m, single(data.outputs), inputs=single(inputs), prior=p)
        row[form] = {
            "mean_err_sd": in_standard_deviations(back(result.mean), reference),
            "loglik_diff": float(result.loglik) - float(reference.loglik),
            "status": type(result).flags.describe(result.any_status),
            "cond_max": largest_condition_number(result.cov),
        }
    return row


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=None, help="the flight-data directory (default: found)")
    parser.add_argument("--json", default=None, help="write the results here (default: stdout)")
    args = parser.parse_args(argv)
    rows = []
    for name, data in records(args.data).items():
        for filter_name, Filter in FILTERS.items():
            row = {"record": name, "steps": len(data.t), "filter": filter_name}
            rows.append(row | float32_errors(Filter, data))
            print(rows[-1], flush=True)
    emit_json({"rows": rows}, args.json)


if __name__ == "__main__":
    main()
