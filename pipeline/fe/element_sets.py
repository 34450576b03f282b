"""Named sets of elements of a mesh file (gmsh physical volumes, Abaqus ``*ELSET``), as
indices of the body's tetrahedra: what a ``materials`` or ``masses`` entry names with
``elements: NAME``.

:func:`pipeline.fe.mesh.read.read_mesh` renumbers the file's vertices and reorders its
tetrahedra; :func:`element_sets_of` finds each set's tetrahedra again among the body's by
their four (renumbered) vertices.
"""

from __future__ import annotations

import numpy as np

TETRA = ("tetra", "tetra10")


def _rows(a: np.ndarray) -> np.ndarray:
    """Rows of an (n, 4) int64 array as one structured (lexicographically ordered) value each."""
    a = np.ascontiguousarray(a, dtype=np.int64)
    return a.view([(f"c{i}", np.int64) for i in range(a.shape[1])]).ravel()


def element_sets_of(mesh, renumber: np.ndarray, tetrahedra: np.ndarray
                    ) -> dict[str, np.ndarray]:
    """name -> sorted indices into ``tetrahedra`` (n_t, 4) of every named set of
    tetrahedra of the meshio ``mesh``; ``renumber`` maps the file's point indices to the
    body's vertex indices. A set whose cells are not all found is left out (its name then
    matches nothing, and a config naming it is told so)."""
    table = order = None  # made for the first set that is not the whole body
    out = {}
    for name, per_block in (mesh.cell_sets or {}).items():
        if name.startswith("gmsh:"):
            continue
        tets = [b.data[np.asarray(ids, dtype=np.int64), :4] for b, ids in zip(mesh.cells, per_block)
                if b.type in TETRA and ids is not None and len(ids)]
        if not tets or not len(tetrahedra):
            continue
        if _whole(mesh, per_block, len(tetrahedra)):  # e.g. gmsh's one physical volume
            out[name] = np.arange(len(tetrahedra))
            continue
        if table is None:  # sorting the rows is the cost: 0.6 s at 1M DOFs
            table = _rows(np.sort(tetrahedra, axis=1))
            order = np.argsort(table, kind="stable")
        keys = _rows(np.sort(renumber[np.concatenate(tets).astype(np.int64)], axis=1))
        pos = np.searchsorted(table[order], keys).clip(0, table.size - 1)
        if np.all(table[order][pos] == keys):
            out[name] = np.unique(order[pos])
    return out


def _whole(mesh, per_block, n_tetrahedra: int) -> bool:
    """Whether a cell set holds every tetrahedron of the file, each once, and the body's
    ``n_tetrahedra`` are all of the file's (read_mesh keeps every tetrahedron)."""
    n_file = 0
    for b, ids in zip(mesh.cells, per_block):
        if b.type not in TETRA:
            continue
        n_file += len(b.data)
        if ids is None or len(ids) != len(b.data):
            return False
        if np.unique(np.asarray(ids, dtype=np.int64)).size != len(b.data):
            return False
    return n_file == n_tetrahedra
