# The two commands of the README quick start.
PYTHON ?= python3

.PHONY: demo test install install-test bench

install:
	$(PYTHON) -m pip install -q -e .

install-test:
	$(PYTHON) -m pip install -q -e ".[test]"

demo: install
	hel-warp demo

test: install-test
	$(PYTHON) -m pytest -q

bench: install
	$(PYTHON) scripts/bench_dem.py
