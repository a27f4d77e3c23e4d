"""Outward rounding of the ellipsoid operations: bounds on their rounding error, and the
inflation that turns a computed ellipsoid into one guaranteed to hold the exact result.

Every operation the filter's guarantee rests on (the linear map and Minkowski sum of the time
update, the strip intersection of the measurement update) computes an ellipsoid E(c^, P^) that
differs from the exact result E(c, P) of the same formulas by rounding. Each returns, besides
(c^, P^), element-wise bounds |c^ - c| <= e_c and |P^ - P| <= E_P from the standard model of
floating-point arithmetic (Higham, *Accuracy and Stability of Numerical Algorithms*, 2nd ed.,
§2.2, §3.1, §3.5): every operation is exact up to a factor (1 + delta), |delta| <= u = eps/2, and
a sum or product of k such factors lies within gamma_k = k u / (1 - k u) of 1. Then
(docs/papers/smf.md, outward rounding, eqs O1-O3):

- with D = diag(sqrt(P^_ii)) and C = D^-1 P^ D^-1 (unit diagonal), any v satisfies
  v^T (P - P^) v <= ||D^-1 E_P D^-1||_F ||D v||^2 <= (||D^-1 E_P D^-1||_F / lambda_min(C)) v^T P^ v,
  so P <= (1 + delta) P^ with delta = ||D^-1 E_P D^-1||_F / lambda_min(C)               (O1)
- ||c^ - c||_{P^-1} <= ||D^-1 e_c|| / sqrt(lambda_min(C)) =: epsilon                    (O2)
- hence E(c, P) lies in E(c^, (sqrt(1 + delta) + epsilon)^2 P^)                           (O3)

The scaling by D keeps the bound tied to the set's own shape: an axis-aligned thin set (the
paper's benchmark after a one-sided measurement) keeps its thin axis to a few ulps, and only a
rotated thin set, whose floating-point entries carry its small axis to about cond(C) eps at best,
is inflated by that much. lambda_min(C) is bounded from below rigorously (closed form for n <= 2,
a Cholesky certificate in the manner of Rump (BIT 46, 2006) above), so the only terms left out
are of second order in u (products of two rounding errors, ~1e-32 in float64).

The inflation factor carries no derivative (it is a constant allowance for rounding, and the
certificate is not differentiable).

The standard model holds only where each product is rounded in the working precision. JAX's
default for float32 matrix products is lower on some accelerators (TF32, 10 mantissa bits, on
recent NVIDIA GPUs, where it cost the parallel Kalman filter about two digits:
docs/parallel.md), which would put the rounding error far outside gamma_k and the exact set
outside the computed one. :func:`jaxest.linalg.working_precision` traces the set operations and
the filter step with float32 products in float32, whatever the caller's setting.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from jaxest.linalg import cholesky, inv_spd


def unit_roundoff(dtype) -> float:
    """u = eps / 2, the relative error bound of one correctly rounded operation."""
    return float(jnp.finfo(dtype).eps) / 2


def gamma(k: int, dtype) -> float:
    """gamma_k = k u / (1 - k u): the relative error bound of k rounded operations in a row."""
    u = unit_roundoff(dtype)
    return k * u / (1 - k * u)


def diagonal_scaling(shape: Float[Array, "n n"]):
    """``(d, C, positive)``: d = sqrt(|P_ii|) (1 where that is 0), C = D^-1 P D^-1, D = diag(d),
    the scaling of eqs O1-O2 and O6, and whether every P_ii > 0 (what
    :func:`correlation_floor` needs besides C)."""
    diagonal = jnp.diagonal(shape)
    scale = jnp.sqrt(jnp.abs(diagonal))
    scale = jnp.where(scale > 0, scale, 1.0)
    return scale, shape / scale[:, None] / scale[None, :], jnp.all(diagonal > 0)


def correlation_floor(C: Float[Array, "n n"], positive: Bool[Array, ""]) -> Float[Array, ""]:
    """A rigorous lower bound on lambda_min of C = D^-1 P D^-1 (:func:`diagonal_scaling`); 0 where
    none is proved (``positive``: every P_ii > 0 is false, or too ill-conditioned to certify).

    n = 1: C = 1. n = 2: lambda_min(C) = 1 - |rho|, rho = P_12 / sqrt(P_11 P_22), computed to
    within 4 roundings. n >= 3: mu = 1 / trace(C^-1) <= lambda_min(C) is estimated from a
    Cholesky factor of C, and mu / 2 is certified: a floating-point Cholesky factorisation of
    C - (mu/2 + tau) I that runs to completion with tau >= gamma_{n+1} trace(C) / (1 -
    gamma_{n+1}) + the rounding of forming it proves C - (mu/2) I positive definite (Rump 2006,
    Thm 2.3; trace(C) = n).
    """
    n = C.shape[-1]
    dtype = C.dtype
    if n == 1:
        return jnp.where(positive, 1.0, 0.0).astype(dtype)
    if n == 2:
        floor = 1 - jnp.abs(C[0, 1]) - gamma(6, dtype)
    else:
        eye = jnp.eye(n, dtype=dtype)
        mu = 1 / jnp.trace(inv_spd(C))  # 1 / trace(C^-1) <= lambda_min(C)
        g = gamma(n + 1, dtype)
        tau = g * n / (1 - g) + 4 * unit_roundoff(dtype) * (1 + mu)
        certified = jnp.all(jnp.isfinite(cholesky(C - (0.5 * mu + tau) * eye)))
        floor = jnp.where(certified & jnp.isfinite(mu), 0.5 * mu, 0.0)
    return jax.lax.stop_gradient(jnp.where(positive, jnp.maximum(floor, 0.0), 0.0))


def outward(
    shape: Float[Array, "n n"],
    shape_error: Float[Array, "n n"],
    center_error: Float[Array, " n"] | None = None,
) -> Float[Array, "n n"]:
    """f P^ with the factor f >= 1 of eq O3: E(c, P) lies in E(c^, f P^) for every exact (c, P)
    with |P - P^| <= ``shape_error`` and |c - c^| <= ``center_error`` element-wise. The rounding
    of multiplying P^ by f is included (2 u |P^| more in E_P, and gamma_4 on f). Where
    lambda_min(C) is not certified positive the result is +inf on the diagonal (the whole space:
    the filter then reports the set as lost). Zero error bounds return ``shape`` unchanged."""
    n = shape.shape[-1]
    scale, C, positive = diagonal_scaling(shape)
    floor = correlation_floor(C, positive)
    u = unit_roundoff(shape.dtype)
    scaled = (shape_error + 2 * u * jnp.abs(shape)) / scale[:, None] / scale[None, :]
    certified = floor > 0
    floor = jnp.where(certified, floor, 1.0)
    delta = jnp.sqrt(jnp.sum(scaled**2)) / floor  # eq O1
    epsilon = 0.0
    if center_error is not None:
        epsilon = jnp.linalg.norm(center_error / scale) / jnp.sqrt(floor)  # eq O2
    factor = (jnp.sqrt(1 + delta) + epsilon) ** 2 * (1 + gamma(4, shape.dtype))  # eq O3
    factor = jax.lax.stop_gradient(factor)
    everything = whole_space(n, shape.dtype)
    inflated = jnp.where(certified & jnp.isfinite(factor), factor * shape, everything)
    exact = jnp.all(shape_error == 0)
    if center_error is not None:
        exact = exact & jnp.all(center_error == 0)
    return jnp.where(exact, shape, inflated)  # nothing was rounded: nothing to inflate


def whole_space(n: int, dtype) -> Float[Array, "n n"]:
    """The shape matrix of a set that contains everything: +inf on the diagonal."""
    return jnp.where(jnp.eye(n, dtype=bool), jnp.inf, 0.0).astype(dtype)
