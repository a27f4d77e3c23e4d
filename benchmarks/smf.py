"""Speed of the set-membership study: jaxest (vmap over runs) against a plain NumPy loop.

    python benchmarks/smf.py [--json out.json] [--runs 200] [--numpy-runs 20] [--devices N]

Prints ``{"study_seconds", "study_seconds_one_device", "devices", "compile_seconds",
"jaxest_runs_per_second", "numpy_runs_per_second", "ratio"}``: the whole smf-fdi Monte Carlo
(all L, all filters, the EKF baseline) after compilation, its runs sharded over ``devices`` (on
a CPU one per core unless ``--devices`` says otherwise, as ``reproduce`` runs the study) and on
one device, and the runs per second of one SMF over the Duffing data on one device, jaxest
under ``vmap`` against the straightforward NumPy loop below (same filter, same process). The
NumPy filter is written from docs/papers/smf.md with the printed (unnormalised) eq 36, and the
tests use it as an independent reference.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

T, K0, KD, C = 0.1, 2.1, 3.0, 0.4


def duffing_f(x):
    return np.array([x[0] + T * x[1], x[1] - T * (K0 * x[0] * (1 + KD * x[0] ** 2) + C * x[1])])


def duffing_jacobian(x):
    return np.array([[1.0, T], [-T * K0 * (1 + 3 * KD * x[0] ** 2), 1 - T * C]])


def duffing_remainder(c, P):
    p11 = P[0, 0]
    alpha2 = 3 * T * K0 * KD * (p11 * math.sqrt(p11) + p11 * abs(c[0]))
    return np.array([0.0, alpha2 * (1 + 8 * np.finfo(float).eps)])


def numpy_add_segment(P, s):
    n = P.shape[0]
    a = s @ np.linalg.solve(P, s)
    if a <= 0:
        return P
    p = (-(n - 1) * a + math.sqrt((n - 1) ** 2 * a**2 + 4 * n * a)) / (2 * n)
    P = (1 + p) * P + (1 + 1 / p) * np.outer(s, s)
    return 0.5 * (P + P.T)  # as jaxest: rounding asymmetry would otherwise grow


def numpy_intersect_strip(c, P, h, z, v):
    """Returns (c, P, empty) with eq 36 solved in its printed, unnormalised form."""
    n = P.shape[0]
    g = h @ P @ h
    phi_p = (z - h @ c + v) / math.sqrt(g)
    phi_m = (z - h @ c - v) / math.sqrt(g)
    if phi_p < -1 or phi_m > 1:
        return c, P, True
    phi_p, phi_m = min(phi_p, 1.0), max(phi_m, -1.0)
    if phi_p * phi_m <= -1.0 / n:
        return c, P, False
    e = math.sqrt(g) * (phi_p + phi_m) / 2
    d = math.sqrt(g) * (phi_p - phi_m) / 2
    A = (n - 1) * g**2
    B = g * ((2 * n - 1) * d**2 - g + e**2)
    Cq = d**2 * (n * (d**2 - e**2) - g)
    q = max(np.roots([A, B, Cq]).real)
    s = d**2 + q * g
    Ph = P @ h
    P = (1 + q - q * e**2 / s) * (P - (q / s) * np.outer(Ph, Ph))
    return c + q * e * Ph / s, 0.5 * (P + P.T), False


def numpy_smf(ys, c, P, w_bar, v_bar, mask=(True, True)):
    """The SMF over ys (paper steps 1..N) from the set (c, P) at step 1: (centres, shapes, empty)."""
    centres, shapes, empties = [], [], []
    for y in ys:
        c_pred, P_pred, empty = c, P, False
        for i in range(len(y)):
            if not mask[i]:
                continue
            h = np.eye(len(y))[i]
            c, P, empty_i = numpy_intersect_strip(c, P, h, y[i], v_bar[i])
            empty |= empty_i
        if empty:
            c, P = c_pred, P_pred
        centres.append(c)
        shapes.append(P)
        empties.append(empty)
        F = duffing_jacobian(c)
        widths = w_bar + duffing_remainder(c, P)
        P = F @ P @ F.T
        for i in range(len(c)):
            P = numpy_add_segment(P, widths[i] * np.eye(len(c))[i])
        c = duffing_f(c)
    return np.array(centres), np.array(shapes), np.array(empties)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", type=Path, default=None, help="also write the result here")
    parser.add_argument("--runs", type=int, default=200)
    parser.add_argument("--numpy-runs", type=int, default=20)
    parser.add_argument("--devices", type=int, default=None, help="CPU devices (default: cores)")
    args = parser.parse_args(argv)

    from jaxest import xla_flags

    xla_flags.add(xla_flags.cpu_devices(args.devices))  # before JAX starts its CPU backend

    import jax

    from jaxest.report import best_of, device_name, emit_json

    jax.config.update("jax_enable_x64", True)
    from jaxest.studies import smf_fdi
    from jaxest.systems import duffing

    keys = jax.random.split(jax.random.key(0), args.runs)
    study = smf_fdi.monte_carlo_function(closed_form_bound=True)  # as the study
    sharded = smf_fdi.shard_runs(keys)
    start = time.perf_counter()
    jax.block_until_ready(study(sharded))
    compile_seconds = time.perf_counter() - start
    study_seconds = best_of(lambda: study(sharded), 5)[1]
    one_device = jax.device_put(keys, jax.devices()[0])
    jax.block_until_ready(study(one_device))
    study_seconds_one_device = best_of(lambda: study(one_device), 5)[1]

    one_filter = smf_fdi.single_filter_function(closed_form_bound=True)
    jax.block_until_ready(one_filter(keys))
    jax_seconds = best_of(lambda: one_filter(keys), 5)[1]

    model, prior = (
        duffing.model(closed_form_bound=True),
        smf_fdi.first_prior(closed_form_bound=True),
    )
    # fault-free data, as single_filter_function runs on the jaxest side
    data = [smf_fdi.simulate_run(k, None) for k in keys[: args.numpy_runs]]
    data = [np.asarray(ys) for _, ys in data]
    c0, P0 = np.asarray(prior.center), np.asarray(prior.shape)
    w_bar, v_bar = np.asarray(model.process_bound), np.asarray(model.measurement_bound)
    start = time.perf_counter()
    for ys in data:
        numpy_smf(ys, c0, P0, w_bar, v_bar)
    numpy_seconds = time.perf_counter() - start

    r, r0 = args.runs / jax_seconds, args.numpy_runs / numpy_seconds
    result = {
        "study_seconds": study_seconds,
        "study_seconds_one_device": study_seconds_one_device,
        "devices": len(sharded.sharding.device_set),
        "compile_seconds": compile_seconds,
        "jaxest_runs_per_second": r,
        "numpy_runs_per_second": r0,
        "ratio": r / r0,
        "runs": args.runs,
        "device": device_name(),
    }
    emit_json(result, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
