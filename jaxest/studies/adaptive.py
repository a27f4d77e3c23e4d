"""Zhang's adaptive observer on the Charlie and Boeing 747 models (figs 2-5), hand-chosen against
gradient-tuned M, Sigma (and the Riccati Q, R).

Set-up (the paper leaves these open; see :mod:`jaxest.systems.aircraft_linear` for the outputs):

- psi(t) = B diag(u(t)) built from the measured input: theta_i is the effectiveness of control
  i (Charlie: elevator, theta = 2; 747: rudder and aileron, theta = [0.9, 3]), the known part
  B(t) u of eq 1 is zero, and the nominal guess is theta_hat(0) = 1.
- Control u_k = -K_bar x_hat(t_k) + r_k, held over each sample (dt = 0.01), with K_bar the LQR
  gain of the nominal model (Q = I, R = I; standing in for the paper's ALGLX) and r a multisine
  reference (three sines per channel, random phases) that keeps psi persistently exciting.
- Observer gain K(t) from the Riccati eq 32, started at its steady state (CARE).
- "hand": M = I, Sigma = I, Q = I, R = I. "tuned": M, Sigma, Q, R by Adam on their Cholesky
  factors, minimising the time-weighted integral of the relative parameter error
  int t |theta_hat - theta| / |theta| dt over noisy training scenarios (random phases, initial
  states and noise); evaluated on other scenarios.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from jaxest.batching import vmap_minor
from jaxest.observers import ObserverStatus as Status
from jaxest.observers.adaptive import (
    AdaptiveObserver,
    ContinuousLTV,
    InputEffectiveness,
    ObserverPrior,
    simulate_closed_loop,
)
from jaxest.progress import Progress
from jaxest.report import markdown_table, write_json
from jaxest.riccati import lqr_gain, solve_filter_care
from jaxest.systems.aircraft_linear import aircraft
from jaxest.tune import fit

DESCRIPTION = "Zhang adaptive observer, Charlie and Boeing 747 (figs 2-5): hand vs tuned M, Sigma"

DT = 0.01
SETTLING_BAND = 0.02
#: persistent-excitation window (samples) of the evaluated observers, hand and tuned
EXCITATION_WINDOW = 200

#: per aircraft: horizon T (model time units) of the nominal and held-out Monte Carlo runs and
#: tune_T of the tuning runs, reference amplitude per input and frequencies, measurement-noise
#: standard deviation, initial-state spread
CONFIG = {
    "charlie": dict(
        T=320.0,
        tune_T=40.0,
        amplitude=(3.0,),
        freqs=(0.5, 1.3, 2.9),
        noise=0.01,
        x0=0.1,
    ),
    "b747": dict(
        T=800.0,
        tune_T=40.0,
        amplitude=(1.0, 3.0),
        freqs=(0.3, 0.7, 1.7),
        noise=0.01,
        x0=0.05,
    ),
}


class Plant(eqx.Module):
    """One aircraft with its observer model, LQR gain and true parameters."""

    model: ContinuousLTV
    feedback_gain: jax.Array
    theta: jax.Array


def make_plant(name: str, printed: bool = False) -> Plant:
    """The plant of aircraft ``name`` (``printed``: the scan's 747 values)."""
    return plant_from_aircraft(aircraft(name, printed))


def plant_from_aircraft(ac: dict) -> Plant:
    """The plant of an :func:`jaxest.systems.aircraft_linear.aircraft` description."""
    A, B, C = (jnp.asarray(ac[k]) for k in ("A", "B", "C"))
    n, l = B.shape
    model = ContinuousLTV(A, jnp.zeros_like(B), C, InputEffectiveness(B))
    Kbar = lqr_gain(A, B, jnp.eye(n), jnp.eye(l))
    return Plant(model, Kbar, jnp.asarray(ac["theta"]))


def hand_observer(plant: Plant, window: int = EXCITATION_WINDOW) -> AdaptiveObserver:
    """M = I, Sigma = I, Q = I, R = I."""
    n, m, p = plant.model.A.shape[0], plant.model.C.shape[0], plant.theta.shape[0]
    return AdaptiveObserver(
        M=jnp.eye(p), Sigma=jnp.eye(m), Q=jnp.eye(n), R=jnp.eye(m), dt=DT, excitation_window=window
    )


def prior_for(observer: AdaptiveObserver, plant: Plant) -> ObserverPrior:
    """x_hat = 0, theta_hat = 1 (nominal effectiveness), P = steady state of eq 32 (filter CARE)."""
    A, C = plant.model.A, plant.model.C
    P0 = solve_filter_care(A, C, observer.Q, observer.R).X
    return ObserverPrior(jnp.zeros(A.shape[0]), jnp.ones_like(plant.theta), P0)


def reference(name: str, T: float, phases) -> jax.Array:
    """Multisine r_j(t) = a_j sum_i sin((j + 1) f_i t + phase_ij), sampled every DT."""
    cfg = CONFIG[name]
    t = jnp.arange(int(round(T / DT))) * DT
    freqs = jnp.asarray(cfg["freqs"])
    channels = [
        a * jnp.sum(jnp.sin((j + 1) * freqs[:, None] * t[None, :] + phases[j][:, None]), axis=0)
        for j, a in enumerate(cfg["amplitude"])
    ]
    return jnp.stack(channels, axis=1)


class Scenario(eqx.Module):
    x0: jax.Array
    phases: jax.Array
    key: jax.Array
    noise: jax.Array  # standard deviation of the measurement noise (0: noise-free)


def nominal_scenario(name: str, plant: Plant, noisy: bool) -> Scenario:
    n, l = plant.feedback_gain.shape[1], plant.feedback_gain.shape[0]
    x0 = jnp.zeros(n).at[0].set(CONFIG[name]["x0"]).at[1].set(0.5 * CONFIG[name]["x0"])
    phases = jnp.tile(jnp.arange(3.0), (l, 1))
    noise = CONFIG[name]["noise"] if noisy else 0.0
    return Scenario(x0, phases, jax.random.PRNGKey(12345), jnp.asarray(noise))


def random_scenarios(name: str, plant: Plant, key, count: int, noisy: bool = True) -> Scenario:
    """``count`` scenarios (batched leaves): random initial states, reference phases and noise."""
    n, l = plant.feedback_gain.shape[1], plant.feedback_gain.shape[0]
    k1, k2, k3 = jax.random.split(key, 3)
    x0 = CONFIG[name]["x0"] * jax.random.normal(k1, (count, n))
    phases = jax.random.uniform(k2, (count, l, 3), maxval=2 * jnp.pi)
    noise = jnp.full((count,), CONFIG[name]["noise"] if noisy else 0.0)
    return Scenario(x0, phases, jax.random.split(k3, count), noise)


def fly(observer, plant: Plant, name: str, scenario: Scenario, T: float):
    """Closed-loop run of ``scenario`` over [0, T]."""
    prior = prior_for(observer, plant)
    r = reference(name, T, scenario.phases)
    return simulate_closed_loop(
        observer,
        plant.model,
        plant.theta,
        scenario.x0,
        prior,
        plant.feedback_gain,
        r,
        key=scenario.key,
        noise_std=scenario.noise,
    )


def relative_theta_error(theta_hat, theta):
    return jnp.abs(theta_hat - theta) / jnp.abs(theta)


def tuning_loss(observer, scenario, plant: Plant, name: str, horizon: float | None = None):
    """Time-weighted integrated relative parameter error, int_0^T (t / T) |theta~ / theta|_1 dt / T,
    over T = ``horizon`` (default: the aircraft's ``tune_T``)."""
    T = CONFIG[name]["tune_T"] if horizon is None else horizon
    sim = fly(observer, plant, name, scenario, T)
    err = jnp.sum(relative_theta_error(sim.estimate.theta, plant.theta), axis=-1)
    weight = jnp.arange(err.shape[0]) / err.shape[0]
    return jnp.mean(weight * err)


def settling_time(theta_hat, theta, band: float = SETTLING_BAND) -> float:
    """Time after which every component of theta_hat stays within ``band`` of the truth
    (inf if it is outside at the end)."""
    outside = np.any(np.asarray(relative_theta_error(theta_hat, theta)) > band, axis=-1)
    if outside[-1]:
        return float("inf")
    last = np.flatnonzero(outside)
    return 0.0 if last.size == 0 else float((last[-1] + 1) * DT)


def record(sim, plant: Plant, window_full: int) -> dict:
    theta = np.asarray(plant.theta)
    est = sim.estimate
    return {
        "theta_true": theta,
        "theta_final": np.asarray(est.theta[-1]),
        "theta_relative_error_final": np.asarray(relative_theta_error(est.theta[-1], plant.theta)),
        "theta_settling_time": settling_time(est.theta, plant.theta),
        "x_error_final": float(jnp.linalg.norm(est.x[-1] - sim.states[-1])),
        "pe_min_eigenvalue": float(jnp.min(est.excitation[window_full:])),
        "excitation_lost_steps": int(jnp.sum((est.status & Status.NOT_EXCITED) != 0)),
        "status_ok": bool(jnp.all((est.status & Status.NONFINITE) == 0)),
    }


def tune(plant: Plant, name: str, key, *, batch: int, steps: int, horizon: float | None = None):
    """Gradient-tuned M, Sigma, Q, R from the hand-chosen start (:func:`jaxest.tune.fit`, Cholesky
    parametrisation; Adam with the gradient norm clipped to 1, non-finite steps skipped), on
    :func:`tuning_loss` over ``horizon``. Returns (observer, loss before each step)."""
    start = hand_observer(plant, window=1)  # the excitation monitor is not needed while tuning
    scenarios = random_scenarios(name, plant, key, batch)

    def loss(observer):
        losses = jax.vmap(lambda s: tuning_loss(observer, s, plant, name, horizon))(scenarios)
        return jnp.mean(losses)

    optimizer = optax.apply_if_finite(
        optax.chain(optax.clip_by_global_norm(1.0), optax.adam(0.1)), max_consecutive_errors=5
    )
    fitted = fit(start, loss, ("M", "Sigma", "Q", "R"), optimizer=optimizer, num_steps=steps)
    tuned = dataclasses.replace(fitted.model, excitation_window=EXCITATION_WINDOW)
    return tuned, np.asarray(fitted.losses)


def concatenate_scenarios(*scenarios: Scenario) -> Scenario:
    """One batch of the given scenarios, single ones (:func:`nominal_scenario`) and batches
    (:func:`random_scenarios`) alike, in order."""
    as_batch = lambda s: s if s.x0.ndim == 2 else jax.tree_util.tree_map(lambda a: a[None], s)
    return jax.tree_util.tree_map(
        lambda *leaves: jnp.concatenate(leaves), *map(as_batch, scenarios)
    )


def fly_all(observers: dict, plant, name, scenarios: Scenario, T: float) -> dict[str, list]:
    """Run a batch of scenarios with each of ``observers`` (label -> observer): one compiled
    function per aircraft and horizon, the observer its argument; returns label -> the list of
    closed-loop runs (as NumPy-backed pytrees).

    One batch, not a loop over small ones: a closed-loop step is a few small matrices, so a run
    of 32,000 steps costs the scan's per-step overhead, which a batch shares (on the Charlie
    horizon, 10 runs at once took 4.4-5.0 s, five batches of 2 runs 11.5 s). The batch is
    :func:`jaxest.vmap_minor`'s, the runs on the minor axis: 12 runs, after compiling, took
    1.4 s for Charlie and 3.7 s for the 747, against 4.3 and 6.6 s under ``jax.vmap`` (2-core
    CPU; the runs agree to 3e-15)."""
    batched = vmap_minor(lambda obs, s: fly(obs, plant, name, s, T), in_axes=(None, 0))
    count = scenarios.x0.shape[0]
    runs = {}
    for label, observer in observers.items():
        batch = jax.tree_util.tree_map(np.asarray, batched(observer, scenarios))
        runs[label] = [
            jax.tree_util.tree_map(lambda leaf, j=j: leaf[j], batch) for j in range(count)
        ]
    return runs


def _plot_errors(path: Path, name: str, runs: dict, plant: Plant, state_names) -> None:
    from jaxest.plot import plt, save

    labels = list(runs)
    p = plant.theta.shape[0]
    rows = len(state_names) + p
    fig, axes = plt.subplots(rows, len(labels), figsize=(5 * len(labels), 1.6 * rows), sharex=True)
    for col, label in enumerate(labels):
        sim = runs[label]
        t = np.arange(sim.states.shape[0]) * DT
        err = sim.estimate.x - sim.states
        for i, s in enumerate(state_names):
            axes[i, col].plot(t, err[:, i], lw=0.8)
            axes[i, col].set_ylabel(f"{s} error")
        for j in range(p):
            ax = axes[len(state_names) + j, col]
            ax.plot(t, sim.estimate.theta[:, j] - np.asarray(plant.theta)[j], lw=0.8, color="C3")
            ax.set_ylabel(f"theta_{j + 1} error")
        axes[0, col].set_title(f"{name}: {label}")
        axes[-1, col].set_xlabel("t")
    save(fig, path, dpi=90)


def _plot_states(path: Path, name: str, sim, label: str, state_names) -> None:
    from jaxest.plot import plt, save

    fig, axes = plt.subplots(len(state_names), 1, figsize=(7, 1.7 * len(state_names)), sharex=True)
    t = np.arange(sim.states.shape[0]) * DT
    for i, s in enumerate(state_names):
        axes[i].plot(t, sim.states[:, i], "b-", lw=1.0, label="x")
        axes[i].plot(t, sim.estimate.x[:, i], "r--", lw=1.0, label="x_hat")
        axes[i].set_ylabel(s)
    axes[0].legend(loc="upper right")
    axes[0].set_title(f"{name}: states and estimates ({label})")
    axes[-1].set_xlabel("t")
    save(fig, path, dpi=90)


def _plot_montecarlo(path: Path, name: str, settle: dict, history: list) -> None:
    from jaxest.plot import plt, save

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 3.5))
    for label, values in settle.items():
        finite = np.asarray([v for v in values if np.isfinite(v)])
        ax1.plot(
            np.sort(finite),
            np.arange(1, finite.size + 1) / len(values),
            drawstyle="steps-post",
            label=label,
        )
    ax1.set_xscale("log")
    ax1.set_xlabel("theta settling time (2 %)")
    ax1.set_ylabel("fraction of held-out runs settled")
    ax1.legend()
    ax2.semilogy(history)
    ax2.set_xlabel("Adam step")
    ax2.set_ylabel("tuning loss")
    fig.suptitle(name)
    save(fig, path, dpi=90)


def run(out: Path, *, runs: int | None, seed: int, quick: bool, options: dict) -> dict:
    """Both aircraft: tune, fly the nominal scenario noise-free and noisy with both observers,
    then a Monte Carlo over held-out scenarios; figures, summary.md and summary.json."""
    out = Path(out) / "adaptive"
    out.mkdir(parents=True, exist_ok=True)
    runs = runs if runs is not None else (2 if quick else 10)
    printed = bool(options.get("printed_747", False))
    tune_steps, tune_batch = (2, 2) if quick else (40, 4)
    key = jax.random.PRNGKey(seed)
    summary: dict = {}
    rows = []
    with Progress("adaptive", total=6) as progress:
        for index, name in enumerate(("charlie", "b747")):
            ac = aircraft(name, printed)  # printed only changes the 747
            plant = plant_from_aircraft(ac)
            T = (20.0 if name == "charlie" else 40.0) if quick else CONFIG[name]["T"]
            # quick: a quarter of tune_T; the tuning runs take most of the quick study's time
            tune_T = 10.0 if quick else CONFIG[name]["tune_T"]
            train_key, test_key = jax.random.split(jax.random.fold_in(key, index))
            tuned, history = tune(
                plant, name, train_key, batch=tune_batch, steps=tune_steps, horizon=tune_T
            )
            progress.advance(f"{name} tuned, loss {history[0]:.3g} -> {history[-1]:.3g}")
            observers = {"hand": hand_observer(plant), "tuned": tuned}
            # the nominal scenario noise-free and noisy, then the held-out ones: one batch
            scenarios = concatenate_scenarios(
                nominal_scenario(name, plant, False),
                nominal_scenario(name, plant, True),
                random_scenarios(name, plant, test_key, runs),
            )
            window_full = observers["hand"].excitation_window
            result: dict = {"noisy": {}}
            flown, held_out = {}, {}
            for label, runs_flown in fly_all(observers, plant, name, scenarios, T).items():
                clean, noisy, *held_out[label] = runs_flown
                flown[label] = clean
                result[label] = record(clean, plant, window_full)
                result["noisy"][label] = record(noisy, plant, window_full)
            progress.advance(f"{name} nominal and held-out runs")
            settle = {}
            mc = {}
            for label in observers:
                recs = [record(sim, plant, window_full) for sim in held_out[label]]
                settle[label] = [r["theta_settling_time"] for r in recs]
                mc[label] = {
                    "theta_settling_time": settle[label],
                    "theta_relative_error_final_max": [
                        float(np.max(r["theta_relative_error_final"])) for r in recs
                    ],
                    "x_error_final": [r["x_error_final"] for r in recs],
                    "settled_fraction": float(np.mean(np.isfinite(settle[label]))),
                }
            with np.errstate(invalid="ignore", divide="ignore"):  # unsettled runs: inf, nan
                speedup = np.asarray(settle["hand"]) / np.asarray(settle["tuned"])
            mc["speedup"] = speedup
            mc["speedup_min"] = float(np.min(speedup))
            mc["speedup_median"] = float(np.median(speedup))
            mc["runs"] = runs
            mc["horizon"] = T
            progress.advance(f"{name} Monte Carlo summarised")
            result["held_out_montecarlo"] = mc
            result["tuned_matrices"] = {
                f: np.asarray(getattr(tuned, f)) for f in ("M", "Sigma", "Q", "R")
            }
            result["tuning_loss"] = history
            result["horizon"] = T
            result["tuning_horizon"] = tune_T
            result["time_unit"] = ac["time_unit"]
            summary[name] = result
            _plot_errors(out / f"{name}_errors.png", name, flown, plant, ac["state_names"])
            _plot_states(
                out / f"{name}_states_hand.png",
                name,
                flown["hand"],
                "hand, noise-free",
                ac["state_names"],
            )
            _plot_states(
                out / f"{name}_states_tuned.png",
                name,
                flown["tuned"],
                "tuned, noise-free",
                ac["state_names"],
            )
            _plot_montecarlo(out / f"{name}_montecarlo.png", name, settle, history)
            for label in ("hand", "tuned"):
                for noise, rec in (("no", result[label]), ("yes", result["noisy"][label])):
                    rows.append(
                        [
                            name,
                            label,
                            noise,
                            np.array2string(np.asarray(rec["theta_final"]), precision=6),
                            rec["theta_settling_time"],
                            float(np.max(rec["theta_relative_error_final"])),
                            rec["x_error_final"],
                            rec["pe_min_eigenvalue"],
                        ]
                    )
            rows.append([name, "held-out speed-up", "yes", "", mc["speedup_median"], "", "", ""])
    headers = [
        "aircraft",
        "observer",
        "noise",
        "theta_final",
        "settling",
        "rel err",
        "x err",
        "pe min eig",
    ]
    (out / "summary.md").write_text(
        "# Zhang adaptive observer\n\n" + markdown_table(headers, rows) + "\n"
        "Held-out speed-up: median over the Monte Carlo runs of hand / tuned settling time.\n"
    )
    write_json(out / "summary.json", summary)
    return summary
