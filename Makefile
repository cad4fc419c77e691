# Two commands on a fresh machine: `make demo` and `make test`. Both create (or reuse)
# .venv from pyproject.toml; it is rebuilt when pyproject.toml changes.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
RUNS := runs

.PHONY: all venv test demo lbipe-benchmark export-lbipe lint bench bench-sim bench-train bench-help device-bundle clean

all: test

# Python keeps the bytecode of the modules it imports (its default, which some environments
# turn off): each module of the venv is compiled once, when first imported, not in every
# process, and not all ahead of time (of the 8,800 modules installed the suite imports 1,400).
unexport PYTHONDONTWRITEBYTECODE

# uv (one wheel, installed into the venv by pip) installs the same packages from the same
# index as pip, downloading and unpacking them in parallel: 4 s instead of 26 s on the
# 2-core CI machine (pip also compiles every module). Where uv cannot be had or fails, pip
# does the whole job.
$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	@if $(BIN)/python -m pip install --quiet 'uv>=0.4' && \
	    $(BIN)/python -m uv pip install --quiet --python $(BIN)/python -e '.[dev]'; \
	then echo "venv: installed with uv"; \
	else echo "venv: uv unavailable, installing with pip"; \
	    $(BIN)/python -m pip install --quiet --upgrade pip && \
	    $(BIN)/python -m pip install --quiet -e '.[dev]'; fi
	@touch $(STAMP)

venv: $(STAMP)

# The test files run in parallel, one worker per core (a file stays on one worker: its
# module fixtures, such as a virtual robot, start once), in the order tests/conftest.py
# gives them (longest first; xdist would otherwise reorder them by their number of tests);
# the 15 slowest tests are printed.
test: $(STAMP)
	$(BIN)/python -m pytest -q -n auto --dist loadfile --no-loadscope-reorder --durations=15

# The hardware tests (real driver, virtual robot) beside a busy loop on every core: they
# must hold on a saturated host. The loops are killed when the tests end (or fail).
.PHONY: test-stress
test-stress: $(STAMP)
	@pids=""; trap 'kill $$pids 2>/dev/null' EXIT INT TERM; \
	for i in $$(seq $$(nproc)); do $(BIN)/python -c "while True: pass" & pids="$$pids $$!"; done; \
	echo "test-stress: $$(nproc) busy loops:$$pids"; \
	$(BIN)/python -m pytest -q tests/test_hardware_*.py tests/test_feetech_*.py

# The paper end to end (quick scale): simulate, train, evaluate, switching loads,
# sim-to-real on shared/lbipe beside the released models; report in runs/demo/report.md.
demo: $(STAMP)
	$(BIN)/jaxinertia reproduce --out $(RUNS)/demo

# The released models on the real data only (Tables I and III, seconds).
lbipe-benchmark: $(STAMP)
	@mkdir -p $(RUNS)
	$(BIN)/jaxinertia lbipe-benchmark --json $(RUNS)/lbipe_benchmark.json \
		--plot $(RUNS)/lbipe_benchmark.png

# The paper-scale simulated training set in the authors' npz layout (seed 0), so that their
# own PyTorch training runs on exactly our data: runs/lbipe_train/{planning,random}.
export-lbipe: $(STAMP)
	$(BIN)/jaxinertia simulate --scenario planning --format lbipe --out $(RUNS)/lbipe_train/planning
	$(BIN)/jaxinertia simulate --scenario random --n 9000 --format lbipe --out $(RUNS)/lbipe_train/random

lint: $(STAMP)
	$(BIN)/ruff check jaxinertia tests experiments


bench: $(STAMP)
	$(BIN)/python experiments/bench_lbipe.py

bench-sim: $(STAMP)
	$(BIN)/python experiments/bench_sim.py --batches 256 1024 4096

bench-train: $(STAMP)
	$(BIN)/python experiments/bench_train.py

# `jaxinertia --help` and every command's, best of 5 fresh processes (target 0.5 s each).
bench-help: $(STAMP)
	$(BIN)/python experiments/bench_help.py

# What the lent GPU machine needs beside the working tree (the `device` tool, carry
# [".device"]): experiments/device/run_full.sh says how it is used.
device-bundle: $(STAMP)
	@bash experiments/device/bundle.sh $(BIN)/python

clean:
	rm -rf $(VENV) $(RUNS) .pytest_cache .ruff_cache .device
