"""Python's cyclic garbage collector, set for a process that traces and compiles far more than
it runs, such as the test suite.

Tracing a program to a jaxpr and lowering it allocate millions of short-lived container objects
(tracers, equations, MLIR attributes). At Python's default thresholds, (700, 10, 10), the
collector runs every 700 net allocations and, up to once every 100 runs, walks every object the
process holds, which in a test-suite worker that has imported jax, scipy and the reference
libraries is several million. In a full ``make test`` on the 2-core machine the two pytest-xdist
workers ran it 21 and 15 thousand times, for 31 and 23 s of their CPU; at :data:`FOR_TRACING` it
ran about 500 times, for 4 s each, and the suite took 334 instead of 392 s (user CPU 609 against
721 s), with the same peak memory (1.7 GB). The studies of ``python -m jaxest reproduce``, which
run more than they compile, gained within the noise (``reproduce filters network``: 79.0 and
86.4 s against 82.9 and 87.0 s), so they keep Python's default. docs/performance.md has the
measurements.

Reference counting still frees everything that is not in a reference cycle as soon as it is
dropped; only cycles wait longer. A library does not change its host's collector on import, so
this is opt-in: :func:`collect_rarely`.
"""

from __future__ import annotations

import gc

__all__ = ["FOR_TRACING", "collect_rarely"]

#: collector thresholds (generation 0, 1, 2): a young collection every 100 000 net allocations
#: instead of 700, a full one after 200 young ones instead of 100
FOR_TRACING = (100_000, 20, 10)


def collect_rarely() -> tuple[int, int, int]:
    """Set the collector's thresholds to :data:`FOR_TRACING`; returns the thresholds before."""
    before = gc.get_threshold()
    gc.set_threshold(*FOR_TRACING)
    return before
