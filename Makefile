# Two commands do all the set-up on a fresh machine:
#   make modes   -> venv, install, run configs/cantilever.yaml -> outputs/cantilever.h5
#   make test    -> venv, install, pytest (the default, fast suite)
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
EXTRAS ?= test,fast,plots,batch
CONFIG ?= configs/cantilever.yaml

.PHONY: modes test test-all bench batch env clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[$(EXTRAS)]"
	touch $(STAMP)

env: $(STAMP)

modes: $(STAMP)
	$(PY) -m pipeline run $(CONFIG)

test: $(STAMP)
	$(PY) -m pytest -q

test-all: $(STAMP)
	$(PY) -m pytest -q -m ""

BATCH ?= configs/batch_convergence.yaml
batch: $(STAMP)
	$(PY) -m pipeline batch $(BATCH) $(BATCH_ARGS)

bench: $(STAMP)
	$(PY) benchmarks/bench_pipeline.py $(BENCH_ARGS)

clean:
	rm -rf outputs/*.h5 meshes/*.msh .pytest_cache
