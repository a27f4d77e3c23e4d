"""JAX's persistent compilation cache, one directory per host processor; off unless asked for.

Off by default: writing a cache entry serialises the compiled executable, and on jaxlib 0.10
that serialisation (``executable.serialize()`` in ``compilation_cache.put_executable_and_time``)
crashed the process with a segmentation fault, at random, in two full test-suite runs on 2-core
CPUs (CI, and a clean clone here: a different test each time, each of which passes when run
again). ``JAXEST_COMPILATION_CACHE=1`` turns it on (:func:`enable`), as does setting
``JAX_COMPILATION_CACHE_DIR``, which JAX itself reads.

An XLA:CPU executable is machine code for the processor it was compiled on, and JAX's cache key
(jax 0.10) names the platform ("cpu") but not the processor: a cache in a home directory shared
by several machines (CI hosts, cluster nodes) can hand one machine's code to another, which
jaxlib 0.10 checks only in part and which can crash the process. :func:`cache_dir` therefore
adds a directory named after the processor (its model and instruction-set flags) and the
jax/jaxlib versions under ``$XDG_CACHE_HOME/jaxest/jax`` (default ``~/.cache/jaxest/jax``).
``JAX_COMPILATION_CACHE_DIR``, where set, is used as it is.

Before the first use of a directory, :func:`probe` compiles a small program in one process and
reloads it in a second. Where the second process does not get a clean cache hit, the cache stays
off on that host: jaxlib 0.10 rejects every entry on some AVX-512 processors ("Target machine
feature +prefer-no-gather is not supported", jax issue #38445), so the cache would only cost time
there, and a rejected load has been seen to end in a segmentation fault. The verdict is kept in
the directory (``PROBE_FILE``).
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

__all__ = [
    "REQUEST", "MIN_COMPILE_SECONDS", "PROBE_FILE", "REJECTED", "host_key", "cache_dir",
    "run_probe_program", "probe", "enable",
]  # fmt: skip

#: the environment variable that asks for the cache
REQUEST = "JAXEST_COMPILATION_CACHE"
#: programs that compile faster than this are not written to the cache
MIN_COMPILE_SECONDS = 0.2
#: the probe's verdict in a cache directory: {"usable": bool, "reason": str}
PROBE_FILE = "jaxest-probe.json"
#: what jaxlib logs when it refuses a cached executable
REJECTED = "is not supported"

_PROBE_PROGRAM = textwrap.dedent(
    """
    import json, sys, time
    import jax, jax.numpy as jnp
    from jax import monitoring

    jax.config.update("jax_compilation_cache_dir", sys.argv[1])
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    hits = []
    monitoring.register_event_listener(
        lambda name, **kw: hits.append(1) if name == "/jax/compilation_cache/cache_hits" else None
    )

    @jax.jit
    def f(x):
        return jax.lax.scan(lambda c, a: (jnp.sin(c) * a + c, c), x, jnp.arange(64.0))[0]

    t = time.perf_counter()
    f(jnp.ones(8)).block_until_ready()
    print(json.dumps({"hits": len(hits), "first_call_s": time.perf_counter() - t}))
    """
)


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


def run_probe_program(directory: Path) -> tuple[dict, str, int]:
    """Run the probe's small jitted scan in a fresh process with its cache in ``directory``:
    ``({"hits": ..., "first_call_s": ...}, stderr, returncode)`` (the dict empty on a crash)."""
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    proc = subprocess.run(
        [sys.executable, "-c", _PROBE_PROGRAM, str(directory)],
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )
    try:
        result = json.loads(proc.stdout.strip().splitlines()[-1])
    except (IndexError, json.JSONDecodeError):
        result = {}
    return result, proc.stderr, proc.returncode


def probe() -> dict:
    """Whether this host reloads what it compiled: the probe program twice on an empty
    directory; usable when the second run hits the cache, exits cleanly and logs no rejection."""
    with tempfile.TemporaryDirectory() as directory:
        cold, _, cold_rc = run_probe_program(Path(directory))
        warm, log, warm_rc = run_probe_program(Path(directory))
    if cold_rc or warm_rc:
        return {"usable": False, "reason": f"probe exited with {cold_rc} / {warm_rc}"}
    rejected = [line for line in log.splitlines() if REJECTED in line]
    if rejected:
        return {"usable": False, "reason": rejected[0].strip()}
    if warm.get("hits", 0) < 1:
        return {"usable": False, "reason": "the second process did not hit the cache"}
    return {"usable": True, "reason": f"reloaded in {warm['first_call_s']:.3f} s"}


def _verdict(path: Path) -> dict:
    """The probe's verdict for ``path``, run once and kept there (written atomically)."""
    record = path / PROBE_FILE
    try:
        return json.loads(record.read_text())
    except (OSError, json.JSONDecodeError):
        pass
    verdict = probe()
    path.mkdir(parents=True, exist_ok=True)
    partial = path / f"{PROBE_FILE}.{os.getpid()}"
    partial.write_text(json.dumps(verdict))
    partial.replace(record)
    return verdict


def enable() -> Path | None:
    """Turn the cache on, where ``JAXEST_COMPILATION_CACHE=1`` asks for it and the probe found
    it usable, in this process and in the processes it starts (through the environment:
    notebooks, subprocesses of tests); returns the directory, or None where the cache stays off.
    An explicit ``JAX_COMPILATION_CACHE_DIR`` is used without a probe."""
    import jax

    explicit = "JAX_COMPILATION_CACHE_DIR" in os.environ
    if not explicit and os.environ.get(REQUEST) != "1":
        return None
    path = cache_dir()
    if not explicit and not _verdict(path)["usable"]:
        return None
    os.environ["JAX_COMPILATION_CACHE_DIR"] = str(path)
    min_seconds = os.environ.setdefault(
        "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", str(MIN_COMPILE_SECONDS)
    )
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_seconds))
    return path
