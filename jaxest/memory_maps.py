"""A warning before XLA:CPU runs the process out of memory mappings.

Every program XLA:CPU compiles keeps its machine code in memory mappings of its own for as long
as the program lives (a jitted function's cache holds its programs until the function is dropped
or ``jax.clear_caches()`` runs). Linux allows a process ``vm.max_map_count`` mappings, 65 530 by
default; at the limit LLVM cannot place the next program's code (``LLVM ERROR: Unable to
allocate section memory!``) and the process dies. Measured with jaxlib 0.10 on the 2-core
machine (docs/performance.md): ``jit(value_and_grad(...))`` of a 6-state filter over a ``vmap``
of 4 runs holds about 640 mappings with XLA's default flags, 213 with
:data:`jaxest.xla_flags.FASTER_COMPILATION` and 120 with
:data:`~jaxest.xla_flags.SERIAL_CODEGEN` as well; with the default flags the process died with a
segmentation fault after about 100 such programs kept alive.

:func:`watch` (called when jaxest is imported) counts the process's mappings after XLA compiles
a program, at intervals that shrink as the count nears the limit, and warns (``RuntimeWarning``)
when it passes :data:`WARN_FRACTION` of the limit: once, until the count falls below it again.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import jax

__all__ = [
    "WARN_FRACTION", "MOST_PER_PROGRAM", "COUNT_EVERY_AFTER_WARNING", "count", "limit",
    "warning_message", "watch",
]  # fmt: skip

#: warn at this fraction of ``vm.max_map_count``
WARN_FRACTION = 0.8
#: mappings one program may add, for spacing the counts: a count is due once this many per
#: compile since the last could have reached the warning level (640 were measured)
MOST_PER_PROGRAM = 5_000
#: compiles between counts once the warning has been given
COUNT_EVERY_AFTER_WARNING = 10
_COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"


def count() -> int | None:
    """The process's memory mappings (lines of ``/proc/self/maps``); ``None`` where the system
    has no such file."""
    try:
        with open("/proc/self/maps", "rb") as maps:
            return maps.read().count(b"\n")
    except OSError:
        return None


def limit() -> int | None:
    """``vm.max_map_count``, the most mappings a process may hold; ``None`` where unknown."""
    try:
        return int(Path("/proc/sys/vm/max_map_count").read_text())
    except (OSError, ValueError):
        return None


def warning_message(mappings: int, most: int) -> str:
    return (
        f"this process holds {mappings} memory mappings of the {most} the system allows "
        "(vm.max_map_count). Each program XLA:CPU has compiled and still holds keeps its own, "
        "and at the limit the next compile kills the process (LLVM ERROR: Unable to allocate "
        "section memory!). Release compiled programs with jax.clear_caches() and by dropping "
        "jitted functions you no longer call, compile with fewer mappings per program "
        "(jaxest.xla_flags.FASTER_COMPILATION and SERIAL_CODEGEN, set before the first "
        "computation), or raise vm.max_map_count (docs/performance.md)."
    )


class _Watch:
    """A ``jax.monitoring`` listener: counts after compiles, warns past the level."""

    def __init__(self, most: int):
        self.most = most
        self.warn_at = int(WARN_FRACTION * most)
        self.compiles_to_skip = 0
        self.warned = False

    def __call__(self, event: str, seconds: float, **kwargs) -> None:
        if event != _COMPILE_EVENT:
            return
        if self.compiles_to_skip > 0:
            self.compiles_to_skip -= 1
            return
        mappings = count()  # readable: watch() started this listener only where it is
        if mappings < self.warn_at:
            self.warned = False
            self.compiles_to_skip = (self.warn_at - mappings) // MOST_PER_PROGRAM
            return
        if not self.warned:
            warnings.warn(warning_message(mappings, self.most), RuntimeWarning, stacklevel=2)
            self.warned = True
        self.compiles_to_skip = COUNT_EVERY_AFTER_WARNING


_watch: _Watch | None = None


def watch() -> bool:
    """Start counting (once per process); ``False`` where the mappings or their limit cannot be
    read (not Linux)."""
    global _watch
    if _watch is None:
        most = limit()
        if most is None or count() is None:
            return False
        _watch = _Watch(most)
        jax.monitoring.register_event_duration_secs_listener(_watch)
    return True
