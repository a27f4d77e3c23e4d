"""The benchmark scripts (``benchmarks/*.py``, not a package) loaded as modules for their tests."""

import importlib.util
import sys
from pathlib import Path

BENCHMARKS = Path(__file__).parent.parent / "benchmarks"


def load(name: str):
    """``benchmarks/<name>.py`` as the module ``name``, registered in ``sys.modules`` (equinox
    Modules defined in it look their module up)."""
    spec = importlib.util.spec_from_file_location(name, BENCHMARKS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module
