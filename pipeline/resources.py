"""Memory awareness: estimate what a mesh will need before assembling it.

The estimate covers the largest of the phases that coexist in memory: K and M in
CSR (3x3 node blocks), the sparse factorisation of the shifted stiffness, and the
Lanczos vectors. The factor size of 3D nested dissection grows like n^(4/3); the
constant is calibrated on the benchmark (``make bench``, docs/performance.md).
"""

from __future__ import annotations

import logging
import os

from .errors import ResourceError

log = logging.getLogger(__name__)

# bytes of the sparse factor per n_dofs^(4/3); calibrated by benchmarks/bench_pipeline.py
FACTOR_BYTES_COEFF = 110.0
BLOCKS_PER_NODE = {1: 15.0, 2: 25.0}


def available_memory_bytes() -> int:
    """Memory this process may use: MemAvailable, capped by a cgroup limit if any."""
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
    for cg in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            text = open(cg).read().strip()
            if text.isdigit():
                avail = min(avail, int(text))
        except OSError:
            continue
    return int(avail)


def estimate_memory_bytes(n_nodes: int, n_elements: int, order: int, n_modes: int) -> int:
    """Peak bytes of assembly + factorisation + eigensolve for a mesh of this size."""
    n = 3 * n_nodes
    blocks = BLOCKS_PER_NODE.get(order, 25.0) * n_nodes
    matrices = 2 * blocks * 9 * 12  # K and M, CSR (8 B value + 4 B index)
    pattern = n_elements * (10 if order == 2 else 4) ** 2 * 8 * 2  # keys + slots
    factor = FACTOR_BYTES_COEFF * n ** (4.0 / 3.0)
    lanczos = 8 * n * (2 * n_modes + 20) * 2
    return int(max(matrices + pattern, matrices + factor + lanczos) + 300e6)


def check_memory(space, n_modes: int, available: int | None = None) -> int:
    """Refuse a mesh whose estimate exceeds the available memory (ResourceError).

    Returns the estimate in bytes. The message gives both figures and the mesh size
    (element edge length, m) that would fit, scaling DOFs like size^-3.
    """
    need = estimate_memory_bytes(space.n_nodes, space.body.n_tetrahedra, space.order, n_modes)
    have = available_memory_bytes() if available is None else available
    log.info("memory estimate %.2f GB of %.2f GB available", need / 1e9, have / 1e9)
    if need > have:
        # DOFs ~ size^-3 and memory ~ DOFs^(4/3) ~ size^-4
        factor = (need / (0.8 * have)) ** 0.25
        raise ResourceError(
            f"mesh with {3 * space.n_nodes} DOFs needs about {need / 1e9:.1f} GB, but only "
            f"{have / 1e9:.1f} GB is available; a mesh.size about {factor:.2f} times larger "
            "would fit")
    return need
