"""XLA:CPU compiler flags that shorten compilation where compiling, not running, takes the time.

On a CPU most of the time of jaxest's test suite and of a notebook is XLA compiling: estimators on
small matrices are unrolled element-wise code (``jaxest.linalg``), so a filter step is hundreds of
small fusions and its gradient twice as many. Three flags of the pinned jaxlib (0.10) cut that:

- :data:`FASTER_COMPILATION`, ``--xla_cpu_use_fusion_emitters=false``: each element-wise fusion
  goes straight to LLVM IR instead of through XLA's MLIR fusion pipeline. Compiling takes about
  half as long, and what it compiles runs as fast (the studies' results agree to rounding), so
  ``python -m jaxest reproduce`` uses it.
- :data:`UNOPTIMISED_MACHINE_CODE`, ``--xla_backend_optimization_level=0``: LLVM does not
  optimise, compiling faster again and running slower; for the test suite.
- :data:`SERIAL_CODEGEN`, ``--xla_cpu_parallel_codegen_split_count=1``: XLA:CPU otherwise
  splits each program's LLVM module into parts compiled on its thread pool. Where every core
  already runs a process of its own (the test suite's two workers) the split only adds work;
  one part compiles in less CPU time. On an idle machine the split is faster in wall time, so
  ``reproduce`` uses it only for the studies it runs beside another (``--jobs``).

docs/performance.md ("XLA flags that compile faster") has the measurements.

:func:`cpu_devices` (``--xla_force_host_platform_device_count``) is not about compiling: it
gives the process one CPU device per core, over which a study can shard its runs
(``reproduce --jobs N`` gives it to the smf-fdi study's process, which runs alone).

Options for one program rather than the process go to ``jax.jit(..., compiler_options=...)``
through :func:`compile_options`: :data:`NO_YNN_FUSION`, which :func:`jaxest.vmap_minor` uses.

XLA reads ``XLA_FLAGS`` once, when JAX starts its CPU backend (the first computation), and an
XLA that does not know a flag aborts the process. So :func:`add` changes nothing on a jaxlib
other than the ones measured (:data:`MEASURED_JAXLIB`), never overrides a flag already in
``XLA_FLAGS``, and has to run before the first computation to reach this process (it always
reaches the processes this one starts, which inherit the environment).
"""

from __future__ import annotations

import os
from collections.abc import MutableMapping

import jaxlib

__all__ = [
    "MEASURED_JAXLIB", "FASTER_COMPILATION", "UNOPTIMISED_MACHINE_CODE", "SERIAL_CODEGEN",
    "OPTIMISED_MACHINE_CODE", "add", "current", "NO_YNN_FUSION", "compile_options",
    "cpu_devices",
]  # fmt: skip

#: the jaxlib release series whose XLA knows these flags and on which they were measured
MEASURED_JAXLIB = "0.10."
#: element-wise fusions straight to LLVM IR: about half the compile time, code as fast
FASTER_COMPILATION = ("--xla_cpu_use_fusion_emitters=false",)
#: no LLVM optimisation: faster compiling again, slower code (the test suite's)
UNOPTIMISED_MACHINE_CODE = ("--xla_backend_optimization_level=0",)
#: each program's LLVM module compiled in one piece, where every core runs a process of its own
SERIAL_CODEGEN = ("--xla_cpu_parallel_codegen_split_count=1",)
#: ``jax.jit(f, compiler_options=OPTIMISED_MACHINE_CODE)`` undoes :data:`UNOPTIMISED_MACHINE_CODE`
#: for one program, where it runs far longer than it compiles (in the test suite: the particle
#: filter's stochastic-gradient fit, first call 11.1 s at level 0, 2.6 s at level 2).
OPTIMISED_MACHINE_CODE = {"xla_backend_optimization_level": 2}


def add(
    flags: tuple[str, ...], environment: MutableMapping[str, str] | None = None
) -> tuple[str, ...]:
    """Append ``flags`` (``--name=value`` each) to ``XLA_FLAGS`` in ``environment`` (default: this
    process's, ``os.environ``; a copy of it for a process about to be started), except those whose
    name ``XLA_FLAGS`` already sets; returns the flags added. Adds nothing on a jaxlib outside
    :data:`MEASURED_JAXLIB`."""
    for flag in flags:
        if not (flag.startswith("--") and "=" in flag):
            raise ValueError(f"flags: {flag!r} is not of the form --name=value")
    if not _measured_jaxlib():
        return ()
    environment = os.environ if environment is None else environment
    present = environment.get("XLA_FLAGS", "").split()
    names_present = {_name(item) for item in present}
    added = tuple(flag for flag in flags if _name(flag) not in names_present)
    if added:
        environment["XLA_FLAGS"] = " ".join([*present, *added])
    return added


def cpu_devices(count: int | None = None) -> tuple[str, ...]:
    """XLA's CPU client with ``count`` devices (default: one per core of this machine;
    ``jax.devices()`` lists them): a program whose batch is sharded over them runs each shard on
    a core of its own. Without it the CPU is one device, and a batched program (a Monte Carlo's
    ``vmap``) mostly runs on one core: XLA splits only large operations over its thread pool."""
    return (f"--xla_force_host_platform_device_count={count or os.cpu_count() or 1}",)


def current() -> str:
    """``XLA_FLAGS`` as this process holds it ("" where unset): what the studies' index and the
    benchmarks' JSON record beside their times."""
    return os.environ.get("XLA_FLAGS", "")


def _name(flag: str) -> str:
    """``--name`` of ``--name=value``."""
    return flag.split("=", 1)[0]


#: ``jax.jit(f, compiler_options=compile_options(NO_YNN_FUSION))``: XLA:CPU hands no fusion of
#: ``f`` to YNNPACK. It takes every fusion with 4 096 elements or more; on the batch-minor arrays
#: of :func:`jaxest.vmap_minor` those are the contractions, which YNNPACK ran 2.4-3x slower than
#: XLA's own loops (docs/performance.md).
NO_YNN_FUSION = {"xla_cpu_experimental_ynn_fusion_type": ""}


def compile_options(options: dict) -> dict | None:
    """``options`` for ``jax.jit(..., compiler_options=...)`` where the running jaxlib is one
    they were measured on (:data:`MEASURED_JAXLIB`; an XLA that does not know an option rejects
    the program), else ``None``."""
    return dict(options) if _measured_jaxlib() else None


def _measured_jaxlib() -> bool:
    """Whether the running jaxlib is of :data:`MEASURED_JAXLIB`."""
    return jaxlib.__version__.startswith(MEASURED_JAXLIB)
