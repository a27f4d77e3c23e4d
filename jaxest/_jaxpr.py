"""Walking jaxprs: the jaxprs an equation carries in its parameters."""

from __future__ import annotations

from collections.abc import Iterator

from jax.extend import core as jex_core


def inner_jaxprs(eqn) -> Iterator[jex_core.Jaxpr]:
    """The jaxprs in ``eqn``'s parameters (a ``ClosedJaxpr``'s own): a scan's body, a cond's
    branches, a jit's program, a custom derivative rule's primal."""
    for value in eqn.params.values():
        for inner in value if isinstance(value, tuple | list) else (value,):
            inner = getattr(inner, "jaxpr", inner)
            if isinstance(inner, jex_core.Jaxpr):
                yield inner
