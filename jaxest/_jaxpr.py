"""Walking jaxprs: the jaxprs an equation carries in its parameters, and outputs that are zero
by construction."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
from jax.extend import core as jex_core

#: primitives whose outputs are zero where every array operand is (a ``select_n``: every case)
_ZERO_PRESERVING = frozenset({
    "broadcast_in_dim", "reshape", "squeeze", "expand_dims", "transpose", "split", "slice",
    "concatenate", "copy", "convert_element_type", "add", "add_any", "sub", "neg", "select_n",
})  # fmt: skip


def inner_jaxprs(eqn) -> Iterator[jex_core.Jaxpr]:
    """The jaxprs in ``eqn``'s parameters (a ``ClosedJaxpr``'s own): a scan's body, a cond's
    branches, a jit's program, a custom derivative rule's primal."""
    for value in eqn.params.values():
        for inner in value if isinstance(value, tuple | list) else (value,):
            inner = getattr(inner, "jaxpr", inner)
            if isinstance(inner, jex_core.Jaxpr):
                yield inner


def any_equation(jaxpr: jex_core.Jaxpr, predicate) -> bool:
    """Whether ``predicate(eqn)`` holds for an equation of ``jaxpr`` or of a jaxpr inside it
    (:func:`inner_jaxprs`)."""
    return any(
        predicate(eqn) or any(any_equation(inner, predicate) for inner in inner_jaxprs(eqn))
        for eqn in jaxpr.eqns
    )


def zero_outputs(jaxpr: jex_core.Jaxpr) -> bool:
    """Whether every output of ``jaxpr`` is zero whatever its inputs: built from zero literals
    by broadcasting, reshaping, slicing, concatenating, adding and selecting alone, as JAX
    writes a derivative that is zero. ``False`` where that is not seen (it may still be zero)."""
    zero = set()

    def is_zero(v) -> bool:
        if isinstance(v, jex_core.Literal):
            return bool(np.all(np.asarray(v.val) == 0))
        return v in zero

    for eqn in jaxpr.eqns:
        name = eqn.primitive.name
        operands = eqn.invars[1:] if name == "select_n" else eqn.invars  # not the predicate
        if name in _ZERO_PRESERVING and all(map(is_zero, operands)):
            zero.update(eqn.outvars)
    return all(map(is_zero, jaxpr.outvars))
