"""What a traced program asks of XLA, read from its lowered text."""

import re

import jax


def dot_precisions(fn, *args) -> list[str]:
    """The precision of every matrix product in ``jax.jit(fn)``'s lowered program ("" where it
    carries none)."""
    lines = [
        line for line in jax.jit(fn).lower(*args).as_text().splitlines() if "dot_general" in line
    ]
    return [m[1] if (m := re.search(r"precision = \[(\w+), \w+\]", line)) else "" for line in lines]
