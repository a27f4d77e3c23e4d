"""The API reference's pages (``docs/api/*.md``) and the modules they show, read by the Griffe
extension (docs/sphinx_roles.py, which links only to what the pages show) and by
tests/test_api_reference.py (which checks the pages against the package); importing it needs
nothing beyond the standard library."""

from __future__ import annotations

from pathlib import Path

PAGES = Path(__file__).resolve().parent / "api"


def documented_modules() -> list[str]:
    """The modules the API pages show (their ``::: module`` lines), page by page."""
    return [
        line.split()[1]
        for page in sorted(PAGES.glob("*.md"))
        for line in page.read_text().splitlines()
        if line.startswith(":::")
    ]
