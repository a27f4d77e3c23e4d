"""Small linear-algebra pieces shared by the estimators, and the precision of their products.

**Matrix products in the working precision.** JAX's default precision for float32 matrix
products is the platform's: full float32 on CPUs, TF32 (10 mantissa bits) on recent NVIDIA GPUs.
On an H100, TF32 cost the parallel Kalman filter about two digits of its float32 log-likelihood
at n = 20, enough to flag the standard form inconsistent, and traced at "highest" it cost no
time (docs/parallel.md, "Float32 on a GPU"). So every estimator's entry point (``run``, the
smoothers, ``fit_em``, the Riccati solvers, ``simulate``) is traced under
:func:`working_precision_by_default`: float32 means float32 unless the caller has chosen a
precision (``jax.default_matmul_precision(...)`` or the ``jax_default_matmul_precision``
setting), which is then respected. Code whose correctness rests on the precision (the
set-membership filter's rounding bounds) uses :func:`working_precision`, which holds whatever
the caller chose. The precision is fixed when a product is traced: a ``custom_vjp`` backward
rule, traced after its forward call has returned, carries the decorator itself (the Riccati
solvers' implicit gradients), and a loop of one's own over ``estimator.step`` is traced at
whatever precision surrounds it. On a CPU neither changes anything: XLA compiles the same
program whatever the products' precision attribute (checked on the flight EKF).

The eigen/SVD factorisation P = U diag(D)^2 U^T is not unique when eigenvalues repeat (P0 = c I,
isotropic Q), and ``jnp.linalg.svd``'s derivative divides by differences of singular values, so it
is NaN there. Estimators whose outputs depend on P only through U D^2 U^T are differentiated at the
covariance level instead: :func:`factor_psd` and :func:`cov_tangent_to_factor` choose, for a
covariance tangent dP, the factor tangent dU = 1/2 dP U^-T D^-2, dD = 0, which reproduces dP exactly
(dU D^2 U^T + U D^2 dU^T = dP), at every order of differentiation, and is finite whatever the
multiplicities (docs/papers/svd_ekf.md, "Gradients through an SVD").
"""

from __future__ import annotations

import functools
import operator

import jax
import jax.numpy as jnp
from jax.ad_checkpoint import checkpoint_name
from jax.custom_derivatives import SymbolicZero


def working_precision(fn):
    """``fn`` traced under ``jax.default_matmul_precision("highest")``: its matrix products, and
    those of the functions it calls (a model's f and h included), are rounded in the working
    precision whatever JAX's default on the platform or the caller's choice (module docstring).
    The precision is fixed when a product is traced, so this holds under ``jit``, ``vmap`` and
    ``grad`` of ``fn``."""
    return _traced_at_highest(fn, keep_callers_choice=False)


def working_precision_by_default(fn):
    """As :func:`working_precision`, unless the caller has set a matrix-product precision
    (``jax.default_matmul_precision(...)`` around the call or the
    ``jax_default_matmul_precision`` setting): then ``fn`` is traced at the caller's."""
    return _traced_at_highest(fn, keep_callers_choice=True)


def _traced_at_highest(fn, keep_callers_choice: bool):
    @functools.wraps(fn)
    def traced_at_working_precision(*args, **kwargs):
        if keep_callers_choice and jax.config.jax_default_matmul_precision is not None:
            return fn(*args, **kwargs)
        with jax.default_matmul_precision("highest"):
            return fn(*args, **kwargs)

    return traced_at_working_precision


def astype(tree, dtype):
    """``tree`` (a model, a prior, data, a result, or a tuple of them) with every real
    floating-point array cast to ``dtype``; other leaves (integer, boolean, complex and PRNG key
    arrays, Python numbers, functions) as they are. ``je.astype((model, prior, ys),
    jnp.float32)`` runs a study in float32; ``jnp.float64`` is float32 unless
    ``jax_enable_x64`` is on. ``dtype`` must be a floating-point type (``ValueError``
    otherwise)."""
    try:
        floating_dtype = jnp.dtype(dtype)
    except TypeError as err:
        raise ValueError(f"dtype: not a data type: {dtype!r}") from err
    if not jnp.issubdtype(floating_dtype, jnp.floating):
        raise ValueError(f"dtype: expected a floating-point type, got {floating_dtype}")

    def cast(leaf):
        floating = hasattr(leaf, "dtype") and jnp.issubdtype(leaf.dtype, jnp.floating)
        return jnp.asarray(leaf, dtype) if floating else leaf

    return jax.tree.map(cast, tree)


def symmetrize(P):
    """(P + P^T) / 2 over the last two axes."""
    return 0.5 * (P + jnp.swapaxes(P, -1, -2))


def cov_from_factor(U, D):
    """P = U diag(D)^2 U^T (over the last axes: stacked factors give stacked P)."""
    return (U * D[..., None, :] ** 2) @ jnp.swapaxes(U, -1, -2)


def factor_tangent_to_cov(U, D, dU, dD):
    """The covariance tangent dP of P = U D^2 U^T for factor tangents (dU, dD)."""
    half = (dU * D**2) @ U.T + (U * (D * dD)) @ U.T
    return half + half.T


def tangent_or_zeros(tangent, primal):
    """``tangent``, or zeros shaped as ``primal`` where it is ``None``: the tangent of an
    argument ``eqx.filter_custom_jvp`` was not asked to differentiate."""
    return jnp.zeros_like(primal) if tangent is None else tangent


def root_tangent_to_cov(L, dL):
    """The covariance tangent dP = dL L^T + L dL^T of P = L L^T (any leading axes; ``dL`` None
    for a zero tangent), in ``jnp.matmul``, which reverse mode can transpose where ``dL`` is
    a tangent."""
    if dL is None:
        return jnp.zeros(L.shape[:-1] + L.shape[-2:-1], L.dtype)
    half = dL @ jnp.swapaxes(L, -1, -2)
    return half + jnp.swapaxes(half, -1, -2)


def cov_tangent_to_factor(U, D, dP):
    """A factor tangent (dU, dD) = (dP U^-T D^-2 / 2, 0) whose covariance tangent is ``dP``
    (``factor_tangent_to_cov``), defined where D has repeated entries, where the SVD's own
    tangent is not (see module docstring).

    U^-T is U for the orthogonal factors given here, but it is differentiated as an inverse
    (:func:`_orthogonal_inverse_transpose`): then dU D^2 U^T = dP / 2 holds for every U, not only
    an orthogonal one, so factors moved along these tangents keep U D^2 U^T = P to every order,
    and second derivatives through the SVD filters equal the covariance filters'. (With U in
    place of U^-T their forward-over-forward Hessians were wrong.)"""
    return 0.5 * dP @ (_orthogonal_inverse_transpose(U) / D**2), jnp.zeros_like(D)


@jax.custom_jvp
def _orthogonal_inverse_transpose(U):
    """U^-T of an orthogonal U (U itself), with the inverse's tangent -U^-T dU^T U^-T."""
    return U


@_orthogonal_inverse_transpose.defjvp
def _orthogonal_inverse_transpose_jvp(primals, tangents):
    (U,), (dU,) = primals, tangents
    inverse_transpose = _orthogonal_inverse_transpose(U)
    return inverse_transpose, -inverse_transpose @ dU.T @ inverse_transpose


#: the name (``jax.ad_checkpoint.checkpoint_name``) of the SVD and eigen factors that the
#: covariance-level derivative rules read. A step recomputed in the reverse pass keeps them from
#: the forward pass (``AbstractGaussianFilter.checkpoint_policy``): factors are not unique where
#: singular values repeat, and a recomputed factor can differ from the one the next step was given.
FACTORS = "svd_factors"


def keep_factors(*factors):
    """``factors``, named :data:`FACTORS` for a recomputing reverse pass to keep."""
    return checkpoint_name(factors, FACTORS)


@jax.custom_jvp
def factor_psd(P):
    """U, D with P = U diag(D)^2 U^T (U orthogonal, D >= 0 descending) by a symmetric SVD.

    LAPACK's eigh at every size: :func:`jacobi_svd` gives the same factors (tested), but in the
    SVD-EKF (linear 4 x 2 and 6 x 3 models, 200 runs under ``vmap``) it compiled slower (2.7 and
    7.1 s against 2.2 and 3.5 s) and ran slower (3.7 and 20 against 3.0 and 17 us per step)."""
    w, U = jnp.linalg.eigh(symmetrize(P))
    return U[..., :, ::-1], jnp.sqrt(jnp.clip(w[..., ::-1], 0.0))


@factor_psd.defjvp
def _factor_psd_jvp(primals, tangents):
    (P,), (dP,) = primals, tangents
    U, D = keep_factors(*factor_psd(P))
    return (U, D), cov_tangent_to_factor(U, D, symmetrize(dP))


def factor_psd_or_nan(P):
    """:func:`factor_psd`, with D NaN where P is indefinite beyond rounding: an eigenvalue below
    about -64 n eps max|P_ij|, seen as the part of P the clipped factors miss. For the noise and
    prior covariances the SVD filters factor, which must be positive semidefinite: clipping
    would change the model silently under ``jit`` (where the argument checks cannot see values);
    a NaN shows in the step's status instead."""
    U, D = factor_psd(P)
    n = P.shape[-1]
    scale = jnp.max(jnp.abs(P), axis=(-2, -1))
    missed = jnp.max(jnp.abs(symmetrize(P) - cov_from_factor(U, D)), axis=(-2, -1))
    indefinite = missed > 64 * n * jnp.finfo(P.dtype).eps * scale
    return U, jnp.where(indefinite[..., None], jnp.nan, D)


def right_svd(A):
    """Singular values s (descending) and right singular vectors V of a tall A (p >= n), so
    A^T A = V diag(s)^2 V^T: :func:`jacobi_svd` for at most ``SMALL_FACTOR`` columns and
    ``2 * SMALL_FACTOR`` rows, LAPACK otherwise. The row bound is compile time, since the
    sweep grows with the rows. Measured against Jacobi, 100 matrices under ``vmap``: the
    improved SVD filter's 29 x 6 innovation factor on the flight model compiles in 0.16 against
    1.4 s and runs in 12 against 13 us per matrix; the order-3 Gauss-Hermite SVD form's 85 x 4
    time update on bearings in 0.25 against 0.8 s and 8.1 against 8.7 us.
    Not differentiated itself (its callers define their derivatives at the covariance level)."""
    if A.shape[-1] > SMALL_FACTOR or A.shape[-2] > 2 * SMALL_FACTOR:
        _, s, Vt = jnp.linalg.svd(A, full_matrices=False)
        return s, jnp.swapaxes(Vt, -1, -2)
    s, V = jacobi_svd(A)
    s, (V,) = _descending(s, V)
    return s, V


#: sweeps of :func:`jacobi_svd` by matrix width n. Measured (300 matrices of each kind, float32
#: and float64: Gaussian, columns graded 1 .. 1e-9, condition 1e12, repeated singular values,
#: symmetric PSD of rank n and n - 1): the largest off-diagonal cosine |a_i . a_j| / (|a_i| |a_j|)
#: reached its floor of about eps after 3 (n = 2), 4 (3), 5 (4), 6 (6) and 8 (8) sweeps; one
#: more than that here (n = 5, 7 from their neighbours). tests/test_linalg.py checks the result.
JACOBI_SWEEPS = {1: 0, 2: 4, 3: 5, 4: 6, 5: 7, 6: 7, 7: 9, 8: 9}


def _rotation(alpha, beta, gamma):
    """(c, s) of the plane rotation that makes the 2 x 2 Gram matrix [[alpha, gamma], [gamma,
    beta]] diagonal (Rutishauser's formulas, the smaller angle); none where |gamma| <= eps
    sqrt(alpha beta) (the pair is orthogonal to working accuracy)."""
    eps = jnp.finfo(alpha.dtype).eps
    rotate = jnp.abs(gamma) > eps * jnp.sqrt(jnp.abs(alpha)) * jnp.sqrt(jnp.abs(beta))
    zeta = (beta - alpha) / (2 * jnp.where(rotate, gamma, 1))
    t = jnp.where(zeta >= 0, 1.0, -1.0) / (jnp.abs(zeta) + jnp.hypot(1.0, zeta))
    c = 1 / jnp.sqrt(1 + t * t)
    return jnp.where(rotate, c, 1.0), jnp.where(rotate, c * t, 0.0)


def jacobi_svd(A, sweeps: int | None = None):
    """One-sided (Hestenes) cyclic Jacobi SVD of A (..., p, n): returns (s, V) with
    A V = U diag(s) (U's columns orthonormal), s >= 0 unsorted.

    A sweep is unrolled over the column pairs and the sweeps are a ``fori_loop``: unrolling the
    sweeps as well made XLA compile 3-6x longer (12 x 6: 4.8 against 1.7 s; 16 x 8: 15 against
    2.4 s) and run no faster; a loop over the pairs compiles 2-4x faster again but runs 2-4x
    slower (column gathers and scatters in place of fused elementwise code).

    A V is formed by plane rotations of A's columns; A^T A is never formed, so small singular
    values keep their relative accuracy (Demmel & Veselic 1992), which the SVD filters need.
    Elementwise over the batch: no LAPACK call. ``sweeps`` defaults to ``JACOBI_SWEEPS[n]``.
    """
    n = A.shape[-1]
    sweeps = JACOBI_SWEEPS.get(n, 10) if sweeps is None else sweeps
    cols = [A[..., :, i] for i in range(n)]
    eye = jnp.eye(n, dtype=A.dtype)
    vcols = [jnp.broadcast_to(eye[:, i], (*A.shape[:-2], n)) for i in range(n)]

    def sweep(_, carry):
        cols, vcols = map(list, carry)
        for i in range(n - 1):
            for j in range(i + 1, n):
                a, b = cols[i], cols[j]
                alpha, beta, gamma = (jnp.sum(x * y, -1) for x, y in ((a, a), (b, b), (a, b)))
                c, s = (r[..., None] for r in _rotation(alpha, beta, gamma))
                cols[i], cols[j] = c * a - s * b, s * a + c * b
                v, w = vcols[i], vcols[j]
                vcols[i], vcols[j] = c * v - s * w, s * v + c * w
        return cols, vcols

    cols, vcols = jax.lax.fori_loop(0, sweeps, sweep, (cols, vcols))
    s = jnp.stack([jnp.sqrt(jnp.sum(c * c, -1)) for c in cols], -1)
    return s, jnp.stack(vcols, -1)


def _descending(keys, *matrices):
    """``keys`` (..., n) sorted descending, and each matrix's columns in the same order (a
    stable sort by comparisons and a permutation product: elementwise, no sort call)."""
    n = keys.shape[-1]
    ki, kj = keys[..., :, None], keys[..., None, :]
    before = (kj > ki) | ((kj == ki) & (jnp.arange(n)[None, :] < jnp.arange(n)[:, None]))
    rank = jnp.sum(before, -1)  # position of entry i after sorting
    perm = (rank[..., :, None] == jnp.arange(n)).astype(keys.dtype)  # perm[i, r]
    return mv(jnp.swapaxes(perm, -1, -2), keys), tuple(mm(M, perm) for M in matrices)


def cho_solve_lower(L, B):
    """Solve (L L^T) X = B for lower-triangular L."""
    Z = solve_triangular(L, B, lower=True)
    return solve_triangular(jnp.swapaxes(L, -1, -2), Z, lower=False)


def chol_inverse(L):
    """(L L^T)^-1, symmetric, from the lower-triangular factor L."""
    return symmetrize(cho_solve_lower(L, jnp.eye(L.shape[-1], dtype=L.dtype)))


def inv_spd(P):
    """Inverse of a symmetric positive definite matrix through its Cholesky factor."""
    return chol_inverse(cholesky(P))


def logdet_chol(L):
    """ln det (L L^T) from the lower-triangular factor L (positive diagonal)."""
    return 2.0 * jnp.sum(jnp.log(jnp.diag(L)))


#: largest m * k * n for which :func:`mm` multiplies by broadcasting instead of a dot
SMALL_MATMUL = 512
#: under ``vmap`` on the CPU, the largest m * k * n that :func:`mm` writes as the rank-one sum;
#: above it the batched dot (the rank-one sum's consumers recompute it, see :func:`mm`)
SMALL_BATCHED_MATMUL = 200


def mm(a, b):
    """Matrix product ``a @ b`` (last two axes), fast for the small matrices filters use.

    XLA's CPU dot has a fixed cost per call that dominates for, say, 4 x 4 matrices inside a
    ``scan`` (measured 4-10x slower than a fused multiply-and-sum); above ``SMALL_MATMUL``
    multiply-adds the ordinary dot is used. Below it the product is written elementwise, in the
    form that is fastest for how it runs, which only ``vmap`` knows (a ``custom_vmap``):

    - one sequence: a multiply-and-reduce over the middle axis. The sum of rank-one terms
      a[:, k] b[k, :] reads strided column slices: a scan of A P A^T ran 1.2-6.6x slower with
      it (3 x 3 to 8 x 8), and the 6 x 3 Kalman filter's value_and_grad took 14.6-14.9
      against 6.5-6.7 us per step.
    - under ``vmap``: the sum over k of the rank-one terms, which XLA:CPU vectorises over the
      whole batch, where the multiply-and-reduce runs as scalar loops of length k (4 x 2
      Kalman filter, 200 runs: 3.4x faster per step), up to ``SMALL_BATCHED_MATMUL``
      multiply-adds. Above it, on the CPU, the batched dot: XLA fuses the rank-one sum into
      its consumer, and a consumer that reads each entry several times recomputes it per entry
      written (the inner product of a 6-state Joseph update six times over). 200 runs of the
      Kalman filter: 6 states 0.77 -> 0.66 us per step and run, 7 states 1.59 -> 0.83; below
      the threshold the dot is slower. An NVIDIA H200 runs the rank-one sum faster at every
      size, so other platforms keep it (``lax.platform_dependent``; docs/performance.md has
      the figures).

    The derivative is the multiply-and-reduce in both cases (its transpose is again one per
    operand). ``custom_vmap`` cannot be transposed, so a custom derivative rule must not apply
    :func:`mm` to tangents (reverse mode would fail): ``jnp.matmul`` there.
    """
    if _multiply_adds(a, b) > SMALL_MATMUL:
        return a @ b
    return _small_mm(a, b)


def _multiply_adds(a, b) -> int:
    """m * k * n of one product a @ b: its size, which the thresholds above compare."""
    return a.shape[-2] * a.shape[-1] * b.shape[-1]


def mv(a, x):
    """Matrix-vector product ``a @ x`` (``a`` (..., m, k), ``x`` (..., k)) as :func:`mm`."""
    return mm(a, x[..., None])[..., 0]


def _unit_slices(A, axis):
    """A's slices of width one along ``axis`` (-1 or -2), each keeping that axis."""
    axis = A.ndim + axis
    return jax.lax.split(A, (1,) * A.shape[axis], axis=axis)


def _reduce_mm(a, b):
    return jnp.sum(a[..., :, :, None] * b[..., None, :, :], axis=-2)


def _rank_one_mm(a, b):
    terms = (c * r for c, r in zip(_unit_slices(a, -1), _unit_slices(b, -2), strict=True))
    return functools.reduce(operator.add, terms)


@jax.custom_batching.custom_vmap
def _product(a, b):
    return _reduce_mm(a, b)


@_product.def_vmap
def _batched_product(axis_size, in_batched, a, b):
    if not any(in_batched):
        return _reduce_mm(a, b), False
    if _multiply_adds(a, b) > SMALL_BATCHED_MATMUL:
        return jax.lax.platform_dependent(a, b, cpu=jnp.matmul, default=_rank_one_mm), True
    return _rank_one_mm(a, b), True


@jax.custom_jvp
def _small_mm(a, b):
    return _product(a, b)


def _small_mm_jvp(primals, tangents):
    # The tangent as one multiply-and-reduce: its transpose (the reverse pass) is again one
    # multiply-and-reduce per operand, where the rank-one sum's would be a pad per term
    # (measured 1.7x slower gradients of the 4x2 Kalman filter); a zero tangent (a constant
    # operand) adds no term.
    (a, b), (da, db) = primals, tangents
    out = _small_mm(a, b)
    terms = []
    if not isinstance(da, SymbolicZero):
        terms.append(_reduce_mm(da, b))
    if not isinstance(db, SymbolicZero):
        terms.append(_reduce_mm(a, db))
    return out, sum(terms[1:], terms[0]) if terms else jnp.zeros_like(out)


_small_mm.defjvp(_small_mm_jvp, symbolic_zeros=True)


def sandwich(A, P):
    """A P A^T."""
    return mm(mm(A, P), jnp.swapaxes(A, -1, -2))


#: largest matrix size whose Cholesky factor and triangular solves are unrolled into fused
#: elementwise jnp code instead of a LAPACK call (whose fixed per-call cost dominates small
#: batched matrices on CPU)
SMALL_FACTOR = 8


def cholesky(A):
    """Lower Cholesky factor of SPD ``A`` (last two axes); NaN where ``A`` is not positive
    definite, as LAPACK's. Unrolled over the matrix size up to ``SMALL_FACTOR``."""
    if A.shape[-1] > SMALL_FACTOR:
        return jnp.linalg.cholesky(A)
    return _small_cholesky(A)


def solve_triangular(L, B, *, lower: bool):
    """X with L X = B for triangular ``L`` (B a matrix, or a vector); substitution unrolled up
    to ``SMALL_FACTOR``."""
    if L.shape[-1] > SMALL_FACTOR:
        return jax.scipy.linalg.solve_triangular(L, B, lower=lower)
    if B.ndim == L.ndim - 1:
        return solve_triangular(L, B[..., None], lower=lower)[..., 0]
    return _small_solve_triangular(L, B, lower)


# The two unrolled kernels carry matrix-level derivatives, written with the same unrolled
# substitutions. Differentiating the unrolled scalar recursions instead wrote the 6 x 3 Kalman
# filter's value_and_grad as 261 fusions (81 with LAPACK), compiled in 4.7 s (LAPACK: 1.5 s);
# with these rules it is 189 fusions and 4.0 s.
#
# The unrolled kernels (and :func:`mm`'s rank-one sum) take a matrix apart with one ``split``
# per axis, not one entry at a time (A[..., i, j]: a slice and a reshape per entry), and the
# Cholesky factor keeps its pieces' unit axes so that they combine without reshapes or
# broadcasts. The 6 x 3 Kalman filter's value_and_grad under ``vmap`` has a jaxpr of 3 451 lines
# instead of 7 002 and its first call (trace, lower, compile) takes 1.83-1.84 s instead of
# 2.38-2.43 s, running as fast (docs/performance.md, "Compile time of the small-matrix
# kernels").


def _entries(A):
    """A's entries as rows of (..., 1, 1) pieces: ``_entries(A)[i][j]`` is A[..., i:i+1, j:j+1]."""
    return [_unit_slices(row, -1) for row in _unit_slices(A, -2)]


def _assemble(rows):
    """The inverse of :func:`_entries`: rows of (..., 1, 1) pieces as one matrix."""
    axis = rows[0][0].ndim - 1
    return jax.lax.concatenate([jax.lax.concatenate(row, axis) for row in rows], axis - 1)


def _unrolled_cholesky(A):
    n = A.shape[-1]
    a = _entries(A)
    L = [[None] * n for _ in range(n)]
    for j in range(n):
        for i in range(j, n):  # column j, its diagonal first
            rest = functools.reduce(operator.sub, (L[i][k] * L[j][k] for k in range(j)), a[i][j])
            L[i][j] = jnp.sqrt(rest) if i == j else rest / L[j][j]
    zero = jnp.zeros_like(a[0][0])
    return _assemble([[L[i][j] if j <= i else zero for j in range(n)] for i in range(n)])


def _unrolled_substitution(L, B, lower):
    """X with L X = B (B a matrix), reading only L's ``lower`` or upper triangle. B's rows and
    the solution's are kept as (..., p) arrays: as (..., 1, p) pieces the 4 x 2 Kalman filter's
    value_and_grad under ``vmap`` ran 1.3x slower."""
    n = L.shape[-1]
    entries = [_unit_slices(row[..., 0, :], -1) for row in _unit_slices(L, -2)]  # (..., 1) each
    b = [row[..., 0, :] for row in _unit_slices(B, -2)]
    X = [None] * n
    for i in range(n) if lower else range(n - 1, -1, -1):
        done = range(i) if lower else range(i + 1, n)
        acc = functools.reduce(operator.sub, (entries[i][k] * X[k] for k in done), b[i])
        X[i] = acc / entries[i][i]
    return jnp.stack(X, -2)


@jax.custom_jvp
def _small_cholesky(A):
    return _unrolled_cholesky(A)


@_small_cholesky.defjvp
def _small_cholesky_jvp(primals, tangents):
    (A,), (dA,) = primals, tangents
    L = _small_cholesky(A)
    return L, cholesky_tangent(L, dA)


def cholesky_tangent(L, dA):
    """The tangent dL of the Cholesky factor L of A along dA: dL = L Phi(L^-1 dA L^-T), Phi = the
    lower triangle with its diagonal halved (Murray, "Differentiation of the Cholesky
    decomposition", 2016); dA symmetrised first, as ``jnp.linalg.cholesky``'s derivative does.
    Substitutions unrolled up to ``SMALL_FACTOR``."""
    if L.shape[-1] > SMALL_FACTOR:
        solve = functools.partial(jax.scipy.linalg.solve_triangular, lower=True)
        product = jnp.matmul
    else:
        solve = functools.partial(_unrolled_substitution, lower=True)
        product = _reduce_mm
    Y = solve(L, symmetrize(dA))
    S = solve(L, jnp.swapaxes(Y, -1, -2))
    Phi = jnp.tril(S) - 0.5 * jnp.eye(L.shape[-1], dtype=L.dtype) * S
    return product(L, Phi)


@functools.partial(jax.custom_jvp, nondiff_argnums=(2,))
def _small_solve_triangular(L, B, lower):
    return _unrolled_substitution(L, B, lower)


def _small_solve_triangular_jvp(lower, primals, tangents):
    """dX = L^-1 (dB - dL X), dL restricted to the triangle that is read."""
    (L, B), (dL, dB) = primals, tangents
    X = _small_solve_triangular(L, B, lower)
    rhs = jnp.zeros_like(X) if isinstance(dB, SymbolicZero) else dB
    if not isinstance(dL, SymbolicZero):
        rhs = rhs - _reduce_mm(jnp.tril(dL) if lower else jnp.triu(dL), X)
    return X, _unrolled_substitution(L, rhs, lower)


_small_solve_triangular.defjvp(_small_solve_triangular_jvp, symbolic_zeros=True)


def _qr_lower(X, *, with_q: bool):
    """QR of X^T (X of shape (..., n, p), p >= n) with R's diagonal made non-negative: returns
    (Q, L = R^T), X = L Q^T; Q is None unless ``with_q``."""
    Xt = jnp.swapaxes(X, -1, -2)
    if with_q:
        Q, R = jnp.linalg.qr(Xt)
    else:
        Q, R = None, jnp.linalg.qr(Xt, mode="r")
    sign = jnp.where(jnp.diagonal(R, axis1=-2, axis2=-1) < 0, -1.0, 1.0).astype(R.dtype)
    L = jnp.swapaxes(R * sign[..., :, None], -1, -2)
    return (None if Q is None else Q * sign[..., None, :]), L


def tria(X):
    """The lower-triangular L (n x n, non-negative diagonal) with L L^T = X X^T for X of shape
    (..., n, p), by QR of X^T without forming X X^T; X is zero-padded to n columns when p < n.
    Differentiated through QR (needs X of full row rank); :func:`tria_gram` where only L L^T
    matters."""
    n, p = X.shape[-2:]
    if p < n:
        X = jnp.concatenate([X, jnp.zeros((*X.shape[:-1], n - p), X.dtype)], -1)
    return _qr_lower(X, with_q=False)[1]


@jax.custom_jvp
def tria_gram(X):
    """:func:`tria` (p >= n) with the tangent dL = dX Q (X^T = Q R, L = R^T = X Q): a tangent of
    L L^T whatever the rank of X (QR's own derivative needs R invertible), but not lower
    triangular, so only for factors that enter through L L^T."""
    return tria(X)


@tria_gram.defjvp
def _tria_gram_jvp(primals, tangents):
    (X,), (dX,) = primals, tangents
    Q, L = _qr_lower(X, with_q=True)
    return L, dX @ Q


def after(value, dependencies):
    """``value`` (a pytree), made to depend on every array of ``dependencies`` through a zero
    added to it, so that XLA computes ``dependencies`` first.

    XLA:CPU schedules by data dependency, and two independent batched LAPACK calls above about
    2e5 flops of batch each can run at once and deadlock jaxlib 0.10's CPU thread pool
    (:mod:`jaxest.montecarlo`); ``lax.optimization_barrier`` does not order them. The zero is 0
    times one entry of each dependency, set to 0 where not finite so that a NaN does not spread.
    """
    leaves = [a for a in jax.tree.leaves(dependencies) if a.size]
    if not leaves:
        return value
    first = jnp.stack([a.ravel()[0].astype(jnp.float32) for a in leaves])
    zero = 0 * jnp.sum(jnp.where(jnp.isfinite(first), first, 0))
    return jax.tree.map(lambda a: a + zero.astype(a.dtype), value)
