"""jaxest against dynamax in one process, on the same problems (issue: core, acceptance).

Problems: ``linear_4x2`` and ``linear_6x3`` (n = 4, m = 2 and n = 6, m = 3 random stable
systems) and ``duffing_ekf`` (the Duffing map of docs/papers/smf.md with Gaussian noise), T = 1000,
against dynamax; ``duffing_smf``, the set-membership filter of docs/papers/smf.md on the Duffing
protocol (T = 100 steps per run, bounded noise), against the plain NumPy loop of
benchmarks/smf.py (dynamax has no set-membership filter): its rows carry ``reference`` and their
``dynamax_us_per_step`` column holds the NumPy loop's time. Modes: one sequence, and 200 runs with
a different process covariance (SMF: process bound) per run, under ``jax.vmap`` ("vmap200") and
with jaxest under :func:`jaxest.vmap_minor`, the runs on the minor axis ("minor200"; the
reference stays under ``jax.vmap``). Passes: forward
(log-likelihood and filtered means; SMF: log volume of the last set and the centres) and
``value_and_grad`` of that scalar with respect to the Q (bound) scale. The NumPy loop has no
gradient: the SMF's value_and_grad rows compare with its forward loop.
Per-step time = wall time / (runs * T), best of several repeats after compilation.

    python benchmarks/speed.py --json out.json
"""

from __future__ import annotations

import argparse
import functools
import importlib.util
import json
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

import jaxest as je  # noqa: E402
from jaxest import batching  # noqa: E402
from jaxest.filters import KalmanFilter  # noqa: E402
from jaxest.linalg import cholesky, logdet_chol  # noqa: E402
from jaxest.report import device_name, emit_json, timed  # noqa: E402
from jaxest.setmembership.smf import BoundedNoiseModel, SetMembershipFilter  # noqa: E402
from jaxest.studies import smf_fdi  # noqa: E402
from jaxest.systems import duffing  # noqa: E402
from jaxest.systems.duffing import Duffing  # noqa: E402

T, RUNS = 1000, 200
#: runs of the NumPy SMF loop timed for the per-step time of its vmap rows (a loop: the per-step
#: time does not depend on how many)
NUMPY_RUNS = 20


def linear_model(n=4, m=2):
    """A random stable n-state / m-measurement model (seed 0) and its prior; for m = 2 the
    fixed R of the first benchmark, a random SPD one otherwise."""
    rng = np.random.default_rng(0)
    F = 0.95 * np.linalg.qr(rng.normal(size=(n, n)))[0]
    H = rng.normal(size=(m, n))
    A = rng.normal(size=(n, n))
    Q = A @ A.T / n + 0.1 * np.eye(n)
    if m == 2:
        R = np.array([[0.5, 0.1], [0.1, 0.3]])
    else:
        B = rng.normal(size=(m, m))
        R = B @ B.T / m + 0.2 * np.eye(m)
    model = je.LinearGaussian(*(jnp.asarray(a) for a in (F, H, Q, R)))
    return model, je.Gaussian(jnp.zeros(n), jnp.eye(n))


def scaled_q_run(estimator, model, prior, save=None):
    """(q_scale, ys) -> (log-likelihood, filtered means) of ``estimator`` on ``model`` with its
    Q scaled (benchmarks/vmap_minor.py runs every Gaussian filter so)."""

    def run(q_scale, ys):
        scaled = je.LinearGaussian(model.F, model.H, q_scale * model.Q, model.R)
        result = je.run(estimator, scaled, ys, prior=prior, save=save)
        return result.loglik, result.mean

    return run


def linear_problem(n=4, m=2):
    model, prior = linear_model(n, m)
    jaxest_loglik = scaled_q_run(KalmanFilter(), model, prior)

    from dynamax.linear_gaussian_ssm import LinearGaussianSSM, lgssm_filter

    params, _ = LinearGaussianSSM(n, m).initialize(
        jax.random.PRNGKey(0),
        initial_mean=prior.mean, initial_covariance=prior.cov,
        dynamics_weights=model.F, dynamics_covariance=model.Q,
        emission_weights=model.H, emission_covariance=model.R,
    )  # fmt: skip

    def dynamax_loglik(q_scale, ys):
        p = params._replace(dynamics=params.dynamics._replace(cov=q_scale * model.Q))
        post = lgssm_filter(p, ys)
        return post.marginal_loglik, post.filtered_means

    return model, prior, jaxest_loglik, dynamax_loglik


def duffing_problem():
    f = Duffing()
    h = lambda x, u=None: x
    Q, R = 1e-5 * jnp.eye(2), 1e-4 * jnp.eye(2)
    model = je.NonlinearGaussian(f, h, Q, R)
    prior = je.Gaussian(jnp.asarray([0.2, 0.3]), 0.01 * jnp.eye(2))

    def jaxest_loglik(q_scale, ys):
        mdl = je.NonlinearGaussian(f, h, q_scale * Q, R)
        res = je.run(KalmanFilter(), mdl, ys, prior=prior)
        return res.loglik, res.mean

    from dynamax.nonlinear_gaussian_ssm import ParamsNLGSSM, extended_kalman_filter

    def dynamax_loglik(q_scale, ys):
        p = ParamsNLGSSM(prior.mean, prior.cov, lambda x: f(x), q_scale * Q, lambda x: x, R)
        post = extended_kalman_filter(p, ys, output_fields=["filtered_means"])
        return post.marginal_loglik, post.filtered_means

    return model, prior, jaxest_loglik, dynamax_loglik


def smf_problem():
    """The SMF of the set-membership study (closed-form remainder bound) on fault-free Duffing
    data: (w_scale, ys) -> (log volume of the last set, centres), jaxest and the NumPy loop of
    benchmarks/smf.py (the tests' independent reference)."""
    spec = importlib.util.spec_from_file_location("smf_numpy", Path(__file__).with_name("smf.py"))
    numpy_ref = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(numpy_ref)
    model, prior = duffing.model(closed_form_bound=True), smf_fdi.first_prior(True)

    def jaxest_volume(w_scale, ys):
        mdl = BoundedNoiseModel(
            model.f, model.h, w_scale * model.process_bound, model.measurement_bound,
            model.f_remainder,
        )  # fmt: skip
        res = je.run(SetMembershipFilter(), mdl, ys, prior=prior)
        return logdet_chol(cholesky(res.shape[-1])), res.center

    c0, P0 = np.asarray(prior.center), np.asarray(prior.shape)
    w_bar, v_bar = np.asarray(model.process_bound), np.asarray(model.measurement_bound)

    def numpy_volume(w_scale, ys):
        centres, shapes, _ = numpy_ref.numpy_smf(np.asarray(ys), c0, P0, w_scale * w_bar, v_bar)
        return np.linalg.slogdet(shapes[-1])[1], centres

    return jaxest_volume, numpy_volume


def _runs(measurements, runs):
    """``measurements(key)`` of ``runs`` keys (seed 1) and a noise scale per run, 0.5 to 2."""
    keys = jax.random.split(jax.random.PRNGKey(1), runs)
    return jax.vmap(measurements)(keys), jnp.linspace(0.5, 2.0, runs)


def gaussian_data(model, prior, runs, steps):
    """The measurements of ``runs`` simulated sequences and a Q scale per run."""
    return _runs(lambda k: je.simulate(model, prior, steps, k).y, runs)


def smf_data(runs):
    """The measurements of ``runs`` fault-free runs of the smf-fdi study's protocol and a
    process-bound scale per run."""
    return _runs(lambda k: smf_fdi.simulate_run(k, None)[1], runs)


def jaxest_case(problem, runs=RUNS, steps=T):
    """jaxest's function of a problem, ``(scale, ys) -> outputs``, with the data and scales
    its rows are timed on (benchmarks/profile_step.py profiles it)."""
    if problem == "duffing_smf":
        return smf_problem()[0], *smf_data(runs)
    model, prior, ours, _ = GAUSSIAN_PROBLEMS[problem]()
    return ours, *gaussian_data(model, prior, runs, steps)


def passes(loglik):
    """forward and value_and_grad versions of a (q_scale, ys) -> (loglik, means) function."""
    value_and_grad = jax.value_and_grad(lambda q, ys: loglik(q, ys)[0])
    return {"forward": loglik, "value_and_grad": value_and_grad}


def numpy_seconds(fn, scales, ys, repeats: int = 3) -> float:
    """Best of ``repeats`` wall times of the NumPy loop over the runs (scales[i], ys[i])."""
    best = math.inf
    for _ in range(repeats):
        start = time.perf_counter()
        for q, y in zip(scales, ys, strict=True):
            fn(q, y)
        best = min(best, time.perf_counter() - start)
    return best


def dynamax_rows(name, build, args):
    """The rows of one problem against dynamax (same data, same modes and passes)."""
    model, prior, ours, theirs = build()
    ys, scales = gaussian_data(model, prior, args.runs, args.steps)
    a, b = ours(1.0, ys[0])[0], theirs(1.0, ys[0])[0]
    if not np.isclose(a, b, rtol=1e-6):  # Joseph vs plain update differ in rounding
        raise RuntimeError(f"{name}: the two libraries disagree ({a} vs {b}): not the same problem")
    rows = []
    for mode in modes(ys, scales):
        for pass_name in ("forward", "value_and_grad"):
            c_ours, t_ours, _ = mode.timed(passes(ours)[pass_name])
            _, t_theirs, _ = timed(mode.reference_wrap(passes(theirs)[pass_name]), mode.args)
            rows.append(
                row(name, mode.name, pass_name, t_ours / mode.steps, t_theirs / mode.steps, c_ours)
            )
    return rows


class Mode(NamedTuple):
    """How a row runs: ``wrap`` batches jaxest's function, ``reference_wrap`` the reference's,
    on ``args``, ``steps`` time steps per call; jaxest's program is compiled with
    ``compiler_options``."""

    name: str
    wrap: Callable
    reference_wrap: Callable
    args: tuple
    steps: int
    compiler_options: dict | None = None

    def timed(self, fn, repeats: int = 5):
        """:func:`jaxest.report.timed` of jaxest's ``fn`` batched and compiled as this mode
        runs it."""
        return timed(self.wrap(fn), self.args, repeats, self.compiler_options)


def modes(ys, scales) -> list[Mode]:
    """One sequence at scale 1, and every run of ``ys`` (runs, T, m) with its own scale under
    ``jax.vmap`` and with jaxest under ``je.vmap_minor`` (the reference under ``jax.vmap``).
    ``vmap_minor``'s compiler options are passed to ``timed``: its jit, which compiles the
    function here, does not pass on those of a jit nested in it."""
    runs, steps = ys.shape[:2]
    single = lambda fn: fn
    return [
        Mode("single", single, single, (jnp.asarray(1.0), ys[0]), steps),
        Mode("vmap200", jax.vmap, jax.vmap, (scales, ys), steps * runs),
        Mode(
            "minor200", je.vmap_minor, jax.vmap, (scales, ys), steps * runs,
            batching.COMPILER_OPTIONS,
        ),
    ]  # fmt: skip


def smf_rows(args):
    """The SMF rows: jaxest (single run, and vmap over runs) against the NumPy loop."""
    ours, numpy_volume = smf_problem()
    ys, scales = smf_data(args.runs)
    steps = ys.shape[1]
    a, b = ours(1.0, ys[0])[0], numpy_volume(1.0, ys[0])[0]
    if not np.isclose(a, b, rtol=1e-9):
        raise RuntimeError(f"duffing_smf: jaxest and the NumPy loop disagree ({a} vs {b})")
    ys_np, scales_np = np.asarray(ys), np.asarray(scales)
    t_numpy = {
        "single": numpy_seconds(numpy_volume, [1.0], ys_np[:1]) / steps,
        "vmap200": numpy_seconds(numpy_volume, scales_np[:NUMPY_RUNS], ys_np[:NUMPY_RUNS])
        / (NUMPY_RUNS * steps),
    }
    t_numpy["minor200"] = t_numpy["vmap200"]
    rows = []
    for mode in modes(ys, scales):
        for pass_name in ("forward", "value_and_grad"):
            c_ours, t_ours, _ = mode.timed(passes(ours)[pass_name])
            per_step = t_ours / mode.steps
            rows.append(
                row("duffing_smf", mode.name, pass_name, per_step, t_numpy[mode.name], c_ours)
            )
            rows[-1]["reference"] = "numpy loop (benchmarks/smf.py), forward only"
    return rows


def row(problem, mode, pass_name, ours_s, theirs_s, compile_s):
    """One output row from per-step seconds."""
    result = {
        "problem": problem,
        "mode": mode,
        "pass": pass_name,
        "jaxest_us_per_step": 1e6 * ours_s,
        "dynamax_us_per_step": 1e6 * theirs_s,
        "ratio": ours_s / theirs_s,
        "jaxest_compile_s": compile_s,
    }
    print(json.dumps(result), flush=True)
    return result


#: the problems with a dynamax reference, by name
GAUSSIAN_PROBLEMS = {
    "linear_4x2": linear_problem,
    "linear_6x3": lambda: linear_problem(6, 3),
    "duffing_ekf": duffing_problem,
}
PROBLEMS = {
    **{
        name: functools.partial(dynamax_rows, name, build)
        for name, build in GAUSSIAN_PROBLEMS.items()
    },
    "duffing_smf": smf_rows,
}


def main(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--json", help="write the results here as well as to stdout")
    parser.add_argument("--steps", type=int, default=T, help="time steps per run (default 1000)")
    parser.add_argument("--runs", type=int, default=RUNS, help="runs under vmap (default 200)")
    parser.add_argument(
        "--problems", nargs="+", choices=list(PROBLEMS), default=list(PROBLEMS),
        help="which problems (default: all)",
    )  # fmt: skip
    args = parser.parse_args(argv)
    rows = []
    for name in args.problems:
        rows += PROBLEMS[name](args)
    forward = {
        (r["problem"], r["mode"]): r["jaxest_us_per_step"] for r in rows if r["pass"] == "forward"
    }
    for r in rows:
        if r["pass"] == "value_and_grad":
            r["grad_over_forward"] = r["jaxest_us_per_step"] / forward[(r["problem"], r["mode"])]
    emit_json({"device": device_name(), "rows": rows}, args.json)


if __name__ == "__main__":
    main()
