"""Memory awareness: estimate what a mesh will need before assembling it.

The pipeline's peak is the eigensolve: K and M (CSR), the upper triangle handed to the
sparse Cholesky, the factor itself, the Lanczos basis and the mode shapes, on top of
the mesh. The factor dominates from 100k DOFs on; its size under nested dissection
grows like n^(4/3) in 3D. The constants below are calibrated on the cantilever with
``make bench`` (docs/performance.md): at 977k DOFs the PARDISO factor is 8.99 GB and
the whole run peaks at 11.7 GB; the estimate gives 9.1 and 12.1 GB. A compact body
(a casting rather than a beam) fills in more: there the exact factor size, known after
PARDISO's analysis and before its factorisation, is checked again
(:func:`check_factor_memory`, called by :mod:`pipeline.solve.factorization`).
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os

import numpy as np

from pipeline.errors import ResourceError

log = logging.getLogger(__name__)

# bytes of the Cholesky factor per n_dofs^(4/3) (PARDISO, METIS ordering; cantilever:
# 0.38 GB at 101k DOFs, 8.99 GB at 977k DOFs, i.e. 82 and 93 B)
FACTOR_BYTES_COEFF = 93.0
# node blocks (3x3) per node of the node-pair pattern (measured: P2 25.0 at 101k DOFs,
# 26.9 at 1.03M; P1 about 14)
BLOCKS_PER_NODE = {1: 15.0, 2: 27.0}
# bytes per node block while the eigensolve runs: K (9 entries of 8 B value + 4 B index),
# M (3 entries), the upper triangle of K for the factorisation (about 5 entries)
BYTES_PER_BLOCK = 12 * (9 + 3 + 5)
# bytes per node for the mesh, the FE space and region data, and per node during
# assembly (pattern, element factors, both matrices: 2.45 GB measured at 345k nodes)
MESH_BYTES_PER_NODE = 600
ASSEMBLY_BYTES_PER_NODE = 7200
BASELINE_BYTES = 250e6  # interpreter, numpy, scipy, scikit-fem, gmsh, MKL
HEADROOM = 0.9  # use at most this fraction of the available memory
# nodes of a P2 tetrahedral mesh per vertex (about 1.6 nodes per tetrahedron, 0.2 of them
# vertices; measured 7.3 on the cantilever at 101k DOFs)
VERTEX_FRACTION = 7.0
# (n x width) double blocks held by the factor-free LOBPCG (see multigrid_terms; measured
# 12.9 at 371k DOFs, width 25, peak minus the resident memory before LOBPCG)
LOBPCG_BLOCKS = 13
# bytes of the coarse P1 factor of the two-grid path per n_c^(4/3) (PARDISO; cantilever:
# 0.14 GB at 52.8k coarse DOFs, 0.51 GB at 137k, 2.16 GB at 376k: 71, 70 and 80 B)
COARSE_FACTOR_COEFF = 80.0
# from this many free DOFs, modes.method auto tries the factor-free two-grid solver first
# when the mesh is quadratic (crossover on the cantilever about 450k: see
# pipeline.solve.eigen); a slowly converging trial falls back to a factor
MULTIGRID_AUTO_DOFS = 500_000


def usable_cores() -> int:
    """Cores this process may run on (affinity mask), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


@functools.lru_cache(maxsize=1)
def _libc():
    """The C library (ctypes), or None; looked up once (``find_library`` runs
    ``ldconfig`` in a subprocess, about 4 ms a call in a run at 100k DOFs, where
    :func:`release_free_heap` is called half a dozen times)."""
    import ctypes
    import ctypes.util

    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:
        return None


def release_free_heap() -> None:
    """Give the C heap's free pages back to the system (glibc's ``malloc_trim``).

    Worker threads allocate their numpy temporaries in their own malloc arenas, which
    keep their free pages after the threads end (measured: 110-170 MB after the
    threaded assembly at 100k DOFs, raising the run's peak by as much). A no-op where
    the C library has no ``malloc_trim``."""
    lib = _libc()
    if lib is not None and hasattr(lib, "malloc_trim"):
        lib.malloc_trim(0)


@contextlib.contextmanager
def openmp_pools_kept():
    """Put every OpenMP runtime loaded at entry back to the thread count it had, in the
    calling thread, when the block ends.

    gmsh sets the OpenMP thread count (``General.NumThreads``) through whichever OpenMP
    runtime the process loaded first, MKL's included, which would leave the host's pool
    resized. threadpoolctl finds the runtimes on every platform and reads and writes
    their counts through their public C APIs. Only OpenMP pools are touched: restoring a
    BLAS pool would pin it (MKL's restore is thread-local), which is a change of its own.
    Without threadpoolctl the block runs unchanged."""
    try:
        from threadpoolctl import ThreadpoolController
    except ImportError:  # pragma: no cover - a dependency; kept optional for minimal installs
        yield
        return
    with ThreadpoolController().select(user_api="openmp").limit(limits=None):
        yield  # records each runtime's count; restores it on exit


def resident_bytes() -> int:
    """This process's resident memory now (bytes; the peak so far where /proc is absent)."""
    try:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        import resource

        return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024


# glibc mallopt parameters
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, _M_MMAP_MAX = -1, -3, -4
#: measured growth of the peak when freed memory stays in the heap: 5.9 -> 6.8 GB (1.15x)
#: for the factor-free eigensolve at 1M DOFs, 13.6 -> 14.0 GB for the whole factor path
RETAINED_HEAP_GROWTH = 1.25
_retaining = [False]
#: the opt-in: glibc's thresholds are process-wide, so a library call changes them only
#: where the process asked for it (the CLI sets it: pipeline.cli.process)
RETAIN_HEAP_VARIABLE = "PIPELINE_RETAIN_HEAP"


def heap_tuning_allowed() -> bool:
    """True when this process opted in to :func:`retained_heap` (the environment variable
    :data:`RETAIN_HEAP_VARIABLE` is ``1``)."""
    return os.environ.get(RETAIN_HEAP_VARIABLE, "") == "1"


@contextlib.contextmanager
def retained_heap(new_bytes: float):
    """Keep memory freed inside the block in this process (glibc), then give it back.

    An opt-in (:func:`heap_tuning_allowed`: ``PIPELINE_RETAIN_HEAP=1``, which the CLI
    sets for its own process): glibc's ``mallopt`` thresholds belong to the whole
    process, and the defaults restored on exit need not be what the host had set, so
    without the opt-in the block runs unchanged and yields False.

    On the VMs this project runs on, memory the guest has not written for a few seconds
    is handed back to the host, and writing it again costs 2.7-3.1 s/GB (docs/
    performance.md). An iterative solver that frees and allocates (n x k) blocks every
    sweep pays that again and again: glibc serves such large blocks with mmap and
    returns them to the kernel on free. Inside this block they come from the heap and
    stay there (``M_MMAP_MAX`` = 0, no trimming below 2 GB); on exit the defaults are
    restored and ``malloc_trim`` gives the free pages back. On the factor-free
    eigensolve at 1M DOFs this removes most of the system time, about a third of the
    LOBPCG stage, for about 15 % more peak memory (docs/performance.md, ``make bench``).

    ``new_bytes``: what the block will allocate beyond the current resident memory. The
    heap is kept only when RETAINED_HEAP_GROWTH times the resulting peak still fits
    (the heap cannot reuse every hole); else, and where the C library has no
    ``mallopt``, the block runs unchanged. Yields whether the heap is kept.
    """
    lib = _libc()
    usable = HEADROOM * available_memory_bytes()
    peak = resident_bytes() + float(new_bytes)
    keep = (heap_tuning_allowed() and lib is not None and hasattr(lib, "mallopt")
            and not _retaining[0]
            and float(new_bytes) + (RETAINED_HEAP_GROWTH - 1.0) * peak <= usable)
    def restore() -> None:
        lib.mallopt(_M_MMAP_MAX, 65536)  # glibc's default
        lib.mallopt(_M_TRIM_THRESHOLD, 128 * 1024)
        # setting a threshold stops glibc's own adjustment; 32 MB is where it ends up
        lib.mallopt(_M_MMAP_THRESHOLD, 32 * 2**20)
        if hasattr(lib, "malloc_trim"):
            lib.malloc_trim(0)

    if keep:
        set_ = [bool(lib.mallopt(_M_MMAP_MAX, 0)),
                bool(lib.mallopt(_M_TRIM_THRESHOLD, 2**31 - 1))]
        keep = all(set_)
        if any(set_) and not keep:
            restore()
    if not keep:
        yield False
        return
    _retaining[0] = True
    try:
        yield True
    finally:
        restore()
        _retaining[0] = False


#: a cgroup's memory files, v2 then v1: (its limit, its usage, its statistics, the
#: statistic of the inactive file pages it may reclaim)
CGROUP_MEMORY = (
    ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current",
     "/sys/fs/cgroup/memory.stat", "inactive_file"),
    ("/sys/fs/cgroup/memory/memory.limit_in_bytes",
     "/sys/fs/cgroup/memory/memory.usage_in_bytes",
     "/sys/fs/cgroup/memory/memory.stat", "total_inactive_file"),
)


def _read_int(path: str) -> int | None:
    try:
        text = open(path).read().strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None  # "max": no limit


def cgroup_left_bytes() -> int | None:
    """What this process's cgroup memory limit still leaves (bytes): the limit minus
    the cgroup's usage (every process in it, this one included) less its inactive file
    pages, which the kernel reclaims before it refuses memory; the smallest over the
    cgroup files found (:data:`CGROUP_MEMORY`), None without a limit."""
    left = None
    for limit_file, usage_file, stat_file, inactive_key in CGROUP_MEMORY:
        limit = _read_int(limit_file)
        if limit is None:
            continue
        used = _read_int(usage_file) or 0
        try:
            with open(stat_file) as fh:
                for line in fh:
                    key, _, value = line.partition(" ")
                    if key == inactive_key and value.strip().isdigit():
                        used -= int(value)
                        break
        except OSError:
            pass
        here = max(0, limit - max(used, 0))
        left = here if left is None else min(left, here)
    return left


def available_memory_bytes() -> int:
    """Memory this process may still take (bytes): MemAvailable, capped by what a
    cgroup limit leaves (:func:`cgroup_left_bytes`: the limit less what the cgroup
    uses, not the limit itself, which counted the memory already held twice)."""
    avail = None
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    avail = int(line.split()[1]) * 1024
                    break
    except OSError:
        pass
    if avail is None:
        avail = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    left = cgroup_left_bytes()
    if left is not None:
        avail = min(avail, left)
    return int(avail)


def factor_bytes(n_dofs: int) -> float:
    """Estimated bytes of the sparse Cholesky factor of an n_dofs stiffness matrix."""
    return FACTOR_BYTES_COEFF * float(n_dofs) ** (4.0 / 3.0)


def lobpcg_guard(n_modes: int) -> int:
    """Guard columns of the factor-free LOBPCG beside ``n_modes`` wanted ones."""
    return max(3, n_modes // 4)


def lobpcg_layout(n_dofs: int, n_modes: int, guard: int, free_bytes: float) -> tuple[int, int]:
    """(batch, guard): the modes per LOBPCG batch and the guard columns of each
    (:mod:`pipeline.solve.batched`) whose blocks fit in ``free_bytes``.

    One batch of all ``n_modes`` with ``guard`` columns when it fits (LOBPCG_BLOCKS
    blocks of (n_dofs x (n_modes + guard)) doubles); else fewer guard columns (down to
    1); else batches of b modes with max(2, min(guard, b // 2)) guard columns, which
    also keep the modes found before (Y and M Y: 2 n_dofs (n_modes - b) doubles); the
    largest b that fits, else the smallest layout."""
    if guard < 1:  # the coarse space limits the block: no room to choose
        return n_modes, guard

    def need(b: int, g: int) -> float:
        return 8.0 * n_dofs * (LOBPCG_BLOCKS * (b + g) + 2 * (n_modes - b))

    for g in range(guard, 0, -1):
        if need(n_modes, g) <= free_bytes:
            return n_modes, g
    for b in range(n_modes - 1, 0, -1):
        g = max(2, min(guard, b // 2))
        if need(b, g) <= free_bytes:
            return b, g
    return 1, 2


def multigrid_terms(n_nodes: int, n_modes: int, free_bytes: float = float("inf")
                    ) -> dict[str, float]:
    """Bytes of the factor-free path (:mod:`pipeline.solve.multigrid`, quadratic mesh of
    ``n_nodes`` nodes, n = 3 n_nodes DOFs) while LOBPCG runs, its peak, term by term:

    - ``K``, ``M``: CSR with 32-bit indices, 12 B an entry: K 9 and M 3 entries (M
      couples equal components only) per node block, BLOCKS_PER_NODE[2] blocks a node;
    - ``float32 D^-1 K``: the smoother's copy (4 B an entry, indices shared with K) and
      the diagonals D^-1 in double and float32;
    - ``prolongation``: P, P^T and P^T D (about 1.9 entries a row, 12 B each);
    - ``coarse factor``: the P1 problem on the vertices (n / VERTEX_FRACTION DOFs),
      COARSE_FACTOR_COEFF * n_c^(4/3);
    - ``LOBPCG``: LOBPCG_BLOCKS blocks of (n x (b + g)) doubles and the modes of earlier
      batches (:func:`lobpcg_layout` for what is left of ``free_bytes``).
    The mesh, the FE space and the interpreter are the caller's
    (:func:`estimate_memory_bytes`); after LOBPCG the path needs less (the modes, and
    PCG's PCG_BLOCKS blocks as wide as the load cases for the static correction).
    """
    n = 3.0 * n_nodes
    blocks = BLOCKS_PER_NODE[2] * n_nodes
    terms = {"K": 12.0 * 9 * blocks, "M": 12.0 * 3 * blocks,
             "float32 D^-1 K": 4.0 * 9 * blocks + 12.0 * n,
             "prolongation": 3 * 12.0 * 1.9 * n,
             "coarse factor": COARSE_FACTOR_COEFF * (n / VERTEX_FRACTION) ** (4.0 / 3.0)}
    # what the caller adds (interpreter, mesh) is not free for LOBPCG either
    left = free_bytes - sum(terms.values()) - BASELINE_BYTES - MESH_BYTES_PER_NODE * n_nodes
    batch, guard = lobpcg_layout(int(n), n_modes, lobpcg_guard(n_modes), left)
    terms["LOBPCG"] = 8.0 * n * (LOBPCG_BLOCKS * (batch + guard) + 2 * (n_modes - batch))
    return terms


def multigrid_bytes(n_nodes: int, n_modes: int, free_bytes: float = float("inf")) -> float:
    """Peak bytes of the factor-free path, K and M included (:func:`multigrid_terms`)."""
    return float(sum(multigrid_terms(n_nodes, n_modes, free_bytes).values()))


def factor_path_bytes(n_dofs: int, n_modes: int, single: bool = False) -> float:
    """Bytes a shift-invert solve needs beside K and M: the factor (half of it in float32),
    the Lanczos basis with its images F^-T v (kept so the Ritz vectors need no final
    solve) and the Ritz vectors with K and M times them."""
    block = 4 if n_modes <= 4 else 8
    lanczos = 2 * 8.0 * n_dofs * (max(3 * n_modes + 4 * block, n_modes + 8 * block) + block)
    shapes = 8.0 * n_dofs * n_modes * 4
    return factor_bytes(n_dofs) * (0.5 if single else 1.0) + lanczos + shapes


def eigensolve_bytes(n_nodes: int, order: int, n_modes: int, method: str = "auto",
                     available: int | None = None, solver: str = "auto") -> float:
    """Peak bytes of the modes stage on top of the mesh: K, M and the eigensolver that
    :func:`pipeline.solve.eigen.solve_modes` will choose, by the same rule: (``auto``,
    order 2, from :data:`MULTIGRID_AUTO_DOFS` DOFs) the factor-free multigrid solver
    (:func:`multigrid_bytes`), else a double factor if it fits, else a float32 one, else
    (``auto``, order 2) the multigrid solver; ``multigrid`` always the latter,
    ``factor`` never. When nothing fits, the smallest of the allowed ones. ``solver``
    ``cudss`` (the GPU) keeps the factor in GPU memory (checked against cuDSS's own
    estimate when it is known): here only the host's part of its path.
    """
    n = 3 * n_nodes
    matrices = BYTES_PER_BLOCK * BLOCKS_PER_NODE.get(order, 27.0) * n_nodes
    if solver == "cudss" and method != "multigrid":
        return matrices + factor_path_bytes(n, n_modes) - factor_bytes(n)
    usable = HEADROOM * (available_memory_bytes() if available is None else available)
    options = []
    two_grid = multigrid_bytes(n_nodes, n_modes, usable)
    if method == "auto" and order == 2 and n >= MULTIGRID_AUTO_DOFS:
        options.append(two_grid)  # tried first (its fallback factor is checked exactly)
    if method in ("auto", "factor"):
        options += [matrices + factor_path_bytes(n, n_modes, single)
                    for single in (False, True)]
    if method == "multigrid" or (method == "auto" and order == 2):
        options.append(two_grid)
    if not options:
        raise ValueError(f"method '{method}': expected auto, factor or multigrid")
    return next((need for need in options if need <= usable), min(options))


def estimate_memory_bytes(n_nodes: int, n_elements: int, order: int, n_modes: int,
                          method: str = "auto", available: int | None = None,
                          solver: str = "auto") -> int:
    """Peak bytes of the whole pipeline for a mesh of this size (see the module doc)."""
    mesh = MESH_BYTES_PER_NODE * n_nodes + 64 * n_elements
    assembly = ASSEMBLY_BYTES_PER_NODE * n_nodes + 400 * n_elements
    eigensolve = eigensolve_bytes(n_nodes, order, n_modes, method, available, solver)
    return int(BASELINE_BYTES + mesh + max(assembly, eigensolve))


def typical_edge_length(space) -> float:
    """Edge length (m) of a regular tetrahedron of the mesh's mean element volume."""
    v = space.body.vertices
    t = space.body.tetrahedra
    a = v[t[:, 0]]
    vol6 = np.abs(np.einsum("ij,ij->i", np.cross(v[t[:, 1]] - a, v[t[:, 2]] - a),
                            v[t[:, 3]] - a))
    return float((np.sqrt(2.0) * vol6.mean()) ** (1.0 / 3.0))


def _scale_to_fit(need: float, have: float, exponent: float = 4.0) -> float:
    """Factor on the element size that brings ``need`` within the usable memory.

    DOFs scale like size^-3 and the dominant factor like DOFs^(4/3), so memory like
    size^-4.
    """
    return max(1.0, (need / (HEADROOM * have)) ** (1.0 / exponent)) * 1.05


def beyond_usable(need: float, have: float, available: str = "available") -> str:
    """The clause of a memory refusal: ``need`` bytes against the HEADROOM share of
    ``have`` that a run may use, with both figures, so that a need between the usable
    share and all of ``have`` does not read as fitting.

    >>> beyond_usable(0.95e9, 1.0e9)
    'more than the 0.90 GB usable (90% of the 1.00 GB available)'
    """
    digits = 1 if have >= 10e9 else 2  # two decimals below 10 GB: 0.28 is not 0.3
    return (f"more than the {HEADROOM * have / 1e9:.{digits}f} GB usable ({HEADROOM:.0%} "
            f"of the {have / 1e9:.{digits}f} GB {available})")


def check_memory(space, n_modes: int, available: int | None = None,
                 method: str = "auto", solver: str = "auto") -> int:
    """Refuse a mesh whose estimate exceeds the available memory (ResourceError).

    Returns the estimate in bytes. The message gives both figures and the ``mesh.size``
    (m) that would fit, scaling memory like size^-4: the one the mesh was made with
    (``space.body.element_size``) times that factor, where it made the mesh (gmsh's edges
    are not mesh.size long: 1.27 times it on the cantilever at 0.00146 m); else how much
    coarser a mesh of the file's own elements must be.
    """
    have = available_memory_bytes() if available is None else int(available)
    need = estimate_memory_bytes(space.n_nodes, space.body.n_tetrahedra, space.order, n_modes,
                                 method, have, solver)
    log.info("memory estimate %.2f GB of %.2f GB available", need / 1e9, have / 1e9)
    if need > HEADROOM * have:
        factor = _scale_to_fit(need, have)
        size = space.body.element_size
        if size:
            fit = (f"a mesh.size of about {size * factor:.3g} m (now {size:g} m, i.e. "
                   f"{factor:.2f} times larger) would fit")
        else:
            fit = (f"a mesh about {factor:.2f} times coarser would fit (its elements' "
                   f"typical edge is now {typical_edge_length(space):.3g} m; mesh.size does "
                   "not change the elements of a mesh file or of a script that meshes itself)")
        raise ResourceError(f"mesh with {space.n_dofs} DOFs needs about {need / 1e9:.1f} GB, "
                            f"{beyond_usable(need, have)}; {fit}")
    return need


def coarser_mesh(factor: float) -> str:
    """What makes a mesh ``factor`` times coarser, for a refusal that does not know where
    the mesh came from.

    >>> coarser_mesh(1.5)
    'mesh.size 1.50 times larger where gmsh makes the mesh'
    """
    return f"mesh.size {factor:.2f} times larger where gmsh makes the mesh"


def check_factor_memory(factor_bytes_exact: float, n_dofs: int,
                        available: int | None = None) -> None:
    """Refuse to factorise when the factor (known after the analysis) will not fit."""
    have = available_memory_bytes() if available is None else int(available)
    if factor_bytes_exact > HEADROOM * have:
        factor = _scale_to_fit(factor_bytes_exact, have)
        raise ResourceError(
            f"the sparse factorisation of the {n_dofs}-DOF stiffness matrix needs "
            f"{factor_bytes_exact / 1e9:.1f} GB, {beyond_usable(factor_bytes_exact, have)}; "
            f"a mesh about {factor:.2f} times coarser would fit ({coarser_mesh(factor)})")


@contextlib.contextmanager
def environment_kept():
    """Give ``os.environ`` back on exit as it was on entry: variables set inside the block
    are removed, changed ones get their old value.

    For third-party code that writes the host's environment: dask's ``Nanny`` sets its
    workers' variables (``MKL_NUM_THREADS=1``, ``OMP_NUM_THREADS=1``, ``PYTHONHASHSEED``,
    ``MALLOC_TRIM_THRESHOLD_``) in the process that starts them. Left there, every process
    the host starts later inherits them: a ``python -m pipeline run`` child then solved on
    one MKL thread, the host on two, and the residual flexibility (a difference of nearly
    equal terms, summed in another order) of the two runs of one config differed by
    1.6e-7 of itself."""
    saved = dict(os.environ)
    try:
        yield
    finally:
        for name in [k for k in os.environ if k not in saved]:
            del os.environ[name]
        for name, value in saved.items():
            if os.environ.get(name) != value:
                os.environ[name] = value
