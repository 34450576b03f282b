"""Assembly: the vectorised kernel equals plain scikit-fem; the pattern, restriction and
storage formats behave as documented."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from pipeline.fe import assemble as asm
from pipeline.fe import pattern as pat
from pipeline.config import Geometry, Material, MeshSpec
from pipeline.fe.space import build_space
from pipeline.fe.mesh import generate_mesh, read_mesh

ALUMINIUM = Material(E=69.0e9, nu=0.33, rho=2700.0)


def _space(tmp_path_factory, order: int, size: float = 0.01):
    path = tmp_path_factory.mktemp("asm") / f"box_{order}.msh"
    generate_mesh(Geometry("box", 0.1, 0.02, 0.03), MeshSpec(order=order, size=size,
                                                             algorithm="delaunay"), path)
    return build_space(read_mesh(path), order)


@pytest.fixture(scope="module", params=[1, 2], ids=["P1", "P2"])
def space(request, tmp_path_factory):
    return _space(tmp_path_factory, request.param)


@pytest.fixture(scope="module")
def matrices(space):
    return asm.assemble_stiffness_mass(space, ALUMINIUM)


def _rel(A, B) -> float:
    return abs(A - B).max() / abs(B).max()


def test_equals_plain_scikit_fem(space, matrices):
    K, M = matrices
    K_ref, M_ref = asm.assemble_reference(space, ALUMINIUM)
    assert K.shape == K_ref.shape == (space.n_dofs, space.n_dofs)
    assert _rel(K, K_ref) < 1e-13
    assert _rel(M, M_ref) < 1e-13


def test_edge_numbering_is_scikit_fems(space):
    """fespace numbers the P2 midpoints with integer keys; scikit-fem's MeshTet must agree
    edge for edge, or the DOF order would differ from skfem's Basis."""
    from skfem import MeshTet

    from pipeline.fe.space import edge_numbering

    body = space.body
    mesh = MeshTet(body.vertices.T.copy(), body.tetrahedra.T.copy(), validate=False,
                   sort_t=False)
    edges, t2e = edge_numbering(body.tetrahedra, body.n_vertices)
    np.testing.assert_array_equal(edges, mesh.edges.T)
    np.testing.assert_array_equal(t2e, mesh.t2e.T)
    assert edges.shape[0] > body.n_vertices  # a real 3D mesh: more edges than vertices


def test_chunks_do_not_change_the_result(space, matrices):
    K, M = matrices
    K2, M2 = asm.assemble_stiffness_mass(space, ALUMINIUM, chunk_size=37)
    assert _rel(K2, K) < 1e-14 and _rel(M2, M) < 1e-14


def test_progress_counts_every_element(space):
    done = []
    asm.assemble_stiffness_mass(space, ALUMINIUM, chunk_size=50, progress=done.append)
    assert sum(done) == space.body.n_tetrahedra


def test_storage_symmetric_32bit_and_mass_without_zeros(space, matrices):
    K, M = matrices
    for A in (K, M):
        assert A.indices.dtype == np.int32 and A.indptr.dtype == np.int32
        assert A.has_sorted_indices
        assert abs(A - A.T).max() <= 1e-12 * abs(A).max()
    # K: full 3x3 node blocks; M: only equal components couple (a third of K's entries)
    assert K.nnz == 9 * pat.block_pattern(space).n_blocks
    assert M.nnz * 3 == K.nnz
    rows = np.repeat(np.arange(M.shape[0]), np.diff(M.indptr))
    assert np.all(rows % 3 == M.indices % 3)


def test_rigid_motions_are_free_and_mass_is_exact(space, matrices):
    K, M = matrices
    x = space.node_points
    n = space.n_nodes
    translations = np.kron(np.ones(n), np.eye(3)).T  # (3n, 3)
    rotation = np.zeros((n, 3))
    rotation[:, 0], rotation[:, 1] = -x[:, 1], x[:, 0]  # about z
    for u in list(translations.T) + [rotation.ravel()]:
        assert np.linalg.norm(K @ u) <= 1e-9 * abs(K).max() * np.linalg.norm(u)
    mass = translations[:, 0] @ (M @ translations[:, 0])
    assert mass == pytest.approx(ALUMINIUM.rho * 0.1 * 0.02 * 0.03, rel=1e-12)


def _pattern_by_unique(space):
    """The node-pair pattern by ``np.unique`` of all element pair keys: an independent
    construction of indptr, indices and every pair's block index."""
    en = space.element_nodes.astype(np.int64)
    n_t, nb = en.shape
    n = space.n_nodes
    keys = np.repeat(en, nb, axis=1).reshape(-1) * n + np.tile(en, (1, nb)).reshape(-1)
    unique, slots = np.unique(keys, return_inverse=True)
    indptr = np.concatenate([[0], np.cumsum(np.bincount(unique // n, minlength=n))])
    return indptr, unique % n, slots.reshape(n_t, nb * nb)


@pytest.mark.parametrize("threads", [1, 2])
def test_pattern_equals_unique_pairs(space, threads):
    indptr, indices, slots = _pattern_by_unique(space)
    pattern = pat.block_pattern(space, threads=threads)
    assert np.array_equal(pattern.indptr, indptr)
    assert np.array_equal(pattern.indices, indices)
    assert np.array_equal(pattern.slots, slots)


def test_pattern_public_fallback_equals_fast_path(space, monkeypatch):
    fast = pat.block_pattern(space)
    from scipy.sparse import _sparsetools

    monkeypatch.delattr(_sparsetools, "csr_sample_values")
    slow = pat.block_pattern(space)
    assert np.array_equal(fast.slots, slow.slots)


@pytest.mark.parametrize("overwrite", [False, True])
def test_restrict_equals_fancy_indexing(matrices, overwrite):
    K, _ = matrices
    n = K.shape[0]
    keep = np.sort(np.random.default_rng(3).choice(n, 2 * n // 3, replace=False))
    expected = K[keep][:, keep]
    source = K.copy() if overwrite else K
    R = asm.restrict(source, keep, overwrite=overwrite)
    assert R.shape == (keep.size, keep.size)
    assert R.indices.dtype == np.int32
    assert R.has_sorted_indices
    assert abs(R - expected).max() == 0.0
    assert R.nnz == expected.nnz
    if overwrite:
        assert source.data.size == 0  # emptied: a second copy never existed
    else:
        assert abs(K - K.copy()).max() == 0.0 and K.nnz == 9 * (K.nnz // 9)


def test_restrict_keeps_everything_and_accepts_other_formats(matrices):
    K, _ = matrices
    n = K.shape[0]
    assert asm.restrict(K, np.arange(n)) is K
    keep = np.arange(0, n, 2)
    R = asm.restrict(sp.coo_matrix(K), keep)
    assert abs(R - K[keep][:, keep]).max() == 0.0


@pytest.mark.parametrize("change", [{"nu": 0.5}, {"nu": 0.6}, {"nu": -1.0}, {"E": -1.0},
                                    {"rho": 0.0}])
def test_a_material_without_positive_definite_matrices_is_refused(space, change):
    import dataclasses

    from pipeline.errors import SolverError

    bad = dataclasses.replace(ALUMINIUM, **change)
    with pytest.raises(SolverError, match=r"material .*expected E > 0, -1 < nu < 0\.5"):
        asm.assemble_stiffness_mass(space, bad)


@pytest.mark.parametrize("which", ["whole nodes", "some components", "none fixed"])
def test_stiffness_straight_onto_free_dofs_equals_restriction(space, matrices, which):
    """assemble_on_nodes(..., nodes) drops fixed nodes' blocks before anything is summed
    when whole nodes are fixed; other supports restrict the whole matrix. Both must equal
    K[free][:, free] exactly (same structure; values summed in the same order)."""
    K, M = matrices
    x = space.node_points[:, 0]
    if which == "whole nodes":
        fixed_nodes = np.flatnonzero(x < x.min() + 0.3 * np.ptp(x))
        fixed = (3 * fixed_nodes[:, None] + np.arange(3)).ravel()
    elif which == "some components":
        fixed = np.union1d(3 * np.flatnonzero(x < x.min() + 1e-9),
                           3 * np.arange(space.n_nodes) + 2)
    else:
        fixed = np.zeros(0, dtype=np.int64)
    free = np.setdiff1d(np.arange(space.n_dofs), fixed)
    nodes = asm.whole_nodes(free, space.n_nodes)
    assert (nodes is not None) == (which != "some components")
    assembled = asm.assemble_on_nodes(space, ALUMINIUM, nodes)
    Kf, Mf = assembled.K, assembled.M
    if nodes is None:
        Kf = asm.restrict(Kf, free, overwrite=True)
        Mf = asm.restrict(Mf, free, overwrite=True)
    for A, full in ((Kf, K), (Mf, M)):
        ref = full[free][:, free].tocsr()
        ref.sort_indices()
        assert A.shape == ref.shape and A.has_sorted_indices
        np.testing.assert_array_equal(A.indptr, ref.indptr)
        np.testing.assert_array_equal(A.indices, ref.indices)
        np.testing.assert_array_equal(A.data, ref.data)
        assert A.indices.dtype == np.int32
    # the spare rows were cut off in place, not by holding a view of a larger array
    assert (Kf.data.base if Kf.data.base is not None else Kf.data).size == Kf.nnz


def test_scatter_fallback_equals_fast_path(space, matrices, monkeypatch):
    """Without scipy's private CSC kernel the element sums fall back to np.add.at; the
    two sum the same element values in different orders, so they agree to the round-off of
    a sum of at most n_t terms per entry (bounded here by 1e-13 of the largest entry)."""
    from scipy.sparse import _sparsetools

    K, M = matrices
    monkeypatch.delattr(_sparsetools, "csc_matvecs")
    K2, M2 = asm.assemble_stiffness_mass(space, ALUMINIUM)
    assert _rel(K2, K) < 1e-13 and _rel(M2, M) < 1e-13


@pytest.mark.parametrize("threads", [1, 2])
def test_threads_do_not_change_a_bit(space, matrices, threads):
    """The elements are always summed in the same two halves, so one thread or two give
    bitwise the same K and mass blocks (the result does not depend on the machine)."""
    K, M = matrices
    lower, upper, _ = asm.element_groups(space)
    chunk = min(lower.size, upper.size) // 8  # small enough for the threaded branch
    assert chunk >= 4
    pattern = pat.block_pattern(space)
    one = asm.assemble_on_nodes(space, ALUMINIUM, None, pattern, chunk_size=chunk,
                                threads=threads)
    other = asm.assemble_on_nodes(space, ALUMINIUM, None, pattern, chunk_size=chunk,
                                  threads=3 - threads)
    np.testing.assert_array_equal(one.K.data, other.K.data)
    np.testing.assert_array_equal(one.node_mass.data, other.node_mass.data)
    assert _rel(one.K, K) < 1e-14 and _rel(one.M, M) < 1e-14
    # the node-level mass is M's: M = node_mass (x) I_3
    assert _rel(sp.kron(one.node_mass, sp.identity(3)).tocsr(), M) < 1e-15


@pytest.mark.parametrize("threads", [1, 2])
def test_chunked_index_steps_equal_one_pass(space, monkeypatch, threads):
    """The pattern's slot look-up, K's layout and M's gather run by chunks on two
    threads at scale; with chunks of a few blocks and elements on this small body (some
    nodes dropped) they give bitwise the same K, M and node masses as one pass."""
    x = space.node_points[:, 0]
    nodes = np.flatnonzero(x >= x.min() + 0.2 * np.ptp(x))
    whole = asm.assemble_on_nodes(space, ALUMINIUM, nodes, threads=1)
    monkeypatch.setattr(pat, "LAYOUT_CHUNK_BLOCKS", 97)
    monkeypatch.setattr(pat, "SLOT_CHUNK_ELEMENTS", 3)
    assert len(pat._row_chunks(pat.block_pattern(space).indptr)[1]) > 3
    chunked = asm.assemble_on_nodes(space, ALUMINIUM, nodes, threads=threads)
    for name in ("K", "M", "node_mass"):
        a, b = getattr(chunked, name), getattr(whole, name)
        for field in ("indptr", "indices", "data"):
            np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    assert whole.K.shape == (3 * nodes.size,) * 2


def test_64_bit_indices_give_the_same_matrices(space, monkeypatch):
    """Above 2^31 entries every index array is 64-bit (a body of tens of millions of
    DOFs): with the limit lowered, this small body takes that path (scipy narrows the
    final matrices' indices again where they fit) and gives the same K and M."""
    x = space.node_points[:, 0]
    nodes = np.flatnonzero(x >= x.min() + 0.2 * np.ptp(x))
    narrow = asm.assemble_on_nodes(space, ALUMINIUM, nodes)
    monkeypatch.setattr(pat, "INT32_MAX", 1000)
    monkeypatch.setattr(pat, "LAYOUT_CHUNK_BLOCKS", 97)
    pattern = pat.block_pattern(space, threads=2)
    assert pattern.indices.dtype == pattern.slots.dtype == np.int64
    assert pat.stiffness_layout(pattern, nodes, threads=2).indices.dtype == np.int64
    wide = asm.assemble_on_nodes(space, ALUMINIUM, nodes, pattern, threads=2)
    for name in ("K", "M", "node_mass"):
        a, b = getattr(wide, name), getattr(narrow, name)
        for field in ("indptr", "indices", "data"):
            np.testing.assert_array_equal(getattr(a, field), getattr(b, field))


def test_element_groups_split_the_rows_and_cover_every_element(space):
    """The two halves summed side by side must never write the same node row: no node
    of the lower group's elements is a node of the upper group's; with the cut layer the
    three groups are a partition of the elements."""
    lower, upper, cut = asm.element_groups(space)
    en = space.element_nodes
    assert np.intersect1d(en[lower], en[upper]).size == 0
    together = np.concatenate([lower, upper, cut])
    assert np.array_equal(np.sort(together), np.arange(space.body.n_tetrahedra))
    assert min(lower.size, upper.size) > cut.size  # a layer, not the bulk


def test_body_properties_from_the_node_level_mass_equal_the_full_mass(space, matrices):
    """body_properties accepts M = N (x) I_3 as N: mass, centre of mass and inertia must
    agree with R^T M R on the full (3n x 3n) matrix to round-off."""
    from pipeline.fe.body import body_properties

    _, M = matrices
    node_mass = asm.assemble_on_nodes(space, ALUMINIUM).node_mass
    full = body_properties(M, space.node_points)
    nodal = body_properties(node_mass, space.node_points)
    assert nodal.mass == pytest.approx(full.mass, rel=1e-13)
    np.testing.assert_allclose(nodal.rigid_mass, full.rigid_mass, rtol=0,
                               atol=1e-13 * np.abs(full.rigid_mass).max())


def test_a_failing_half_stops_the_other_at_its_next_chunk(space, monkeypatch):
    """An exception in one thread (here from the progress callback; an interrupt takes the
    same path in the main thread) propagates, and the other half stops at its next chunk
    instead of summing the rest of the body. The other half's progress call waits until
    the stop is set, so the check does not depend on how fast either thread runs."""
    import threading
    import types

    stops = []

    def event() -> threading.Event:
        stops.append(threading.Event())
        return stops[-1]

    monkeypatch.setattr(asm, "threading", types.SimpleNamespace(Event=event,
                                                                Lock=threading.Lock))
    lower, upper, _ = asm.element_groups(space)
    chunk = min(lower.size, upper.size) // 8
    calls = []

    def progress(n):
        calls.append(n)
        if len(calls) == 1:
            raise RuntimeError("stop here")
        assert stops[0].wait(timeout=60), "the failure never set the stop"

    with pytest.raises(RuntimeError, match="stop here"):
        asm.assemble_on_nodes(space, ALUMINIUM, chunk_size=chunk, progress=progress,
                              threads=2)
    # the failing chunk and at most one of the other half: without the stop the other
    # half would report all of its >= 8 chunks
    assert len(stops) == 1 and stops[0].is_set() and len(calls) <= 2, len(calls)


def test_the_stiffness_pattern_hook_gets_the_final_structure_of_k(tmp_path):
    """build_fe_model hands K's CSR structure on the free DOFs to on_stiffness_pattern
    before the values exist (the solver analyses it meanwhile): exactly K's."""
    from conftest import ROOT
    from pipeline.config import load_config
    from pipeline.fe.model import build_fe_model

    cfg = load_config(ROOT / "configs" / "cantilever.yaml", ["mesh.size=0.02"])
    seen = []
    fe = build_fe_model(cfg, tmp_path, on_stiffness_pattern=lambda indptr, indices:
                        seen.append((indptr.copy(), indices.copy())))
    assert len(seen) == 1
    assert np.array_equal(seen[0][0], fe.K.indptr) and np.array_equal(seen[0][1], fe.K.indices)


def test_the_stiffness_pattern_hook_runs_before_the_element_pairs_are_looked_up(
        tmp_path, monkeypatch):
    """K's structure comes from the node graph alone, so the solver's analysis of it
    starts before the element slots are looked up and before any element value is
    summed (it then overlaps both); the pattern the hook gets is still exactly K's."""
    from conftest import ROOT
    from pipeline.config import load_config
    from pipeline.fe import model

    events = []
    slots = model.element_slots
    monkeypatch.setattr(model, "element_slots",
                        lambda *a, **k: events.append("slots") or slots(*a, **k))
    cfg = load_config(ROOT / "configs" / "cantilever.yaml", ["mesh.size=0.02"])
    seen = []

    def hook(indptr, indices):
        events.append("pattern")
        seen.append((indptr.copy(), indices.copy()))

    fe = model.build_fe_model(cfg, tmp_path, on_stiffness_pattern=hook)
    assert events == ["pattern", "slots"]
    assert np.array_equal(seen[0][0], fe.K.indptr) and np.array_equal(seen[0][1], fe.K.indices)


def test_the_late_imports_beside_gmsh_leave_no_thread_behind(tmp_path, monkeypatch):
    """run_pipeline imports the modules the stages after gmsh need on a second thread
    while gmsh meshes; the run joins it, so no thread of the library outlives it."""
    import threading

    from conftest import ROOT
    from pipeline import run
    from pipeline.config import load_config

    names = []
    monkeypatch.setattr(run, "AFTER_MESH_MODULES", ("json", "no_such_module_here"))
    preload = run.preload_stage_modules
    monkeypatch.setattr(run, "preload_stage_modules",
                        lambda modules=run.STAGE_MODULES: names.append(
                            (threading.current_thread().name, modules)) or preload(modules))
    cfg = load_config(ROOT / "configs" / "cantilever.yaml",
                      ["mesh.size=0.02", "modes.count=4"])
    run.run_pipeline(cfg, tmp_path / "out.h5")
    assert names == [("pipeline-imports", ("json", "no_such_module_here"))]
    assert not any(t.name == "pipeline-imports" for t in threading.enumerate())


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_diagonal_in_row_halves_equals_scipys(matrices, monkeypatch, dtype):
    """K's and M's diagonal scanned as two row halves side by side (from
    DIAGONAL_HALVES_ROWS rows, lowered here) is scipy's ``diagonal()`` bit for bit,
    also for a row without a stored diagonal entry, an odd row count and a row whose
    only entry is the diagonal."""
    from pipeline._util import sparse

    monkeypatch.setattr(sparse, "DIAGONAL_HALVES_ROWS", 4)
    for A in matrices:
        odd = A.shape[0] - 1 - A.shape[0] % 2
        A = A.astype(dtype)[:odd, :odd].tolil()
        A[5, 5] = 0.0  # a row without a diagonal entry
        A[7, :] = 0.0
        A[7, 7] = -2.5  # a row holding only its diagonal
        A = A.tocsr()
        A.eliminate_zeros()
        assert A.shape[0] % 2 == 1
        got = sparse.csr_diagonal(A, threads=2)
        assert got.dtype == dtype
        np.testing.assert_array_equal(got, A.diagonal())
        assert got[5] == 0.0 and got[7] == -2.5
