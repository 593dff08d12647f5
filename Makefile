# Single entry point: every target creates .venv and installs the project when needed.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# The modules setup.py compiles with mypyc (listed in protocols/compiled.py).
HOT_SOURCES := $(shell $(PYTHON) -c "import sys; sys.path.insert(0, '.'); from protocols.compiled import source_paths; print(' '.join(source_paths()))")
NATIVE := build/.native

.PHONY: demo test lint bench build clean

$(STAMP): pyproject.toml setup.py
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

# Compile in place when a compiled module is missing or older than its source (after an
# install that compiled them all, nothing is left to do).
$(NATIVE): $(STAMP) $(HOT_SOURCES) protocols/compiled.py setup.py
	$(BIN)/python protocols/compiled.py . || $(BIN)/python setup.py --quiet build_ext --inplace --force
	mkdir -p build && touch $(NATIVE)

build: $(NATIVE)

demo: $(NATIVE)
	$(BIN)/glider-hil demo

test: $(NATIVE)
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -q

lint: $(STAMP)
	$(BIN)/ruff check .

bench: $(NATIVE)
	$(BIN)/glider-hil experiment --bench --samples 5000
	$(BIN)/python benchmarks/bench_replay.py --samples 20000
	$(BIN)/python benchmarks/bench_service.py --samples 20000 --latency-samples 1500 --memory-samples 500000

clean:
	rm -rf $(VENV) build *.egg-info glider_hil_native__mypyc*.so
	find hil_service protocols -name '*.so' -delete
