# The usual targets.  `make check` is what CI's second step runs; `make test` is the README's test command.
PY ?= python3

.PHONY: install dev test test-slow lint format typecheck docs docs-serve docs-outputs check bench clean

install:            ## the package and what its tests need
	$(PY) -m pip install -e ".[test]"

dev:                ## everything a contributor uses (tests, lint, types, docs, pre-commit)
	$(PY) -m pip install -e ".[dev,docs]"
	pre-commit install

test:               ## the fast suite (two workers; under 5 minutes on a loaded 2-core machine)
	pytest -q

test-slow:          ## the long studies and basins
	pytest -q -m slow

lint:
	ruff check .
	ruff format --check .

format:
	ruff check --fix .
	ruff format .

typecheck:
	mypy

docs:               ## the documentation site, as CI builds it
	NO_MKDOCS_2_WARNING=1 mkdocs build --strict

docs-serve:
	NO_MKDOCS_2_WARNING=1 mkdocs serve

check: lint typecheck docs test test-slow

bench:              ## the benchmark scripts that write the docs' figures (minutes)
	$(PY) benchmarks/bench_calibrate.py
	$(PY) benchmarks/bench_cli.py

clean:
	rm -rf build dist site .pytest_cache .mypy_cache .ruff_cache out

docs-outputs:       ## write what the docs' marked blocks print into the pages, and redraw the site's pictures
	$(PY) tests/docs_blocks.py --write
	$(PY) benchmarks/docs_figures.py
