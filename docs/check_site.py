"""Open every page of the built site in headless Chromium and fail on broken internal links,
images that did not load, notebook cells that raised, and API reference pages that show a
docstring's Sphinx role as text instead of a link (docs/sphinx_roles.py rewrites them).

    python docs/check_site.py site

Fails, saying so, where Chromium or chromedriver is absent (Debian: ``apt-get install chromium
chromium-driver``, which ``make docs-check`` runs): a check that did not run has not passed.
"""

from __future__ import annotations

import re
import shutil
import sys
from pathlib import Path
from urllib.parse import unquote, urlparse

from sphinx_roles import ROLE_NAMES  # docs/, beside this script

NOTEBOOK_PAGES = "notebooks"
RAISED = "Traceback (most recent call last)"
API_PAGES = "api"
#: a Sphinx cross-reference role as the page shows it when nothing rewrote it (":class:Gaussian")
SPHINX_ROLE = re.compile(rf":(?:{ROLE_NAMES}):\s*\S")


def browser():
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = shutil.which("chromium") or shutil.which("chromium-browser")
    for flag in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage"):
        options.add_argument(flag)
    return webdriver.Chrome(service=Service(shutil.which("chromedriver")), options=options)


def target_exists(href: str) -> bool:
    """Whether a file:// link points at a file of the site (a directory means its index.html)."""
    path = Path(unquote(urlparse(href).path))
    return (path / "index.html").is_file() if path.is_dir() else path.is_file()


def check_page(driver, page: Path) -> list[str]:
    driver.get(page.as_uri())
    problems = []
    for href in driver.execute_script(
        "return Array.from(document.querySelectorAll('a[href]'), a => a.href)"
    ):
        if href.startswith("file://") and not target_exists(href.split("#")[0]):
            problems.append(f"broken link {href}")
    images = driver.execute_script(
        "return Array.from(document.images, i => [i.src, i.complete && i.naturalWidth > 0])"
    )
    problems += [f"image did not load {src[:120]}" for src, ok in images if not ok]
    text = driver.execute_script("return document.body.innerText")
    if API_PAGES in page.parts:
        problems += [f"Sphinx role shown as text: {m[:40]!r}" for m in SPHINX_ROLE.findall(text)]
    if NOTEBOOK_PAGES in page.parts:
        if RAISED in text:
            problems.append("a notebook cell raised")
        if not any(ok for _, ok in images):
            problems.append("notebook page shows no figure")
    return problems


def main(site: str) -> int:
    if not (shutil.which("chromium") or shutil.which("chromium-browser")) or not shutil.which(
        "chromedriver"
    ):
        print("docs-check FAILED: chromium and chromedriver not found (apt-get install chromium ")
        print("chromium-driver); the site was built but not opened in a browser.")
        return 1
    pages = sorted(p for p in Path(site).resolve().rglob("*.html") if p.name != "404.html")
    if not pages:
        print(f"no pages under {site}: run `make docs` first")
        return 1
    driver = browser()
    failures = 0
    try:
        for page in pages:
            problems = check_page(driver, page)
            failures += len(problems)
            for problem in problems:
                print(f"{page.relative_to(Path(site).resolve())}: {problem}")
    finally:
        driver.quit()
    print(f"docs-check: {len(pages)} pages opened in headless Chromium, {failures} problems")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1] if len(sys.argv) > 1 else "site"))
