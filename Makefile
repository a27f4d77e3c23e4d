PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
OUT ?= results
# JAX's persistent compilation cache, outside the clone: a second `make test` / `make reproduce`
# reloads compiled programs instead of compiling them again (tests/conftest.py uses the same path).
JAX_COMPILATION_CACHE_DIR ?= $(or $(XDG_CACHE_HOME),$(HOME)/.cache)/jaxest/jax
export JAX_COMPILATION_CACHE_DIR
export JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS ?= 0.2

.PHONY: reproduce test lint format clean docs docs-check

$(BIN)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e .
	touch $@

$(BIN)/.installed-dev: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e ".[dev]"
	$(BIN)/python -m ipykernel install --prefix $(VENV) --name python3 > /dev/null
	touch $@ $(BIN)/.installed

$(BIN)/.installed-docs: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e ".[dev,docs]"
	$(BIN)/python -m ipykernel install --prefix $(VENV) --name python3 > /dev/null
	touch $@ $(BIN)/.installed-dev $(BIN)/.installed

reproduce: $(BIN)/.installed
	$(BIN)/python -m jaxest reproduce all --out $(OUT)

lint: $(BIN)/.installed-dev
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

test: lint
	$(BIN)/python -m pytest -n 2 -q --durations=20

format: $(BIN)/.installed-dev
	$(BIN)/ruff check --fix .
	$(BIN)/ruff format .

# The site, notebooks executed at build time, into site/.
docs: $(BIN)/.installed-docs
	PATH=$(CURDIR)/$(BIN):$$PATH $(BIN)/mkdocs build --strict

# Opens every built page in headless Chromium (skips, saying so, where chromium is absent).
docs-check: docs
	$(BIN)/python docs/check_site.py site

clean:
	rm -rf $(VENV) results .pytest_cache site
