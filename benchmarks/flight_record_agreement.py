"""Why the ATTAS records disagree on the sideslip vane (issue 16); prints JSON.

    python -m jaxest reproduce svd-ekf --out results
    python benchmarks/flight_record_agreement.py --summary results/svd-ekf/summary.json \
        [--json PATH] [--figure PNG]

The svd-ekf study's three ATTAS records are 25-30 s slices of one 170 s flight. The book's files
hold all of it, each maneuver flown twice back to back: fAttasElv1 and fAttasElv2, then
fAttasAilRud1 and fAttasAilRud2, each an aileron slice followed by a rudder slice (the first's
rudder slice is the study's rudder record). This script fits all six slices as
:func:`jaxest.studies.svd_ekf.estimate_record` does (the pinned model, a first pass for the
residuals' colour factors, a second with R scaled by them, the RTS smoother's x(0|T), P(0|T); the
study's delays and tuned input noise from its ``summary.json``; EKF, float64) and reports:

- ``flight``: each slice's time span in the flight, and the largest difference between the
  slices and the study's records (zero: they are the same samples);
- ``altitude_pull``: per slice, what holding b_beta at zero mean sideslip (b_beta = the slice's
  mean beta_m) costs in the first pass's log-likelihood, and the change of each output channel's
  sum of e_j^2 / S_jj: which measurement sets b_beta;
- ``models``: every slice's estimates (report units, with the colour-corrected standard errors and
  whether the slice identifies the parameter: posterior / prior std below 0.5, as in the study)
  and, for every parameter, the largest disagreement in standard errors between slices that
  identify it, over the study's three slices and over all six, under three models:
  - ``study``: the study's model;
  - ``altitude_deweighted``: the same with the pressure altitude's noise std set to 10 km, which
    takes its information out;
  - ``wind_states``: the air mass's motion as three states (:mod:`jaxest.systems.flight_wind`),
    the wind's north, east and down components relative to the start of the slice, each a
    random walk (``wind_step`` m/s per sample); the flow sensors (V, beta, alpha) see the
    kinematic velocity minus the wind in body axes. The accelerometers' noise std
    (``accelerometer``, m/s^2), which the study's tuning set to 1.9 and 3.3 m/s^2 for a_x and a_z
    to take up the turbulence, is chosen anew with it: the pair of the grid with the largest
    summed log-likelihood of the six slices (``wind_grid``).

``--figure`` draws b_beta, lam_beta and b_alpha_trim of every slice under the three models.
"""

from __future__ import annotations

import argparse
import itertools
import json
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
import scipy.io  # noqa: E402

from jaxest import Gaussian, plot  # noqa: E402
from jaxest.filters import EKF  # noqa: E402
from jaxest.report import emit_json  # noqa: E402
from jaxest.studies import svd_ekf  # noqa: E402
from jaxest.systems import flight_data, flight_wind  # noqa: E402

#: the six slices in flight order: name -> (file, first row, rows); the study's records are
#: ``elevator``, ``aileron`` and ``rudder``
SLICES = {
    "elevator": ("fAttasElv1.mat", 0, 626),
    "elevator_repeat": ("fAttasElv2.mat", 0, 626),
    "aileron": ("fAttasAilRud1.mat", 0, 751),
    "aileron_repeat": ("fAttasAilRud2.mat", 0, 751),
    "rudder": ("fAttasAilRud1.mat", 751, 751),
    "rudder_repeat": ("fAttasAilRud2.mat", 751, 751),
}
STUDY_SLICES = ("elevator", "aileron", "rudder")
#: the pressure altitude's noise std (m) of ``altitude_deweighted``
DEWEIGHTED_ALTITUDE_STD = 1e4
#: the ``wind_states`` grid: accelerometer noise std (m/s^2) x wind step std (m/s per sample)
ACCELEROMETER_GRID = (0.2, 1.0, 2.0)
WIND_STEP_GRID = (0.03, 0.05, 0.08)
#: prior std of the wind states (m/s) and of a held b_beta (rad): zero in effect, positive because
#: the filters take a positive definite prior
WIND_START_STD, HELD_STD = 1e-6, 1e-9


def read_slices(data_dir=None) -> dict[str, tuple[float, flight_data.FlightData]]:
    """The six slices of the ATTAS flight, unaligned: (start time in the flight (s), record)."""
    directory = flight_data.find_data_dir(data_dir)
    if directory is None:
        raise ValueError(f"data: no flight-data directory. {flight_data.DOWNLOAD_HINT}")
    slices = {}
    for name, (file, first, rows) in SLICES.items():
        table = scipy.io.loadmat(directory / file)[Path(file).stem][first : first + rows]
        record = flight_data.attas_record(table, f"ATTAS {name}")
        slices[name] = (float(table[0, 0]), record)
    return slices


def wind_model(dt, input_std, output_std, wind_step):
    """The pinned model with the wind states of :func:`flight_wind.with_wind`, and all names."""
    return flight_wind.with_wind(*svd_ekf.pinned_model(dt, input_std, output_std), wind_step)


def wind_prior(data):
    """:func:`svd_ekf.reduced_prior` with the wind states at zero (relative to the start)."""
    prior = svd_ekf.reduced_prior(data, svd_ekf.PINNED)
    return flight_wind.prior_with_wind(prior, WIND_START_STD)


def model_and_prior(name, data, input_std, settings):
    """(model_for_r, prior) of one of the three models of the module docstring."""
    if name == "wind_states":
        input_std = np.asarray(input_std).copy()
        input_std[:3] = settings["accelerometer"]
        step = settings["wind_step"]
        return (lambda std: wind_model(data.dt, input_std, std, step)), wind_prior(data)
    return (lambda std: svd_ekf.pinned_model(data.dt, input_std, std)), svd_ekf.reduced_prior(
        data, svd_ekf.PINNED
    )


def output_std_of(name):
    std = np.asarray(svd_ekf.REAL_OUTPUT_STD, float).copy()
    if name == "altitude_deweighted":
        std[svd_ekf.OUTPUTS.index("h")] = DEWEIGHTED_ALTITUDE_STD
    return std


def fit(name, data, input_std, settings=None) -> dict:
    """The colour-corrected fit of one slice under model ``name``: the first pass's
    log-likelihood and the sensor parameters (b_alpha as b_alpha_trim), in report units."""
    model_for_r, prior = model_and_prior(name, data, input_std, settings)
    result = svd_ekf.colour_corrected_fit(model_for_r, data, prior, output_std_of(name), EKF())
    table, std_ratio = svd_ekf.smoothed_parameters(result, prior)
    for p in table:
        table[p]["identified"] = std_ratio[p] < svd_ekf.OBSERVABLE_RATIO
    return {
        "loglik_white": float(result.first.loglik),
        "status": int(np.max(np.asarray(result.result.status))),
        "parameters": table,
    }


def first_pass_loglik(name, data, input_std, settings) -> float:
    model_for_r, prior = model_and_prior(name, data, input_std, settings)
    model, _ = model_for_r(output_std_of(name))
    result, _ = svd_ekf.filter_record(model, data, prior, EKF())
    return float(result.loglik)


def worst_disagreement(fits, slices) -> dict:
    """Per parameter, the largest |difference| / combined std over pairs of ``slices`` that both
    identify it: {"pair": "a-b", "se": ...} (None where fewer than two identify it)."""
    out = {}
    for p in fits[slices[0]]["parameters"]:
        ident = [s for s in slices if fits[s]["parameters"][p]["identified"]]
        if len(ident) < 2:
            out[p] = None
            continue
        pairs = svd_ekf.bias_agreement({s: {p: fits[s]["parameters"][p]} for s in ident})[p]
        pair, se = max(pairs.items(), key=lambda kv: kv[1])
        out[p] = {"pair": pair, "se": float(se)}
    return out


def altitude_pull(data, input_std) -> dict:
    """Holding b_beta at the slice's mean beta_m (zero mean sideslip) in the study's first pass:
    the log-likelihood change and each output's change of sum_k e_j(k)^2 / S_jj(k)."""
    model_for_r, prior = model_and_prior("study", data, input_std, None)
    model, names = model_for_r(output_std_of("study"))
    j = names.index("b_beta")
    held_at = float(np.nanmean(data.outputs[:, svd_ekf.OUTPUTS.index("beta")]))
    held = Gaussian(prior.mean.at[j].set(held_at),
                    prior.cov.at[j, :].set(0.0).at[:, j].set(0.0).at[j, j].set(HELD_STD**2))  # fmt: skip

    def pass_with(p):
        result, _ = svd_ekf.filter_record(model, data, p, EKF())
        e, S = np.asarray(result.innovation), np.asarray(result.innovation_cov)
        return float(result.loglik), np.nansum(e**2 / np.diagonal(S, axis1=-2, axis2=-1), axis=0)

    (free_ll, free_sq), (held_ll, held_sq) = pass_with(prior), pass_with(held)
    return {
        "b_beta_held_deg": held_at / svd_ekf.DEG,
        "loglik_change": held_ll - free_ll,
        "normalised_square_change": {
            o: float(held_sq[k] - free_sq[k]) for k, o in enumerate(svd_ekf.OUTPUTS)
        },
    }


#: the parameters drawn by :func:`figure`, with their axis labels
FIGURE_PARAMETERS = {"b_beta": "b_beta (deg)", "lam_beta": "lam_beta",
                     "b_alpha_trim": "b_alpha_trim (deg)"}  # fmt: skip


def figure(models: dict, path) -> Path:
    """Each parameter of :data:`FIGURE_PARAMETERS` per slice (flight order) under every model, with
    its standard error; open markers where the slice does not identify it."""
    fig, axes = plot.subplots(1, len(FIGURE_PARAMETERS), width=4.6, height=3.6)
    names = list(SLICES)
    for ax, (p, label) in zip(axes[0], FIGURE_PARAMETERS.items(), strict=True):
        for k, (model, entry) in enumerate(models.items()):
            x = np.arange(len(names)) + 0.2 * (k - 1)
            table = [entry["by_slice"][s]["parameters"][p] for s in names]
            value, std = np.array([t["value"] for t in table]), np.array([t["std"] for t in table])
            filled = np.array([t["identified"] for t in table])
            ax.errorbar(x, value, yerr=std, fmt="none", capsize=2, color=f"C{k}")
            ax.plot(x[filled], value[filled], "o", color=f"C{k}", label=model.replace("_", " "))
            ax.plot(x[~filled], value[~filled], "o", mfc="none", color=f"C{k}")
        ax.set_xticks(range(len(names)), [s.replace("_repeat", "\nrepeat") for s in names],
                      fontsize=8)  # fmt: skip
        ax.set_ylabel(label)
        ax.axhline(0.0, color="0.7", lw=0.8)
    axes[0][0].legend(fontsize=8)
    return plot.save(fig, path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--summary", required=True, help="the svd-ekf study's summary.json")
    parser.add_argument("--data", default=None, help="the flight-data directory")
    parser.add_argument("--json", default=None)
    parser.add_argument("--figure", default=None, help="PNG of the estimates per slice")
    args = parser.parse_args()
    delays, input_std = svd_ekf.real_data_settings(json.loads(Path(args.summary).read_text()))
    raw = read_slices(args.data)
    slices = {s: svd_ekf.aligned(d, delays) for s, (_, d) in raw.items()}
    study_records = {m: flight_data.load_attas(m, args.data) for m in STUDY_SLICES}
    report = {
        "flight": {
            "slices_s": {s: [t0, t0 + float(d.t[-1])] for s, (t0, d) in raw.items()},
            "max_difference_to_study_records": max(
                float(np.nanmax(np.abs(np.concatenate([
                    raw[m][1].inputs - r.inputs, raw[m][1].outputs - r.outputs], axis=1))))
                for m, r in study_records.items()),
        },
        "altitude_pull": {s: altitude_pull(d, input_std) for s, d in slices.items()},
    }  # fmt: skip
    print("altitude pull done", flush=True)
    grid = {}
    for acc, step in itertools.product(ACCELEROMETER_GRID, WIND_STEP_GRID):
        settings = {"accelerometer": acc, "wind_step": step}
        lls = {
            s: first_pass_loglik("wind_states", d, input_std, settings) for s, d in slices.items()
        }
        grid[f"{acc},{step}"] = {**settings, "loglik_white": lls, "total": sum(lls.values())}
        print("wind grid", acc, step, round(grid[f"{acc},{step}"]["total"], 1), flush=True)
    best = max(grid.values(), key=lambda g: g["total"])
    report["wind_grid"] = {
        "points": grid,
        "best": {k: best[k] for k in ("accelerometer", "wind_step")},
    }
    report["models"] = {}
    for name in ("study", "altitude_deweighted", "wind_states"):
        fits = {s: fit(name, d, input_std, report["wind_grid"]["best"]) for s, d in slices.items()}
        report["models"][name] = {
            "by_slice": fits,
            "worst_study_slices_se": worst_disagreement(fits, STUDY_SLICES),
            "worst_all_slices_se": worst_disagreement(fits, list(SLICES)),
        }
        print(name, {s: round(f["loglik_white"], 1) for s, f in fits.items()}, flush=True)
    if args.figure:
        figure(report["models"], args.figure)
    emit_json(report, args.json)


if __name__ == "__main__":
    main()
