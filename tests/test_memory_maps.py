"""The warning before XLA:CPU's compiled programs exhaust the process's memory mappings
(jaxest.memory_maps)."""

import warnings

import jax
import jax.numpy as jnp
import pytest

from jaxest import memory_maps

COMPILE = "/jax/core/compile/backend_compile_duration"

pytestmark = pytest.mark.skipif(
    memory_maps.count() is None or memory_maps.limit() is None,
    reason="the mappings and their limit are read from /proc (Linux)",
)


def test_counts_grow_with_the_programs_kept_and_the_limit_is_read():
    before = memory_maps.count()
    kept = [jax.jit(lambda x, i=i: jnp.sin(x) * i) for i in range(1, 6)]
    for program in kept:
        program(jnp.ones(3)).block_until_ready()
    assert memory_maps.count() >= before + 5  # each compiled program holds mappings of its own
    assert memory_maps.limit() > 1000


def test_warns_once_past_the_level_then_again_after_falling_below():
    now = memory_maps.count()
    watch = memory_maps._Watch(most=now)  # the process is already at its "limit"
    with pytest.warns(RuntimeWarning, match=rf"holds \d+ memory mappings of the {now}"):
        watch(COMPILE, 0.1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        watch("/jax/core/compile/jaxpr_trace_duration", 0.1)  # other events: not counted
        for _ in range(3 * memory_maps.COUNT_EVERY_AFTER_WARNING):
            watch(COMPILE, 0.1)  # still past the level: said once
        watch.most, watch.warn_at = 10**9, 10**8  # far below the level: re-armed
        watch.compiles_to_skip = 0
        watch(COMPILE, 0.1)
    # far below, counts are spaced by what a program may add (the count moves a little)
    spacing = (watch.warn_at - now) // memory_maps.MOST_PER_PROGRAM
    assert spacing > 0 and abs(watch.compiles_to_skip - spacing) <= 1
    watch.warn_at, watch.compiles_to_skip = 0, 0
    with pytest.warns(RuntimeWarning, match="jax.clear_caches"):
        watch(COMPILE, 0.1)


def test_importing_jaxest_watches_every_compile():
    import jaxest  # noqa: F401  (watch() ran on import)

    watch = memory_maps._watch
    assert watch is not None and memory_maps.watch()  # once per process
    saved = watch.warn_at, watch.warned, watch.compiles_to_skip
    watch.warn_at, watch.warned, watch.compiles_to_skip = 0, False, 0
    try:
        with pytest.warns(RuntimeWarning, match="vm.max_map_count"):
            jax.jit(lambda x: jnp.cos(x) * 3.25)(jnp.ones(4)).block_until_ready()
    finally:
        watch.warn_at, watch.warned, watch.compiles_to_skip = saved
