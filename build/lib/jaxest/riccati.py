"""Algebraic Riccati equations in JAX: jit-able, vmap-able and differentiable.

Both solvers take scipy's (control) argument convention:

- :func:`solve_dare` solves  X = A^T X A - A^T X B (R + B^T X B)^{-1} B^T X A + Q
  (the filter form, eq 5 of the Wiener-smoother paper, is ``solve_dare(F.T, H.T, G Q G.T, R)``);
- :func:`solve_care` solves  A^T X + X A - X B R^{-1} B^T X + Q = 0;
- :func:`lqr_gain` is the continuous-time LQR gain K = R^{-1} B^T X (u = -K x).

They return the stabilising solution: the closed loop A - B K is Schur (discrete) / Hurwitz
(continuous). They assume (A, B) stabilisable and (Q, A) detectable (every mode of A outside the
stability region is controllable through B and observable through Q); then that solution is also
the unique positive semidefinite one, and the doubling iteration is guaranteed to converge to it.
When the arguments are concrete (not traced) both conditions are checked and a ``ValueError`` says
which mode fails; under ``jit``/``vmap`` a violated assumption shows up as NaN or a
non-stabilising result instead.

Forward solvers: the structured doubling algorithm (SDA) for the DARE and the matrix sign function
of the Hamiltonian for the CARE, both with quadratic convergence. Gradients (reverse mode) come
from implicit differentiation: with K the optimal gain and A_c = A - B K, the derivative dX of
either equation solves a Stein (discrete) or Lyapunov (continuous) equation in A_c, so the
cotangent needs one adjoint solve, A_c Y A_c^T - Y + Xbar = 0 resp. A_c Y + Y A_c^T + Xbar = 0,
after which Qbar = Y, Rbar = K Y K^T, Abar = 2 X A_c Y (discrete) or 2 X Y (continuous) and
Bbar = -Abar K^T.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxest.checks import check_matrix, is_concrete
from jaxest.linalg import symmetrize

_MAX_ITERATIONS = 100


def _converge(update, start, size):
    """Iterate ``update(carry) -> (carry, relative_change)`` from ``start`` with a quadratically
    convergent method: stop two iterations after the change first drops below sqrt(eps) (by then
    it is at rounding level), after ``_MAX_ITERATIONS`` or once the change is not finite."""
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
    final, *_ = jax.lax.while_loop(cond, body, (start, one, 0, 0))
    return final


def _relative_change(new, old):
    scale = jnp.maximum(jnp.max(jnp.abs(new)), jnp.finfo(new.dtype).tiny)
    return jnp.max(jnp.abs(new - old)) / scale


# --------------------------------------------------------------------------- Stein / Lyapunov
@jax.jit
def _solve_stein(T, C):
    """Y = T Y T^T + C for Schur-stable T, by squared Smith doubling:
    Y_{j+1} = Y_j + T_j Y_j T_j^T, T_{j+1} = T_j^2 (Y_j sums the first 2^j terms)."""

    def update(carry):
        Y, Tj = carry
        Y_new = Y + Tj @ Y @ Tj.T
        return (Y_new, Tj @ Tj), _relative_change(Y_new, Y)

    Y, _ = _converge(update, (C, T), C)
    return Y


@jax.jit
def _solve_lyapunov(Ac, C):
    """Y with Ac Y + Y Ac^T + C = 0 for Hurwitz Ac, through the Cayley transform
    T = (Ac - g I)^{-1} (Ac + g I), which maps it to the Stein equation
    Y = T Y T^T + 2 g (Ac - g I)^{-1} C (Ac - g I)^{-T}."""
    n = Ac.shape[-1]
    eye = jnp.eye(n, dtype=Ac.dtype)
    g = jnp.maximum(jnp.linalg.norm(Ac) / jnp.sqrt(n), jnp.finfo(Ac.dtype).tiny)
    shifted = jax.scipy.linalg.lu_factor(Ac - g * eye)  # one factorisation, three solves
    T = jax.scipy.linalg.lu_solve(shifted, Ac + g * eye)
    M = jax.scipy.linalg.lu_solve(shifted, C)
    return _solve_stein(T, 2 * g * jax.scipy.linalg.lu_solve(shifted, M.T).T)


# --------------------------------------------------------------------------- forward solvers
@jax.jit
def _dare_sda(A, B, Q, R):
    """Structured doubling: A_0 = A, G_0 = B R^-1 B^T, H_0 = Q; with W = I + G_k H_k,
    A_{k+1} = A_k W^-1 A_k, G_{k+1} = G_k + A_k W^-1 G_k A_k^T, H_{k+1} = H_k + A_k^T H_k W^-1 A_k;
    H_k converges quadratically to the stabilising X."""
    n = A.shape[-1]
    eye = jnp.eye(n, dtype=A.dtype)
    G = symmetrize(B @ jnp.linalg.solve(R, B.T))

    def update(carry):
        Ak, Gk, Hk = carry
        W = eye + Gk @ Hk
        WA, WG = jnp.split(jnp.linalg.solve(W, jnp.concatenate([Ak, Gk], axis=1)), 2, axis=1)
        H_new = symmetrize(Hk + Ak.T @ Hk @ WA)
        new = (Ak @ WA, symmetrize(Gk + Ak @ WG @ Ak.T), H_new)
        return new, _relative_change(H_new, Hk)

    _, _, X = _converge(update, (A, G, symmetrize(Q)), Q)
    return X


@jax.jit
def _care_sign(A, B, Q, R):
    """Matrix sign function of the Hamiltonian Z = [[A, -G], [-Q, -A^T]] (G = B R^-1 B^T) by the
    determinant-scaled Newton iteration Z <- (c Z + (c Z)^-1) / 2; the stable invariant subspace
    [I; X] is the null space of sign(Z) + I, so [[W12], [W22 + I]] X = -[[W11 + I], [W21]]."""
    n = A.shape[-1]
    G = B @ jnp.linalg.solve(R, B.T)
    Z = jnp.block([[A, -G], [-Q, -A.T]])

    def update(Zk):
        _, logdet = jnp.linalg.slogdet(Zk)
        c = jnp.exp(-logdet / (2 * n))
        Z_new = 0.5 * (c * Zk + jnp.linalg.inv(Zk) / c)
        return Z_new, _relative_change(Z_new, Zk)

    W = _converge(update, Z, Q)
    eye = jnp.eye(n, dtype=A.dtype)
    lhs = jnp.concatenate([W[:n, n:], W[n:, n:] + eye])
    rhs = -jnp.concatenate([W[:n, :n] + eye, W[n:, :n]])
    X = jnp.linalg.lstsq(lhs, rhs)[0]
    return symmetrize(X)


# --------------------------------------------------------------------------- implicit gradients
@jax.custom_vjp
def _dare(A, B, Q, R):
    return _dare_sda(A, B, Q, R)


def _dare_fwd(A, B, Q, R):
    X = _dare_sda(A, B, Q, R)
    return X, (A, B, R, X)


def _dare_bwd(residuals, Xbar):
    A, B, R, X = residuals
    K = jnp.linalg.solve(R + B.T @ X @ B, B.T @ X @ A)
    Ac = A - B @ K
    Y = _solve_stein(Ac, symmetrize(Xbar))
    Abar = 2 * X @ Ac @ Y
    return Abar, -Abar @ K.T, Y, K @ Y @ K.T


_dare.defvjp(_dare_fwd, _dare_bwd)


@jax.custom_vjp
def _care(A, B, Q, R):
    return _care_sign(A, B, Q, R)


def _care_fwd(A, B, Q, R):
    X = _care_sign(A, B, Q, R)
    return X, (A, B, R, X)


def _care_bwd(residuals, Xbar):
    A, B, R, X = residuals
    K = jnp.linalg.solve(R, B.T @ X)
    Y = _solve_lyapunov(A - B @ K, symmetrize(Xbar))
    Abar = 2 * X @ Y
    return Abar, -Abar @ K.T, Y, K @ Y @ K.T


_care.defvjp(_care_fwd, _care_bwd)


# --------------------------------------------------------------------------- argument checks
def _check_arguments(A, B, Q, R, *, discrete: bool):
    """Shapes always; symmetry, definiteness, stabilisability and the boundary-mode condition when
    the values are concrete. Returns the arrays in one floating dtype."""
    for name, value in (("A", A), ("B", B), ("Q", Q), ("R", R)):
        if np.ndim(value) != 2:
            raise ValueError(f"{name}: expected a matrix, got shape {np.shape(value)}")
    n, m = np.shape(B)
    check_matrix("A", A, (n, n))
    check_matrix("Q", Q, (n, n), psd=True)
    check_matrix("R", R, (m, m), spd=True)
    dtype = jnp.result_type(A, B, Q, R, jnp.zeros((), jnp.float32))
    A, B, Q, R = (jnp.asarray(v, dtype) for v in (A, B, Q, R))
    if all(is_concrete(v) for v in (A, B, Q)):
        _check_modes(
            np.asarray(A, np.float64),
            np.asarray(B, np.float64),
            np.asarray(Q, np.float64),
            discrete,
        )
    return A, B, Q, R


def _check_modes(A, B, Q, discrete):
    """PBH tests on the modes of A outside the stability region (|lambda| >= 1, resp.
    Re lambda >= 0): each must be controllable through B and observable through Q."""
    n = A.shape[0]
    scale = max(1.0, np.linalg.norm(A, 2), np.linalg.norm(B, 2), np.linalg.norm(Q, 2))
    tol = 1e-9 * scale
    where = "|lambda| >= 1" if discrete else "Re lambda >= 0"
    for lam in np.linalg.eigvals(A):
        if (abs(lam) - 1.0 if discrete else lam.real) < -1e-9:
            continue
        shifted = A - lam * np.eye(n)
        if np.linalg.svd(np.hstack([shifted, B]), compute_uv=False)[-1] <= tol:
            raise ValueError(
                f"(A, B): not stabilisable: the mode {lam:.6g} of A ({where}) is not controllable "
                "through B"
            )
        if np.linalg.svd(np.vstack([shifted, Q]), compute_uv=False)[-1] <= tol:
            raise ValueError(
                f"(Q, A): not detectable: the mode {lam:.6g} of A ({where}) is not observable "
                "through Q"
            )


# --------------------------------------------------------------------------- public API
def solve_dare(
    A: Float[Array, "n n"], B: Float[Array, "n m"], Q: Float[Array, "n n"], R: Float[Array, "m m"]
) -> Float[Array, "n n"]:
    """Stabilising solution X of X = A^T X A - A^T X B (R + B^T X B)^{-1} B^T X A + Q
    (scipy.linalg.solve_discrete_are's convention; filter form: ``solve_dare(F.T, H.T, GQG^T, R)``
    gives the steady-state prediction covariance, eq 5). Q symmetric PSD, R symmetric PD."""
    return _dare(*_check_arguments(A, B, Q, R, discrete=True))


def solve_care(
    A: Float[Array, "n n"], B: Float[Array, "n m"], Q: Float[Array, "n n"], R: Float[Array, "m m"]
) -> Float[Array, "n n"]:
    """Stabilising solution X of A^T X + X A - X B R^{-1} B^T X + Q = 0
    (scipy.linalg.solve_continuous_are's convention). Q symmetric PSD, R symmetric PD."""
    return _care(*_check_arguments(A, B, Q, R, discrete=False))


def lqr_gain(
    A: Float[Array, "n n"], B: Float[Array, "n m"], Q: Float[Array, "n n"], R: Float[Array, "m m"]
) -> Float[Array, "m n"]:
    """Continuous-time LQR gain K = R^{-1} B^T X with X = ``solve_care(A, B, Q, R)``: the control
    u = -K x minimises the integral of x^T Q x + u^T R u subject to dx/dt = A x + B u."""
    A, B, Q, R = _check_arguments(A, B, Q, R, discrete=False)
    return jnp.linalg.solve(R, B.T @ _care(A, B, Q, R))
