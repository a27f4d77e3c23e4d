"""Which sensor terms the ATTAS records support beyond the study's model (issue 16); prints JSON.

    python -m jaxest reproduce svd-ekf --out results
    python benchmarks/flight_sensor_terms.py --summary results/svd-ekf/summary.json [--json PATH]

The svd-ekf study's real-data estimates disagree between the aileron and the rudder record in
the sideslip vane's bias and scale factor (docs/papers/svd_ekf.md). This script refits each ATTAS
record as :func:`jaxest.studies.svd_ekf.estimate_record` does (the pinned model, a first
filter pass for the residuals' colour factors, a second with R scaled by them, the RTS smoother's
x(0|T), P(0|T)), with extra constant states appended to the pinned model, one variant at a time:

- ``vane_rate_terms``: k_p, k_r (m) in beta_vane = atan2(v + r k_r - p k_p, u), what lever arms
  of the beta vane (or sidewash from the rates) would add (prior std 10 m);
- ``bank_angle_scale``: lam_phi in phi_m = (1 + lam_phi) phi + b_phi (prior std 0.05);
- ``roll_gyro_scale``: lam_p, the roll gyro read as (1 + lam_p) p_m (prior std 0.05).

It takes the study's tuned input noise and flow-vane delays from its ``summary.json``, so that
the model without extra states (``none``) gives the study's numbers. Reported per record: the
first pass's log-likelihood (white-noise R, the same for every variant), the estimates with their
colour-corrected standard errors (deg, deg/s, m/s^2, m), and for every pair of records the
difference in standard errors, as in the study. EKF, float64 (the SVD-EKF agrees to rounding).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import equinox as eqx
import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax.scipy.linalg import block_diag  # noqa: E402

from jaxest import Gaussian  # noqa: E402
from jaxest.filters import EKF  # noqa: E402
from jaxest.models import NonlinearGaussian  # noqa: E402
from jaxest.report import emit_json  # noqa: E402
from jaxest.studies import svd_ekf  # noqa: E402
from jaxest.systems import flight, flight_data  # noqa: E402

#: variant -> its extra states; their prior std
VARIANTS = {
    "none": (),
    "vane_rate_terms": ("k_p", "k_r"),
    "bank_angle_scale": ("lam_phi",),
    "roll_gyro_scale": ("lam_p",),
}
EXTRA_STD = {"k_p": 10.0, "k_r": 10.0, "lam_phi": 0.05, "lam_p": 0.05}
#: the estimates reported, and the report unit of each
REPORTED = {"b_ay": 1.0, "b_p": 1 / svd_ekf.DEG, "b_r": 1 / svd_ekf.DEG,
            "b_beta": 1 / svd_ekf.DEG, "lam_beta": 1.0}  # fmt: skip
#: the roll rate's entries in the interval input [u_m(k), u_m(k + 1)]
ROLL_RATE = np.array([3, 3 + flight.N_IN])


def roll_gyro_read(u, extra, names):
    """The interval input with the roll rate scaled by 1 + lam_p (unchanged without lam_p)."""
    if "lam_p" not in names:
        return u
    return u * jnp.ones_like(u).at[ROLL_RATE].set(1.0 + extra[names.index("lam_p")])


class ExtendedTransition(eqx.Module):
    f: eqx.Module
    extra: tuple[str, ...] = eqx.field(static=True)

    def __call__(self, x, u):
        n = len(self.extra)
        u = roll_gyro_read(u, x[-n:], self.extra)
        return jnp.concatenate([self.f(x[:-n], u), x[-n:]])


class ExtendedNoiseGain(eqx.Module):
    gain: eqx.Module
    extra: tuple[str, ...] = eqx.field(static=True)

    def __call__(self, x, u):
        n = len(self.extra)
        G = self.gain(x[:-n], roll_gyro_read(u, x[-n:], self.extra))
        return jnp.concatenate([G, jnp.zeros((n, G.shape[1]), G.dtype)])


class ExtendedObservation(eqx.Module):
    h: eqx.Module
    names: tuple[str, ...] = eqx.field(static=True)  # the pinned model's states
    extra: tuple[str, ...] = eqx.field(static=True)

    def __call__(self, x, u):
        n, i = len(self.extra), {s: k for k, s in enumerate(self.names)}
        z, extra = x[:-n], dict(zip(self.extra, x[-n:], strict=True))
        y = self.h(z, u)
        if "k_p" in extra:
            p, r = u[3] + z[i["b_p"]], u[5] + z[i["b_r"]]
            at_vane = jnp.arctan2(z[i["v"]] + r * extra["k_r"] - p * extra["k_p"], z[i["u"]])
            shift = at_vane - jnp.arctan2(z[i["v"]], z[i["u"]])
            y = y.at[1].add((1.0 + z[i["lam_beta"]]) * shift)
        if "lam_phi" in extra:
            y = y.at[4].add(extra["lam_phi"] * z[i["phi"]])
        return y


def model_with(dt, input_std, output_std, extra):
    """The study's pinned model with the states ``extra`` appended, and all state names."""
    pinned, names = svd_ekf.pinned_model(dt, input_std, output_std)
    if not extra:
        return pinned, names
    model = NonlinearGaussian(
        ExtendedTransition(pinned.transition_fn, extra),
        ExtendedObservation(pinned.observation_fn, names, extra),
        pinned.Q,
        pinned.R,
        noise_gain=ExtendedNoiseGain(pinned.noise_gain, extra),
    )
    return model, names + extra


def prior_with(data, extra):
    prior = svd_ekf.reduced_prior(data, svd_ekf.PINNED)
    std = jnp.asarray([EXTRA_STD[e] for e in extra])
    cov = block_diag(prior.cov, jnp.diag(std**2))
    return Gaussian(jnp.concatenate([prior.mean, jnp.zeros(len(extra))]), cov)


def estimate(data, input_std, output_std, extra) -> dict:
    fit = svd_ekf.colour_corrected_fit(
        lambda std: model_with(data.dt, input_std, std, extra), data, prior_with(data, extra),
        output_std, EKF(),
    )  # fmt: skip
    mean, cov, names = np.asarray(fit.smooth.mean[0]), np.asarray(fit.smooth.cov[0]), fit.names
    units = REPORTED | dict.fromkeys(extra, 1.0)
    return {
        "loglik_white": float(fit.first.loglik),
        "status": int(np.max(np.asarray(fit.result.status))),
        "parameters": {
            p: {"value": float(mean[names.index(p)] * u),
                "std": float(np.sqrt(cov[names.index(p), names.index(p)]) * u)}
            for p, u in units.items()
        },
    }  # fmt: skip


def records_and_noise(summary: dict):
    """The aligned ATTAS records and the tuned input noise of the study's ``summary.json``."""
    delays, input_std = svd_ekf.real_data_settings(summary)
    data_dir = flight_data.find_data_dir()
    records = {
        m: svd_ekf.aligned(flight_data.load_attas(m, data_dir), delays)
        for m in summary["real_data"]["files"]
    }
    return records, input_std


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--summary", required=True, help="the svd-ekf study's summary.json")
    parser.add_argument("--variants", nargs="+", choices=list(VARIANTS), default=list(VARIANTS))
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    records, input_std = records_and_noise(json.loads(Path(args.summary).read_text()))
    result = {}
    for variant in args.variants:
        fits = {m: estimate(d, input_std, svd_ekf.REAL_OUTPUT_STD, VARIANTS[variant])
                for m, d in records.items()}  # fmt: skip
        agreement = svd_ekf.bias_agreement({m: f["parameters"] for m, f in fits.items()})
        result[variant] = {"by_maneuver": fits, "agreement_se": agreement}
        print(variant, {m: round(f["loglik_white"], 1) for m, f in fits.items()}, flush=True)
    emit_json(result, args.json)


if __name__ == "__main__":
    main()
