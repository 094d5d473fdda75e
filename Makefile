# The two commands of the README quick start, and the user's guide.
#
# Everything runs inside the project's own virtual environment `.venv`, so the commands work on a system
# Python that refuses `pip install` outside one (PEP 668, stock Debian and Ubuntu). The environment is created
# on first use and reinstalled only when pyproject.toml changes (a stamp file per extra), so a second
# `make test` goes straight to the tests.
PYTHON ?= python3
export NO_MKDOCS_2_WARNING := 1
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip

.PHONY: demo test docs docs-serve install install-test bench

$(PY):
	@$(PYTHON) -c "import venv, ensurepip" 2>/dev/null || { \
	  echo "make: $(PYTHON) cannot create a virtual environment (no venv/ensurepip module);" \
	       "install it first, e.g. 'sudo apt-get install python3-venv'" >&2; exit 2; }
	$(PYTHON) -m venv $(VENV)

$(VENV)/.stamp-run: pyproject.toml | $(PY)
	$(PIP) install -q -e .
	@touch $@

$(VENV)/.stamp-test: pyproject.toml | $(PY)
	$(PIP) install -q -e ".[test,docs]"
	@touch $@ $(VENV)/.stamp-run

install: $(VENV)/.stamp-run

install-test: $(VENV)/.stamp-test

demo: install
	$(VENV)/bin/hel-warp demo

# CI runs `make test` (.ci/run): the user's guide must build with warnings as errors, then the suite runs.
test: install-test
	$(VENV)/bin/mkdocs build --strict --quiet
	$(PY) -m pytest -q

docs: install-test
	$(VENV)/bin/mkdocs build --strict

docs-serve: install-test
	$(VENV)/bin/mkdocs serve

bench: install
	$(PY) scripts/bench_dem.py
