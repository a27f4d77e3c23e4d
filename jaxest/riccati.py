"""Algebraic Riccati equations in JAX: jit-able, vmap-able and differentiable.

The control-form solvers take scipy's argument convention:

- :func:`solve_dare` solves  X = A^T X A - A^T X B (R + B^T X B)^{-1} B^T X A + Q;
- :func:`solve_care` solves  A^T X + X A - X B R^{-1} B^T X + Q = 0;
- :func:`lqr_gain` is the continuous-time LQR gain K = R^{-1} B^T X (u = -K x).

The filter forms take the model's own matrices: :func:`solve_filter_dare` solves eq 5 of the
Wiener-smoother paper (docs/papers/wiener.md), Sigma = F Sigma F^T - F Sigma H^T
(H Sigma H^T + R)^{-1} H Sigma F^T + Q, and :func:`solve_filter_care` the Kalman-Bucy equation
F Sigma + Sigma F^T - Sigma H^T R^{-1} H Sigma + Q = 0 (they are the control forms of
(F^T, H^T), with argument checks and messages in terms of F and H).

Each returns a :class:`RiccatiSolution`: the stabilising solution X (the closed loop A - B K is
Schur, resp. Hurwitz), the gain K, and a ``status`` (:class:`RiccatiStatus`) that says, under
``jit`` too, when X is not to be trusted. A stabilising solution exists if and only if every
mode of A outside or on the stability boundary is controllable through B and no mode *on* the
boundary is unobservable through Q (R > 0, Q >= 0); an unobservable mode strictly outside is
allowed (F = 2, H = 1, Q = 0: Sigma = 3, where the Kalman filter converges). When the arguments
are concrete these conditions are checked first and a ``ValueError`` names the mode and the
arguments; under ``jit`` the status carries ``NOT_STABILISING`` instead.

Forward solver, in three stages:

0. balancing: the states are rescaled by powers of two that balance the Hamiltonian
   (:func:`_balancing`), so that states in very different units cost no accuracy; the stages
   below and the status see the balanced problem, and X and K are scaled back exactly;
1. a start: the structured doubling algorithm (SDA) for the DARE, the matrix sign function of the
   Hamiltonian for the CARE, both on Q + delta I with delta = sqrt(eps) (|Q| + 1 / |B R^-1 B^T|),
   which makes (Q, A) observable so that they converge whenever (A, B) is stabilisable; their
   gain is stabilising for the true Q too, but B R^-1 B^T (formed from the Cholesky factor of R)
   costs them cond(R) eps of accuracy;
2. Newton's method (Hewer's for the DARE, Kleinman's for the CARE) in correction form: with K
   the gain of X and A_c = A - B K, the correction N solves A_c^T N A_c - N + res(X) = 0, resp.
   A_c^T N + N A_c + res(X) = 0. The DARE residual is evaluated with R + B^T X B (never R^-1),
   the CARE's with L^-1 B^T X (L the Cholesky factor of R), so the answer is accurate to a small
   multiple of the equation's own conditioning even for cond(R) ~ 1e12. Newton converges
   quadratically from a stabilising start; it stops once the correction is at rounding level or
   stops shrinking.

The status check: ``NONFINITE``; ``NOT_STABILISING`` when the closed loop's decay margin
(1 - rho(A_c), resp. -max Re lambda(A_c) / |A_c|) is below 10 sqrt(eps) -- where no stabilising
solution exists, Newton stalls with a closed-loop mode within about sqrt(eps) of the boundary;
``INACCURATE`` when the residual, relative to |X| times the size of its derivative in X (plus
|Q|; so it estimates X's relative error where the equation is well conditioned: where the
inverse of its derivative is not much larger than one over its size, docs/robustness.md), is
above sqrt(eps); when the residual cannot certify that much because its own rounding level is
higher (the terms before cancellation: |K|^2 |R| in the DARE's closed-loop form, where a
nearly singular R meets a small X; and in the CARE what rounding R moves it by through R's
Cholesky factor, :func:`_rounded_R_effect`, which the residual, evaluated through the same
factor as the solution, cannot see); or when Newton did not converge.

Derivatives, forward and reverse mode, come from implicit differentiation: the derivative dX
of either equation solves a Stein (discrete) or Lyapunov (continuous) equation in A_c, a
``jax.lax.custom_linear_solve`` whose transpose is the adjoint solve, A_c Y A_c^T - Y + Xbar =
0 resp. A_c Y + Y A_c^T + Xbar = 0, after which Qbar = Y, Rbar = K Y K^T, Abar = 2 X A_c Y
(discrete) or 2 X Y (continuous) and Bbar = -Abar K^T. (A ``custom_vjp`` gave reverse mode
only: ``jax.jvp``, ``jacfwd`` and ``linearize`` raised a TypeError, for the steady-state Kalman
filter too.) The status, residual and margin carry no derivative.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from jaxest._checks import check_matrix, is_concrete
from jaxest._status import Status, StatusOfOne, status_where
from jaxest.linalg import (
    cho_solve_lower,
    cholesky,
    solve_triangular,
    symmetrize,
    working_precision_by_default,
)

_MAX_ITERATIONS = 100
#: Newton steps at most: enough to walk from the regularised start down to rounding level in
#: the linearly convergent case of a mode on the boundary
_MAX_NEWTON = 50
#: an iterate below _COLLAPSE n eps times the last is taken for 0 (:func:`_newton`)
_COLLAPSE = 64
#: squarings of the closed loop in :func:`_log_spectral_radius` (powers up to 2^40)
_SQUARINGS = 40
#: sweeps of the balancing (:func:`_balancing`): each halves the distance to balance
_BALANCING_SWEEPS = 32
#: a closed-loop margin below MARGIN_FACTOR sqrt(eps) is reported as not stabilising
MARGIN_FACTOR = 10.0

RiccatiStatus = Status.extend(
    "RiccatiStatus",
    NOT_STABILISING=(
        64,
        "the closed loop A - B K is not stable (within 10 sqrt(eps), relative to |A - B K| "
        "in continuous time): no stabilising solution exists -- a mode of A outside the "
        "stability region is not controllable through B, or a mode on its boundary is not "
        "observable through Q; call the solver with concrete arguments to have the mode "
        "named -- or, in continuous time, a stiff loop whose slowest mode is that close to 0 "
        "next to its fastest (Re -1.4e-3 beside -1e5), whose stability the margin cannot "
        "certify",
    ),
    INACCURATE=(
        128,
        "Newton's refinement did not converge, or the Riccati residual is above sqrt(eps) "
        "relative to |X| times its derivative's size, or its own rounding level is: the "
        "equation is too ill-conditioned for this precision; use float64 or rescale the "
        "states",
    ),
)
"""The Riccati solvers' status flags: the core's and their own."""


class RiccatiSolution(StatusOfOne):
    """The solution of an algebraic Riccati equation and how far to trust it.

    ``X`` the stabilising solution; ``K`` its gain (control forms: u = -K x with closed loop
    A - B K; filter forms: the gain with closed loop F - K H); ``status`` the
    :class:`RiccatiStatus` bits (0 = OK); ``residual`` the residual's norm relative to |Q| + |X|
    times the size of its derivative in X (an estimate of X's relative error where the equation
    is well conditioned; module docstring); ``margin`` the closed loop's decay margin,
    -log rho(A - B K) ~ 1 - rho (discrete) or -max Re lambda(A - B K) / |A - B K| (continuous),
    negative when it is unstable. Both are those of the balanced problem (the module
    docstring's stage 0), whose norms weigh every state alike: X_ij is then known to about
    ``residual`` |D X D| / (d_i d_j), D the balancing scales.
    """

    flags = RiccatiStatus

    X: Float[Array, "n n"]
    K: Float[Array, "m n"]
    status: Int[Array, ""]
    residual: Float[Array, ""]
    margin: Float[Array, ""]


# --------------------------------------------------------------------------- iterations
def _converge(update, start, size):
    """Iterate ``update(carry) -> (carry, relative_change)`` from ``start`` with a quadratically
    convergent method: stop two iterations after the change first drops below sqrt(eps) (by then
    it is at rounding level), after ``_MAX_ITERATIONS`` or once the change is not finite.
    Returns (carry, converged)."""
    tol = jnp.sqrt(jnp.finfo(size.dtype).eps)

    def cond(state):
        _, change, k, extra = state
        return (k < _MAX_ITERATIONS) & (extra < 2) & jnp.isfinite(change)

    def body(state):
        carry, _, k, extra = state
        carry, change = update(carry)
        extra = jnp.where((change <= tol) | (extra > 0), extra + 1, extra)
        return carry, change, k + 1, extra

    one = jnp.ones((), size.dtype)
    final, change, _, extra = jax.lax.while_loop(cond, body, (start, one, 0, 0))
    return final, (extra >= 2) & jnp.isfinite(change)


def _relative_change(new, old):
    scale = jnp.maximum(jnp.max(jnp.abs(new)), jnp.finfo(new.dtype).tiny)
    return jnp.max(jnp.abs(new - old)) / scale


def _newton(step, X0):
    """Newton's method ``step(X) -> (X_new, solved)`` from X0, keeping the last X whose step
    solved. Stops when the relative correction is below eps, when it is below sqrt(eps) but no
    longer shrinks by a quarter (rounding level: quadratic convergence would have dropped it to
    eps), when a step's linear solve fails, or after ``_MAX_NEWTON`` steps. A stabilising
    solution on the stability boundary makes Newton converge only linearly (the correction
    halves each step); it then goes on to rounding level, which leaves the closed-loop mode
    within about sqrt(eps) of the boundary for the status check. An iterate below
    ``_COLLAPSE`` n eps times the one before is the solution 0 (and if it is not, the next step
    goes on from 0).
    Returns (X, converged): converged when the last accepted correction was below sqrt(eps)."""
    eps = jnp.finfo(X0.dtype).eps
    tol = jnp.sqrt(eps)

    def cond(state):
        _, _, k, done = state
        return (k < _MAX_NEWTON) & ~done

    def body(state):
        X, change, k, _ = state
        X_new, solved = step(X)
        # where the solution is 0 (Q = 0 with A stable) each correction cancels X to rounding,
        # and the iterates would shrink by 3-20 eps a step (n = 5) without settling: they are 0
        collapsed = jnp.max(jnp.abs(X_new)) <= _COLLAPSE * X.shape[-1] * eps * jnp.max(jnp.abs(X))
        X_new = jnp.where(collapsed, 0, X_new)
        new_change = _relative_change(X_new, X)
        accept = solved & jnp.isfinite(new_change)
        stalled = (new_change <= tol) & (new_change > 0.75 * change)
        done = ~accept | (new_change <= eps) | stalled
        return (
            jnp.where(accept, X_new, X),
            jnp.where(accept, new_change, change),
            k + 1,
            done,
        )

    inf = jnp.full((), jnp.inf, X0.dtype)
    X, change, _, _ = jax.lax.while_loop(cond, body, (X0, inf, 0, jnp.zeros((), bool)))
    return X, change <= tol


# --------------------------------------------------------------------------- Stein / Lyapunov
def _stein(T, C):
    """Y = T Y T^T + C for Schur-stable T, by squared Smith doubling:
    Y_{j+1} = Y_j + T_j Y_j T_j^T, T_{j+1} = T_j^2 (Y_j sums the first 2^j terms).
    Returns (Y, converged)."""

    def update(carry):
        Y, Tj = carry
        Y_new = Y + Tj @ Y @ Tj.T
        return (Y_new, Tj @ Tj), _relative_change(Y_new, Y)

    (Y, _), converged = _converge(update, (C, T), C)
    return Y, converged


def _lyapunov(Ac, C):
    """Y with Ac Y + Y Ac^T + C = 0 for Hurwitz Ac, through the Cayley transform
    T = (Ac - g I)^{-1} (Ac + g I), which maps it to the Stein equation
    Y = T Y T^T + 2 g (Ac - g I)^{-1} C (Ac - g I)^{-T}. Returns (Y, converged)."""
    n = Ac.shape[-1]
    eye = jnp.eye(n, dtype=Ac.dtype)
    g = jnp.maximum(jnp.linalg.norm(Ac) / jnp.sqrt(n), jnp.finfo(Ac.dtype).tiny)
    shifted = jax.scipy.linalg.lu_factor(Ac - g * eye)  # one factorisation, three solves
    T = jax.scipy.linalg.lu_solve(shifted, Ac + g * eye)
    M = jax.scipy.linalg.lu_solve(shifted, C)
    return _stein(T, 2 * g * jax.scipy.linalg.lu_solve(shifted, M.T).T)


def _log_spectral_radius(T):
    """log rho(T) as log |T^(2^J)| / 2^J after J = ``_SQUARINGS`` squarings, each normalised by
    its largest entry (whose logarithms are summed), so nothing overflows; the transient
    factor of a non-normal T contributes log(kappa) / 2^J, i.e. nothing."""
    tiny = jnp.finfo(T.dtype).tiny

    def body(_, carry):
        Tj, log_scale = carry
        square = Tj @ Tj
        s = jnp.maximum(jnp.max(jnp.abs(square)), tiny)
        return square / s, 2 * log_scale + jnp.log(s)

    s0 = jnp.maximum(jnp.max(jnp.abs(T)), tiny)
    _, log_scale = jax.lax.fori_loop(0, _SQUARINGS, body, (T / s0, jnp.log(s0)))
    return log_scale / 2.0**_SQUARINGS


# --------------------------------------------------------------------------- shared pieces
def _input_gramian(B, R):
    """G = B R^-1 B^T as the Gram matrix of L^-1 B^T, L the Cholesky factor of R."""
    V = solve_triangular(cholesky(R), B.T, lower=True)
    return V.T @ V


def _regularised(Q, G):
    """Q + delta I with delta = sqrt(eps) (|Q| + 1 / |G|): (Q + delta I, A) is observable, so the
    starting iterations converge whenever (A, B) is stabilisable; Newton removes delta."""
    n = Q.shape[-1]
    eps = jnp.finfo(Q.dtype).eps
    g = jnp.max(jnp.abs(G))
    inverse_g = jnp.where(g > 0, 1 / jnp.where(g > 0, g, 1), 0)
    delta = jnp.sqrt(eps) * (jnp.max(jnp.abs(Q)) + inverse_g)
    return Q + delta * jnp.eye(n, dtype=Q.dtype)


def _frobenius(M):
    """The Frobenius norm, scaled by the largest entry first: ``jnp.linalg.norm`` squares the
    entries, which overflows in float32 from entries of about 1.8e19 on. Then the status
    check's ``scale`` was infinite, the relative residual 0 and X certified by nothing."""
    largest = jnp.max(jnp.abs(M))
    safe = jnp.where(largest > 0, largest, 1.0)
    return largest * jnp.linalg.norm(M / safe)


def _dare_terms(A, B, Q, R, X):
    """(K, A_c, residual, scale, floor) at X: K = (R + B^T X B)^-1 B^T X A (no R^-1),
    A_c = A - B K and the residual in closed-loop form Q + A_c^T X A_c + K^T R K - X, which
    differs from the DARE's by (K - K*)^T (R + B^T X B) (K - K*) only (second order in the error
    of K; measured more accurate than the DARE's own form). ``scale`` = |Q| + (|A_c|^2 + 1) |X|
    (Frobenius norms): |X| times the size of the derivative N -> A_c^T N A_c - N, so that
    residual / scale estimates X's relative error. ``floor`` adds |K|^2 |R|, the size K^T R K can
    have before cancellation: eps ``floor`` is the residual's rounding level."""
    BtX = B.T @ X
    K = cho_solve_lower(cholesky(symmetrize(R + BtX @ B)), BtX @ A)
    Ac = A - B @ K
    residual = symmetrize(Q + Ac.T @ X @ Ac + K.T @ R @ K - X)
    norm = _frobenius
    scale = norm(Q) + (norm(Ac) ** 2 + 1) * norm(X)
    return K, Ac, residual, scale, scale + norm(K) ** 2 * norm(R)


def _care_terms(A, B, Q, R, X):
    """(K, A_c, residual, scale, floor) at X: with V = L^-1 B^T X (L L^T = R), K = L^-T V,
    A_c = A - B K and the residual Q + A^T X + X A - V^T V (measured more accurate than the
    closed-loop form, whose A_c is large when R is nearly singular). ``scale`` =
    |Q| + 2 |A_c| |X| (Frobenius norms): |X| times the size of the derivative
    N -> A_c^T N + N A_c, so that residual / scale estimates X's relative error (an X off by
    eps |X| along a fast closed-loop mode leaves a residual of |A_c| eps |X|). ``floor`` adds
    2 |A| |X| + |V|^2, the size the other terms can have before cancellation, and what rounding
    R moves V^T V by (:func:`_rounded_R_effect`): eps ``floor`` is the residual's rounding
    level."""
    L = cholesky(R)
    V = solve_triangular(L, B.T @ X, lower=True)
    K = solve_triangular(L.T, V, lower=False)
    XA = X @ A
    residual = symmetrize(Q + XA + XA.T - V.T @ V)
    norm = _frobenius
    Ac = A - B @ K
    scale = norm(Q) + 2 * norm(Ac) * norm(X)
    floor = scale + 2 * norm(A) * norm(X) + norm(V) ** 2 + norm(_rounded_R_effect(L, K))
    return K, Ac, residual, scale, floor


def _rounded_R_effect(L, K):
    """|K|^T |L| |L|^T |K| (entrywise absolute values), eps times which bounds to first order how
    far rounding R moves V^T V = K^T R K in :func:`_care_terms`: V^T V takes R^-1 through R's
    Cholesky factor L, which is exact for a perturbed R + dR with |dR| of order eps |L| |L|^T
    entrywise (the factorisation's backward error, Higham 2002, thm 10.3), and dR moves it by
    K^T dR K. The residual, evaluated through the same factor as the solution, cannot see that
    change. It is small where R is well conditioned or diagonal (whatever its scales) and large
    where a nearly singular R is not aligned with the axes."""
    L, K = jnp.abs(L), jnp.abs(K)
    return K.T @ (L @ L.T) @ K


def _balancing(A, G, Q):
    """Powers of two d (n,) that balance the Hamiltonian H = [[A, -G], [-Q, -A^T]]
    (G = B R^-1 B^T) by the similarity diag(D, D^-1), D = diag(d): the data become
    D^-1 A D, D^-1 B, D^-1 G D^-1, D Q D, and the solution D X D (exactly, since d are powers
    of two).

    Osborne's balancing (Parlett & Reinsch 1969) with the Hamiltonian's structure kept (Benner
    1997), in its parallel form: scaling d_i by f moves the sum of the off-diagonal |entries|
    of H that d_i touches to a_i / f + p_i f (a_i: row i of A and of G, p_i: column i of A and
    row i of Q, each off-diagonal entry counted twice as H holds it twice; G_ii and Q_ii, which
    scale with f^2, counted once), least at f = sqrt(a_i / p_i). Each of
    ``_BALANCING_SWEEPS`` sweeps moves every log2 d_i half way there, all at once (half, so that
    the coupled states do not overshoot), and d is rounded to powers of two at the end. One loop
    of n-vector operations, which adds about 0.25 s (a quarter) to compiling a solver; the
    sequential form, one state at a time, balanced no better on the sweep's problems and
    compiled twice as long. States given in very different units (a position in km beside a
    rate in mm/s) are otherwise a Riccati problem float32 cannot solve (docs/robustness.md);
    the Newton steps and the status work on the balanced problem."""
    sweep = _balancing_sweep(A, G, Q, jnp)
    log_d, _ = jax.lax.scan(
        lambda log_d, _: (sweep(log_d), None), jnp.zeros(A.shape[-1], A.dtype), None,
        length=_BALANCING_SWEEPS,
    )  # fmt: skip
    return _power_of_two(jnp.round(log_d))


def _balancing_sweep(A, G, Q, xp):
    """One sweep of :func:`_balancing` (log2 d -> log2 d), in the array namespace ``xp``:
    ``jax.numpy`` for the solver, ``numpy`` for the eager checks (:func:`_check_modes`)."""
    n = A.shape[-1]
    off = ~xp.eye(n, dtype=bool)
    abs_A = xp.where(off, xp.abs(A), 0)
    abs_G, abs_Q = xp.abs(G), xp.abs(Q)
    G_off, Q_off = xp.where(off, abs_G, 0), xp.where(off, abs_Q, 0)
    limit = xp.finfo(A.dtype).nmant  # |log2 d_i| at most: D Q D stays far from overflow
    safe_positive = lambda x: xp.where(x > 0, x, 1)  # a harmless argument for an unused log

    def sweep(log_d):
        d = xp.exp2(log_d)
        a = 2 * (abs_A @ d + G_off @ (1 / d)) / d + xp.diagonal(abs_G) / d**2
        p = 2 * ((1 / d) @ abs_A + Q_off @ d) * d + xp.diagonal(abs_Q) * d**2
        coupled = (a > 0) & (p > 0)  # else the state's scale does not matter
        balancing_step = 0.5 * xp.log2(safe_positive(a) / safe_positive(p))
        return xp.clip(log_d + xp.where(coupled, 0.5 * balancing_step, 0), -limit, limit)

    return sweep


def _balanced(d, A, B, Q):
    """(D^-1 A D, D^-1 B, D Q D), D = diag(d): the problem in :func:`_balancing`'s coordinates,
    whose solution is D X D."""
    return A * d / d[:, None], B / d[:, None], Q * d * d[:, None]


def _power_of_two(exponent):
    """2^exponent for integer-valued ``exponent``, exactly (``jnp.exp2`` is not exact)."""
    return jnp.ldexp(jnp.ones_like(exponent), exponent.astype(jnp.int32))


# --------------------------------------------------------------------------- forward solvers
def _dare_start(A, G, Q):
    """Structured doubling on Q + delta I: A_0 = A, G_0 = G = B R^-1 B^T, H_0 = Q + delta I; with
    W = I + G_k H_k, A_{k+1} = A_k W^-1 A_k, G_{k+1} = G_k + A_k W^-1 G_k A_k^T,
    H_{k+1} = H_k + A_k^T H_k W^-1 A_k; H_k converges quadratically to the stabilising X."""
    n = A.shape[-1]
    eye = jnp.eye(n, dtype=A.dtype)
    H0 = _regularised(symmetrize(Q), G)

    def update(carry):
        Ak, Gk, Hk = carry
        W = eye + Gk @ Hk
        WA, WG = jnp.split(jnp.linalg.solve(W, jnp.concatenate([Ak, Gk], axis=1)), 2, axis=1)
        H_new = symmetrize(Hk + Ak.T @ Hk @ WA)
        new = (Ak @ WA, symmetrize(Gk + Ak @ WG @ Ak.T), H_new)
        return new, _relative_change(H_new, Hk)

    (_, _, X), _ = _converge(update, (A, G, H0), Q)
    return X


@jax.jit
def _dare_solve(A, B, Q, R, G):
    """The stabilising DARE solution: SDA start, then Hewer's Newton steps in correction form,
    A_c^T N A_c - N + res(X) = 0. Returns (X, converged)."""
    Q = symmetrize(Q)

    def step(X):
        _, Ac, residual, _, _ = _dare_terms(A, B, Q, R, X)
        N, solved = _stein(Ac.T, residual)
        return symmetrize(X + N), solved

    return _newton(step, _dare_start(A, G, Q))


def _care_start(A, G, Q):
    """Matrix sign function of the Hamiltonian Z = [[A, -G], [-Q - delta I, -A^T]]
    (G = B R^-1 B^T) by the determinant-scaled Newton iteration Z <- (c Z + (c Z)^-1) / 2; the
    stable invariant subspace [I; X] is the null space of sign(Z) + I, so
    [[W12], [W22 + I]] X = -[[W11 + I], [W21]]."""
    n = A.shape[-1]
    Z = jnp.block([[A, -G], [-_regularised(symmetrize(Q), G), -A.T]])

    def update(Zk):
        _, logdet = jnp.linalg.slogdet(Zk)
        c = jnp.exp(-logdet / (2 * n))
        Z_new = 0.5 * (c * Zk + jnp.linalg.inv(Zk) / c)
        return Z_new, _relative_change(Z_new, Zk)

    W, _ = _converge(update, Z, Q)
    eye = jnp.eye(n, dtype=A.dtype)
    lhs = jnp.concatenate([W[:n, n:], W[n:, n:] + eye])
    rhs = -jnp.concatenate([W[:n, :n] + eye, W[n:, :n]])
    return symmetrize(jnp.linalg.lstsq(lhs, rhs)[0])


@jax.jit
def _care_solve(A, B, Q, R, G):
    """The stabilising CARE solution: sign-function start, then Kleinman's Newton steps in
    correction form, A_c^T N + N A_c + res(X) = 0. Returns (X, converged)."""
    Q = symmetrize(Q)

    def step(X):
        _, Ac, residual, _, _ = _care_terms(A, B, Q, R, X)
        N, solved = _lyapunov(Ac.T, residual)
        return symmetrize(X + N), solved

    return _newton(step, _care_start(A, G, Q))


# --------------------------------------------------------------------------- implicit derivatives
def _zero_for_zero(solve):
    """``solve(b)`` for ``custom_linear_solve``, zero where b is: the solution of a linear
    equation with a zero right-hand side, whatever the operator. Where there is no stabilising
    solution A_c is unstable, and the Stein and Lyapunov solvers turn even a zero b into NaN
    (zero times A_c's overflowing powers); so a batch member masked out by its own status
    (``where(s.ok, s.X, 0)``), whose cotangent is zero, made the whole gradient NaN."""
    return lambda _, b: jnp.where(jnp.all(b == 0), jnp.zeros_like(b), solve(b))


@jax.custom_jvp
def _dare(A, B, Q, R, G):
    return _dare_solve(A, B, Q, R, G)


@_dare.defjvp
@working_precision_by_default
def _dare_jvp(primals, tangents):
    """dX = A_c^T dX A_c + E: the Stein equation of the module docstring, with
    E = dQ + dA_K^T X A_c + A_c^T X dA_K + K^T dR K and dA_K = dA - dB K (K is optimal, so its
    own change drops out). Solved as a ``custom_linear_solve``, whose transpose (the adjoint
    Stein equation, ``_stein(A_c, .)``) gives reverse mode."""
    A, B, Q, R, G = primals
    dA, dB, dQ, dR, _ = tangents  # G = B R^-1 B^T only starts the iteration
    X, converged = _dare(A, B, Q, R, G)
    K = jnp.linalg.solve(R + B.T @ X @ B, B.T @ X @ A)
    Ac = A - B @ K
    XdA = X @ (dA - dB @ K)
    E = symmetrize(dQ + Ac.T @ XdA + XdA.T @ Ac + K.T @ dR @ K)
    dX = jax.lax.custom_linear_solve(
        lambda N: N - Ac.T @ N @ Ac,
        E,
        solve=_zero_for_zero(lambda b: _stein(Ac.T, b)[0]),
        transpose_solve=_zero_for_zero(lambda b: _stein(Ac, b)[0]),
    )
    return (X, converged), (dX, np.zeros(np.shape(converged), jax.dtypes.float0))


@jax.custom_jvp
def _care(A, B, Q, R, G):
    return _care_solve(A, B, Q, R, G)


@_care.defjvp
@working_precision_by_default
def _care_jvp(primals, tangents):
    """A_c^T dX + dX A_c + E = 0 with E = dQ + dA_K^T X + X dA_K + K^T dR K, dA_K = dA - dB K,
    as for :func:`_dare_jvp`; the transpose solves A_c Y + Y A_c^T + Xbar = 0."""
    A, B, Q, R, G = primals
    dA, dB, dQ, dR, _ = tangents
    X, converged = _care(A, B, Q, R, G)
    K = cho_solve_lower(cholesky(R), B.T @ X)
    Ac = A - B @ K
    XdA = X @ (dA - dB @ K)
    E = symmetrize(dQ + XdA + XdA.T + K.T @ dR @ K)
    dX = jax.lax.custom_linear_solve(
        lambda N: -(Ac.T @ N + N @ Ac),
        E,
        solve=_zero_for_zero(lambda b: _lyapunov(Ac.T, b)[0]),
        transpose_solve=_zero_for_zero(lambda b: _lyapunov(Ac, b)[0]),
    )
    return (X, converged), (dX, np.zeros(np.shape(converged), jax.dtypes.float0))


# --------------------------------------------------------------------------- status
@functools.partial(jax.jit, static_argnames=("discrete", "filter_form"))
def _solve(A, B, Q, R, *, discrete: bool, filter_form: bool) -> RiccatiSolution:
    """The stabilising solution with its gain and status, compiled as one program: the public
    solvers run it after their eager argument checks (docs/performance.md, "First calls outside
    jit"). In the filter forms (A, B) are the user's (F, H), transposed here, and so is K."""
    if filter_form:
        A, B = A.T, B.T
    G = jax.lax.stop_gradient(_input_gramian(B, R))  # for the balancing and the start
    d = jax.lax.stop_gradient(_balancing(A, G, Q))
    (A, B, Q), G = _balanced(d, A, B, Q), G / d / d[:, None]
    X, converged = (_dare if discrete else _care)(A, B, Q, R, G)
    balanced = _solution(A, B, Q, R, X, converged, discrete=discrete)
    X, K = balanced.X / d / d[:, None], balanced.K / d  # back from the balanced coordinates
    return eqx.tree_at(lambda s: (s.X, s.K), balanced, (X, K.T if filter_form else K))


def _solution(A, B, Q, R, X, converged, *, discrete: bool) -> RiccatiSolution:
    """X with its gain and status (module docstring: the status check)."""
    K, Ac, residual, scale, floor = (_dare_terms if discrete else _care_terms)(A, B, Q, R, X)
    # K is differentiable through X; the status carries no gradient
    Ac, residual, scale, floor = jax.lax.stop_gradient((Ac, residual, scale, floor))
    eps = jnp.finfo(X.dtype).eps
    relative = _frobenius(residual) / jnp.maximum(scale, jnp.finfo(X.dtype).tiny)
    # the residual certifies X to sqrt(eps) only where its own rounding level is below that,
    # and where the sizes it is measured by are finite
    uncertified = ~(eps * floor <= jnp.sqrt(eps) * scale) | ~jnp.isfinite(floor)
    if discrete:
        margin = -_log_spectral_radius(Ac)
    else:
        fastest = jnp.maximum(jnp.max(jnp.abs(Ac)), jnp.finfo(X.dtype).tiny)
        margin = -_log_spectral_radius(jax.scipy.linalg.expm(Ac / fastest))
    finite = jnp.all(jnp.isfinite(X)) & jnp.all(jnp.isfinite(K))
    status = (
        status_where(~finite, RiccatiStatus.NONFINITE)
        | status_where(~(margin > MARGIN_FACTOR * jnp.sqrt(eps)), RiccatiStatus.NOT_STABILISING)
        | status_where(
            ~converged | ~(relative <= jnp.sqrt(eps)) | uncertified, RiccatiStatus.INACCURATE
        )
    )
    return RiccatiSolution(X, K, status, relative, margin)


# --------------------------------------------------------------------------- argument checks
#: the eager checks' wording: control form (A, B, Q) and filter form (F, H, Q)
_CONTROL = {
    "names": ("A", "B", "Q", "R"),
    "unstabilisable": "(A, B): not stabilisable: the mode {lam} of A ({where}) is not "
    "controllable through B",
    "boundary": "(Q, A): no stabilising solution: the mode {lam} of A (on {boundary}) is not "
    "observable through Q",
}
_FILTER = {
    "names": ("F", "H", "Q", "R"),
    "unstabilisable": "(F, H): not detectable: the mode {lam} of F ({where}) is not observable "
    "through H",
    "boundary": "(F, Q): no stabilising solution: the mode {lam} of F (on {boundary}) is not "
    "excited by the process noise Q (not controllable through it)",
}


def _check_arguments(A, B, Q, R, *, discrete: bool, filter_form: bool = False):
    """Shapes always; symmetry, definiteness and the existence of a stabilising solution when
    the values are concrete. ``filter_form``: (A, B) are the user's (F, H), named so in the
    errors, whose modes are checked in control form (F^T, H^T). Returns the arrays in one
    floating dtype."""
    wording = _FILTER if filter_form else _CONTROL
    names = wording["names"]
    for name, value in zip(names, (A, B, Q, R), strict=True):
        if np.ndim(value) != 2:
            raise ValueError(f"{name}: expected a matrix, got shape {np.shape(value)}")
    check_matrix(names[0], A, square=True)
    n = np.shape(A)[0]
    if n == 0:
        raise ValueError(f"{names[0]}: has no states (shape {np.shape(A)})")
    m, n_of_B = np.shape(B) if filter_form else np.shape(B)[::-1]
    if n_of_B != n:
        side = "columns" if filter_form else "rows"
        raise ValueError(
            f"{names[1]}: expected {n} {side} to match {names[0]} ({n} x {n}), "
            f"got shape {np.shape(B)}"
        )
    if m == 0:
        what = "measurements" if filter_form else "inputs"
        raise ValueError(f"{names[1]}: has no {what} (shape {np.shape(B)})")
    check_matrix(names[1], B)  # finite and real
    check_matrix(names[2], Q, (n, n), psd=True)
    check_matrix(names[3], R, (m, m), spd=True)
    dtype = jnp.result_type(A, B, Q, R, jnp.zeros((), jnp.float32))
    A, B, Q, R = (jnp.asarray(v, dtype) for v in (A, B, Q, R))
    if all(is_concrete(v) for v in (A, B, Q)):
        control_A, control_B = (np.asarray(v, np.float64) for v in (A, B))
        if filter_form:
            control_A, control_B = control_A.T, control_B.T
        _check_modes(
            control_A,
            control_B,
            np.asarray(Q, np.float64),
            # R scales the balancing only (every R > 0 has the same answer): I where traced, as
            # under grad in R (a notebook's d MSE / d r), which np.asarray cannot read
            np.asarray(R, np.float64) if is_concrete(R) else np.eye(R.shape[0]),
            discrete,
            wording,
            max(1e-9, 100 * float(jnp.finfo(dtype).eps)),
        )
    return A, B, Q, R


def _unit_columns(M) -> np.ndarray:
    """M with each non-zero column scaled to unit norm: an input (a measurement) in other units
    scales B's column (H^T's) without changing which modes it reaches."""
    norms = np.linalg.norm(M, axis=0)
    return M / np.where(norms > 0, norms, 1.0)


def _check_modes(A, B, Q, R, discrete, wording, tol):
    """PBH tests: every mode of A outside or on the stability boundary (|lambda| >= 1, resp.
    Re lambda >= 0) must be controllable through B, and every mode on it observable through Q.
    ``tol`` (relative) is the boundary's width and the rank tolerance: 1e-9, or 100 eps of the
    arguments' dtype (float32 data put a mode on the unit circle only to within its rounding),
    relative to the norms of the matrices each test stacks: with Q's in the controllability
    test's, a large Q (1e12 in float64, 1e6 in float32) made (A, B) = (2, 1) "not
    stabilisable".
    The tests are made in the solver's balanced coordinates (:func:`_balancing`: D^-1 A D,
    D^-1 B, D Q D), with B's columns and Q scaled to unit norm, since units change none of the
    answers: a double integrator in mm and km/s, a measurement H = 1e-10 with R = 1e-20
    (H = R = 1 in other units), and a small process noise (Q = diag(0, 1e-12); in float32
    1e-5) were refused as having no solution, which the solver under ``jit`` found with
    status OK."""
    n = A.shape[0]
    sweep = _balancing_sweep(A, B @ np.linalg.solve(R, B.T), Q, np)
    log_d = np.zeros(n)
    for _ in range(_BALANCING_SWEEPS):
        log_d = sweep(log_d)
    A, B, Q = _balanced(np.exp2(np.round(log_d)), A, B, Q)
    B = _unit_columns(B)
    Q = Q / max(np.linalg.norm(Q, 2), np.finfo(np.float64).tiny)
    size = lambda *matrices: max(1.0, *(np.linalg.norm(M, 2) for M in matrices))
    rank_tol_B, rank_tol_Q = tol * size(A, B), tol * size(A, Q)
    smallest = lambda M: np.linalg.svd(M, compute_uv=False)[-1]
    where = "|lambda| >= 1" if discrete else "Re lambda >= 0"
    boundary = "the unit circle" if discrete else "the imaginary axis"
    for lam in np.linalg.eigvals(A):
        distance = abs(lam) - 1.0 if discrete else lam.real
        if distance < -tol:
            continue
        shifted = A - lam * np.eye(n)
        if smallest(np.hstack([shifted, B])) <= rank_tol_B:
            raise ValueError(wording["unstabilisable"].format(lam=f"{lam:.6g}", where=where))
        on_boundary = distance <= tol
        if on_boundary and smallest(np.vstack([shifted, Q])) <= rank_tol_Q:
            raise ValueError(wording["boundary"].format(lam=f"{lam:.6g}", boundary=boundary))


# --------------------------------------------------------------------------- public API
@working_precision_by_default
def solve_dare(
    A: Float[Array, "n n"], B: Float[Array, "n m"], Q: Float[Array, "n n"], R: Float[Array, "m m"]
) -> RiccatiSolution:
    """Stabilising solution X of X = A^T X A - A^T X B (R + B^T X B)^{-1} B^T X A + Q
    (scipy.linalg.solve_discrete_are's convention), with K = (R + B^T X B)^{-1} B^T X A.
    Q symmetric PSD, R symmetric PD."""
    arguments = _check_arguments(A, B, Q, R, discrete=True)
    return _solve(*arguments, discrete=True, filter_form=False)


@working_precision_by_default
def solve_care(
    A: Float[Array, "n n"], B: Float[Array, "n m"], Q: Float[Array, "n n"], R: Float[Array, "m m"]
) -> RiccatiSolution:
    """Stabilising solution X of A^T X + X A - X B R^{-1} B^T X + Q = 0
    (scipy.linalg.solve_continuous_are's convention), with K = R^{-1} B^T X.
    Q symmetric PSD, R symmetric PD."""
    arguments = _check_arguments(A, B, Q, R, discrete=False)
    return _solve(*arguments, discrete=False, filter_form=False)


@working_precision_by_default
def solve_filter_dare(
    F: Float[Array, "n n"], H: Float[Array, "m n"], Q: Float[Array, "n n"], R: Float[Array, "m m"]
) -> RiccatiSolution:
    """Steady-state prediction covariance Sigma = F Sigma F^T - F Sigma H^T (H Sigma H^T + R)^{-1}
    H Sigma F^T + Q of x(t+1) = F x(t) + w, y = H x + v (eq 5 of the Wiener-smoother paper, Q the
    covariance of w), stabilising: F - K H is Schur with K = F Sigma H^T (H Sigma H^T + R)^{-1},
    the one-step predictor gain. It exists when every mode of F with |lambda| >= 1 is
    observable through H and none on the unit circle is unexcited by Q."""
    arguments = _check_arguments(F, H, Q, R, discrete=True, filter_form=True)
    return _solve(*arguments, discrete=True, filter_form=True)


@working_precision_by_default
def solve_filter_care(
    F: Float[Array, "n n"], H: Float[Array, "m n"], Q: Float[Array, "n n"], R: Float[Array, "m m"]
) -> RiccatiSolution:
    """Steady-state Kalman-Bucy covariance: F Sigma + Sigma F^T - Sigma H^T R^{-1} H Sigma + Q = 0
    for dx/dt = F x + w, y = H x + v, stabilising: F - K H is Hurwitz with K = Sigma H^T R^{-1}."""
    arguments = _check_arguments(F, H, Q, R, discrete=False, filter_form=True)
    return _solve(*arguments, discrete=False, filter_form=True)


def lqr_gain(
    A: Float[Array, "n n"], B: Float[Array, "n m"], Q: Float[Array, "n n"], R: Float[Array, "m m"]
) -> Float[Array, "m n"]:
    """Continuous-time LQR gain K = R^{-1} B^T X with X = ``solve_care(A, B, Q, R).X``: the
    control u = -K x minimises the integral of x^T Q x + u^T R u subject to dx/dt = A x + B u.
    NaN where the solution's status is not OK (use :func:`solve_care` to see the status)."""
    solution = solve_care(A, B, Q, R)
    return jnp.where(solution.ok, solution.K, jnp.nan)
