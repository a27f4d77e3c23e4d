PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
OUT ?= results
# JAX's persistent compilation cache: off unless JAXEST_COMPILATION_CACHE=1 (jaxest/compile_cache.py
# says why); then outside the clone, one directory per processor.

.PHONY: reproduce test test-fast lint format clean docs docs-check wheel-check

# The venv's pip installs uv, and uv installs jaxest and its dependencies: from a fresh clone, with
# no cache, 32 s against pip's 78 s (2026-12-01, `make test`'s dev extras, byte-compiled as pip
# does: every test process would otherwise compile the modules it imports).
INSTALL = $(BIN)/pip install --quiet uv && $(BIN)/uv pip install --quiet --python $(BIN)/python \
	--compile-bytecode

$(BIN)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(INSTALL) -e .
	touch $@

$(BIN)/.installed-dev: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(INSTALL) -e ".[dev]"
	touch $@ $(BIN)/.installed

$(BIN)/.installed-docs: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(INSTALL) -e ".[dev,docs]"
	$(BIN)/python -m ipykernel install --prefix $(VENV) --name python3 > /dev/null
	touch $@ $(BIN)/.installed-dev $(BIN)/.installed

# Two studies at a time, each in its own process: one study keeps about 1.2 of 2 cores busy
# (user CPU 830 s over 684 s wall); the two whose tables report wall times run alone.
JOBS ?= 2
reproduce: $(BIN)/.installed
	$(BIN)/python -m jaxest reproduce all --jobs $(JOBS) --out $(OUT)

lint: $(BIN)/.installed-dev
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

# two pytest-xdist workers, one per core of the 2-core machines this runs on
PYTEST = $(BIN)/python -m pytest -n 2 -q

test: lint
	$(PYTEST) --durations=20

# The inner loop: the suite without the tests marked slow (whole studies, notebooks, several
# processes); `make test` stays the whole suite.
test-fast: lint
	$(PYTEST) -m "not slow"

format: $(BIN)/.installed-dev
	$(BIN)/ruff check --fix .
	$(BIN)/ruff format .

# The site, notebooks executed at build time, into site/. mkdocs-jupyter's cache keys on the
# notebook alone (not on jaxest's code), so it is dropped: every build executes every notebook.
docs: $(BIN)/.installed-docs
	rm -rf .cache/mkdocs-jupyter
	PATH=$(CURDIR)/$(BIN):$$PATH $(BIN)/mkdocs build --strict

# Opens every built page in headless Chromium. Debian's chromium and chromium-driver are installed
# where absent (as root or by sudo; 19 s here), since a fresh machine has neither; where they can be
# neither found nor installed the check fails rather than passing unseen.
SUDO = $(if $(filter 0,$(shell id -u)),,sudo)
BROWSER_PACKAGES = chromium chromium-driver
docs-check: docs
	command -v chromedriver > /dev/null && command -v chromium > /dev/null || \
		$(SUDO) apt-get install -y -q $(BROWSER_PACKAGES) > /dev/null || \
		($(SUDO) apt-get update -q > /dev/null && $(SUDO) apt-get install -y -q $(BROWSER_PACKAGES) > /dev/null)
	$(BIN)/python docs/check_site.py site

# A wheel built from the sdist (as a release is, so nothing left in build/ gets in) installs into a
# clean venv outside the clone, imports every module it ships from there (a module that needs a
# dev-only package fails here), has its console script, and runs a quick study. .ci/run calls it.
define WHEEL_IMPORTS_EVERY_MODULE
import importlib, pathlib, pkgutil, jaxest
assert pathlib.Path(jaxest.__file__).is_relative_to(pathlib.Path("venv").resolve()), jaxest.__file__
names = [m.name for m in pkgutil.walk_packages(jaxest.__path__, "jaxest.") if m.name != "jaxest.__main__"]
for name in names: importlib.import_module(name)
print(f"wheel: {len(names)} modules of jaxest import")
endef
export WHEEL_IMPORTS_EVERY_MODULE
WHEEL_TMP ?= $(or $(TMPDIR),/tmp)/jaxest-wheel-check
wheel-check:
	rm -rf $(WHEEL_TMP)
	$(PYTHON) -m venv $(WHEEL_TMP)/venv
	$(WHEEL_TMP)/venv/bin/pip install --quiet --upgrade pip build
	$(WHEEL_TMP)/venv/bin/python -m build --outdir $(WHEEL_TMP)/dist .
	$(WHEEL_TMP)/venv/bin/pip install --quiet $(WHEEL_TMP)/dist/jaxest-*.whl
	cd $(WHEEL_TMP) && venv/bin/python -c "$$WHEEL_IMPORTS_EVERY_MODULE"
	cd $(WHEEL_TMP) && venv/bin/jaxest reproduce --help > /dev/null
	cd $(WHEEL_TMP) && venv/bin/python -m jaxest reproduce filters --quick --out results
	test -s $(WHEEL_TMP)/results/filters/summary.json

clean:
	rm -rf $(VENV) results .pytest_cache site .cache/mkdocs-jupyter
