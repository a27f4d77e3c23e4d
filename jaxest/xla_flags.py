"""XLA:CPU compiler flags that shorten compilation where compiling, not running, takes the time.

Most of the time in jaxest's test suite and studies on a CPU is XLA compiling, not running:
estimators on small matrices are written as unrolled element-wise code (``jaxest.linalg``), so
one filter step is hundreds of small fusions, and a gradient doubles them. Two flags of the
jaxlib this package pins (0.10) cut that time:

- :data:`FASTER_COMPILATION`, ``--xla_cpu_use_fusion_emitters=false``: XLA:CPU emits each
  element-wise fusion directly to LLVM IR instead of through its MLIR fusion pipeline. Measured
  on a 2-core CPU: ``jit(value_and_grad)`` of the 4-state EKF log-likelihood compiles in 2.5 s
  instead of 4.1 s (its forward pass 0.54 s instead of 1.11 s); across
  ``benchmarks/speed.py`` compile times fall by 10-55 %. The code it generates is not always
  as fast: 6 of those 16 rows ran slower per step (the set-membership filter on one sequence by
  40 %), and the full ``filters`` and ``adaptive`` studies, which run more than they compile,
  took 359-368 s against 319-347 s. So it pays where compiling dominates (the test suite,
  notebooks, small problems), and ``python -m jaxest reproduce`` does not use it.
- :data:`UNOPTIMISED_MACHINE_CODE`, ``--xla_backend_optimization_level=0``: LLVM generates code
  without optimising it. It compiles faster again (the EKF gradient above in 1.5 s) but the
  code runs slower, so only the test suite, which compiles far more than it runs, uses it.

XLA reads ``XLA_FLAGS`` once, when JAX starts its CPU backend (the first computation), and an
XLA that does not know a flag aborts the process. So :func:`add` changes nothing on a jaxlib
other than the ones measured (:data:`MEASURED_JAXLIB`), never overrides a flag already in
``XLA_FLAGS``, and has to run before the first computation to reach this process (it always
reaches the processes this one starts, which inherit the environment).
"""

from __future__ import annotations

import os

#: the jaxlib release series whose XLA knows these flags and on which they were measured
MEASURED_JAXLIB = "0.10."
FASTER_COMPILATION = ("--xla_cpu_use_fusion_emitters=false",)
UNOPTIMISED_MACHINE_CODE = ("--xla_backend_optimization_level=0",)


def add(flags: tuple[str, ...]) -> tuple[str, ...]:
    """Append ``flags`` (``--name=value`` each) to ``XLA_FLAGS`` in this process's environment,
    except those whose name ``XLA_FLAGS`` already sets; returns the flags added. Adds nothing
    on a jaxlib outside :data:`MEASURED_JAXLIB`."""
    import jaxlib

    for flag in flags:
        if not (flag.startswith("--") and "=" in flag):
            raise ValueError(f"flags: {flag!r} is not of the form --name=value")
    if not jaxlib.__version__.startswith(MEASURED_JAXLIB):
        return ()
    present = os.environ.get("XLA_FLAGS", "").split()
    names_present = {item.split("=", 1)[0] for item in present}
    added = tuple(flag for flag in flags if flag.split("=", 1)[0] not in names_present)
    if added:
        os.environ["XLA_FLAGS"] = " ".join([*present, *added])
    return added
