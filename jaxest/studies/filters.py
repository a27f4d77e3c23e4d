"""Core filters study: robustness on the ill-conditioned update, and gradient tuning of Q and R.

1. Every Gaussian filter on the Dyer-McReynolds test (docs/papers/svd_ekf.md), float64 and float32:
   relative error of P+ against the closed form for d = 1e-1 ... 1e-16, and P+'s variance along
   the direction the measurements pin down against the exact one.
2. Tuning on the 2-D tracking model (:mod:`jaxest.systems.tracking`): starting from Q x 10 and
   R / 10, fit the log-diagonals of Q and R with L-BFGS by maximum likelihood (through the SVD-EKF) and by
   a supervised loss (filtered-mean error against the known truth), over a batch of runs. The
   tolerance of the ML fit: each fitted log-variance must lie within 3 standard errors of the
   truth, the standard errors from the observed Fisher information (the Hessian of the negative
   log-likelihood at the fit), i.e. what the data can resolve. The supervised loss depends on
   Q and R only through the Kalman gain, which is unchanged when both are scaled together, so
   it cannot recover their scale: it is judged by the RMSE it reaches, measured on fresh runs.
"""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxest as je
from jaxest.filters import EKF, SVDEKF, ImprovedSVDKF, InformationFilter, KalmanFilter, SquareRootKF
from jaxest.montecarlo import monte_carlo
from jaxest.plot import save, subplots
from jaxest.progress import Progress
from jaxest.report import markdown_table, write_json
from jaxest.systems import tracking
from jaxest.systems.ill_conditioned import posterior, relative_error, smallest_variance_ratio
from jaxest.tune import (
    FIXED_STEPS_LBFGS,
    fit,
    log_variance_standard_errors,
    log_variances,
    neg_loglik,
    supervised_mse,
)

DESCRIPTION = "core filters: ill-conditioned robustness of every filter; tuning Q, R by gradient"
FILTERS = {
    "kf": KalmanFilter,
    "ekf": EKF,
    "information": InformationFilter,
    "sqrt_kf": SquareRootKF,
    "svd_ekf": SVDEKF,
    "svd_improved": ImprovedSVDKF,
}
DELTAS = [10.0**-e for e in range(1, 17)]


def robustness() -> list[dict]:
    """For every filter, dtype and d: the relative error of P+ and its variance along the
    direction the measurements pin down over the exact one (None where not finite), and the
    update's status."""
    rows = []
    for name, Filter in FILTERS.items():
        for dtype in (jnp.float64, jnp.float32):
            for d in DELTAS:
                result = posterior(Filter, d, dtype)
                err, ratio = relative_error(result, d), smallest_variance_ratio(result, d)
                rows.append(
                    {
                        "filter": name,
                        "dtype": jnp.dtype(dtype).name,
                        "delta": d,
                        "rel_error": err if np.isfinite(err) else None,
                        "smallest_variance_ratio": ratio if np.isfinite(ratio) else None,
                        "status": result.flags.describe(result.status[0]),
                    }
                )
    return rows


def rmse(model, ys, states, prior) -> float:
    means = jax.vmap(lambda y: je.run(SVDEKF(), model, y, prior=prior).mean)(ys)
    return float(jnp.sqrt(jnp.mean((means - states) ** 2)))


def tuning(
    runs: int,
    num_steps: int,
    seed: int,
    fit_steps: int,
    optimizer=FIXED_STEPS_LBFGS,
) -> dict:
    """Fit Q, R from a 10x wrong start by ML and by supervised loss; compare with the truth.
    ``fit_steps`` L-BFGS steps reach what 3000 Adam steps do; optimistix's compiles the
    gradient once (docs/performance.md)."""
    truth, prior = tracking.model(), tracking.prior()
    simulate = lambda key: je.simulate(truth, prior, num_steps, key)
    train = monte_carlo(simulate, jax.random.PRNGKey(seed), runs)
    test = monte_carlo(simulate, jax.random.PRNGKey(seed + 1), runs)
    wrong = je.LinearGaussian(truth.F, truth.H, 10.0 * truth.Q, truth.R / 10.0)
    params = {"Q": "log_diagonal", "R": "log_diagonal"}
    fits = {
        "ml": fit(
            wrong,
            neg_loglik(SVDEKF(), train.y, prior=prior),
            params,
            optimizer=optimizer,
            num_steps=fit_steps,
        ),
        "supervised": fit(
            wrong,
            supervised_mse(SVDEKF(), train.y, train.states, prior=prior),
            params,
            optimizer=optimizer,
            num_steps=fit_steps,
        ),
    }
    out = {
        "runs": runs,
        "steps": num_steps,
        "true": {"Q_diag": np.diag(truth.Q), "R_diag": np.diag(truth.R)},
        "start": {"Q_diag": np.diag(wrong.Q), "R_diag": np.diag(wrong.R)},
        "rmse": {
            "true": rmse(truth, test.y, test.states, prior),
            "start": rmse(wrong, test.y, test.states, prior),
        },
    }
    for name, result in fits.items():
        out[name] = {
            "Q_diag": np.diag(result.model.Q),
            "R_diag": np.diag(result.model.R),
            "loss_first": float(result.losses[0]),
            "loss_last": float(result.losses[-1]),
            "losses": np.asarray(result.losses),
        }
        out["rmse"][name] = rmse(result.model, test.y, test.states, prior)
    ml = fits["ml"].model
    count = train.y.shape[0] * train.y.shape[1]
    se = log_variance_standard_errors(ml, neg_loglik(KalmanFilter(), train.y, prior=prior), count)
    out["ml"]["standard_errors"] = se
    out["ml"]["z_scores"] = np.asarray(log_variances(ml) - log_variances(truth)) / se
    return out


def _robustness_figure(rows, path: Path):
    fig, axes = subplots(1, 2, width=5.5, height=4.0, sharey=True)
    for ax, dtype in zip(axes[0], ("float64", "float32"), strict=True):
        for name in FILTERS:
            pts = [
                (r["delta"], r["rel_error"])
                for r in rows
                if r["filter"] == name and r["dtype"] == dtype
            ]
            d, e = zip(*[(d, np.nan if e is None else max(e, 1e-17)) for d, e in pts], strict=True)
            ax.loglog(d, e, marker="o", ms=3, label=name)
        ax.invert_xaxis()
        ax.set_xlabel("d")
        ax.set_title(f"P+ relative error, {dtype} (gaps: NaN)")
        ax.grid(True, which="major", alpha=0.3)
    axes[0, 0].set_ylabel("||P+ - P_exact|| / ||P_exact||")
    axes[0, 0].legend(fontsize=8)
    save(fig, path)


def _tuning_figure(result, path: Path):
    fig, axes = subplots(1, 2, width=5.5, height=3.8)
    for name in ("ml", "supervised"):
        losses = np.asarray(result[name]["losses"])
        axes[0, 0].plot((losses - losses.min()) / (losses[0] - losses.min()), label=name)
    axes[0, 0].set_yscale("log")
    axes[0, 0].set_xlabel("optimiser step")
    axes[0, 0].set_ylabel("normalised loss")
    axes[0, 0].legend()
    labels = ["Q11", "Q22", "Q33", "Q44", "R11", "R22"]
    x = np.arange(6)
    true = np.concatenate([result["true"]["Q_diag"], result["true"]["R_diag"]])
    ml = np.concatenate([result["ml"]["Q_diag"], result["ml"]["R_diag"]]) / true
    se = np.asarray(result["ml"]["standard_errors"])
    # +-3 s.e. of the log-variance as a factor; one the data do not resolve (a quick run's
    # Q11: s.e. ~10^3) ends 10^6 times from the estimate, past the axis, instead of overflowing
    factor = np.exp(np.minimum(3 * se, np.log(1e6)))
    band = [ml - ml / factor, ml * factor - ml]
    axes[0, 1].errorbar(x - 0.15, ml, yerr=band, fmt="o", label="ml (±3 s.e.)")
    sup = np.concatenate([result["supervised"]["Q_diag"], result["supervised"]["R_diag"]]) / true
    axes[0, 1].plot(x + 0.15, sup, "s", label="supervised (scale not identifiable)")
    start = np.concatenate([result["start"]["Q_diag"], result["start"]["R_diag"]]) / true
    axes[0, 1].plot(x, start, "kx", label="start")
    axes[0, 1].axhline(1.0, color="gray", lw=0.8)
    axes[0, 1].set_yscale("log")
    axes[0, 1].set_xticks(x, labels)
    axes[0, 1].set_ylabel("fitted / true")
    axes[0, 1].legend(fontsize=8)
    save(fig, path)


def run(out: Path, *, runs: int | None, seed: int, quick: bool, options: dict) -> dict:
    out_dir = Path(out) / "filters"
    runs = runs or (8 if quick else 20)
    with Progress("filters", total=3) as progress:
        rows = robustness()
        progress.advance("robustness")
        tuned = tuning(runs, 150 if quick else 400, seed, 60)
        progress.advance("tuning")
        _robustness_figure(rows, out_dir / "robustness.png")
        _tuning_figure(tuned, out_dir / "tuning.png")
        at = {(r["filter"], r["dtype"], r["delta"]): r["rel_error"] for r in rows}
        table = markdown_table(
            ["filter", "dtype", *[f"{d:.0e}" for d in DELTAS[::3]]],
            [
                [
                    f,
                    dt,
                    *[
                        "NaN" if at[(f, dt, d)] is None else f"{at[(f, dt, d)]:.1e}"
                        for d in DELTAS[::3]
                    ],
                ]
                for f in FILTERS
                for dt in ("float64", "float32")
            ],
        )
        tune_rows = []
        for name in ("ml", "supervised"):
            r = tuned[name]
            tune_rows.append(
                [
                    name,
                    *[f"{v:.3g}" for v in r["Q_diag"]],
                    *[f"{v:.3g}" for v in r["R_diag"]],
                    f"{np.max(np.abs(r['z_scores'])):.2f}" if "z_scores" in r else "n/a",
                    f"{tuned['rmse'][name]:.4f}",
                ]
            )
        tune_rows.insert(
            0,
            [
                "true",
                *tuned["true"]["Q_diag"],
                *tuned["true"]["R_diag"],
                "0",
                f"{tuned['rmse']['true']:.4f}",
            ],
        )
        tune_rows.insert(
            1,
            [
                "start (10x wrong)",
                *tuned["start"]["Q_diag"],
                *tuned["start"]["R_diag"],
                "",
                f"{tuned['rmse']['start']:.4f}",
            ],
        )
        tune_table = markdown_table(
            ["fit", "Q11", "Q22", "Q33", "Q44", "R11", "R22", "max abs z", "test RMSE"], tune_rows
        )
        (out_dir / "tables.md").write_text(
            "## Ill-conditioned update: relative error of P+\n\n"
            + table
            + "\n## Tuning Q, R from a 10x wrong start\n\n"
            + tune_table
        )
        summary = {"robustness": rows, "tuning": {k: v for k, v in tuned.items()}}
        for name in ("ml", "supervised"):
            summary["tuning"][name] = {k: v for k, v in tuned[name].items() if k != "losses"}
        write_json(out_dir / "summary.json", summary)
        progress.advance("written")
    return summary
