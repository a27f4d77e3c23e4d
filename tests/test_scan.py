"""jaxest.scan.associative_scan against lax.associative_scan on non-commutative associative
operations (2 x 2 matrix products, affine maps), both directions, lengths that are not powers of
two, under jit, vmap and grad; its schedule covers the Brent-Kung tree once per combination."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxest import scan
from tests import benchmark_scripts

LENGTHS = [1, 2, 3, 7, 64, 100, 1000]


def matmul(a, b):
    """a then b, as maps: b @ a."""
    return b @ a


def affine(a, b):
    """x -> A x + c, a then b: (A_b A_a, A_b c_a + c_b)."""
    return {"A": b["A"] @ a["A"], "c": b["A"] @ a["c"] + b["c"]}


def matrices(T, seed=0):
    return jnp.asarray(np.random.default_rng(seed).normal(size=(T, 2, 2)) * 0.7)


def affine_maps(T, seed=1):
    rng = np.random.default_rng(seed)
    return {
        "A": jnp.asarray(0.6 * rng.normal(size=(T, 3, 3))),
        "c": jnp.asarray(rng.normal(size=(T, 3))),
    }


def both_scans(fn, elems, reverse=False):
    """jaxest's and lax's associative scans of ``elems`` under ``fn``, in one compiled program."""
    scans = (scan.associative_scan, jax.lax.associative_scan)
    return jax.jit(lambda e: tuple(s(jax.vmap(fn), e, reverse=reverse) for s in scans))(elems)


def assert_same(actual, desired):
    for a, d in zip(jax.tree.leaves(actual), jax.tree.leaves(desired), strict=True):
        d = np.asarray(d)
        np.testing.assert_allclose(a, d, rtol=1e-12, atol=1e-12 * np.max(np.abs(d)))


@pytest.mark.parametrize("reverse", [False, True], ids=["forward", "reverse"])
@pytest.mark.parametrize("T", LENGTHS)
def test_equals_lax_associative_scan(T, reverse):
    ours = {}
    for fn, elems in ((matmul, matrices(T)), (affine, affine_maps(T))):
        ours[fn], theirs = both_scans(fn, elems, reverse)
        assert_same(ours[fn], theirs)
    # and the sequential products themselves (the operation is not commutative)
    m = np.asarray(matrices(T))
    prefix = np.eye(2)
    for k in range(T) if not reverse else range(T - 1, -1, -1):
        prefix = m[k] @ prefix
    last = ours[matmul][-1 if not reverse else 0]
    np.testing.assert_allclose(last, prefix, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("chunks", [2, 16, 1000])
def test_step_width_does_not_change_the_result(monkeypatch, chunks):
    """Few wide steps (as on accelerators) or many narrow ones: the same combinations."""
    monkeypatch.setattr(scan, "CHUNKS", chunks)
    for T in (5, 100, 1000):
        for reverse in (False, True):
            assert_same(*both_scans(affine, affine_maps(T), reverse))


@pytest.mark.parametrize("T", [2, 3, 100, 1000, 100_000])
def test_schedule_is_the_brent_kung_tree_in_few_steps(T):
    """Every combination of eqs (1)-(2) exactly once, the unused lanes dropped, and at most
    2 CHUNKS + 2 log2 T steps (O(log T) depth)."""
    C = scan.lanes(T)
    steps = scan.schedule(T, C)
    used = steps[:, 2] < T
    pairs = sorted(zip(steps[:, 0][used].tolist(), steps[:, 1][used].tolist(), strict=True))
    expected = []
    for d in range(int(math.log2(T)) + 1):
        expected += [(j - 2**d, j) for j in range(2 ** (d + 1) - 1, T, 2 ** (d + 1))]
        expected += [(j - 2**d, j) for j in range(3 * 2**d - 1, T, 2 ** (d + 1))]
    assert pairs == sorted(expected)
    assert np.all(steps[:, 2][~used] == T)
    assert np.all(steps[:, 1] == np.where(used, steps[:, 2], steps[:, 1]))
    assert steps.shape[0] <= 2 * scan.CHUNKS + 2 * math.ceil(math.log2(T))
    for left, _, out in steps:  # a step writes each place once, and none that it reads
        written = out[out < T].tolist()
        assert len(set(written)) == len(written)
        assert not set(written) & set(left.tolist())


def test_vmap_and_grad_equal_lax():
    elems = affine_maps(37)
    batch = jax.tree.map(lambda a: jnp.stack([a, 2 * a]), elems)
    ours = jax.jit(jax.vmap(lambda e: scan.associative_scan(jax.vmap(affine), e)))(batch)
    theirs = jax.jit(jax.vmap(lambda e: jax.lax.associative_scan(jax.vmap(affine), e)))(batch)
    assert_same(ours, theirs)

    def loss(scan_fn, e):
        out = scan_fn(jax.vmap(affine), e, reverse=True)
        return jnp.sum(out["c"] ** 2) + jnp.sum(jnp.sin(out["A"]))

    assert_same(jax.jit(jax.grad(lambda e: loss(scan.associative_scan, e)))(elems),
                jax.jit(jax.grad(lambda e: loss(jax.lax.associative_scan, e)))(elems))  # fmt: skip


def test_lane_sweep_picks_the_width_fastest_relative_to_the_best():
    """``benchmarks/scan_lanes.py``: each configuration's times are divided by its fastest, so a
    slow configuration does not outvote the others, and the width with the least mean wins."""
    scan_lanes = benchmark_scripts.load("scan_lanes")
    times = {  # (n, T): run seconds for T / C = 16, 256; lax rows (chunks None) are ignored
        (4, 10_000): (2.0, 1.0),
        (20, 10_000): (2.0, 1.0),
        (20, 100_000): (100.0, 110.0),  # summed seconds would pick 16
    }
    rows = [
        {"n": n, "T": T, "dtype": "float32", "method": "parallel_sqrt", "chunks": c, "run_s": t}
        for (n, T), pair in times.items()
        for c, t in zip((16, 256), pair, strict=True)
    ]
    rows.append({**rows[0], "chunks": None, "run_s": 0.1})
    best, means = scan_lanes.best_chunks(rows)
    assert best == 256
    assert means[16] == pytest.approx((2.0 + 2.0 + 1.0) / 3)
    assert means[256] == pytest.approx((1.0 + 1.0 + 1.1) / 3)


def test_leaves_of_other_lengths_are_named():
    """Leaves with leading axes of 5 and 6 raised a reshape's TypeError from inside the scan."""
    elems = (jnp.ones(5), jnp.ones(6))
    with pytest.raises(
        ValueError, match=r"^elems: every leaf needs the same leading axis.*\[5, 6\]"
    ):
        scan.associative_scan(lambda a, b: (a[0] + b[0], a[1] + b[1]), elems)
    with pytest.raises(ValueError, match=r"^elems: .*\[5, None\]"):
        scan.associative_scan(lambda a, b: (a[0] + b[0], a[1]), (jnp.ones(5), jnp.ones(())))
