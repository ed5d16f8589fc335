# The two quick-start commands (`make demo`, `make test`) create or reuse .venv by themselves.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp

.PHONY: demo test lint venv clean bench

$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[dev]"
	@touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(BIN)/shgm-slam demo

# tests spread over the machine's cores, a test file per worker (6-7 min on 2 cores, 2026-12-06; one process takes about a third longer)
test: $(STAMP)
	$(BIN)/python -m ruff check shgm_slam tests tools
	$(BIN)/python -m pytest -q -n auto --dist loadfile

lint: $(STAMP)
	$(BIN)/python -m ruff check shgm_slam tests tools

clean:
	rm -rf $(VENV) .pytest_cache results
