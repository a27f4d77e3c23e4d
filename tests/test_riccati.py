"""Riccati solvers against scipy, under jit/vmap/grad, gradients against finite differences."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg as sl
from jax import enable_x64

from jaxest.riccati import lqr_gain, solve_care, solve_dare


def random_problem(seed, n, m):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, n)) / np.sqrt(n) * 1.3  # some modes unstable
    B = rng.normal(size=(n, m))
    C = rng.normal(size=(n, n))
    Q = C @ C.T / n
    R = np.eye(m) + 0.2 * np.ones((m, m))
    return A, B, Q, R


SIZES = [(1, 1), (3, 2), (8, 3)]


@pytest.mark.parametrize("n,m", SIZES)
def test_dare_matches_scipy(n, m):
    with enable_x64(True):
        A, B, Q, R = random_problem(n + m, n, m)
        X = np.asarray(solve_dare(A, B, Q, R))
        ref = sl.solve_discrete_are(A, B, Q, R)
        np.testing.assert_allclose(X, ref, rtol=1e-9, atol=1e-9 * np.abs(ref).max())
        residual = A.T @ X @ A - A.T @ X @ B @ np.linalg.solve(R + B.T @ X @ B, B.T @ X @ A) + Q - X
        assert np.abs(residual).max() < 1e-9 * np.abs(X).max()


@pytest.mark.parametrize("n,m", SIZES)
def test_care_matches_scipy(n, m):
    with enable_x64(True):
        A, B, Q, R = random_problem(n + m, n, m)
        X = np.asarray(solve_care(A, B, Q, R))
        ref = sl.solve_continuous_are(A, B, Q, R)
        np.testing.assert_allclose(X, ref, rtol=1e-9, atol=1e-9 * np.abs(ref).max())
        K = np.asarray(lqr_gain(A, B, Q, R))
        np.testing.assert_allclose(K, np.linalg.solve(R, B.T @ ref), rtol=1e-8, atol=1e-9)
        assert np.linalg.eigvals(A - B @ K).real.max() < 0  # stabilising


def test_float32_stays_float32_and_is_accurate():
    A, B, Q, R = random_problem(3, 3, 1)
    A32, B32, Q32, R32 = (np.float32(v) for v in (A, B, Q, R))
    for solve, ref in ((solve_dare, sl.solve_discrete_are), (solve_care, sl.solve_continuous_are)):
        X = solve(A32, B32, Q32, R32)
        assert X.dtype == jnp.float32
        np.testing.assert_allclose(X, ref(A, B, Q, R), rtol=2e-4, atol=2e-4)


def test_paper_filter_riccati_eq5():
    """The Wiener paper's example (docs/papers/wiener.md): Sigma from the filter form of eq 5."""
    with enable_x64(True):
        Phi = np.array([[0.2, 0.1], [0.0, 1.0]])
        Gamma = np.array([[1.0], [1.0]])
        H = np.array([[1.0, 0.0]])
        Sigma = solve_dare(Phi.T, H.T, Gamma @ Gamma.T, np.eye(1))
        np.testing.assert_allclose(Sigma, [[1.078811, 1.441808], [1.441808, 4.030933]], atol=5e-7)


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_jit_and_vmap(dtype):
    with enable_x64(dtype == "float64"):
        problems = [random_problem(s, 3, 2) for s in range(4)]
        A, B, Q, R = (jnp.asarray(np.stack(p), dtype) for p in zip(*problems, strict=True))
        for solve, ref in (
            (solve_dare, sl.solve_discrete_are),
            (solve_care, sl.solve_continuous_are),
        ):
            X = jax.jit(jax.vmap(solve))(A, B, Q, R)
            assert X.dtype == jnp.dtype(dtype)
            tol = 1e-9 if dtype == "float64" else 1e-3
            for i, p in enumerate(problems):
                np.testing.assert_allclose(X[i], ref(*p), rtol=tol, atol=tol)


def _loss(solve, weights):
    return jax.jit(lambda A, B, Q, R: jnp.sum(weights * solve(A, B, Q, R)))


@pytest.mark.parametrize("solve", [solve_dare, solve_care], ids=["dare", "care"])
def test_gradient_matches_finite_differences(solve):
    with enable_x64(True):
        A, B, Q, R = random_problem(5, 3, 2)
        weights = np.random.default_rng(9).normal(size=(3, 3))
        loss = _loss(solve, weights)
        grads = jax.jit(jax.grad(loss, argnums=(0, 1, 2, 3)))(A, B, Q, R)
        args = [A, B, Q, R]
        rng = np.random.default_rng(1)
        for i in range(4):
            direction = rng.normal(size=args[i].shape)
            if i >= 2:  # Q and R are symmetric: perturb symmetrically
                direction = direction + direction.T
            h = 1e-6
            plus = [a + h * direction if j == i else a for j, a in enumerate(args)]
            minus = [a - h * direction if j == i else a for j, a in enumerate(args)]
            fd = (loss(*plus) - loss(*minus)) / (2 * h)
            np.testing.assert_allclose(np.sum(grads[i] * direction), fd, rtol=1e-6, atol=1e-8)


def test_gradient_under_vmap_float32():
    A, B, Q, R = (np.float32(v) for v in random_problem(7, 2, 1))
    weights = np.ones((2, 2), np.float32)
    g = jax.vmap(jax.grad(_loss(solve_dare, weights)), in_axes=(0, None, None, None))(
        np.stack([A, 0.9 * A]), B, Q, R
    )
    assert g.dtype == jnp.float32 and np.all(np.isfinite(g))
    with enable_x64(True):
        g64 = jax.grad(_loss(solve_dare, weights))(A.astype(np.float64), B, Q, R)
    np.testing.assert_allclose(g[0], g64, rtol=1e-3, atol=1e-3)


def test_lqr_gain_gradient_through_the_gain():
    with enable_x64(True):
        A, B, Q, R = random_problem(2, 3, 1)
        f = jax.jit(lambda A: jnp.sum(lqr_gain(A, B, Q, R) ** 2))
        g = jax.grad(f)(A)
        d = np.random.default_rng(3).normal(size=A.shape)
        fd = (f(A + 1e-6 * d) - f(A - 1e-6 * d)) / 2e-6
        np.testing.assert_allclose(np.sum(g * d), fd, rtol=1e-6)


def test_not_stabilisable_raises():
    A = np.diag([2.0, 0.5])
    B = np.array([[0.0], [1.0]])  # the unstable mode 2 is not reachable
    with pytest.raises(ValueError, match="not stabilisable"):
        solve_dare(A, B, np.eye(2), np.eye(1))
    with pytest.raises(ValueError, match="not stabilisable"):
        solve_care(A, B, np.eye(2), np.eye(1))


def test_not_detectable_raises():
    B = np.array([[1.0], [1.0]])
    Q = np.diag([0.0, 1.0])  # the first mode is invisible to Q
    with pytest.raises(ValueError, match="not detectable"):
        solve_dare(np.diag([1.0, 0.5]), B, Q, np.eye(1))  # ... and on the unit circle
    with pytest.raises(ValueError, match="not detectable"):
        solve_care(np.diag([0.0, -1.0]), B, Q, np.eye(1))  # ... and on the imaginary axis
    with pytest.raises(ValueError, match="not detectable"):
        solve_dare(np.diag([2.0, 0.5]), B, Q, np.eye(1))  # ... and unstable


def test_stable_modes_need_neither_control_nor_observation():
    with enable_x64(True):
        A, B, Q, R = np.diag([0.5, -0.3]), np.zeros((2, 1)), np.zeros((2, 2)), np.eye(1)
        np.testing.assert_array_equal(solve_dare(A, B, Q, R), np.zeros((2, 2)))
        Q = np.eye(2)  # then X = sum_k A^k Q A^k = diag(1 / (1 - a^2))
        np.testing.assert_allclose(
            solve_dare(A, B, Q, R), np.diag([1 / 0.75, 1 / 0.91]), rtol=1e-12
        )


@pytest.mark.parametrize(
    "args,name",
    [
        ((np.eye(2), np.ones((3, 1)), np.eye(2), np.eye(1)), "A"),
        ((np.eye(2), np.ones((2, 1)), np.eye(2), -np.eye(1)), "R"),
        ((np.eye(2), np.ones((2, 1)), np.array([[1.0, 2.0], [0.0, 1.0]]), np.eye(1)), "Q"),
        ((np.eye(2), np.ones(2), np.eye(2), np.eye(1)), "B"),
    ],
)
def test_bad_arguments_name_the_argument(args, name):
    with pytest.raises(ValueError, match=f"^{name}:"):
        solve_dare(*args)
