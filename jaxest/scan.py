"""An associative scan whose compiled size does not grow with the sequence length.

``lax.associative_scan`` evaluates the Brent-Kung combination tree level by level: the up-sweep
combines, at level d = 0, 1, ..., the elements j = 2^(d+1) (i+1) - 1 with their left partners
j - 2^d,

    a_j <- a_(j - 2^d) * a_j,   j + 1 a multiple of 2^(d+1),                                (1)

and the down-sweep, at levels d = ..., 1, 0, completes the prefixes in between,

    a_j <- a_(j - 2^d) * a_j,   j + 1 an odd multiple of 2^d, j >= 3 2^d - 1.               (2)

Each of its 2 log2 T levels has its own number of combinations, so XLA compiles the combination
once per level (0.3-0.6 s each on a 2-core CPU for the Kalman filter's elements).
:func:`associative_scan` runs the same tree, eqs (1)-(2) in the same order, as one ``lax.scan``
over a schedule fixed at trace time: each step gathers ``C`` left and right operands from the
buffer of all T elements, combines them as one batch and scatters the results back, and a level
with more than ``C`` combinations takes several steps. The combination is compiled once, whatever
T. The lanes a level leaves unused in its last step repeat one of its own combinations and their
results are dropped, so every combination evaluated is one of the scan's own.

``C`` is the smallest power of two >= T / ``CHUNKS`` (at least ``MIN_LANES``, at most the T / 2
combinations of the first level): the first level takes about ``CHUNKS`` / 2 steps, the whole
scan at most 2 ``CHUNKS`` + 2 log2 T steps of ``C`` independent combinations each (O(log T) depth
for a fixed ``CHUNKS``), and the unused lanes add fewer than ``C`` combinations per level. Each
step also has a fixed cost (the combination's kernels and LAPACK calls, ~0.1 ms for the Kalman
filter's elements on CPU), so narrow steps trade unused lanes for more steps. ``CHUNKS`` = 256,
measured for filter + smoother (``benchmarks/scan_lanes.py``): on a 2-core CPU, where an unused
lane costs as much as a used one, it was 6-35 % slower per run than ``lax.associative_scan``
(interleaved runs, n = 4 and 20, T = 10^2-10^4), and 16, 64 and 1024 were slower still; on an
NVIDIA H100, where the lanes of a step run side by side, run times for T / C = 4, 16, 64 and 256
were within 2 % of each other (9 % for the 3-5 ms runs at n = 4, T = 10^4) and as fast as
``lax.associative_scan`` (n = 4 and 20, T = 10^4 and 10^5, float32), so one value serves both. Other accelerators are not measured. The elements are
packed into one (T, width) array per dtype, so a step gathers and scatters one array each.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from jaxest._checks import check_callable

#: T / C, the steps the first level is cut into (module docstring)
CHUNKS = 256
#: fewest lanes per step
MIN_LANES = 8


def lanes(T: int) -> int:
    """``C``, the combinations per step for T >= 2 elements (module docstring)."""
    return min(T // 2, max(MIN_LANES, 1 << max(0, math.ceil(math.log2(T / CHUNKS)))))


def schedule(T: int, C: int) -> np.ndarray:
    """Eqs (1)-(2) as steps of ``C`` lanes: int32 array (steps, 3, C) of the left operand, the
    right operand and where the result goes (T, out of range, for the unused lanes)."""
    depth = T.bit_length() - 1  # 2^(d+1) <= T for d < depth
    up = [np.arange(2 ** (d + 1) - 1, T, 2 ** (d + 1)) for d in range(depth)]  # eq (1)
    down = [np.arange(3 * 2**d - 1, T, 2 ** (d + 1)) for d in range(depth - 1, -1, -1)]  # (2)
    levels = [(right - 2**d, right) for d, right in enumerate(up)]
    levels += [(right - 2 ** (depth - 1 - i), right) for i, right in enumerate(down)]
    steps = []
    for left, right in levels:
        for start in range(0, left.size, C):
            l, r = left[start : start + C], right[start : start + C]
            pad = C - l.size
            steps.append([np.pad(l, (0, pad), mode="edge"), np.pad(r, (0, pad), mode="edge"),
                          np.pad(r, (0, pad), constant_values=T)])  # fmt: skip
    return np.asarray(steps, np.int32).reshape(-1, 3, C)


def _packing(elems):
    """Functions packing ``elems`` (leading axis T) into one (T, width) array per dtype, and
    back: a step then gathers and scatters one array per dtype instead of one per leaf."""
    leaves, treedef = jax.tree.flatten(elems)
    groups = {}
    for i, leaf in enumerate(leaves):
        groups.setdefault(jnp.dtype(leaf.dtype), []).append(i)
    shapes = [leaf.shape[1:] for leaf in leaves]
    widths = [math.prod(shape) for shape in shapes]

    def pack(tree):
        flat = jax.tree.leaves(tree)
        rows = flat[0].shape[0]
        return [jnp.concatenate([flat[i].reshape(rows, widths[i]) for i in group], 1)
                for group in groups.values()]  # fmt: skip

    def unpack(arrays):
        flat = [None] * len(leaves)
        for array, group in zip(arrays, groups.values(), strict=True):
            offsets = np.cumsum([0] + [widths[i] for i in group])
            for i, start, stop in zip(group, offsets[:-1], offsets[1:], strict=True):
                flat[i] = array[:, start:stop].reshape(array.shape[0], *shapes[i])
        return jax.tree.unflatten(treedef, flat)

    return pack, unpack


def associative_scan(fn, elems, *, reverse: bool = False):
    """All prefixes ``elems[0] * ... * elems[k]`` (``fn`` batched over the leading axis, as for
    ``lax.associative_scan``; ``reverse=True``: suffixes, ``fn`` still called as ``fn(a, b)``
    with ``a`` the element later in the sequence), by the same combination tree as
    ``lax.associative_scan`` and with the combination compiled once (module docstring)."""
    check_callable("fn", fn)
    lengths = {jnp.shape(leaf)[0] if jnp.ndim(leaf) else None for leaf in jax.tree.leaves(elems)}
    if len(lengths) != 1 or None in lengths:  # a reshape's TypeError from inside the scan
        raise ValueError(
            f"elems: every leaf needs the same leading axis, the sequence's; got lengths "
            f"{sorted(lengths, key=str)}"
        )
    T = lengths.pop()
    if T < 2:
        return elems
    if reverse:
        elems = jax.tree.map(lambda a: jnp.flip(a, 0), elems)
    pack, unpack = _packing(elems)
    steps = jnp.asarray(schedule(T, lanes(T)))

    def step(buffers, indices):
        left, right, out = indices
        new = pack(fn(unpack([x[left] for x in buffers]), unpack([x[right] for x in buffers])))
        return [x.at[out].set(v, mode="drop") for x, v in zip(buffers, new, strict=True)], None

    elems = unpack(jax.lax.scan(step, pack(elems), steps)[0])
    if reverse:
        elems = jax.tree.map(lambda a: jnp.flip(a, 0), elems)
    return elems


__all__ = ["associative_scan"]
