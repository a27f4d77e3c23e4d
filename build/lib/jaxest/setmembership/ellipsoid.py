"""Ellipsoid operations of the set-membership filter, as pure JAX functions.

E(c, P) = {x : (x - c)^T P^{-1} (x - c) <= 1}. The two operations are the paper's time update
(an outer ellipsoid of the vector sum of an ellipsoid and a segment, eqs 15-17) and measurement
update (an outer ellipsoid of the intersection of an ellipsoid and a strip, eqs 27-36), with the
corrections of NOTES.md §2. Both choose the member of a one-parameter family of outer ellipsoids
with the least volume. They run under ``jit``/``vmap`` and differentiate (square roots and
divisions are guarded so that branches not taken give no NaN gradients).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from jaxest.linalg import symmetrize


class Ellipsoid(eqx.Module):
    """E(center, shape) = {x : (x - center)^T shape^{-1} (x - center) <= 1}; shape is SPD."""

    center: Float[Array, " n"]
    shape: Float[Array, "n n"]


def _safe(condition, value, fallback=1.0):
    """``value`` where ``condition`` else a harmless ``fallback`` (the double-where trick)."""
    return jnp.where(condition, value, fallback)


def add_segment(shape: Float[Array, "n n"], direction: Float[Array, " n"]) -> Float[Array, "n n"]:
    """Shape of the least-volume ellipsoid of the family (1 + p) P + (1 + 1/p) s s^T containing
    E(c, P) + {t s : |t| <= 1} (eqs 16-17; the centre is unchanged).

    p > 0 is the root of n p^2 + (n - 1) a p - a = 0, a = s^T P^{-1} s, computed as
    p = 2a / ((n - 1) a + sqrt((n - 1)^2 a^2 + 4 n a)) (no cancellation; n = 1 gives sqrt(a)).
    A zero segment leaves P unchanged.
    """
    n = shape.shape[-1]
    a = direction @ spd_solve(shape, direction)
    nonzero = a > 0
    a_ = _safe(nonzero, a)
    p = 2 * a_ / ((n - 1) * a_ + jnp.sqrt((n - 1) ** 2 * a_**2 + 4 * n * a_))
    grown = (1 + p) * shape + (1 + 1 / p) * jnp.outer(direction, direction)
    return jnp.where(nonzero, symmetrize(grown), shape)


def add_box(shape: Float[Array, "n n"], half_widths: Float[Array, " n"]) -> Float[Array, "n n"]:
    """Outer ellipsoid of E(c, P) + {w : |w_i| <= half_widths_i}: the box is the sum of the n
    segments half_widths_i e_i, added one at a time (eq 16 for i = 1..n; P_{k|k-1} = P^n)."""
    n = shape.shape[-1]
    for i in range(n):
        shape = add_segment(shape, half_widths[i] * jnp.eye(n, dtype=shape.dtype)[i])
    return shape


def intersect_strip(
    center: Float[Array, " n"],
    shape: Float[Array, "n n"],
    normal: Float[Array, " n"],
    value: Float[Array, ""],
    half_width: Float[Array, ""],
) -> tuple[Float[Array, " n"], Float[Array, "n n"], Bool[Array, ""]]:
    """Outer ellipsoid of E(c, P) ∩ {x : |value - normal^T x| <= half_width} (eqs 27-36).

    With g = h^T P h and phi+- = (z - h^T c +- v) / sqrt(g) (eqs 29-31):

    - the intersection is empty iff phi+ < -1 or phi- > 1; then (c, P) is returned unchanged
      with ``empty = True`` (the caller decides what an inconsistent measurement means);
    - phi+ is clipped to <= 1 and phi- to >= -1 (the strip cut down to the ellipsoid's slab);
    - if phi+ phi- <= -1/n the ellipsoid is already the least-volume member: no update;
    - otherwise, with e = sqrt(g)(phi+ + phi-)/2, d = sqrt(g)(phi+ - phi-)/2 (eq 35) and q > 0
      the root of (n-1) g^2 q^2 + g[(2n-1) d^2 - g + e^2] q + d^2 [n(d^2 - e^2) - g] = 0 (eq 36),
      s = d^2 + q g:  c+ = c + q e P h / s,  P+ = (1 + q - q e^2/s)(P - (q/s) P h h^T P)
      (eqs 32-34). Dividing eq 36 by g^2 shows q depends on phi+- only; it is solved so.
    - n = 1: the exact interval intersection.

    Returns ``(center, shape, empty)``.
    """
    n = shape.shape[-1]
    Ph = shape @ normal
    g = normal @ Ph
    positive = g > 0
    root_g = jnp.sqrt(_safe(positive, g))
    offset = value - normal @ center
    phi_plus = (offset + half_width) / root_g
    phi_minus = (offset - half_width) / root_g
    empty = positive & ((phi_plus < -1) | (phi_minus > 1))
    phi_plus = jnp.minimum(phi_plus, 1.0)
    phi_minus = jnp.maximum(phi_minus, -1.0)
    e = 0.5 * (phi_plus + phi_minus)  # e / sqrt(g), eq 35
    d = 0.5 * (phi_plus - phi_minus)  # d / sqrt(g)
    if n == 1:
        new_center = center + e * root_g * Ph / _safe(positive, g)
        new_shape = d**2 * shape
        update = positive & ~empty
    else:
        update = positive & ~empty & (phi_plus * phi_minus > -1.0 / n)
        A = n - 1.0
        B = (2 * n - 1) * d**2 - 1 + e**2
        C = d**2 * (n * (d**2 - e**2) - 1)  # < 0 exactly when an update is due
        root_disc = jnp.sqrt(_safe(update, B**2 - 4 * A * C))
        q = jnp.where(B >= 0, -2 * C / _safe(update, B + root_disc), (root_disc - B) / (2 * A))
        s = _safe(update, d**2 + q)  # s / g
        new_center = center + (q * e / s / root_g) * Ph
        new_shape = (1 + q - q * e**2 / s) * (
            shape - (q / (s * _safe(positive, g))) * jnp.outer(Ph, Ph)
        )
    return (
        jnp.where(update, new_center, center),
        jnp.where(update, symmetrize(new_shape), shape),
        empty,
    )


def contains(
    center: Float[Array, " n"], shape: Float[Array, "n n"], x: Float[Array, " n"]
) -> Bool[Array, ""]:
    """Whether x lies in E(center, shape)."""
    dx = x - center
    return dx @ spd_solve(shape, dx) <= 1.0


def spd_solve(matrix: Float[Array, "n n"], vector: Float[Array, " n"]) -> Float[Array, " n"]:
    """matrix^{-1} vector; closed form for n <= 2 (XLA's batched LAPACK calls dominate the
    filter's run time on CPU for such small matrices), ``jnp.linalg.solve`` otherwise."""
    n = matrix.shape[-1]
    if n == 1:
        return vector / matrix[0, 0]
    if n == 2:
        (a, b), (c, d) = matrix[0], matrix[1]
        det = a * d - b * c
        return jnp.stack([d * vector[0] - b * vector[1], a * vector[1] - c * vector[0]]) / det
    return jnp.linalg.solve(matrix, vector)


def is_positive_definite(matrix: Float[Array, "n n"]) -> Bool[Array, ""]:
    """Whether the symmetric ``matrix`` is positive definite (leading minors for n <= 2, a
    Cholesky factorisation otherwise)."""
    n = matrix.shape[-1]
    if n == 1:
        return matrix[0, 0] > 0
    if n == 2:
        return (matrix[0, 0] > 0) & (matrix[0, 0] * matrix[1, 1] - matrix[0, 1] * matrix[1, 0] > 0)
    return jnp.all(jnp.isfinite(jnp.linalg.cholesky(matrix)))
