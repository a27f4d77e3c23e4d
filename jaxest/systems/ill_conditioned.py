"""The ill-conditioned measurement update of Dyer & McReynolds / Grewal & Andrews (docs/papers/svd_ekf.md).

P0 = I3, H = [[1, 1, 1], [1, 1, 1 + d]], R = d^2 I2, one update. As d -> 0 the conventional
Kalman filter's P+ = P - K S K^T loses all accuracy near d = 1e-8 in float64.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

import jaxest as je

__all__ = ["exact_posterior", "problem", "posterior_error"]


def exact_posterior(d: float) -> np.ndarray:
    """Closed form of P+, evaluated in extended precision."""
    d = np.longdouble(d)
    a, b = 5 + 2 * d * (1 + d), -2 - d
    P = np.array([[a, -3, b], [-3, a, b], [b, b, 4 + d**2]], dtype=np.longdouble)
    return (P / (8 + 2 * d * (1 + d))).astype(np.float64)


def problem(d: float, dtype=jnp.float64):
    """(model, prior, ys) of the test in ``dtype``: one zero measurement. P+ of that one update
    does not depend on Q; Q = I (not 0) lets every filter, those that factor Q too, predict."""
    H = jnp.asarray([[1.0, 1.0, 1.0], [1.0, 1.0, 1.0 + d]], dtype)
    R = jnp.asarray(d, dtype) ** 2 * jnp.eye(2, dtype=dtype)
    model = je.LinearGaussian(jnp.eye(3, dtype=dtype), H, jnp.eye(3, dtype=dtype), R)
    return (
        model,
        je.Gaussian(jnp.zeros(3, dtype), jnp.eye(3, dtype=dtype)),
        jnp.zeros((1, 2), dtype),
    )


def posterior_error(Filter, d: float, dtype=jnp.float64) -> float:
    """Relative (Frobenius) error of the filter's P+ against the closed form (NaN if not finite)."""
    model, prior, ys = problem(d, dtype)
    P = np.asarray(je.run(Filter(), model, ys, prior=prior).cov[0], np.float64)
    exact = exact_posterior(d)
    return float(np.linalg.norm(P - exact) / np.linalg.norm(exact))
