# The two commands of the README: `make demo` and `make test`. Both create .venv and install the
# project (with its dev extra) when it is missing or pyproject.toml changed.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test lint bench vcan-test clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev]'
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/pvt demo

test: $(STAMP)
	$(PY) -m pytest -q

lint: $(STAMP)
	$(VENV)/bin/ruff check planner streamer bus tests benchmarks
	$(VENV)/bin/mypy --strict planner

bench: $(STAMP)
	$(PY) -m benchmarks

clean:
	rm -rf $(VENV) demo-out .pytest_cache .hypothesis

vcan-test: $(STAMP)
	tools/vcan-vm/vcan-test.sh
