# Set-up and entry points. `make demo` runs the main job, `make test` the test suite;
# both create .venv with pip on first use.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
SHARED ?= $(abspath ../shared)

.PHONY: demo test test-all venv bench clean

$(STAMP): pyproject.toml setup.py
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e '.[test,pybullet]'
	touch $(STAMP)

venv: $(STAMP)

# the demo starts afresh each time (--overwrite): a repeated `make demo` replaces runs/demo
demo: $(STAMP)
	$(BIN)/bulbjax run --env CartPole --learners vae,vae_rpl,beta_vae --seeds 2 --epochs 6 --out runs/demo --small --overwrite

# `make test`: every test but the slow tier (marked `slow`, listed in tests/conftest.py): what CI
# runs; `make test-all`: every test
test: $(STAMP)
	$(BIN)/python -m pytest -q -n 2 --dist loadfile --durations=25 -m "not slow" tests

test-all: $(STAMP)
	$(BIN)/python -m pytest -q -n 2 --dist loadfile --durations=25 tests

bench: $(STAMP)
	$(BIN)/python benchmarks/bench_throughput.py

clean:
	rm -rf $(VENV) runs
