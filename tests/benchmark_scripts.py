"""Scripts outside the package (``benchmarks/*.py``, ``docs/*.py``; not packages) loaded as
modules for their tests."""

import importlib.util
import sys
from pathlib import Path

BENCHMARKS = Path(__file__).parent.parent / "benchmarks"
DOCS = Path(__file__).parent.parent / "docs"


def load(name: str):
    """``benchmarks/<name>.py`` as the module ``name`` (:func:`load_file`)."""
    return load_file(BENCHMARKS / f"{name}.py")


def load_file(path: Path):
    """The script at ``path`` as a module named after it, registered in ``sys.modules``
    (equinox Modules defined in it look their module up). While it loads, its folder leads
    ``sys.path``, as when it is run: its imports of its siblings by name resolve."""
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[path.stem] = module
    sys.path.insert(0, str(path.parent))
    try:
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(path.parent))
    return module
