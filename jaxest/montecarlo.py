"""Batched Monte Carlo studies: one ``vmap`` per chunk, chunks in a ``lax.map``, runs sharded over
the devices of a ``jax.sharding.Mesh`` (and over hosts after ``jax.distributed.initialize()``).

Run i always receives ``jax.random.split(key, num_runs)[i]``, whatever the chunk size, device
count or host count, so a study is reproducible from one key and gives the same numbers on one
device and on many.

Compiled once per ``run_fn``: the batched program is cached on the function object (and, for an
``eqx.Module`` run function, on its structure, its arrays being inputs), so a study that calls
:func:`monte_carlo` again with the same ``run_fn`` -- e.g. another seed, or a Module holding a
different noise level -- reuses the compilation.

jaxlib 0.10 on CPU: two batched LAPACK calls (``solve``, ``cholesky``, ``svd``, ``eigh``...) that
run at once with more than about 2e5 flops of batch each can deadlock XLA's CPU thread pool. If a
run function with several independent small-matrix factorisations hangs, lower ``chunk_size``
(fewer runs per batched call) or write the small factorisations in plain ``jnp``.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from jaxest._checks import check_callable, check_key, check_positive_int, is_concrete
from jaxest.batching import COMPILER_OPTIONS, jit_with_options_at_top_level, vmap_minor

RUNS_AXIS = "runs"


def default_mesh() -> Mesh | None:
    """A 1-D mesh over every device (all hosts), or ``None`` when there is only one."""
    devices = jax.devices()
    return Mesh(np.array(devices), (RUNS_AXIS,)) if len(devices) > 1 else None


def monte_carlo(
    run_fn: Callable,
    key,
    num_runs: int,
    *,
    chunk_size: int | None = None,
    mesh: Mesh | None | str = "auto",
    batching: str = "vmap",
):
    """Evaluate ``run_fn(key_i)`` for ``num_runs`` independent keys and stack the outputs.

    Args:
        run_fn: one Monte Carlo run, ``key -> pytree of arrays``; pure and traceable.
        key: the study's PRNG key.
        num_runs: number of runs N.
        chunk_size: runs vectorised together on each device (bounds peak memory at about
            chunk_size runs' intermediates per device); ``None``: all runs at once. Each device
            then computes the same batch shape whatever the device count, so results agree on
            one device and on many to rounding (bitwise where XLA compiles the per-device
            program alike; fused small-matrix arithmetic can differ in the last bits).
        mesh: a 1-D ``Mesh`` whose axis shards the runs, ``None`` for one device, or ``"auto"``
            (every device when there are several).
        batching: how a chunk's runs are batched: ``"vmap"`` (``jax.vmap``) or ``"minor"``
            (:func:`jaxest.vmap_minor`, the runs on the minor axis of every array: faster for
            filters on small matrices on the CPU, docs/performance.md; the same results to
            rounding).

    Returns the outputs with a leading axis of length N (on every host).

    A typed key of any implementation works. With the ``rbg`` and ``unsafe_rbg`` ones, JAX's
    draws under ``vmap`` are not those of the same key unbatched, so the results then depend on
    ``chunk_size`` (``chunk_size=1`` gives a loop's) and agree with a loop only in distribution;
    the default ``threefry2x32`` draws the same numbers either way.

    On one process it runs inside ``jit``, ``vmap`` and ``grad`` too (e.g. a jitted gradient
    step of a study's mean loss); across processes it gathers the outputs on the hosts, so it is
    called outside ``jit`` with a concrete key.
    """
    check_callable("run_fn", run_fn)
    check_key("key", key)
    check_positive_int("num_runs", num_runs)
    if batching not in _BATCHINGS:
        raise ValueError(f"batching: must be one of {sorted(_BATCHINGS)}, got {batching!r}")
    if chunk_size is not None:
        check_positive_int("chunk_size", chunk_size)
    if isinstance(mesh, str) and mesh == "auto":
        mesh = default_mesh()
    if not (mesh is None or isinstance(mesh, Mesh) and len(mesh.axis_names) == 1):
        raise ValueError(f"mesh: expected a 1-D jax.sharding.Mesh, None or 'auto', got {mesh!r}")
    num_runs, chunk_size = int(num_runs), chunk_size and int(chunk_size)
    num_devices = 1 if mesh is None else mesh.devices.size
    per_device = chunk_size or math.ceil(num_runs / num_devices)
    chunk = per_device * num_devices
    num_chunks = math.ceil(num_runs / chunk)

    across_processes = mesh is not None and jax.process_count() > 1
    if across_processes and not is_concrete(key):
        raise ValueError(
            "key: monte_carlo across processes gathers the results on every host, outside jit; "
            "call it with a concrete key, outside jit and vmap"
        )

    padded = _chunked_key_data(jax.random.split(key, num_runs), num_chunks, chunk)
    if mesh is not None:
        sharding = NamedSharding(mesh, PartitionSpec(None, mesh.axis_names[0]))
        if is_concrete(padded):
            host = np.asarray(padded)
            padded = jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])
        else:
            padded = jax.lax.with_sharding_constraint(padded, sharding)
    out = _BATCHINGS[batching](run_fn, padded, _key_impl(key))
    if across_processes:
        from jax.experimental import multihost_utils

        out = multihost_utils.process_allgather(out, tiled=True)
    return jax.tree.map(lambda a: a.reshape(num_chunks * chunk, *a.shape[2:])[:num_runs], out)


@functools.partial(jax.jit, static_argnums=(1, 2))
def _chunked_key_data(keys, num_chunks: int, chunk: int):
    """The keys' raw data, padded with copies of the last key to num_chunks * chunk runs and
    shaped (num_chunks, chunk, ...)."""
    raw = jax.random.key_data(keys) if _is_typed(keys) else keys
    raw = jnp.concatenate([raw, jnp.repeat(raw[-1:], num_chunks * chunk - raw.shape[0], 0)])
    return raw.reshape(num_chunks, chunk, *raw.shape[1:])


def _all_chunks(run_fn: Callable, raw_keys, impl, *, batch: Callable):
    """Every run: a ``lax.map`` over chunks of a ``batch`` (``jax.vmap`` or ``vmap_minor``)
    over the runs of a chunk; ``impl``: the typed key's implementation (``None`` for raw keys)."""
    chunk_keys = raw_keys if impl is None else jax.random.wrap_key_data(raw_keys, impl=impl)
    return jax.lax.map(batch(run_fn), chunk_keys)


#: the compiled program of each batching
_BATCHINGS = {
    "vmap": eqx.filter_jit(functools.partial(_all_chunks, batch=jax.vmap)),
    "minor": jit_with_options_at_top_level(
        eqx.filter_jit, functools.partial(_all_chunks, batch=vmap_minor), COMPILER_OPTIONS
    ),
}


def _is_typed(keys) -> bool:
    return jnp.issubdtype(keys.dtype, jax.dtypes.prng_key)


def _key_impl(key):
    """A typed key's implementation (any PRNG: threefry, rbg, ...), ``None`` for a raw key."""
    return jax.random.key_impl(key) if _is_typed(key) else None
