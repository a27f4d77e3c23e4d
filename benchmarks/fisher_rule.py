"""The Kalman filter's closed-form gradient (jaxest.filters.fisher) against float64 autodiff where
the noise is far below the state's uncertainty.

A 2-state constant-velocity model with a position sensor, prior P0 = I, T = 200 simulated steps
(Q = 1e-2 I, R = 0.1); the gradient of log p(y) in F, H, Q and R at Q = q I, R = r for a grid of
(q, r), by the closed form and by autodiff through the filter (``closed_form_gradient=False``),
each in float32 and float64, against float64 autodiff. Per row: the largest error over a
matrix's entries relative to that matrix's largest reference gradient entry.

    python benchmarks/fisher_rule.py [--steps 200] [--json out.json]
"""

from __future__ import annotations

import argparse

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import jaxest as je
from jaxest.report import emit_json

#: (q, r): the noise scales, from the state's prior variance (1) down
SCALES = [(1e-2, 1e-1), (1e-4, 1e-1), (1e-6, 1e-1), (1e-12, 1e-1), (1e-2, 1e-5), (1e-2, 1e-7)]
FILTERS = {
    "closed_form": je.KalmanFilter(),
    "autodiff": je.KalmanFilter(closed_form_gradient=False),
}
MATRICES = ("F", "H", "Q", "R")


def gradients(filt, model, prior, ys, dtype):
    """d log p(y) / d(F, H, Q, R) at every (q, r) of ``SCALES`` in ``dtype``."""
    cast = lambda tree: jax.tree.map(lambda a: jnp.asarray(a, dtype), tree)
    model, prior, ys = cast((model, prior, ys))

    def one(scale):
        scaled = eqx.tree_at(lambda m: (m.Q, m.R), model, (scale[0] * model.Q, scale[1] * model.R))
        loglik = lambda m: je.run(filt, m, ys, prior=prior).loglik
        grads = jax.grad(loglik)(scaled)
        return [getattr(grads, name) for name in MATRICES]

    return jax.jit(jax.vmap(one))(cast(jnp.asarray(SCALES)))


def main(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--json", help="write the results here as well as to stdout")
    args = parser.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    F, H = jnp.array([[1.0, 0.1], [0.0, 1.0]]), jnp.array([[1.0, 0.0]])
    prior = je.Gaussian(jnp.zeros(2), jnp.eye(2))
    model = je.LinearGaussian(F, H, jnp.eye(2), jnp.eye(1))  # scaled per row
    truth = je.LinearGaussian(F, H, 1e-2 * jnp.eye(2), jnp.array([[0.1]]))
    ys = je.simulate(truth, prior, args.steps, jax.random.key(1)).y
    reference = gradients(FILTERS["autodiff"], model, prior, ys, jnp.float64)
    rows = []
    for name, filt in FILTERS.items():
        for dtype in (jnp.float32, jnp.float64):
            got = gradients(filt, model, prior, ys, dtype)
            for i, (q, r) in enumerate(SCALES):
                errors = {}
                for matrix, g, want in zip(MATRICES, got, reference, strict=True):
                    scale = np.max(np.abs(np.asarray(want[i])))
                    error = np.max(np.abs(np.asarray(g[i], np.float64) - np.asarray(want[i])))
                    errors[f"{matrix}_relative_error"] = float(error / scale)
                rows.append(
                    {"gradient": name, "dtype": jnp.dtype(dtype).name, "q": q, "r": r, **errors}
                )
    emit_json({"steps": args.steps, "rows": rows}, args.json)


if __name__ == "__main__":
    main()
