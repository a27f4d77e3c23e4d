"""Network filter: design and run time against N, jaxest vs a plain NumPy/SciPy implementation.

Design: steady state of the covariance ODEs 28-31 with the step-4 gains, jaxest (diffrax Tsit5,
jit) against the same joint ODE written in NumPy (gains by least squares on the constraint) and
integrated by ``scipy.integrate.solve_ivp`` (RK45) to the jaxest settling time; both J values are
reported. Run: the eq 9 filter over sampled data, jaxest (lax.scan, jit) against a NumPy loop.

    PYTHONPATH=. python benchmarks/network.py [--sizes 3 10 30 100] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import numpy as np
import scipy.integrate

jax.config.update("jax_enable_x64", True)

from jaxest import Gaussian, run  # noqa: E402
from jaxest.network import CommunicationStructure, NetworkFilter, steady_state  # noqa: E402
from jaxest.network.structure import block_diag  # noqa: E402
from jaxest.report import best_of, device_name, emit_json  # noqa: E402
from jaxest.systems.chain import initial_prior, mass_chain  # noqa: E402


def numpy_design_rate(system, hears):
    """dP/dt of eqs 28-31 in NumPy, gains by the closed form of step 4 with lstsq-based lemma 2."""
    A, C, F, L, H1, H2, Q, R = (
        np.asarray(getattr(system, m)) for m in ("A", "C", "F", "L", "H1", "H2", "Q", "R")
    )
    N, n, q = A.shape[0], A.shape[-1], H1.shape[1]
    used = hears | np.eye(N, dtype=bool)
    Abar = np.einsum("ij,iab->ijab", np.eye(N), A) + np.einsum(
        "iac,ijcb->ijab", C, L * used[:, :, None, None]
    )
    Hbar = np.einsum("ij,iab->ijab", np.eye(N), H1) + np.einsum(
        "iqc,ijcb->ijqb", H2, L * used[:, :, None, None]
    )
    parts = []
    for i in range(N):  # lemma 2: G = B + Gt phi with phi a basis of the left null space of H2 E
        E = np.concatenate(
            [L[i, j] for j in range(N) if not used[i, j]] or [np.zeros((L.shape[2], 1))], axis=1
        )
        M = H2[i] @ E
        B = C[i] @ E @ np.linalg.pinv(M)
        U, s, _ = np.linalg.svd(M)
        rank = int(np.sum(s > max(M.shape) * np.finfo(float).eps * (s[0] if s.size else 0)))
        parts.append((B, U[:, rank:].T))
    FQF = np.einsum("iap,ipq,ibq->iab", F, Q, F)

    def rate(t, p):
        P = p.reshape(N * n, N * n)
        Pb = P.reshape(N, n, N, n).transpose(0, 2, 1, 3)
        K = np.einsum("ijab,ijcb->iac", Pb, Hbar)
        G = np.zeros((N, n, q))
        for i, (B, phi) in enumerate(parts):
            G[i] = B
            if phi.shape[0]:
                G[i] += (K[i] - B @ R[i]) @ phi.T @ np.linalg.solve(phi @ R[i] @ phi.T, phi)
        Phi = (
            (Abar - np.einsum("iaq,ijqb->ijab", G, Hbar))
            .transpose(0, 2, 1, 3)
            .reshape(N * n, N * n)
        )
        W = np.zeros((N * n, N * n))
        for i in range(N):
            W[i * n : (i + 1) * n, i * n : (i + 1) * n] = FQF[i] + G[i] @ R[i] @ G[i].T
        dP = Phi @ P + P @ Phi.T + W
        return dP.reshape(-1)

    return rate


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[3, 10, 30, 100])
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument(
        "--numpy-max-N", type=int, default=30, help="largest N for the SciPy design"
    )
    parser.add_argument("--json", type=str, default=None)
    args = parser.parse_args()
    dt, rows = 1e-3, []
    for N in args.sizes:
        system = mass_chain(N)
        mean0, cov0 = initial_prior(N)
        structure = CommunicationStructure.chain(N)
        start = time.perf_counter()
        ss = jax.block_until_ready(steady_state(system, structure, cov0))
        first = time.perf_counter() - start
        ss, design_s = best_of(lambda: steady_state(system, structure, cov0), 3)
        row = {
            "N": N,
            "jaxest_design_s": design_s,
            "jaxest_design_first_call_s": first,
            "J": float(ss.J),
        }
        if N <= args.numpy_max_N:
            rate = numpy_design_rate(system, np.asarray(structure.hears))
            P0 = np.asarray(block_diag(cov0))
            start = time.perf_counter()
            sol = scipy.integrate.solve_ivp(
                rate, (0.0, float(ss.settle_time)), P0.reshape(-1), rtol=1e-10, atol=1e-12
            )
            row["scipy_design_s"] = time.perf_counter() - start
            P = sol.y[:, -1].reshape(2 * N, 2 * N)
            row["J_scipy"] = float(np.trace(P))
            row["J_relative_difference"] = abs(row["J_scipy"] - row["J"]) / row["J"]
        ys = jax.random.normal(jax.random.key(0), (args.steps, N, system.obs_dim))
        filt = NetworkFilter(structure, ss.gains, dt)
        runner = jax.jit(lambda ys: run(filt, system, ys, prior=Gaussian(mean0, cov0)).mean)
        means, run_s = best_of(lambda: runner(ys), 3)
        row["jaxest_run_s"] = run_s
        # NumPy loop of the same eq 9 step (innovation form), for speed and agreement
        A, C, L, H1, H2 = (np.asarray(getattr(system, m)) for m in ("A", "C", "L", "H1", "H2"))
        G, used = np.asarray(ss.gains), np.asarray(structure.hears) | np.eye(N, dtype=bool)
        Lu, y_np, x = L * used[:, :, None, None], np.asarray(ys), np.asarray(mean0).copy()
        start = time.perf_counter()
        out = np.empty((args.steps, N, 2))
        for k in range(args.steps):
            out[k] = x
            z = np.einsum("ijhn,jn->ih", Lu, x)
            innov = y_np[k] - np.einsum("iqn,in->iq", H1, x) - np.einsum("iqh,ih->iq", H2, z)
            x = x + dt * (
                np.einsum("iab,ib->ia", A, x)
                + np.einsum("iah,ih->ia", C, z)
                + np.einsum("iaq,iq->ia", G, innov)
            )
        row["numpy_run_s"] = time.perf_counter() - start
        row["run_max_abs_difference"] = float(np.abs(out - np.asarray(means)).max())
        row["run_steps"] = args.steps
        rows.append(row)
        print(json.dumps(row))
    result = {"benchmark": "network", "device": device_name(), "rows": rows}
    emit_json(result, args.json)


if __name__ == "__main__":
    main()
