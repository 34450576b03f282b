#!/bin/sh
# Sets up the environment of the distributed (MPI) path, idempotently: `make mpi-env`.
#
# PETSc, SLEPc, their Python bindings and OpenMPI come from Debian's packages
# (python3-petsc4py, python3-slepc4py: 3.18 with MUMPS, built for /usr/bin/python3 and
# Debian's numpy 1.x). They install in a minute as binary packages, where building
# petsc4py against the project's numpy 2 means compiling the bindings (and PETSc itself
# from PyPI's sources: an hour). So the MPI path runs in its own virtual environment
# on the system Python, seeing Debian's packages (--system-site-packages) with numpy
# kept below 2 (the bindings' ABI); the project runs on numpy >= 1.24.
#
# Usage: tools/mpi_env.sh VENV   (prints the PETSC_DIR and SLEPC_DIR it found)
set -eu
VENV=${1:-.venv-mpi}
SYSPY=${MPI_PYTHON:-/usr/bin/python3}
find_dir() { ls -d "$1"/*/*-real 2>/dev/null | sort -V | tail -n 1; }
have_bindings() {
  PETSC_DIR=$(find_dir /usr/lib/petscdir) SLEPC_DIR=$(find_dir /usr/lib/slepcdir) \
    "$SYSPY" -c "from petsc4py import PETSc; from slepc4py import SLEPc" >/dev/null 2>&1
}
if ! have_bindings || ! command -v mpiexec >/dev/null 2>&1; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "mpi-env: installing Debian's PETSc/SLEPc bindings and OpenMPI (apt-get)"
    (DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
       python3-petsc4py python3-slepc4py python3-mpi4py openmpi-bin python3-venv >/dev/null) ||
    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq \
       --no-install-recommends python3-petsc4py python3-slepc4py python3-mpi4py openmpi-bin \
       python3-venv >/dev/null)
  fi
  if ! have_bindings || ! command -v mpiexec >/dev/null 2>&1; then
    echo "mpi-env: PETSc/SLEPc Python bindings or mpiexec missing: as root run" \
         "'apt-get install python3-petsc4py python3-slepc4py openmpi-bin' (Debian/Ubuntu)," \
         "or 'pip install mpi4py petsc4py slepc4py' with PETSC_DIR/SLEPC_DIR set" >&2
    exit 1
  fi
fi
# Debian's PETSc and MUMPS link the generic libblas.so.3 and liblapack.so.3, which point
# to the reference BLAS unless an optimised one is installed: OpenBLAS (its serial build:
# one thread a rank) takes them over through Debian's alternatives. MUMPS' dense
# kernels and SLEPc's orthogonalisation run on it (2 ranks, 100k DOFs: the modes stage
# 11.3 -> 5.8-8.5 s with MUMPS' factor, 248k DOFs factor-free 15.4 -> 11.7-12.3 s)
if [ ! -e /usr/lib/x86_64-linux-gnu/openblas-serial/libblas.so.3 ] && \
   [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
  echo "mpi-env: installing OpenBLAS for Debian's PETSc and MUMPS (apt-get)"
  (DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
     libopenblas0-serial >/dev/null) ||
    echo "mpi-env: OpenBLAS not installed; PETSc and MUMPS use the reference BLAS" >&2
fi
if [ ! -x "$VENV/bin/python" ]; then
  "$SYSPY" -m venv --system-site-packages "$VENV"
fi
"$VENV/bin/python" -m pip install --quiet -e . pytest "numpy>=1.24,<2"
# Debian's bindings live in the real-scalar PETSc and SLEPc trees (its petsc4py.pth finds
# them only through PETSC_DIR): name them to the venv once, so that no environment
# variable is needed at run time, on any rank
SITE=$("$VENV/bin/python" -c "import sysconfig; print(sysconfig.get_paths()['purelib'])")
printf '%s\n%s\n' "$(find_dir /usr/lib/petscdir)/lib/python3/dist-packages" \
  "$(find_dir /usr/lib/slepcdir)/lib/python3/dist-packages" > "$SITE/petsc-slepc-debian.pth"
"$VENV/bin/python" -c "from petsc4py import PETSc; from slepc4py import SLEPc; from mpi4py import MPI"
echo "PETSC_DIR=$(find_dir /usr/lib/petscdir)"
echo "SLEPC_DIR=$(find_dir /usr/lib/slepcdir)"
