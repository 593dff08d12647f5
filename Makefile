# Single entry point: every target creates .venv and installs the project when needed.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test lint bench clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/glider-hil demo

test: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -q

lint: $(STAMP)
	$(BIN)/ruff check .

bench: $(STAMP)
	$(BIN)/glider-hil experiment --bench --samples 5000
	$(BIN)/python benchmarks/bench_replay.py --samples 20000
	$(BIN)/python benchmarks/bench_service.py --samples 20000 --latency-samples 1500 --memory-samples 500000

clean:
	rm -rf $(VENV) build *.egg-info
