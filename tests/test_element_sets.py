"""Named element sets of a mesh file found again among the body's tetrahedra
(:func:`pipeline.fe.element_sets.element_sets_of`)."""

import meshio
import numpy as np
import pytest

from pipeline.fe import element_sets


def _mesh_and_body():
    """A meshio mesh of 12 tetrahedra in two blocks (one ``tetra10``), with sets; the body's
    tetrahedra: the file's, vertices renumbered (reversed) and elements shuffled."""
    rng = np.random.default_rng(5)
    points = rng.standard_normal((20, 3))
    tets = np.array([rng.choice(20, 4, replace=False) for _ in range(12)])
    tet10 = np.hstack([tets[7:], np.zeros((5, 6), dtype=tets.dtype)])
    cells = [meshio.CellBlock("tetra", tets[:7]), meshio.CellBlock("triangle", tets[:3, :3]),
             meshio.CellBlock("tetra10", tet10)]
    cell_sets = {
        "body": [np.array([3, 0, 1, 2, 6, 5, 4]), None, np.arange(5)[::-1]],
        "part": [np.array([1, 5]), None, np.array([2])],
        "faces": [None, np.arange(3), None],
        "repeated": [np.array([0, 0, 1, 2, 3, 4, 5]), None, np.arange(5)],
        "gmsh:bounding_entities": [np.arange(7), None, np.arange(5)],
    }
    mesh = meshio.Mesh(points, cells, cell_sets=cell_sets)
    renumber = np.arange(20)[::-1].copy()
    shuffle = rng.permutation(12)
    body = renumber[tets][shuffle]
    return mesh, renumber, body, shuffle


@pytest.mark.parametrize("shortcut", [True, False])
def test_element_sets_are_found_by_their_vertices(monkeypatch, shortcut):
    """Each set's tetrahedra are found in the body whatever their order and vertex
    numbering; a set holding every tetrahedron once is the whole body (found without
    sorting when ``shortcut``, and the same by the vertex search); a set that names one
    tetrahedron twice is not the whole body; face sets and gmsh's own sets are left out."""
    mesh, renumber, body, shuffle = _mesh_and_body()
    whole = element_sets._whole
    if not shortcut:
        monkeypatch.setattr(element_sets, "_whole", lambda *a: False)
    out = element_sets.element_sets_of(mesh, renumber, body)
    where = np.argsort(shuffle)  # file tetrahedron i is body tetrahedron where[i]
    assert set(out) == {"body", "part", "repeated"}
    assert np.array_equal(out["body"], np.arange(12))
    assert np.array_equal(out["part"], np.sort(where[[1, 5, 7 + 2]]))
    assert np.array_equal(out["repeated"], np.sort(where[np.r_[0:6, 7:12]]))
    assert whole(mesh, mesh.cell_sets["body"], 12)
    assert not whole(mesh, mesh.cell_sets["repeated"], 12)
    assert not whole(mesh, mesh.cell_sets["body"], 11)
