"""``vmap_minor``: ``jax.vmap`` with the batch laid on the last (minor) axis of every array.

``jax.vmap`` puts the batch on the leading axis of every array it batches: ``lax.scan`` and most
batching rules move it there. A filter step on small matrices then reads each entry P[i, j] of a
(runs, n, n) covariance as a strided slice, and XLA:CPU's loops over those slices vectorise
poorly. Laid out as (n, n, runs), every entry is a contiguous vector of the runs, and every
operation of the step is an element-wise loop over them. docs/performance.md ("je.vmap_minor:
the runs on the minor axis") has the measurements: in one run of ``benchmarks/speed.py``, the
6-state / 3-measurement Kalman filter over 200 runs took 0.27 us per step and run against 1.37
under ``jax.vmap`` (dynamax: 0.76), its ``value_and_grad`` 1.77 against 3.54.

The layout cannot be asked of ``jax.vmap``, so :func:`vmap_minor` is a transformation of its own:
it traces ``fn`` for one run to a jaxpr and evaluates that jaxpr on batch-minor arrays, primitive
by primitive. Element-wise, structural (broadcast, reshape, slice, concatenate, transpose ...),
reduction, contraction (``dot_general`` as a multiply and a sum), ``scan``, ``cond`` and call
primitives have batch-minor rules here; every other primitive (LAPACK factorisations, random
bits, ``while`` loops, scatters) runs under ``jax.vmap`` with the batch moved to the front and back
again, which is always correct and costs two transposes. :func:`vmap_minor_fallbacks` lists the
primitives of a function that take that path.

Custom derivative rules (``custom_jvp``, ``custom_vjp``) are evaluated by their primal function:
differentiate inside the batched function, ``vmap_minor(jax.value_and_grad(loss))``, where the
rules have already been applied when the jaxpr is traced. A derivative taken outside
(``jax.grad(vmap_minor(f))``, also under ``jax.vmap``) of a function with such rules runs under
``jax.vmap``, which keeps them: autodiff of the primal code gave NaN gradients through the SVD
filters, whose rules exist because the SVD's own derivative is NaN. Only a derivative taken
through a caller's ``jit`` around ``vmap_minor`` (``jax.grad(jax.jit(g))`` with ``g`` calling
it) cannot be seen here and is still autodiff of the primal code.

The returned function is ``jax.jit``-compiled, with XLA:CPU's YNNPACK fusions turned off for it
(:data:`jaxest.xla_flags.NO_YNN_FUSION`): YNNPACK takes every fusion with 4 096 elements or more,
which here is every contraction, and ran the Kalman filter's about 3x slower than XLA's own
loops over the minor axis. Called inside a caller's ``jit``, the program is compiled as part of
the caller's, without that option: still batch-minor, but slower on the CPU (pass the option to
that ``jit``).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.extend import core as jex_core

from jaxest import xla_flags
from jaxest._checks import check_callable
from jaxest._jaxpr import any_equation
from jaxest.linalg import SMALL_MATMUL

#: primitives that act entry by entry (operands of equal shape, or broadcast from size 1)
ELEMENTWISE = frozenset(
    """abs acos acosh add add_any and asin asinh atan atan2 atanh cbrt ceil clamp conj
    convert_element_type copy cos cosh digamma div eq erf erf_inv erfc exp exp2 expm1 floor ge gt imag
    integer_pow is_finite le lgamma log log1p logistic lt max min mul ne neg nextafter not or
    population_count pow real reduce_precision rem round rsqrt select_n shift_left
    shift_right_arithmetic shift_right_logical sign sin sinh sqrt square stop_gradient sub tan
    tanh xor""".split()
)
#: element-wise primitives that take no size-1 broadcasting: operands of one shape
EQUAL_SHAPES = frozenset({"add_any", "clamp", "select_n"})
#: primitives whose ``axes``, ``axis`` or ``dimension`` parameters name per-run axes and whose
#: output keeps the batch axis last (reductions, cumulative sums, reversal)
SAME_PARAMETERS = frozenset(
    """argmax argmin cumlogsumexp cummax cummin cumprod cumsum reduce_and reduce_max reduce_min
    reduce_or reduce_prod reduce_sum reduce_xor rev squeeze split unstack""".split()
)
#: what :func:`vmap_minor` compiles its program with at top level (``None`` on a jaxlib the
#: option was not measured on); a caller compiling it inside its own ``jit`` passes these
COMPILER_OPTIONS = xla_flags.compile_options(xla_flags.NO_YNN_FUSION)


def vmap_minor(fn: Callable, in_axes=0) -> Callable:
    """``jax.vmap(fn, in_axes)`` computed with the batch on the minor axis (module docstring).

    Args:
        fn: a function of one run's arrays (pytrees of arrays), traceable by JAX.
        in_axes: 0 (batched along the leading axis) or ``None`` (shared by every run): one
            value for every argument, or a tuple with an entry per argument, each a pytree
            prefix of its argument, as for ``jax.vmap``.

    Returns:
        A jitted function of the batched arguments whose outputs carry the batch on their
        leading axis, as ``jax.vmap``'s do (``out_axes=0``); outputs that do not depend on a
        batched argument are broadcast.
    """
    check_callable("fn", fn)
    _check_in_axes(in_axes)

    def batched(*args):
        traced = _traced(fn, args, in_axes)
        values = [
            jnp.moveaxis(x, 0, -1) if b else x
            for x, b in zip(traced.leaves, traced.batched, strict=True)
        ]
        outs, out_batched = traced.evaluate(values)
        outs = [
            jnp.moveaxis(out, -1, 0) if b else jnp.broadcast_to(out, (traced.size, *jnp.shape(out)))
            for out, b in zip(outs, out_batched, strict=True)
        ]
        return jax.tree.unflatten(traced.out_tree, outs)

    compiled = jit_with_options_at_top_level(jax.jit, batched, COMPILER_OPTIONS)

    @functools.wraps(fn)
    def call(*args):
        leaves, _, _ = _flat_arguments(args, in_axes)  # the argument errors, before tracing
        if any(map(_differentiated, leaves)) and _has_custom_rules(_traced(fn, args, in_axes)):
            return jax.vmap(fn, in_axes)(*args)  # keeps the rules (module docstring)
        return compiled(*args)

    return call


def _differentiated(x) -> bool:
    """Whether ``x`` carries a forward- or reverse-mode derivative being taken outside (a JVP or
    linearize tracer, possibly under ``jax.vmap``'s)."""
    while isinstance(x, jax.core.Tracer):
        kind = type(x).__name__
        if kind in ("JVPTracer", "LinearizeTracer"):
            return True
        x = getattr(x, "val", None) if kind == "BatchTracer" else None
    return False


def _has_custom_rules(traced: _Traced) -> bool:
    """Whether the traced function has a ``custom_jvp`` or ``custom_vjp`` rule anywhere."""
    custom = ("custom_jvp_call", "custom_vjp_call")
    return any_equation(traced.jaxpr.jaxpr, lambda eqn: eqn.primitive.name in custom)


def vmap_minor_fallbacks(fn: Callable, *args, in_axes=0) -> dict[str, int]:
    """The primitives of ``vmap_minor(fn, in_axes)(*args)`` that have no batch-minor rule and
    run under ``jax.vmap`` with the batch moved to the front (name: how many equations)."""
    _check_in_axes(in_axes)
    traced = _traced(fn, args, in_axes)
    counts: dict[str, int] = {}
    avals = [
        _aval(x, (*x.shape[1:], traced.size) if b else None)
        for x, b in zip(traced.leaves, traced.batched, strict=True)
    ]
    jax.eval_shape(lambda *values: traced.evaluate(values, counts)[0], *avals)
    return counts


class _Traced(NamedTuple):
    """``fn`` traced for one run: its jaxpr, the arguments' leaves, which are batched, the
    batch size and the outputs' tree."""

    jaxpr: jex_core.ClosedJaxpr
    leaves: list
    batched: list[bool]
    size: int
    out_tree: object

    def evaluate(self, values, fallbacks=None):
        """The jaxpr on the leaves' batch-minor ``values`` (:func:`evaluate`)."""
        return evaluate(
            self.jaxpr.jaxpr, self.jaxpr.consts, values, self.batched, self.size, fallbacks
        )


def _traced(fn, args, in_axes) -> _Traced:
    leaves, batched, size = _flat_arguments(args, in_axes)
    tree = jax.tree.structure(args)
    one_run = [_aval(x, x.shape[1:] if b else None) for x, b in zip(leaves, batched, strict=True)]
    closed, out_shapes = jax.make_jaxpr(
        lambda *flat: fn(*jax.tree.unflatten(tree, flat)), return_shape=True
    )(*one_run)
    return _Traced(closed, leaves, batched, size, jax.tree.structure(out_shapes))


def jit_with_options_at_top_level(jit: Callable, fn: Callable, compiler_options) -> Callable:
    """``jit(fn)`` (``jax.jit`` or ``eqx.filter_jit``) compiled with ``compiler_options`` where
    nothing traces the call, without them where a caller's ``jit``, ``vmap`` or ``grad`` does:
    JAX takes compiler options only for a program of its own, and rejects them on a jit that
    is traced into a caller's program."""
    top_level, nested = jit(fn, compiler_options=compiler_options), jit(fn)
    return lambda *args: (top_level if _at_top_level() else nested)(*args)


def _at_top_level() -> bool:
    """Whether nothing traces the current call: the current trace is JAX's eval trace
    (``jax.extend`` names no type for it)."""
    with jex_core.take_current_trace() as trace:
        return type(trace).__name__ == "EvalTrace"


def _check_in_axes(in_axes) -> None:
    for axis in jax.tree.leaves(in_axes, is_leaf=lambda x: x is None):
        if axis is not None and axis != 0:
            raise ValueError(f"in_axes: each entry must be 0 or None, got {axis!r}")


def _flat_arguments(args, in_axes) -> tuple[list, list[bool], int]:
    """The arguments' leaves, whether each is batched, and the batch size; ``ValueError`` on
    ``in_axes`` that do not fit the arguments, and on arguments that do not fit ``in_axes``."""
    if isinstance(in_axes, (list, tuple)):
        if len(in_axes) != len(args):
            raise ValueError(f"in_axes: {len(in_axes)} entries for {len(args)} arguments")
        per_argument = in_axes
    else:
        per_argument = (in_axes,) * len(args)
    leaves, batched_leaves = [], []
    for i, (arg, axes) in enumerate(zip(args, per_argument, strict=True)):
        try:
            jax.tree.map(
                lambda axis, sub: batched_leaves.extend([axis == 0] * len(jax.tree.leaves(sub))),
                axes, arg, is_leaf=lambda x: x is None,
            )  # fmt: skip
        except ValueError as error:
            raise ValueError(
                f"in_axes: entry {i} is not a pytree prefix of argument {i}"
            ) from error
        for leaf in jax.tree.leaves(arg):
            if not (hasattr(leaf, "shape") and hasattr(leaf, "dtype")):
                raise ValueError(
                    f"argument {i}: a leaf of type {type(leaf).__name__} is not an array"
                )
            leaves.append(leaf)
    if any(b and leaf.ndim == 0 for leaf, b in zip(leaves, batched_leaves, strict=True)):
        raise ValueError("in_axes: a batched argument is a scalar (it has no axis 0)")
    sizes = {leaf.shape[0] for leaf, b in zip(leaves, batched_leaves, strict=True) if b}
    if not sizes:
        raise ValueError("in_axes: no argument is batched")
    if len(sizes) > 1:
        raise ValueError(
            f"arguments: the batched arguments disagree on the batch size: {sorted(sizes)}"
        )
    return leaves, batched_leaves, sizes.pop()


def _aval(x, shape=None) -> jax.ShapeDtypeStruct:
    """``x``'s shape (or ``shape``), dtype and weak type (a weakly typed float32 times a float16
    is float16 under ``jax.vmap``; dropping the weak type made it float32)."""
    shape = jnp.shape(x) if shape is None else tuple(shape)
    weak = bool(getattr(getattr(x, "aval", None), "weak_type", False))
    return jax.ShapeDtypeStruct(shape, jnp.result_type(x), weak_type=weak)


# ---- the interpreter -------------------------------------------------------------------------


def evaluate(jaxpr, consts, values, batched, size, fallbacks=None):
    """Evaluate ``jaxpr`` on ``values``, those flagged in ``batched`` carrying the batch (of
    ``size``) as their last axis; returns (outputs, which outputs are batched). ``fallbacks``,
    a dict, counts the equations that went through :func:`_fallback`."""
    env = {}

    def read(var):
        if isinstance(var, jex_core.Literal):
            return np.asarray(var.val, var.aval.dtype), False
        return env[var]

    for var, const in zip(jaxpr.constvars, consts, strict=True):
        env[var] = (const, False)
    for var, value, b in zip(jaxpr.invars, values, batched, strict=True):
        env[var] = (value, b)
    for eqn in jaxpr.eqns:
        ins = [read(var) for var in eqn.invars]
        in_values = [value for value, _ in ins]
        in_batched = [b for _, b in ins]
        if not any(in_batched):
            outs = eqn.primitive.bind(*in_values, **eqn.primitive.get_bind_params(eqn.params))
            outs = outs if eqn.primitive.multiple_results else [outs]
            out_batched = [False] * len(outs)
        else:
            rule = _RULES.get(eqn.primitive.name, _fallback)
            outs, out_batched = rule(eqn, in_values, in_batched, size, fallbacks)
        for var, out, b in zip(eqn.outvars, outs, out_batched, strict=True):
            if not isinstance(var, jex_core.DropVar):
                env[var] = (out, b)
    outs = [read(var) for var in jaxpr.outvars]
    return [value for value, _ in outs], [b for _, b in outs]


def _minor(x, size):
    """An unbatched ``x`` with the batch axis appended (broadcast)."""
    x = jnp.asarray(x)
    return lax.broadcast_in_dim(x, (*x.shape, size), tuple(range(x.ndim)))


def _batched_where_wanted(values, batched, wanted, size):
    """``values``, those unbatched where ``wanted`` holds given the batch axis (:func:`_minor`)."""
    return [
        _minor(v, size) if want and not b else v
        for v, b, want in zip(values, batched, wanted, strict=True)
    ]


def _all_minor(values, batched, size):
    return _batched_where_wanted(values, batched, [True] * len(values), size)


def _fallback(eqn, values, batched, size, fallbacks):
    """The primitive under ``jax.vmap``, the batch moved to the front and back (counted in
    ``fallbacks``)."""
    if fallbacks is not None:
        fallbacks[eqn.primitive.name] = fallbacks.get(eqn.primitive.name, 0) + 1
    params = eqn.primitive.get_bind_params(eqn.params)
    moved = [jnp.moveaxis(v, -1, 0) if b else v for v, b in zip(values, batched, strict=True)]
    outs = jax.vmap(
        lambda *args: eqn.primitive.bind(*args, **params),
        in_axes=[0 if b else None for b in batched],
        axis_size=size,
    )(*moved)
    outs = outs if eqn.primitive.multiple_results else [outs]
    return [jnp.moveaxis(out, 0, -1) for out in outs], [True] * len(outs)


def _elementwise(eqn, values, batched, size, fallbacks):
    """Operands of one rank, unbatched ones with a trailing axis of size 1 (element-wise
    primitives broadcast size-1 axes), broadcast in full for :data:`EQUAL_SHAPES`."""
    shapes = [v.shape[:-1] if b else jnp.shape(v) for v, b in zip(values, batched, strict=True)]
    rank = max(len(s) for s in shapes)
    operands = []
    for value, b, shape in zip(values, batched, shapes, strict=True):
        value = value if b else jnp.asarray(value)
        target = (1,) * (rank - len(shape)) + tuple(shape) + ((size,) if b else (1,))
        operands.append(value if value.shape == target else lax.reshape(value, target))
    if eqn.primitive.name in EQUAL_SHAPES:
        full = jnp.broadcast_shapes(*(x.shape for x in operands))
        operands = [jnp.broadcast_to(x, full) for x in operands]
    out = eqn.primitive.bind(*operands, **eqn.params)
    return ([out] if not eqn.primitive.multiple_results else list(out)), [True]


def _same_parameters(eqn, values, batched, size, fallbacks):
    outs = eqn.primitive.bind(*_all_minor(values, batched, size), **eqn.params)
    outs = list(outs) if eqn.primitive.multiple_results else [outs]
    return outs, [True] * len(outs)


def _broadcast_in_dim(eqn, values, batched, size, fallbacks):
    params = eqn.params
    shape, dims = params["shape"], params["broadcast_dimensions"]
    return [lax.broadcast_in_dim(values[0], (*shape, size), (*dims, len(shape)))], [True]


def _reshape(eqn, values, batched, size, fallbacks):
    if eqn.params.get("dimensions") is not None:
        return _fallback(eqn, values, batched, size, fallbacks)
    return [lax.reshape(values[0], (*eqn.params["new_sizes"], size))], [True]


def _transpose(eqn, values, batched, size, fallbacks):
    permutation = eqn.params["permutation"]
    return [lax.transpose(values[0], (*permutation, len(permutation)))], [True]


def _slice(eqn, values, batched, size, fallbacks):
    params = eqn.params
    strides = params["strides"] or (1,) * len(params["start_indices"])
    out = lax.slice(
        values[0], (*params["start_indices"], 0), (*params["limit_indices"], size), (*strides, 1)
    )
    return [out], [True]


def _concatenate(eqn, values, batched, size, fallbacks):
    return [lax.concatenate(_all_minor(values, batched, size), eqn.params["dimension"])], [True]


def _stack(eqn, values, batched, size, fallbacks):
    return [eqn.primitive.bind(*_all_minor(values, batched, size), **eqn.params)], [True]


def _pad(eqn, values, batched, size, fallbacks):
    if batched[1]:  # a padding value per run
        return _fallback(eqn, values, batched, size, fallbacks)
    config = (*eqn.params["padding_config"], (0, 0, 0))
    return [lax.pad(values[0], values[1], config)], [True]


def _dynamic_slice(eqn, values, batched, size, fallbacks):
    if any(batched[1:]):  # indices per run: a gather
        return _fallback(eqn, values, batched, size, fallbacks)
    zero = jnp.zeros((), jnp.result_type(values[1]) if len(values) > 1 else jnp.int32)
    sizes = (*eqn.params["slice_sizes"], size)
    return [lax.dynamic_slice(values[0], (*values[1:], zero), sizes)], [True]


def _dynamic_update_slice(eqn, values, batched, size, fallbacks):
    if any(batched[2:]):  # indices per run: a scatter
        return _fallback(eqn, values, batched, size, fallbacks)
    operand, update = _all_minor(values[:2], batched[:2], size)
    zero = jnp.zeros((), jnp.result_type(values[2]) if len(values) > 2 else jnp.int32)
    return [lax.dynamic_update_slice(operand, update, (*values[2:], zero))], [True]


def _gather(eqn, values, batched, size, fallbacks):
    if batched[1]:  # indices per run
        return _fallback(eqn, values, batched, size, fallbacks)
    params = dict(eqn.params)
    numbers = params["dimension_numbers"]
    out_rank = len(eqn.outvars[0].aval.shape)
    params["dimension_numbers"] = numbers._replace(offset_dims=(*numbers.offset_dims, out_rank))
    params["slice_sizes"] = (*params["slice_sizes"], size)
    return [eqn.primitive.bind(values[0], values[1], **params)], [True]


def _dot_general(eqn, values, batched, size, fallbacks):
    """A contraction of at most ``SMALL_MATMUL`` multiply-adds per run as a multiply and a
    sum over the contracted axes: each operand arranged as (batch dims, lhs free, rhs free,
    contracted, runs), with size-1 axes where it has none. A larger one is XLA's dot, with the
    runs as a batch dimension in front (:func:`_fallback`): the broadcast product of two 23 x 23
    matrices would be 23 times the size of either."""
    out_elements = math.prod(eqn.outvars[0].aval.shape)
    lhs_shape = eqn.invars[0].aval.shape
    (lhs_contract, rhs_contract), (lhs_batch, rhs_batch) = eqn.params["dimension_numbers"]
    if out_elements * math.prod(lhs_shape[d] for d in lhs_contract) > SMALL_MATMUL:
        return _fallback(eqn, values, batched, size, fallbacks)
    lhs_rank, rhs_rank = (len(var.aval.shape) for var in eqn.invars)
    lhs_free = [d for d in range(lhs_rank) if d not in lhs_contract and d not in lhs_batch]
    rhs_free = [d for d in range(rhs_rank) if d not in rhs_contract and d not in rhs_batch]

    def arrange(x, b, batch_dims, free, contract, ones_before, ones_after):
        order = (*batch_dims, *free, *contract)
        x = lax.transpose(x, (*order, len(order))) if b else lax.transpose(x, order)[..., None]
        shape = x.shape
        n_batch = len(batch_dims)
        head, free_shape, tail = (
            shape[:n_batch],
            shape[n_batch : n_batch + len(free)],
            shape[n_batch + len(free) :],
        )
        return lax.reshape(x, (*head, *ones_before, *free_shape, *ones_after, *tail))

    lhs = arrange(
        values[0], batched[0], lhs_batch, lhs_free, lhs_contract, (), (1,) * len(rhs_free)
    )
    rhs = arrange(
        values[1], batched[1], rhs_batch, rhs_free, rhs_contract, (1,) * len(lhs_free), ()
    )
    start = len(lhs_batch) + len(lhs_free) + len(rhs_free)
    out_dtype = eqn.outvars[0].aval.dtype  # preferred_element_type: in the narrow inputs'
    product = lhs.astype(out_dtype) * rhs.astype(out_dtype)  # dtype the products overflowed
    out = (
        jnp.sum(product, axis=tuple(range(start, start + len(lhs_contract))))
        if lhs_contract
        else product
    )
    out = jnp.broadcast_to(out, (*out.shape[:-1], size))
    return [out], [True]


def _branch_flags(branches, avals, batched, size) -> list[bool]:
    """Which outputs of any of ``branches`` are batched, from an abstract evaluation of each
    on ``avals``."""
    flags = []
    for branch in branches:
        box = []

        def run(*args, branch=branch, box=box):
            outs, out_batched = evaluate(branch.jaxpr, branch.consts, args, batched, size)
            box.append(out_batched)
            return outs

        jax.eval_shape(run, *avals)
        flags.append(box[0])
    return [any(column) for column in zip(*flags, strict=True)]


def _cond(eqn, values, batched, size, fallbacks):
    """An unbatched branch index: ``lax.switch`` over the branches evaluated batch-minor; a
    batched one: every branch evaluated and the results selected per run, as ``jax.vmap``
    does."""
    branches = eqn.params["branches"]
    index, operands, operand_batched = values[0], values[1:], batched[1:]
    if batched[0]:
        results = [
            _all_minor(
                *evaluate(b.jaxpr, b.consts, operands, operand_batched, size, fallbacks), size
            )
            for b in branches
        ]
        selected = [
            lax.select_n(jnp.broadcast_to(index, outs[0].shape), *outs)
            for outs in zip(*results, strict=True)
        ]
        return selected, [True] * len(selected)
    out_batched = _branch_flags(branches, [_aval(v) for v in operands], operand_batched, size)

    def branch_fn(branch):
        def run(*args):
            outs, flags = evaluate(
                branch.jaxpr, branch.consts, list(args), operand_batched, size, fallbacks
            )
            return _batched_where_wanted(outs, flags, out_batched, size)

        return run

    outs = lax.switch(index, [branch_fn(b) for b in branches], *operands)
    return list(outs), out_batched


def _scan(eqn, values, batched, size, fallbacks):
    """``lax.scan`` of the body evaluated batch-minor. A carry becomes batched where the body
    makes it so (found by evaluating the body abstractly until the carries' flags settle);
    its initial value is then broadcast."""
    params = eqn.params
    body, n_consts, n_carry = params["jaxpr"], params["num_consts"], params["num_carry"]
    consts, init, xs = (
        values[:n_consts],
        values[n_consts : n_consts + n_carry],
        values[n_consts + n_carry :],
    )
    const_b = batched[:n_consts]
    init_b = batched[n_consts : n_consts + n_carry]
    xs_b = batched[n_consts + n_carry :]
    carry_b = list(init_b)
    while True:
        avals = [
            *(_aval(v) for v in consts),
            *(
                _aval(v, (*jnp.shape(v), size) if b and not ib else None)
                for v, b, ib in zip(init, carry_b, init_b, strict=True)
            ),
            *(_aval(v, jnp.shape(v)[1:]) for v in xs),
        ]
        flags = _branch_flags([body], avals, [*const_b, *carry_b, *xs_b], size)
        settled = [a or b for a, b in zip(carry_b, flags[:n_carry], strict=True)]
        if settled == carry_b:
            break
        carry_b = settled
    init = _batched_where_wanted(init, init_b, carry_b, size)

    def step(carry, x):
        outs, out_b = evaluate(
            body.jaxpr,
            body.consts,
            [*consts, *carry, *x],
            [*const_b, *carry_b, *xs_b],
            size,
            fallbacks,
        )
        carry = _batched_where_wanted(outs[:n_carry], out_b[:n_carry], carry_b, size)
        return carry, outs[n_carry:]

    carry, ys = lax.scan(
        step, init, xs, length=params["length"], reverse=params["reverse"], unroll=params["unroll"]
    )
    return [*carry, *ys], [*carry_b, *flags[n_carry:]]


def _inline(jaxpr_param: str, closed: bool = True):
    """The rule of a call primitive: evaluate its jaxpr (for custom derivatives, the primal)."""

    def rule(eqn, values, batched, size, fallbacks):
        jaxpr = eqn.params[jaxpr_param]
        if closed:
            return evaluate(jaxpr.jaxpr, jaxpr.consts, values, batched, size, fallbacks)
        return evaluate(jaxpr, (), values, batched, size, fallbacks)

    return rule


_RULES: dict[str, Callable] = {
    **dict.fromkeys(ELEMENTWISE, _elementwise),
    **dict.fromkeys(SAME_PARAMETERS, _same_parameters),
    "broadcast_in_dim": _broadcast_in_dim,
    "reshape": _reshape,
    "transpose": _transpose,
    "slice": _slice,
    "concatenate": _concatenate,
    "stack": _stack,
    "pad": _pad,
    "dynamic_slice": _dynamic_slice,
    "dynamic_update_slice": _dynamic_update_slice,
    "gather": _gather,
    "dot_general": _dot_general,
    "cond": _cond,
    "scan": _scan,
    "jit": _inline("jaxpr"),
    "custom_jvp_call": _inline("call_jaxpr"),
    "custom_vjp_call": _inline("call_jaxpr"),
    "custom_vmap_call": _inline("call"),
    "remat2": _inline("jaxpr", closed=False),
}

__all__: Sequence[str] = ["vmap_minor", "vmap_minor_fallbacks"]
