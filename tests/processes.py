"""The environment of a child Python process that a test starts on host CPU devices."""

import os
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def cpu_devices_env(count: int) -> dict[str, str]:
    """This process's environment for a child on ``count`` host CPU devices: the suite's XLA
    flags kept (tests/conftest.py), JAX on the CPU, and the repository importable (``tests.``)."""
    env = dict(os.environ)
    flags = f"{env.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count={count}"
    env.update(
        XLA_FLAGS=flags.strip(),
        JAX_PLATFORMS="cpu",
        PYTHONPATH=str(ROOT) + os.pathsep + env.get("PYTHONPATH", ""),
    )
    return env
