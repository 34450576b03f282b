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
# test processes of `make test` / `make test-all` (pytest-xdist, whole files per process):
# the suite takes 7.5-9 min on 2 cores with 2 (its clean-clone CI runs), about twice that
# with 1 (TEST_WORKERS=1 runs it in one process, without xdist)
TEST_WORKERS ?= 2
XDIST := $(if $(filter 1,$(TEST_WORKERS)),,-n $(TEST_WORKERS) --dist loadfile)

.PHONY: modes test test-all test-reliability bench bench-baseline batch env clean api \
        mpi-env mpi-modes mpi-parts mpi-test

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[$(EXTRAS)]"
	touch $(STAMP)

env: $(STAMP)

modes: $(STAMP)
	$(PY) -m pipeline run $(CONFIG)

test: $(STAMP)
	$(PY) -m pytest -q $(XDIST)

test-all: $(STAMP)
	$(PY) -m pytest -q -m "" $(XDIST)

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
	$(PY) benchmarks/bench_solvers.py $(SOLVER_BENCH_ARGS)
	if [ -x $(MPI_PY) ]; then $(MPI_PY) benchmarks/bench_mpi.py && \
	$(MPI_PY) benchmarks/bench_mpi.py --method multigrid --no-cuts; \
	else echo "distributed section skipped: make mpi-env"; fi

# this tree against an earlier revision, run by run in one window (the speed-up of a
# change as a ratio the host's speed changes cannot move): make bench-baseline REV=6f9150d
REV ?=
bench-baseline: $(STAMP)
	$(PY) benchmarks/bench_baseline.py --baseline "$(REV)" $(BASELINE_ARGS)

# The distributed path (docs/distributed.md): PETSc, SLEPc and OpenMPI from Debian's
# packages under the system Python, in its own venv (tools/mpi_env.sh says why)
MPI_VENV  ?= .venv-mpi
MPI_PY    := $(MPI_VENV)/bin/python
MPI_STAMP := $(MPI_VENV)/.installed
MPI_RANKS ?= 2
MPIEXEC   ?= mpiexec
# root may start MPI ranks only when it says so (containers, CI)
MPI_ROOT  := $(if $(filter 0,$(shell id -u)),--allow-run-as-root,)
MPI_RUN   = OMPI_ALLOW_RUN_AS_ROOT=1 OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1 PYTHONPATH=$(CURDIR) \
            $(MPIEXEC) $(MPI_ROOT) --oversubscribe -n $(MPI_RANKS) -x PYTHONPATH

$(MPI_STAMP): pyproject.toml tools/mpi_env.sh
	sh tools/mpi_env.sh $(MPI_VENV)
	touch $(MPI_STAMP)

mpi-env: $(MPI_STAMP)

mpi-modes: $(MPI_STAMP)
	mkdir -p outputs
	$(MPI_RUN) $(MPI_PY) -m pipeline run $(CONFIG) --set modes.solver=slepc -o outputs/$(basename $(notdir $(CONFIG)))-mpi.h5

# rank 0's mesh phase once, on one process (python -m pipeline partition), then the ranks
# each read their own part of the parts file (mesh.parts; docs/distributed.md)
MPI_PARTS = outputs/$(basename $(notdir $(CONFIG)))-parts$(MPI_RANKS).h5
mpi-parts: $(MPI_STAMP)
	mkdir -p outputs
	$(MPI_PY) -m pipeline partition $(CONFIG) --ranks $(MPI_RANKS) -o $(MPI_PARTS)
	$(MPI_RUN) $(MPI_PY) -m pipeline run $(CONFIG) --set modes.solver=slepc \
	  --set mesh.parts=$(MPI_PARTS) -o outputs/$(basename $(notdir $(CONFIG)))-mpi-parts.h5

mpi-test: $(MPI_STAMP)
	$(MPI_PY) -m pytest -q -m mpi tests/test_mpi*.py

clean:
	rm -rf outputs/*.h5 meshes/*.msh .pytest_cache
