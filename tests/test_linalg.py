"""The unrolled small-matrix kernels against LAPACK, under jit, vmap and grad, float32 and 64."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxest as je
from jaxest.linalg import (
    SMALL_FACTOR,
    after,
    cho_solve_lower,
    cholesky,
    cov_from_factor,
    factor_psd,
    mm,
    mv,
    right_svd,
    solve_triangular,
    tria,
    tria_gram,
)
from tests.lowering import custom_call_targets


def spd(rng, n, cond=1e3):
    Q = np.linalg.qr(rng.normal(size=(n, n)))[0]
    return Q @ np.diag(np.geomspace(1.0, 1.0 / cond, n)) @ Q.T


@pytest.mark.parametrize("n", [1, 2, 3, 5, SMALL_FACTOR, SMALL_FACTOR + 1])
@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_cholesky_and_solves_match_lapack(n, dtype):
    rng = np.random.default_rng(n)
    A = jnp.asarray(np.stack([spd(rng, n) for _ in range(7)]), dtype)
    B = jnp.asarray(rng.normal(size=(7, n, 3)), dtype)
    tol = 1e-4 if dtype == jnp.float32 else 1e-11
    L = jax.jit(jax.vmap(cholesky))(A)
    assert L.dtype == dtype
    np.testing.assert_allclose(L, np.linalg.cholesky(np.asarray(A, np.float64)), rtol=tol, atol=tol)

    @jax.jit
    def solves(L, B):
        X = jax.vmap(lambda L, B: solve_triangular(L, B, lower=True))(L, B)
        Y = jax.vmap(lambda L, B: solve_triangular(jnp.swapaxes(L, -1, -2), B, lower=False))(L, B)
        v = solve_triangular(L[0], B[0, :, 0], lower=True)  # a vector right-hand side
        return X, Y, v, cho_solve_lower(L, B)

    X, Y, v, Z = (np.asarray(a, np.float64) for a in solves(L, B))
    A, L, B = (np.asarray(a, np.float64) for a in (A, L, B))
    np.testing.assert_allclose(L @ X, B, rtol=tol, atol=tol)
    np.testing.assert_allclose(np.swapaxes(L, -1, -2) @ Y, B, rtol=tol, atol=tol)
    np.testing.assert_allclose(L[0] @ v, B[0, :, 0], rtol=tol, atol=tol)
    np.testing.assert_allclose(A @ Z, B, rtol=100 * tol, atol=100 * tol)


@pytest.mark.parametrize("shape", [(1, 1, 1), (4, 4, 4), (2, 6, 3), (8, 8, 8), (9, 8, 8)])
@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@pytest.mark.parametrize("under_vmap", [False, True])
def test_mm_matches_matmul_with_its_derivatives(shape, dtype, under_vmap):
    """Values, tangents and gradients of five stacked products, written over the leading axis
    (the one-sequence form) or mapped over it by vmap (the batched form)."""
    m, k, n = shape
    rng = np.random.default_rng(sum(shape))
    a, da = (jnp.asarray(rng.normal(size=(5, m, k)), dtype) for _ in range(2))
    b, db = (jnp.asarray(rng.normal(size=(5, k, n)), dtype) for _ in range(2))
    tol = 1e-5 if dtype == jnp.float32 else 1e-13
    over_runs = jax.vmap if under_vmap else lambda fn: fn
    ref = np.asarray(a, np.float64) @ np.asarray(b, np.float64)
    out = jax.jit(over_runs(mm))(a, b)
    assert out.dtype == dtype
    np.testing.assert_allclose(out, ref, rtol=tol, atol=tol)
    jvp_both = over_runs(lambda *a: jax.jvp(mm, a[:2], a[2:])[1])
    jvp_a = over_runs(lambda a, b, da: jax.jvp(lambda a: mm(a, b), (a,), (da,))[1])
    tangent, const_b = jax.jit(jvp_both)(a, b, da, db), jax.jit(jvp_a)(a, b, da)
    loss = lambda a, b: jnp.sum(jnp.sin(mm(a, b)))
    g_a, g_b = jax.jit(over_runs(jax.grad(loss, argnums=(0, 1))))(a, b)
    if dtype == jnp.float64:  # the gradient against central differences
        step = 1e-6
        fd = jax.jit(
            lambda a, b, da: (loss(a + step * da, b) - loss(a - step * da, b)) / (2 * step)
        )
        np.testing.assert_allclose(jnp.sum(g_a * da), fd(a, b, da), rtol=1e-7)
    a, b, da, db = (np.asarray(x, np.float64) for x in (a, b, da, db))
    np.testing.assert_allclose(tangent, da @ b + a @ db, rtol=tol, atol=tol)
    np.testing.assert_allclose(const_b, da @ b, rtol=tol, atol=tol)  # a constant operand
    g = np.cos(a @ b)
    np.testing.assert_allclose(g_a, g @ np.swapaxes(b, -1, -2), rtol=tol, atol=tol)
    np.testing.assert_allclose(g_b, np.swapaxes(a, -1, -2) @ g, rtol=tol, atol=tol)


def test_mm_takes_the_form_of_how_it_runs():
    """One sequence: a multiply-and-reduce. Under vmap, with either operand or both batched,
    and in a vmap of a vmap: the rank-one terms, with no reduction (the form XLA:CPU
    vectorises over the batch), or on the CPU above SMALL_BATCHED_MATMUL a dot; the values
    of a @ b; its Hessian through the vmap."""
    rng = np.random.default_rng(0)
    a, b = jnp.asarray(rng.normal(size=(3, 4))), jnp.asarray(rng.normal(size=(4, 2)))
    a5, b5 = jnp.stack([a * i for i in range(5)]), jnp.stack([b * i for i in range(5)])

    def reductions(fn, *args):
        return str(jax.make_jaxpr(fn)(*args)).count("reduce_sum")

    assert reductions(mm, a, b) == 1
    for in_axes, args in (((0, 0), (a5, b5)), ((0, None), (a5, b)), ((None, 0), (a, b5))):
        assert reductions(jax.vmap(mm, in_axes), *args) == 0
        np.testing.assert_allclose(
            jax.vmap(mm, in_axes)(*args), jax.vmap(jnp.matmul, in_axes)(*args), rtol=1e-13
        )
    nested = jax.vmap(jax.vmap(mm))
    a25, b25 = jnp.stack([a5] * 5), jnp.stack([b5 * 2] * 5)
    assert reductions(nested, a25, b25) == 0
    np.testing.assert_allclose(nested(a25, b25), a25 @ b25, rtol=1e-13)
    # above SMALL_BATCHED_MATMUL multiply-adds (5^3 below, 6^3 above) the batched form is a
    # dot on the CPU; other platforms (lowered here for CUDA) keep the rank-one sum
    for size, dots in ((5, 0), (6, 1)):
        square = jnp.stack([jnp.asarray(rng.normal(size=(size, size))) for _ in range(5)])
        jaxpr = str(jax.make_jaxpr(jax.vmap(mm))(square, square))
        assert jaxpr.count("dot_general") == dots and jaxpr.count("reduce_sum") == 0
        for platform, platform_dots in (("cpu", dots), ("cuda", 0)):
            lowered = jax.export.export(jax.jit(jax.vmap(mm)), platforms=[platform])
            assert ("dot_general" in lowered(square, square).mlir_module()) == bool(platform_dots)
        np.testing.assert_allclose(jax.vmap(mm)(square, square), square @ square, rtol=1e-13)
    # differentiated around the vmap, reverse then forward (the batched form's derivative)
    hessian = jax.hessian(lambda a: jnp.sum(jnp.sin(jax.vmap(mm)(a, b5))))(a5)
    reference = jax.hessian(lambda a: jnp.sum(jnp.sin(a @ b5)))(a5)
    np.testing.assert_allclose(hessian, reference, atol=1e-12)


def test_mv_is_mm_of_a_column():
    rng = np.random.default_rng(0)
    a, x = jnp.asarray(rng.normal(size=(3, 5, 4))), jnp.asarray(rng.normal(size=(3, 4)))
    np.testing.assert_allclose(jax.vmap(mv)(a, x), np.einsum("bij,bj->bi", a, x), rtol=1e-13)


def assert_within(actual, desired, bound):
    """|actual - desired| <= bound elementwise (bound broadcast: a per-matrix scale)."""
    error = np.abs(np.asarray(actual, np.float64) - np.asarray(desired, np.float64))
    bound = np.broadcast_to(bound, error.shape)
    assert np.all(error <= bound), f"error up to {np.max(error - bound):.3g} over the bound"


def tall_matrices(rng, kind, p, n, count=40):
    """Test matrices for the SVD kernels: Gaussian, graded columns, condition 1e12 (1e6 in
    float32 terms), repeated singular values."""
    X = rng.normal(size=(count, p, n))
    orth = lambda *shape: np.linalg.qr(rng.normal(size=shape))[0]
    if kind == "graded":
        X = X * np.geomspace(1, 1e-9, n)
    if kind == "ill":
        X = (orth(count, p, n) * np.geomspace(1, 1e-12, n)) @ orth(count, n, n)
    if kind == "repeated":
        X = orth(count, p, n) @ orth(count, n, n)
    return X


#: one program per shape and dtype, shared by the four kinds of matrix
batched_right_svd = jax.jit(jax.vmap(right_svd))


@pytest.mark.parametrize("n", [1, 2, 3, 4, 6, 8, 9])
@pytest.mark.parametrize("kind", ["gaussian", "graded", "ill", "repeated"])
@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_right_svd_matches_numpy(n, kind, dtype):
    """Singular values to a few eps relative to the largest, and, where they are well separated
    relative to that error, each to a few eps relative to itself (one-sided Jacobi keeps
    relative accuracy for graded columns); V orthogonal and A^T A = V S^2 V^T."""
    rng = np.random.default_rng(n)
    A64 = tall_matrices(rng, kind, 2 * n, n)
    A = jnp.asarray(A64, dtype)
    s, V = batched_right_svd(A)
    assert s.dtype == V.dtype == dtype
    eps = float(jnp.finfo(dtype).eps)
    s_ref = np.linalg.svd(np.asarray(A, np.float64), compute_uv=False)
    assert np.all(np.diff(np.asarray(s), axis=-1) <= 0)  # descending
    assert_within(s, s_ref, 100 * eps * s_ref[:, :1])
    if kind == "graded":  # small singular values to relative accuracy
        assert_within(s, s_ref, 100 * eps * s_ref)
    eye = np.eye(n)
    VtV = np.swapaxes(V, -1, -2) @ V
    np.testing.assert_allclose(VtV, np.broadcast_to(eye, VtV.shape), atol=100 * eps)
    AV = np.asarray(A, np.float64) @ np.asarray(V, np.float64)
    # the columns of A V are orthogonal with norms s: A = U S V^T
    gram = np.swapaxes(AV, -1, -2) @ AV
    assert_within(gram, s_ref[:, :, None] ** 2 * eye, 100 * eps * s_ref[:, :1, None] ** 2)


@pytest.mark.parametrize("n", [1, 2, 3, 4, 6, 8, 9])
@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_factor_psd_matches_eigh(n, dtype):
    rng = np.random.default_rng(10 + n)
    B = rng.normal(size=(30, n, n)) * np.geomspace(1, 1e-4, n)
    P64 = B @ np.swapaxes(B, -1, -2)
    P64[:10, :, -1] = P64[:10, -1, :] = 0  # singular (as a PSD Q may be)
    P64[10:15] = np.eye(n)  # repeated eigenvalues
    P = jnp.asarray(P64, dtype)
    U, D = jax.jit(jax.vmap(factor_psd))(P)
    assert U.dtype == D.dtype == dtype
    eps = float(jnp.finfo(dtype).eps)
    w = np.linalg.eigvalsh(np.asarray(P, np.float64))[:, ::-1]
    scale = w[:, :1]
    assert_within(D**2, np.clip(w, 0, None), 100 * eps * scale)
    assert_within(cov_from_factor(U, D), P, 100 * eps * scale[:, :, None])
    UtU = np.swapaxes(U, -1, -2) @ U
    np.testing.assert_allclose(UtU, np.broadcast_to(np.eye(n), UtU.shape), atol=100 * eps)
    # the derivative is defined at the covariance level: a tangent of U alone reproducing dP
    P0 = jnp.asarray(P64[20] + w[20, 0] * np.eye(n), dtype)  # well conditioned in float32 too
    dP = jnp.asarray(P64[21], dtype)
    (U0, D0), (dU, dD) = jax.jit(lambda P, dP: jax.jvp(factor_psd, (P,), (dP,)))(P0, dP)
    half = (dU * D0**2) @ U0.T
    assert_within(half + half.T, dP, 1e3 * eps * w[20, 0])
    assert np.all(dD == 0)


def test_not_positive_definite_gives_nan_like_lapack():
    A = jnp.asarray([[1.0, 2.0], [2.0, 1.0]])
    assert np.isnan(np.asarray(cholesky(A))).any()
    assert np.isnan(np.asarray(jnp.linalg.cholesky(A))).any()


def test_gradient_of_logdet_matches_finite_differences():
    rng = np.random.default_rng(0)
    A = jnp.asarray(spd(rng, 4, cond=10.0))
    dA = jnp.asarray(spd(rng, 4, cond=10.0))
    logdet = lambda t: 2 * jnp.sum(jnp.log(jnp.diag(cholesky(A + t * dA))))
    grad = jax.grad(logdet)(0.0)
    fd = (logdet(1e-6) - logdet(-1e-6)) / 2e-6
    np.testing.assert_allclose(grad, fd, rtol=1e-7)
    np.testing.assert_allclose(grad, jnp.trace(jnp.linalg.solve(A, dA)), rtol=1e-10)


@pytest.mark.parametrize("n", [1, 3, 6])
@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_cholesky_and_solve_derivatives_equal_lapacks(n, dtype):
    """The kernels' own derivative rules against jax's for LAPACK: tangents (a non-symmetric dA
    is symmetrised by both) and cotangents, both triangles, under vmap; and a second derivative
    against central differences of the first."""
    rng = np.random.default_rng(10 + n)
    A, dA = (jnp.asarray(np.stack([spd(rng, n, 10.0) for _ in range(3)]), dtype) for _ in "12")
    dA = dA + jnp.asarray(rng.normal(size=dA.shape), dtype) * 0.1
    B, dB = (jnp.asarray(rng.normal(size=(3, n, 2)), dtype) for _ in "12")
    tol = 1e-4 if dtype == jnp.float32 else 1e-11
    # each side is one compiled program (here and below): these are checks of derivative
    # rules, and op-by-op dispatch would compile every primitive of the unrolled kernels alone
    chol_tangent = lambda chol: jax.jit(jax.vmap(lambda A, dA: jax.jvp(chol, (A,), (dA,))[1]))
    np.testing.assert_allclose(
        chol_tangent(cholesky)(A, dA), chol_tangent(jnp.linalg.cholesky)(A, dA), rtol=tol, atol=tol
    )
    for lower in (True, False):
        L = jnp.linalg.cholesky(A)
        L = L if lower else jnp.swapaxes(L, -1, -2)
        dL = jnp.asarray(rng.normal(size=L.shape), dtype)  # full: the other triangle is unread
        solve_ours = lambda L, B: solve_triangular(L, B, lower=lower)
        solve_ref = lambda L, B: jax.scipy.linalg.solve_triangular(L, B, lower=lower)
        solve_tangent = lambda solve: jax.jit(jax.vmap(lambda *a: jax.jvp(solve, a[:2], a[2:])[1]))
        np.testing.assert_allclose(
            solve_tangent(solve_ours)(L, B, dL, dB), solve_tangent(solve_ref)(L, B, dL, dB),
            rtol=tol, atol=tol,
        )  # fmt: skip
        loss = lambda solve, chol: lambda L, B, A: jnp.sum(jnp.sin(solve(L, B)) * chol(A)[..., :1])
        grads = jax.jit(jax.grad(loss(solve_ours, cholesky), argnums=(0, 1, 2)))(L, B, A)
        grads_ref = jax.jit(jax.grad(loss(solve_ref, jnp.linalg.cholesky), argnums=(0, 1, 2)))(
            L, B, A
        )
        for g, g_ref in zip(grads, grads_ref, strict=True):
            np.testing.assert_allclose(g, g_ref, rtol=tol, atol=tol)
    if dtype == jnp.float64:
        direction = dA[0] + dA[0].T  # symmetric: a non-symmetric one is read differently
        logdet_grad = jax.grad(
            lambda t: jnp.sum(jnp.log(jnp.diagonal(cholesky(A[0] + t * direction))))
        )
        step = 1e-5
        first = jax.jit(jax.vmap(logdet_grad))(jnp.asarray([step, -step]))
        fd = (first[0] - first[1]) / (2 * step)
        np.testing.assert_allclose(jax.jit(jax.grad(logdet_grad))(0.0), fd, rtol=1e-6)


@pytest.mark.parametrize("p", [2, 4, 7])
@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_tria_is_the_cholesky_factor_of_the_gram_matrix(p, dtype):
    """tria(X) is lower triangular with a non-negative diagonal and L L^T = X X^T; with X of
    full row rank it is NumPy's Cholesky factor of X X^T (p < n: padded, rank p)."""
    rng = np.random.default_rng(p)
    X = rng.normal(size=(5, 4, p))
    L = jax.jit(jax.vmap(tria))(jnp.asarray(X, dtype))
    assert L.shape == (5, 4, 4) and L.dtype == dtype
    tol = 1e-5 if dtype == jnp.float32 else 1e-12
    np.testing.assert_array_equal(np.triu(L, 1), 0)
    assert np.all(np.diagonal(L, axis1=1, axis2=2) >= 0)
    np.testing.assert_allclose(L @ np.swapaxes(L, 1, 2), X @ np.swapaxes(X, 1, 2), atol=tol * 10)
    if p >= 4:
        np.testing.assert_allclose(L, np.linalg.cholesky(X @ np.swapaxes(X, 1, 2)), atol=tol * 10)


def test_tria_gram_tangent_is_a_tangent_of_the_gram_matrix_at_any_rank():
    """d(L L^T) from tria_gram's tangent equals d(X X^T), also for X of rank 2 < n = 4, where
    QR's own derivative is not defined; the primal equals tria's."""
    rng = np.random.default_rng(0)
    X = rng.normal(size=(4, 2)) @ rng.normal(size=(2, 6))  # rank 2
    dX = rng.normal(size=(4, 6))
    L, dL = jax.jvp(tria_gram, (jnp.asarray(X),), (jnp.asarray(dX),))
    np.testing.assert_allclose(L, tria(jnp.asarray(X)), atol=1e-12)
    assert np.all(np.isfinite(dL))
    np.testing.assert_allclose(dL @ L.T + L @ dL.T, dX @ X.T + X @ dX.T, atol=1e-10)


def test_after_leaves_values_and_gradients_unchanged_and_stops_nan():
    """after(value, deps) is value (exactly, also when a dependency is NaN or infinite) and
    differentiates as the identity in value and as zero in the dependencies."""
    value = {"a": jnp.arange(3.0), "b": jnp.ones((2, 2), jnp.float32)}
    deps = (jnp.asarray([jnp.nan, 1.0]), jnp.asarray([[jnp.inf]]), jnp.zeros((0,)))
    out = jax.jit(after)(value, deps)
    np.testing.assert_array_equal(out["a"], value["a"])
    assert out["b"].dtype == jnp.float32
    np.testing.assert_array_equal(out["b"], value["b"])
    grad_value, grad_dep = jax.grad(lambda v, d: jnp.sum(after(v, d) ** 2), argnums=(0, 1))(
        jnp.arange(3.0), jnp.asarray([2.0, 5.0])
    )
    np.testing.assert_array_equal(grad_value, 2 * jnp.arange(3.0))
    np.testing.assert_array_equal(grad_dep, 0.0)


def test_right_svd_unrolls_only_small_matrices():
    """Jacobi (no LAPACK call) up to SMALL_FACTOR columns and twice that many rows; a taller
    matrix (the flight filter's 29 x 6 innovation factor) goes to LAPACK, which compiles faster."""

    def lapack_calls(shape):
        hlo = jax.jit(right_svd).lower(jnp.ones(shape)).compile().as_text()
        return [call for call in custom_call_targets(hlo) if call.startswith("lapack_")]

    assert lapack_calls((2 * SMALL_FACTOR, 6)) == []
    assert lapack_calls((29, 6)) != []
    assert lapack_calls((20, SMALL_FACTOR + 1)) != []


def test_astype_casts_floating_arrays_and_leaves_the_rest():
    """Every floating-point array of a model, a prior and data in one call; the integer and
    boolean arrays, Python numbers and the model's functions as they are."""
    model = je.NonlinearGaussian(lambda x, u: 0.9 * x, lambda x, u: x[:1], jnp.eye(2), jnp.eye(1))
    prior = je.Gaussian(jnp.zeros(2), jnp.eye(2))
    key = jax.random.key(0)
    tree = (model, prior, jnp.ones((3, 1)), jnp.arange(3), jnp.array([True]), 0.5, None, key)
    single = je.astype(tree, jnp.float32)
    arrays = [leaf for leaf in jax.tree.leaves(single) if hasattr(leaf, "dtype")]
    floats = [leaf for leaf in arrays if jnp.issubdtype(leaf.dtype, jnp.floating)]
    assert len(floats) == 5 and all(leaf.dtype == jnp.float32 for leaf in floats)
    assert single[0].transition_fn is model.transition_fn
    assert single[0].observation_fn is model.observation_fn
    assert single[3].dtype == jnp.arange(3).dtype and single[4].dtype == jnp.bool_
    assert single[5] == 0.5 and single[6] is None and single[7] is key
    back = je.astype(single, jnp.float64)
    assert back[1].cov.dtype == jnp.float64
    np.testing.assert_array_equal(back[2], tree[2])
    # an integer type truncated every float without a word; a misspelt name was JAX's TypeError
    with pytest.raises(ValueError, match="^dtype: expected a floating-point type, got int32"):
        je.astype(tree, jnp.int32)
    with pytest.raises(ValueError, match="^dtype: not a data type: 'float33'"):
        je.astype(tree, "float33")
