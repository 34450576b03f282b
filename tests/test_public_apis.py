"""Where the package leans on another library's internals, it goes through a public API or
keeps a fallback; each fallback is exercised here by taking the internal away.

- scipy: a ``csr_array`` is taken as it is, like a ``csr_matrix`` (``sp.isspmatrix_csr``
  is False for it; the restriction would have copied it silently);
- scikit-fem: the strain recovery's mapping is the public ``MappingAffine``, the one a
  ``Basis`` builds itself; the fast edge numbering is checked against ``MeshTet.edges``
  and ``MeshTet.t2e`` once, and scikit-fem's own arrays are used where they differ;
- distributed: the clusters left by an interrupted start are found in its private
  registry where there is one, else through the garbage collector.
"""

from __future__ import annotations

import logging

import numpy as np
import pytest
import scipy.sparse as sp

from conftest import build_model
from pipeline.fe import space as space_module
from pipeline.fe import strain
from pipeline.fe.assemble import restrict


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    return build_model(tmp_path_factory.mktemp("apis"), size=0.02, order=2)


# --------------------------------------------------------------------------- scipy
@pytest.mark.parametrize("overwrite", [False, True])
def test_restrict_takes_a_csr_array_as_a_csr_matrix(model, overwrite):
    K = model.K
    keep = np.arange(5, K.shape[0], 2)
    ref = K[keep][:, keep]
    A = sp.csr_array(K, copy=True)
    got = restrict(A, keep, overwrite=overwrite)
    assert isinstance(got, sp.csr_matrix)
    assert abs(got - ref).max() == 0.0
    if overwrite:  # compacted in place: the csr_array given is emptied, not a copy of it
        assert A.data.size == 0 and A.indices.size == 0
    else:
        assert A.nnz == K.nnz
    whole = restrict(sp.csr_array(K), np.arange(K.shape[0]))
    assert isinstance(whole, sp.csr_matrix) and abs(whole - K).max() == 0.0


# --------------------------------------------------------------------------- scikit-fem
def test_strain_mapping_is_the_one_scikit_fem_builds_itself(model):
    from skfem import Basis

    space = model.space
    elements = np.arange(0, space.element_nodes.shape[0], 3)
    ours = strain._basis(space, elements)
    own = Basis(space.skfem_mesh, space.skfem_element(), intorder=2, elements=elements)
    assert type(ours.mapping) is type(own.mapping)
    np.testing.assert_array_equal(ours.dx, own.dx)
    for a, b in zip(ours.basis, own.basis):
        np.testing.assert_array_equal(a[0].grad, b[0].grad)


def test_the_fast_edge_numbering_is_scikit_fems(model):
    assert space_module.edge_numbering_matches_skfem()
    mesh = model.space.skfem_mesh
    edges, t2e = space_module.edge_numbering(model.space.body.tetrahedra,
                                             model.space.body.n_vertices)
    np.testing.assert_array_equal(edges, mesh.edges.T)
    np.testing.assert_array_equal(t2e, mesh.t2e.T)


def test_a_scikit_fem_that_numbers_edges_otherwise_gets_its_own_numbering(model, monkeypatch,
                                                                          caplog):
    monkeypatch.setattr(space_module, "edge_numbering_matches_skfem", lambda: False)
    with caplog.at_level(logging.WARNING, logger=space_module.__name__):
        fallback = space_module.build_space(model.space.body, 2)
    assert "numbers edges differently" in caplog.text
    for name in ("node_points", "element_nodes", "edges"):
        np.testing.assert_array_equal(getattr(fallback, name), getattr(model.space, name))


# --------------------------------------------------------------------------- distributed
def _cluster_class():
    pytest.importorskip("distributed")
    from distributed.deploy.spec import SpecCluster

    class Unstarted(SpecCluster):
        """A cluster object whose start never ran (as when a Ctrl-C cuts it short)."""

        def __init__(self):
            self._cluster_info = {"name": f"unstarted-{id(self)}"}  # what == compares
            self.closed = False

        def close(self, timeout=None):
            self.closed = True

    return SpecCluster, Unstarted


def test_unfinished_clusters_are_closed_from_distributeds_registry(monkeypatch):
    import weakref

    from pipeline.apps.batch.scheduler import close_unfinished_clusters

    SpecCluster, Unstarted = _cluster_class()
    cluster = Unstarted()
    registry = weakref.WeakSet([cluster])
    monkeypatch.setattr(SpecCluster, "_instances", registry)
    close_unfinished_clusters()
    assert cluster.closed and cluster not in registry


def test_unfinished_clusters_are_found_without_the_private_registry(monkeypatch):
    from pipeline.apps.batch.scheduler import close_unfinished_clusters

    SpecCluster, Unstarted = _cluster_class()
    monkeypatch.delattr(SpecCluster, "_instances")
    cluster = Unstarted()
    close_unfinished_clusters()
    assert cluster.closed
