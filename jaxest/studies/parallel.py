"""Parallel-in-time filtering and smoothing, and EM against gradient fitting (issue 14, part 3).

1. Speed (:func:`timing`): sequential (``KalmanFilter`` + ``rts_smooth``) against parallel
   (``ParallelKalmanFilter`` + ``rts_smooth(parallel=True)``, square-root and standard forms)
   filter+smoother on a random stable n-state model with m = 2 measurements, float64 and
   float32: compile time, wall time per run (best of a few after compiling) and the relative
   log-likelihood difference from the float64 sequential filter, over the grid :data:`GRID`
   (T = 10^2 .. 10^5, n = 4 and 20, float64 and float32; ``--quick``: :data:`QUICK_GRID`),
   with a figure (``speed.png``) and the CPU crossover (the smallest T at which a parallel form
   beats the sequential one, if any) in the summary. ``benchmarks/parallel.py`` runs the same
   grid (:func:`speed_grid`) without the EM part.
2. EM against gradient fitting on a simulated 4-state model (T = 1000): ``je.fit_em`` and
   ``je.fit`` (L-BFGS on the negative log-likelihood of F, H, Q, R with Q, R in Cholesky
   parametrisation) from the same start: iterations, wall time (including compilation), final
   log-likelihood, and the recovered similarity invariants (eigenvalues of F, innovation
   covariance) against the truth, with standard errors by the delta method from the observed
   information at the better of the two fits (the maximum-likelihood estimate: the information
   is not positive semidefinite at a point short of the maximum).
"""

from __future__ import annotations

import functools
import itertools
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.flatten_util import ravel_pytree

import jaxest as je
from jaxest.plot import save, subplots
from jaxest.progress import Progress
from jaxest.report import device_name, markdown_table, timed, write_json

DESCRIPTION = "parallel-in-time Kalman filter/smoother speed and accuracy; EM vs gradient fitting"
#: its tables report wall times (the speed grid, EM against gradient fitting)
TIMED = True

METHODS = {
    "sequential": (je.KalmanFilter(), False),
    "parallel_sqrt": (je.ParallelKalmanFilter(), True),
    "parallel_standard": (je.ParallelKalmanFilter(square_root=False), True),
}


def random_model(n: int, m: int = 2, seed: int = 0, dtype=jnp.float64):
    """A random stable n-state model (spectral radius 0.95) with m measurements, and a prior."""
    rng = np.random.default_rng(seed)
    F = 0.95 * np.linalg.qr(rng.normal(size=(n, n)))[0]
    H = rng.normal(size=(m, n))
    A = rng.normal(size=(n, n))
    Q = A @ A.T / n + 0.1 * np.eye(n)
    R = 0.5 * np.eye(m)
    model = je.LinearGaussian(*(jnp.asarray(a, dtype) for a in (F, H, Q, R)))
    return model, je.Gaussian(jnp.zeros(n, dtype), jnp.eye(n, dtype=dtype))


def _filter_smoother(filt, parallel: bool):
    @jax.jit
    def fn(model, prior, ys):
        res = je.run(filt, model, ys, prior=prior)
        smoothed = je.rts_smooth(model, res, parallel=parallel)
        return res.loglik, res.any_status, smoothed.mean, smoothed.cov

    return fn


@functools.lru_cache(maxsize=4)
def _problem(n: int, T: int):
    """:func:`random_model`'s float64 model and prior, T measurements simulated from them and
    the sequential filter's log-likelihood: simulated once for the dtypes and methods timed."""
    model, prior = random_model(n)
    ys = je.simulate(model, prior, T, jax.random.PRNGKey(n)).y
    reference = je.run(je.KalmanFilter(), model, ys, prior=prior, save=je.SaveAt(fields=()))
    return model, prior, ys, float(reference.loglik)


def timing(n: int, T: int, dtype, repeats: int = 3, methods=tuple(METHODS)) -> list[dict]:
    """Compile and run time of filter+smoother for each of ``methods`` (keys of
    :data:`METHODS`), its log-likelihood's relative difference from the float64 sequential
    filter's, and the filter's status flags."""
    model64, prior64, ys, reference = _problem(n, T)
    args = je.astype((model64, prior64, ys), dtype)
    rows = []
    for name in methods:
        filt, parallel = METHODS[name]
        compile_s, run_s, (loglik, status, mean, cov) = timed(
            _filter_smoother(filt, parallel), args, repeats
        )
        finite = bool(jnp.all(jnp.isfinite(mean)) & jnp.all(jnp.isfinite(cov)))
        rel = abs(float(loglik) / reference - 1.0)
        rows.append({
            "n": n, "T": T, "dtype": jnp.dtype(dtype).name, "method": name,
            "compile_s": compile_s, "run_s": run_s, "finite": finite,
            "loglik_rel_diff": rel if np.isfinite(rel) else None,
            "status": je.ParallelStatus.describe(status),  # the core's bits and the parallel one
        })  # fmt: skip
    return rows


#: the speed grid: states, sequence lengths, dtypes
GRID = {"states": (4, 20), "lengths": (100, 1_000, 10_000, 100_000),
        "dtypes": ("float64", "float32")}  # fmt: skip
QUICK_GRID = {"states": (4,), "lengths": (100, 1_000), "dtypes": ("float64", "float32")}


def _configurations(states, lengths, dtypes):
    """(n, T, dtype, repeats) of the grid in the order measured: best of 3 runs after a warm-up
    run; at T >= 10^5 the single first run after compiling, which takes up to 45 s on a 2-core
    CPU."""
    for n, T, dtype in itertools.product(states, lengths, dtypes):
        yield n, T, dtype, 0 if T >= 100_000 else 3


def expected_seconds(n: int, T: int, repeats: int) -> float:
    """A guess at one grid point's seconds on a 2-core CPU, the progress display's weight:
    about 4 s compiling the three programs, then 1 + ``repeats`` runs of the three forms at about
    30 us per time step for n = 4, growing as n^1.5. Fitted to the published run (2026-11-29;
    grid points of 3.5-9 s at n = 4 and 4.4-44 s at n = 20, the last at T = 10^5)."""
    return 4.0 + (1 + repeats) * T * 3e-5 * (n / 4) ** 1.5


def grid_weights(grid: dict) -> list[float]:
    """:func:`expected_seconds` of each (n, T, dtype) configuration of ``grid``, in order."""
    return [expected_seconds(n, T, repeats) for n, T, _, repeats in _configurations(**grid)]


def speed_rows(states, lengths, dtypes):
    """:func:`timing` over the grid, one (label, rows) per (n, T, dtype) as it is measured."""
    for n, T, dtype, repeats in _configurations(states, lengths, dtypes):
        yield f"n={n} T={T} {dtype}", timing(n, T, jnp.dtype(dtype), repeats)


def speed_grid(states, lengths, dtypes, progress: Progress | None = None) -> list[dict]:
    """:func:`speed_rows` as one list."""
    rows = []
    for label, new in speed_rows(states, lengths, dtypes):
        rows += new
        if progress is not None:
            progress.advance(label)
    return rows


def over_sequential(rows: list[dict]) -> list[float]:
    """Each row's run time over the sequential filter+smoother's at the same n, T and dtype."""
    sequential = {(r["n"], r["T"], r["dtype"]): r["run_s"] for r in rows
                  if r["method"] == "sequential"}  # fmt: skip
    return [r["run_s"] / sequential[r["n"], r["T"], r["dtype"]] for r in rows]


def crossover(rows: list[dict]) -> list[dict]:
    """For each n, dtype and parallel method: the smallest T at which it ran faster than the
    sequential filter+smoother (``None``: at no T of the grid) and the range of its time over
    the sequential one's."""
    ratio_of = over_sequential(rows)
    out = []
    for n, dtype, method in dict.fromkeys((r["n"], r["dtype"], r["method"]) for r in rows):
        if method == "sequential":
            continue
        ratios = {r["T"]: ratio for r, ratio in zip(rows, ratio_of, strict=True)
                  if (r["n"], r["dtype"], r["method"]) == (n, dtype, method)}  # fmt: skip
        faster = [T for T, ratio in sorted(ratios.items()) if ratio < 1]
        out.append({"n": n, "dtype": dtype, "method": method,
                    "crossover_T": faster[0] if faster else None,
                    "min_ratio": min(ratios.values()), "max_ratio": max(ratios.values())})  # fmt: skip
    return out


def speed_figure(rows: list[dict], path: Path) -> Path:
    """Wall time per run (solid) and compile time (dashed) against T, log-log: a panel per n
    and dtype, a line per method."""
    states = sorted({r["n"] for r in rows})
    dtypes = list(dict.fromkeys(r["dtype"] for r in rows))
    fig, axes = subplots(len(states), len(dtypes), width=4.6, height=3.4)
    for i, n in enumerate(states):
        for j, dtype in enumerate(dtypes):
            ax = axes[i, j]
            for k, method in enumerate(METHODS):
                mine = sorted((r["T"], r["run_s"], r["compile_s"]) for r in rows
                              if (r["n"], r["dtype"], r["method"]) == (n, dtype, method))  # fmt: skip
                T, run_s, compile_s = (np.array(c) for c in zip(*mine, strict=True))
                ax.plot(T, run_s, "o-", color=f"C{k}", label=f"{method} run")
                ax.plot(T, compile_s, "x--", color=f"C{k}", alpha=0.6, label=f"{method} compile")
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlabel("T (steps)")
            ax.set_ylabel("seconds")
            ax.set_title(f"filter + smoother, n = {n}, {dtype}")
            ax.grid(True, which="major", alpha=0.3)
    axes[0, 0].legend(fontsize=7)
    return save(fig, path)


def _crossover_text(rows: list[dict], device: str) -> str:
    lines = []
    for c in crossover(rows):
        where = (f"faster from T = {c['crossover_T']}" if c["crossover_T"] is not None
                 else "slower than the sequential scan at every T")  # fmt: skip
        lines.append(f"- n = {c['n']}, {c['dtype']}, {c['method']}: {where} "
                     f"({c['min_ratio']:.1f}-{c['max_ratio']:.1f} times its run time)")  # fmt: skip
    return (
        f"Crossover on {device} (run time of the parallel filter + smoother over the "
        "sequential one's; a CPU with 2 cores has little to run in parallel, so the "
        "parallel forms are expected to be slower there):\n\n" + "\n".join(lines)
    )


# --- EM against gradient fitting ----------------------------------------------------------


#: optax's L-BFGS (zoom line search): in 200 steps optimistix's backtracking L-BFGS stops far short
#: on this fit of F and H, flat along similarity transforms (docs/performance.md)
GRADIENT_FIT_OPTIMIZER = optax.lbfgs()
#: the EM-against-gradient part's seconds in the published run, the progress display's weight
EM_SECONDS = 14.0
EM_TRUE_F = np.array([[0.9, 0.2, 0, 0], [-0.2, 0.9, 0, 0], [0, 0, 0.6, 0.3], [0, 0, 0, -0.5]])


def em_problem(T: int, seed: int):
    rng = np.random.default_rng(seed)
    H = rng.normal(size=(2, 4))
    truth = je.LinearGaussian(*map(jnp.asarray, (EM_TRUE_F, H, 0.1 * np.eye(4), 0.2 * np.eye(2))))
    prior = je.Gaussian(jnp.zeros(4), jnp.eye(4))
    ys = je.simulate(truth, prior, T, jax.random.PRNGKey(seed)).y
    A0 = rng.normal(size=(4, 4))
    start = je.LinearGaussian(
        jnp.asarray(0.8 * A0 / np.max(np.abs(np.linalg.eigvals(A0)))),
        jnp.asarray(rng.normal(size=(2, 4))), 0.5 * jnp.eye(4), jnp.eye(2),
    )  # fmt: skip
    return truth, prior, ys, start


@jax.jit
def _innovation_cov(model):
    return je.steady_state_gain(model).innovation_cov


def _innovation_invariants(model) -> np.ndarray:
    """Similarity invariants: eigenvalues of F (sorted by real, then imaginary part, as real and
    imaginary parts) and the steady-state innovation covariance (upper triangle)."""
    eig = np.sort_complex(np.linalg.eigvals(np.asarray(model.F)))
    S = np.asarray(_innovation_cov(model))
    return np.concatenate([eig.real, eig.imag, S[np.triu_indices(S.shape[0])]])


def _free(model):
    chol = jnp.linalg.cholesky
    return (model.F, model.H, chol(model.Q), chol(model.R))


def _model(theta):
    F, H, Lq, Lr = theta
    Lq, Lr = jnp.tril(Lq), jnp.tril(Lr)
    return je.LinearGaussian(F, H, Lq @ Lq.T, Lr @ Lr.T)


def standard_errors(model, prior, ys, step: float = 1e-6) -> np.ndarray:
    """Standard errors of the invariants at ``model`` by the delta method: the inverse observed
    information of the log-likelihood in (F, H, Lq, Lr), pseudo-inverted (the similarity
    directions are flat), mapped through the invariants' Jacobian (central differences)."""
    flat0, unravel = ravel_pytree(_free(model))
    loglik = lambda flat: je.run(je.KalmanFilter(), _model(unravel(flat)), ys, prior=prior).loglik
    info = -np.asarray(jax.jit(jax.hessian(loglik))(flat0))
    cov = np.linalg.pinv(info, rcond=1e-8, hermitian=True)
    invariants = lambda flat: _innovation_invariants(_model(unravel(jnp.asarray(flat))))
    base = np.asarray(flat0)
    J = np.stack([(invariants(base + step * e) - invariants(base - step * e)) / (2 * step)
                  for e in np.eye(base.size)], axis=1)  # fmt: skip
    return np.sqrt(np.clip(np.diag(J @ cov @ J.T), 0.0, None))


def em_versus_gradient(
    T: int, em_iters: int, grad_steps: int, seed: int, optimizer=GRADIENT_FIT_OPTIMIZER
) -> dict:
    truth, prior, ys, start = em_problem(T, seed)
    truth_loglik = float(je.run(je.KalmanFilter(), truth, ys, prior=prior).loglik)
    t0 = time.perf_counter()
    em = je.fit_em(start, ys, prior=prior, num_iters=em_iters, fixed=("prior.mean", "prior.cov"))
    em_model = jax.block_until_ready(em.model)
    em_s = time.perf_counter() - t0
    em_loglik = float(je.run(je.KalmanFilter(), em_model, ys, prior=prior).loglik)

    # gradient fitting of the same parameters (L-BFGS on minus the log-likelihood)
    loss = lambda model: -je.run(je.KalmanFilter(), model, ys, prior=prior).loglik
    params = {"F": "unconstrained", "H": "unconstrained", "Q": "cholesky", "R": "cholesky"}
    t0 = time.perf_counter()
    fitted = je.fit(start, loss, params, optimizer=optimizer, num_steps=grad_steps)
    grad_model, losses = jax.block_until_ready((fitted.model, fitted.losses))
    grad_s = time.perf_counter() - t0
    grad_loglik = float(je.run(je.KalmanFilter(), grad_model, ys, prior=prior).loglik)

    best = em_model if em_loglik > grad_loglik else grad_model
    se = standard_errors(best, prior, ys)
    rows = []
    names = ["Re eig1", "Re eig2", "Re eig3", "Re eig4", "Im eig1", "Im eig2", "Im eig3",
             "Im eig4", "S11", "S12", "S22"]  # fmt: skip
    values = {k: np.asarray(_innovation_invariants(m)) for k, m in
              (("truth", truth), ("em", em_model), ("gradient", grad_model))}  # fmt: skip
    for i, name in enumerate(names):
        rows.append({"invariant": name, "truth": float(values["truth"][i]),
                     "em": float(values["em"][i]), "gradient": float(values["gradient"][i]),
                     "se": float(se[i])})  # fmt: skip
    return {
        "T": T,
        "truth_loglik": truth_loglik,
        "em": {"iterations": em_iters, "wall_s": em_s, "loglik": em_loglik,
               "status": je.EMStatus.describe(em.any_status)},
        "gradient": {"iterations": grad_steps, "wall_s": grad_s, "loglik": grad_loglik,
                     "finite": bool(np.all(np.isfinite(np.asarray(losses))))},
        "invariants": rows,
    }  # fmt: skip


def run(out: Path, *, runs: int | None, seed: int, quick: bool, options: dict) -> dict:
    out_dir = Path(out) / "parallel"
    grid = QUICK_GRID if quick else GRID
    weights = [*grid_weights(grid), EM_SECONDS]
    with Progress("parallel", weights=weights) as progress:
        start = time.perf_counter()
        speed = speed_grid(**grid, progress=progress)
        speed_s = time.perf_counter() - start
        em = em_versus_gradient(500 if quick else 1000, 100 if quick else 500,
                                50 if quick else 200, seed)  # fmt: skip
        progress.advance("EM vs gradient")
    speed_table = markdown_table(
        ["n", "T", "dtype", "method", "compile s", "run ms", "× sequential", "finite",
         "rel. loglik diff", "status"],
        [[r["n"], r["T"], r["dtype"], r["method"], f"{r['compile_s']:.1f}",
          f"{1e3 * r['run_s']:.2f}", f"{ratio:.1f}",
          r["finite"], "nan" if r["loglik_rel_diff"] is None else f"{r['loglik_rel_diff']:.1e}",
          r["status"]]
         for r, ratio in zip(speed, over_sequential(speed), strict=True)],
    )  # fmt: skip
    fit_table = markdown_table(
        ["method", "iterations", "wall s", "final loglik"],
        [["truth", "", "", f"{em['truth_loglik']:.2f}"]]
        + [[k, em[k]["iterations"], f"{em[k]['wall_s']:.1f}", f"{em[k]['loglik']:.2f}"]
           for k in ("em", "gradient")],
    )  # fmt: skip
    invariant_table = markdown_table(
        ["invariant", "truth", "EM", "gradient", "s.e."],
        [[r["invariant"], f"{r['truth']:.3f}", f"{r['em']:.3f}", f"{r['gradient']:.3f}",
          f"{r['se']:.3f}"] for r in em["invariants"]],
    )  # fmt: skip
    device = device_name()
    summary = {"device": device, "speed": speed, "speed_wall_s": speed_s,
               "crossover": crossover(speed), "em_vs_gradient": em}  # fmt: skip
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json(out_dir / "summary.json", summary)
    speed_figure(speed, out_dir / "speed.png")
    (out_dir / "summary.md").write_text(
        f"# Parallel-in-time filtering and EM ({device})\n\n"
        f"## Filter + RTS smoother\n\n{speed_table}\n\n"
        f"(wall time per run: best of 3 after compiling and a warm-up run; at T = 10^5 the first "
        f"run after compiling; the speed grid took "
        f"{speed_s:.0f} s in all.) ![speed](speed.png)\n\n{_crossover_text(speed, device)}\n\n"
        f"## EM against gradient fitting (T = {em['T']})\n\n{fit_table}\n\n{invariant_table}\n"
    )
    return summary
