"""Study ``svd-ekf``: flight state and sensor-parameter estimation with the SVD-based EKF
(Zhang, Dai & Zhang), on simulated maneuvers and on real ATTAS / HFB-320 flight data.

1. Monte Carlo on the simulator (:mod:`jaxest.systems.flight_sim`): for every maneuver (elevator
   3-2-1-1, aileron bank-to-bank, rudder doublet), sample rate (10 and 32 Hz) and dtype (float64,
   float32), ``runs`` flights with their own true sensor parameters (drawn from the prior), sensor
   noise and initial estimate, filtered by the paper's EKF, its SVD-EKF and the improved SVD filter
   (Kulikova & Tsyganova), all ``vmap``ped. Reported: state RMSE, parameter error, diverged runs,
   NEES, and which parameters each maneuver makes observable.
2. Real data (:mod:`jaxest.systems.flight_data`): the same reconstruction of the ATTAS elevator,
   aileron and rudder maneuvers and of the HFB-320 record, with biases, scale factors and residuals.
3. Maximum-likelihood tuning of the input-noise (Q) and measurement-noise (R) levels by gradient
   ascent of the SVD filter's log-likelihood, on simulated and real data.
"""

from __future__ import annotations

from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from jaxest.filters import EKF, SVDEKF, ImprovedSVDKF  # noqa: E402
from jaxest.progress import Progress  # noqa: E402
from jaxest.report import markdown_table, write_json  # noqa: E402
from jaxest.run import Gaussian, Status  # noqa: E402
from jaxest.run import run as run_filter  # noqa: E402
from jaxest.systems import flight, flight_data  # noqa: E402
from jaxest.systems import flight_sim as sim  # noqa: E402
from jaxest.systems.flight import KINEMATIC_STATES, N_KIN, N_STATE, OUTPUTS, PARAMETERS  # noqa: E402

NAME = "svd-ekf"
DESCRIPTION = "SVD-EKF flight state & sensor-parameter estimation (simulated + ATTAS/HFB-320 data)"

FILTERS = {"ekf": EKF(), "svd_ekf": SVDEKF(), "svd_improved": ImprovedSVDKF()}
DEG = np.pi / 180.0
#: prior std of the kinematic states: u, v, w (m/s), phi, theta, psi (rad), h (m)
KINEMATIC_STD = np.array([1.0, 1.0, 1.0, 0.5 * DEG, 0.5 * DEG, 2.0 * DEG, 10.0])
#: a run diverged if its status flags anything or its mean NEES exceeds this (dimension 23)
NEES_DIVERGED = 1000.0
#: seconds of initial convergence left out of the state RMSE
SETTLE_S = 1.0
#: a parameter counts as observable in a maneuver when its posterior std falls below this
#: fraction of its prior std
OBSERVABLE_RATIO = 0.5
#: units in which the tables and JSON report each state / parameter / output
STATE_UNITS = {"u": 1, "v": 1, "w": 1, "phi": 1 / DEG, "theta": 1 / DEG, "psi": 1 / DEG, "h": 1}
PARAMETER_UNITS = np.array([1, 1, 1, 1 / DEG, 1 / DEG, 1 / DEG, 1, 1 / DEG, 1 / DEG, 1 / DEG,
                            1 / DEG, 1, 1, 1, 1, 1])  # fmt: skip
OUTPUT_UNITS = np.array([1, 1 / DEG, 1 / DEG, 1 / DEG, 1 / DEG, 1])
#: HFB-320 noise levels of ../shared/data/README.md in output units (V m/s, angles deg)
HFB320_NOISE = {"V": 0.13, "alpha": 0.057, "theta": 0.025}


def prior_cov(dtype):
    std = np.concatenate([KINEMATIC_STD, sim.PARAMETER_STD])
    return jnp.asarray(np.diag(std**2), dtype)


def simulated_batch(truth: sim.TrueFlight, runs: int, key, dtype, noise_scale: float = 1.0):
    """``runs`` corrupted copies of ``truth``: (ys, interval inputs, priors, true states), each
    with a leading run axis; all in ``dtype``."""

    def one(k):
        k_par, k_noise, k_init = jax.random.split(k, 3)
        params = sim.draw_parameters(k_par, truth.states.dtype)
        record = sim.corrupt(
            truth, params, k_noise, sim.INPUT_STD * noise_scale, sim.OUTPUT_STD * noise_scale
        )
        mean0 = sim.initial_guess(record.true_states[0], k_init, KINEMATIC_STD)
        inputs = flight.interval_inputs(record.measured_inputs)
        cast = lambda a: a.astype(dtype)
        return cast(record.measurements), cast(inputs), cast(mean0), cast(record.true_states)

    return jax.jit(jax.vmap(one))(jax.random.split(key, runs))


def model_for(rate_hz, dtype, noise_scale=1.0, lever_arms=sim.LEVER_ARMS, output_std=None):
    output_std = sim.OUTPUT_STD if output_std is None else output_std
    return flight.flight_model(
        1.0 / rate_hz,
        jnp.asarray(sim.INPUT_STD * noise_scale, dtype),
        jnp.asarray(output_std * noise_scale, dtype),
        lever_arms,
    )


#: one compiled single-run filter, shared by the figures and the real-data runs
filter_once = eqx.filter_jit(run_filter)


def run_metrics(estimator, model, ys, inputs, mean0, P0, truth, settle: int):
    """Per-run summary of one filter run: squared state errors averaged over time after ``settle``
    steps, final parameter errors and standard deviations, mean NEES, status."""
    result = run_filter(estimator, model, ys, inputs, Gaussian(mean0, P0))
    err = (result.mean - truth).astype(jnp.float64)
    cov = result.cov.astype(jnp.float64)
    nees = jax.vmap(lambda e, P: e @ jnp.linalg.solve(P, e))(err, cov)
    status = jnp.bitwise_or.reduce(result.status)
    return {
        "sq_err": jnp.mean(err[settle:, :N_KIN] ** 2, axis=0),
        "param_err": err[-1, N_KIN:],
        "final_std": jnp.sqrt(jnp.diagonal(cov[-1])),
        "nees": jnp.mean(nees),
        "status": status,
    }


def monte_carlo(estimator, model, batch, P0, settle, chunk):
    """:func:`run_metrics` over the runs of ``batch``, ``vmap``ped in chunks of ``chunk`` runs."""
    return jax.tree.map(np.asarray, _monte_carlo(estimator, model, batch, P0, settle, chunk))


@eqx.filter_jit
def _monte_carlo(estimator, model, batch, P0, settle, chunk):
    ys, inputs, mean0, truth = batch
    f = lambda a: run_metrics(estimator, model, a[0], a[1], a[2], P0, a[3], settle)
    return jax.lax.map(f, (ys, inputs, mean0, truth), batch_size=chunk)


def diverged(metrics):
    """Runs that flagged a status bit, produced NaN or whose NEES exceeds ``NEES_DIVERGED``."""
    nees = metrics["nees"]
    return (metrics["status"] != Status.OK) | ~np.isfinite(nees) | (nees > NEES_DIVERGED)


def summarise(metrics, common):
    """The per-filter F block of summary.json; RMSE, parameter error and NEES over ``common``, the
    runs no filter lost (so the filters are compared on the same flights)."""
    bad = diverged(metrics)
    lost_pd = (metrics["status"] & Status.NOT_POSITIVE_DEFINITE) != 0
    use = common if np.any(common) else ~bad
    rms = lambda a: (
        np.sqrt(np.mean(a[use], axis=0)) if np.any(use) else np.full(a.shape[1:], np.nan)
    )
    sq = rms(metrics["sq_err"])
    perr = rms(metrics["param_err"] ** 2) * PARAMETER_UNITS
    return {
        "rmse": {s: float(sq[i] * STATE_UNITS[s]) for i, s in enumerate(KINEMATIC_STATES)},
        "param_error": {p: float(perr[i]) for i, p in enumerate(PARAMETERS)},
        "diverged_runs": int(np.sum(bad)),
        "lost_definiteness_runs": int(np.sum(lost_pd)),
        "runs": int(bad.shape[0]),
        "compared_runs": int(np.sum(use)),
        "nees": float(np.mean(metrics["nees"][use])) if np.any(use) else float("nan"),
        "nees_expected": N_STATE,
    }


def observability(metrics):
    """Median ratio posterior std / prior std of every parameter at the end of the maneuver."""
    ratio = np.median(metrics["final_std"][:, N_KIN:], axis=0) / sim.PARAMETER_STD
    return {p: float(ratio[i]) for i, p in enumerate(PARAMETERS)}


# ---------------------------------------------------------------------------------------------
# figures


def plot_states_and_fits(path, t, truth, estimate, measured, computed, title):
    """Fig 1-2 of the paper: estimated vs true states, and computed vs measured responses."""
    fig, axes = plt.subplots(2, 6, figsize=(18, 6), sharex=True)
    names = ["u", "v", "w", "phi", "theta", "h"]
    idx = [0, 1, 2, 3, 4, 6]
    for ax, name, i in zip(axes[0], names, idx, strict=True):
        scale = STATE_UNITS[name]
        if truth is not None:
            ax.plot(t, truth[:, i] * scale, "k-", lw=1.5, label="true")
        ax.plot(t, estimate[:, i] * scale, "r--", lw=1, label="estimated")
        ax.set_title(name + (" (deg)" if scale != 1 else ""))
    for j, (ax, name) in enumerate(zip(axes[1], OUTPUTS, strict=True)):
        ax.plot(t, measured[:, j] * OUTPUT_UNITS[j], "k.", ms=2, label="measured")
        ax.plot(t, computed[:, j] * OUTPUT_UNITS[j], "r-", lw=1, label="computed")
        ax.set_title(f"{name}_m" + (" (deg)" if OUTPUT_UNITS[j] != 1 else ""))
        ax.set_xlabel("t (s)")
    axes[0, 0].legend(fontsize=8)
    axes[1, 0].legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def single_run_figure(path, truth_flight, rate_hz, key, title):
    batch = simulated_batch(truth_flight, 1, key, jnp.float64)
    ys, inputs, mean0, truth = (a[0] for a in batch)
    model = model_for(rate_hz, jnp.float64)
    result = filter_once(SVDEKF(), model, ys, inputs, Gaussian(mean0, prior_cov(jnp.float64)))
    computed = jax.vmap(model.h)(result.mean, inputs)
    plot_states_and_fits(path, np.asarray(truth_flight.t), np.asarray(truth), np.asarray(result.mean),
                         np.asarray(ys), np.asarray(computed), title)  # fmt: skip


# ---------------------------------------------------------------------------------------------
# real data


def real_prior(data: flight_data.FlightData):
    """Initial state from the first measured sample (no lever arms: the data are at the CG), the
    parameters' prior mean 0, prior std three times the simulator's (the real sensors are unknown)."""
    y0 = data.outputs[0]
    vel = np.asarray(flight.body_velocity(y0[0], y0[2], y0[1]))
    h0 = y0[5] if np.isfinite(y0[5]) else 0.0
    mean = np.concatenate([vel, [y0[4], y0[3], 0.0, h0], np.zeros(len(PARAMETERS))])
    std = np.concatenate([KINEMATIC_STD, 3.0 * sim.PARAMETER_STD])
    return Gaussian(jnp.asarray(mean), jnp.asarray(np.diag(std**2)))


#: output noise assumed for real data: the simulator's, with 1 m for the pressure altitude
REAL_OUTPUT_STD = np.concatenate([sim.OUTPUT_STD[:5], [1.0]])


def reconstruct(data, input_std, output_std, estimator=None):
    """Filter a real record; returns the result, the model and the interval inputs."""
    model = flight.flight_model(data.dt, jnp.asarray(input_std), jnp.asarray(output_std))
    inputs = flight.interval_inputs(jnp.asarray(data.inputs))
    est = SVDEKF() if estimator is None else estimator
    prior = real_prior(data)
    result = filter_once(est, model, jnp.asarray(data.outputs), inputs, prior)
    return result, model, inputs


def residual_rms(data, result, model, inputs, settle):
    """RMS of the innovations y_k - h(x(k|k-1)) (one-step prediction errors) and of the filtered
    residuals y_k - h(x(k|k)), per output channel in output units, after ``settle`` samples."""
    pred = np.asarray(jax.vmap(model.h)(result.predicted_mean, inputs))
    post = np.asarray(jax.vmap(model.h)(result.mean, inputs))
    rms = lambda r: np.sqrt(np.nanmean((r[settle:]) ** 2, axis=0)) * OUTPUT_UNITS
    innov, filt = rms(data.outputs - pred), rms(data.outputs - post)
    as_dict = lambda v: {
        o: (float(v[i]) if np.isfinite(v[i]) else None) for i, o in enumerate(OUTPUTS)
    }
    return as_dict(innov), as_dict(filt), post


def parameter_table(result):
    mean = np.asarray(result.mean[-1, N_KIN:]) * PARAMETER_UNITS
    std = np.sqrt(np.diag(np.asarray(result.cov[-1]))[N_KIN:]) * PARAMETER_UNITS
    return {p: {"value": float(mean[i]), "std": float(std[i])} for i, p in enumerate(PARAMETERS)}


def bias_agreement(parameters):
    """For every parameter and pair of maneuvers: |difference| / sqrt(std_a^2 + std_b^2)."""
    names = list(parameters)
    out = {}
    for p in PARAMETERS:
        pairs = {}
        for i, a in enumerate(names):
            for b in names[i + 1 :]:
                pa, pb = parameters[a][p], parameters[b][p]
                pairs[f"{a}-{b}"] = abs(pa["value"] - pb["value"]) / np.hypot(pa["std"], pb["std"])
        out[p] = pairs
    return out


# ---------------------------------------------------------------------------------------------
# maximum-likelihood tuning of Q and R


def tune_noise(data_ys, inputs, prior, dt, input_std, output_std, lever_arms, steps, lr=0.05):
    """Maximise the SVD-EKF log-likelihood over log std of the 6 input noises and 6 output noises
    (Adam on the log-likelihood per sample). Returns (input_std, output_std, loglik history)."""
    import optax

    def loglik(log_std):
        model = flight.flight_model(dt, jnp.exp(log_std[:6]), jnp.exp(log_std[6:]), lever_arms)
        return run_filter(SVDEKF(), model, data_ys, inputs, prior).loglik

    n_obs = float(np.sum(np.isfinite(np.asarray(data_ys))))
    value_and_grad = jax.jit(jax.value_and_grad(lambda z: -loglik(z) / n_obs))
    params = jnp.log(jnp.concatenate([jnp.asarray(input_std), jnp.asarray(output_std)]))
    opt = optax.adam(lr)
    state = opt.init(params)
    history = []
    for i in range(steps + 1):
        value, grad = value_and_grad(params)
        history.append(-float(value) * n_obs)
        if i < steps:
            updates, state = opt.update(grad, state)
            params = optax.apply_updates(params, updates)
    std = np.exp(np.asarray(params))
    return std[:6], std[6:], history


def noise_dict(input_std, output_std):
    units_in = [1, 1, 1, 1 / DEG, 1 / DEG, 1 / DEG]
    d = {f"{n}": float(s * u) for n, s, u in zip(flight.INPUTS, input_std, units_in, strict=True)}
    d.update(
        {f"{n}": float(s * u) for n, s, u in zip(OUTPUTS, output_std, OUTPUT_UNITS, strict=True)}
    )
    return d


# ---------------------------------------------------------------------------------------------


def conditions_for(quick: bool):
    maneuvers = ("elevator",) if quick else sim.MANEUVERS
    rates = (10,) if quick else (10, 32)
    dtypes = ("float64",) if quick else ("float64", "float32")
    return [(m, r, d) for r in rates for d in dtypes for m in maneuvers]


def run(out: Path, *, runs: int | None, seed: int, quick: bool, options: dict) -> dict:  # noqa: C901
    out = Path(out) / NAME
    out.mkdir(parents=True, exist_ok=True)
    runs = runs or (3 if quick else 100)
    duration = 6.0 if quick else sim.DURATION
    chunk = min(runs, 25)
    key = jax.random.key(seed)
    conditions = conditions_for(quick)
    data_dir = flight_data.find_data_dir(options.get("data") if options else None)
    tune_steps = 0 if quick else 40
    summary: dict = {"conditions": {}, "observability": {}, "settings": {
        "runs": runs, "duration_s": duration, "seed": seed, "nees_diverged": NEES_DIVERGED,
        "observable_ratio": OBSERVABLE_RATIO, "units": "m/s, deg, deg/s, m/s^2, m",
    }}  # fmt: skip
    tables = []
    figures = () if quick else ((10, 1), (32, 2))  # --quick: only the real-data figure
    total = len(conditions) * len(FILTERS) + len(figures) + ((1 if quick else 5) if data_dir else 0)
    with Progress(NAME, total) as progress:
        truths = {}
        for maneuver, rate, dtype_name in conditions:
            dtype = jnp.dtype(dtype_name)
            if (maneuver, rate) not in truths:
                truths[maneuver, rate] = sim.true_flight(maneuver, rate, duration)
            truth = truths[maneuver, rate]
            cond_key = jax.random.fold_in(key, 100 * sim.MANEUVERS.index(maneuver) + rate)
            batch = simulated_batch(truth, runs, cond_key, dtype)  # same flights in both dtypes
            model, P0 = model_for(rate, dtype), prior_cov(dtype)
            settle = int(SETTLE_S * rate)
            metrics = {}
            for fname, est in FILTERS.items():
                metrics[fname] = monte_carlo(est, model, batch, P0, settle, chunk)
                progress.advance(f"{maneuver} {rate} Hz {dtype_name} {fname}")
            common = ~np.any([diverged(m) for m in metrics.values()], axis=0)
            name = f"{maneuver}_{rate}hz_{dtype_name}"
            entry = {"maneuver": maneuver, "rate_hz": rate, "dtype": dtype_name}
            entry.update({f: summarise(m, common) for f, m in metrics.items()})
            summary["conditions"][name] = entry
            if dtype_name == "float64" and rate == max(r for _, r, _ in conditions):
                summary["observability"][maneuver] = {
                    "std_ratio": observability(metrics["svd_ekf"]),
                    "observable": [
                        p
                        for p, r in observability(metrics["svd_ekf"]).items()
                        if r < OBSERVABLE_RATIO
                    ],  # fmt: skip
                }
            for f in FILTERS:
                F = entry[f]
                tables.append([name, f, F["diverged_runs"], F["runs"], F["nees"],
                               *[F["rmse"][s] for s in KINEMATIC_STATES]])  # fmt: skip
        for rate, fig in figures:
            maneuver = "elevator" if quick else "aileron"
            path = out / f"fig{fig}_states_{rate}hz.png"
            if (maneuver, rate) not in truths:
                truths[maneuver, rate] = sim.true_flight(maneuver, rate, duration)
            single_run_figure(path, truths[maneuver, rate], rate, jax.random.fold_in(key, fig),
                              f"SVD-EKF, simulated {maneuver} maneuver, {rate} Hz")  # fmt: skip
            progress.advance(f"figure {fig}")
        # compiling the likelihood gradient is the slowest piece: --quick leaves tuning out
        summary["tuning"] = (
            {} if quick else {"simulated": tune_simulated(key, duration, tune_steps)}
        )
        if data_dir is not None:
            summary["real_data"] = real_data_part(out, data_dir, quick, tune_steps, progress)
            summary["tuning"]["real"] = summary["real_data"].pop("tuning")
        else:
            summary["real_data_note"] = f"no flight data found. {flight_data.DOWNLOAD_HINT}"
    write_tables(out, summary, tables)
    write_json(out / "summary.json", summary)
    return summary


def tune_simulated(key, duration, steps):
    """ML tuning on one simulated elevator flight whose true noise is twice the nominal level,
    starting from the nominal level: the tuned values should move towards the truth."""
    rate = 32
    truth = sim.true_flight("elevator", rate, duration)
    ys, inputs, mean0, _ = (a[0] for a in simulated_batch(truth, 1, jax.random.fold_in(key, 7),
                                                          jnp.float64, noise_scale=2.0))  # fmt: skip
    prior = Gaussian(mean0, prior_cov(jnp.float64))
    in_std, out_std, hist = tune_noise(ys, inputs, prior, 1.0 / rate, sim.INPUT_STD,
                                       sim.OUTPUT_STD, sim.LEVER_ARMS, steps)  # fmt: skip
    return {
        "true_noise": noise_dict(2 * sim.INPUT_STD, 2 * sim.OUTPUT_STD),
        "initial_noise": noise_dict(sim.INPUT_STD, sim.OUTPUT_STD),
        "tuned_noise": noise_dict(in_std, out_std),
        "loglik_initial": hist[0],
        "loglik_tuned": hist[-1],
        "steps": steps,
    }


def real_data_part(out, data_dir, quick, tune_steps, progress):
    maneuvers = ("elevator",) if quick else tuple(flight_data.ATTAS_FILES)
    records = {m: flight_data.load_attas(m, data_dir) for m in maneuvers}
    if quick:  # first 5 s
        d = records["elevator"]
        n = int(5 * d.rate_hz)
        records["elevator"] = flight_data.FlightData(d.name, d.t[:n], d.inputs[:n], d.outputs[:n])
    elev = records["elevator"]
    settle = int(SETTLE_S * elev.rate_hz)
    report: dict = {"files": {m: flight_data.ATTAS_FILES[m] for m in maneuvers}}
    in_std, out_std = sim.INPUT_STD, REAL_OUTPUT_STD
    report["tuning"] = {}
    if tune_steps:  # ML tuning of Q and R on the elevator maneuver, used for every maneuver
        in_std, out_std, hist = tune_noise(
            jnp.asarray(elev.outputs), flight.interval_inputs(jnp.asarray(elev.inputs)),
            real_prior(elev), elev.dt, sim.INPUT_STD, REAL_OUTPUT_STD, flight.LeverArms(),
            tune_steps,
        )  # fmt: skip
        report["tuning"] = {
            "initial_noise": noise_dict(sim.INPUT_STD, REAL_OUTPUT_STD),
            "tuned_noise": noise_dict(in_std, out_std),
            "loglik_initial": hist[0], "loglik_tuned": hist[-1], "steps": tune_steps,
            "data": "ATTAS elevator",
        }  # fmt: skip
        progress.advance("real-data tuning")
    params, residuals, residuals_untuned = {}, {}, {}
    for m, d in records.items():
        result, model, inputs = reconstruct(d, in_std, out_std)
        innov, filt, computed = residual_rms(d, result, model, inputs, settle)
        params[m] = parameter_table(result)
        residuals[m] = {"innovation_rms": innov, "filtered_rms": filt,
                        "diverged": bool(np.any(np.asarray(result.status) != 0))}  # fmt: skip
        if tune_steps:
            r0, model0, inputs0 = reconstruct(d, sim.INPUT_STD, REAL_OUTPUT_STD)
            residuals_untuned[m] = residual_rms(d, r0, model0, inputs0, settle)[0]
        plot_states_and_fits(out / f"fig_attas_{m}.png", d.t, None, np.asarray(result.mean),
                             d.outputs, computed, f"SVD-EKF on ATTAS {m} maneuver (25 Hz)")  # fmt: skip
        progress.advance(f"ATTAS {m}")
    report["parameters"] = params["elevator"]
    report["parameters_by_maneuver"] = params
    report["residual_rms"] = residuals["elevator"]["innovation_rms"]
    report["residuals_by_maneuver"] = residuals
    report["innovation_rms_untuned"] = residuals_untuned
    report["hfb320_noise_x3"] = {k: 3 * v for k, v in HFB320_NOISE.items()}
    report["bias_agreement_sigma"] = bias_agreement(params) if len(params) > 1 else {}
    if not quick:
        report["hfb320"] = reconstruct_hfb320(out, data_dir)
        progress.advance("HFB-320")
    return report


def reconstruct_hfb320(out, data_dir):
    """The HFB-320 record (10 Hz, no altitude channel) with the nominal noise levels."""
    hfb = flight_data.load_hfb320(data_dir)
    hfb_std = np.concatenate([sim.OUTPUT_STD[:5], [1.0]])
    result, model, inputs = reconstruct(hfb, sim.INPUT_STD, hfb_std)
    innov, filt, computed = residual_rms(hfb, result, model, inputs, int(SETTLE_S * hfb.rate_hz))
    plot_states_and_fits(out / "fig_hfb320.png", hfb.t, None, np.asarray(result.mean), hfb.outputs,
                         computed, "SVD-EKF on HFB-320 elevator record (10 Hz)")  # fmt: skip
    return {"parameters": parameter_table(result), "innovation_rms": innov, "filtered_rms": filt}


def write_tables(out, summary, rows):
    text = "# SVD-EKF flight estimation: simulated Monte Carlo\n\n"
    text += "State RMSE after the first second (m/s, deg, m), over the runs no filter lost.\n\n"
    text += markdown_table(["condition", "filter", "diverged", "runs", "NEES (23)",
                            *KINEMATIC_STATES], rows)  # fmt: skip
    text += "\n## Parameter observability (posterior std / prior std, SVD-EKF)\n\n"
    obs = summary["observability"]
    text += markdown_table(["parameter", *obs], [[p, *[obs[m]["std_ratio"][p] for m in obs]]
                                                 for p in PARAMETERS], floatfmt=".2f")  # fmt: skip
    if "real_data" in summary:
        real = summary["real_data"]
        text += "\n## ATTAS: estimated parameters (value ± std; m/s^2, deg/s, m/s, deg, m)\n\n"
        by = real["parameters_by_maneuver"]
        text += markdown_table(["parameter", *by], [
            [p, *[f"{by[m][p]['value']:.4g} ± {by[m][p]['std']:.2g}" for m in by]]
            for p in PARAMETERS])  # fmt: skip
        text += "\n## ATTAS: innovation RMS with tuned Q, R (m/s, deg, m)\n\n"
        res = real["residuals_by_maneuver"]
        text += markdown_table(["maneuver", *OUTPUTS], [[m, *[res[m]["innovation_rms"][o]
                                                              for o in OUTPUTS]] for m in res])  # fmt: skip
    (out / "tables.md").write_text(text)
