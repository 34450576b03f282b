"""Node indices and coordinates of a mesh read from a user's file, checked before use.

A mesh file (any format meshio reads) lists cells by node index; an index past the node
table, or a used node with a NaN or infinite coordinate, would end in an IndexError or
a NaN stiffness deep in the assembly. :func:`check_nodes` refuses both with one
:class:`~pipeline.errors.MeshError` line naming the file (exit code 3).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.errors import MeshError


def check_nodes(used: np.ndarray, points: np.ndarray, path: str | Path) -> None:
    """``used``: the sorted node indices the volume cells refer to; ``points``: the
    file's node table (n, >= 3). Every index in 0..n-1, every used coordinate finite."""
    n = points.shape[0]
    if used.size and (used[0] < 0 or used[-1] >= n):
        raise MeshError(f"mesh file '{path}': volume cells refer to nodes {int(used[0])}.."
                        f"{int(used[-1])}, expected nodes inside 0..{n - 1} (the file's node "
                        "table); the file is damaged", key=str(path))
    bad = ~np.all(np.isfinite(points[used, :3]), axis=1)
    if np.any(bad):
        raise MeshError(f"mesh file '{path}': {int(bad.sum())} node(s) of its cells have NaN "
                        f"or infinite coordinates (e.g. node {int(used[bad][0])}); expected "
                        "finite coordinates", key=str(path))
