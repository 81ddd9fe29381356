# make setup | serve | test | bench | lint: each does whatever set-up is still missing.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.uacell-installed
NODE_STAMP := interop/node_modules/.uacell-installed

.PHONY: setup serve test bench lint clean models

setup: $(STAMP) models $(NODE_STAMP)

$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[test]'
	@touch $@

models: $(STAMP)
	$(BIN)/uacell models fetch

$(NODE_STAMP): interop/package.json interop/package-lock.json
	cd interop && npm ci --no-audit --no-fund --loglevel=error
	@touch $@

serve: $(STAMP) models
	$(BIN)/uacell serve $(ARGS)

test: setup
	$(BIN)/python -m pytest -q $(PYTEST_ARGS)

bench: setup
	$(BIN)/python -m benchmarks

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/mypy

clean:
	rm -rf $(VENV) interop/node_modules
