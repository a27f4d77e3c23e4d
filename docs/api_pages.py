"""The API reference's pages (``docs/api/*.md``), the modules they show, and the ``#:`` comments
that document constants and fields: read by the Griffe extension (docs/sphinx_roles.py, which
links only to what the pages show and makes the comments docstrings) and by
tests/test_api_reference.py (which checks the pages and the comments against the package);
importing it needs nothing beyond the standard library."""

from __future__ import annotations

import re
from pathlib import Path

PAGES = Path(__file__).resolve().parent / "api"
#: a ``#:`` comment line above an assignment; the same after the assignment on its first line
COMMENT_ABOVE = re.compile(r"^\s*#:\s?(.*)$")
COMMENT_AFTER = re.compile(r"\S.*?\s#:\s?(.*)$")


def documented_modules() -> list[str]:
    """The modules the API pages show (their ``::: module`` lines), page by page."""
    return [
        line.split()[1]
        for page in sorted(PAGES.glob("*.md"))
        for line in page.read_text().splitlines()
        if line.startswith(":::")
    ]


def attribute_comment(lines: list[str], lineno: int) -> str | None:
    """The ``#:`` comment documenting the assignment on line ``lineno`` (from 1) of a source's
    ``lines``: on that line after the assignment, or the comment lines right above it; None
    where there is none."""
    if match := COMMENT_AFTER.match(lines[lineno - 1].strip()):
        return match.group(1)
    above = []
    for line in reversed(lines[: lineno - 1]):
        if not (match := COMMENT_ABOVE.match(line)):
            break
        above.insert(0, match.group(1))
    return "\n".join(above) or None
