"""Study "wiener": the example of §4 of Sun & Cui (2003), the fixed-interval Wiener smoother.

1. The steady-state quantities of eq 25's system: Sigma, K, the eigenvalues of Psi_f, the ARMA
   innovation model (eqs 26-28), compared with the printed numbers.
2. One realisation (N = 300): the Wiener smoother from the paper's arbitrary start
   x(0|N) = x(1|N) = [10, 20], from the eq-13 start (x(1|N) chosen) and from the optimal start;
   delta(t) against the optimal (eq 15) smoother, its settling time, decay rate and the bound of
   eq 20 (figs 1-4 of the paper and a delta(t) figure).
3. Monte Carlo (``runs`` realisations under ``vmap``, x(0) ~ N(0, I)): empirical smoothing error
   of the Wiener smoother (three starts, and the theorem as printed), the steady-state smoother
   (eq 15) and the RTS smoother.
"""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxest._priors import Gaussian
from jaxest.models import simulate
from jaxest.progress import Progress
from jaxest.report import markdown_table, write_json
from jaxest.smoothers.steady_state import steady_state_smooth
from jaxest.smoothers.wiener import WienerSmoother
from jaxest.systems.wiener_example import ARBITRARY_START, PAPER, PRINTED_ADJ_K, N, paper_model

DESCRIPTION = (
    "Fixed-interval Wiener smoother (Sun & Cui 2003): ARMA model, 3 starts, Monte Carlo vs RTS"
)
NAME = "wiener"
SETTLING_FRACTION = (
    1e-3  # |delta(t)| stays below this fraction of |delta(0)| of the arbitrary start
)


def settling_step(delta_norm: np.ndarray, threshold: float) -> int:
    """First t after which |delta(t)| stays below ``threshold``."""
    above = np.nonzero(delta_norm >= threshold)[0]
    return 0 if above.size == 0 else int(above[-1] + 1)


def decay_rate(delta_norm: np.ndarray, start: int) -> float | None:
    """Geometric mean of |delta(t+1)| / |delta(t)| from ``start`` to the last t where |delta| is
    still 1e-9 of its size at ``start`` (above rounding)."""
    alive = np.nonzero(delta_norm > 1e-9 * delta_norm[start])[0]
    end = int(alive[-1])
    if end <= start:
        return None
    return float((delta_norm[end] / delta_norm[start]) ** (1.0 / (end - start)))


def eq20_bound(delta: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """|delta_i(t)| <= n_d c_lambda lambda_m^t (eq 20), with c_j^(i) fitted to delta(0..n_d-1)
    through eq 21 (all eigenvalues) and lambda_m the largest |lambda_j| whose c_j is not zero."""
    n_d = lam.shape[0]
    V = np.vander(lam, n_d, increasing=True).T  # rows t = 0..n_d-1, columns lambda_j^t
    c = np.linalg.solve(V, delta[:n_d])  # (n_d, n): c_j^(i)
    c_lambda = np.max(np.abs(c))
    active = np.max(np.abs(c), axis=1) > 1e-9 * max(c_lambda, 1e-300)
    lam_m = np.max(np.abs(lam[active])) if active.any() else 0.0
    return n_d * c_lambda * lam_m ** np.arange(delta.shape[0])


def single_realisation(smoother: WienerSmoother, key, model):
    sim = simulate(model, jnp.zeros(2), N + 1, key)
    ys = sim.y
    optimal, final = smoother.optimal_start(ys, jnp.zeros(2))
    arbitrary = jnp.asarray(ARBITRARY_START)
    chosen = smoother.eq13_initial_values(arbitrary, optimal)
    starts = {"arbitrary": arbitrary, "eq13": chosen, "optimal": optimal}
    paths = {name: np.asarray(smoother.smooth(ys, x0, final)) for name, x0 in starts.items()}
    printed = np.asarray(smoother.smooth(ys, optimal, None))  # the theorem as printed (no end term)
    return np.asarray(sim.states), ys, starts, paths, printed


def monte_carlo(smoother: WienerSmoother, model, runs: int, key):
    """Mean squared error per smoother over ``runs`` realisations, x(0) ~ N(0, I)."""
    from jaxest._run import run as run_filter
    from jaxest.filters.kalman import KalmanFilter
    from jaxest.smoothers.rts import rts_smooth

    prior = Gaussian(jnp.zeros(2), jnp.eye(2))
    arbitrary = jnp.asarray(ARBITRARY_START)

    def one(k):
        sim = simulate(model, prior, N + 1, k)
        ys = sim.y
        steady = steady_state_smooth(model, ys, prior=prior, gain=smoother.gain)  # eq 15
        optimal, final = smoother.start_from(steady)
        rts = rts_smooth(model, run_filter(KalmanFilter(), model, ys, prior=prior))
        estimates = {
            "rts": rts.mean,
            "steady_state": steady.mean,
            "wiener_optimal": smoother.smooth(ys, optimal, final),
            "wiener_eq13": smoother.smooth(
                ys, smoother.eq13_initial_values(arbitrary, optimal), final
            ),
            "wiener_arbitrary": smoother.smooth(ys, arbitrary, final),
            "wiener_as_printed": smoother.smooth(ys, optimal, None),
        }
        errors = {name: (x - sim.states) ** 2 for name, x in estimates.items()}
        return errors, jnp.trace(rts.cov, axis1=-2, axis2=-1)

    keys = jax.random.split(key, runs)
    errors, rts_trace = jax.jit(jax.vmap(one))(keys)
    return {name: np.asarray(jnp.mean(e, axis=0)) for name, e in errors.items()}, np.asarray(
        rts_trace.mean(0)
    )


def _figures(directory: Path, states, paths, deltas, bounds, lam):
    from jaxest.plot import plt, save

    t = np.arange(states.shape[0])
    files = []
    for i in range(2):  # figs 1-2: arbitrary and eq-13 starts; figs 3-4: optimal start
        for fig_no, names in ((1 + i, ("arbitrary", "eq13")), (3 + i, ("optimal",))):
            fig, ax = plt.subplots(figsize=(7, 3.2))
            ax.plot(t, states[:, i], "k-", lw=1.0, label=f"x{i + 1}(t)")
            styles = {"arbitrary": ":", "eq13": "--", "optimal": ":"}
            for name in names:
                ax.plot(
                    t,
                    paths[name][:, i],
                    styles[name],
                    lw=1.2,
                    label=f"x{i + 1}(t|{N}), {name} start",
                )
            ax.set_xlabel("t")
            ax.set_title(f"Fig. {fig_no}: x{i + 1}(t) and the fixed-interval Wiener smoother")
            ax.legend(fontsize=8)
            name = f"fig{fig_no}_x{i + 1}.png"
            save(fig, directory / name, dpi=120)
            files.append(name)
    fig, ax = plt.subplots(figsize=(7, 3.6))
    horizon = 120
    for name, style in (("arbitrary", "C0"), ("eq13", "C1"), ("optimal", "C2")):
        ax.semilogy(
            t[:horizon],
            np.linalg.norm(deltas[name], axis=1)[:horizon] + 1e-300,
            color=style,
            label=f"|delta(t)|, {name}",
        )
        if name in bounds:
            ax.semilogy(
                t[:horizon],
                bounds[name][:horizon],
                color=style,
                ls="--",
                lw=0.8,
                label=f"eq-20 bound, {name}",
            )
    ax.set_ylim(1e-16, 1e3)
    ax.set_xlabel("t")
    ax.set_title(f"delta(t) = x(t|N) - x°(t|N); eigenvalues {lam[0]:.4f}, {lam[1]:.4f}")
    ax.legend(fontsize=7, ncol=2)
    save(fig, directory / "delta.png", dpi=120)
    return [*files, "delta.png"]


def run(out: Path, *, runs: int | None, seed: int, quick: bool, options: dict) -> dict:
    directory = Path(out) / NAME
    directory.mkdir(parents=True, exist_ok=True)
    runs = runs if runs is not None else (50 if quick else 500)
    model = paper_model()
    key_single, key_mc = jax.random.split(jax.random.key(seed))
    with Progress(NAME, total=3) as progress:
        smoother = WienerSmoother.from_model(model)
        gain, arma = smoother.gain, smoother.arma
        lam = np.asarray(smoother.eigenvalues())
        if np.any(lam.imag != 0):
            raise ValueError("the example's Psi_f should have real eigenvalues")
        lam = lam.real
        adj_K = np.einsum("jab,b->ja", np.asarray(arma.adj), np.asarray(gain.K[:, 0]))
        progress.advance("steady-state quantities")

        states, ys, starts, paths, printed = single_realisation(smoother, key_single, model)
        reference = paths["optimal"]
        steady = np.asarray(
            steady_state_smooth(model, ys, prior=Gaussian(jnp.zeros(2), jnp.eye(2))).mean
        )
        deltas = {name: path - reference for name, path in paths.items()}
        size0 = float(np.linalg.norm(deltas["arbitrary"][0]))
        threshold = SETTLING_FRACTION * size0
        norms = {name: np.linalg.norm(d, axis=1) for name, d in deltas.items()}
        settling = {name: settling_step(v, threshold) for name, v in norms.items()}
        rates = {
            "arbitrary": decay_rate(norms["arbitrary"], 10),
            "eq13": decay_rate(norms["eq13"], 0),
        }
        bounds = {name: eq20_bound(deltas[name], lam) for name in ("arbitrary", "eq13")}
        bound_ratio = {  # where the bound is above rounding level
            name: float(np.max((np.abs(deltas[name]).max(axis=1) / b)[b > 1e-12 * b[0]]))
            for name, b in bounds.items()
        }
        printed_error = np.max(np.abs(printed - steady), axis=1)
        figures = _figures(directory, states, paths, deltas, bounds, lam)
        progress.advance("single realisation")

        mse_paths, rts_trace = monte_carlo(smoother, model, runs, key_mc)
        mc_mse = {name: float(v.mean()) for name, v in mse_paths.items()}
        skip = 50
        mc_mse_after = {name: float(v[skip:].mean()) for name, v in mse_paths.items()}
        progress.advance(f"Monte Carlo, {runs} runs")

    computed = {
        "Sigma": np.asarray(gain.Sigma),
        "K": np.asarray(gain.K[:, 0]),
        "eigenvalues": lam,
        "ar_coeffs": np.asarray(arma.ar[:, 0, 0]),
        "ma_coeffs": np.asarray(arma.ma),
        "smoother_transition": np.asarray(gain.smoother_transition),
        "innovation_gain": np.asarray(gain.innovation_gain[:, 0]),
    }
    matches = {
        k: bool(np.allclose(np.round(v, 4), PAPER[k], atol=1e-12)) for k, v in computed.items()
    }
    summary = {
        **computed,
        "innovation_variance": float(gain.innovation_cov[0, 0]),
        "adj_K": adj_K,
        "adj_K_printed": PRINTED_ADJ_K,
        "paper": PAPER,
        "matches_paper_to_4_decimals": matches,
        "x0_chosen": np.asarray(starts["eq13"][0]),
        "x1_chosen": np.asarray(starts["eq13"][1]),
        "x_optimal_initial": np.asarray(starts["optimal"]),
        "settling_steps": settling,
        "settling_threshold": threshold,
        "decay_rate": rates,
        "eq20_max_ratio_delta_to_bound": bound_ratio,
        "max_abs_wiener_optimal_minus_eq15": float(np.max(np.abs(reference - steady))),
        "theorem_as_printed_error": {
            "max_over_interval": float(printed_error.max()),
            "at_t_N": float(printed_error[-1]),
            "max_over_t_le_N_minus_100": float(printed_error[: N - 99].max()),
        },
        "mc_runs": runs,
        "mc_mse": mc_mse,
        f"mc_mse_t_ge_{skip}": mc_mse_after,
        "rts_mean_trace_cov_per_state": float(rts_trace.mean() / 2),
        "N": N,
        "seed": seed,
        "figures": figures,
    }
    write_json(directory / "summary.json", summary)
    tables = [
        "# Wiener smoother study (Sun & Cui 2003, §4)\n",
        markdown_table(
            ["quantity", "computed", "paper", "matches"],
            [[k, np.round(v, 6).tolist(), str(PAPER[k]), matches[k]] for k, v in computed.items()],
        ),
        f"\nadj(I - q^-1 Psi_f) K: q^0 {np.round(adj_K[0], 4).tolist()}, q^-1 {np.round(adj_K[1], 4).tolist()} "
        f"(printed q^-1: {PRINTED_ADJ_K[1]}, the adjugate with flipped off-diagonal signs)\n\n",
        markdown_table(
            [
                "start",
                "x(0|N)",
                "x(1|N)",
                "settling steps",
                "decay rate",
                "max |delta| / eq-20 bound",
            ],
            [
                [
                    name,
                    np.round(np.asarray(starts[name][0]), 4).tolist(),
                    np.round(np.asarray(starts[name][1]), 4).tolist(),
                    settling[name],
                    "-" if rates.get(name) is None else f"{rates[name]:.4f}",
                    f"{bound_ratio[name]:.3g}" if name in bound_ratio else "-",
                ]
                for name in ("arbitrary", "eq13", "optimal")
            ],
        ),
        f"\nMonte Carlo, {runs} runs, x(0) ~ N(0, I): mean squared error per state component\n\n",
        markdown_table(
            ["smoother", "MSE, t = 0..N", f"MSE, t = {skip}..N"],
            [[name, mc_mse[name], mc_mse_after[name]] for name in mc_mse],
        ),
    ]
    (directory / "tables.md").write_text("".join(tables))
    return summary
