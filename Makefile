# Single entry point: every target creates .venv and installs the project when needed.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test lint bench build clean mutate foxglove-client
FOXGLOVE_CLIENT := tests/foxglove_client

$(STAMP): pyproject.toml setup.py
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

# Delete compiled modules that are not on protocols/compiled.py's list (a removed or
# delisted module's .so would run in place of its source), then compile in place when a
# module of the list is missing or older than its source; the check is cheap, and after an
# install that compiled them all it passes.
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

# Two pytest-xdist workers: most tests wait on real processes over real-time links, so two
# halve the wall time on 2 cores; more would contend for the cores the tests' own services
# and emulators need. TEST_WORKERS=0 runs them in one process.
TEST_WORKERS ?= 2

test: build foxglove-client
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS)

# mypy is not in `make test`: a library's new stubs must not fail a test run.
lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy hil_service protocols plant_emulator

bench: build
	$(BIN)/glider-hil experiment --bench --samples 5000
	$(BIN)/python benchmarks/bench_replay.py --samples 20000
	$(BIN)/python benchmarks/bench_service.py --samples 20000 --latency-samples 1500 --memory-samples 500000

# Mutation testing of what keeps commands off the wire (README "Mutation testing"); not part
# of `make test`. Runs mutmut ([tool.mutmut] in pyproject.toml) on a copy of the tree in
# build/mutate, the Python sources only, with the in-process tests (`-m "not wire"`), over
# the functions below; prints every mutant that survived. MUTANTS=... narrows it further.
MUTATE_DIR := build/mutate
MUTANTS ?= \
	'hil_service.pipeline.xǁChannelPipelineǁblocked_reason__mutmut_*' \
	'hil_service.pipeline.xǁChannelPipelineǁobserve__mutmut_*' \
	'hil_service.pipeline.xǁChannelPipelineǁ_observe__mutmut_*' \
	'hil_service.pipeline.xǁVehiclePipelineǁdecide__mutmut_*' \
	'hil_service.inputs.xǁSetpointLimitsǁviolation__mutmut_*' \
	'hil_service.inputs.xǁInboxǁ*__mutmut_*' \
	'protocols.mapping.xǁTelemetryMappingǁballast_command__mutmut_*' \
	'protocols.mapping.x_is_ballast_command__mutmut_*' \
	'hil_service.offline.replay.x__compare__mutmut_*' \
	'hil_service.offline.replay.x__same_values__mutmut_*' \
	'hil_service.offline.replay.xǁ_Replayǁ_feed__mutmut_*' \
	'hil_service.offline.replay.xǁ_Replayǁrun__mutmut_*' \
	'hil_service.offline.replay.xǁ_Replayǁ_finish__mutmut_*'

mutate: $(STAMP)
	test -x $(BIN)/mutmut || $(BIN)/python -m pip install --quiet -e '.[mutation]'
	rm -rf $(MUTATE_DIR) && mkdir -p $(MUTATE_DIR)
	git ls-files -co --exclude-standard | grep -v '^build/' | tar cf - -T - | tar xf - -C $(MUTATE_DIR)
	cd $(MUTATE_DIR) && GLIDER_HIL_INTERPRETED=1 $(CURDIR)/$(BIN)/mutmut run $(MUTANTS) >mutmut.log 2>&1 \
		|| { tail -n 40 mutmut.log; exit 1; }
	@cd $(MUTATE_DIR) && tail -n 3 mutmut.log && echo "surviving mutants (none: nothing below):" \
		&& GLIDER_HIL_INTERPRETED=1 $(CURDIR)/$(BIN)/mutmut results \
		| grep -v -e ': killed' -e ': not checked' || true

clean:
	rm -rf $(VENV) build *.egg-info glider_hil_native__mypyc*.so
	find hil_service protocols -name '*.so' -delete
	rm -rf $(FOXGLOVE_CLIENT)/node_modules
