"""Interval arithmetic in JAX with outward rounding, and guaranteed Lagrange-remainder bounds.

An :class:`Interval` holds arrays ``lo <= hi`` of one shape. Every operation returns an
interval that contains the exact real result of the operation on every point of its arguments:

- ``+ - * /`` and ``sqrt`` are correctly rounded in IEEE arithmetic, so moving each computed
  endpoint one ulp outward (``jnp.nextafter``) is enough;
- sums of k terms, integer powers and dot products carry up to k roundings: the endpoints move
  outward by k * eps * |value| (:func:`_widen`) and then one more ulp;
- library functions (exp, log, sin, tan, asin, atan, tanh...) are not correctly rounded; XLA's are
  accurate to a few ulps, and their endpoints move outward by ``_LIBM_ULPS`` ulps;
- sinh, cosh, erfc, exp2, log1p and x^y (``pow``, :func:`pow_`) are composed of those rules
  (``_composed``), and so are atanh and acosh;
- floor, ceil, round and clamp are non-decreasing and exact, applied to both endpoints.

A ``lax.scan`` (and a ``fori_loop`` with a fixed trip count, an integrator's substeps) has its
body evaluated over intervals once per step (:func:`_scan`); a ``lax.cond`` / ``lax.switch``
takes the hull of the branches its index may select (:func:`_cond`). A primitive without a rule
raises ``NotImplementedError`` naming it.

:func:`eval_jaxpr` interprets a jaxpr over intervals (constants and literals stay exact), which
gives :func:`hessian_interval`, an enclosure of the Hessian of any ``jax.numpy`` function over a
box, and :func:`remainder_bound`, the bound of the linearisation remainder over an ellipsoid's
bounding box (paper eqs 11 and 20, docs/papers/smf.md).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.extend import core as jex
from jaxtyping import Array, Float

from jaxest._checks import check_callable, check_operands, is_concrete
from jaxest._jaxpr import any_equation, zero_outputs

#: outward widening (in ulps) of library functions that are not correctly rounded
_LIBM_ULPS = 4


class Interval(eqx.Module):
    """The box {x : lo <= x <= hi} (element-wise). Boolean intervals (``lo``: certainly true,
    ``hi``: possibly true) are the result of comparing intervals."""

    lo: Array
    hi: Array

    @property
    def shape(self):
        return self.lo.shape

    @property
    def dtype(self):
        return self.lo.dtype

    def mag(self) -> Array:
        """max |x| over the interval."""
        return jnp.maximum(jnp.abs(self.lo), jnp.abs(self.hi))

    def __add__(self, other):
        return add(self, other)

    def __sub__(self, other):
        return sub(self, other)

    def __mul__(self, other):
        return mul(self, other)

    def __neg__(self):
        return Interval(-self.hi, -self.lo)


def point(x) -> Interval:
    """The degenerate interval [x, x]."""
    x = jnp.asarray(x)
    return Interval(x, x)


def lift(x) -> Interval:
    return x if isinstance(x, Interval) else point(x)


@jax.custom_jvp
def _down(x):
    """The next float below x (one ulp outward); its derivative is taken as 1."""
    return jnp.nextafter(x, jnp.asarray(-jnp.inf, x.dtype))


@jax.custom_jvp
def _up(x):
    """The next float above x (one ulp outward); its derivative is taken as 1."""
    return jnp.nextafter(x, jnp.asarray(jnp.inf, x.dtype))


_down.defjvp(lambda primals, tangents: (_down(*primals), tangents[0]))
_up.defjvp(lambda primals, tangents: (_up(*primals), tangents[0]))


def _eps(x):
    return jnp.finfo(x.dtype).eps


def _widen(lo, hi, roundings) -> Interval:
    """Move the endpoints outward by ``roundings`` relative rounding errors, then one ulp;
    integers (an index computed from a step, ``floor(x).astype(int) - 1``) are exact."""
    if not jnp.issubdtype(jnp.result_type(lo), jnp.inexact):
        return Interval(lo, hi)
    if roundings <= 1:
        return Interval(_down(lo), _up(hi))
    k = roundings * _eps(lo)
    return Interval(_down(lo - k * jnp.abs(lo)), _up(hi + k * jnp.abs(hi)))


def _both(prim, x: Interval, **params) -> Interval:
    """Apply an order-preserving structural primitive (reshape, slice...) to both endpoints."""
    return Interval(prim.bind(x.lo, **params), prim.bind(x.hi, **params))


# ----------------------------------------------------------------------------- arithmetic


def add(a, b) -> Interval:
    a, b = lift(a), lift(b)
    return _widen(a.lo + b.lo, a.hi + b.hi, 1)


def sub(a, b) -> Interval:
    a, b = lift(a), lift(b)
    return _widen(a.lo - b.hi, a.hi - b.lo, 1)


def mul(a, b) -> Interval:
    a, b = lift(a), lift(b)
    pairs = [(a.lo, b.lo), (a.lo, b.hi), (a.hi, b.lo), (a.hi, b.hi)]
    # 0 * inf and 0 * NaN are NaN; the product is 0 there: an exact zero times an unbounded factor,
    # or times a factor whose enclosure failed (a NaN endpoint), is zero, as a Hessian's entries
    # that do not depend on a row whose enclosure failed are (its zero cotangent times the NaN).
    # A NaN endpoint times anything but an exact zero interval stays NaN (the lower and upper
    # products' minimum and maximum take it), and shows in the filter's status.
    zero_times = lambda x, y: ((x == 0) & ~jnp.isfinite(y)) | (~jnp.isfinite(x) & (y == 0))
    products = [jnp.where(zero_times(x, y), 0.0, x * y) for x, y in pairs]
    lo = jnp.minimum(jnp.minimum(products[0], products[1]), jnp.minimum(products[2], products[3]))
    hi = jnp.maximum(jnp.maximum(products[0], products[1]), jnp.maximum(products[2], products[3]))
    return _widen(lo, hi, 1)


def div(a, b) -> Interval:
    a, b = lift(a), lift(b)
    q = [a.lo / b.lo, a.lo / b.hi, a.hi / b.lo, a.hi / b.hi]
    lo = jnp.minimum(jnp.minimum(q[0], q[1]), jnp.minimum(q[2], q[3]))
    hi = jnp.maximum(jnp.maximum(q[0], q[1]), jnp.maximum(q[2], q[3]))
    out = _widen(lo, hi, 1)
    has_zero = (b.lo <= 0) & (b.hi >= 0)
    inf = jnp.asarray(jnp.inf, out.dtype)
    return Interval(jnp.where(has_zero, -inf, out.lo), jnp.where(has_zero, inf, out.hi))


def integer_pow(x: Interval, y: int) -> Interval:
    if y == 0:
        return point(jnp.ones_like(x.lo))
    if y < 0:
        return div(point(jnp.ones_like(x.lo)), integer_pow(x, -y))
    if y % 2:  # odd powers are increasing
        return _widen(x.lo**y, x.hi**y, y)
    mig = jnp.where((x.lo <= 0) & (x.hi >= 0), 0.0, jnp.minimum(jnp.abs(x.lo), jnp.abs(x.hi)))
    return _widen(mig**y, x.mag() ** y, y)


def _increasing(fn, x: Interval, roundings=_LIBM_ULPS) -> Interval:
    return _widen(fn(x.lo), fn(x.hi), roundings)


def sqrt(x: Interval) -> Interval:
    out = _widen(jnp.sqrt(jnp.maximum(x.lo, 0.0)), jnp.sqrt(x.hi), 1)
    return Interval(jnp.maximum(out.lo, 0.0), out.hi)


def log(x: Interval) -> Interval:
    return _increasing(jnp.log, Interval(jnp.maximum(x.lo, 0.0), x.hi))


def _unit_domain(x: Interval) -> Interval:
    """x restricted to [-1, 1], the domain of asin and acos (an x wholly outside it gives NaN)."""
    return Interval(jnp.maximum(x.lo, -1.0), jnp.minimum(x.hi, 1.0))


def asin(x: Interval) -> Interval:
    return _increasing(jnp.arcsin, _unit_domain(x))


def acos(x: Interval) -> Interval:
    """Decreasing: each end of the result comes from the other end of x."""
    x = _unit_domain(x)
    return _widen(jnp.arccos(x.hi), jnp.arccos(x.lo), _LIBM_ULPS)


def erf_inv(y: Interval) -> Interval:
    """The inverse of erf over y restricted to [-1, 1] (+-inf at +-1; a y wholly outside it
    gives NaN), increasing. XLA's was measured 5e5 ulps off near 1 in float64, so it only
    proposes each end: XLA's value moved outward by 4^k eps |x| (k = 1..13, then a smallest
    normal) is taken for the lower end x_lo where erf's enclosure at x_lo lies at or below
    y_lo, the least moved that does (erf increasing: x_lo <= erf^-1(y_lo)); none does: -inf.
    The upper end likewise."""
    y = _unit_domain(lift(y))
    erf = _unary_increasing["erf"]
    steps = 4.0 ** jnp.arange(1, 14, dtype=y.dtype)

    def end(v, outward):  # outward: -1 for the lower end, +1 for the upper
        x = jax.scipy.special.erfinv(v)[..., None]
        tiny = jnp.finfo(y.dtype).tiny
        candidates = x + outward * (steps * _eps(y.lo) * jnp.abs(x) + tiny)
        at = _increasing(erf, Interval(candidates, candidates))
        holds = at.hi <= v[..., None] if outward < 0 else at.lo >= v[..., None]
        chosen = jnp.take_along_axis(candidates, jnp.argmax(holds, -1)[..., None], -1)[..., 0]
        bound = jnp.where(jnp.any(holds, -1), chosen, outward * jnp.inf)
        return jnp.where(jnp.isnan(x[..., 0]), jnp.nan, bound)

    empty = y.lo > y.hi  # wholly outside [-1, 1]
    return Interval(
        jnp.where(empty, jnp.nan, end(y.lo, -1)), jnp.where(empty, jnp.nan, end(y.hi, 1))
    )


def _half(x: Interval) -> Interval:
    return Interval(0.5 * x.lo, 0.5 * x.hi)  # exact in binary floating point, but on underflow


def atanh(x: Interval) -> Interval:
    """(log(1 + x) - log(1 - x)) / 2 over x restricted to [-1, 1] (+-inf at +-1; an x wholly
    outside it gives NaN): tight, as both terms increase with x. Composed, as XLA's own atanh
    was measured 127 ulps off in float64."""
    x, one = _unit_domain(x), point(jnp.ones_like(x.lo))
    return _half(sub(log(add(one, x)), log(sub(one, x))))


def acosh(x: Interval) -> Interval:
    """log(x + sqrt((x - 1)(x + 1))) over x restricted to [1, inf) (an x wholly below 1 gives
    NaN): tight, as every term increases with x there. Composed, as atanh is."""
    x = Interval(jnp.maximum(x.lo, 1.0), jnp.where(x.hi < 1, jnp.nan, x.hi))
    one = point(jnp.ones_like(x.lo))
    return log(add(x, sqrt(mul(sub(x, one), add(x, one)))))


def abs_(x: Interval) -> Interval:
    straddles = (x.lo <= 0) & (x.hi >= 0)
    mig = jnp.where(straddles, 0.0, jnp.minimum(jnp.abs(x.lo), jnp.abs(x.hi)))
    return Interval(mig, x.mag())


def is_finite(x: Interval) -> Interval:
    """Certainly finite where both ends are; possibly finite but where the interval is the one
    point +inf or -inf. A NaN end (a failed enclosure) leaves it open: [False, True]."""
    possible = ~((x.lo == x.hi) & jnp.isinf(x.lo))
    return Interval(jnp.isfinite(x.lo) & jnp.isfinite(x.hi), possible)


def _clip_unit(out: Interval) -> Interval:
    return Interval(jnp.maximum(out.lo, -1.0), jnp.minimum(out.hi, 1.0))


def _contains_point(x: Interval, offset, period):
    """Whether some offset + j * period (j integer) lies in x (conservatively: widened by 1e-12)."""
    slack = 1e-12 * (1.0 + x.mag()) if x.dtype == jnp.float64 else 1e-5 * (1.0 + x.mag())
    j = jnp.ceil((x.lo - slack - offset) / period)
    return offset + j * period <= x.hi + slack


def sin(x: Interval) -> Interval:
    two_pi = 2 * math.pi
    ends = _widen(
        jnp.minimum(jnp.sin(x.lo), jnp.sin(x.hi)),
        jnp.maximum(jnp.sin(x.lo), jnp.sin(x.hi)),
        _LIBM_ULPS,
    )
    wide = x.hi - x.lo >= two_pi
    hi = jnp.where(wide | _contains_point(x, math.pi / 2, two_pi), 1.0, ends.hi)
    lo = jnp.where(wide | _contains_point(x, -math.pi / 2, two_pi), -1.0, ends.lo)
    return _clip_unit(Interval(lo, hi))


def cos(x: Interval) -> Interval:
    two_pi = 2 * math.pi
    ends = _widen(
        jnp.minimum(jnp.cos(x.lo), jnp.cos(x.hi)),
        jnp.maximum(jnp.cos(x.lo), jnp.cos(x.hi)),
        _LIBM_ULPS,
    )
    wide = x.hi - x.lo >= two_pi
    hi = jnp.where(wide | _contains_point(x, 0.0, two_pi), 1.0, ends.hi)
    lo = jnp.where(wide | _contains_point(x, math.pi, two_pi), -1.0, ends.lo)
    return _clip_unit(Interval(lo, hi))


def tan(x: Interval) -> Interval:
    out = _increasing(jnp.tan, x)
    pole = (x.hi - x.lo >= math.pi) | _contains_point(x, math.pi / 2, math.pi)
    inf = jnp.asarray(jnp.inf, out.dtype)
    return Interval(jnp.where(pole, -inf, out.lo), jnp.where(pole, inf, out.hi))


def atan2(y: Interval, x: Interval) -> Interval:
    """The angle of the box y x x: attained at its corners unless the box touches the origin or
    the branch cut (the negative x axis), where it is [-pi, pi]."""
    y, x = lift(y), lift(x)
    corners = [jnp.arctan2(yy, xx) for yy in (y.lo, y.hi) for xx in (x.lo, x.hi)]
    out = _widen(
        jnp.min(jnp.stack(corners), axis=0), jnp.max(jnp.stack(corners), axis=0), _LIBM_ULPS
    )
    cut = (x.lo <= 0) & (y.lo <= 0) & (y.hi >= 0)
    pi = jnp.asarray(math.pi, out.dtype)
    return Interval(jnp.where(cut, -_up(pi), out.lo), jnp.where(cut, _up(pi), out.hi))


def rem(x, y) -> Interval:
    """``lax.rem`` (C's fmod, ``%`` and ``jnp.mod`` build on it): x - y trunc(x / y), exact in
    floating point, of x's sign and below |y| in size. For a divisor known exactly (an angle
    wrapped by 2 pi) it increases with x between the nonzero multiples of y, where it drops by
    |y|: applied to both ends where x's interval holds none (:func:`_rem_wraps`); else, and for
    a divisor that is an interval, every value of x's sign below the largest |y|. A divisor
    that may be 0 gives NaN (flagged)."""
    x, y = lift(x), lift(y)
    at_ends = Interval(lax.rem(x.lo, y.lo), lax.rem(x.hi, y.lo))
    size = y.mag()
    below = Interval(jnp.where(x.lo >= 0, 0, -size), jnp.where(x.hi <= 0, 0, size))
    wraps = _rem_wraps(x, y)
    out = Interval(jnp.where(wraps, below.lo, at_ends.lo), jnp.where(wraps, below.hi, at_ends.hi))
    if not jnp.issubdtype(out.dtype, jnp.inexact):
        return out
    zero = (y.lo <= 0) & (y.hi >= 0)
    return Interval(jnp.where(zero, jnp.nan, out.lo), jnp.where(zero, jnp.nan, out.hi))


def _rem_wraps(x: Interval, y: Interval):
    """Whether rem(., y) may drop over x's interval: y not one value, or x's interval holding a
    nonzero multiple of it, where the ends' remainders are out of order or the interval is as
    wide as |y| (its width rounded up; narrower, it holds at most one multiple, past which the
    upper end's remainder is the lower's minus |y| plus the width)."""
    out_of_order = lax.rem(x.lo, y.lo) > lax.rem(x.hi, y.lo)
    return (y.lo != y.hi) | out_of_order | (_up(x.hi - x.lo) >= jnp.abs(y.lo))


def max_(a, b) -> Interval:
    a, b = lift(a), lift(b)
    return Interval(jnp.maximum(a.lo, b.lo), jnp.maximum(a.hi, b.hi))


def clamp(low, x, high) -> Interval:
    """``lax.clamp``: min(max(x, low), high), non-decreasing in each argument."""
    low, x, high = lift(low), lift(x), lift(high)
    return Interval(lax.clamp(low.lo, x.lo, high.lo), lax.clamp(low.hi, x.hi, high.hi))


def min_(a, b) -> Interval:
    a, b = lift(a), lift(b)
    return Interval(jnp.minimum(a.lo, b.lo), jnp.minimum(a.hi, b.hi))


def _widen_sum(lo, hi, magnitude, terms) -> Interval:
    """Endpoints of a floating-point sum of ``terms`` terms moved outward by the bound
    terms * eps * sum|x_i| of its rounding error (relative to sum|x_i|, not |sum x_i|: a
    cancelling sum has an error far larger than eps |sum|), then one ulp; integers (a running
    count, ``jnp.piecewise``'s) are exact."""
    if not jnp.issubdtype(jnp.result_type(lo), jnp.inexact):
        return Interval(lo, hi)
    slack = terms * _eps(lo) * magnitude
    return Interval(_down(lo - slack), _up(hi + slack))


def reduce_sum(x: Interval, axes) -> Interval:
    terms = math.prod(x.shape[a] for a in axes)
    magnitude = jnp.sum(jnp.maximum(jnp.abs(x.lo), jnp.abs(x.hi)), axis=axes)
    return _widen_sum(jnp.sum(x.lo, axis=axes), jnp.sum(x.hi, axis=axes), magnitude, terms)


def cumsum(x: Interval, axis: int, reverse: bool) -> Interval:
    """Running sums along ``axis``: the k-th of k terms, widened as :func:`reduce_sum` widens a
    sum of that many (all of ``axis``'s length, the most any of them has)."""
    running = lambda v: lax.cumsum(v, axis=axis, reverse=reverse)
    magnitude = running(jnp.maximum(jnp.abs(x.lo), jnp.abs(x.hi)))
    return _widen_sum(running(x.lo), running(x.hi), magnitude, x.shape[axis])


def cumprod(x: Interval, axis: int, reverse: bool) -> Interval:
    """Running products along ``axis``: interval products (:func:`mul`, each rounded outward) of
    the running product and the next term, in the tree ``lax.associative_scan`` takes (any
    grouping of exact interval products holds the product of the sets)."""
    return lax.associative_scan(mul, x, reverse=reverse, axis=axis)


def cumulative_extremum(x: Interval, name: str, axis: int, reverse: bool) -> Interval:
    """``cummax`` / ``cummin``: non-decreasing in every entry, so applied to both ends (exact)."""
    running = {"cummax": lax.cummax, "cummin": lax.cummin}[name]
    return Interval(
        running(x.lo, axis=axis, reverse=reverse), running(x.hi, axis=axis, reverse=reverse)
    )


def _last_axis_pairs(x: Interval, axis: int):
    """``(a_lo, a_hi, b_lo, b_hi)``: x's entries along ``axis`` moved last and paired, a the
    ``[..., i, None]`` and b the ``[..., None, j]`` entries."""
    lo, hi = jnp.moveaxis(x.lo, axis, -1), jnp.moveaxis(x.hi, axis, -1)
    return lo[..., :, None], hi[..., :, None], lo[..., None, :], hi[..., None, :]


def sort(operands, dimension: int, is_stable: bool, num_keys: int) -> list:
    """``lax.sort`` of one key along ``dimension``, with payloads (``jnp.argsort``'s indices, a
    derivative's permutation): the k-th smallest of the key's intervals lies in [k-th smallest
    lower end, k-th smallest upper end] (each order statistic is non-decreasing in every entry).
    A payload follows the order of the lower ends where no two of the key's intervals along
    ``dimension`` meet (the order is then the same over the box); in a slice where two may,
    any entry may come to any place, and each payload's result is the hull of its slice. A key
    interval with a NaN end (a failed enclosure) makes its slice NaN."""
    if num_keys != 1:
        raise NotImplementedError("interval evaluation: sort with more than one key")
    key, payloads = lift(operands[0]), [lift(v) for v in operands[1:]]
    bind = lambda *vs: lax.sort_p.bind(*vs, dimension=dimension, is_stable=is_stable, num_keys=1)
    order = lax.broadcasted_iota(jnp.int32, key.shape, dimension)
    (lo,), (hi,), (_, perm) = bind(key.lo), bind(key.hi), bind(key.lo, order)
    a_lo, a_hi, b_lo, b_hi = _last_axis_pairs(key, dimension)
    distinct = ~jnp.eye(key.shape[dimension], dtype=bool)
    meet = jnp.any(distinct & (a_lo <= b_hi) & (b_lo <= a_hi), axis=(-2, -1))
    nan = jnp.any(jnp.isnan(key.lo) | jnp.isnan(key.hi), axis=dimension)
    meet, nan = jnp.expand_dims(meet, dimension), jnp.expand_dims(nan, dimension)
    out = [Interval(jnp.where(nan, jnp.nan, lo), jnp.where(nan, jnp.nan, hi))]
    for p in payloads:
        take = lambda v: jnp.take_along_axis(v, perm, axis=dimension)
        hull_lo = jnp.min(p.lo, axis=dimension, keepdims=True)
        hull_hi = jnp.max(p.hi, axis=dimension, keepdims=True)
        out.append(
            Interval(jnp.where(meet, hull_lo, take(p.lo)), jnp.where(meet, hull_hi, take(p.hi)))
        )
    return out


def arg_extremum(x: Interval, name: str, axis: int, index_dtype) -> Interval:
    """``argmax`` / ``argmin`` along ``axis``: the integer interval from the first to the last
    index whose entry may be the largest (smallest), the first of those tied: an entry whose
    interval reaches the largest lower end and passes every lower end before it. A NaN end (a
    failed enclosure, or a NaN, which ``argmax`` takes) may be any."""
    x = x if name == "argmax" else -x
    lo, hi = jnp.moveaxis(x.lo, axis, -1), jnp.moveaxis(x.hi, axis, -1)
    top = jnp.max(lo, axis=-1, keepdims=True)
    before = lax.cummax(
        jnp.concatenate([jnp.full_like(lo[..., :1], _extremes(lo.dtype)[1]), lo[..., :-1]], -1),
        axis=lo.ndim - 1,
    )
    nan = jnp.any(jnp.isnan(lo) | jnp.isnan(hi), axis=-1, keepdims=True)
    may = ((hi >= top) & (hi > before)) | nan
    first = jnp.argmax(may, axis=-1)
    last = lo.shape[-1] - 1 - jnp.argmax(may[..., ::-1], axis=-1)
    return Interval(first.astype(index_dtype), last.astype(index_dtype))


def _at_uncertain_index(primitive, x, indices, params) -> Interval:
    """``gather`` / ``dynamic_slice`` with an integer index known as an interval (an
    ``argmax`` 's, a ``sort`` 's permutation): exact where every index is one value; else
    anything in x may be picked, so its hull (with what the end indices pick: a fill value out
    of bounds)."""
    x = lift(x)
    ends = [[i.lo if isinstance(i, Interval) else i for i in indices],
            [i.hi if isinstance(i, Interval) else i for i in indices]]  # fmt: skip
    at = [[primitive.bind(v, *e, **params) for e in ends] for v in (x.lo, x.hi)]
    exact = jnp.all(
        jnp.asarray([jnp.all(i.lo == i.hi) for i in indices if isinstance(i, Interval)])
    )
    lo = jnp.minimum(jnp.min(x.lo), jnp.minimum(*at[0]))
    hi = jnp.maximum(jnp.max(x.hi), jnp.maximum(*at[1]))
    return Interval(jnp.where(exact, at[0][0], lo), jnp.where(exact, at[1][0], hi))


def _scatter(primitive, operand, indices, updates, **params) -> Interval:
    """``scatter-add`` (the transpose of a gather, in a derivative) and ``scatter``: with exact
    indices, applied to both ends (the sum widened as :func:`_widen_sum` widens one of every
    update and the operand); with indices known as an interval (an ``argmax`` 's, a ``sort`` 's
    permutation) that may hold more than one value, any update may land anywhere: an entry is
    the operand's plus any of the updates' negative to positive parts (``scatter``: the hull
    of the operand and every update)."""
    operand, updates = lift(operand), lift(updates)
    at = indices.lo if isinstance(indices, Interval) else indices
    bind = lambda a, b: primitive.bind(a, at, b, **params)
    magnitude = lambda x: jnp.maximum(jnp.abs(x.lo), jnp.abs(x.hi))
    adds = primitive.name != "scatter"
    if adds:
        exact = _widen_sum(
            bind(operand.lo, updates.lo), bind(operand.hi, updates.hi),
            bind(magnitude(operand), magnitude(updates)), updates.lo.size + 1,
        )  # fmt: skip
    else:
        exact = Interval(bind(operand.lo, updates.lo), bind(operand.hi, updates.hi))
    if not isinstance(indices, Interval):
        return exact
    if adds:
        anywhere = _widen_sum(
            operand.lo + jnp.sum(jnp.minimum(updates.lo, 0)),
            operand.hi + jnp.sum(jnp.maximum(updates.hi, 0)),
            magnitude(operand) + jnp.sum(magnitude(updates)), updates.lo.size + 1,
        )  # fmt: skip
    else:
        anywhere = Interval(jnp.minimum(operand.lo, jnp.min(updates.lo)),
                            jnp.maximum(operand.hi, jnp.max(updates.hi)))  # fmt: skip
    one = jnp.all(indices.lo == indices.hi)
    return Interval(jnp.where(one, exact.lo, anywhere.lo), jnp.where(one, exact.hi, anywhere.hi))


def dot_general(a, b, **params) -> Interval:
    """Midpoint-radius product (Rump): [ma +- ra] . [mb +- rb] is inside
    ma.mb +- (|ma|.rb + ra.|mb| + ra.rb), exact in the radius when one factor is a point."""
    a, b = lift(a), lift(b)
    mid_a, rad_a = _midrad(a)
    mid_b, rad_b = _midrad(b)
    dot = lambda u, v: lax.dot_general(u, v, **params)
    center = dot(mid_a, mid_b)
    radius = dot(jnp.abs(mid_a), rad_b) + dot(rad_a, jnp.abs(mid_b) + rad_b)
    contracted = math.prod(a.shape[i] for i in params["dimension_numbers"][0][0]) + 2
    # rounding of the centre product and of the radius products, each <= contracted * eps * |.|
    slack = contracted * _eps(center) * (dot(jnp.abs(mid_a), jnp.abs(mid_b)) + 2 * radius)
    return _widen(center - radius - slack, center + radius + slack, 1)


def _midrad(x: Interval):
    mid = 0.5 * x.lo + 0.5 * x.hi
    rad = _up(jnp.maximum(x.hi - mid, mid - x.lo))
    return mid, rad


# ----------------------------------------------------------------------------- booleans


def _compare(a, b, name) -> Interval:
    if a is b and isinstance(a, Interval) and name in ("eq", "ne"):
        # x == x for one variable (jnp.isnan's x != x): certain unless x may be NaN
        nan = jnp.isnan(a.lo) | jnp.isnan(a.hi)
        return Interval(~nan, ~nan) if name == "eq" else Interval(nan, nan)
    a, b = lift(a), lift(b)
    # a NaN end (a failed enclosure) may hide any value: the comparison may go either way
    unknown = jnp.isnan(a.lo) | jnp.isnan(a.hi) | jnp.isnan(b.lo) | jnp.isnan(b.hi)
    if name in ("lt", "le"):
        strict = name == "lt"
        certain = a.hi < b.lo if strict else a.hi <= b.lo
        possible = a.lo < b.hi if strict else a.lo <= b.hi
        return Interval(certain, possible | unknown)
    if name in ("gt", "ge"):
        return _compare(b, a, "lt" if name == "gt" else "le")
    overlap = (a.lo <= b.hi) & (b.lo <= a.hi) | unknown
    exact = (a.lo == a.hi) & (b.lo == b.hi) & (a.lo == b.lo)
    if name == "eq":
        return Interval(exact, overlap)
    return Interval(~overlap, ~exact)  # ne


def _extremes(dtype) -> tuple:
    """The largest and the smallest value of ``dtype`` (floats: the infinities)."""
    if jnp.issubdtype(dtype, jnp.inexact):
        return jnp.inf, -jnp.inf
    if dtype == jnp.bool_:
        return True, False
    return jnp.iinfo(dtype).max, jnp.iinfo(dtype).min


def select_n(pred, *cases) -> Interval | Array:
    if not isinstance(pred, Interval):
        if not any(isinstance(c, Interval) for c in cases):
            return lax.select_n(pred, *cases)
        cases = [lift(c) for c in cases]
        return Interval(
            lax.select_n(pred, *[c.lo for c in cases]), lax.select_n(pred, *[c.hi for c in cases])
        )
    cases = [lift(c) for c in cases]
    first, last = pred.lo.astype(jnp.int32), pred.hi.astype(jnp.int32)
    largest, smallest = _extremes(cases[0].dtype)  # the empty hull's ends
    lo = jnp.full(cases[0].shape, largest, cases[0].dtype)
    hi = jnp.full(cases[0].shape, smallest, cases[0].dtype)
    for i, c in enumerate(cases):
        take = (first <= i) & (i <= last)
        lo = jnp.where(take, jnp.minimum(lo, c.lo), lo)
        hi = jnp.where(take, jnp.maximum(hi, c.hi), hi)
    return Interval(lo, hi)


# ----------------------------------------------------------------------------- interpreter

_unary_increasing = {
    "exp": jnp.exp,
    "expm1": jnp.expm1,
    "tanh": jnp.tanh,
    "atan": jnp.arctan,
    "asinh": jnp.arcsinh,
    "cbrt": jnp.cbrt,
    "logistic": jax.nn.sigmoid,
    "erf": jax.scipy.special.erf,
}


def _exp(x) -> Interval:
    return _increasing(jnp.exp, lift(x))


def _ln2(dtype) -> Interval:
    """An interval around ln 2 in ``dtype`` (its rounded value one ulp either way)."""
    ln2 = jnp.asarray(math.log(2.0), dtype)
    return Interval(_down(ln2), _up(ln2))


def pow_(x, y) -> Interval:
    """x^y. ``x ** 3.0`` traces as ``pow``, not ``integer_pow``: an exponent known when tracing
    takes :func:`integer_pow`'s rule where its value is an integer, which holds for x < 0 as
    JAX's x^y does; elsewhere x^y = e^(y log x), which encloses x^y where x >= 0 (JAX's x^y is
    NaN at x < 0 and a non-integer y). An exponent known only when running (traced) gives NaN
    where the box reaches x < 0: its value may be an integer, so the enclosure fails, and the
    filter's status says so (it had dropped x < 0, a set without the truth, with status OK)."""
    x = lift(x)
    positive = _exp(mul(y, log(x)))
    if isinstance(y, Interval) or not is_concrete(y):
        negative = x.lo < 0
        return Interval(jnp.where(negative, jnp.nan, positive.lo),
                        jnp.where(negative, jnp.nan, positive.hi))  # fmt: skip
    exponents = np.asarray(y)
    out = positive
    for value in np.unique(exponents[np.mod(exponents, 1) == 0]):
        integer = integer_pow(x, int(value))
        at = exponents == value
        out = Interval(jnp.where(at, integer.lo, out.lo), jnp.where(at, integer.hi, out.hi))
    return out


# functions composed of the rules above, so their enclosures are guaranteed as those are (no
# assumption on XLA's own sinh, cosh, erfc, exp2, log1p or pow): sinh = (e^x - e^-x) / 2 is
# tight, as both terms increase with x; cosh = (e^|x| + e^-|x|) / 2 bounds its two terms apart,
# so it can be wider than cosh's range; erfc = 1 - erf; 2^x = e^(x ln 2) and log1p x = log(1 + x)
# (XLA's own were measured 113 and 10 ulps off, past _LIBM_ULPS); x^y: pow_
_composed = {
    "sinh": lambda x: _half(sub(_exp(x), _exp(-lift(x)))),
    "cosh": lambda x: _half(add(_exp(abs_(lift(x))), _exp(-abs_(lift(x))))),
    "erfc": lambda x: sub(
        point(jnp.ones_like(lift(x).lo)), _increasing(_unary_increasing["erf"], lift(x))
    ),
    "exp2": lambda x: _exp(mul(lift(x), _ln2(lift(x).dtype))),
    "log1p": lambda x: log(add(point(jnp.ones_like(lift(x).lo)), x)),
    "pow": pow_,
}

#: rounding to integers: non-decreasing and exact in floating point, so applied to both ends
_ROUNDING = {"floor": lax.floor_p, "ceil": lax.ceil_p, "round": lax.round_p}

_structural = {
    "reshape", "broadcast_in_dim", "transpose", "squeeze", "expand_dims", "slice", "rev",
    "dynamic_slice", "gather", "reduce_max", "reduce_min", "copy", "copy_p", "tile",
}  # fmt: skip


def _rule(name: str) -> Callable | None:
    simple = {
        "add": add, "add_any": add, "sub": sub, "mul": mul, "div": div, "sqrt": sqrt,
        "log": log, "abs": abs_, "sin": sin, "cos": cos, "tan": tan, "atan2": atan2,
        "asin": asin, "acos": acos, "atanh": atanh, "acosh": acosh, "erf_inv": erf_inv,
        "max": max_, "min": min_, "clamp": clamp, "select_n": select_n, "rem": rem,
        "neg": lambda x: -lift(x),
        "square": lambda x: integer_pow(lift(x), 2),
        "sign": lambda x: Interval(jnp.sign(x.lo), jnp.sign(x.hi)),
        "rsqrt": lambda x: div(point(jnp.ones_like(x.lo)), sqrt(x)),
        "not": lambda x: Interval(~x.hi, ~x.lo),
        "is_finite": is_finite,
        # its value (remainder_bound differentiates fn without it: with_pairwise_extrema)
        "stop_gradient": lambda x: x,
        "and": lambda a, b: Interval(lift(a).lo & lift(b).lo, lift(a).hi & lift(b).hi),
        "or": lambda a, b: Interval(lift(a).lo | lift(b).lo, lift(a).hi | lift(b).hi),
    }  # fmt: skip
    if name in simple:
        return simple[name]
    if name in ("eq", "ne", "lt", "le", "gt", "ge"):
        return lambda a, b: _compare(a, b, name)
    if name in _composed:
        return _composed[name]
    if name in _unary_increasing:
        fn = _unary_increasing[name]
        return lambda x: _increasing(fn, x)
    return None


#: the non-smooth primitives :func:`_kink` knows, and what switching branch does: "kink" where
#: the value stays continuous (the first derivative jumps), "jump" where it need not; and
#: ``convert_element_type`` to or from integers or booleans (:func:`_is_discrete_cast`)
_NON_SMOOTH = {
    "abs": "kink", "max": "kink", "min": "kink", "clamp": "kink", "reduce_max": "kink",
    "reduce_min": "kink",
    "sign": "jump", "select_n": "jump", "atan2": "jump", "floor": "jump", "ceil": "jump",
    "round": "jump", "cummax": "kink", "cummin": "kink", "sort": "kink", "argmax": "jump",
    "argmin": "jump", "rem": "jump",
}  # fmt: skip


def _is_discrete_cast(from_dtype, to_dtype) -> bool:
    """Whether a ``convert_element_type`` is to or from integers or booleans: a step. Truncating
    x to an integer, or a comparison's result turned into a number (``(x > 0).astype(float)``),
    changes value in jumps, and JAX differentiates it as a constant (a zero derivative), so
    neither the Taylor nor the mean-value bound sees it."""
    floating = lambda dtype: jnp.issubdtype(dtype, jnp.inexact)
    return not (floating(from_dtype) and floating(to_dtype))


def _makes_a_step(cast_eqn) -> bool:
    """Whether a ``convert_element_type`` equation may start a step: a float truncated to
    integers or booleans, or a comparison's result made a number. A cast from integers is left
    out: its integer is exact (a step index ``k``) or comes from one of those casts, so counting
    it would only evaluate the primal over intervals for nothing."""
    source = cast_eqn.invars[0].aval.dtype
    from_integers = jnp.issubdtype(source, jnp.integer)
    return not from_integers and _is_discrete_cast(source, cast_eqn.params["new_dtype"])


def _kink(name: str, params, invals) -> tuple[str, Array] | None:
    """For a primitive of :data:`_NON_SMOOTH` or a discrete cast, ``(kind, flag)``: ``flag``
    whether it may switch branch (a cast: change value) inside its arguments' intervals (a
    scalar boolean); ``None`` otherwise (or where the argument that decides the branch is
    exact)."""
    if name == "convert_element_type":
        x = invals[0]
        if not (isinstance(x, Interval) and _is_discrete_cast(x.dtype, params["new_dtype"])):
            return None
        cast = lambda v: lax.convert_element_type(v, params["new_dtype"])
        return "jump", jnp.any(cast(x.lo) != cast(x.hi))
    if name not in _NON_SMOOTH:
        return None
    if name in ("max", "min"):
        return _NON_SMOOTH[name], jnp.any(_may_cross(invals[0], invals[1]))
    if name == "clamp":
        low, x, high = invals
        return _NON_SMOOTH[name], jnp.any(_may_cross(x, low) | _may_cross(x, high))
    if name == "rem":  # where it wraps
        return _NON_SMOOTH[name], jnp.any(_rem_wraps(lift(invals[0]), lift(invals[1])))
    if name == "atan2":  # pi on the negative x axis, near -pi just below it; undefined at 0
        y, x = lift(invals[0]), lift(invals[1])
        across_the_cut = (x.lo < 0) & (y.lo < 0) & (y.hi >= 0)
        at_the_origin = (x.lo <= 0) & (x.hi >= 0) & (y.lo <= 0) & (y.hi >= 0)
        return _NON_SMOOTH[name], jnp.any(across_the_cut | at_the_origin)
    x = invals[0]
    if not isinstance(x, Interval):
        return None
    if name == "select_n":
        return _NON_SMOOTH[name], jnp.any(x.lo != x.hi)
    if name in _ROUNDING:  # a step at every integer (round: every half-integer)
        rounded = _both(_ROUNDING[name], x, **params)
        return _NON_SMOOTH[name], jnp.any(rounded.lo != rounded.hi)
    if name in ("argmax", "argmin"):  # an index that may change
        index = arg_extremum(x, name, params["axes"][0], params["index_dtype"])
        return _NON_SMOOTH[name], jnp.any(index.lo != index.hi)
    if name == "sort":  # the order of two entries that may cross may change (payloads: jump)
        a_lo, a_hi, b_lo, b_hi = _last_axis_pairs(x, params["dimension"])
        cross = _may_cross(Interval(a_lo, a_hi), Interval(b_lo, b_hi))
        kind = "jump" if len(invals) > 1 else "kink"  # argsort's indices jump
        return kind, jnp.any(cross & ~jnp.eye(x.shape[params["dimension"]], dtype=bool))
    if name in ("cummax", "cummin"):  # more than one entry so far may be the extremum
        x = x if name == "cummax" else -x
        a_lo, a_hi, _, _ = _last_axis_pairs(x, params["axis"])
        running_lo = lax.cummax(jnp.moveaxis(x.lo, params["axis"], -1), axis=x.lo.ndim - 1,
                                reverse=params["reverse"])[..., None, :]  # fmt: skip
        n = x.shape[params["axis"]]
        # entry i is among those so far for the running extremum at j: i <= j (reverse: i >= j)
        so_far = (jnp.tril if params["reverse"] else jnp.triu)(jnp.ones((n, n), bool))
        candidates = jnp.sum(so_far & (a_hi >= running_lo), axis=-2)
        return _NON_SMOOTH[name], jnp.any(candidates > 1)
    if name in ("reduce_max", "reduce_min"):
        x, axes = (x if name == "reduce_max" else -x), params["axes"]
        # more than one entry can be the largest: the maximum switches between them
        top = jnp.max(x.lo, axis=axes, keepdims=True)
        return _NON_SMOOTH[name], jnp.any(jnp.sum(x.hi >= top, axis=axes) > 1)
    return _NON_SMOOTH[name], jnp.any((x.lo < 0) & (x.hi > 0))  # abs, sign


def _may_cross(a, b):
    """Whether a - b may change sign over the intervals (where max, min and clamp switch)."""
    a, b = lift(a), lift(b)
    return (a.lo < b.hi) & (b.lo < a.hi)


#: call primitives: their jaxpr is evaluated in place (:func:`_called`)
_CALLS = ("pjit", "jit", "closed_call", "core_call", "remat", "checkpoint")


def _called(params) -> tuple[jex.Jaxpr, list] | None:
    """The jaxpr a call's (or a loop's) parameters hold, and its constants; ``None`` if none."""
    inner = params.get("jaxpr", params.get("call_jaxpr"))
    if inner is None:
        return None
    return getattr(inner, "jaxpr", inner), list(getattr(inner, "consts", []))


def _scan(params, invals, out_avals, kinks) -> list:
    """A ``lax.scan`` (``fori_loop`` with a fixed trip count too: an integrator's substeps) over
    intervals: its body evaluated over intervals ``length`` times in turn, as the loop runs."""
    body, count = params["jaxpr"], params["num_consts"] + params["num_carry"]
    consts, carry = invals[: params["num_consts"]], invals[params["num_consts"] : count]
    at = lambda x, i: Interval(x.lo[i], x.hi[i]) if isinstance(x, Interval) else x[i]
    steps = range(params["length"])
    outputs = []
    for i in reversed(steps) if params["reverse"] else steps:
        out = eval_jaxpr(
            body.jaxpr, body.consts, *consts, *carry, *[at(x, i) for x in invals[count:]],
            kinks=kinks,
        )  # fmt: skip
        carry = out[: params["num_carry"]]
        outputs.append(out[params["num_carry"] :])
    if params["reverse"]:
        outputs.reverse()
    stacked = []
    for j, aval in enumerate(out_avals[params["num_carry"] :]):
        ys = [step[j] for step in outputs]
        if not any(isinstance(y, Interval) for y in ys):
            stacked.append(jnp.stack(ys) if ys else jnp.zeros(aval.shape, aval.dtype))
            continue
        ys = [lift(y) for y in ys]
        stacked.append(Interval(jnp.stack([y.lo for y in ys]), jnp.stack([y.hi for y in ys])))
    return [*carry, *stacked]


def _cond(branches, index, operands, kinks) -> list:
    """``lax.cond`` / ``lax.switch`` over intervals: the hull of the outputs of the branches the
    index may take over its interval, each evaluated over intervals (every branch is evaluated,
    as the index may be known only when running). Where the index may change over the box the
    value may jump, and the cast that made the index (``cond``'s boolean, a float truncated to
    an integer) is a step :func:`_kink` sees."""
    index = lift(index)
    los = his = None
    for k, branch in enumerate(branches):
        outs = [lift(v) for v in eval_jaxpr(branch.jaxpr, branch.consts, *operands, kinks=kinks)]
        taken = (index.lo <= k) & (k <= index.hi)
        lo_k = [jnp.where(taken, out.lo, _extremes(out.dtype)[0]) for out in outs]
        hi_k = [jnp.where(taken, out.hi, _extremes(out.dtype)[1]) for out in outs]
        los = lo_k if los is None else [jnp.minimum(a, b) for a, b in zip(los, lo_k, strict=True)]
        his = hi_k if his is None else [jnp.maximum(a, b) for a, b in zip(his, hi_k, strict=True)]
    return [Interval(lo, hi) for lo, hi in zip(los, his, strict=True)]


def _apply(eqn, invals, kinks=None):
    name = eqn.primitive.name
    params = dict(eqn.params)
    if not any(isinstance(v, Interval) for v in invals):
        return eqn.primitive.bind(*invals, **params)
    if kinks is not None and (kink := _kink(name, params, invals)) is not None:
        kinks.append(kink)
    if name == "scan":
        return _scan(params, invals, [v.aval for v in eqn.outvars], kinks)
    if name == "cond":
        return _cond(params["branches"], invals[0], invals[1:], kinks)
    called = _called(params)
    if called is not None and name in (*_CALLS, "custom_jvp_call", "custom_vjp_call"):
        jaxpr, consts = called
        return eval_jaxpr(jaxpr, consts, *invals[: len(jaxpr.invars)], kinks=kinks)
    rule = _rule(name)
    if rule is not None:
        return rule(*invals)
    if name == "integer_pow":
        return integer_pow(invals[0], params["y"])
    if name == "reduce_sum":
        return reduce_sum(invals[0], params["axes"])
    if name == "cumsum":
        return cumsum(invals[0], params["axis"], params["reverse"])
    if name == "cumprod":
        return cumprod(invals[0], params["axis"], params["reverse"])
    if name in ("cummax", "cummin"):
        return cumulative_extremum(invals[0], name, params["axis"], params["reverse"])
    if name == "sort":
        return sort(invals, params["dimension"], params["is_stable"], params["num_keys"])
    if name in ("argmax", "argmin"):
        return arg_extremum(invals[0], name, params["axes"][0], params["index_dtype"])
    if name == "dot_general":
        return dot_general(*invals, **params)
    if name == "convert_element_type":
        x = invals[0]
        out = _both(eqn.primitive, x, **params)
        narrowing = (
            not _is_discrete_cast(x.dtype, out.dtype)
            and jnp.finfo(out.dtype).bits < jnp.finfo(x.dtype).bits
        )
        return _widen(out.lo, out.hi, 1) if narrowing else out
    if name in _structural:
        x, *rest = invals
        if any(isinstance(r, Interval) for r in rest):
            if name not in ("gather", "dynamic_slice"):
                raise NotImplementedError(f"interval evaluation: {name} with an interval index")
            return _at_uncertain_index(eqn.primitive, x, rest, params)
        return Interval(
            eqn.primitive.bind(x.lo, *rest, **params), eqn.primitive.bind(x.hi, *rest, **params)
        )
    if name in _ROUNDING:
        return _both(_ROUNDING[name], invals[0], **params)
    if name in ("concatenate", "pad", "stack", "dynamic_update_slice"):
        xs = [lift(v) for v in invals]
        return Interval(
            eqn.primitive.bind(*[x.lo for x in xs], **params),
            eqn.primitive.bind(*[x.hi for x in xs], **params),
        )
    if name in ("scatter-add", "scatter_add", "scatter"):
        return _scatter(eqn.primitive, *invals, **params)
    if name in ("split", "unstack"):  # unstack: the transpose of jnp.stack, in a Hessian
        x = invals[0]
        los, his = eqn.primitive.bind(x.lo, **params), eqn.primitive.bind(x.hi, **params)
        return [Interval(lo, hi) for lo, hi in zip(los, his, strict=True)]
    raise NotImplementedError(f"interval evaluation: no rule for the primitive {name!r}")


def eval_jaxpr(jaxpr, consts, *args, kinks: list | None = None) -> list:
    """Evaluate ``jaxpr`` with arguments that are arrays or :class:`Interval` s; every operation
    touching an interval is replaced by its interval extension (outward rounded). ``kinks``:
    a list that collects, for each non-smooth operation, whether it may switch branch over its
    arguments (:func:`_kink`)."""
    env = {}

    def read(v):
        return v.val if isinstance(v, jex.Literal) else env[v]

    for var, val in zip(jaxpr.constvars, consts, strict=True):
        env[var] = val
    for var, val in zip(jaxpr.invars, args, strict=True):
        env[var] = val
    exponents = _exponent_equations(jaxpr)
    for index, eqn in enumerate(jaxpr.eqns):
        invals = [read(v) for v in eqn.invars]
        if index in exponents and all(is_concrete(v) for v in invals):
            # computed now, inside a trace too, so that pow_ can read the exponent's value (pow's
            # derivative takes y - 1 of its exponent)
            with jax.ensure_compile_time_eval():
                out = eqn.primitive.bind(*invals, **eqn.params)
        else:
            out = _apply(eqn, invals, kinks)
        outs = out if eqn.primitive.multiple_results else [out]
        for var, val in zip(eqn.outvars, outs, strict=True):
            if not isinstance(var, jex.DropVar):
                env[var] = val
    return [read(v) for v in jaxpr.outvars]


def _exponent_equations(jaxpr) -> set[int]:
    """The indices of ``jaxpr``'s equations that compute a ``pow``'s exponent, and those that
    compute their arguments, back to the jaxpr's inputs, constants and literals."""
    producer = {var: index for index, eqn in enumerate(jaxpr.eqns) for var in eqn.outvars}
    wanted = [eqn.invars[1] for eqn in jaxpr.eqns if eqn.primitive.name == "pow"]
    marked = set()
    while wanted:
        var = wanted.pop()
        index = None if isinstance(var, jex.Literal) else producer.get(var)
        if index is not None and index not in marked:
            marked.add(index)
            wanted += jaxpr.eqns[index].invars
    return marked


def _shapes(box: Interval, args):
    example = jax.ShapeDtypeStruct(box.shape, box.dtype)
    return example, [jax.ShapeDtypeStruct(jnp.shape(a), jnp.result_type(a)) for a in args]


def _has_non_smooth(jaxpr) -> bool:
    """Whether ``jaxpr`` or a jaxpr inside it applies a primitive :func:`_kink` knows."""
    return any_equation(
        jaxpr,
        lambda eqn: (
            eqn.primitive.name in _NON_SMOOTH
            or (eqn.primitive.name == "convert_element_type" and _makes_a_step(eqn))
        ),
    )


def kinks_over(primal: jex.ClosedJaxpr, box: Interval, *args) -> tuple[Array, Array] | None:
    """``(kink, jump)``: whether ``fn(x, *args)``, of which ``primal`` is the closed jaxpr
    (:func:`with_pairwise_extrema` gives it), may have, for x in ``box``, a point where its
    first derivative jumps (a continuous non-smooth operation switching branch: abs, max, min)
    or where its value may jump (sign, floor, ceil, round, ``where`` or ``cond`` on a condition
    that changes over the box, a cast to or from integers or booleans whose value changes over
    it, atan2 across its branch cut or at the origin);
    ``None`` where ``fn`` has no non-smooth operation at all (:func:`_kink`)."""
    if not _has_non_smooth(primal.jaxpr):
        return None  # nothing to evaluate (nor a rule to need for the primal's other primitives)
    found = []
    eval_jaxpr(primal.jaxpr, primal.consts, box, *args, kinks=found)
    of = lambda kind: jnp.any(jnp.asarray([False] + [f for k, f in found if k == kind]))
    return (of("kink"), of("jump")) if found else None


#: the reductions :func:`with_pairwise_extrema` writes as trees of two-argument operations
_EXTREMA = {"reduce_max": lax.max, "reduce_min": lax.min}


def _pairwise(op, x, axes):
    """``op`` (``lax.max`` or ``lax.min``) of ``x`` over ``axes``, as a tree of two-argument
    ``op`` s: the same value as the reduction."""
    rest = [size for axis, size in enumerate(x.shape) if axis not in axes]
    x = jnp.moveaxis(x, axes, tuple(range(len(axes)))).reshape((-1, *rest))
    while x.shape[0] > 1:
        half = x.shape[0] // 2
        x = jnp.concatenate([op(x[:half], x[half : 2 * half]), x[2 * half :]])
    return x[0]


def _holds_rewrites(jaxpr) -> bool:
    """Whether ``jaxpr`` (or one inside it) holds what :func:`_eval_pairwise` rewrites."""
    return any_equation(jaxpr, lambda eqn: eqn.primitive.name in (*_EXTREMA, "stop_gradient"))


def _eval_pairwise(jaxpr, consts, *args) -> list:
    """Evaluate ``jaxpr`` with each ``reduce_max`` / ``reduce_min`` as :func:`_pairwise` and
    each ``stop_gradient`` as the identity (outside a custom derivative's primal)."""
    env = {}
    read = lambda v: v.val if isinstance(v, jex.Literal) else env[v]
    env.update(zip(jaxpr.constvars, consts, strict=True))
    env.update(zip(jaxpr.invars, args, strict=True))
    for eqn in jaxpr.eqns:
        invals, name = [read(v) for v in eqn.invars], eqn.primitive.name
        called = _called(eqn.params)
        rewrites = called is not None and _holds_rewrites(called[0])
        if name in _EXTREMA:
            outs = [_pairwise(_EXTREMA[name], invals[0], eqn.params["axes"])]
        elif name == "stop_gradient":
            outs = invals
        elif name == "scan" and rewrites:
            outs = _scan_pairwise(eqn.params, invals)
        elif name == "cond" and any(_holds_rewrites(b.jaxpr) for b in eqn.params["branches"]):
            branches = [
                lambda *operands, b=b: _eval_pairwise(b.jaxpr, b.consts, *operands)
                for b in eqn.params["branches"]
            ]
            outs = lax.switch(invals[0], branches, *invals[1:])
        elif name in _CALLS and rewrites:  # a custom derivative's primal: left to its rule
            outs = _eval_pairwise(*called, *invals)
        else:
            out = eqn.primitive.bind(*invals, **eqn.primitive.get_bind_params(eqn.params))
            outs = out if eqn.primitive.multiple_results else [out]
        env.update((var, val) for var, val in zip(eqn.outvars, outs, strict=True))
    return [read(v) for v in jaxpr.outvars]


def _scan_pairwise(params, invals) -> list:
    """A ``lax.scan`` whose body holds a reduction, run with the body's as :func:`_pairwise`."""
    body, consts = params["jaxpr"], invals[: params["num_consts"]]
    count = params["num_consts"] + params["num_carry"]

    def step(carry, xs):
        out = _eval_pairwise(body.jaxpr, body.consts, *consts, *carry, *xs)
        return out[: params["num_carry"]], out[params["num_carry"] :]

    carry, ys = lax.scan(
        step, invals[params["num_consts"] : count], invals[count:], length=params["length"],
        reverse=params["reverse"], unroll=params["unroll"],
    )  # fmt: skip
    return [*carry, *ys]


def with_pairwise_extrema(
    fn: Callable, box: Interval, args
) -> tuple[Callable, jex.ClosedJaxpr, bool]:
    """``fn`` with every ``jnp.max`` / ``jnp.min`` of an array (``reduce_max``, ``reduce_min``;
    in a loop's body or a ``cond``'s branch too) computed as a tree of two-argument
    ``lax.max`` / ``lax.min``, for ``fn(x, *args)`` at the shapes of ``box`` and ``args``; ``fn`` itself where it has none.
    With it, its closed jaxpr (traced once, for :func:`kinks_over` too). The values are the
    same.
    The derivative is not, over intervals: JAX writes a reduction's as the tangents of the
    largest entries divided by how many there are, a count whose enclosure reaches 0 wherever
    two entries may tie over the box, so the enclosure of the derivative, and the remainder
    bound, was infinite; a two-argument maximum's is a choice between its two arguments'.
    Every ``lax.stop_gradient`` (outside a custom derivative's primal, whose rule is kept) is
    the identity, which it is for values: JAX differentiates it as a constant, so fn's JAX
    derivatives are not those of its values (stop_gradient(x) * x: JAX's Hessian 0, the true
    one 2), and a Taylor bound needs the true ones; :func:`remainder_bound` adds what JAX's
    Jacobian, the filter's, differs from the true one by, where the third value, whether
    ``fn`` holds a ``stop_gradient``, is true."""
    example, arg_shapes = _shapes(box, args)
    closed, out_shape = jax.make_jaxpr(fn, return_shape=True)(example, *arg_shapes)
    if not _holds_rewrites(closed.jaxpr):
        return fn, closed, False
    stops = any_equation(closed.jaxpr, lambda eqn: eqn.primitive.name == "stop_gradient")
    out_tree = jax.tree.structure(out_shape)
    rewritten = lambda x, *a: jax.tree.unflatten(
        out_tree, _eval_pairwise(closed.jaxpr, closed.consts, x, *a)
    )
    return rewritten, jax.make_jaxpr(rewritten)(example, *arg_shapes), stops


def _derivative_jaxpr(derivative: Callable, fn: Callable, box: Interval, args):
    """The closed jaxpr of ``derivative(fn)`` for arguments shaped as ``box`` and ``args``."""
    example, arg_shapes = _shapes(box, args)
    return jax.make_jaxpr(derivative(fn))(example, *arg_shapes)


def _derivative_enclosures(derivative: Callable, fn: Callable, boxes, *args) -> list[Interval]:
    """Enclosures of ``derivative(fn)`` over each of ``boxes`` (one shape), traced once."""
    closed = _derivative_jaxpr(derivative, fn, boxes[0], args)
    return [lift(eval_jaxpr(closed.jaxpr, closed.consts, box, *args)[0]) for box in boxes]


def hessian_interval(fn: Callable, box: Interval, *args) -> Interval:
    """An enclosure of the Hessian d^2 fn / dx^2 (shape (m, n, n)) over every x in ``box`` where
    ``fn`` is twice differentiable.

    ``fn(x, *args)`` is any function written in ``jax.numpy``; ``args`` are held fixed (exact).
    The Hessian's jaxpr is built for ``box``'s shape and evaluated over intervals. JAX
    differentiates a non-smooth operation (abs, max, ``where``) branch by branch, so where
    ``fn`` has a kink in the box (:func:`kinks_over`) this encloses its branches' Hessians,
    not the jump of the first derivative there (a Dirac term of the second): a Taylor bound
    needs more (:func:`remainder_bound`).
    """
    check_callable("fn", fn)
    if not isinstance(box, Interval) or jnp.shape(box.lo) != jnp.shape(box.hi):
        raise ValueError("box: expected an Interval(lo, hi) of two arrays of one shape")
    if is_concrete(box.lo) and is_concrete(box.hi) and np.any(np.asarray(box.lo > box.hi)):
        raise ValueError("box: has lo > hi, an empty box")  # its 'enclosure' was any number
    fn, _, _ = with_pairwise_extrema(fn, box, args)
    return _derivative_enclosures(jax.hessian, fn, [box], *args)[0]


def bounding_box(center: Float[Array, " n"], shape: Float[Array, "n n"]) -> Interval:
    """The smallest box around E(center, shape): centre +- sqrt(diag(shape)), rounded outward."""
    radius = _up(jnp.sqrt(jnp.diagonal(shape)))
    return Interval(_down(center - radius), _up(center + radius))


def remainder_bound(
    fn: Callable, center: Float[Array, " n"], shape: Float[Array, "n n"], *args
) -> Float[Array, " m"]:
    """Half-widths alpha of a box holding the Lagrange remainder of ``fn`` linearised at
    ``center``, for every x in E(center, shape) (paper eqs 11, 20; docs/papers/smf.md):

        fn(x) - fn(c) - J(c)(x - c) = 1/2 dx^T H(xi) dx,   |dx_j| <= r_j = sqrt(P_jj),

    bounded in interval arithmetic with dx_j dx_l in [-r_j r_l, r_j r_l] off the diagonal and
    dx_j^2 in [0, r_j^2] on it; alpha_i is the magnitude of the resulting interval.

    Where ``fn`` may have a kink in the box (:func:`kinks_over`: abs, max, min switching branch)
    it has no Hessian there, and the mean-value form for a Lipschitz function is used instead:
    fn(x) - fn(c) - J(c)(x - c) = (J(xi) - J(c))(x - c), J(xi) in the hull of the branches'
    Jacobians over the box, so alpha_i = sum_j |J_ij(box) - J_ij(c)| r_j (first order in r).
    Where its value may jump (sign, ``where`` on a condition that changes over the box, a cast
    to or from integers or booleans whose value changes over it: ``(x > 0).astype(float)``,
    ``x.astype(int)``; atan2 across the negative x axis or at the origin) no bound holds: NaN,
    which the set-membership filter flags. JAX differentiates such a cast as a constant, and
    atan2 as smooth across its cut, so without this check their bounds miss the jump.

    An ``fn`` without non-smooth operations whose Hessian JAX writes as zeros
    (:func:`jaxest._jaxpr.zero_outputs`: an affine ``fn`` such as ``H @ x + b``) is affine: its
    bound is exactly zero, and nothing else is computed (the enclosure below is still traced,
    so a primitive without an interval rule raises as it would otherwise, and then discarded).

    Across a ``stop_gradient`` JAX's Jacobian J0(c), the filter's, is not that of fn's values:
    the bound is that of fn without it (:func:`with_pairwise_extrema`) plus
    sum_j |J_ij(c) - J0_ij(c)| r_j, both Jacobians enclosed at c.
    """
    check_callable("fn", fn)
    check_operands(shape, {"center": center})
    box = bounding_box(center, shape)
    original = fn
    fn, primal, stops = with_pairwise_extrema(fn, box, args)
    hessian = _derivative_jaxpr(jax.hessian, fn, box, args)
    hess = lift(eval_jaxpr(hessian.jaxpr, hessian.consts, box, *args)[0])  # (m, n, n)
    found = kinks_over(primal, box, *args)
    r = _up(jnp.sqrt(jnp.diagonal(shape)))
    # sum_j |spread_ij| r_j: the bound of spread (x - c) over the box
    first_order = lambda spread: reduce_sum(mul(spread, Interval(-r[None], r[None])), (1,)).mag()
    if found is None and zero_outputs(hessian.jaxpr):
        bound = jnp.zeros(hess.shape[:-2], center.dtype)
    else:
        rr = _up(r[:, None] * r[None, :])
        diagonal = jnp.eye(rr.shape[0], dtype=bool)
        products = Interval(jnp.where(diagonal, 0.0, -rr), rr)
        quadratic = reduce_sum(mul(hess, Interval(products.lo[None], products.hi[None])), (1, 2))
        half = 0.5 * quadratic.mag()  # exact but for subnormals, which _up covers
        bound = jnp.where(half == 0, 0.0, _up(half))  # NaN (a failed enclosure) stays NaN
    if found is not None:
        kink, jump = found
        spread = sub(*_derivative_enclosures(jax.jacfwd, fn, [box, point(center)], *args))
        bound = jnp.where(jump, jnp.nan, jnp.where(kink, _up(first_order(spread)), bound))
    if not stops:
        return bound
    # the filter linearises with JAX's Jacobian of the original fn, J0(c), which is not the
    # rewritten fn's J(c) across a stop_gradient: its remainder is the rewritten fn's plus
    # (J(c) - J0(c))(x - c)
    at_center = lambda g: _derivative_enclosures(jax.jacfwd, g, [point(center)], *args)[0]
    return _up(bound + first_order(sub(at_center(fn), at_center(original))))
