# mvtn-exp: every target that needs Python depends on `install`, so each is one command on a fresh machine.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: help install run test test-all bench clean

help:  ## list targets
	@grep -E '^[a-z-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  make %-10s %s\n", $$1, $$2}'

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet torch==2.13.0
	$(BIN)/pip install --quiet -e '.[test]'
	touch $(STAMP)

install: $(STAMP)  ## create .venv: torch==2.13.0 first (the CUDA build on Linux with a GPU driver; CPU elsewhere), then the package with test extras, editable

run: install  ## train the default MVTN on the embedded synthetic dataset (about 2 minutes; outputs/train/...)
	$(BIN)/mvtn-train

# One pytest worker per core (-n auto), each test file on one worker (--dist loadfile: module fixtures
# built once); tests/conftest.py gives each worker one torch thread so the workers do not fight.
XDIST := -n auto --dist loadfile

test: install  ## run the fast test suite on every core (slow tests: make test-all)
	$(BIN)/python -m pytest -q $(XDIST)

test-all: install  ## run every test, slow ones included
	$(BIN)/python -m pytest -q -m '' $(XDIST)

bench: install  ## renderer speed/memory benchmark; prints a Markdown table, writes outputs/bench/
	$(BIN)/mvtn-bench

clean:  ## remove the virtual environment and caches (keeps outputs/)
	rm -rf $(VENV) *.egg-info .pytest_cache
