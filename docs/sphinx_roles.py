"""A Griffe extension for the API reference: the Sphinx conventions of jaxest's docstrings.

jaxest's docstrings cite other objects as Sphinx roles (:class:`~jaxest.Gaussian`,
:func:`run`), which mkdocstrings' Sphinx docstring style leaves as literal text. After Griffe has
loaded the package, each role becomes a mkdocs-autorefs link to the object's entry on the site
where the reference shows it (``[`Gaussian`][jaxest.Gaussian]``), and inline code where it does
not (a private helper, a module without a page), so that no link is left dangling. Names are
resolved in the docstring's own scope, as Python resolves them in the module (its imports
included). The pages and the modules they show are read from ``docs/api/*.md``.

Attributes are documented the Sphinx way too, by ``#:`` comments above the assignment or after it
on the same line, which Griffe does not read (it takes a string after the assignment): they
become the attributes' docstrings first, so the reference shows the documented constants and
fields.
"""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import griffe

#: the Sphinx cross-reference roles jaxest's docstrings use (docs/check_site.py looks for them)
ROLE_NAMES = "class|func|meth|attr|data|mod|obj|exc|const"
#: :role:`target`, :role:`~target` (shows the last part) and :role:`title <target>`
ROLE = re.compile(rf":({ROLE_NAMES}):`([^`]+)`")


def _load_sibling(name: str):
    """``docs/<name>.py`` as a module: Griffe loads this extension from its path, with docs/ not
    on ``sys.path``."""
    spec = importlib.util.spec_from_file_location(name, Path(__file__).with_name(f"{name}.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


_api_pages = _load_sibling("api_pages")
documented_modules, attribute_comment = _api_pages.documented_modules, _api_pages.attribute_comment


class SphinxRoles(griffe.Extension):
    """Gives attributes their ``#:`` comments as docstrings, then rewrites the roles of every
    docstring in a loaded package (module docstring)."""

    def on_package(self, *, pkg: griffe.Module, **kwargs) -> None:
        for obj in _objects(pkg):
            if obj.is_attribute and obj.docstring is None and (text := _comment(obj)):
                obj.docstring = griffe.Docstring(text, lineno=obj.lineno, parent=obj)
        modules = documented_modules()
        shown = self._shown_paths(pkg, modules)
        for obj in _objects(pkg):
            if obj.docstring is not None:
                obj.docstring.value = ROLE.sub(
                    lambda m: _link(obj, m.group(1), m.group(2), shown, modules),
                    obj.docstring.value,
                )

    @staticmethod
    def _shown_paths(pkg: griffe.Module, modules: list[str]) -> dict[str, str]:
        """Canonical path -> the identifier the reference shows the object under: a documented
        module's path; ``module.name`` for what its ``__all__`` exports; their classes' own
        members. Only objects with a docstring (the reference hides the others)."""
        shown = {}
        for name in modules:
            if name != pkg.path and not name.startswith(pkg.path + "."):
                continue
            module = pkg if name == pkg.path else pkg.get_member(name.removeprefix(pkg.path + "."))
            shown[module.path] = module.path
            for export in module.exports or ():
                if export not in module.members:  # assigned in a way Griffe does not read
                    continue
                target = _final(module.members[export])
                if target is None or not target.docstring:
                    continue
                shown.setdefault(target.path, f"{module.path}.{export}")
                for member_name, member in target.members.items() if target.is_class else ():
                    if not member.is_alias and member.docstring and not member_name.startswith("_"):
                        shown.setdefault(member.path, f"{module.path}.{export}.{member_name}")
        return shown


def _objects(obj: griffe.Object):
    """``obj`` and every object defined inside it (aliases skipped: their targets are visited)."""
    yield obj
    for member in obj.members.values():
        if not member.is_alias:
            yield from _objects(member)


def _comment(attribute: griffe.Attribute) -> str | None:
    """The ``#:`` comment documenting ``attribute`` (docs/api_pages.py says where it is looked
    for); None where there is none."""
    if attribute.lineno is None or attribute.filepath is None:
        return None
    return attribute_comment(attribute.lines_collection[attribute.filepath], attribute.lineno)


def _final(obj: griffe.Object | griffe.Alias) -> griffe.Object | None:
    """What ``obj`` is, past any aliases; None for an alias Griffe cannot follow."""
    try:
        return obj.final_target if obj.is_alias else obj
    except (griffe.AliasResolutionError, griffe.CyclicAliasError):
        return None


def _link(
    obj: griffe.Object, role: str, text: str, shown: dict[str, str], modules: list[str]
) -> str:
    """The Markdown for one role (``role``, ``text``) in ``obj``'s docstring; ``shown`` as
    :meth:`SphinxRoles._shown_paths` makes it, ``modules`` the documented modules."""
    title = None
    if match := re.fullmatch(r"(.+?)\s*<(.+)>", text):
        title, text = match.groups()
    short = text.startswith("~")
    target = text.lstrip("~")
    title = title or (target.rsplit(".", 1)[-1] if short else target)
    path = _resolve(obj, target)
    # a module's name can also be a function's that its package exports (jaxest.network.design)
    if path in shown and (role == "mod") == (shown[path] in modules):
        return f"[`{title}`][{shown[path]}]"
    return f"`{title}`"


def _resolve(obj: griffe.Object, target: str) -> str | None:
    """The canonical path ``target`` names in ``obj``'s scope (aliases followed), or None."""
    head, _, rest = target.partition(".")
    scope = obj if obj.is_module or obj.is_class else obj.parent
    try:
        path = scope.resolve(head)
    except griffe.NameResolutionError:
        if head != "jaxest":
            return None
        path = head
    path = f"{path}.{rest}" if rest else path
    try:
        found = _final(obj.modules_collection[path])
    except KeyError:
        return path
    return path if found is None else found.path
