"""XLA's operations from a ``jax.profiler`` trace, for the profile scripts (not a benchmark).

On the CPU each operation of a compiled program runs as one thunk, and the trace has an event
per thunk run: a fusion, a copy, a library call. It also has the runtime's own spans and, for a
loop, an event whose length depends on how XLA runs it (from its set-up alone to the whole
loop). So :func:`traced_operations` counts only the program's own instructions, less control
flow. Importing this module adds ``--xla_cpu_enable_xprof_traceme=true`` to ``XLA_FLAGS``
(before jax starts its backend: import it before anything is computed), which some XLA:CPU
versions need to report their thunks. The profiler itself slows the run, so read the shares,
not the absolute times.
"""

from __future__ import annotations

import collections
import gzip
import json
import os
import re
import tempfile
from pathlib import Path

from jaxest import xla_flags

# set directly, not by xla_flags.add, which adds only on the jaxlib its flags were measured on
os.environ["XLA_FLAGS"] = f"{xla_flags.current()} --xla_cpu_enable_xprof_traceme=true".strip()

import jax  # noqa: E402

#: operations whose trace events contain other operations' events, or none of their own work
CONTROL_FLOW = ("while", "conditional", "call", "tuple", "get-tuple-element", "parameter")


def instructions(compiled_text: str) -> dict[str, str]:
    """{name: what it runs} of a compiled program's instructions, named as their thunks are in a
    trace: a custom call's library kernel (``lapack_dgesdd_ffi`` is LAPACK's SVD on the CPU),
    else the opcode (``fusion``, ``copy``, ``while`` ...)."""
    found = {}
    for line in compiled_text.splitlines():
        match = re.match(r"\s*(?:ROOT\s+)?%?([\w.\-]+) = (.*)", line)
        if match is None:
            continue
        name, rest = match.groups()
        opcode = re.match(r"\s*\S*?\s*([\w\-]+)\(", _after_tuple_type(rest))
        if opcode is None:
            continue
        target = re.search(r'custom_call_target="([^"]+)"', rest)
        found[name] = target[1] if target else opcode[1]
    return found


def _after_tuple_type(rest: str) -> str:
    """``rest`` of an instruction's line after its type where that is a tuple, ``(f64[2], ...)``."""
    depth = 0
    for i, char in enumerate(rest if rest.startswith("(") else ""):
        depth += {"(": 1, ")": -1}.get(char, 0)
        if depth == 0:
            return rest[i + 1 :]
    return rest


def operation_times(trace_dir: Path, operations) -> tuple[collections.Counter, collections.Counter]:
    """(total microseconds, number of events) per operation named in ``operations`` in the
    perfetto trace."""
    (trace,) = trace_dir.rglob("*.trace.json.gz")
    events = json.loads(gzip.decompress(trace.read_bytes()))
    events = events["traceEvents"] if isinstance(events, dict) else events
    total, calls = collections.Counter(), collections.Counter()
    for event in events:
        name = event.get("name", "")
        if event.get("ph") == "X" and name in operations:
            total[name] += event.get("dur", 0)
            calls[name] += 1
    return total, calls


def traced_operations(call, compiled_text: str):
    """(total microseconds, number of events, :func:`instructions`) of the operations of one
    ``call()`` of the compiled program whose text is ``compiled_text`` (warmed up), control flow
    left out; its result awaited."""
    ops = instructions(compiled_text)
    leaves = {name for name, kind in ops.items() if kind not in CONTROL_FLOW}
    with tempfile.TemporaryDirectory() as trace_dir:
        jax.profiler.start_trace(trace_dir, create_perfetto_trace=True)
        jax.block_until_ready(call())
        jax.profiler.stop_trace()
        total, calls = operation_times(Path(trace_dir), leaves)
    return total, calls, ops
