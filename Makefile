# Two commands on a fresh machine: `make demo` and `make test`. Both create (or reuse)
# .venv from pyproject.toml; it is rebuilt when pyproject.toml changes.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
RUNS := runs

.PHONY: all venv test demo lint bench bench-sim clean

all: test

$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	@touch $(STAMP)

venv: $(STAMP)

test: $(STAMP)
	$(BIN)/python -m pytest -q

demo: $(STAMP)
	@mkdir -p $(RUNS)
	$(BIN)/jaxinertia lbipe-benchmark --json $(RUNS)/lbipe_benchmark.json \
		--plot $(RUNS)/lbipe_benchmark.png

lint: $(STAMP)
	$(BIN)/ruff check jaxinertia tests experiments


bench: $(STAMP)
	$(BIN)/python experiments/bench_lbipe.py

bench-sim: $(STAMP)
	$(BIN)/python experiments/bench_sim.py --batches 256 1024 4096

clean:
	rm -rf $(VENV) $(RUNS) .pytest_cache .ruff_cache
