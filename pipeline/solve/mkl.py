"""Intel MKL: find and load its runtime library, check its integer interface, and scope
its thread count.

MKL comes with the ``fast`` extra (pypardiso depends on the ``mkl`` wheel). It is found
as ``PYPARDISO_MKL_RT``, else ``libmkl_rt`` under the interpreter's prefix, else on the
linker's search path. The ``ctypes`` signatures of :mod:`pipeline.solve.backends.pardiso`
and :mod:`pipeline.solve.blas` pass 32-bit integers, i.e. MKL's LP64 interface:
:func:`mkl_library` asks the runtime for that interface and refuses (returns None, with a
one-line reason in the log) a library that runs the ILP64 one, so that every MKL path
falls back to scipy instead of passing 32-bit integers where 64-bit ones are read.

Thread count: MKL's own default on some 2-vCPU machines is one thread, and its sparse
products and PARDISO follow it (K of 1M DOFs times 25 vectors was 2.4 times faster on two
threads than on one). :func:`threads` sets the count for the calling thread only
(``mkl_set_num_threads_local``) and restores the previous setting on exit, so the host
process's own MKL settings are left as they were. ``MKL_NUM_THREADS`` in the environment
is the user's choice and is then left alone.

The library never writes ``os.environ``. MKL's OpenMP threads spin for 200 ms after every
call unless ``KMP_BLOCKTIME`` is 0 when the OpenMP runtime starts; on a 2-core machine that
spinning competes with the numpy work between solves (the Rayleigh-Ritz step was 10 times
slower), so the command-line entry point sets it in its own process.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import glob
import logging
import os
import sys
from typing import Any, Iterator

from pipeline._util.resources import usable_cores

log = logging.getLogger(__name__)

#: MKL's interface layers (``mkl_set_interface_layer``): bit 0 set means ILP64
INTERFACE_LP64 = 0
INTERFACE_ILP64 = 1
#: MKL's threading layers (``mkl_set_threading_layer``): Intel OpenMP
THREADING_INTEL = 0


def _candidates() -> Iterator[str]:
    """Paths to try for ``libmkl_rt``, most specific first; the system's search
    (``find_library``: a subprocess, about 10 ms) only when those before it fail."""
    from ctypes.util import find_library

    # find_library runs gcc on a named temporary file: an interrupt there would leave it
    from pipeline._util.atomic import signals_held

    if os.environ.get("PYPARDISO_MKL_RT"):
        yield os.environ["PYPARDISO_MKL_RT"]
    for prefix in (sys.prefix, sys.base_prefix):
        yield from sorted(glob.glob(os.path.join(prefix, "lib", "libmkl_rt.so*")), key=len)
        yield from sorted(glob.glob(os.path.join(prefix, "Library", "bin", "mkl_rt*.dll")),
                          key=len)
    with signals_held():
        name = find_library("mkl_rt")
    if name:
        yield name


def interface_is_lp64(lib: Any) -> bool:
    """Whether ``lib`` runs MKL's LP64 (32-bit integer) interface.

    ``mkl_set_interface_layer`` selects the layer when called before MKL's first use and
    returns the layer in effect either way: asking for LP64 sets it on a fresh library
    and reports the ILP64 one that an earlier user (or ``MKL_INTERFACE_LAYER``) chose."""
    setter = getattr(lib, "MKL_Set_Interface_Layer", None)
    if setter is None:
        return False
    setter.restype = ctypes.c_int
    setter.argtypes = [ctypes.c_int]
    return (int(setter(INTERFACE_LP64)) & INTERFACE_ILP64) == 0


def pin_threading_layer(lib: Any) -> int | None:
    """Select MKL's Intel OpenMP threading layer, unless ``MKL_THREADING_LAYER`` names one.

    ``libmkl_rt`` picks its threading layer at its first threaded call, and takes GNU
    OpenMP (``libgomp``) when that runtime is already in the process: gmsh loads it. GNU
    OpenMP's thread pool does not survive ``fork``: a forked child (a batch case run in its
    own process) then hangs in its first parallel PARDISO call. Intel's runtime does. The
    layer can be chosen only before MKL's first use; once the host has used MKL, its
    choice stands and this returns it. Returns the layer in effect, or None where the
    library cannot tell."""
    setter = getattr(lib, "MKL_Set_Threading_Layer", None)
    if setter is None:
        return None
    setter.restype = ctypes.c_int
    setter.argtypes = [ctypes.c_int]
    if os.environ.get("MKL_THREADING_LAYER"):
        return None
    return int(setter(THREADING_INTEL))


@functools.lru_cache(maxsize=1)
def mkl_library() -> Any | None:
    """The MKL runtime library (``libmkl_rt``) with its PARDISO signature declared, or None
    when it is not installed or does not run the LP64 interface (logged)."""
    for path in _candidates():
        try:
            lib = ctypes.CDLL(path)
            lib.pardiso  # noqa: B018  (the symbol must exist)
            lib.MKL_Set_Num_Threads_Local  # noqa: B018
        except (OSError, AttributeError):
            continue
        pin_threading_layer(lib)
        if not interface_is_lp64(lib):
            log.warning("MKL at %s runs the ILP64 interface; its 32-bit calls are not used "
                        "(scipy instead)", path)
            return None
        P = ctypes.POINTER
        lib.pardiso.restype = None
        lib.pardiso.argtypes = [P(ctypes.c_int64)] + [P(ctypes.c_int32)] * 5 + [
            ctypes.c_void_p, P(ctypes.c_int32), P(ctypes.c_int32), P(ctypes.c_int32),
            P(ctypes.c_int32), P(ctypes.c_int32), P(ctypes.c_int32), ctypes.c_void_p,
            ctypes.c_void_p, P(ctypes.c_int32)]
        lib.MKL_Set_Num_Threads_Local.restype = ctypes.c_int
        lib.MKL_Set_Num_Threads_Local.argtypes = [ctypes.c_int]
        lib.MKL_Get_Max_Threads.restype = ctypes.c_int
        log.debug("MKL runtime: %s", path)
        return lib
    return None


def max_threads() -> int | None:
    """The threads MKL would use for a call from this thread now, or None without MKL."""
    lib = mkl_library()
    return None if lib is None else int(lib.MKL_Get_Max_Threads())


@contextlib.contextmanager
def threads(count: int | None = None) -> Iterator[Any]:
    """Run MKL on ``count`` threads (default: the cores this process may use) in the
    calling thread for the duration of the block, then restore its previous setting.

    Yields the MKL library (None without MKL: the block then runs without it). With
    ``MKL_NUM_THREADS`` set in the environment, MKL's settings are left as they are."""
    lib = mkl_library()
    if lib is None or "MKL_NUM_THREADS" in os.environ:
        yield lib
        return
    previous = int(lib.MKL_Set_Num_Threads_Local(int(count or usable_cores())))
    try:
        yield lib
    finally:
        lib.MKL_Set_Num_Threads_Local(previous)  # 0: back to the global setting
