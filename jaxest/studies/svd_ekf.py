"""Study ``svd-ekf``: flight state and sensor-parameter estimation with the SVD-based EKF
(Zhang, Dai & Zhang), on simulated maneuvers and on real ATTAS / HFB-320 flight data.

1. Monte Carlo on the simulator (:mod:`jaxest.systems.flight_sim`): for every maneuver (elevator
   3-2-1-1, aileron bank-to-bank, rudder doublet), sample rate (10 and 32 Hz) and dtype (float64,
   float32), ``runs`` flights with their own true sensor parameters (drawn from the prior), sensor
   noise and initial estimate (a GPS-aided INS's uncertainty, :data:`INS_KINEMATIC_STD`), filtered
   by the paper's EKF, its SVD-EKF and the improved SVD filter (Kulikova & Tsyganova), all
   ``vmap``ped. Reported: state RMSE, parameter error, diverged runs, NEES (also of the EKF from
   the air-data start, :func:`air_data_start`), and which parameters each maneuver makes
   observable.
2. Real data (:mod:`jaxest.systems.flight_data`): the same reconstruction of the ATTAS elevator,
   aileron and rudder maneuvers and of the HFB-320 record, with biases, scale factors and residuals,
   after estimating the flow vanes' delay behind the inertial sensors by maximum likelihood (a
   likelihood profile over whole-sample delays, :func:`estimate_delays`).
3. Maximum-likelihood tuning of the noise levels by L-BFGS on the SVD filter's log-likelihood
   (:func:`tune_noise`): input (Q) and measurement (R) noise on simulated data, Q only on the real
   data, where a free R collapses towards zero for alpha and beta (see the notebook).
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxest._priors import Gaussian
from jaxest._run import run as run_filter
from jaxest._status import Status
from jaxest.filters import EKF, SVDEKF, FilterResult, ImprovedSVDKF
from jaxest.models import simulate
from jaxest.plot import plt, save
from jaxest.progress import Progress
from jaxest.report import markdown_table, write_json
from jaxest.setmembership.fdi import chi_square_threshold
from jaxest.smoothers import SmootherResult, rts_smooth
from jaxest.systems import flight, flight_data, flight_sim as sim
from jaxest.systems.flight import DEG, KINEMATIC_STATES, N_KIN, N_STATE, OUTPUTS, PARAMETERS
from jaxest.tune import FIXED_STEPS_LBFGS, fit

NAME = "svd-ekf"
DESCRIPTION = "SVD-EKF flight state & sensor-parameter estimation (simulated + ATTAS/HFB-320 data)"

FILTERS = {"ekf": EKF(), "svd_ekf": SVDEKF(), "svd_improved": ImprovedSVDKF()}
#: prior std of the kinematic states u, v, w (m/s), phi, theta, psi (rad), h (m) from air data and
#: attitude sensors alone, as on the ATTAS records: with no independent velocity reference, v at
#: the start is known from the beta vane, whose 0.5 deg bias prior is about 1 m/s at 120 m/s. The
#: real data's start, and the simulated conditions' in :func:`air_data_start`.
AIR_DATA_KINEMATIC_STD = np.array([1.0, 1.0, 1.0, 0.5 * DEG, 0.5 * DEG, 2.0 * DEG, 10.0])
#: the simulated conditions' start: a tenth of :data:`AIR_DATA_KINEMATIC_STD` (u, v, w 0.1 m/s;
#: phi, theta 0.05 deg; psi 0.2 deg; h 1 m), what a GPS-aided INS gives. From the air-data start
#: no Gaussian filter is consistent on this model (issue 16;
#: docs/papers/svd_ekf.md#the-initial-velocity-error-decides-it).
INS_KINEMATIC_STD = 0.1 * AIR_DATA_KINEMATIC_STD
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
#: report units of each parameter by name (b_alpha_trim: see trim_reparametrised)
UNITS = dict(zip(PARAMETERS, PARAMETER_UNITS, strict=True)) | {"b_alpha_trim": 1 / DEG}
OUTPUT_UNITS = np.array([1, 1 / DEG, 1 / DEG, 1 / DEG, 1 / DEG, 1])
#: HFB-320 noise levels of ../shared/data/README.md in output units (V m/s, angles deg)
HFB320_NOISE = {"V": 0.13, "alpha": 0.057, "theta": 0.025}
#: what the between-record comparison of the ATTAS estimates shows (numbers in summary.json and
#: docs/papers/svd_ekf.md)
AGREEMENT_NOTE = (
    "Estimates are RTS-smoothed with b_V, b_h, b_phi and b_theta pinned at 0 and the alpha offset "
    "taken at alpha_trim; standard errors from the pass whose R carries each channel's residual "
    "colour factor. Pairs are compared where both records identify the parameter (posterior/prior "
    "std < 0.5). Where they disagree beyond 3 s.e.: the sideslip vane's bias and scale factor "
    "between the aileron and the rudder record, and b_alpha_trim by about 0.1 deg between the "
    "elevator and aileron records. The cause (benchmarks/flight_record_agreement.py): the model "
    "takes the turbulence up as accelerometer noise, in the kinematic velocities, which the "
    "pressure altitude integrates, and the altitude then sets b_beta (through v sin(phi) in h'); "
    "with the air mass's motion as three random-walk wind states instead, all three agree within "
    "2.2 s.e. (neither rate terms at the vane nor a bank-angle or roll-gyro scale factor "
    "reconcile b_beta: benchmarks/flight_sensor_terms.py). The scale factor "
    "lam_alpha exceeds 0.15 only on the lateral records, where alpha stays within 0.2 deg (std) "
    "of trim and its posterior std is half its prior's; the elevator record and the joint fit "
    "give |lam_alpha| < 0.07. In the aileron record the phi innovation follows the bank angle: a "
    "roll-channel scale factor of about -2.8 % that the records support but eq 31 does not "
    "have (same script); it pulls b_ay and b_r. The records start from air data alone (u, v, w "
    "uncertain by 1 m/s), and from that start the EKF's NEES exceeds 23 even on flights "
    "simulated from its own model (air_data_start; from the simulated conditions' INS start it "
    "does not), so formal standard errors are somewhat small before any correction for coloured "
    "residuals."
)


def prior_cov(dtype, kinematic_std=AIR_DATA_KINEMATIC_STD):
    """The filters' prior covariance: diag(``kinematic_std``, the parameters' prior std)^2."""
    std = np.concatenate([kinematic_std, sim.PARAMETER_STD])
    return jnp.asarray(np.diag(std**2), dtype)


def simulated_batch(
    truth: sim.TrueFlight, runs: int, key, dtype, noise_scale: float = 1.0,
    parameter_std=sim.PARAMETER_STD, kinematic_std=AIR_DATA_KINEMATIC_STD,
):  # fmt: skip
    """``runs`` corrupted copies of ``truth``: (ys, interval inputs, priors, true states), each
    with a leading run axis; all in ``dtype``. The sensor parameters are drawn with
    ``parameter_std`` (a zero holds one at 0), the initial guesses' kinematic errors with
    ``kinematic_std`` (to match :func:`prior_cov`)."""
    keys = jax.random.split(key, runs)
    stds = (jnp.asarray(a, truth.states.dtype) for a in (parameter_std, kinematic_std))
    return tuple(a.astype(dtype) for a in _simulated_batch(truth, keys, noise_scale, *stds))


@jax.jit
def _simulated_batch(truth, keys, noise_scale, parameter_std, kinematic_std):
    """:func:`simulated_batch` in the truth's dtype, compiled once per flight length, rate and
    run count (a closure jitted per call recompiled every time: about 3 s a call at 32 Hz)."""

    def one(k):
        k_par, k_noise, k_init = jax.random.split(k, 3)
        params = sim.draw_parameters(k_par, truth.states.dtype, parameter_std)
        record = sim.corrupt(
            truth, params, k_noise, sim.INPUT_STD * noise_scale, sim.OUTPUT_STD * noise_scale
        )
        mean0 = sim.initial_guess(record.true_states[0], k_init, kinematic_std)
        inputs = flight.interval_inputs(record.measured_inputs)
        return record.measurements, inputs, mean0, record.true_states

    return jax.vmap(one)(keys)


def model_for(rate_hz, dtype, noise_scale=1.0, lever_arms=sim.LEVER_ARMS, output_std=None):
    output_std = sim.OUTPUT_STD if output_std is None else output_std
    return flight.flight_model(
        1.0 / rate_hz,
        jnp.asarray(sim.INPUT_STD * noise_scale, dtype),
        jnp.asarray(output_std * noise_scale, dtype),
        lever_arms,
    )


#: NEES groups: all 23 states, the 7 kinematic states, the 16 sensor parameters (their dimensions)
def nees_groups(n: int) -> dict[str, int]:
    """Degrees of freedom of the NEES groups of an n-entry state: the kinematic states followed
    by the parameters (all 23, or fewer with some pinned)."""
    return {"all": n, "kinematic": N_KIN, "parameters": n - N_KIN}


NEES_GROUPS = nees_groups(N_STATE)


def nees_by_group(err, cov):
    """NEES of one step for the groups of :data:`NEES_GROUPS`, each with its marginal covariance:
    one batched Cholesky factorisation of P and of P with the parameters ordered first (the
    leading block of a Cholesky factor is the factor of the leading block of P). The state is the
    kinematic states followed by the parameters: all 23, or fewer with some pinned."""
    n = err.shape[-1]
    order = np.r_[N_KIN:n, 0:N_KIN]
    covs = jnp.stack([cov, cov[order][:, order]])
    errs = jnp.stack([err, err[order]])
    whitened = jax.scipy.linalg.solve_triangular(
        jnp.linalg.cholesky(covs), errs[..., None], lower=True
    )[..., 0]
    squares = whitened**2
    return jnp.stack([squares[0].sum(), squares[0, :N_KIN].sum(), squares[1, : n - N_KIN].sum()])


def run_metrics(estimator, model, ys, inputs, mean0, P0, truth, settle: int):
    """Per-run summary of one filter run: squared state errors averaged over time after ``settle``
    steps, final parameter errors and standard deviations, NEES per group and NIS per output
    channel over time, status."""
    result = run_filter(estimator, model, ys, inputs=inputs, prior=Gaussian(mean0, P0))
    err = (result.mean - truth).astype(jnp.float64)
    cov = result.cov.astype(jnp.float64)
    innovation_var = jnp.diagonal(result.innovation_cov, axis1=-2, axis2=-1)
    nis = (result.innovation**2 / innovation_var).astype(jnp.float64)
    status = jnp.bitwise_or.reduce(result.status)
    return {
        "sq_err": jnp.mean(err[settle:, :N_KIN] ** 2, axis=0),
        "param_err": err[-1, N_KIN:],
        "final_std": jnp.sqrt(jnp.diagonal(cov[-1])),
        "nees_t": jax.vmap(nees_by_group)(err, cov),
        "nis_t": nis,
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
    nees = np.mean(metrics["nees_t"][..., 0], axis=-1)
    return (metrics["status"] != Status.OK) | ~np.isfinite(nees) | (nees > NEES_DIVERGED)


@functools.lru_cache
def nees_band(runs: int, dof: int, coverage: float = 0.95) -> tuple[float, float]:
    """The two-sided ``coverage`` band of the NEES averaged over ``runs`` consistent runs at one
    time: chi-square(runs dof) / runs (Bar-Shalom, Li & Kirubarajan 2001, sec 5.4.2). With
    ``dof`` = 1 it is the band of one channel's NIS, and with ``runs`` the number of runs times
    the number of steps, that of its average over time (innovations are white where the filter
    is consistent)."""
    tail = (1 - coverage) / 2
    low = chi_square_threshold(runs * dof, 1 - tail) / runs
    return low, chi_square_threshold(runs * dof, tail) / runs


def nees_summary(nees_t, groups=NEES_GROUPS) -> dict:
    """Time-averaged NEES per group of ``nees_t`` (runs, T, groups), with the 95 % band of the
    run average at one time and the fraction of time steps inside it."""
    runs = nees_t.shape[0]
    out = {}
    for g, (group, dof) in enumerate(groups.items()):
        average = np.mean(nees_t[..., g], axis=0)  # the run average at each time
        low, high = nees_band(runs, dof)
        out[group] = {
            "nees": float(np.mean(average)),
            "expected": dof,
            "band_95": [low, high],
            "fraction_in_band": float(np.mean((average >= low) & (average <= high))),
        }
    return out


def consistency(metrics, use):
    """:func:`nees_summary` and, per output channel, the NIS averaged over time and the runs
    ``use``, the 95 % band of that average, and the fraction of time steps whose run average lies
    in the band of one step."""
    out = nees_summary(metrics["nees_t"][use])
    nis_t = metrics["nis_t"][use]
    runs, steps = nis_t.shape[:2]
    average = np.mean(nis_t, axis=0)  # (T, channels): the run average at each time
    low, high = nees_band(runs, 1)
    in_band = np.mean((average >= low) & (average <= high), axis=0)
    out["nis"] = {o: float(np.mean(average[:, i])) for i, o in enumerate(OUTPUTS)}
    out["nis_band_95"] = list(nees_band(runs * steps, 1))
    out["nis_fraction_in_band"] = {o: float(in_band[i]) for i, o in enumerate(OUTPUTS)}
    return out


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
        **(consistency(metrics, use) if np.any(use) else {}),
    }


def table_row(condition: str, filter_name: str, F: dict) -> list:
    """One row of the Monte Carlo table from a :func:`summarise` block (NaN where no run was
    compared)."""
    nees = [F[g]["nees"] if g in F else float("nan") for g in NEES_GROUPS]
    nis = np.mean(list(F["nis"].values())) if "nis" in F else float("nan")
    rmse = [F["rmse"][s] for s in KINEMATIC_STATES]
    return [condition, filter_name, F["diverged_runs"], F["runs"], *nees, nis, *rmse]


def own_model_flights(model, batch, key):
    """``batch`` with its measurements and true states replaced by flights simulated from the
    filter's own discrete model: x_{k+1} = f(x_k, u_k) + G w_k, y_k = h(x_k, u_k) + v_k with its
    G, Q and R, the study's measured inputs and true initial states (:func:`jaxest.simulate`), so
    that neither the simulator's continuous inputs nor how its input noise enters two intervals
    differs from what the filter assumes."""
    ys, inputs, mean0, truth = batch
    keys = jax.random.split(key, ys.shape[0])
    own = eqx.filter_jit(jax.vmap(lambda x0, u, k: simulate(model, x0, ys.shape[1], k, inputs=u)))
    sims = own(truth[:, 0], inputs, keys)
    return sims.y, inputs, mean0, sims.states


def own_model_simulation(model, batch, P0, settle, chunk, key) -> dict:
    """The EKF on :func:`own_model_flights`. The NEES excess that remains is the EKF's own
    approximation of the nonlinear model (``benchmarks/flight_nees.py`` locates it)."""
    metrics = monte_carlo(EKF(), model, own_model_flights(model, batch, key), P0, settle, chunk)
    return summarise(metrics, ~diverged(metrics))


def kinematic_std_with_velocity(velocity_std: float):
    """:data:`AIR_DATA_KINEMATIC_STD` with the velocities u, v, w at ``velocity_std`` (m/s)."""
    velocities = np.isin(np.array(KINEMATIC_STATES), ("u", "v", "w"))
    return np.where(velocities, velocity_std, AIR_DATA_KINEMATIC_STD)


def air_data_start(truth, runs, key, model, settle, chunk):
    """The EKF on the flights of ``key`` (the study's simulator, the same draws) started from
    :data:`AIR_DATA_KINEMATIC_STD`, ten times the conditions' initial error and prior std. Its NEES
    excess is h linearised about a velocity estimate that far off, which the maneuvers hardly
    correct (docs/papers/svd_ekf.md). Returns the :func:`summarise` block and the NEES and NIS
    over time of the runs it kept, (runs, T, groups) and (runs, T, channels)."""
    batch = simulated_batch(truth, runs, key, jnp.float64)
    metrics = monte_carlo(EKF(), model, batch, prior_cov(jnp.float64), settle, chunk)
    use = ~diverged(metrics)
    return summarise(metrics, use), {k: metrics[k][use] for k in ("nees_t", "nis_t")}


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
    save(fig, path, dpi=90)


def consistency_figure(path, series_by_rate, metric, panels, title):
    """``metric`` ("nees_t" or "nis_t") over time, averaged over the runs, with the 95 % band of
    that average: ``series_by_rate[rate][label][metric]`` is one series' (runs, T, panels), and
    ``panels`` the (name, degrees of freedom) of its last axis; the band is the first series'."""
    fig, axes = plt.subplots(len(series_by_rate), len(panels),
                             figsize=(4.7 * len(panels), 3.2 * len(series_by_rate)),
                             squeeze=False)  # fmt: skip
    for row, (rate, series) in zip(axes, series_by_rate.items(), strict=True):
        runs, steps = next(iter(series.values()))[metric].shape[:2]
        t = np.arange(steps) / rate
        for g, (ax, (name, dof)) in enumerate(zip(row, panels, strict=True)):
            low, high = nees_band(runs, dof)
            ax.fill_between(t, low, high, color="0.85", label=f"95 % band, {runs} runs")
            ax.axhline(dof, color="k", lw=0.8)
            for (label, metrics), colour in zip(series.items(), ("r", "b"), strict=False):
                ax.plot(t, np.mean(metrics[metric][..., g], axis=0), colour, lw=1, label=label)
            ax.set_title(f"{name} ({dof}), {rate} Hz")
            ax.set_xlabel("t (s)")
        row[0].legend(fontsize=8)
    fig.suptitle(title)
    save(fig, path, dpi=90)


def single_run_figure(path, truth_flight, rate_hz, key, title):
    batch = simulated_batch(truth_flight, 1, key, jnp.float64, kinematic_std=INS_KINEMATIC_STD)
    ys, inputs, mean0, truth = (a[0] for a in batch)
    model = model_for(rate_hz, jnp.float64)
    prior = Gaussian(mean0, prior_cov(jnp.float64, INS_KINEMATIC_STD))
    result = run_filter(SVDEKF(), model, ys, inputs=inputs, prior=prior)
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
    std = np.concatenate([AIR_DATA_KINEMATIC_STD, 3.0 * sim.PARAMETER_STD])
    return Gaussian(jnp.asarray(mean), jnp.asarray(np.diag(std**2)))


#: output noise assumed for real data: the simulator's, with 1 m for the pressure altitude
REAL_OUTPUT_STD = np.concatenate([sim.OUTPUT_STD[:5], [1.0]])


def reconstruct(data, input_std, output_std, estimator=None):
    """Filter a real record; returns the result, the model and the interval inputs."""
    model = flight.flight_model(data.dt, jnp.asarray(input_std), jnp.asarray(output_std))
    inputs = flight.interval_inputs(jnp.asarray(data.inputs))
    est = SVDEKF() if estimator is None else estimator
    prior = real_prior(data)
    result = run_filter(est, model, jnp.asarray(data.outputs), inputs=inputs, prior=prior)
    return result, model, inputs


#: output channels whose sensor delay is estimated on real data (the flow vanes), and the largest
#: delay tried (s). Candidates are whole sample intervals: a delay between samples would be read by
#: linear interpolation, which averages the noise of two samples and so biases the likelihood
#: towards half-sample delays (seen on simulated data: a 2-sample lag came out as 1.5)
DELAYED_OUTPUTS = ("beta", "alpha")
MAX_DELAY_S = 0.2
#: coordinate-ascent sweeps over the delayed channels
DELAY_SWEEPS = 2


def delay_grid(dt):
    return dt * np.arange(int(MAX_DELAY_S / dt + 1e-9) + 1)


def max_delays():
    return tuple(MAX_DELAY_S if o in DELAYED_OUTPUTS else 0.0 for o in OUTPUTS)


def aligned(data: flight_data.FlightData, delays) -> flight_data.FlightData:
    """``data`` with its outputs advanced by ``delays`` (s, one per output channel)."""
    outputs = flight_data.advance_channels(data.outputs, data.dt, delays, max_delays())
    return flight_data.FlightData(data.name, data.t, data.inputs, np.asarray(outputs))


def real_data_settings(summary: dict):
    """What the study chose on the real records, read back from its ``summary.json``: the six
    output delays (s; :func:`aligned`) and the input noise std tuned on the elevator record (SI
    units, the order of :data:`flight.INPUTS`)."""
    real = summary["real_data"]
    delays = np.zeros(len(OUTPUTS))
    for channel, seconds in real["sensor_delays_s"].items():
        delays[OUTPUTS.index(channel)] = seconds
    tuned = summary["tuning"]["real"]["tuned_noise"]
    input_std = np.array([tuned[n] for n in flight.INPUTS]) / PARAMETER_UNITS[: flight.N_IN]
    return delays, input_std


@eqx.filter_jit
def _delay_profile(model, outputs, inputs, prior, candidates, dt, limits):
    def loglik(delays):
        ys = flight_data.advance_channels(outputs, dt, delays, limits)
        return run_filter(SVDEKF(), model, ys, inputs=inputs, prior=prior).loglik

    return jax.vmap(loglik)(candidates)


def delay_profile(data, channel, delays, input_std, output_std):
    """SVD-EKF log-likelihood of ``data`` for every delay of output ``channel`` in
    ``delay_grid(data.dt)``, the other channels delayed by ``delays``: one ``vmap`` over the grid."""
    model = flight.flight_model(data.dt, jnp.asarray(input_std), jnp.asarray(output_std))
    grid = delay_grid(data.dt)
    candidates = np.tile(np.asarray(delays, float), (len(grid), 1))
    candidates[:, OUTPUTS.index(channel)] = grid
    inputs = flight.interval_inputs(jnp.asarray(data.inputs))
    return np.asarray(_delay_profile(model, jnp.asarray(data.outputs), inputs, real_prior(data),
                                     jnp.asarray(candidates), data.dt, max_delays()))  # fmt: skip


def estimate_delays(records, input_std, output_std):
    """Maximum-likelihood sensor delays of ``DELAYED_OUTPUTS``, common to all ``records`` (they are
    properties of the sensors, not of a maneuver; the records share one sample rate): coordinate
    ascent of the summed log-likelihood over ``delay_grid``. Returns the 6 delays (s) and, per
    channel, the last sweep's profiles and each record's own best delay."""
    intervals = np.array([d.dt for d in records.values()])
    if not np.allclose(intervals, intervals[0], rtol=1e-6):
        raise ValueError(f"records: expected one sample interval, got {intervals}")
    grid = delay_grid(intervals[0])
    delays = np.zeros(len(OUTPUTS))
    profiles, computed = {}, {}  # computed: profiles by (channel, the other channels' delays)
    for _ in range(DELAY_SWEEPS):
        for channel in DELAYED_OUTPUTS:
            others = delays.copy()
            others[OUTPUTS.index(channel)] = 0.0
            if (channel, tuple(others)) not in computed:
                computed[channel, tuple(others)] = {
                    m: delay_profile(d, channel, others, input_std, output_std)
                    for m, d in records.items()
                }
            curves = profiles[channel] = computed[channel, tuple(others)]
            delays[OUTPUTS.index(channel)] = grid[np.argmax(sum(curves.values()))]
    best = {c: {m: float(grid[np.argmax(v)]) for m, v in curves.items()}
            for c, curves in profiles.items()}  # fmt: skip
    return delays, profiles, best


def plot_delay_profiles(path, profiles, delays, grid):
    fig, axes = plt.subplots(1, len(profiles), figsize=(5 * len(profiles), 3.6))
    for ax, (channel, curves) in zip(np.atleast_1d(axes), profiles.items(), strict=True):
        for m, ll in curves.items():
            ax.plot(grid, ll - ll.max(), "o-", ms=3, label=m)
        ax.axvline(delays[OUTPUTS.index(channel)], color="k", ls="--", lw=1, label="estimate")
        ax.set_yscale("symlog", linthresh=10.0)
        ax.set_xlabel(f"{channel} sensor delay (s)")
        ax.set_ylabel("log-likelihood - max")
        ax.legend(fontsize=8)
    fig.suptitle("Flow-vane delays on the ATTAS maneuvers (SVD-EKF likelihood profiles)")
    save(fig, path, dpi=90)


def channel_rms(residuals, settle):
    """RMS per output channel in output units over the samples after ``settle`` that were
    measured; NaN for a channel the record does not have (HFB-320 has no altitude channel),
    without numpy's "Mean of empty slice" warning."""
    squares = residuals[settle:] ** 2
    count = np.sum(np.isfinite(squares), axis=0)
    total = np.nansum(squares, axis=0)
    return np.sqrt(np.where(count > 0, total / np.maximum(count, 1), np.nan)) * OUTPUT_UNITS


def residual_rms(data, result, model, inputs, settle):
    """RMS of the innovations y_k - h(x(k|k-1)) (one-step prediction errors) and of the filtered
    residuals y_k - h(x(k|k)), per output channel in output units, after ``settle`` samples."""
    pred = np.asarray(jax.vmap(model.h)(result.predicted_mean, inputs))
    post = np.asarray(jax.vmap(model.h)(result.mean, inputs))
    innov, filt = channel_rms(data.outputs - pred, settle), channel_rms(data.outputs - post, settle)
    as_dict = lambda v: {
        o: (float(v[i]) if np.isfinite(v[i]) else None) for i, o in enumerate(OUTPUTS)
    }
    return as_dict(innov), as_dict(filt), post


def parameter_table(mean, cov, names):
    """Estimate and standard deviation of every sensor parameter among ``names`` (the entries of
    ``mean`` / ``cov``; kinematic states are left out), in report units."""
    std = np.sqrt(np.diag(np.asarray(cov)))
    return {
        p: {"value": float(mean[i] * UNITS[p]), "std": float(std[i] * UNITS[p])}
        for i, p in enumerate(names)
        if p in UNITS
    }


#: loadings below this are left out of an identifiability combination
LOADING_SHOWN = 0.2


def record_information(prior_cov, smoothed_cov0, names, count: int = 4) -> list[dict]:
    """The combinations of the initial state x_0 (kinematic states and sensor parameters) that a
    record informs least. For a linear(ised) Gaussian model the RTS smoother's P(0|T) is the
    posterior covariance of x_0 given all measurements, so the information the record carries
    about x_0 is its Fisher information

        I = P(0|T)^-1 - P0^-1                                                              (F1)

    (without process noise, the observability Gramian sum_k Phi_k^T H_k^T R^-1 H_k Phi_k,
    Phi_k = F_{k-1} ... F_0). In units of the prior standard deviations S, Ib = S I S, an
    eigenvector v of Ib with eigenvalue e is the combination v^T S^-1 x_0 whose posterior/prior
    variance ratio is 1 / (1 + e): e << 1, the record cannot separate it. Returns the ``count``
    smallest eigenvalues, each with that std ratio and the loadings of magnitude at least
    ``LOADING_SHOWN`` on ``names`` (the states of x_0), largest first."""
    P0 = np.asarray(prior_cov, np.float64)
    std = np.sqrt(np.diag(P0))
    info = np.linalg.inv(np.asarray(smoothed_cov0, np.float64)) - np.linalg.inv(P0)
    values, vectors = np.linalg.eigh(np.outer(std, std) * info)
    out = []
    for i in np.argsort(values)[:count]:
        v = vectors[:, i] * np.sign(vectors[np.argmax(np.abs(vectors[:, i])), i])
        shown = [j for j in np.argsort(-np.abs(v)) if abs(v[j]) >= LOADING_SHOWN]
        out.append({
            "information": float(values[i]),
            "std_ratio": float(1.0 / np.sqrt(1.0 + max(values[i], 0.0))),
            "loadings": {names[j]: float(v[j]) for j in shown},
        })  # fmt: skip
    return out


def bias_agreement(parameters):
    """For every entry of the parameter tables and pair of maneuvers:
    |difference| / sqrt(std_a^2 + std_b^2)."""
    names = list(parameters)
    return {
        p: {f"{a}-{b}": abs(parameters[a][p]["value"] - parameters[b][p]["value"])
            / np.hypot(parameters[a][p]["std"], parameters[b][p]["std"])
            for i, a in enumerate(names) for b in names[i + 1:]}
        for p in parameters[names[0]]
    }  # fmt: skip


# ---------------------------------------------------------------------------------------------
# real data: pinned parameters, smoothed estimates, coloured residuals, the joint fit

#: sensor parameters pinned at 0 on the real records, from the Fisher information of the full
#: model (record_information; summary.json least_informed_full_model, in prior variances):
#: b_V, a constant airspeed offset, which the integrated accelerometers cannot tell from the
#: initial speed (0.006-0.06, std ratio 0.97-1.00 on every ATTAS record); b_h, an altitude offset,
#: the same against the initial altitude (0.006-0.52, with u and h); b_phi, a bank-angle offset,
#: the same against the initial bank angle except through g sin(phi) in v', where it trades with
#: b_ay (0.15 on the elevator record). b_theta is pinned because the records fix only its
#: difference from the alpha offset (the flight-path angle theta - alpha enters h'): free, it
#: came out 0.44 +- 0.27, -0.60 +- 0.07 and -0.24 +- 0.11 deg on the three records, correlated
#: 0.87-0.99 with b_alpha, while the alpha offset at trim minus b_theta agreed within 0.1 deg.
#: Pinned, the initial states absorb them: u, h, phi and theta are referenced to the airspeed,
#: altitude and attitude sensors, and b_alpha is the alpha vane's offset relative to the pitch
#: attitude reference, which is what a flight-path reconstruction without an independent
#: reference can claim.
PINNED = {"b_V": 0.0, "b_h": 0.0, "b_phi": 0.0, "b_theta": 0.0}
#: the Bartlett window of the residual autocorrelation (s), the length of the maneuvers' longest
#: input pulses; residual power at longer periods is not counted
RESIDUAL_LAG_S = 2.0
#: the angle of attack (rad) at which the alpha-vane offset is reported (the ATTAS records' mean,
#: 2.1-2.3 deg): b_alpha_trim = b_alpha + lam_alpha alpha_trim, the offset of alpha_m there
ALPHA_TRIM = 2.2 * DEG


def trim_reparametrised(mean, cov, names):
    """(mean, cov, names) with b_alpha replaced by b_alpha_trim = b_alpha + lam_alpha alpha_trim
    (:data:`ALPHA_TRIM`): alpha_m = (1 + lam_alpha) alpha + b_alpha (eq 28) is the same as
    (1 + lam_alpha)(alpha - alpha_trim) + alpha_trim + b_alpha_trim. Where alpha barely leaves
    its trim value (the lateral records: std 0.16-0.21 deg) the data fix b_alpha_trim and leave
    b_alpha and lam_alpha free along b_alpha = b_alpha_trim - lam_alpha alpha_trim (correlation
    near -0.9). A linear change of variables, x' = M x, cov' = M cov M^T: for the (affine
    invariant) EKF and RTS smoother it is the same as estimating b_alpha_trim directly."""
    names = list(names)
    M = np.eye(len(names))
    M[names.index("b_alpha"), names.index("lam_alpha")] = ALPHA_TRIM
    names[names.index("b_alpha")] = "b_alpha_trim"
    return M @ np.asarray(mean), M @ np.asarray(cov) @ M.T, tuple(names)


def long_run_variance_ratio(x, max_lag: int):
    """Per column of ``x`` (T x m), the ratio of the long-run variance to the variance,

        kappa = 1 + 2 sum_{l=1}^{L} (1 - l / (L + 1)) rho(l)                                (C1)

    with rho the sample autocorrelation and Bartlett weights (Newey & West 1987), L = ``max_lag``.
    A constant estimated from T samples of noise with this autocorrelation has kappa times the
    variance it would have from white noise (T / kappa effective samples); kappa = (1 + a) / (1 - a)
    for an AR(1) series with coefficient a, as L grows."""
    x = np.asarray(x, np.float64)
    if x.ndim != 2 or not 0 < max_lag < x.shape[0]:
        raise ValueError(f"max_lag: expected 0 < max_lag < {x.shape[0]} on a T x m array, got "
                         f"{max_lag} and shape {x.shape}")  # fmt: skip
    x = x - x.mean(axis=0)
    var = np.mean(x**2, axis=0)
    lags = np.arange(1, max_lag + 1)
    rho = np.stack([np.sum(x[lag:] * x[:-lag], axis=0) / x.shape[0] for lag in lags])
    return 1.0 + 2.0 * np.sum((1.0 - lags / (max_lag + 1))[:, None] * rho, axis=0) / var


def colour_factors(result, ys, rate_hz):
    """(C1) of every output channel's normalised innovation e_j / sqrt(S_jj) over the samples
    where every channel was measured, floored at 1 (white-noise standard errors are never
    reduced)."""
    observed = np.all(np.isfinite(np.asarray(ys)), axis=1)
    var = np.diagonal(np.asarray(result.innovation_cov), axis1=-2, axis2=-1)
    normalised = np.asarray(result.innovation)[observed] / np.sqrt(var[observed])
    return np.maximum(long_run_variance_ratio(normalised, int(RESIDUAL_LAG_S * rate_hz)), 1.0)


def filter_record(model, data, prior, estimator=None):
    """``estimator`` (default the SVD-EKF) over one record: the result and the interval inputs."""
    inputs = flight.interval_inputs(jnp.asarray(data.inputs))
    est = SVDEKF() if estimator is None else estimator
    return run_filter(est, model, jnp.asarray(data.outputs), inputs=inputs, prior=prior), inputs


def reduced_prior(data, pinned):
    """:func:`real_prior` restricted to the states :func:`flight.pin_parameters` keeps."""
    prior = real_prior(data)
    keep = np.array([i for i, s in enumerate(flight.STATES) if s not in pinned])
    return Gaussian(prior.mean[keep], prior.cov[np.ix_(keep, keep)])


def pinned_model(dt, input_std, output_std):
    """:func:`flight.flight_model` with :data:`PINNED` held (:func:`flight.pin_parameters`): the
    model of the real records, and its state names."""
    full = flight.flight_model(dt, jnp.asarray(input_std), jnp.asarray(output_std))
    return flight.pin_parameters(full, PINNED)


class ColourCorrectedFit(NamedTuple):
    """What :func:`colour_corrected_fit` returns."""

    first: FilterResult  # the pass with white-noise R
    result: FilterResult  # the pass with R_j kappa_j
    smooth: SmootherResult  # its RTS smoother
    model: object  # the second pass's model
    inputs: jax.Array  # the interval inputs
    kappa: np.ndarray  # the colour factors, one per output
    names: tuple[str, ...]  # the model's states


def colour_corrected_fit(model_for_r, data, prior, output_std, estimator=None):
    """A first filter pass for the innovations' colour factors kappa_j (C1), then filter and RTS
    smoother with measurement noise R_j kappa_j, the white-noise variance that carries the
    residuals' low-frequency power; ``model_for_r(output_std)`` builds (model, state names) for
    an output noise std, ``estimator`` as in :func:`filter_record`."""
    model, names = model_for_r(output_std)
    first, _ = filter_record(model, data, prior, estimator)
    kappa = colour_factors(first, data.outputs, data.rate_hz)
    model, _ = model_for_r(np.asarray(output_std) * np.sqrt(kappa))
    result, inputs = filter_record(model, data, prior, estimator)
    smooth = rts_smooth(model, result, inputs=inputs)
    return ColourCorrectedFit(first, result, smooth, model, inputs, kappa, names)


def smoothed_parameters(fit: ColourCorrectedFit, prior):
    """The sensor parameters of ``fit``'s smoothed x(0|T), b_alpha as b_alpha_trim: their
    :func:`parameter_table` and each one's posterior / prior std (``prior`` the fit's)."""
    mean, cov, names = trim_reparametrised(fit.smooth.mean[0], fit.smooth.cov[0], fit.names)
    _, prior_cov, _ = trim_reparametrised(prior.mean, prior.cov, fit.names)
    table = parameter_table(mean, cov, names)
    ratio = np.sqrt(np.diag(cov) / np.diag(prior_cov))
    return table, {p: float(ratio[names.index(p)]) for p in table}


def estimate_record(data, input_std, output_std):
    """The pinned model (:data:`PINNED`) on one record, :func:`colour_corrected_fit`. The smoothed
    x(0|T), P(0|T) of its second pass are the reported estimates and standard errors: for a
    constant seen through noise of long-run variance kappa_j R_j, P(0|T) is then the estimate's
    variance (C1), where the first pass assumed white residuals. For constant parameters of a
    linear(ised) model x(k|T) is the same at every k and equals the last filtered estimate; the
    entry ``smoothed_minus_last_filtered`` (in standard errors) checks it. Returns a dict for
    summary.json and (model, prior, kappa) for the joint fit."""
    model_for_r = lambda std: pinned_model(data.dt, input_std, std)
    prior = reduced_prior(data, PINNED)
    fit = colour_corrected_fit(model_for_r, data, prior, output_std)
    first, result, smooth, model, inputs, kappa, names = fit
    white, last = (parameter_table(*trim_reparametrised(r.mean[-1], r.cov[-1], names))
                   for r in (first, result))  # fmt: skip
    table, std_ratio = smoothed_parameters(fit, prior)
    entry = {
        "colour_factor": {o: float(kappa[j]) for j, o in enumerate(OUTPUTS)},
        "parameters": table,
        "white_noise_std": {p: white[p]["std"] for p in table},
        "smoothed_minus_last_filtered": max(
            abs(table[p]["value"] - last[p]["value"]) / table[p]["std"] for p in table),
        "std_ratio": std_ratio,
        "identified": [p for p, ratio in std_ratio.items() if ratio < OBSERVABLE_RATIO],
        "least_informed": record_information(prior.cov, smooth.cov[0], names),
        "residual_rms": smoothed_residual_rms(data, model, smooth, inputs),
    }  # fmt: skip
    return entry, (model, prior, kappa)


def joint_estimate(runs, n_shared: int):
    """One set of the last ``n_shared`` states (the constant parameters) from several records,
    ``runs`` = [(model, ys, inputs, prior), ...]: the SVD-EKF runs through them in turn, each
    record starting from its own prior for the other states and from the parameters' posterior
    (mean and covariance block) that the previous record left. Records are independent given the
    parameters, so for a linear model this is the Gaussian posterior of the parameters given all
    records (p(theta | Y_1, Y_2) ~ p(Y_2 | theta) p(theta | Y_1)), which is also every record's
    smoothed estimate of them. Returns the parameters' mean and covariance."""
    mean = cov = None
    for model, ys, inputs, prior in runs:
        if mean is not None:
            prior = Gaussian(prior.mean.at[-n_shared:].set(mean),
                             prior.cov.at[-n_shared:, -n_shared:].set(cov))  # fmt: skip
        result = run_filter(SVDEKF(), model, ys, inputs=inputs, prior=prior)
        mean, cov = result.mean[-1, -n_shared:], result.cov[-1, -n_shared:, -n_shared:]
    return mean, cov


def joint_residuals(data, input_std, output_std, kappa, values):
    """Smoothed residual RMS of one record with every sensor parameter held at ``values`` (the
    joint estimate, a dict by name; :data:`PINNED` included): the 7 kinematic states only."""
    full = flight.flight_model(data.dt, jnp.asarray(input_std),
                               jnp.asarray(np.asarray(output_std) * np.sqrt(kappa)))  # fmt: skip
    model, _ = flight.pin_parameters(full, values)
    # the covariance-form EKF: for 7 states the SVD filters' Jacobi SVD takes XLA about 40 s to
    # compile per record length, and in float64 both filters agree to rounding
    result, inputs = filter_record(model, data, reduced_prior(data, values), EKF())
    return smoothed_residual_rms(data, model, rts_smooth(model, result, inputs=inputs), inputs)


def smoothed_residual_rms(data, model, smooth, inputs):
    """RMS of y_k - h(x(k|T)) per output channel, in output units."""
    computed = np.asarray(jax.vmap(model.h)(smooth.mean, inputs))
    rms = channel_rms(data.outputs - computed, 0)
    return {o: float(rms[i]) for i, o in enumerate(OUTPUTS) if np.isfinite(rms[i])}


def real_estimation(records, input_std, output_std):
    """Pinned, smoothed, colour-corrected estimates per ATTAS record and jointly, with residual
    RMS, scale factors and the between-record agreement in corrected standard errors (of the
    parameters that both records of a pair identify, and of each record with the joint fit)."""
    per, fits = {}, {}
    for m, d in records.items():
        per[m], fits[m] = estimate_record(d, input_std, output_std)
    out: dict = {"pinned": PINNED, "residual_lag_s": RESIDUAL_LAG_S,
                 "alpha_trim_deg": ALPHA_TRIM / DEG, "by_maneuver": per}  # fmt: skip
    if len(records) < 2:
        return out
    runs = [
        (model, jnp.asarray(d.outputs), flight.interval_inputs(jnp.asarray(d.inputs)), prior)
        for d, (model, prior, _) in zip(records.values(), fits.values(), strict=True)
    ]
    mean, cov = joint_estimate(runs, len(PARAMETERS) - len(PINNED))
    free = [p for p in PARAMETERS if p not in PINNED]
    joint = parameter_table(*trim_reparametrised(mean, cov, free))
    values = {p: float(mean[i]) for i, p in enumerate(free)} | PINNED
    out["joint"] = {"parameters": joint, "residual_rms": {
        m: joint_residuals(d, input_std, output_std, fits[m][2], values)
        for m, d in records.items()}}  # fmt: skip
    tables = {m: e["parameters"] for m, e in per.items()}
    pairs = bias_agreement(tables)
    both = lambda p, pair: all(p in per[m]["identified"] for m in pair.split("-"))
    out["agreement_se"] = {
        p: {pair: z for pair, z in v.items() if both(p, pair)} for p, v in pairs.items()
    }
    out["agreement_se"] = {p: v for p, v in out["agreement_se"].items() if v}
    out["disagreeing_3se"] = [p for p, v in out["agreement_se"].items() if max(v.values()) > 3]
    out["joint_minus_maneuver_se"] = {
        p: {m: abs(joint[p]["value"] - tables[m][p]["value"]) / tables[m][p]["std"]
            for m in per if p in per[m]["identified"]} for p in joint
    }  # fmt: skip
    lam = [p for p in free if p.startswith("lam_")]
    out["scale_factors"] = {p: {**{m: tables[m][p]["value"] for m in per},
                                "joint": joint[p]["value"]} for p in lam}  # fmt: skip
    out["scale_factors_within_0.15"] = all(
        abs(v) <= 0.15 for d in out["scale_factors"].values() for v in d.values()
    )
    return out


# ---------------------------------------------------------------------------------------------
# maximum-likelihood tuning of Q and R


class NoiseLevels(eqx.Module):
    """The tuned covariances: Qc of the 6 measured inputs per sample (the model's Q is
    blockdiag(Qc, Qc) on the interval input, so one Qc ties both blocks) and R of the 6 outputs."""

    Qc: jax.Array
    R: jax.Array

    def model(self, dt, lever_arms):
        std = lambda cov: jnp.sqrt(jnp.diagonal(cov))
        return flight.flight_model(dt, std(self.Qc), std(self.R), lever_arms)


def tune_noise(
    data_ys,
    inputs,
    prior,
    dt,
    input_std,
    output_std,
    lever_arms,
    steps,
    *,
    tune_r=True,
    optimizer=FIXED_STEPS_LBFGS,
):
    """Maximise the SVD-EKF log-likelihood over the 6 input noise variances and, if ``tune_r``, the
    6 output noise variances (log-diagonal parameters, ``steps`` L-BFGS steps of
    :func:`jaxest.tune.fit`). Returns (input_std, output_std, log-likelihood before every step and after the last)."""
    n_obs = float(np.sum(np.isfinite(np.asarray(data_ys))))

    def loss(noise):  # minus the log-likelihood per measurement
        model = noise.model(dt, lever_arms)
        return -run_filter(SVDEKF(), model, data_ys, inputs=inputs, prior=prior).loglik / n_obs

    start = NoiseLevels(
        jnp.diag(jnp.asarray(input_std) ** 2), jnp.diag(jnp.asarray(output_std) ** 2)
    )
    params = {"Qc": "log_diagonal", "R": "log_diagonal"} if tune_r else {"Qc": "log_diagonal"}
    fitted = fit(start, loss, params, optimizer=optimizer, num_steps=steps)
    losses = np.append(np.asarray(fitted.losses), float(loss(fitted.model)))
    std = lambda cov: np.sqrt(np.diagonal(np.asarray(cov)))
    return std(fitted.model.Qc), std(fitted.model.R), list(-losses * n_obs)


def noise_dict(input_std, output_std):
    units_in = PARAMETER_UNITS[: flight.N_IN]  # the input biases' units
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
    summary: dict = {"conditions": {}, "own_model_simulation": {}, "air_data_start": {},
                     "observability": {}, "settings": {
        "runs": runs, "duration_s": duration, "seed": seed, "nees_diverged": NEES_DIVERGED,
        "observable_ratio": OBSERVABLE_RATIO, "units": "m/s, deg, deg/s, m/s^2, m",
        "kinematic_std": INS_KINEMATIC_STD.tolist(),
        "air_data_kinematic_std": AIR_DATA_KINEMATIC_STD.tolist(),
    }}  # fmt: skip
    tables = []
    over_time = {}  # rate -> label -> NEES and NIS over time of the float64 elevator runs
    figures = () if quick else ((10, 1), (32, 2))  # --quick: only the real-data figure
    own_model = [c for c in conditions if c[0] == "elevator" and c[2] == "float64"]
    air_data = [c for c in conditions if c[2] == "float64"]
    air_data_label = f"air-data start, u, v, w {AIR_DATA_KINEMATIC_STD[0]:g} m/s"
    study_label = f"INS start, u, v, w {INS_KINEMATIC_STD[0]:g} m/s"
    weights = step_weights(conditions, own_model, air_data, figures, quick, data_dir is not None)
    with Progress(NAME, weights=weights) as progress:
        truths = {}
        for maneuver, rate, dtype_name in conditions:
            dtype = jnp.dtype(dtype_name)
            if (maneuver, rate) not in truths:
                truths[maneuver, rate] = sim.true_flight(maneuver, rate, duration)
            truth = truths[maneuver, rate]
            cond_key = jax.random.fold_in(key, 100 * sim.MANEUVERS.index(maneuver) + rate)
            # the same flights in both dtypes
            batch = simulated_batch(truth, runs, cond_key, dtype, kinematic_std=INS_KINEMATIC_STD)
            model, P0 = model_for(rate, dtype), prior_cov(dtype, INS_KINEMATIC_STD)
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
                ratios = observability(metrics["svd_ekf"])
                summary["observability"][maneuver] = {
                    "std_ratio": ratios,
                    "observable": [p for p, r in ratios.items() if r < OBSERVABLE_RATIO],
                }
            tables += [table_row(name, f, entry[f]) for f in FILTERS]
            if (maneuver, rate, dtype_name) in own_model:
                own = own_model_simulation(model, batch, P0, settle, chunk,
                                           jax.random.fold_in(cond_key, 1))  # fmt: skip
                summary["own_model_simulation"][name] = {"ekf": own}
                tables.append(table_row(f"{name} (own-model simulation)", "ekf", own))
                progress.advance(f"{maneuver} {rate} Hz own-model simulation")
            if (maneuver, rate, dtype_name) in air_data:
                block, air_data_t = air_data_start(truth, runs, cond_key, model, settle, chunk)
                summary["air_data_start"][name] = {"ekf": block}
                tables.append(table_row(f"{name} ({air_data_label})", "ekf", block))
                progress.advance(f"{maneuver} {rate} Hz {air_data_label}")
                if (maneuver, rate, dtype_name) in own_model:  # the figure's elevator runs
                    over_time[rate] = {
                        f"EKF, {air_data_label}": air_data_t,
                        f"SVD-EKF, {study_label}": {k: metrics["svd_ekf"][k][common]
                                                    for k in ("nees_t", "nis_t")},
                    }  # fmt: skip
        if over_time:
            where = "averaged over the runs, simulated elevator maneuver, float64"
            consistency_figure(out / "fig_nees_elevator.png", over_time, "nees_t",
                               list(NEES_GROUPS.items()), f"NEES {where}")  # fmt: skip
            consistency_figure(out / "fig_nis_elevator.png", over_time, "nis_t",
                               [(o, 1) for o in OUTPUTS], f"NIS per channel {where}")  # fmt: skip
        for rate, fig in figures:
            maneuver = "elevator" if quick else "aileron"
            path = out / f"fig{fig}_states_{rate}hz.png"
            if (maneuver, rate) not in truths:
                truths[maneuver, rate] = sim.true_flight(maneuver, rate, duration)
            single_run_figure(path, truths[maneuver, rate], rate, jax.random.fold_in(key, fig),
                              f"SVD-EKF, simulated {maneuver} maneuver, {rate} Hz")  # fmt: skip
            progress.advance(f"figure {fig}")
        # compiling the likelihood gradient is the slowest piece: --quick leaves tuning out
        if quick:
            summary["tuning"] = {}
        else:
            if ("elevator", 32) not in truths:
                truths["elevator", 32] = sim.true_flight("elevator", 32, duration)
            summary["tuning"] = {
                "simulated": tune_simulated(key, truths["elevator", 32], tune_steps)
            }
            progress.advance("simulated tuning")
        if data_dir is not None:
            summary["real_data"] = real_data_part(out, data_dir, quick, tune_steps, progress)
            summary["tuning"]["real"] = summary["real_data"].pop("tuning")
        else:
            summary["real_data_note"] = f"no flight data found. {flight_data.DOWNLOAD_HINT}"
    write_tables(out, summary, tables)
    write_json(out / "summary.json", summary)
    return summary


#: seconds of the study's steps in a fresh-clone ``make reproduce`` (2-core CPU, beside another
#: study, 2026-11-29), the progress display's weights: a filter's runs take its entry per 10 Hz
#: of rate, and its first condition at a rate and dtype "compile" more
STEP_SECONDS = {"ekf": 1.3, "svd_ekf": 3.4, "svd_improved": 3.2, "compile": 5.0,
                "own-model simulation": 6.0, "figure": 8.0, "simulated tuning": 18.0,
                "sensor delays": 18.0, "real-data tuning": 24.0, "ATTAS maneuver": 4.0,
                "ATTAS estimates": 25.0, "HFB-320": 11.0}  # fmt: skip


def step_weights(conditions, own_model, air_data, figures, quick, real_data) -> list[float]:
    """The expected seconds (:data:`STEP_SECONDS`) of :func:`run`'s progress steps, in order."""
    weights, compiled = [], set()
    for maneuver, rate, dtype in conditions:
        for fname in FILTERS:
            first = (fname, rate, dtype) not in compiled
            compiled.add((fname, rate, dtype))
            weights.append(rate / 10 * STEP_SECONDS[fname] + first * STEP_SECONDS["compile"])
        if (maneuver, rate, dtype) in own_model:
            weights.append(STEP_SECONDS["own-model simulation"])
        if (maneuver, rate, dtype) in air_data:  # one EKF Monte Carlo
            weights.append(rate / 10 * STEP_SECONDS["ekf"])
    weights += [STEP_SECONDS["figure"]] * len(figures)
    if not quick:
        weights.append(STEP_SECONDS["simulated tuning"])
    if real_data:  # as real_data_part advances
        steps = ["sensor delays"] + ["real-data tuning"] * (not quick)
        steps += ["ATTAS maneuver"] * (1 if quick else len(flight_data.ATTAS_FILES))
        steps += ["ATTAS estimates"] + ["HFB-320"] * (not quick)
        weights += [STEP_SECONDS[step] for step in steps]
    return weights


def tune_simulated(key, truth: sim.TrueFlight, steps, **fit_options):
    """ML tuning on one simulated flight (``truth``) whose true noise is twice the nominal level,
    starting from the nominal level: the tuned values should move towards the truth."""
    rate = truth.rate_hz
    batch = simulated_batch(truth, 1, jax.random.fold_in(key, 7), jnp.float64, noise_scale=2.0,
                            kinematic_std=INS_KINEMATIC_STD)  # fmt: skip
    ys, inputs, mean0, _ = (a[0] for a in batch)
    prior = Gaussian(mean0, prior_cov(jnp.float64, INS_KINEMATIC_STD))
    in_std, out_std, hist = tune_noise(ys, inputs, prior, 1.0 / rate, sim.INPUT_STD,
                                       sim.OUTPUT_STD, sim.LEVER_ARMS, steps, **fit_options)  # fmt: skip
    return {
        "true_noise": noise_dict(2 * sim.INPUT_STD, 2 * sim.OUTPUT_STD),
        "initial_noise": noise_dict(sim.INPUT_STD, sim.OUTPUT_STD),
        "tuned_noise": noise_dict(in_std, out_std),
        "loglik_initial": hist[0],
        "loglik_tuned": hist[-1],
        "steps": steps,
    }


def real_data_part(out, data_dir, quick, tune_steps, progress):  # noqa: C901
    maneuvers = ("elevator",) if quick else tuple(flight_data.ATTAS_FILES)
    raw = {m: flight_data.load_attas(m, data_dir) for m in maneuvers}
    if quick:  # first 5 s
        d = raw["elevator"]
        n = int(5 * d.rate_hz)
        raw["elevator"] = flight_data.FlightData(d.name, d.t[:n], d.inputs[:n], d.outputs[:n])
    report: dict = {"files": {m: flight_data.ATTAS_FILES[m] for m in maneuvers}}
    delays, profiles, best = estimate_delays(raw, sim.INPUT_STD, REAL_OUTPUT_STD)
    report["sensor_delays_s"] = {o: float(delays[OUTPUTS.index(o)]) for o in DELAYED_OUTPUTS}
    report["sensor_delays_by_maneuver_s"] = best
    plot_delay_profiles(
        out / "fig_attas_delays.png", profiles, delays, delay_grid(raw["elevator"].dt)
    )
    progress.advance("sensor delays")
    records = {m: aligned(d, delays) for m, d in raw.items()}
    elev = records["elevator"]
    settle = int(SETTLE_S * elev.rate_hz)
    in_std, out_std = sim.INPUT_STD, REAL_OUTPUT_STD
    report["tuning"] = {}
    if tune_steps:  # ML tuning of Q and R on the elevator maneuver, used for every maneuver
        in_std, out_std, hist = tune_noise(
            jnp.asarray(elev.outputs), flight.interval_inputs(jnp.asarray(elev.inputs)),
            real_prior(elev), elev.dt, sim.INPUT_STD, REAL_OUTPUT_STD, flight.LeverArms(),
            tune_steps, tune_r=False,
        )  # fmt: skip
        report["tuning"] = {
            "initial_noise": noise_dict(sim.INPUT_STD, REAL_OUTPUT_STD),
            "tuned_noise": noise_dict(in_std, out_std),
            "loglik_initial": hist[0], "loglik_tuned": hist[-1], "steps": tune_steps,
            "data": "ATTAS elevator, flow angles aligned",
        }  # fmt: skip
        progress.advance("real-data tuning")
    residuals, residuals_untuned, residuals_unaligned, information = {}, {}, {}, {}
    for m, d in records.items():
        result, model, inputs = reconstruct(d, in_std, out_std)
        innov, filt, computed = residual_rms(d, result, model, inputs, settle)
        smooth = rts_smooth(model, result, inputs=inputs)
        information[m] = record_information(real_prior(d).cov, smooth.cov[0], flight.STATES)
        residuals[m] = {"innovation_rms": innov, "filtered_rms": filt,
                        "diverged": bool(np.any(np.asarray(result.status) != 0))}  # fmt: skip
        r_raw, model_raw, inputs_raw = reconstruct(raw[m], in_std, out_std)
        residuals_unaligned[m] = residual_rms(raw[m], r_raw, model_raw, inputs_raw, settle)[0]
        if tune_steps:
            r0, model0, inputs0 = reconstruct(d, sim.INPUT_STD, REAL_OUTPUT_STD)
            residuals_untuned[m] = residual_rms(d, r0, model0, inputs0, settle)[0]
        plot_states_and_fits(out / f"fig_attas_{m}.png", d.t, None, np.asarray(result.mean),
                             d.outputs, computed, f"SVD-EKF on ATTAS {m} maneuver (25 Hz)")  # fmt: skip
        progress.advance(f"ATTAS {m}")
    report["least_informed_full_model"] = information
    report["estimation"] = real_estimation(records, in_std, out_std)
    progress.advance("ATTAS pinned, smoothed and joint estimates")
    report["residual_rms"] = residuals["elevator"]["innovation_rms"]
    report["residuals_by_maneuver"] = residuals
    report["innovation_rms_untuned"] = residuals_untuned
    report["innovation_rms_unaligned"] = residuals_unaligned
    report["hfb320_noise_x3"] = {k: 3 * v for k, v in HFB320_NOISE.items()}
    if len(records) > 1:
        report["agreement_note"] = AGREEMENT_NOTE
    if not quick:
        report["hfb320"] = reconstruct_hfb320(out, data_dir)
        progress.advance("HFB-320")
    return report


def reconstruct_hfb320(out, data_dir):
    """The HFB-320 record (10 Hz, no altitude channel) with the nominal noise levels."""
    hfb = flight_data.load_hfb320(data_dir)
    delays, _, _ = estimate_delays({"hfb320": hfb}, sim.INPUT_STD, REAL_OUTPUT_STD)
    hfb = aligned(hfb, delays)
    result, model, inputs = reconstruct(hfb, sim.INPUT_STD, REAL_OUTPUT_STD)
    innov, filt, computed = residual_rms(hfb, result, model, inputs, int(SETTLE_S * hfb.rate_hz))
    plot_states_and_fits(out / "fig_hfb320.png", hfb.t, None, np.asarray(result.mean), hfb.outputs,
                         computed, "SVD-EKF on HFB-320 elevator record (10 Hz)")  # fmt: skip
    return {"parameters": parameter_table(result.mean[-1], result.cov[-1], flight.STATES), "innovation_rms": innov, "filtered_rms": filt,
            "sensor_delays_s": {o: float(delays[OUTPUTS.index(o)]) for o in DELAYED_OUTPUTS}}  # fmt: skip


def write_tables(out, summary, rows):
    text = "# SVD-EKF flight estimation: simulated Monte Carlo\n\n"
    text += "State RMSE after the first second (m/s, deg, m), over the runs no filter lost.\n\n"
    text += "NEES of all states (expected 23), the kinematic states (7) and the sensor parameters "
    text += "(16), averaged over time and runs; NIS averaged over the six output channels "
    text += "(expected 1; per channel in summary.json). Every condition starts from a GPS-aided "
    text += f"INS's kinematic uncertainty (u, v, w {INS_KINEMATIC_STD[0]:g} m/s; "
    text += 'settings.kinematic_std). Rows marked "own-model simulation": the EKF on flights '
    text += 'simulated from its own discrete model; rows marked "air-data start": the EKF on the '
    text += "same flights as the condition, with ten times the initial kinematic error and prior "
    text += f"std (u, v, w {AIR_DATA_KINEMATIC_STD[0]:g} m/s), as on the real records.\n\n"
    text += markdown_table(["condition", "filter", "diverged", "runs", "NEES (23)", "kin (7)",
                            "par (16)", "NIS (1)", *KINEMATIC_STATES], rows)  # fmt: skip
    text += "\n## Parameter observability (posterior std / prior std, SVD-EKF)\n\n"
    obs = summary["observability"]
    text += markdown_table(["parameter", *obs], [[p, *[obs[m]["std_ratio"][p] for m in obs]]
                                                 for p in PARAMETERS], floatfmt=".2f")  # fmt: skip
    if "real_data" in summary:
        real = summary["real_data"]
        est = real["estimation"]
        by = {m: e["parameters"] for m, e in est["by_maneuver"].items()}
        if "joint" in est:
            by["joint"] = est["joint"]["parameters"]
        pinned = ", ".join(est["pinned"])
        text += (
            "\n## ATTAS: sensor parameters, RTS-smoothed, standard errors corrected for "
            f"coloured residuals ({pinned} pinned at 0; m/s^2, deg/s, m/s, deg, m)\n\n"
        )
        text += markdown_table(["parameter", *by], [
            [p, *[f"{by[m][p]['value']:.4g} ± {by[m][p]['std']:.2g}" for m in by]]
            for p in by[next(iter(by))]])  # fmt: skip
        text += "\n## ATTAS: smoothed residual RMS per channel (m/s, deg, m)\n\n"
        rows = [[m, "own parameters", *[e["residual_rms"].get(o) for o in OUTPUTS]]
                for m, e in est["by_maneuver"].items()]  # fmt: skip
        if "joint" in est:
            rows += [[m, "joint parameters", *[r.get(o) for o in OUTPUTS]]
                     for m, r in est["joint"]["residual_rms"].items()]  # fmt: skip
            text += markdown_table(["maneuver", "parameters", *OUTPUTS], rows)
            text += f"\nDisagreeing by more than 3 s.e.: {est['disagreeing_3se']}. "
            text += real["agreement_note"] + "\n"
        else:
            text += markdown_table(["maneuver", "parameters", *OUTPUTS], rows)
        delays = ", ".join(f"{c} {v:.2f} s" for c, v in real["sensor_delays_s"].items())
        text += f"\n## ATTAS: innovation RMS (m/s, deg, m); flow-vane delays {delays}\n\n"
        res = real["residuals_by_maneuver"]
        rows = [
            [m, "aligned, tuned Q", *[res[m]["innovation_rms"][o] for o in OUTPUTS]] for m in res
        ]
        for label, key in (
            ("aligned, nominal Q", "innovation_rms_untuned"),
            ("not aligned, tuned Q", "innovation_rms_unaligned"),
        ):
            rows += [[m, label, *[v[o] for o in OUTPUTS]] for m, v in real[key].items()]
        text += markdown_table(["maneuver", "data, noise", *OUTPUTS], rows)
        text += (
            "\n## ATTAS: least informed combinations of the initial state, full model "
            "(Fisher information in prior variances; posterior / prior std)\n\n"
        )
        text += markdown_table(["maneuver", "information", "std ratio",
                                "combination (loadings >= 0.2)"], [
            [m, f"{c['information']:.3g}", f"{c['std_ratio']:.2f}",
             ", ".join(f"{v:+.2f} {p}" for p, v in c["loadings"].items())]
            for m, combos in real["least_informed_full_model"].items() for c in combos
        ])  # fmt: skip
    (out / "tables.md").write_text(text)
