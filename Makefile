# Single entry point: every target creates .venv and installs the project when needed.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test lint bench build clean

$(STAMP): pyproject.toml setup.py
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

# Compile in place when a module of protocols/compiled.py's list is missing or older than
# its source; the check is cheap, and after an install that compiled them all it passes.
build: $(STAMP)
	$(BIN)/python protocols/compiled.py . || $(BIN)/python setup.py --quiet build_ext --inplace --force

demo: build
	$(BIN)/glider-hil demo

test: build
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -q

lint: $(STAMP)
	$(BIN)/ruff check .

bench: build
	$(BIN)/glider-hil experiment --bench --samples 5000
	$(BIN)/python benchmarks/bench_replay.py --samples 20000
	$(BIN)/python benchmarks/bench_service.py --samples 20000 --latency-samples 1500 --memory-samples 500000

clean:
	rm -rf $(VENV) build *.egg-info glider_hil_native__mypyc*.so
	find hil_service protocols -name '*.so' -delete
