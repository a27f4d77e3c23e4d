"""The ill-conditioned measurement update of Dyer & McReynolds / Grewal & Andrews (docs/papers/svd_ekf.md).

P0 = I3, H = [[1, 1, 1], [1, 1, 1 + d]], R = d^2 I2, one update. As d -> 0 the conventional
Kalman filter's P+ = P - K S K^T loses all accuracy near d = 1e-8 in float64.

Two measures of a filter's P+: its relative (Frobenius) error, which the largest entries
dominate, and its variance along the direction the two measurements pin down, where P+'s
smallest eigenvalue, of order d^2, lies (:func:`smallest_variance_ratio`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

import jaxest as je

__all__ = [
    "exact_posterior",
    "posterior",
    "posterior_error",
    "problem",
    "relative_error",
    "smallest_variance",
    "smallest_variance_ratio",
]


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


def smallest_variance(d: float, dtype=jnp.float64) -> tuple[float, np.ndarray]:
    """The smallest eigenvalue of P+ and its unit eigenvector, for the test as ``dtype`` holds
    it (1 + d rounded; float32 holds 1 + 1e-8 as 1). With P0 = I, P+^-1 = I + H^T R^-1 H, whose
    largest eigenvalue, of order 6 / d^2 and far from the others (1 and about 4/3), float64
    resolves to its last digits from H and R however small d is; P+'s smallest eigenvalue is its
    inverse, with the same eigenvector."""
    model, _, _ = problem(d, dtype)
    H, R = (np.asarray(a, np.float64) for a in (model.H, model.R))
    eigenvalues, vectors = np.linalg.eigh(np.eye(3) + H.T @ np.linalg.solve(R, H))
    return float(1.0 / eigenvalues[-1]), vectors[:, -1]


def posterior(Filter, d: float, dtype=jnp.float64):
    """The filter's result of the test's one update in ``dtype``, with P+, the factor of P+ it
    keeps (if any) and its status saved."""
    model, prior, ys = problem(d, dtype)
    return je.run(Filter(), model, ys, prior=prior, save=je.SaveAt(("cov", "factor", "status")))


def relative_error(result, d: float) -> float:
    """Relative (Frobenius) error of a :func:`posterior`'s P+ against the closed form (NaN if
    not finite)."""
    P = np.asarray(result.cov[0], np.float64)
    exact = exact_posterior(d)
    return float(np.linalg.norm(P - exact) / np.linalg.norm(exact))


def posterior_error(Filter, d: float, dtype=jnp.float64) -> float:
    """:func:`relative_error` of the filter's P+."""
    return relative_error(posterior(Filter, d, dtype), d)


def smallest_variance_ratio(result, d: float) -> float:
    """v^T P+ v of a :func:`posterior` over the exact smallest eigenvalue, v its eigenvector
    (:func:`smallest_variance`, for the test as the result's dtype holds it): 1 where the filter
    resolves the direction the measurements pin down. Taken in float64 from the square root the
    filter keeps (SVD or Cholesky factor), which resolves variances far below eps ||P+||; from
    P+ itself for the filters that keep P."""
    exact, v = smallest_variance(d, result.cov.dtype)
    if result.factor is None or not result.factor.is_square_root:
        return float(v @ np.asarray(result.cov[0], np.float64) @ v / exact)
    factor = jax.tree.map(lambda a: np.asarray(a[0], np.float64), result.factor)
    return float(np.sum((factor.square_root.T @ v) ** 2) / exact)
