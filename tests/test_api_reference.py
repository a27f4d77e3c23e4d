"""The API reference (docs/api/*.md, mkdocstrings) lists what each documented module's
``__all__`` names; every public object a package gathers, or a module defines, must be in it,
or it is missing from the site. (The top-level ``__all__`` was lost once and the page showed one
function.)"""

import ast
import importlib
import pkgutil
import types
from pathlib import Path

import pytest

import jaxest.systems
from tests import benchmark_scripts

#: docs/api_pages.py, which the site's Griffe extension reads too
API_PAGES = benchmark_scripts.load_file(benchmark_scripts.DOCS / "api_pages.py")
#: public names deliberately left out of the reference
UNDOCUMENTED = {"jaxest": {"filter"}}  # the deprecated alias of run


def documented_modules() -> list[str]:
    return sorted(API_PAGES.documented_modules())


def test_every_api_page_has_a_module():
    modules = documented_modules()
    assert "jaxest" in modules and len(modules) == len(set(modules)) == 20
    # every example system and every process setting has its section
    systems = {
        f"jaxest.systems.{info.name}"
        for info in pkgutil.iter_modules(jaxest.systems.__path__)
        if not info.name.startswith("_")
    }
    settings = {"jaxest.xla_flags", "jaxest.compile_cache", "jaxest.gc_thresholds"}
    assert systems | settings | {"jaxest.memory_maps"} <= set(modules)


@pytest.mark.parametrize("name", documented_modules())
def test_all_names_every_public_object(name):
    module = importlib.import_module(name)
    if hasattr(module, "__path__"):  # a package: what it gathers from jaxest's modules
        public = {
            key for key, value in vars(module).items()
            if not key.startswith("_") and not isinstance(value, types.ModuleType)
            and (getattr(value, "__module__", name) or "").startswith("jaxest")
        }  # fmt: skip
    else:  # a module: what it defines (not what it imports)
        public = {key for key in defined_names(module) if not key.startswith("_")}
    assert set(module.__all__) == public - UNDOCUMENTED.get(name, set())


def defined_names(module) -> set[str]:
    """Names a module's top level binds by ``def``, ``class`` or assignment."""
    names = set()
    for node in ast.parse(Path(module.__file__).read_text()).body:
        if isinstance(node, ast.FunctionDef | ast.ClassDef):
            names.add(node.name)
        for target in assignment_targets(node):
            names |= {n.id for n in ast.walk(target) if isinstance(n, ast.Name)}
    return names


def assignment_targets(node: ast.stmt) -> list[ast.expr]:
    """The targets a statement assigns by ``=`` or an annotated assignment; none otherwise."""
    if isinstance(node, ast.Assign):
        return node.targets
    return [node.target] if isinstance(node, ast.AnnAssign) else []


@pytest.mark.parametrize("name", documented_modules())
def test_every_exported_constant_is_documented(name):
    """The reference shows a module's constant only with its documentation, a ``#:`` comment
    (which the site's Griffe extension reads) or a string after the assignment, and only where
    it is assigned alone: Griffe does not see names unpacked from a tuple (``A, B = 1, 2``)."""
    module = importlib.import_module(name)
    exported = set(module.__all__)
    lines = Path(module.__file__).read_text().splitlines()
    body = ast.parse("\n".join(lines)).body
    undocumented = []
    for node, after in zip(body, [*body[1:], None], strict=True):
        for target in assignment_targets(node):
            if isinstance(target, ast.Tuple):
                unpacked = {n.id for n in ast.walk(target) if isinstance(n, ast.Name)}
                undocumented += [f"{n} (unpacked)" for n in sorted(unpacked & exported)]
            elif isinstance(target, ast.Name) and target.id in exported:
                string_after = (
                    isinstance(after, ast.Expr)
                    and isinstance(after.value, ast.Constant)
                    and isinstance(after.value.value, str)
                )
                if not (string_after or API_PAGES.attribute_comment(lines, node.lineno)):
                    undocumented.append(target.id)
    assert not undocumented, f"{name}: document (or assign alone) {undocumented}"
