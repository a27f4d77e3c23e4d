"""Ellipsoid operations of the set-membership filter, as pure JAX functions.

E(c, P) = {x : (x - c)^T P^{-1} (x - c) <= 1}. The two operations are the paper's time update
(an outer ellipsoid of the vector sum of an ellipsoid and a segment, eqs 15-17) and measurement
update (an outer ellipsoid of the intersection of an ellipsoid and a strip, eqs 27-36), with the
corrections of docs/papers/smf.md. Both choose the member of a one-parameter family of outer ellipsoids
with the least volume. They run under ``jit``/``vmap`` and differentiate (square roots and
divisions are guarded so that branches not taken give no NaN gradients).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from jaxest._checks import check_operands
from jaxest.linalg import cho_solve_lower, cholesky, symmetrize, working_precision
from jaxest.setmembership.rounding import (
    correlation_floor,
    diagonal_scaling,
    gamma,
    outward,
    unit_roundoff,
)


class Ellipsoid(eqx.Module):
    """E(center, shape) = {x : (x - center)^T shape^{-1} (x - center) <= 1}; shape is SPD."""

    center: Float[Array, " n"]
    shape: Float[Array, "n n"]


def _safe(condition, value, fallback=1.0):
    """``value`` where ``condition`` else a harmless ``fallback`` (the double-where trick)."""
    return jnp.where(condition, value, fallback)


def add_segment(shape: Float[Array, "n n"], direction: Float[Array, " n"]) -> Float[Array, "n n"]:
    """Shape of the least-volume ellipsoid of the family (1 + p) P + (1 + 1/p) s s^T containing
    E(c, P) + {t s : |t| <= 1} (eqs 16-17; the centre is unchanged), rounded outward (eq O3).

    p > 0 is the root of n p^2 + (n - 1) a p - a = 0, a = s^T P^{-1} s, computed as
    p = 2a / ((n - 1) a + sqrt((n - 1)^2 a^2 + 4 n a)) (no cancellation; n = 1 gives sqrt(a)).
    A zero segment leaves P unchanged.
    """
    check_operands(shape, {"direction": direction})
    return add_box_of_segments(shape, direction[None, :])


def add_box(
    shape: Float[Array, "n n"],
    half_widths: Float[Array, " n"],
    shape_error: Float[Array, "n n"] | None = None,
) -> Float[Array, "n n"]:
    """Outer ellipsoid of E(c, P) + {w : |w_i| <= half_widths_i}: the box is the sum of the n
    segments half_widths_i e_i, added one at a time (eq 16 for i = 1..n; P_{k|k-1} = P^n),
    rounded outward once at the end (eq O3). ``shape_error`` bounds the rounding error already in
    ``shape`` (element-wise; the time update's F P F^T)."""
    check_operands(shape, {"half_widths": half_widths})
    if shape_error is not None and jnp.shape(shape_error) != shape.shape:
        raise ValueError(
            f"shape_error: expected the shape's {shape.shape}, got {jnp.shape(shape_error)}"
        )
    n = shape.shape[-1]
    segments = half_widths[:, None] * jnp.eye(n, dtype=shape.dtype)
    return add_box_of_segments(shape, segments, shape_error)


@jax.custom_jvp
def _segment_norm(shape, direction):
    """a = s^T P^-1 s of eq 17: inf, NaN or any number where P is singular."""
    return direction @ spd_solve(shape, direction)


@_segment_norm.defjvp
def _segment_norm_jvp(primals, tangents):
    """da = 2 x^T ds - x^T dP x, x = P^-1 s; none where the solve is not finite (p is then the
    constant 1/(n - 1), :func:`add_box_of_segments`), instead of NaN through the singular solve."""
    shape, direction = primals
    d_shape, d_direction = tangents
    solved = spd_solve(shape, direction)
    x = jnp.where(jnp.all(jnp.isfinite(solved)), solved, 0.0)
    return direction @ solved, 2 * x @ d_direction - x @ d_shape @ x


@working_precision
def add_box_of_segments(shape, segments, shape_error=None):
    """E(c, P) + the segments {t s_i : |t| <= 1} (rows of ``segments``) one at a time, each with
    its least-volume p_i (eqs 16-17), then rounded outward (eq O3). Any p_i > 0 gives an outer
    ellipsoid, so the rounding of p_i costs nothing; the bound E_P of the rest follows the
    recursion P_{i+1} = (1 + p_i) P_i + (1 + 1/p_i) s_i s_i^T: E_{i+1} = (1 + p_i) E_i +
    gamma_6 ((1 + p_i) |P_i| + (1 + 1/p_i) |s_i| |s_i|^T) (six roundings per entry, the
    symmetrisation included). A segment of infinite or NaN length (a remainder bound over a set
    that holds a pole) makes the sum unbounded: the shape is +inf.

    A singular P (a flat set: F P F^T of a singular Jacobian, a state driven by noise alone)
    with s outside its range has a = +inf, which the solve gives as inf, NaN or, rounded, any
    number: wherever the computed a is not finite and positive for a nonzero segment, p takes
    the limit 1/(n - 1), the least volume of the family as a -> inf, and for n = 1 the sum is the
    interval (sqrt(P + E_P) + |s|)^2 itself. Any p > 0 bounds the sum for every positive
    semidefinite P (Cauchy-Schwarz on the support functions), so an a that the solve got wrong
    costs volume, never the guarantee."""
    n = shape.shape[-1]
    dtype = shape.dtype
    error = jnp.zeros_like(shape) if shape_error is None else shape_error
    bounded = jnp.ones((), bool)
    for direction in segments:
        finite = jnp.all(jnp.isfinite(direction))
        bounded = bounded & finite  # skipping it as if it were zero would lose the state
        a = _segment_norm(shape, direction)
        usable = jnp.isfinite(a) & (a > 0)
        flat = finite & jnp.any(direction != 0) & ~usable
        nonzero = usable | flat
        outer = jnp.outer(direction, direction)
        a_ = _safe(usable, a)
        p = 2 * a_ / ((n - 1) * a_ + jnp.sqrt((n - 1) ** 2 * a_**2 + 4 * n * a_))
        if n > 1:
            p = jnp.where(flat, jnp.asarray(1 / (n - 1), dtype), p)
        grown = symmetrize((1 + p) * shape + (1 + 1 / p) * outer)
        grown_error = (1 + p) * error + gamma(6, dtype) * (
            (1 + p) * jnp.abs(shape) + (1 + 1 / p) * jnp.abs(outer)
        )
        if n == 1:  # flat: the exact interval sum, E_P inside it
            extent = jnp.maximum(shape + error, 0)
            positive = extent > 0  # sqrt' is infinite at 0: the derivative of |F| there is 0
            root = jnp.where(positive, jnp.sqrt(_safe(positive, extent)), 0.0)
            exact = (root + jnp.abs(direction)) ** 2
            grown = jnp.where(flat, exact, grown)
            grown_error = jnp.where(flat, gamma(6, dtype) * exact, grown_error)
        shape = jnp.where(nonzero, grown, shape)
        error = jnp.where(nonzero, grown_error, error)
    return jnp.where(bounded, outward(shape, error), jnp.inf)


@working_precision
def linear_image(matrix: Float[Array, "n n"], shape: Float[Array, "n n"]):
    """``(F P F^T, bound on its rounding error)``: the shape of F E(c, P) = E(F c, F P F^T)
    (eq 15) and gamma_{2n} |F| |P| |F|^T (two products, Higham eq 3.13), to be rounded outward
    with the segments that follow (:func:`add_box`)."""
    image = symmetrize(matrix @ shape @ matrix.T)
    n = shape.shape[-1]
    error = gamma(2 * n + 1, shape.dtype) * (jnp.abs(matrix) @ jnp.abs(shape) @ jnp.abs(matrix).T)
    return image, error


@working_precision
def intersect_strip(
    center: Float[Array, " n"],
    shape: Float[Array, "n n"],
    normal: Float[Array, " n"],
    value: Float[Array, ""],
    half_width: Float[Array, ""],
) -> tuple[Float[Array, " n"], Float[Array, "n n"], Bool[Array, ""]]:
    """Outer ellipsoid of E(c, P) ∩ {x : |value - normal^T x| <= half_width} (eqs 27-36),
    rounded outward (eqs O1-O5 of docs/papers/smf.md).

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

    Rounding (eq O4): the strip is widened by the rounding error of phi+-, and the slab's
    half-width 1 by that of sqrt(g), so the cut strip holds every point of the exact one; an
    empty intersection is reported only where the widened strip misses the widened slab (a
    guaranteed alarm). Any q > 0 gives an outer ellipsoid, so q's rounding costs nothing; the
    factor 1 + q - q e^2/s is bounded from above, and the centre and shape (:func:`_joseph`)
    carry element-wise error bounds into :func:`~jaxest.setmembership.rounding.outward`.

    A negative ``half_width`` is an empty strip: ``empty`` (it shrank the set instead).

    Returns ``(center, shape, empty)``.
    """
    check_operands(shape, {"center": center, "normal": normal},
                   {"value": value, "half_width": half_width})  # fmt: skip
    n = shape.shape[-1]
    dtype = shape.dtype
    u = unit_roundoff(dtype)
    Ph = shape @ normal
    abs_Ph = jnp.abs(shape) @ jnp.abs(normal)
    g = normal @ Ph
    positive = g > 0
    root_g = jnp.sqrt(_safe(positive, g))
    # |g^ - g| / g^ and the slab's half-width in units of the computed sqrt(g) (eq O4)
    g_error = gamma(2 * n, dtype) * (jnp.abs(normal) @ abs_Ph) / _safe(positive, g)
    slab = 1 + g_error + 2 * u
    offset = value - normal @ center
    offset_error = gamma(n + 1, dtype) * (jnp.abs(value) + jnp.abs(normal) @ jnp.abs(center))
    slack = (offset_error + gamma(4, dtype) * (jnp.abs(offset) + half_width)) / root_g
    phi_plus = (offset + half_width) / root_g + slack
    phi_minus = (offset - half_width) / root_g - slack
    # the widened strip is empty (phi+ < phi-: a negative half-width) or misses the slab
    empty = positive & ((phi_plus < phi_minus) | (phi_plus < -slab) | (phi_minus > slab))
    phi_plus = jnp.minimum(phi_plus, slab)
    phi_minus = jnp.maximum(phi_minus, -slab)
    e = 0.5 * (phi_plus + phi_minus)  # e / sqrt(g), eq 35
    # d / sqrt(g), rounded up so that [e - d, e + d] covers [phi-, phi+]
    d = 0.5 * (phi_plus - phi_minus) * (1 + 2 * u) + 2 * u * jnp.abs(e)
    if n == 1:
        step = e * root_g * Ph / _safe(positive, g)
        new_center = center + step
        new_shape = d**2 * shape
        center_error = gamma(6, dtype) * jnp.abs(step) + u * jnp.abs(new_center)
        shape_error = gamma(6, dtype) * jnp.abs(new_shape)
        update = positive & ~empty
    else:
        update = positive & ~empty & (phi_plus * phi_minus > -1.0 / n)
        A = n - 1.0
        B = (2 * n - 1) * d**2 - 1 + e**2
        C = d**2 * (n * (d**2 - e**2) - 1)  # < 0 exactly when an update is due
        root_disc = jnp.sqrt(_safe(update, B**2 - 4 * A * C))
        q = jnp.where(B >= 0, -2 * C / _safe(update, B + root_disc), (root_disc - B) / (2 * A))
        update = update & (q > 0)
        q = _safe(update, q)
        s = d**2 + q  # s / g
        shrink = q * e**2 / s
        # the factor 1 + q - q e^2/s, rounded up; g^ != g changes it by at most shrink g_error
        scale = 1 + q - shrink + gamma(6, dtype) * (1 + q + shrink) + 2 * g_error * shrink
        scale = jnp.maximum(scale, 0.0)
        coefficient = q * e / s / root_g
        step = coefficient * Ph
        new_center = center + step
        center_error = (
            (gamma(6, dtype) + 2 * g_error) * jnp.abs(step)
            + jnp.abs(coefficient) * gamma(n, dtype) * abs_Ph
            + u * jnp.abs(new_center)
        )
        joseph, joseph_error = _joseph(shape, normal, Ph, g, d**2 / q)
        new_shape = scale * joseph
        shape_error = scale * joseph_error + u * jnp.abs(new_shape)
    # u |P+|: the symmetrisation's rounding
    new_shape = outward(symmetrize(new_shape), shape_error + u * jnp.abs(new_shape), center_error)
    return (
        jnp.where(update, new_center, center),
        jnp.where(update, new_shape, shape),
        empty,
    )


def _joseph(shape, normal, Ph, g, r_over_g):
    """``(J, bound on its rounding error)``: P - (q/s) P h h^T P (eq 33) in the Joseph-like
    form J = (I - k h^T) P (I - k h^T)^T + r k k^T.

    By Sherman-Morrison, P - (q/s) P h h^T P = (P^{-1} + h h^T / r)^{-1} with r = d^2/q
    (d, q unnormalised; r = g d^2/q in the normalised variables used here), i.e. a Kalman update
    with measurement variance r and gain k = P h / (g + r). The direct form loses the shrunk axis
    to cancellation (relative error about eps g / r); here the shrunk axis comes from the
    non-negative term r k k^T and the rounding of (I - k h^T) enters only squared
    (docs/papers/smf.md, strip intersection).

    For *any* gain k, J(k) = (P^-1 + h h^T/r)^-1 + (g + r)(k - k*)(k - k*)^T >= the exact
    update, and a larger r only enlarges it: the gain's rounding costs nothing, and r is rounded
    up (by gamma_8: its own four roundings and g^ against sqrt(g^)^2). What remains is the
    rounding of forming J from the computed k (eq O5): the computed A^ = fl(I - k h^T) is
    within u (|k| |h|^T + |A^|) of the exact I - k h^T, and the products add gamma_{2n}, so with
    M = |k| |h|^T |P| |A^|^T, |J^ - J| <= gamma_{2n+4} (|A^| |P| |A^|^T + r |k| |k|^T) +
    gamma_2 (M + M^T) to first order. Only |A^|, never |k h^T| twice, multiplies P: along a
    direction the update shrinks, A^ is small and so is the bound.
    """
    n = shape.shape[-1]
    dtype = shape.dtype
    r = g * r_over_g * (1 + gamma(8, dtype))
    gain = Ph / _safe(g + r > 0, g + r)
    reduce = jnp.eye(n, dtype=dtype) - jnp.outer(gain, normal)
    gain_gain = jnp.outer(gain, gain)
    joseph = reduce @ shape @ reduce.T + r * gain_gain
    abs_reduce = jnp.abs(reduce)
    spread = jnp.outer(jnp.abs(gain), jnp.abs(normal)) @ jnp.abs(shape) @ abs_reduce.T  # M
    error = gamma(2 * n + 4, dtype) * (
        abs_reduce @ jnp.abs(shape) @ abs_reduce.T + r * jnp.abs(gain_gain)
    ) + gamma(2, dtype) * (spread + spread.T)
    return joseph, error


@working_precision
def strips_ellipsoid(
    normals: Float[Array, "m n"],
    values: Float[Array, " m"],
    half_widths: Float[Array, " m"],
    rows: Bool[Array, " m"],
) -> tuple[Float[Array, " n"], Float[Array, "n n"], Bool[Array, ""], Bool[Array, ""]]:
    """An ellipsoid holding S = {x : |values_i - normals_i^T x| <= half_widths_i, i in ``rows``},
    the strips alone (no prior set; docs/papers/smf.md, recovery, eqs R1-R3).

    With D = diag(half_widths) over the m rows used, A = D^-1 H, t = D^-1 z and G = A^T A:
    every x in S has ||A x - t||^2 <= m (each term is at most 1), and (R1)

        ||A x - t||^2 = (x - x*)^T G (x - x*) + rho^2,  x* = G^-1 A^T t,  rho^2 = ||A x* - t||^2,

    so S lies in E(x*, (m - rho^2) G^-1) (R2), and S is empty when m < rho^2 (R3). For m = n
    (rho = 0) this is the least-volume ellipsoid around the parallelotope S.

    The rows must constrain every direction: G positive definite with condition number at most
    :func:`max_condition` (the limit every trusted set passes; cond(G) = cond(shape)) and every
    half-width used positive. The shape is inflated by a
    first-order rounding margin: the relative error n cond(G) eps of the solves (forming the
    shape and testing a point against it) and the centre's, n cond(G) eps |x*| in units of the
    shortest semi-axis sqrt((m - rho^2) / lambda_max(G)) (bounded through trace(G)).

    Returns ``(center, shape, bounded, empty)``: ``bounded`` where the rows constrain every
    direction and m > rho^2 (else S is empty or a single point and ``shape`` is not to be used);
    ``empty`` where they constrain every direction and m < rho^2.
    """
    if jnp.ndim(normals) != 2:
        raise ValueError(f"normals: expected an (m, n) matrix, got shape {jnp.shape(normals)}")
    m, n = normals.shape
    for name, array in (("values", values), ("half_widths", half_widths), ("rows", rows)):
        if jnp.shape(array) != (m,):
            raise ValueError(f"{name}: expected shape ({m},), one per row, got {jnp.shape(array)}")
    if jnp.result_type(rows) != jnp.bool_:  # rows & (h > 0) took 2 & True = 0: a row dropped
        raise ValueError(f"rows: expected a boolean mask, got {jnp.result_type(rows)}")
    dtype = normals.dtype
    used = rows & (half_widths > 0)
    weights = jnp.where(used, 1.0 / _safe(used, half_widths), 0.0)
    A = weights[:, None] * normals
    t = weights * jnp.where(used, values, 0.0)
    gram = A.T @ A
    kappa = condition_number(gram)
    spanning = jnp.all(used | ~rows) & (kappa <= max_condition(dtype, n))
    gram = jnp.where(spanning, gram, jnp.eye(n, dtype=dtype))  # a harmless stand-in otherwise
    kappa = jnp.where(spanning, kappa, 1.0)
    center = spd_solve(gram, A.T @ t)
    residual = A @ center - t
    slack = jnp.sum(rows) - residual @ residual  # m - rho^2, eq R2
    positive = slack > 0
    relative = n * kappa * jnp.finfo(dtype).eps
    centre_error = jnp.linalg.norm(center) * jnp.sqrt(jnp.trace(gram) / _safe(positive, slack))
    # a constant allowance for rounding: no derivative (cond and |x*| have none at isotropy, 0)
    margin = jax.lax.stop_gradient((1 + relative * (2 + centre_error)) ** 2)
    shape = slack * margin * symmetrize(spd_solve(gram, jnp.eye(n, dtype=dtype)))
    return center, shape, spanning & positive, spanning & (slack < 0)


@working_precision
def contains(
    center: Float[Array, " n"], shape: Float[Array, "n n"], x: Float[Array, " n"]
) -> Bool[Array, ""]:
    """Whether x may lie in E(center, shape), rounded outward: False only where the exact x is
    certainly outside (eq O6 of docs/papers/smf.md), so a point of the exact set is never
    reported outside. Also True where ``shape`` is not certified positive definite.

    With D = diag(sqrt(P_ii)), C = D^-1 P D^-1 and y = D^-1 (x - c), the quadratic form
    t = y^T C^-1 y is computed by a Cholesky (or, n <= 2, closed-form) solve, which is exact for
    some C + Delta C with ||Delta C||_2 <= n^2 gamma_{3n+1} (Higham Thm 10.4 and ||C||_2 <= n),
    plus 2 u n for forming C. Then t_exact >= (t^ - gamma_n |y|^T |w|)(1 - ||Delta C|| /
    lambda_min(C)), and the rounding of y (2u |y|) moves sqrt(t) by at most
    2u ||y|| / sqrt(lambda_min(C)).
    """
    check_operands(shape, {"center": center, "x": x})
    n = shape.shape[-1]
    dtype = shape.dtype
    u = unit_roundoff(dtype)
    scale, C, positive = diagonal_scaling(shape)
    y = (x - center) / scale
    w = spd_solve(C, y)
    t = y @ w - gamma(n, dtype) * (jnp.abs(y) @ jnp.abs(w))
    floor = correlation_floor(C, positive)
    certified = floor > 0
    floor = jnp.where(certified, floor, 1.0)
    backward = (n**2 * gamma(3 * n + 1, dtype) + 2 * u * n) / floor
    root_t = jnp.sqrt(jnp.maximum(t * (1 - backward), 0.0))
    outside = root_t - 2 * (1 + u) * u * jnp.linalg.norm(y) / jnp.sqrt(floor) > 1 + 4 * u
    return ~(certified & (backward < 1) & outside)


def spd_solve(matrix: Float[Array, "n n"], vector: Float[Array, " n"]) -> Float[Array, " n"]:
    """matrix^{-1} vector; closed form for n <= 2 (XLA's batched LAPACK calls dominate the
    filter's run time on CPU for such small matrices), through the Cholesky factor otherwise
    (unrolled up to ``SMALL_FACTOR``: NaN where ``matrix`` is not positive definite)."""
    n = matrix.shape[-1]
    if n == 1:
        return vector / matrix[0, 0]
    if n == 2:
        (a, b), (c, d) = matrix[0], matrix[1]
        det = a * d - b * c
        return jnp.stack([d * vector[0] - b * vector[1], a * vector[1] - c * vector[0]]) / det
    return cho_solve_lower(cholesky(matrix), vector)


def is_positive_definite(matrix: Float[Array, "n n"]) -> Bool[Array, ""]:
    """Whether the symmetric ``matrix`` is positive definite (leading minors for n <= 2, a
    Cholesky factorisation otherwise)."""
    n = matrix.shape[-1]
    if n == 1:
        return matrix[0, 0] > 0
    if n == 2:
        return (matrix[0, 0] > 0) & (matrix[0, 0] * matrix[1, 1] - matrix[0, 1] * matrix[1, 0] > 0)
    return jnp.all(jnp.isfinite(cholesky(matrix)))


def condition_number(matrix: Float[Array, "n n"]) -> Float[Array, ""]:
    """lambda_max / lambda_min of the symmetric ``matrix`` (+inf unless positive definite);
    closed form for n <= 2 (lambda_min = det / lambda_max, free of cancellation)."""
    n = matrix.shape[-1]
    if n == 1:
        return jnp.where(matrix[0, 0] > 0, 1.0, jnp.inf).astype(matrix.dtype)
    if n == 2:
        a, b, d = matrix[0, 0], matrix[0, 1], matrix[1, 1]
        largest = 0.5 * (a + d) + jnp.sqrt(0.25 * (a - d) ** 2 + b**2)
        det = a * d - b * b
        ok = is_positive_definite(matrix) & (largest > 0)
        return jnp.where(ok, largest**2 / _safe(ok, det), jnp.inf)
    eig = jnp.linalg.eigvalsh(matrix)
    return jnp.where(eig[0] > 0, eig[-1] / _safe(eig[0] > 0, eig[0]), jnp.inf)


def max_condition(dtype, n: int) -> float:
    """Largest condition number of a shape matrix the filter trusts: kappa n eps <= 2^-10 keeps
    the relative error of a solve with it (the containment test, eq 16's a) below 1e-3."""
    return 2.0**-10 / (n * float(jnp.finfo(dtype).eps))
