"""What a traced program asks of XLA, read from its lowered or compiled text."""

import re

import jax


def dot_precisions(fn, *args) -> list[str]:
    """The precision of every matrix product in ``jax.jit(fn)``'s lowered program ("" where it
    carries none)."""
    lines = [
        line for line in jax.jit(fn).lower(*args).as_text().splitlines() if "dot_general" in line
    ]
    return [m[1] if (m := re.search(r"precision = \[(\w+), \w+\]", line)) else "" for line in lines]


def custom_call_targets(compiled_text: str) -> list[str]:
    """The library kernels a compiled program calls (``custom_call_target``), one per call."""
    return re.findall(r'custom_call_target="([^"]+)"', compiled_text)


def fusion_kinds(compiled_text: str) -> set[str]:
    """The kinds of a compiled program's backend fusions (``"__ynn_fusion"``: YNNPACK's)."""
    return set(re.findall(r'"fusion_config":\{"kind":"([^"]+)"', compiled_text))


#: the monitoring event JAX records once for every program XLA compiles
BACKEND_COMPILE = "/jax/core/compile/backend_compile_duration"


def programs_compiled(fn, *args) -> int:
    """How many XLA programs ``fn(*args)`` compiles, its result awaited: one per operation for
    code that runs op by op outside ``jit``, one per jitted function otherwise."""
    events = []

    def record(event, seconds, **kwargs):
        if event == BACKEND_COMPILE:
            events.append(seconds)

    jax.monitoring.register_event_duration_secs_listener(record)
    try:
        jax.block_until_ready(fn(*args))
    finally:
        jax.monitoring.unregister_event_duration_listener(record)
    return len(events)
