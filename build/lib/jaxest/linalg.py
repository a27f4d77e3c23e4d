"""Small linear-algebra pieces shared by the estimators.

The eigen/SVD factorisation P = U diag(D)^2 U^T is not unique when eigenvalues repeat (P0 = c I,
isotropic Q), and ``jnp.linalg.svd``'s derivative divides by differences of singular values, so it
is NaN there. Estimators whose outputs depend on P only through U D^2 U^T are differentiated at the
covariance level instead: :func:`factor_psd` and :func:`cov_tangent_to_factor` choose, for a
covariance tangent dP, the factor tangent dU = 1/2 dP U D^-2, dD = 0, which reproduces dP exactly
(dU D^2 U^T + U D^2 dU^T = dP) and is finite whatever the multiplicities (NOTES.md section 1).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def symmetrize(P):
    """(P + P^T) / 2 over the last two axes."""
    return 0.5 * (P + jnp.swapaxes(P, -1, -2))


def cov_from_factor(U, D):
    """P = U diag(D)^2 U^T."""
    return (U * D**2) @ U.T


def factor_tangent_to_cov(U, D, dU, dD):
    """The covariance tangent dP of P = U D^2 U^T for factor tangents (dU, dD)."""
    half = (dU * D**2) @ U.T + (U * (D * dD)) @ U.T
    return half + half.T


def cov_tangent_to_factor(U, D, dP):
    """A factor tangent (dU, dD) whose covariance tangent is ``dP`` (see module docstring)."""
    return 0.5 * dP @ (U / D**2), jnp.zeros_like(D)


@jax.custom_jvp
def factor_psd(P):
    """U, D with P = U diag(D)^2 U^T (U orthogonal, D >= 0 descending) by a symmetric SVD."""
    w, U = jnp.linalg.eigh(symmetrize(P))
    return U[:, ::-1], jnp.sqrt(jnp.clip(w[::-1], 0.0))


@factor_psd.defjvp
def _factor_psd_jvp(primals, tangents):
    (P,), (dP,) = primals, tangents
    U, D = factor_psd(P)
    return (U, D), cov_tangent_to_factor(U, D, symmetrize(dP))


def right_svd(A):
    """Singular values s and right singular vectors V of a tall A, so A^T A = V diag(s)^2 V^T."""
    _, s, Vt = jnp.linalg.svd(A, full_matrices=False)
    return s, Vt.T


def cho_solve_lower(L, B):
    """Solve (L L^T) X = B for lower-triangular L."""
    Z = jax.scipy.linalg.solve_triangular(L, B, lower=True)
    return jax.scipy.linalg.solve_triangular(L.T, Z, lower=False)


def chol_inverse(L):
    """(L L^T)^-1, symmetric, from the lower-triangular factor L."""
    return symmetrize(cho_solve_lower(L, jnp.eye(L.shape[-1], dtype=L.dtype)))


def inv_spd(P):
    """Inverse of a symmetric positive definite matrix through its Cholesky factor."""
    return chol_inverse(jnp.linalg.cholesky(P))


def logdet_chol(L):
    """ln det (L L^T) from the lower-triangular factor L (positive diagonal)."""
    return 2.0 * jnp.sum(jnp.log(jnp.diag(L)))


#: largest m * k * n for which :func:`mm` multiplies by broadcasting instead of a dot
SMALL_MATMUL = 512


def mm(a, b):
    """Matrix product ``a @ b`` (last two axes), fast for the small matrices filters use.

    XLA's CPU dot has a fixed cost per call that dominates for, say, 4 x 4 matrices inside a
    ``scan`` (measured 4-10x slower than a fused multiply-and-sum); above ``SMALL_MATMUL``
    multiply-adds the ordinary dot is used.
    """
    m, k, n = a.shape[-2], a.shape[-1], b.shape[-1]
    if m * k * n > SMALL_MATMUL:
        return a @ b
    return jnp.sum(a[..., :, :, None] * b[..., None, :, :], axis=-2)


def sandwich(A, P):
    """A P A^T."""
    return mm(mm(A, P), jnp.swapaxes(A, -1, -2))
