"""A rank's rows of K and M, assembled from the elements that touch its nodes.

Rank r owns the PETSc rows ``lo:hi`` of :class:`~pipeline.distributed.partition.RowPartition`
and holds only its part of the mesh (:class:`~pipeline.distributed.submesh.RankMesh`: the
elements touching its points, local node numbers, the PETSc row of each local DOF).
It assembles K and M on its part with the serial assembly
(:func:`pipeline.fe.assemble.assemble_on_nodes`: the kernels of :mod:`pipeline.fe.kernels`,
K_e[(a, i), (b, j)] = R[a nb + b, :] @ F_e[:, 3 i + j], M_e = rho |det J| M_ref[a, b]
delta_ij, scattered into the part's node-block CSR pattern), keeps the rows it owns and
the free columns, and renumbers them: a local CSR block (hi - lo, n_free) with PETSc's
global column numbers. The elements of the slab's
boundary layer are computed by both neighbours, which is all the communication the
assembly needs; no rank holds another's rows.

The body's node-level mass N (for the mass properties) is split by elements instead:
rank r sums the elements its part marks as its own (``mass_elements``), every element
of the mesh on exactly one rank, so sum_r R_r^T N_r R_r = R^T N R.

Several materials: each element takes its own law (C_e, rho_e) as in the serial
assembly (:func:`pipeline.fe.kernels.element_factors_general`); point and area masses
(the distributing kind) add their owned rows to M.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from pipeline.config import Material
from pipeline.distributed.submesh import RankMesh
from pipeline.fe.assemble import assemble_on_nodes
from pipeline.fe.kernels import inverse_jacobians, reference_data
from pipeline.fe.materials import ElementMaterials


@dataclass(frozen=True)
class LocalRows:
    """K, M: (hi - lo, n_free) CSR rows of this rank (N/m, kg), PETSc's column numbers
    (int32 indices); lo, hi: the rows; n_elements: elements computed here."""

    K: sp.csr_matrix
    M: sp.csr_matrix
    lo: int
    hi: int
    n_elements: int


def _law(material: Material | ElementMaterials) -> Material | ElementMaterials:
    """The one isotropic Material when every element has it (the fast path, bit for bit
    the single-material assembly), else the per-element materials."""
    if isinstance(material, ElementMaterials) and material.uniform is not None:
        return material.uniform
    return material


def local_rows(mesh: RankMesh) -> LocalRows:
    """This rank's rows of K (N/m) and M (kg) on the free DOFs (see the module), from
    its part of the mesh (:class:`~pipeline.distributed.submesh.RankMesh`: its elements
    in the whole mesh's order, their materials, the PETSc row of each local DOF, its rows
    of the point and area masses, which go into M).

    The serial assembly (:func:`pipeline.fe.assemble.assemble_on_nodes`: the node-block
    pattern, element values scattered into CSR) on the part's space, then the rows of
    the DOFs this rank owns, in PETSc's order, with PETSc's column numbers and the held
    columns dropped. The part's other rows (its one element layer of other ranks' nodes)
    are summed too and dropped: their elements are computed here anyway. At 405k free
    DOFs (one rank's half) 0.8 s against 6.1 s for the triplets of 512 elements summed
    pairwise that it replaces."""
    lo, hi = mesh.lo, mesh.hi
    petsc_row = np.asarray(mesh.dof_rows, dtype=np.int64)
    assembled = assemble_on_nodes(mesh.space, _law(mesh.materials))
    owned = np.flatnonzero((petsc_row >= lo) & (petsc_row < hi))
    owned = owned[np.argsort(petsc_row[owned], kind="stable")]
    if owned.size != hi - lo:
        raise AssertionError(f"rank's part holds {owned.size} of its {hi - lo} rows")
    K = _petsc_columns(assembled.K[owned], petsc_row, mesh.n_free)
    M = _petsc_columns(assembled.M[owned], petsc_row, mesh.n_free)
    elements = int(np.count_nonzero(mesh.owned_nodes[mesh.space.element_nodes].any(axis=1)))
    if mesh.added is not None:  # its owned rows, PETSc's row and column numbers
        M = M + mesh.added
    return LocalRows(K=with_int32_indices(K), M=with_int32_indices(M), lo=lo, hi=hi,
                     n_elements=elements)


def _petsc_columns(A: sp.csr_matrix, petsc_row: np.ndarray, n_free: int) -> sp.csr_matrix:
    """Rows of a local-DOF matrix with their columns renumbered to PETSc's (a held DOF,
    PETSc row -1, dropped), (rows, n_free) CSR."""
    A = sp.csr_matrix(A)
    cols = petsc_row[A.indices]
    keep = cols >= 0
    row_of = np.repeat(np.arange(A.shape[0]), np.diff(A.indptr))
    indptr = np.concatenate([[0], np.cumsum(np.bincount(row_of[keep],
                                                        minlength=A.shape[0]))])
    out = sp.csr_matrix((A.data[keep], cols[keep], indptr), shape=(A.shape[0], n_free))
    out.has_sorted_indices = False
    out.sort_indices()
    return out


def with_int32_indices(A: sp.spmatrix) -> sp.csr_matrix:
    """``A`` as CSR with sorted int32 indices (what
    :func:`pipeline.distributed.eigen.petsc_matrix` takes)."""
    A = sp.csr_matrix(A)
    A.sum_duplicates()
    A.sort_indices()
    A.indices = A.indices.astype(np.int32, copy=False)
    A.indptr = A.indptr.astype(np.int32, copy=False)
    return A


def local_node_mass(mesh: RankMesh) -> sp.csr_matrix:
    """(n_loc, n_loc) node-level mass (kg) of the elements whose mass this rank sums
    (``mesh.mass_elements``, local node numbers); over the ranks every element once, so
    the ranks' rigid masses R^T N R add up to the body's (M = N (x) I_3)."""
    space, chunk = mesh.space, mesh.mass_elements
    _, mass_ref = reference_data(space.order)
    _, vol = inverse_jacobians(space, chunk)
    en = space.element_nodes[chunk]
    nb = en.shape[1]
    material = _law(mesh.materials)
    rho = material.rho if isinstance(material, Material) else material.rho[chunk]
    vals = (rho * vol)[:, None, None] * mass_ref[None]
    rows = np.broadcast_to(en[:, :, None], (chunk.size, nb, nb))
    cols = np.broadcast_to(en[:, None, :], (chunk.size, nb, nb))
    return sp.csr_matrix((vals.ravel(), (rows.ravel(), cols.ravel())),
                         shape=(space.n_nodes, space.n_nodes))
