# Single entry point: every target creates .venv and installs the project when needed.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test lint bench build clean foxglove-client
FOXGLOVE_CLIENT := tests/foxglove_client

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

# The reference Foxglove client of tests/test_foxglove_live.py, from its lock file, when node
# and npm are on the machine (without them that test is skipped and says why).
foxglove-client: $(FOXGLOVE_CLIENT)/node_modules/.installed

$(FOXGLOVE_CLIENT)/node_modules/.installed: $(FOXGLOVE_CLIENT)/package-lock.json
	@if command -v node >/dev/null && command -v npm >/dev/null; then \
		npm ci --prefix $(FOXGLOVE_CLIENT) --no-audit --no-fund && touch $@; \
	else echo "node/npm not found: the Foxglove client test will be skipped"; fi

test: build foxglove-client
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
	rm -rf $(FOXGLOVE_CLIENT)/node_modules
