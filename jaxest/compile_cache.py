"""JAX's persistent compilation cache, one directory per host processor.

An XLA:CPU executable is machine code for the processor it was compiled on, and JAX's cache key
(jax 0.10) names the platform ("cpu") but not the processor: a cache in a home directory shared
by several machines (CI hosts, cluster nodes) can hand one machine's code to another, which
jaxlib 0.10 checks only in part and which can crash the process. :func:`cache_dir` therefore
adds a directory named after the processor (its model and instruction-set flags) and the
jax/jaxlib versions under ``$XDG_CACHE_HOME/jaxest/jax`` (default ``~/.cache/jaxest/jax``).
``JAX_COMPILATION_CACHE_DIR``, where set, is used as it is.
"""

from __future__ import annotations

import hashlib
import os
import platform
from pathlib import Path

#: programs that compile faster than this are not written to the cache
MIN_COMPILE_SECONDS = 0.2


def _processor_description() -> str:
    """The processor's model and instruction-set flags (Linux), else what ``platform`` says."""
    try:
        cpuinfo = Path("/proc/cpuinfo").read_text()
    except OSError:
        return f"{platform.machine()} {platform.processor()}"
    wanted = ("model name", "flags", "Features", "CPU part")  # x86 and ARM spellings
    lines = {}
    for line in cpuinfo.splitlines():
        key, _, value = line.partition(":")
        key = key.strip()
        if key in wanted and key not in lines:
            lines[key] = " ".join(sorted(value.split())) if key in ("flags", "Features") else value
    return f"{platform.machine()} " + " | ".join(f"{k}: {lines[k]}" for k in sorted(lines))


def host_key() -> str:
    """A short name for this processor and jax/jaxlib version, e.g. ``x86_64-0.10.2-3f9a…``."""
    import jax
    import jaxlib

    text = f"{_processor_description()} jax {jax.__version__} jaxlib {jaxlib.__version__}"
    digest = hashlib.sha256(text.encode()).hexdigest()[:12]
    return f"{platform.machine()}-{jax.__version__}-{digest}"


def cache_dir() -> Path:
    """``$JAX_COMPILATION_CACHE_DIR`` where set, else
    ``$XDG_CACHE_HOME/jaxest/jax/<host_key()>`` (``~/.cache`` without XDG_CACHE_HOME)."""
    explicit = os.environ.get("JAX_COMPILATION_CACHE_DIR")
    if explicit:
        return Path(explicit)
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "jaxest" / "jax" / host_key()


def enable() -> Path:
    """Turn the cache on in this process and in the processes it starts (through the
    environment: notebooks, subprocesses of tests); returns the directory."""
    import jax

    path = cache_dir()
    os.environ["JAX_COMPILATION_CACHE_DIR"] = str(path)
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", str(MIN_COMPILE_SECONDS))
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update(
        "jax_persistent_cache_min_compile_time_secs",
        float(os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"]),
    )
    return path
