"""Ellipsoid sum with a segment and intersection with a strip: brute-force containment of sampled
points, volume against simple outer bounds and the rest of each family, exact empty test."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxest.setmembership import ellipsoid

# Compiled once per shape: op by op, every primitive of a kernel would compile on its own.
add_box, add_segment, contains, intersect_strip = (
    jax.jit(f)
    for f in (
        ellipsoid.add_box,
        ellipsoid.add_segment,
        ellipsoid.contains,
        ellipsoid.intersect_strip,
    )
)


def _random_ellipsoid(rng, n):
    A = rng.normal(size=(n, n))
    return rng.normal(size=n), A @ A.T + 0.1 * np.eye(n)


def _inside_points(rng, c, P, count=20000):
    n = len(c)
    u = rng.normal(size=(count, n))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    u[: count // 2] *= rng.uniform(size=(count // 2, 1)) ** (1 / n)  # half on the boundary
    return c + u @ np.linalg.cholesky(P).T


def _quadratic_form(X, c, P):
    d = X - c
    return np.einsum("ij,ij->i", d, np.linalg.solve(P, d.T).T)


@pytest.mark.parametrize("n", [1, 2, 3, 5])
def test_sum_with_segment_contains_sampled_sums_and_is_least_volume(n):
    rng = np.random.default_rng(n)
    for _ in range(5):
        c, P = _random_ellipsoid(rng, n)
        s = rng.normal(size=n)
        new = np.asarray(add_segment(jnp.asarray(P), jnp.asarray(s)))
        X = _inside_points(rng, c, P) + rng.choice([-1.0, 1.0, 0.3], size=(20000, 1)) * s
        assert np.all(_quadratic_form(X, c, new) <= 1 + 1e-10)
        # no larger than any other member of the family (p = 1 is the simple outer bound)
        family = [(1 + p) * P + (1 + 1 / p) * np.outer(s, s) for p in np.geomspace(1e-3, 1e3, 61)]
        assert np.linalg.det(new) <= min(np.linalg.det(F) for F in family) * (1 + 1e-9)


def test_box_sum_contains_sampled_points_and_zero_width_is_identity():
    rng = np.random.default_rng(10)
    c, P = _random_ellipsoid(rng, 3)
    w = np.array([0.3, 0.0, 1.2])
    new = np.asarray(add_box(jnp.asarray(P), jnp.asarray(w)))
    X = _inside_points(rng, c, P) + rng.uniform(-1, 1, (20000, 3)) * w
    X[:8] = c + np.array([[a, 0, b] for a in (-1, 1) for b in (-1, 1)] * 2) * w  # box corners
    assert np.all(_quadratic_form(X, c, new) <= 1 + 1e-10)
    np.testing.assert_array_equal(np.asarray(add_box(jnp.asarray(P), jnp.zeros(3))), P)


@pytest.mark.parametrize("n, rank", [(1, 0), (2, 0), (2, 1), (3, 1), (3, 2), (5, 3)])
def test_box_sum_of_a_flat_set_is_bounded_and_holds_the_sum(n, rank):
    """A singular P (a flat set: F P F^T of a singular Jacobian) plus a box: the sum is bounded,
    where the shape used to be +inf (the unbounded flag); it holds E(0, P) + box by support
    functions, sqrt(d^T P+ d) >= sqrt(d^T P d) + sum_i w_i |d_i| for every direction d, and for
    n = 1 it is the interval itself (rounded outward)."""
    rng = np.random.default_rng(10 * n + rank)
    A = rng.normal(size=(n, rank))
    P = A @ A.T
    w = rng.uniform(0.1, 1.0, n)
    new = np.asarray(add_box(jnp.asarray(P), jnp.asarray(w)))
    assert np.all(np.isfinite(new)) and np.all(np.linalg.eigvalsh(new) > 0)
    d = rng.normal(size=(4000, n))
    d[:n] = np.eye(n)
    support = lambda M: np.sqrt(np.einsum("ki,ij,kj->k", d, M, d))
    assert np.all(support(new) >= support(P) + np.abs(d) @ w)
    if n == 1:
        assert w[0] ** 2 <= new[0, 0] <= w[0] ** 2 * (1 + 1e-14)


@pytest.mark.parametrize("n", [1, 2, 3, 4])
def test_strip_intersection_contains_sampled_points_and_is_least_volume(n):
    rng = np.random.default_rng(100 + n)
    for _ in range(8):
        c, P = _random_ellipsoid(rng, n)
        h = rng.normal(size=n)
        g = h @ P @ h
        z = h @ c + rng.uniform(-1.2, 1.2) * np.sqrt(g)
        v = rng.uniform(0.05, 0.8) * np.sqrt(g)
        c2, P2, empty = map(np.asarray, intersect_strip(*map(jnp.asarray, (c, P, h, z, v))))
        X = _inside_points(rng, c, P, 40000)
        X = X[np.abs(z - X @ h) <= v]
        assert not empty and len(X) > 0
        assert np.all(_quadratic_form(X, c2, P2) <= 1 + 1e-9)
        assert np.linalg.det(P2) <= np.linalg.det(P) * (1 + 1e-12)  # q = 0 member: E itself
        if n > 1 and not np.allclose(P2, P):  # least volume over the family of eqs 32-34
            pp, pm = min((z - h @ c + v) / np.sqrt(g), 1), max((z - h @ c - v) / np.sqrt(g), -1)
            e, d = np.sqrt(g) * (pp + pm) / 2, np.sqrt(g) * (pp - pm) / 2
            Ph = P @ h
            dets = []
            for q in np.geomspace(1e-4, 1e4, 200):
                s = d**2 + q * g
                dets.append(
                    np.linalg.det((1 + q - q * e**2 / s) * (P - (q / s) * np.outer(Ph, Ph)))
                )
            assert np.linalg.det(P2) <= min(dets) * (1 + 1e-9)
        if n == 1:  # the exact interval intersection
            lo = max(c[0] - np.sqrt(P[0, 0]), min((z - v) / h[0], (z + v) / h[0]))
            hi = min(c[0] + np.sqrt(P[0, 0]), max((z - v) / h[0], (z + v) / h[0]))
            np.testing.assert_allclose(
                [c2[0] - np.sqrt(P2[0, 0]), c2[0] + np.sqrt(P2[0, 0])], [lo, hi], rtol=1e-12
            )


def test_empty_intersection_iff_slabs_are_disjoint():
    rng = np.random.default_rng(7)
    c, P = _random_ellipsoid(rng, 3)
    h = rng.normal(size=3)
    half = np.sqrt(h @ P @ h)  # the ellipsoid spans h^T c +- half along h
    v = 0.2
    for gap, expect in ((1e-6, True), (-1e-6, False), (0.5, True), (-0.5, False)):
        for side in (1, -1):
            z = h @ c + side * (half + v + gap)
            _, _, empty = intersect_strip(*map(jnp.asarray, (c, P, h, z, v)))
            assert bool(empty) == expect


def test_wide_strip_leaves_ellipsoid_unchanged():
    c, P = np.zeros(2), np.diag([1.0, 4.0])
    h = np.array([1.0, 0.0])
    c2, P2, empty = intersect_strip(*map(jnp.asarray, (c, P, h, 0.1, 0.95)))  # phi+ phi- <= -1/2
    np.testing.assert_array_equal(np.asarray(P2), P)
    np.testing.assert_array_equal(np.asarray(c2), c)
    assert not empty


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_operations_under_jit_vmap_grad(dtype):
    rng = np.random.default_rng(3)
    cs = jnp.asarray(rng.normal(size=(4, 2)) * 0.1, dtype)
    P = jnp.asarray([[1.0, 0.3], [0.3, 0.5]], dtype)
    h = jnp.asarray([1.0, -0.5], dtype)

    def step(c, z):
        c2, P2, empty = intersect_strip(c, P, h, z, jnp.asarray(0.3, dtype))
        P3 = add_box(P2, jnp.asarray([0.1, 0.2], dtype))
        return jnp.linalg.slogdet(P3)[1] + jnp.sum(c2), empty

    out, empty = jax.jit(jax.vmap(step, in_axes=(0, None)))(cs, jnp.asarray(0.4, dtype))
    assert out.dtype == dtype and out.shape == (4,) and not np.any(empty)
    grad = jax.jit(jax.grad(lambda z: step(cs[0], z)[0]))(jnp.asarray(0.4, dtype))
    eps = 1e-2 if dtype == jnp.float32 else 1e-6
    fd = jax.jit(lambda z: (step(cs[0], z + eps)[0] - step(cs[0], z - eps)[0]) / (2 * eps))(0.4)
    np.testing.assert_allclose(grad, fd, rtol=2e-2 if dtype == jnp.float32 else 1e-6)
    assert np.isfinite(grad)
    # a branch not taken (no update: a strip wider than the ellipsoid) still has finite gradients
    g2 = jax.jit(
        jax.grad(lambda v: jnp.sum(intersect_strip(cs[0], P, h, jnp.asarray(0.0, dtype), v)[1]))
    )(jnp.asarray(5.0, dtype))
    assert np.isfinite(g2) and g2 == 0
    assert bool(contains(cs[0], P, cs[0])) and not bool(contains(cs[0], P, cs[0] + 10))


def _exact_strip(c, P, h, z, v):
    """Eqs 27-36 in the direct form, in 60-digit decimal arithmetic (cancellation is harmless)."""
    from decimal import Decimal as D, localcontext

    with localcontext() as ctx:
        ctx.prec = 60
        n = len(c)
        c = [D(float(x)) for x in c]
        P = [[D(float(x)) for x in row] for row in P]
        h, z, v = [D(float(x)) for x in h], D(float(z)), D(float(v))
        Ph = [sum(P[i][j] * h[j] for j in range(n)) for i in range(n)]
        g = sum(h[i] * Ph[i] for i in range(n))
        offset = z - sum(h[i] * c[i] for i in range(n))
        pp, pm = min((offset + v) / g.sqrt(), D(1)), max((offset - v) / g.sqrt(), D(-1))
        e, d = (pp + pm) / 2, (pp - pm) / 2
        A, B = D(n - 1), (2 * n - 1) * d * d - 1 + e * e
        C = d * d * (n * (d * d - e * e) - 1)
        q = (-B + (B * B - 4 * A * C).sqrt()) / (2 * A)
        s = d * d + q
        beta = 1 + q - q * e * e / s
        shape = [
            [beta * (P[i][j] - q / (s * g) * Ph[i] * Ph[j]) for j in range(n)] for i in range(n)
        ]
        return np.array([[float(x) for x in row] for row in shape])


def test_strip_on_an_elongated_set_matches_exact_arithmetic():
    """The issue's reproduction: sqrt(P22) = 1e7, strip half-width 0.05 (direct form: P22 = 0)."""
    P = np.diag([2e5, 1e14])
    c, shape, _ = intersect_strip(
        jnp.zeros(2), jnp.asarray(P), jnp.array([0.0, 1.0]), jnp.asarray(0.01), jnp.asarray(0.05)
    )
    exact = _exact_strip([0, 0], P, [0, 1], 0.01, 0.05)
    assert abs(float(shape[1, 1]) / exact[1, 1] - 1) < 1e-6
    assert bool(contains(c, shape, jnp.array([0.0, 0.04])))


def test_a_negative_half_width_is_an_empty_strip():
    # the strip |z - h^T x| <= -0.1 holds no point; it shrank the set and reported it non-empty
    for n in (1, 2):
        c, P, h = jnp.zeros(n), jnp.eye(n), jnp.ones(n)
        c2, P2, empty = intersect_strip(c, P, h, jnp.asarray(0.0), jnp.asarray(-0.1))
        assert bool(empty)
        np.testing.assert_array_equal(np.asarray(P2), np.asarray(P))
        _, _, empty = intersect_strip(c, P, h, jnp.asarray(0.0), jnp.asarray(0.0))
        assert not bool(empty)  # a zero half-width is a hyperplane through the set


def test_each_operation_names_a_bad_operand_also_under_jit():
    P, c, v = jnp.eye(2), jnp.zeros(2), jnp.asarray(0.1)
    cases = [
        (lambda: add_box(P, jnp.ones(3)), "^half_widths: expected shape \\(2,\\)"),
        (lambda: add_box(jnp.ones((2, 3)), jnp.ones(2)), "^shape: expected a square"),
        (lambda: add_segment(P, jnp.ones(3)), "^direction: expected shape"),
        (lambda: intersect_strip(c, P, jnp.ones(3), v, v), "^normal: expected shape"),
        (lambda: intersect_strip(c, P, c, jnp.ones(1), v), "^value: expected shape \\(\\)"),
        (lambda: intersect_strip(c, P.astype(int), c, v, v), "^shape: must be real floating"),
        (lambda: contains(c, P, jnp.zeros(3)), "^x: expected shape"),
        (lambda: contains(c.astype(int), P, c), "^center: must be real floating"),
        (lambda: contains([0.0, 0.0], P, c), "^center: expected an array, got list"),
    ]
    for call, message in cases:
        with pytest.raises(ValueError, match=message):
            call()
    # an integer mask of rows: 2 & True was 0, a row silently dropped
    with pytest.raises(ValueError, match="^rows: expected a boolean mask"):
        ellipsoid.strips_ellipsoid(P, c, jnp.ones(2), jnp.array([1, 2]))
