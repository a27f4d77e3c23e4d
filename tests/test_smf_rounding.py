"""Outward rounding of the ellipsoid operations (eqs O1-O6 of docs/papers/smf.md), checked in
exact rational arithmetic: random ellipsoids of condition number up to 1e12, strips down to 1e-7
of the set's extent, boxes, and points of the exact set as close to its boundary as floating
point allows. Every such point must lie in the computed set, exactly."""

from fractions import Fraction

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxest import run
from jaxest.setmembership.ellipsoid import (
    Ellipsoid,
    add_box,
    add_box_of_segments,
    contains,
    intersect_strip,
    linear_image,
    max_condition,
)
from jaxest.setmembership.smf import SetMembershipFilter
from jaxest.systems import duffing
from tests.lowering import dot_precisions

PROBLEMS = 60  # per dimension


def _exact_form(x, center, shape):
    """(x - c)^T P^-1 (x - c) in rational arithmetic (Gaussian elimination on Fractions); x may
    be Fractions, c and P floats (NumPy's: an entry read from a JAX array costs a dispatch)."""
    center, shape = np.asarray(center, dtype=float), np.asarray(shape, dtype=float)
    n = len(center)
    d = [Fraction(x[i]) - Fraction(center[i]) for i in range(n)]
    M = [[Fraction(shape[i, j]) for j in range(n)] + [d[i]] for i in range(n)]
    for k in range(n):
        pivot = max(range(k, n), key=lambda i: abs(M[i][k]))
        M[k], M[pivot] = M[pivot], M[k]
        for i in range(k + 1, n):
            f = M[i][k] / M[k][k]
            M[i] = [a - f * b for a, b in zip(M[i], M[k], strict=True)]
    w = [Fraction(0)] * n
    for i in reversed(range(n)):
        w[i] = (M[i][n] - sum(M[i][j] * w[j] for j in range(i + 1, n))) / M[i][i]
    return sum(d[i] * w[i] for i in range(n))


def _random_shapes(rng, n, count):
    """Rotated shapes with eigenvalues spread over up to 12 decades."""
    shapes = []
    for _ in range(count):
        Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
        spread = rng.uniform(0, 12)
        P = Q @ np.diag(10.0 ** (rng.uniform(0, 1, n) * spread - spread / 2)) @ Q.T
        shapes.append(0.5 * (P + P.T))
    return np.stack(shapes)


def _boundary_points(rng, center, shape, count):
    """Float points near the boundary of E(c, P), on both sides (scaled by 1 +- 1e-14)."""
    n = len(center)
    u = rng.normal(size=(count, n))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    u *= 1 + rng.uniform(-1e-14, 1e-14, (count, 1))
    return center + u @ np.linalg.cholesky(shape).T


def _touching_points(rng, center, shape, normal, value, half_width, count=40):
    """Float points next to where the ellipsoid's boundary meets the strip's two planes
    h^T x = z +- v: there the least-volume outer ellipsoid touches the intersection, so these
    are the points a rounding error would lose. x = c + L u with |u| = 1 and (L^T h)^T u = b."""
    n = len(center)
    L = np.linalg.cholesky(shape)
    a = L.T @ normal
    points = []
    for plane in (value + half_width, value - half_width):
        b = (plane - normal @ center) / (a @ a)
        if b**2 * (a @ a) >= 1:
            continue
        w = rng.normal(size=(count, n))
        w -= np.outer(w @ a, a) / (a @ a)
        w /= np.linalg.norm(w, axis=1, keepdims=True)
        u = b * a + np.sqrt(1 - b**2 * (a @ a)) * w
        u *= 1 + rng.uniform(-1e-14, 1e-14, (count, 1))
        points.append(center + u @ L.T)
    return np.concatenate(points) if points else np.zeros((0, n))


@pytest.mark.parametrize("n", [2, 3])
def test_strip_intersection_keeps_every_exact_point(n):
    rng = np.random.default_rng(100 + n)
    shapes = _random_shapes(rng, n, PROBLEMS)
    centers = rng.normal(size=(PROBLEMS, n)) * 10
    normals = rng.normal(size=(PROBLEMS, n))
    g = np.einsum("bi,bij,bj->b", normals, shapes, normals)
    half_widths = np.sqrt(g) * 10.0 ** rng.uniform(-7, -0.3, PROBLEMS)
    values = np.einsum("bi,bi->b", normals, centers) + rng.uniform(-0.9, 0.9, PROBLEMS) * np.sqrt(g)
    out_c, out_P, empty = jax.jit(jax.vmap(intersect_strip))(
        *map(jnp.asarray, (centers, shapes, normals, values, half_widths))
    )
    assert not np.any(empty)
    checked = 0
    for b in range(PROBLEMS):
        if not np.all(np.isfinite(out_P[b])):  # not certified: the whole space (flagged)
            assert np.linalg.cond(shapes[b]) > 1e-3 * max_condition(jnp.float64, n)
            continue
        X = _touching_points(rng, centers[b], shapes[b], normals[b], values[b], half_widths[b])
        h, z, v = normals[b], values[b], half_widths[b]
        for x in X:
            inside_strip = abs(sum(Fraction(h[i]) * Fraction(x[i]) for i in range(n)) - Fraction(z))
            if inside_strip <= Fraction(v) and _exact_form(x, centers[b], shapes[b]) <= 1:
                assert _exact_form(x, out_c[b], out_P[b]) <= 1, (b, x)
                checked += 1
    assert checked > PROBLEMS * 10


def _segment_touching_points(rng, P, s, count=40):
    """Float points of E(0, P) + {t s : |t| <= 1} where the least-volume outer ellipsoid
    (1 + p) P + (1 + 1/p) s s^T touches it: its support sqrt(eta^T M eta) equals the sum's,
    sqrt(eta^T P eta) + |eta^T s|, exactly where |eta^T s| = p sqrt(eta^T P eta) (AM-GM); the
    touching point is then P eta / sqrt(eta^T P eta) + sign(eta^T s) s. Returns the pairs
    (y, sign) with y on the boundary of E(0, P)."""
    n = len(s)
    a = s @ np.linalg.solve(P, s)
    p = 2 * a / ((n - 1) * a + np.sqrt((n - 1) ** 2 * a**2 + 4 * n * a))
    gap = lambda eta: abs(eta @ s) - p * np.sqrt(eta @ P @ eta)
    pairs = []
    while len(pairs) < count:
        e0, e1 = rng.normal(size=(2, n))
        lo, hi = 0.0, 1.0
        if np.sign(gap(e0)) == np.sign(gap(e0 + e1)):
            continue
        for _ in range(60):  # bisection along eta0 + t eta1
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if np.sign(gap(e0 + mid * e1)) == np.sign(gap(e0)) else (lo, mid)
        eta = e0 + lo * e1
        pairs.append((P @ eta / np.sqrt(eta @ P @ eta), np.sign(eta @ s)))
    return pairs


@pytest.mark.parametrize("n", [2, 3])
def test_linear_image_and_segment_keep_every_exact_point(n):
    rng = np.random.default_rng(200 + n)
    shapes = _random_shapes(rng, n, PROBLEMS)
    maps = rng.normal(size=(PROBLEMS, n, n))
    images = np.einsum("bij,bjk,blk->bil", maps, shapes, maps)
    segments = rng.normal(size=(PROBLEMS, n)) * np.sqrt(np.einsum("bii->bi", images))

    def time_update(F, P, segment):
        image, error = linear_image(F, P)
        return add_box_of_segments(image, segment[None, :], error)

    out_P = jax.jit(jax.vmap(time_update))(*map(jnp.asarray, (maps, shapes, segments)))
    checked = 0
    for b in range(PROBLEMS):
        if not np.all(np.isfinite(out_P[b])):
            continue
        F, P = maps[b], shapes[b]
        image = 0.5 * (images[b] + images[b].T)
        for y, sign in _segment_touching_points(rng, image, segments[b]):
            # y = F y0 with y0 on the boundary of E(0, P); nudged inside in exact arithmetic
            y0 = np.linalg.solve(F, y)
            y0 = y0 / np.sqrt(y0 @ np.linalg.solve(P, y0))
            step = 1e-16
            while _exact_form(y0, np.zeros(n), P) > 1:
                y0, step = y0 * (1 - step), 2 * step
            x = [
                sum(Fraction(F[i][j]) * Fraction(y0[j]) for j in range(n))
                + int(sign) * Fraction(segments[b][i])
                for i in range(n)
            ]
            assert _exact_form(x, np.zeros(n), out_P[b]) <= 1, (b, y0)
            checked += 1
    assert checked > PROBLEMS * 20


def test_box_contains_its_corners_and_a_zero_box_changes_nothing():
    rng = np.random.default_rng(7)
    P = _random_shapes(rng, 3, 1)[0]
    widths = np.array([0.3, 0.0, 1.2]) * np.sqrt(np.diag(P))
    out = add_box(jnp.asarray(P), jnp.asarray(widths))
    for y in _boundary_points(rng, np.zeros(3), P, 50):
        if _exact_form(y, np.zeros(3), P) <= 1:
            for corner in ((1, 1, 1), (-1, 1, -1), (1, -1, -1), (-1, -1, 1)):
                x = [Fraction(y[i]) + corner[i] * Fraction(widths[i]) for i in range(3)]
                assert _exact_form(x, np.zeros(3), out) <= 1
    np.testing.assert_array_equal(np.asarray(add_box(jnp.asarray(P), jnp.zeros(3))), P)


def test_rounding_margin_is_small_where_the_set_is_well_conditioned():
    """The inflation costs at most 16 n u cond(P) cond(P+) of the exact set's own metric
    (measured up to about 10 u cond(P) cond(P+) for rotated shapes), and a few ulps where
    nothing cancels: the issue's axis-aligned elongated set keeps P22 to 1e-14."""
    from tests.test_ellipsoid import _exact_strip

    u = np.finfo(float).eps / 2
    rng = np.random.default_rng(5)
    for n in (2, 3):
        for _ in range(30):
            P = _random_shapes(rng, n, 1)[0]
            h = rng.normal(size=n)
            g = h @ P @ h
            v = np.sqrt(g) * 10.0 ** rng.uniform(-6, -0.5)
            z = rng.uniform(-0.5, 0.5) * np.sqrt(g)
            _, shape, _ = intersect_strip(*map(jnp.asarray, (np.zeros(n), P, h, z, v)))
            exact = _exact_strip(np.zeros(n), P, h, z, v)
            Li = np.linalg.inv(np.linalg.cholesky(exact))
            grown = np.linalg.eigvalsh(Li @ (np.asarray(shape) - exact) @ Li.T)
            bound = 16 * n * u * np.linalg.cond(P) * np.linalg.cond(exact)
            assert grown[0] > -1e-12 and grown[-1] < max(bound, 1e-12), (grown, bound)
    P = np.diag([2e5, 1e14])
    _, shape, _ = intersect_strip(
        jnp.zeros(2), jnp.asarray(P), jnp.array([0.0, 1.0]), jnp.asarray(0.01), jnp.asarray(0.05)
    )
    exact = _exact_strip([0, 0], P, [0, 1], 0.01, 0.05)
    assert 0 <= float(shape[1, 1]) / exact[1, 1] - 1 < 1e-14


@pytest.mark.parametrize("n", [2, 3])
def test_containment_test_never_rejects_an_exact_point(n):
    """``contains`` is rounded outward: every float point inside E(c, P) in exact arithmetic is
    reported inside, near-boundary ones included; points outside by 1e-6 are reported outside."""
    rng = np.random.default_rng(300 + n)
    test = jax.jit(jax.vmap(contains, in_axes=(None, None, 0)))
    for P in _random_shapes(rng, n, 20):
        c = rng.normal(size=n)
        X = _boundary_points(rng, c, P, 200)
        exact = np.array([_exact_form(x, c, P) <= 1 for x in X])
        reported = np.asarray(test(jnp.asarray(c), jnp.asarray(P), jnp.asarray(X)))
        assert np.all(reported[exact])
        far = c + (X - c) * (1 + 1e-6)
        if np.linalg.cond(P) < 1e6:
            assert not np.any(test(jnp.asarray(c), jnp.asarray(P), jnp.asarray(far)))


def test_products_are_rounded_in_the_working_precision_on_every_platform():
    """The bounds assume each product rounds in the working precision; JAX's default for float32
    products on recent NVIDIA GPUs is TF32 (10 mantissa bits). With TF32 asked for globally,
    every product of the set operations and of the filter step, the model's own included, is
    still traced at "highest", under ``vmap`` too, while a product outside them gets TF32
    ("HIGH"), so the check can fail. (The global setting is explicit here because importing
    dynamax sets JAX's to float32 for the whole process.)"""
    dtype = jnp.float32
    P = jnp.asarray([[2.0, 0.3], [0.3, 1.0]], dtype)
    c, a = jnp.asarray([0.1, -0.2], dtype), jnp.asarray([1.0, 0.5], dtype)
    set_operations = [
        (lambda P: linear_image(2 * P, P), P),
        (lambda P: add_box_of_segments(P, P), P),
        (lambda P: intersect_strip(c, P, a, a[0], a[1]), P),
        (lambda P: contains(c, P, a), P),
    ]
    model = duffing.model(closed_form_bound=True, dtype=dtype)
    prior = Ellipsoid(jnp.asarray(duffing.X0, dtype), 0.01 * jnp.eye(2, dtype=dtype))
    runs = jax.vmap(lambda ys: run(SetMembershipFilter(), model, ys, prior=prior).shape)
    predicted = lambda P: SetMembershipFilter().predict(model, Ellipsoid(c, P)).shape  # noqa: E731
    with jax.default_matmul_precision("tensorfloat32"):
        for fn, arg in [*set_operations, (predicted, P), (runs, jnp.ones((3, 5, 2), dtype))]:
            precisions = dot_precisions(fn, arg)
            assert precisions and set(precisions) == {"HIGHEST"}
        assert dot_precisions(lambda P: P @ P, P) == ["HIGH"]
