"""The Riccati solvers' status on random problems: an OK status must mean what it says.

Random control-form problems (``solve_dare``, ``solve_care``) of five kinds, n in {1, 2, 3, 5, 8}
states and m in {1, 2, 3} inputs, in float64 and float32, each solved in one ``jit(vmap(...))``
(so the status, not the eager argument check, is what speaks):

- ``generic``: Gaussian A (spectral radius about 0.5-3), Q = C^T C of random rank, R with a
  condition number up to 1e8, rotated;
- ``near_boundary``: a mode of A within 1e-2 .. 1e-10 of the stability boundary, half the time
  unobservable through Q (no stabilising solution when it sits on the boundary);
- ``uncontrollable_unstable``: an unstable mode of A that B cannot reach (no stabilising
  solution);
- ``scaled``: states scaled by factors 1e-3 .. 1e3;
- ``zero_Q``: Q = 0 (the solution is 0 where A is stable).

Each solution is checked in float64 NumPy on the data as the solver saw them (rounded to its
dtype), against scipy's solution of the same data:

- ``ok``: status OK; ``wrong`` among them: the residual of the given equation, evaluated in
  float64, above 10 sqrt(eps) relative to its terms, or the closed loop not stable, or, where
  the solution is 0 (Q = 0, A stable), an X above 1e-6 (float32) / 1e-12 (float64);
- ``far_from_reference`` among the OK: X's largest entry error relative to scipy's largest
  entry above 10 sqrt(eps), where scipy's solution is accurate (residual < 1e-8, margin > 1e-6):
  an answer the residual could not tell from a right one (an ill-conditioned equation);
- ``flagged``: status not OK; ``false_alarm`` among them: scipy's solution is accurate (residual
  < 1e-8) with a closed-loop margin above 1e-3, and, in float32, the flag is INACCURATE while
  X is within sqrt(eps) / 10 of scipy's (float64) or any flag is raised (float64);
- ``error_p50``, ``error_max``: X's largest entry error relative to scipy's, over the OK
  solutions where scipy's is accurate.

    python benchmarks/riccati_sweep.py --json out.json      # 7-10 minutes on 2 cores
"""

from __future__ import annotations

import argparse
import itertools

import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg as sl

from jaxest.report import emit_json
from jaxest.riccati import RiccatiStatus, solve_care, solve_dare

KINDS = ("generic", "near_boundary", "uncontrollable_unstable", "scaled", "zero_Q")
STATES = (1, 2, 3, 5, 8)
INPUTS = (1, 2, 3)


def _spd(rng, m, condition):
    basis, _ = np.linalg.qr(rng.standard_normal((m, m)))
    return (basis * np.logspace(0, -np.log10(condition), m)) @ basis.T


def _with_eigenvalues(rng, eigenvalues):
    basis = rng.standard_normal((len(eigenvalues),) * 2) + 2 * np.eye(len(eigenvalues))
    return basis @ np.diag(eigenvalues) @ np.linalg.inv(basis), basis


def draw(rng, kind, n, m, discrete):
    """One problem (A, B, Q, R) of ``kind`` (module docstring)."""
    B = rng.standard_normal((n, m))
    C = rng.standard_normal((rng.integers(1, n + 1), n))
    Q = C.T @ C
    R = _spd(rng, m, 10 ** rng.uniform(0, 8))
    if kind == "generic":
        A = rng.standard_normal((n, n)) / np.sqrt(n) * rng.choice([0.5, 1.0, 1.5, 3.0])
        if not discrete:
            A = A - rng.uniform(-1, 1) * np.eye(n)
    elif kind == "near_boundary":
        offset = rng.choice([-1, 1]) * 10 ** -rng.uniform(2, 10)
        others = rng.uniform(-0.9, 0.9, n - 1) if discrete else rng.uniform(-3, 1, n - 1)
        A, basis = _with_eigenvalues(rng, np.r_[(1 if discrete else 0) + offset, others])
        if rng.uniform() < 0.5:  # the mode unobservable through Q
            v = basis[:, 0] / np.linalg.norm(basis[:, 0])
            projection = np.eye(n) - np.outer(v, v)
            Q = projection @ Q @ projection
    elif kind == "uncontrollable_unstable":
        unstable = rng.uniform(1.05, 2) if discrete else rng.uniform(0.05, 1)
        others = rng.uniform(-0.9, 0.9, n - 1) if discrete else rng.uniform(-3, -0.1, n - 1)
        A, basis = _with_eigenvalues(rng, np.r_[unstable, others])
        w = np.linalg.inv(basis)[0]  # the unstable mode's left eigenvector
        B = B - np.outer(w, w @ B) / (w @ w)
    elif kind == "scaled":
        A = rng.standard_normal((n, n)) / np.sqrt(n) - (0 if discrete else 0.5) * np.eye(n)
        scales = 10 ** rng.uniform(-3, 3, n)
        A = scales[:, None] * A / scales[None, :]
        B = scales[:, None] * B
        Q = Q / scales[:, None] / scales[None, :]
    else:  # zero_Q
        A = rng.standard_normal((n, n)) / np.sqrt(n) * 1.5
        Q = np.zeros((n, n))
    return A, B, Q, R


def _stable(A, discrete):
    eigenvalues = np.linalg.eigvals(A)
    return np.abs(eigenvalues).max() < 1 if discrete else eigenvalues.real.max() < 0


def residual_and_margin(A, B, Q, R, X, discrete):
    """The relative residual of the equation at X, in float64, and the closed loop's margin
    (1 - spectral radius, resp. -max Re lambda / max |A_c|)."""
    if not np.all(np.isfinite(X)):
        return np.inf, -np.inf
    if discrete:
        K = np.linalg.solve(R + B.T @ X @ B, B.T @ X @ A)
        terms = (A.T @ X @ A, X, A.T @ X @ B @ K, Q)
        residual = terms[0] - terms[1] - terms[2] + terms[3]
        closed_loop = A - B @ K
        margin = 1 - np.abs(np.linalg.eigvals(closed_loop)).max()
    else:
        K = np.linalg.solve(R, B.T @ X)
        terms = (A.T @ X, X @ A, X @ B @ K, Q)
        residual = terms[0] + terms[1] - terms[2] + terms[3]
        closed_loop = A - B @ K
        margin = -np.linalg.eigvals(closed_loop).real.max() / max(np.abs(closed_loop).max(), 1e-300)
    scale = max(max(np.abs(t).max() for t in terms), 1e-300)
    return np.abs(residual).max() / scale, margin


def sweep_one(rng, discrete, kind, dtype, runs):
    """Counts for one (form, kind, dtype) over every size."""
    counts = dict(ok=0, wrong=0, far_from_reference=0, flagged=0, false_alarm=0, zero_solution=0)
    errors = []
    eps = float(jnp.finfo(dtype).eps)
    solve = jax.jit(jax.vmap(solve_dare if discrete else solve_care))
    reference_solve = sl.solve_discrete_are if discrete else sl.solve_continuous_are
    for n, m in itertools.product(STATES, INPUTS):
        if m > n and kind != "generic":
            continue
        problems = [draw(rng, kind, n, m, discrete) for _ in range(runs)]
        data = [np.stack(arrays).astype(dtype) for arrays in zip(*problems, strict=True)]
        solution = solve(*data)
        for i in range(runs):
            A, B, Q, R = (np.float64(d[i]) for d in data)
            X, status = np.float64(solution.X[i]), int(solution.status[i])
            counts["ok" if status == 0 else "flagged"] += 1
            if not Q.any() and _stable(A, discrete):  # the solution is 0
                counts["zero_solution"] += 1
                counts["wrong"] += status == 0 and np.abs(X).max() > (
                    1e-6 if eps > 1e-10 else 1e-12
                )
                continue
            try:
                reference = reference_solve(A, B, Q, R)
            except (ValueError, np.linalg.LinAlgError):
                reference = None
            reference_residual, reference_margin = (
                residual_and_margin(A, B, Q, R, reference, discrete)
                if reference is not None
                else (np.inf, -np.inf)
            )
            reference_good = reference_residual < 1e-8 and reference_margin > 1e-6
            error = (
                np.abs(X - reference).max() / np.abs(reference).max() if reference_good else np.inf
            )
            if status == 0:
                residual, margin = residual_and_margin(A, B, Q, R, X, discrete)
                counts["wrong"] += not (residual < 10 * np.sqrt(eps) and margin > 0)
                if reference_good:
                    errors.append(error)
                    counts["far_from_reference"] += error > 10 * np.sqrt(eps)
            elif reference_good and reference_margin > 1e-3:
                if eps < 1e-10 or (status & RiccatiStatus.INACCURATE and error < np.sqrt(eps) / 10):
                    counts["false_alarm"] += 1
        jax.clear_caches()
    counts["error_p50"] = float(np.median(errors)) if errors else None
    counts["error_max"] = float(np.max(errors)) if errors else None
    return counts


def main(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--runs", type=int, default=40, help="problems per size and kind")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", help="write the results here as well as to stdout")
    args = parser.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    rng = np.random.default_rng(args.seed)
    rows = []
    for discrete, kind, dtype in itertools.product((True, False), KINDS, (np.float64, np.float32)):
        counts = sweep_one(rng, discrete, kind, dtype, args.runs)
        rows.append(dict(equation="dare" if discrete else "care", kind=kind,
                         dtype=np.dtype(dtype).name, **counts))  # fmt: skip
    emit_json({"runs_per_size": args.runs, "seed": args.seed, "rows": rows}, args.json)


if __name__ == "__main__":
    main()
