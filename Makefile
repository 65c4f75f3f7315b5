# The two set-up commands (README): `make demo` and `make test`. Each creates/refreshes .venv and
# installs the project into it before running.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install demo test lint bench clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

$(STAMP): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e ".[dev]"
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(BIN)/fp demo

test: $(STAMP)
	$(BIN)/ruff check fpcore services tests bench examples
	$(BIN)/ruff format --check fpcore services tests bench examples
	$(BIN)/python -m mypy fpcore
	$(BIN)/python -m pytest

bench: $(STAMP)
	$(BIN)/python bench/bench_kernel.py

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info
