# Two commands do all the set-up on a fresh machine:
#   make modes   -> venv, install, run configs/cantilever.yaml -> outputs/cantilever.h5
#   make test    -> venv, install, pytest (the default, fast suite)
#   make api     -> the API reference from the docstrings (pdoc) -> build/api/index.html
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
EXTRAS ?= test,fast,plots,batch
CONFIG ?= configs/cantilever.yaml

.PHONY: modes test test-all test-reliability bench batch env clean api

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

RELIABILITY_TESTS := tests/test_reliability_fuzz.py tests/test_reliability_files.py \
                     tests/test_reliability_kill.py tests/test_reliability_numerics.py
test-reliability: $(STAMP)
	mkdir -p outputs && rm -f outputs/reliability_counts.json
	RELIABILITY_COUNTS=outputs/reliability_counts.json $(PY) -m pytest -q -m "" $(RELIABILITY_TESTS)
	cat outputs/reliability_counts.json

BATCH ?= configs/batch_convergence.yaml
batch: $(STAMP)
	$(PY) -m pipeline batch $(BATCH) $(BATCH_ARGS)

API_DIR ?= build/api
api: $(STAMP)
	$(PY) tools/api_docs.py $(API_DIR)

bench: $(STAMP)
	$(PY) benchmarks/bench_pipeline.py $(BENCH_ARGS)

clean:
	rm -rf outputs/*.h5 meshes/*.msh .pytest_cache
