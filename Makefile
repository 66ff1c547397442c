# RAP: thin wrappers. Every target installs what it needs (uv, the workspace).
SHELL := /bin/bash
PYTHON ?= python3
UV := $(shell command -v uv 2>/dev/null || echo "$(PYTHON) -m uv")
RUN := $(UV) run --frozen --no-sync
PYTEST_ARGS ?=
DEMO_ARGS ?=
EVAL_ARGS ?=
EVAL_SHIP_ARGS ?= --runs 5 --rerun
FUZZ_ARGS ?=
FAULTS_ARGS ?=
# third-party AADL / RoboChart designs the importers must read (not part of this repository)
DESIGN_MODELS ?= $(abspath $(CURDIR)/../shared/models)

.PHONY: help setup sync test acceptance lint format typecheck schemas bench bench-fabric bench-knowledge bench-sim bench-twin bench-loop bench-fleet bench-trust bench-secure fuzz faults demo eval eval-ship clean

help:
	@echo "make demo       run the lidar-occlusion loop end to end (out/demo/summary.json, demo.rrd)"
	@echo "make eval       evaluate the loop on seeded scenarios (out/eval/lidar_occlusion.json)"
	@echo "make eval-ship  the ship-motion case on seeded weather fronts (out/eval/ship_motion.json, .rrd)"
	@echo "make test       run the test suite (RAP_REQUIRE_SERVICES=1 makes missing servers fail)"
	@echo "make acceptance the design parsers on third-party designs (DESIGN_MODELS=folder)"
	@echo "make lint       ruff format check + ruff lint"
	@echo "make typecheck  mypy --strict on schemas, libs and services"
	@echo "make schemas    export JSON Schema of every wire message to schemas/json, and the model reference"
	@echo "make bench      run the benchmarks; results in bench/results and docs/benchmarks.md"
	@echo "make bench-fleet  50 robots' loops at 5 Hz on this machine (bench/results/fleet.json)"
	@echo "make bench-secure  TLS and access control through a router, against plain (bench/results/secure.json)"
	@echo "make fuzz       fuzz every subscriber of a running loop (bench/results/fuzz.json, docs/reliability.md)"
	@echo "make faults     kill, cut and flood the loop under rap up (~25 min; bench/results/faults.json, docs/reliability.md)"
	@echo "make wheels    RAP's distributions as wheels in WHEELS_DIR (for the image rap generate describes)"

# Install uv from PyPI when it is missing, then sync the locked workspace.
setup:
	@$(UV) --version >/dev/null 2>&1 || $(PYTHON) -m pip install --quiet uv \
		|| $(PYTHON) -m pip install --quiet --user uv
	@$(UV) sync --locked --quiet

test: setup
	$(RUN) pytest $(PYTEST_ARGS)

# the parsers against real third-party designs in $(DESIGN_MODELS) (fails when it is missing)
acceptance: setup
	DESIGN_MODELS="$(DESIGN_MODELS)" $(RUN) pytest acceptance $(PYTEST_ARGS)

lint: setup
	$(RUN) ruff format --check .
	$(RUN) ruff check .

format: setup
	$(RUN) ruff format .
	$(RUN) ruff check --fix .

typecheck: setup
	$(RUN) mypy

schemas: setup
	$(RUN) python -m rap_schemas export schemas/json
	$(RUN) python -m rap_schemas reference docs/toolkit.md
	$(RUN) python -m sim_world.schema

# Every suite runs even if one misses a budget; make fails if any did.
bench: setup
	@rc=0; for b in fabric knowledge sim twin trust secure; do $(RUN) python -m bench.$$b || rc=1; done; exit $$rc

bench-fabric: setup
	$(RUN) python -m bench.fabric

bench-knowledge: setup
	$(RUN) python -m bench.knowledge

bench-sim: setup
	$(RUN) python -m bench.sim

# The lidar case's digital twin: a rollout of one plan period against the simulator (~1 min)
bench-twin: setup
	$(RUN) python -m bench.twin

bench-trust: setup
	$(RUN) python -m bench.trust

# What mutual TLS and the model's access control cost a message through a router (~1 min)
bench-secure: setup
	$(RUN) python -m bench.secure

# The loop race against RPIO 0.4.3 (its own venv in bench/.rpio-venv; ~10 min)
bench-loop: setup
	$(RUN) python -m bench.loop

# 50 simulated robots, each with its own five-stage loop at 5 Hz (sim_world, one knowledge
# service, 2 runners): latency, lost cycles, CPU and RSS (bench/results/fleet.json)
bench-fleet: setup
	$(RUN) python -m bench.fleet

# Mutated samples at every subscriber of a running lidar-occlusion loop, bounded in time
# (FUZZ_ARGS="--seconds 300 --samples 100000 --seed 1"): bench/results/fuzz.json
fuzz: setup
	$(RUN) python -m bench.fuzz $(FUZZ_ARGS)

# Faults injected into the loop under rap up, each bounded in time (~25 min; root for the
# network namespaces, redis-server for the Redis scenarios): kill -9 of every process, Redis
# killed, 5 s and 15 s partitions, 1 kHz into a FIFO inbox for 10 min, fuzz over TLS
# (FAULTS_ARGS="--quick" for a smoke run, "--only kills,redis"): bench/results/faults.json
faults: setup
	$(RUN) python -m bench.faults $(FAULTS_ARGS)

# The lidar-occlusion loop end to end (sim_world, knowledge, the runner; loopback Zenoh).
demo: setup
	$(RUN) python -m lidar_occlusion.demo $(DEMO_ARGS)

# N seeded scenarios with the loop and without: out/eval/lidar_occlusion.json
eval: setup
	$(RUN) python -m lidar_occlusion.eval $(EVAL_ARGS)

# the ship-motion case: N seeded weather fronts, retraining online: out/eval/ship_motion.json
eval-ship: setup
	$(RUN) python -m ship_motion.eval $(EVAL_SHIP_ARGS)

# RAP's own distributions as wheels (they are not on PyPI), e.g. for the image of a package
# that rap generate wrote: make wheels WHEELS_DIR=<generated folder>/deploy/wheels
WHEELS_DIR ?= dist/wheels
.PHONY: wheels
wheels: setup
	$(UV) build --all-packages --wheel --out-dir "$(WHEELS_DIR)"

clean:
	rm -rf .venv .pytest_cache .mypy_cache .ruff_cache out
