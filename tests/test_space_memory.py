"""The FE space built in chunks: the chunked edge numbering, midpoints and element volumes
equal (bit for bit) straightforward references that make every array at once, with
chunks so small that many run and the last one is partial."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.fe import space as space_module
from pipeline.fe import strain
from pipeline.fe.mesh.common import BodyMesh


@pytest.fixture(scope="module")
def body():
    """A refined unit-cube mesh, its tetrahedra listing their vertices in shuffled orders
    (as a mesh file gives them) and its vertices renumbered at random."""
    from skfem import MeshTet

    mesh = MeshTet().refined(3)
    rng = np.random.default_rng(3)
    relabel = rng.permutation(mesh.p.shape[1])
    points = np.empty_like(mesh.p.T)
    points[relabel] = mesh.p.T
    t = relabel[mesh.t.T]
    for row in t:
        rng.shuffle(row)
    return BodyMesh(points, t[rng.permutation(t.shape[0])].astype(np.int64))


def reference_numbering(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Edges as sorted vertex pairs, lexicographic, and each element's edge numbers."""
    pairs = np.sort(t[:, space_module.TET_EDGES].reshape(-1, 2), axis=1)
    edges, inverse = np.unique(pairs, axis=0, return_inverse=True)
    return edges, inverse.reshape(t.shape[0], 6)


@pytest.mark.parametrize("chunk", [1, 7, 64, None])
def test_chunked_edge_numbering_equals_the_reference(body, chunk):
    edges, t2e = space_module.edge_numbering(body.tetrahedra, body.n_vertices, chunk=chunk)
    ref_edges, ref_t2e = reference_numbering(body.tetrahedra)
    assert body.n_tetrahedra > 64 * 20  # many chunks of 64 run
    assert edges.dtype == t2e.dtype == np.int64
    np.testing.assert_array_equal(edges, ref_edges)
    np.testing.assert_array_equal(t2e, ref_t2e)


def test_space_built_in_small_chunks_equals_the_reference(body, monkeypatch):
    monkeypatch.setattr(space_module, "EDGE_CHUNK", 5)
    space = space_module.build_space(body, 2)
    edges, t2e = reference_numbering(body.tetrahedra)
    v = body.vertices
    np.testing.assert_array_equal(space.edges, edges)
    np.testing.assert_array_equal(space.node_points,
                                  np.vstack([v, 0.5 * (v[edges[:, 0]] + v[edges[:, 1]])]))
    np.testing.assert_array_equal(space.element_nodes,
                                  np.hstack([body.tetrahedra, body.n_vertices + t2e]))
    assert space.element_nodes.dtype == np.int64
    np.testing.assert_array_equal(space.skfem_mesh.t, body.tetrahedra.T)


def test_element_volumes_in_small_chunks_equal_the_whole_computation(body, monkeypatch):
    space = space_module.build_space(body, 1)
    corners = body.vertices[body.tetrahedra]
    whole = np.abs(np.linalg.det(corners[:, 1:] - corners[:, :1])) / 6.0
    monkeypatch.setattr(strain, "CHUNK", 11)
    np.testing.assert_array_equal(strain.element_volumes(space), whole)
    # the unit cube: the volumes sum to 1 up to round-off of n_t additions
    assert abs(whole.sum() - 1.0) < 1e-14 * body.n_tetrahedra


def test_node_volumes_in_small_chunks_equal_one_bincount(body, monkeypatch):
    space = space_module.build_space(body, 2)
    vol = strain.element_volumes(space)
    en = space.element_nodes
    whole = np.bincount(en.ravel(), weights=np.repeat(vol, en.shape[1]), minlength=space.n_nodes)
    monkeypatch.setattr(strain, "CHUNK", 13)
    np.testing.assert_array_equal(strain.node_volumes(space), whole)
    # each element's volume counted once at each of its 10 nodes
    assert abs(whole.sum() - 10.0) < 1e-14 * en.size
