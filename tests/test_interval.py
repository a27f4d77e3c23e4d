"""Interval arithmetic: outward rounding against exact rationals, every rule against dense sampling,
Hessian enclosures and remainder bounds against sampled true values, the Duffing closed form."""

import decimal
from fractions import Fraction

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.special

from jaxest._jaxpr import zero_outputs
from jaxest.setmembership import interval as iv
from jaxest.setmembership.interval import Interval, bounding_box, hessian_interval, remainder_bound
from jaxest.systems import duffing


def _random_interval(rng, shape, scale=2.0, dtype=np.float64):
    a, b = rng.uniform(-scale, scale, shape), rng.uniform(-scale, scale, shape)
    return Interval(jnp.asarray(np.minimum(a, b), dtype), jnp.asarray(np.maximum(a, b), dtype))


def _samples(x: Interval, rng, count=400):
    lo, hi = np.asarray(x.lo, np.float64), np.asarray(x.hi, np.float64)
    t = rng.uniform(size=(count, *lo.shape))
    t[0], t[1] = 0.0, 1.0  # the endpoints themselves
    return np.clip(lo + t * (hi - lo), lo, hi)  # the sum may round past hi


def test_outward_rounding_contains_exact_rational_results():
    rng = np.random.default_rng(0)
    a = rng.uniform(-1, 1, 200)
    b = rng.uniform(0.1, 1, 200)
    A, B = iv.point(jnp.asarray(a)), iv.point(jnp.asarray(b))
    for op, exact in ((iv.add, lambda x, y: x + y), (iv.sub, lambda x, y: x - y),
                      (iv.mul, lambda x, y: x * y), (iv.div, lambda x, y: x / y)):  # fmt: skip
        out = op(A, B)
        for i in range(200):
            value = exact(Fraction(float(a[i])), Fraction(float(b[i])))
            assert Fraction(float(out.lo[i])) <= value <= Fraction(float(out.hi[i]))
            assert Fraction(float(out.lo[i])) < value or Fraction(float(out.hi[i])) > value
    # a sum that is not exactly representable: the exact value lies strictly inside
    s = iv.add(iv.point(jnp.asarray(0.1)), iv.point(jnp.asarray(0.2)))
    assert Fraction(float(s.lo)) < Fraction(0.1) + Fraction(0.2) < Fraction(float(s.hi))


UNARY = {
    "sin": (iv.sin, np.sin, 8.0), "cos": (iv.cos, np.cos, 8.0), "exp": (None, np.exp, 2.0),
    "tanh": (None, np.tanh, 3.0), "atan": (None, np.arctan, 3.0), "abs": (iv.abs_, np.abs, 2.0),
    "square": (None, np.square, 2.0), "asin": (iv.asin, np.arcsin, 1.0),
    "acos": (iv.acos, np.arccos, 1.0), "atanh": (None, np.arctanh, 0.999),
}  # fmt: skip


@pytest.mark.parametrize("name", list(UNARY))
def test_unary_rules_contain_dense_samples(name):
    rule, fn, scale = UNARY[name]
    rule = rule or iv._rule(name)
    rng = np.random.default_rng(1)
    x = _random_interval(rng, (300,), scale)
    out = rule(x)
    values = fn(_samples(x, rng))
    assert np.all(values >= np.asarray(out.lo)) and np.all(values <= np.asarray(out.hi))
    # tight: for these monotone-by-piece functions the hull of dense samples nearly fills it
    width = np.asarray(out.hi - out.lo)
    assert np.all(values.max(0) - values.min(0) >= 0.95 * width - 1e-3)


def test_composed_rules_contain_dense_samples():
    """sinh, cosh, erfc and pow are composed of exp, log, erf (no trust in XLA's own); their
    enclosures hold dense samples, the positive bases of pow included, and a function of
    x^2.5 cosh(y), sinh(xy) and asin(xy) has a Hessian enclosure that holds the sampled Hessians."""
    rng = np.random.default_rng(5)
    x = _random_interval(rng, (300,), 3.0)
    xs = _samples(x, rng)
    lo, hi = np.sort(rng.uniform(0.01, 5, (2, 300)), axis=0)
    base = Interval(jnp.asarray(lo), jnp.asarray(hi))
    bs = _samples(base, rng)
    exponents = (2.5, -0.5, 1 / 3)

    @jax.jit  # one program where op-by-op evaluation compiled about a hundred
    def enclosures(x, base):
        return [iv._rule(name)(x) for name in ("sinh", "cosh", "erfc")] + [
            iv._rule("pow")(base, jnp.asarray(y)) for y in exponents
        ] + [iv._rule("pow")(jnp.asarray(2.0), x)]  # fmt: skip

    sampled = [np.sinh(xs), np.cosh(xs), scipy.special.erfc(xs), *[bs**y for y in exponents]]
    for out, values in zip(enclosures(x, base), [*sampled, 2.0**xs], strict=True):
        assert np.all(values >= np.asarray(out.lo)) and np.all(values <= np.asarray(out.hi))
    f = lambda v: jnp.stack(
        [(2 + v[0]) ** 2.5 * jnp.cosh(v[1]), jnp.sinh(v[0] * v[1]) + jnp.arcsin(v[0] * v[1])]
    )
    box = Interval(jnp.asarray([0.1, -0.3]), jnp.asarray([0.4, 0.2]))
    enclosure = jax.jit(iv.hessian_interval, static_argnums=0)(f, box)
    hessians = jax.vmap(jax.hessian(f))(jnp.asarray(_samples(box, rng)))
    assert np.all(hessians >= enclosure.lo) and np.all(hessians <= enclosure.hi)


def test_positive_domain_rules_and_poles():
    rng = np.random.default_rng(2)
    lo, hi = np.sort(rng.uniform(0.01, 5, (2, 200)), axis=0)
    x = Interval(jnp.asarray(lo), jnp.asarray(hi))
    for out, fn in (
        (iv.sqrt(x), np.sqrt),
        (iv.log(x), np.log),
        (iv.integer_pow(x, -2), lambda v: v**-2.0),
        (iv.acosh(iv.add(x, 1.0)), lambda v: np.arccosh(v + 1.0)),
    ):
        values = fn(_samples(x, rng))
        assert np.all(values >= np.asarray(out.lo)) and np.all(values <= np.asarray(out.hi))
    # asin and acos on intervals reaching past [-1, 1]: the range over the part inside it
    reaching = Interval(jnp.asarray([0.5, -3.0]), jnp.asarray([2.0, -0.5]))
    for rule, fn in ((iv.asin, np.arcsin), (iv.acos, np.arccos)):
        out, ends = rule(reaching), fn(np.asarray([[0.5, -1.0], [1.0, -0.5]]))
        assert np.all(np.asarray(out.lo) <= ends.min(0))
        assert np.all(np.asarray(out.hi) >= ends.max(0))
        np.testing.assert_allclose(np.asarray(out.hi - out.lo), np.ptp(ends, 0), rtol=1e-12)
    assert np.isnan(iv.asin(Interval(jnp.asarray([1.5]), jnp.asarray([2.0]))).lo[0])  # no x in it
    # atanh's poles at +-1 and acosh's domain x >= 1: the part inside, or NaN where none is
    assert np.isinf(iv.atanh(reaching).hi[0]) and np.isinf(iv.atanh(reaching).lo[1])
    assert np.isnan(iv.atanh(Interval(jnp.asarray([1.5]), jnp.asarray([2.0]))).lo[0])
    below = iv.acosh(Interval(jnp.asarray([0.0, -2.0]), jnp.asarray([2.0, 0.5])))
    assert float(below.lo[0]) <= 0.0 <= float(below.hi[0]) and np.isnan(below.lo[1])
    t = iv.tan(Interval(jnp.asarray([1.0, -0.5]), jnp.asarray([2.0, 0.5])))  # the first holds pi/2
    assert np.isinf(t.lo[0]) and np.isinf(t.hi[0]) and np.isfinite(t.hi[1])
    d = iv.div(iv.point(jnp.ones(1)), Interval(jnp.asarray([-1.0]), jnp.asarray([1.0])))
    assert np.isinf(d.lo[0]) and np.isinf(d.hi[0])


def test_binary_rules_contain_dense_samples():
    rng = np.random.default_rng(3)
    a, b = _random_interval(rng, (300,)), _random_interval(rng, (300,))
    sa, sb = _samples(a, rng), _samples(b, rng)
    for out, values in (
        (iv.mul(a, b), sa * sb), (iv.integer_pow(a, 3), sa**3), (iv.integer_pow(a, 4), sa**4),
        (iv.atan2(a, b), np.arctan2(sa, sb)), (iv.max_(a, b), np.maximum(sa, sb)),
        (iv.min_(a, b), np.minimum(sa, sb)),
    ):  # fmt: skip
        assert np.all(values >= np.asarray(out.lo)) and np.all(values <= np.asarray(out.hi))


def test_dot_general_contains_sampled_products():
    rng = np.random.default_rng(4)
    A, x = _random_interval(rng, (3, 4)), _random_interval(rng, (4,))
    out = iv.dot_general(A, x, dimension_numbers=(([1], [0]), ([], [])))
    sA, sx = _samples(A, rng, 2000), _samples(x, rng, 2000)
    values = np.einsum("sij,sj->si", sA, sx)
    assert np.all(values >= np.asarray(out.lo)) and np.all(values <= np.asarray(out.hi))
    # a point matrix times an interval vector: the enclosure is (nearly) exact
    M = rng.normal(size=(3, 4))
    exact = iv.dot_general(iv.point(jnp.asarray(M)), x, dimension_numbers=(([1], [0]), ([], [])))
    lo = np.maximum(M, 0) @ np.asarray(x.lo) + np.minimum(M, 0) @ np.asarray(x.hi)
    np.testing.assert_allclose(np.asarray(exact.lo), lo, rtol=1e-12, atol=1e-12)


def _model_functions():
    """Functions touching the primitives ordinary models use."""
    return {
        "trig": lambda x: jnp.stack([jnp.sin(x[0]) * jnp.cos(x[1]), jnp.tan(0.3 * x[0]) + x[1] ** 3]),
        "exp_log": lambda x: jnp.array([jnp.exp(0.5 * x[0]) * jnp.log(2.5 + x[1]), jnp.sqrt(3.0 + x[0] * x[1])]),
        "atan": lambda x: jnp.stack([jnp.arctan2(x[1], 2.0 + x[0]), jnp.arctan(x[0] * x[1])]),
        "tanh_abs_minmax": lambda x: jnp.stack([jnp.tanh(x[0] - x[1]) + jnp.abs(x[0]), jnp.maximum(x[0], x[1]) ** 2 + jnp.minimum(x[0], 0.2)]),
        "dot_index": lambda x: jnp.array([[1.0, -2.0], [0.5, 3.0]]) @ (x * x[jnp.array([1, 0])]) + x[-1] * jnp.sum(x**2),
        "division": lambda x: jnp.stack([x[0] / (2.0 + x[1] ** 2), 1.0 / (3.0 + x[0])]),
    }  # fmt: skip


@pytest.mark.parametrize("name", list(_model_functions()))
def test_hessian_interval_contains_sampled_hessians(name):
    fn = _model_functions()[name]
    rng = np.random.default_rng(5)
    center = jnp.asarray(rng.uniform(-0.5, 0.5, 2))
    box = Interval(center - 0.4, center + 0.4)
    enclosure = jax.jit(lambda b: hessian_interval(fn, b))(box)
    points = _samples(box, rng, 500)
    hessians = np.asarray(jax.vmap(jax.hessian(fn))(jnp.asarray(points)))
    assert np.all(hessians >= np.asarray(enclosure.lo)) and np.all(
        hessians <= np.asarray(enclosure.hi)
    )
    assert np.all(np.isfinite(np.asarray(enclosure.lo)))


def _sampled_remainders(fn, center, shape, rng, count=20000):
    """|fn(x) - fn(c) - J(c)(x - c)| at points of E(c, P), half of them on its boundary."""
    n = center.shape[0]
    u = rng.normal(size=(count, n))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    u[: count // 2] *= rng.uniform(size=(count // 2, 1)) ** (1 / n)
    points = jnp.asarray(np.asarray(center) + u @ np.linalg.cholesky(np.asarray(shape)).T)
    J = jax.jacfwd(fn)(center)
    return np.abs(np.asarray(jax.vmap(lambda x: fn(x) - fn(center) - J @ (x - center))(points)))


@pytest.mark.parametrize(
    "name, fn, center",
    [
        ("min(x^2, 1)", lambda x: jnp.minimum(x**2, 1.0), [0.9, 0.0]),
        ("clip", lambda x: jnp.clip(x, -0.2, 0.3), [0.1, 0.0]),
        ("x |x|", lambda x: x * jnp.abs(x), [0.1, -0.2]),
        ("max of two", lambda x: jnp.maximum(x[:1] ** 2, 2 * x[1:]), [0.5, 0.2]),
        ("hypot", lambda x: jnp.hypot(x[:1], x[1:]), [1.0, 0.5]),
        ("softplus", lambda x: jax.nn.softplus(3 * x), [0.0, 0.1]),
        (
            "max of a vector",
            lambda x: jnp.max(jnp.stack([x[0] ** 2, 2 * x[1], x[0] + x[1]]))[None],
            [0.5, 0.2],
        ),
        ("infinity norm", lambda x: jnp.linalg.norm(x, ord=jnp.inf)[None], [0.1, -0.05]),
        ("min over an axis", lambda x: jnp.min(jnp.outer(x, x + 1.0), axis=1), [0.2, 0.1]),
        (
            "max in a loop",
            lambda x: jax.lax.fori_loop(0, 2, lambda i, v: v + 0.1 * jnp.max(v), x),
            [0.3, 0.3],
        ),
    ],
    ids=[
        "min",
        "clip",
        "x_abs_x",
        "max",
        "hypot",
        "softplus",
        "max_vector",
        "norm_inf",
        "min_axis",
        "max_loop",
    ],
)
def test_remainder_bound_holds_across_a_kink(name, fn, center):
    """A kink in the set (a jump of the first derivative: abs, max, min switching branch) has no
    Hessian: the branches' Hessians bounded min(x^2, 1)'s remainder at c = 0.9, P = 0.25 by
    0.25 where 0.71 is attained. The first-order mean-value bound holds; smooth functions
    written with max and abs (hypot, softplus) keep a finite bound, and so do ``jnp.max`` and
    ``jnp.min`` of an array, whose bound was infinite wherever two entries may tie over the set
    (JAX divides their derivative by the number of tied entries, which intervals put at 0)."""
    center = jnp.asarray(center)
    shape = 0.25 * jnp.eye(2)
    alpha = np.asarray(jax.jit(lambda c, P: remainder_bound(fn, c, P))(center, shape))
    sampled = _sampled_remainders(fn, center, shape, np.random.default_rng(3))
    assert np.all(np.isfinite(alpha)) and np.all(sampled <= alpha)


def test_remainder_bound_is_nan_where_the_value_may_jump():
    """sign and a where whose condition changes over the set may jump: no bound holds (NaN,
    which the set-membership filter flags); over a set where they do not switch, the bound is
    the smooth one (zero for a constant branch)."""
    step = lambda x: jnp.where(x > 0, 1.0, 0.0)
    integer_step = lambda x: jnp.where(x > 0, 1, 0) * x  # raised an OverflowError (inf as int)
    for fn in (jnp.sign, step, integer_step):
        across = remainder_bound(fn, jnp.zeros(1), 0.01 * jnp.eye(1))
        assert np.all(np.isnan(np.asarray(across)))
        away = remainder_bound(fn, jnp.ones(1), 0.01 * jnp.eye(1))
        np.testing.assert_array_equal(away, [0.0])
    # without non-smooth operations the primal is not evaluated over intervals: jnp.prod's
    # reduce_prod has no interval rule, but its Hessian is products, and the bound stays
    product = remainder_bound(
        lambda x: jnp.prod(x)[None], jnp.asarray([2.0, 1.0]), 0.5 * jnp.eye(2)
    )
    assert np.all(np.isfinite(np.asarray(product)))


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_remainder_bound_is_nan_where_a_cast_to_integers_or_booleans_may_change(dtype):
    """A comparison turned into a number and a truncation to integers are steps, which JAX
    differentiates as constants: their bound was 0 across the step, where the sampled remainder
    reaches the step's height. Across a step: NaN; over a box where the cast is constant: the
    bound of the rest; a cast of an exact integer argument is no step."""
    bound = jax.jit(remainder_bound, static_argnums=0)
    shape = 0.01 * jnp.eye(2, dtype=dtype)
    step = lambda x: 0.5 * (x > 0.1).astype(x.dtype)
    truncated = lambda x: x.astype(jnp.int32).astype(x.dtype) + x**2
    over_step = jnp.asarray([0.05, 0.5], dtype)  # x_1 in [-0.05, 0.15]: the step at 0.1
    over_one = jnp.asarray([0.5, 0.95], dtype)  # x_2 in [0.85, 1.05]: truncation steps at 1
    assert _sampled_remainders(step, over_step, shape, np.random.default_rng(0), 2000).max() > 0.4
    assert np.all(np.isnan(np.asarray(bound(step, over_step, shape))))
    assert np.all(np.isnan(np.asarray(bound(truncated, over_one, shape))))
    np.testing.assert_array_equal(bound(step, over_one, shape), [0.0, 0.0])
    np.testing.assert_allclose(bound(truncated, over_step, shape), [0.01, 0.01], rtol=1e-5)
    # arithmetic on integers is exact (moving an integer endpoint an ulp out: an OverflowError)
    shifted = lambda x: (x.astype(jnp.int32) - 1).astype(x.dtype) + x**2
    np.testing.assert_allclose(bound(shifted, over_step, shape), [0.01, 0.01], rtol=1e-5)
    assert np.all(np.isnan(np.asarray(bound(shifted, over_one, shape))))
    # an exact integer (a step index) made a float is no step, and the function is not evaluated
    # over intervals for it: jnp.prod (reduce_prod) has no interval rule, its Hessian has
    count = jnp.asarray(3, jnp.int32)
    scaled = bound(lambda x, n: n.astype(x.dtype) * x, over_step, shape, count)
    np.testing.assert_array_equal(scaled, [0.0, 0.0])
    product = bound(lambda x, n: jnp.prod(x)[None] * n.astype(x.dtype), over_step, shape, count)
    assert np.all(np.isfinite(np.asarray(product))) and float(product[0]) > 0


def test_remainder_bound_is_nan_where_atan2_may_cross_its_branch_cut():
    """atan2 is pi on the negative x axis and near -pi just below it, and undefined at the
    origin; JAX's derivatives are smooth across the cut, so a bearing's bound there was 0.024
    where the sampled remainder reaches 2 pi. Away from the cut and the origin the bound holds."""
    bearing = lambda v: jnp.arctan2(v[1:], v[:1])
    shape = 0.01 * jnp.eye(2)
    on_the_cut = jnp.asarray([-1.0, 0.0])
    assert _sampled_remainders(bearing, on_the_cut, shape, np.random.default_rng(1)).max() > 6
    assert np.isnan(float(remainder_bound(bearing, on_the_cut, shape)[0]))
    assert np.isnan(float(remainder_bound(bearing, jnp.asarray([0.05, 0.05]), shape)[0]))
    for center in ([-1.0, 0.5], [1.0, 0.0]):  # beside the cut; across the positive x axis
        center = jnp.asarray(center)
        alpha = np.asarray(remainder_bound(bearing, center, shape))
        sampled = _sampled_remainders(bearing, center, shape, np.random.default_rng(2))
        assert np.all(np.isfinite(alpha)) and np.all(sampled <= alpha)
    # an exact y (the rule lifts it; it raised an AttributeError): pi throughout, or a jump at 0
    angle = lambda v: jnp.arctan2(jnp.zeros(1), v[:1])
    np.testing.assert_array_equal(remainder_bound(angle, jnp.asarray([-0.5, 0.0]), shape), [0.0])
    assert np.isnan(float(remainder_bound(angle, jnp.asarray([0.05, 0.0]), shape)[0]))


@pytest.mark.parametrize("name", ["trig", "exp_log", "atan", "dot_index"])
def test_remainder_bound_contains_sampled_remainders(name):
    fn = _model_functions()[name]
    rng = np.random.default_rng(6)
    center = jnp.asarray(rng.uniform(-0.5, 0.5, 2))
    A = rng.normal(size=(2, 2)) * 0.2
    shape = jnp.asarray(A @ A.T + 0.01 * np.eye(2))
    alpha = np.asarray(jax.jit(lambda c, P: remainder_bound(fn, c, P))(center, shape))
    u = rng.normal(size=(5000, 2))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    u *= np.sqrt(rng.uniform(size=(5000, 1)))
    points = jnp.asarray(np.asarray(center) + u @ np.linalg.cholesky(np.asarray(shape)).T)
    J = jax.jacfwd(fn)(center)
    remainders = np.asarray(jax.vmap(lambda x: fn(x) - fn(center) - J @ (x - center))(points))
    assert np.all(np.abs(remainders) <= alpha)
    assert np.all(np.max(np.abs(remainders), axis=0) > 0.02 * alpha)  # bound is not vacuous


AFFINE = {
    "identity": lambda x, u: x,
    "matrix": lambda x, u: jnp.asarray([[1.0, 2.0], [3.0, -4.0]]) @ x + 1.0,
    "input_gain": lambda x, u: u * x,
    "reversed": lambda x, u: x[::-1],
    "stacked": lambda x, u: jnp.concatenate([x, 2.0 * x[:1] - x[1:]]),
}


@pytest.mark.parametrize("dtype", ["float32", "float64"])
@pytest.mark.parametrize("name", sorted(AFFINE))
def test_affine_function_bound_is_zero_and_compiles_no_interval_arithmetic(name, dtype):
    """An affine function's remainder is exactly zero; the bound says so when it is traced, so
    the compiled program (here under jit of vmap, the input a traced argument) has none of the
    outward-rounded interval arithmetic (``nextafter``), which made up half of a set-membership
    step with h(x) = x. A quadratic keeps it and a positive bound."""
    fn, dt = AFFINE[name], jnp.dtype(dtype)
    centers = jnp.asarray([[0.2, -0.3], [1.5, 0.7]], dt)
    shapes = jnp.stack([0.01 * jnp.eye(2, dtype=dt), jnp.asarray([[4.0, 1.0], [1.0, 2.0]], dt)])
    inputs = jnp.asarray([[2.0, 3.0], [-1.0, 0.5]], dt)
    bound = jax.jit(jax.vmap(lambda c, P, u: remainder_bound(fn, c, P, u)))
    alpha = bound(centers, shapes, inputs)
    assert alpha.dtype == dt and alpha.shape == (2, jax.eval_shape(fn, centers[0], inputs[0]).size)
    np.testing.assert_array_equal(alpha, 0.0)
    assert "nextafter" not in bound.lower(centers, shapes, inputs).compile().as_text()
    quadratic = jax.jit(
        jax.vmap(lambda c, P, u: remainder_bound(lambda x, u: fn(x, u) ** 2, c, P, u))
    )
    assert np.all(np.asarray(quadratic(centers, shapes, inputs)) > 0)
    assert "nextafter" in quadratic.lower(centers, shapes, inputs).compile().as_text()


def test_zero_hessian_is_not_taken_from_a_kink():
    """A kink (abs, whose branches' Hessians are zero) keeps its first-order bound."""
    across_kink = remainder_bound(jnp.abs, jnp.zeros(2), 0.1 * jnp.eye(2))
    assert np.all(np.asarray(across_kink) > 0)


def test_zero_outputs_sees_zeros_built_from_zero_literals_only():
    """``zero_outputs`` (the test of the shortcut above) is true for the zeros JAX writes as a
    derivative, false for a constant that is not zero and for anything computed from x."""
    x = jnp.zeros(2)
    hessian = lambda fn: jax.make_jaxpr(jax.hessian(fn))(x).jaxpr
    assert zero_outputs(hessian(lambda x: 3.0 * x[::-1] + 1.0))
    assert not zero_outputs(hessian(lambda x: x**2))  # 2 on the diagonal
    assert not zero_outputs(jax.make_jaxpr(lambda x: 0.0 * x)(x).jaxpr)  # NaN where x is inf
    select = jax.make_jaxpr(lambda x: jnp.where(x > 0, 0.0, jnp.ones(2)))(x).jaxpr
    assert not zero_outputs(select)


def test_duffing_closed_form_agrees_with_automatic_bound():
    rng = np.random.default_rng(7)
    f = duffing.Duffing()
    c = jnp.asarray(rng.uniform(-1, 1, (50, 2)))
    A = rng.normal(size=(50, 2, 2)) * rng.uniform(0.01, 0.5, (50, 1, 1))
    P = jnp.asarray(A @ np.swapaxes(A, 1, 2) + 1e-4 * np.eye(2))
    auto = np.asarray(jax.jit(jax.vmap(lambda c, P: remainder_bound(f, c, P)))(c, P))
    closed = np.asarray(jax.vmap(f.remainder_bound)(c, P))
    assert np.all(auto[:, 0] == 0.0) and np.all(closed[:, 0] == 0.0)
    np.testing.assert_allclose(auto[:, 1], closed[:, 1], rtol=1e-13)


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_remainder_bound_under_jit_vmap_grad(dtype):
    dt = jnp.dtype(dtype)
    f = duffing.Duffing()
    centers = jnp.asarray([[0.2, 0.3], [-0.4, 0.1], [0.0, 0.0]], dt)
    P = 0.01 * jnp.eye(2, dtype=dt)
    bound = jax.jit(lambda c, P: remainder_bound(f, c, P)[1])
    batched = jax.jit(jax.vmap(lambda c: remainder_bound(f, c, P)))(centers)
    assert batched.dtype == dt and batched.shape == (3, 2)
    closed = jax.vmap(lambda c: f.remainder_bound(c, P))(centers)
    np.testing.assert_allclose(batched, closed, rtol=1e-5 if dtype == "float32" else 1e-13)
    g, gP = jax.jit(jax.grad(bound, argnums=(0, 1)))(centers[0], P)
    expected = jax.grad(lambda c: f.remainder_bound(c, P)[1])(centers[0])
    np.testing.assert_allclose(g, expected, rtol=1e-4)
    # gradient with respect to P11 against central differences
    h = 1e-3 if dtype == "float32" else 1e-6
    E = jnp.zeros((2, 2), dt).at[0, 0].set(h * 0.01)
    fd = (bound(centers[0], P + E) - bound(centers[0], P - E)) / (2 * h * 0.01)
    np.testing.assert_allclose(gP[0, 0], fd, rtol=1e-2 if dtype == "float32" else 1e-6)


def test_bounding_box_contains_ellipsoid():
    c = jnp.asarray([0.3, -0.2])
    P = jnp.asarray([[0.04, 0.01], [0.01, 0.09]])
    box = bounding_box(c, P)
    assert np.all(np.asarray(box.lo) < np.asarray(c) - np.sqrt([0.04, 0.09]) + 1e-15)
    assert np.all(np.asarray(box.hi) > np.asarray(c) + np.sqrt([0.04, 0.09]) - 1e-15)


def test_unsupported_primitive_is_named():
    fn = lambda x: jnp.linalg.inv(jnp.diag(x + 2.0)).ravel()
    with pytest.raises(NotImplementedError, match="'lu'"):
        hessian_interval(fn, Interval(jnp.zeros(2), jnp.ones(2)))


def _pendulum_substeps(x):
    """Three explicit Euler substeps of a damped pendulum in a ``fori_loop`` (a ``scan``)."""
    field = lambda v: jnp.stack([v[1], -jnp.sin(v[0]) - 0.1 * v[1]])
    return jax.lax.fori_loop(0, 3, lambda i, v: v + 0.1 * field(v), x)


def _outputs_reversed(x):
    """A reversed ``scan`` whose per-step outputs are summed."""
    step = lambda carry, a: (carry + a * carry**2, jnp.sin(carry) * a)
    return jnp.sum(jax.lax.scan(step, x, jnp.asarray([0.5, -1.0, 2.0]), reverse=True)[1], axis=0)


@pytest.mark.parametrize(
    "fn",
    [
        _pendulum_substeps,
        lambda x: jnp.polyval(jnp.asarray([1.0, -2.0, 0.5]), x),
        _outputs_reversed,
        lambda x: jnp.cumsum(jnp.sin(x) * x[::-1]),
        lambda x: jax.lax.cumsum(x**2 * x[0], reverse=True),
    ],
    ids=["fori_loop", "polyval", "scan_reversed", "cumsum", "cumsum_reversed"],
)
def test_loops_are_evaluated_over_intervals_step_by_step(fn):
    """``lax.scan`` and ``fori_loop`` with a fixed trip count (an integrator's substeps, Horner's
    rule in ``jnp.polyval``, a reversed scan with per-step outputs) have their body evaluated
    over intervals once per step; they raised NotImplementedError ('scan'). Running sums
    (``cumsum``, forward and reversed) raised NotImplementedError ('cumsum')."""
    center, shape = jnp.asarray([0.3, 0.5]), 0.04 * jnp.eye(2)
    alpha = np.asarray(jax.jit(lambda c, P: remainder_bound(fn, c, P))(center, shape))
    sampled = _sampled_remainders(fn, center, shape, np.random.default_rng(7))
    assert np.all(np.isfinite(alpha)) and np.all(sampled <= alpha)
    assert np.all(np.max(sampled, axis=0) > 0.05 * alpha)  # bound is not vacuous


def _branch_on_x1(threshold):
    """``cond`` on x_1 > threshold between a product and a cube."""
    return lambda x: jax.lax.cond(
        x[0] > threshold, lambda v: jnp.stack([v[0] * v[1], jnp.sin(v[1])]), lambda v: v**3, x
    )


@pytest.mark.parametrize(
    "fn",
    [
        _branch_on_x1(-5.0),
        _branch_on_x1(5.0),
        lambda x: jax.lax.switch(
            2, [lambda v: v**2, jnp.exp, lambda v: jnp.arctanh(v * v[::-1])], x
        ),
        lambda x: jax.lax.switch(jnp.floor(x[0] + 10).astype(jnp.int32) - 9, [jnp.exp, jnp.sin], x),
        lambda x: jax.lax.cond(
            x[0] > -5.0, lambda v: jnp.stack([v[0] * v[1], jnp.max(v)]), jnp.cos, x
        ),
    ],
    ids=["cond_true", "cond_false", "switch", "switch_on_floor", "max_in_branch"],
)
def test_branches_are_evaluated_over_intervals(fn):
    """``lax.cond`` and ``lax.switch`` whose branch is the same over the set (the index a
    constant, a comparison or a ``floor`` that does not change there) are bounded by that
    branch; a ``jnp.max`` in a branch is rewritten pairwise as elsewhere (its bound was
    infinite). They raised NotImplementedError ('cond'; 'floor' and 'clamp' for the index)."""
    center, shape = jnp.asarray([0.3, 0.5]), 0.04 * jnp.eye(2)
    alpha = np.asarray(jax.jit(lambda c, P: remainder_bound(fn, c, P))(center, shape))
    sampled = _sampled_remainders(fn, center, shape, np.random.default_rng(8))
    assert np.all(np.isfinite(alpha)) and np.all(sampled <= alpha)
    assert np.all(np.max(sampled, axis=0) > 0.05 * alpha)  # bound is not vacuous


def test_branches_that_may_switch_over_the_set_give_nan():
    """A ``cond`` whose condition, or a ``switch`` whose ``floor`` index, changes over the set
    may jump there: NaN, which the set-membership filter flags (the sampled remainder reaches
    the jump)."""
    center, shape = jnp.asarray([0.3, 0.5]), 0.04 * jnp.eye(2)
    on_floor = lambda x: jax.lax.switch(
        jnp.floor(2 * x[0] + 0.5).astype(jnp.int32), [jnp.sin, jnp.exp], x
    )
    for fn in (_branch_on_x1(0.3), on_floor):
        assert _sampled_remainders(fn, center, shape, np.random.default_rng(9)).max() > 0.2
        assert np.all(np.isnan(np.asarray(remainder_bound(fn, center, shape))))


def test_bad_boxes_and_ellipsoids_are_named():
    # an empty box's "enclosure" was any number; a wrong-sized shape failed in JAX's broadcasting
    cube = lambda x: x**3
    with pytest.raises(ValueError, match="^box: has lo > hi"):
        hessian_interval(cube, Interval(jnp.ones(1), -jnp.ones(1)))
    with pytest.raises(ValueError, match="^box: expected an Interval"):
        hessian_interval(cube, Interval(jnp.zeros(1), jnp.ones(2)))
    with pytest.raises(ValueError, match="^center: expected shape \\(3,\\)"):
        remainder_bound(cube, jnp.zeros(2), jnp.eye(3))
    with pytest.raises(ValueError, match="^center: must be real floating point"):
        remainder_bound(cube, jnp.zeros(2, int), jnp.eye(2))
    # a function that is not one was JAX's TypeError from inside
    with pytest.raises(ValueError, match="^fn: expected a function, got str"):
        remainder_bound("x**3", jnp.zeros(2), jnp.eye(2))
    with pytest.raises(ValueError, match="^fn: expected a function, got str"):
        hessian_interval("x**3", Interval(jnp.zeros(1), jnp.ones(1)))


def test_reduce_sum_widens_relative_to_the_magnitude_of_the_terms():
    # the float sum of [1e16, 1, -1e16] is 0; the exact sum 1 must lie in the result
    x = Interval(jnp.array([1e16, 1.0, -1e16]), jnp.array([1e16, 1.0, -1e16]))
    total = iv.reduce_sum(x, (0,))
    assert float(total.lo) <= 1.0 <= float(total.hi)
    rng = np.random.default_rng(3)
    for _ in range(50):
        v = rng.normal(size=8) * 10.0 ** rng.integers(-8, 17, 8)
        exact = sum(Fraction(float(t)) for t in v)
        s = iv.reduce_sum(Interval(jnp.asarray(v), jnp.asarray(v)), (0,))
        assert Fraction(float(s.lo)) <= exact <= Fraction(float(s.hi))


def test_pow_with_an_integer_valued_float_exponent_holds_negative_bases():
    """x ** 3.0 traces as pow, whose rule was e^(3 log x): over a box reaching below 0 it dropped
    the negative part ([-1.3, 0.1] gave [0, 0.001]; the set-membership filter then excluded the
    truth with status OK). Known integer exponents take integer_pow's rule, under jit too, where
    pow's derivative takes y - 1 of its exponent; an exponent known only when running fails
    (NaN) where the base may be negative."""
    rng = np.random.default_rng(11)
    x = _random_interval(rng, (200,), 2.0)
    xs = _samples(x, rng)
    for y in (3.0, 2.0, 4.0, -1.0, -2.0, 0.0):
        out = jax.jit(lambda x: iv._rule("pow")(x, y))(x)
        integer = iv.integer_pow(x, int(y))
        values = xs**y
        finite = np.isfinite(values)
        assert np.all(values[finite] >= np.broadcast_to(out.lo, values.shape)[finite])
        assert np.all(values[finite] <= np.broadcast_to(out.hi, values.shape)[finite])
        np.testing.assert_array_equal(out.lo, integer.lo)
        np.testing.assert_array_equal(out.hi, integer.hi)
    mixed = jax.jit(lambda x: iv._rule("pow")(x, np.asarray([3.0, 0.5])))(
        Interval(jnp.asarray([-1.0, 0.25]), jnp.asarray([2.0, 4.0]))
    )
    np.testing.assert_allclose(mixed.lo, [-1.0, 0.5], rtol=1e-12)
    np.testing.assert_allclose(mixed.hi, [8.0, 2.0], rtol=1e-12)
    traced = jax.jit(lambda x, y: iv._rule("pow")(x, y))(
        Interval(jnp.asarray([-1.0, 0.5]), jnp.asarray([2.0, 4.0])), jnp.asarray([3.0, 3.0])
    )
    assert np.isnan(traced.lo[0]) and np.isnan(traced.hi[0]) and traced.lo[1] <= 0.125
    center, shape = jnp.asarray([-0.6]), jnp.asarray([[0.49]])
    bound = jax.jit(lambda c, P: remainder_bound(lambda v: v**3.0, c, P))
    np.testing.assert_allclose(bound(center, shape), remainder_bound(lambda v: v**3, center, shape),
                               rtol=1e-12)  # fmt: skip
    sampled = np.linspace(-1.3, 0.1, 10_001)
    assert np.max(np.abs(sampled**3 + 0.216 - 1.08 * (sampled + 0.6))) <= bound(center, shape)[0]


def test_exp2_and_log1p_hold_their_exact_values():
    """2^x and log1p x are composed of exp and log: XLA's own were measured 113 ulps (exp2 at 700.3,
    float64), 8 ulps (exp2 at -46.49, float32) and 10 ulps (log1p at -0.3775, float64) off,
    outside their 4-ulp widening. The exact values come from decimal arithmetic (60 digits)."""
    decimal.getcontext().prec = 60
    cases = [("exp2", 700.3, np.float64), ("exp2", -46.49100875854492, np.float32),
             ("exp2", -26.744972647823943, np.float64), ("log1p", -0.3775169312050366, np.float64),
             ("log1p", 1e-12, np.float64), ("log1p", 3.5, np.float32)]  # fmt: skip
    for name, value, dtype in cases:
        x = decimal.Decimal(float(dtype(value)))
        exact = (x * decimal.Decimal(2).ln()).exp() if name == "exp2" else (1 + x).ln()
        out = iv._rule(name)(iv.point(jnp.asarray(value, dtype)))
        assert decimal.Decimal(float(out.lo)) <= exact <= decimal.Decimal(float(out.hi)), name


def test_a_row_whose_enclosure_fails_leaves_the_other_rows_bounds():
    """An exact zero times a failed (NaN) enclosure is zero: the Hessian of [x0, asin(x1)] over a
    box with x1 past 1 had NaN in row 0 too (its zero cotangent times row 1's NaN), so the
    filter skipped both measurements."""
    alpha = remainder_bound(lambda v: jnp.stack([v[0], jnp.arcsin(v[1])]), jnp.asarray([0.0, 3.0]),
                            0.01 * jnp.eye(2))  # fmt: skip
    assert float(alpha[0]) == 0.0 and np.isnan(alpha[1])


def test_nan_endpoints_stay_nan_and_zero_times_infinity_is_zero():
    """An exact zero times an unbounded interval is 0; a NaN endpoint (a failed enclosure) is not
    turned into 0, so a remainder bound built on it is NaN, not a silently zero half-width."""
    unbounded = iv.Interval(jnp.asarray(-jnp.inf), jnp.asarray(jnp.inf))
    zero = iv.mul(iv.Interval(jnp.asarray(0.0), jnp.asarray(0.0)), unbounded)
    assert -1e-300 < float(zero.lo) <= 0.0 <= float(zero.hi) < 1e-300  # 0, rounded outward
    failed = iv.mul(iv.Interval(jnp.asarray(jnp.nan), jnp.asarray(1.0)), iv.lift(jnp.asarray(2.0)))
    assert np.isnan(float(failed.lo))
    alpha = iv.remainder_bound(
        lambda x, a: a * x**2, jnp.zeros(1), jnp.eye(1), jnp.asarray(jnp.nan)
    )
    assert np.all(np.isnan(alpha))
    np.testing.assert_array_equal(
        iv.remainder_bound(lambda x: 3.0 * x + 1.0, jnp.zeros(1), jnp.eye(1)), 0.0
    )
    # a comparison with a failed enclosure may go either way: it was certainly false (lt, le,
    # gt, ge, eq) or certainly true (ne), so a branch or a jump decided on it went unflagged
    for nan_end in (iv.Interval(jnp.asarray(jnp.nan), jnp.asarray(1.0)),
                    iv.Interval(jnp.asarray(0.0), jnp.asarray(jnp.nan))):  # fmt: skip
        for name in ("lt", "le", "gt", "ge", "eq", "ne"):
            for a, b in (
                (nan_end, iv.lift(jnp.asarray(0.5))),
                (iv.lift(jnp.asarray(0.5)), nan_end),
            ):
                either = iv._compare(a, b, name)
                assert not bool(either.lo) and bool(either.hi), (name, a, b)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_order_and_running_rules_contain_dense_samples(dtype):
    """cumprod, cummax, cummin, sort (its keys and an argsort's indices), argmax, argmin and
    is_finite over random boxes that overlap one another (orders that change over the box): every
    sampled value lies in the enclosure. They raised NotImplementedError."""
    rng = np.random.default_rng(12)
    x = _random_interval(rng, (50, 5), 2.0, dtype)
    xs = _samples(x, rng, 600).astype(dtype)
    order = jnp.broadcast_to(jnp.arange(5, dtype=jnp.int32), (50, 5))
    keys, indices = iv.sort([x, order], 1, True, 1)
    cases = [
        (iv.cumprod(x, 1, False), np.cumprod(xs, axis=2)),
        (iv.cumprod(x, 0, True), np.cumprod(xs[:, ::-1], axis=1)[:, ::-1]),
        (iv.cumulative_extremum(x, "cummax", 1, False), np.maximum.accumulate(xs, axis=2)),
        (iv.cumulative_extremum(x, "cummin", 1, True),
         np.minimum.accumulate(xs[..., ::-1], axis=2)[..., ::-1]),
        (keys, np.sort(xs, axis=2)),
        (indices, np.argsort(xs, axis=2, kind="stable")),
        (iv.arg_extremum(x, "argmax", 1, jnp.int32), np.argmax(xs, axis=2)),
        (iv.arg_extremum(x, "argmin", 0, jnp.int32), np.argmin(xs, axis=1)),
    ]  # fmt: skip
    for out, values in cases:
        assert np.all(values >= np.asarray(out.lo)) and np.all(values <= np.asarray(out.hi))
    assert np.any(np.asarray(indices.lo != indices.hi))  # some orders change over the box
    # argmax is exact where one entry is above the others over the box
    apart = Interval(jnp.asarray([[0.0, 2.0, 1.0]], dtype), jnp.asarray([[0.5, 3.0, 1.9]], dtype))
    exact = iv.arg_extremum(apart, "argmax", 1, jnp.int32)
    assert int(exact.lo[0]) == int(exact.hi[0]) == 1
    ends = [-np.inf, -1.0, 0.0, np.inf, np.nan]
    lo, hi = np.meshgrid(ends, ends)
    finite = iv.is_finite(Interval(jnp.asarray(lo, dtype), jnp.asarray(hi, dtype)))
    both = np.isfinite(lo) & np.isfinite(hi)
    np.testing.assert_array_equal(finite.lo, both)  # certainly finite
    one_infinity = (lo == hi) & np.isinf(lo)
    np.testing.assert_array_equal(finite.hi, ~one_infinity)  # possibly finite


def _sampled_within(fn, center, shape=None, seed=13):
    """The remainder bound of fn at center (P = 0.04 I) and sampled remainders (JAX's J(c),
    the filter's)."""
    center = jnp.asarray(center)
    shape = 0.04 * jnp.eye(center.shape[0]) if shape is None else shape
    alpha = np.asarray(jax.jit(lambda c, P: remainder_bound(fn, c, P))(center, shape))
    return alpha, _sampled_remainders(fn, center, shape, np.random.default_rng(seed), 4000)


@pytest.mark.parametrize(
    "fn",
    [
        lambda x: jax.lax.stop_gradient(x) ** 2,
        lambda x: jax.lax.stop_gradient(x) + x,
        lambda x: jax.nn.logsumexp(x)[None],
        jax.nn.softmax,
        lambda x: jnp.where(jnp.isfinite(x), jnp.sin(x), 0.0),
    ],
    ids=["stop_gradient_squared", "stop_gradient_plus_x", "logsumexp", "softmax", "is_finite"],
)
def test_remainder_bound_holds_across_stop_gradient(fn):
    """stop_gradient is the identity for values, but JAX differentiates it as a constant: the
    bound is of the function's values (stop_gradient removed) plus what JAX's J(c), the
    filter's, differs from their Jacobian by. stop_gradient(x)^2 has JAX Hessian and Jacobian
    0, and a remainder x^2 (sampled up to 0.5 here); logsumexp, softmax (stop_gradient, is_finite
    inside) and jnp.isfinite raised NotImplementedError."""
    alpha, sampled = _sampled_within(fn, [0.3, 0.5])
    assert np.all(np.isfinite(alpha)) and np.all(sampled <= alpha)
    assert np.all(np.max(sampled, axis=0) > 1e-3 * alpha)


@pytest.mark.parametrize(
    "fn, center, finite",
    [
        (lambda x: jax.lax.cummax(x), [0.3, 0.5], True),
        (lambda x: jax.lax.cummin(jnp.sin(x), reverse=True), [0.3, 0.5], True),
        (lambda x: jnp.cumprod(x + 1.0), [0.3, 0.5], True),
        (lambda x: jnp.sort(x) * x, [0.3, 0.5], True),
        (lambda x: jnp.sort(x) * x, [0.3, 1.5], True),
        (lambda x: x[jnp.argmax(x)][None] ** 2, [0.3, 1.5], True),
        (lambda x: x[jnp.argmin(x)][None] ** 2, [0.3, 0.5], False),
        (lambda x: jnp.argsort(x).astype(x.dtype), [0.3, 0.5], False),
        (lambda x: jnp.piecewise(x, [x < 0.4, x >= 0.4], [jnp.square, lambda v: v]),
         [0.3, 0.5], False),
        (lambda x: jnp.piecewise(x, [x < 0.4, x >= 0.4], [jnp.square, lambda v: v]),
         [0.0, 1.0], True),
    ],
    ids=["cummax", "cummin", "cumprod", "sort_crossing", "sort_apart", "argmax_apart",
         "argmin_tie", "argsort_jump", "piecewise_across", "piecewise_away"],
)  # fmt: skip
def test_remainder_bound_of_order_statistics(fn, center, finite):
    """cummax and cummin switch between entries where two may be the running extremum: a kink
    (the bound was 0 for cummax over x_1 in [0.1, 0.5], x_2 in [0.3, 0.7], where the sampled
    remainder reaches 0.2); sort's order may change (a kink), argsort's and argmax's indices
    jump (NaN, flagged); where the order is fixed over the set the bound is finite. They, and
    jnp.piecewise (argmax, an integer cumsum), raised NotImplementedError or ValueError."""
    alpha, sampled = _sampled_within(fn, center)
    if not finite:
        assert np.all(np.isnan(alpha))
        return
    # the sampled remainders of an affine row (cumprod's first) are rounding errors of 1e-16
    assert np.all(np.isfinite(alpha)) and np.all(sampled <= alpha + 1e-15)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_erf_inv_contains_dense_samples_up_to_its_poles(dtype):
    """erf^-1 (jax.scipy.special.erfinv; it raised NotImplementedError): XLA's own is 5e5 ulps
    off near 1 in float64, so each end is checked through erf's enclosure. Boxes reaching
    +-1 are unbounded there, one past it is restricted to [-1, 1], one wholly past it NaN."""
    rng = np.random.default_rng(14)
    near_one = 1 - 10 ** rng.uniform(-12, 0, 100)
    lo, hi = np.sort(np.stack([rng.uniform(-1, 1, 200), np.r_[near_one, -near_one]]), axis=0)
    x = Interval(jnp.asarray(lo, dtype), jnp.asarray(hi, dtype))
    out = jax.jit(iv.erf_inv)(x)
    values = scipy.special.erfinv(_samples(x, rng, 400))
    assert np.all(values >= np.asarray(out.lo)) and np.all(values <= np.asarray(out.hi))
    edges = iv.erf_inv(
        Interval(jnp.asarray([0.5, -2.0, 1.5], dtype), jnp.asarray([1.0, 0.0, 2.0], dtype))
    )
    assert np.isinf(edges.hi[0]) and np.isinf(edges.lo[1]) and float(edges.hi[1]) >= 0.0
    assert np.isnan(edges.lo[2]) and np.isnan(edges.hi[2])
    alpha, sampled = _sampled_within(lambda v: jax.scipy.special.erfinv(0.5 * v), [0.3, -0.5])
    assert np.all(np.isfinite(alpha)) and np.all(sampled <= alpha)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_rem_contains_dense_samples(dtype):
    """lax.rem (fmod; % and jnp.mod build on it) over intervals that hold a multiple of the
    divisor or not, on either side of 0 and across it, by divisors of either sign, exact or
    intervals: every sampled value lies in the enclosure. It raised NotImplementedError."""
    rng = np.random.default_rng(15)
    x = _random_interval(rng, (400,), 7.0, dtype)
    xs = _samples(x, rng, 300).astype(dtype)
    for divisor in (1.0, -0.7, 2 * np.pi):
        out = iv.rem(x, iv.point(jnp.asarray(divisor, dtype)))
        values = np.fmod(xs, dtype(divisor))
        assert np.all(values >= np.asarray(out.lo)) and np.all(values <= np.asarray(out.hi))
        exact = ~np.asarray(iv._rem_wraps(x, iv.point(jnp.asarray(divisor, dtype))))
        assert np.any(exact) and np.any(~exact)  # both cases drawn
        # where no multiple lies inside, the enclosure is the remainders of the ends
        np.testing.assert_array_equal(np.asarray(out.lo)[exact], np.fmod(x.lo, divisor)[exact])
    divisors = Interval(jnp.asarray(rng.uniform(0.5, 1, 400), dtype), jnp.full(400, 1.5, dtype))
    out = iv.rem(x, divisors)
    values = np.fmod(xs, _samples(divisors, rng, 300).astype(dtype))
    assert np.all(values >= np.asarray(out.lo)) and np.all(values <= np.asarray(out.hi))
    by_zero = iv.rem(x, Interval(jnp.asarray(-1.0, dtype), jnp.asarray(1.0, dtype)))
    assert np.all(np.isnan(np.asarray(by_zero.lo)))


@pytest.mark.parametrize(
    "fn, center, finite",
    [
        (lambda x: jnp.mod(x**2 + jnp.pi, 2 * jnp.pi) - jnp.pi, [0.3, 2.0], True),
        (lambda x: jnp.mod(x**2 + jnp.pi, 2 * jnp.pi) - jnp.pi, [0.3, 1.75], False),
        (lambda x: jnp.sin(x) % 1.0 + x**2, [0.3, 0.6], True),
        (lambda x: x // 1.0 + x, [0.3, 0.6], True),
        (lambda x: x // 1.0 + x, [0.3, 0.9], False),
    ],
    ids=["wrap_away", "wrap_across", "percent", "floor_divide_away", "floor_divide_across"],
)
def test_remainder_bound_holds_across_rem(fn, center, finite):
    """An angle wrapped into [-pi, pi) (jnp.mod), % and //: a finite bound that holds where no
    multiple of the divisor is in the set, NaN (flagged) where one is, as the value jumps
    there. They raised NotImplementedError ('rem')."""
    alpha, sampled = _sampled_within(fn, center)
    if not finite:
        assert np.all(np.isnan(alpha)) and np.max(sampled) > 0.5
        return
    assert np.all(np.isfinite(alpha)) and np.all(sampled <= alpha)
