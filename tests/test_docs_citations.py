"""Every ``docs/papers/<page>.md`` the code, tests, benchmarks and notebooks cite exists, and a
cited ``#anchor`` or ``, <section>`` names one of that page's headings (``, eq 32`` and the like
are equation citations, not sections)."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CITATION = re.compile(r"docs/papers/(\w+)\.md(?:#([\w-]+)|, ([A-Za-z][\w -]*[\w]))?")
SOURCES = ["jaxest", "benchmarks", "tests", "notebooks", "README.md"]


def headings(page: Path) -> list[str]:
    return [ln.lstrip("#").strip().lower() for ln in page.read_text().splitlines() if ln[:1] == "#"]


def anchor(heading: str) -> str:
    """The id mkdocs' toc extension gives a heading (lower case, punctuation dropped, '-' joins)."""
    return re.sub(r"[\s-]+", "-", re.sub(r"[^\w\s-]", "", heading)).strip("-")


def citations():
    for source in SOURCES:
        path = ROOT / source
        for file in [path] if path.is_file() else path.rglob("*"):
            if file.suffix in {".py", ".ipynb", ".md"} and file.name != Path(__file__).name:
                for match in CITATION.finditer(file.read_text(errors="ignore")):
                    yield file.relative_to(ROOT), match.groups()


def test_cited_pages_and_sections_exist():
    problems = []
    for file, (page, fragment, section) in citations():
        target = ROOT / "docs" / "papers" / f"{page}.md"
        if not target.is_file():
            problems.append(f"{file}: docs/papers/{page}.md does not exist")
            continue
        names = headings(target)
        if fragment and fragment not in {anchor(h) for h in names}:
            problems.append(f"{file}: no heading #{fragment} in docs/papers/{page}.md")
        # a section is the heading's text, or its start (prose may follow the citation)
        if (
            section
            and not re.match(r"(eqs?|equations?|lemma|step)\b", section.lower())
            and not any(
                section.lower().startswith(h) or h.startswith(section.lower()) for h in names
            )
        ):
            problems.append(f"{file}: no section '{section}' in docs/papers/{page}.md")
    assert not problems, "\n".join(problems)


def test_every_paper_page_exists():
    for page in ("svd_ekf", "smf", "wiener", "network", "adaptive"):
        assert headings(ROOT / "docs" / "papers" / f"{page}.md")
