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
from pipeline.fe.body import rigid_body_modes
from pipeline.fe.kernels import (element_factors, element_factors_general, inverse_jacobians,
                                 lame_parameters, reference_data)
from pipeline.fe.materials import ElementMaterials, voigt_to_tensor
from pipeline.fe.space import FESpace


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


def element_blocks(mesh: RankMesh, elements: np.ndarray, chunk_size: int = 512):
    """Per chunk of ``elements`` (local numbers) of the part: (local DOFs (m, nb, 3) of
    (node a, component i), K_e[e, a, b, i, j] (N/m), M_e[e, a, b, i] (kg, the i-i entries:
    M_e is diagonal in the components)), with each element's own law."""
    space = mesh.space
    en = space.element_nodes
    material = _law(mesh.materials)
    if isinstance(material, Material):
        lam, mu = lame_parameters(material)
    else:
        C_laws = voigt_to_tensor(material.D)
    R, mass_ref = reference_data(space.order)
    nb = en.shape[1]
    comp = np.arange(3)
    for start in range(0, elements.size, chunk_size):
        chunk = elements[start:start + chunk_size]
        if isinstance(material, Material):
            F, vol = element_factors(space, lam, mu, chunk)
            rho = np.full(chunk.size, material.rho)
        else:
            F, vol = element_factors_general(space, C_laws[material.index[chunk]], chunk)
            rho = material.rho[chunk]
        block = np.matmul(R, F).reshape(-1, nb, nb, 3, 3)  # [e, a, b, i, j]
        del F
        mvals = (rho * vol)[:, None, None, None] * mass_ref[None, :, :, None]
        yield (3 * en[chunk][:, :, None] + comp, block,
               np.broadcast_to(mvals, (chunk.size, nb, nb, 3)))


def local_rows(mesh: RankMesh) -> LocalRows:
    """This rank's rows of K (N/m) and M (kg) on the free DOFs (see the module), from
    its part of the mesh (:class:`~pipeline.distributed.submesh.RankMesh`: its elements
    in the whole mesh's order, their materials, the PETSc row of each local DOF, its rows
    of the point and area masses, which go into M).

    The serial assembly (:func:`pipeline.fe.assemble.assemble_on_nodes`: the node-block
    pattern, element values scattered into CSR) on the part's space with its nodes
    renumbered in PETSc's row order (:func:`row_ordered_space`), then the rows of the
    DOFs this rank owns with PETSc's column numbers and the held rows and columns
    dropped (:func:`owned_rows`): with the run's partition the renumbering makes PETSc's
    column numbers ascend with the local ones, so the owned rows are one block and their
    columns stay sorted. The part's other rows (its one element layer of other
    ranks' nodes) are summed too and dropped: their elements are computed here anyway.
    Each entry is the same sum in the same order whatever the node numbering (elements
    in order, their groups from the nodes' positions), so the rows are those of the
    part's own numbering bit for bit."""
    lo, hi = mesh.lo, mesh.hi
    space, perm = row_ordered_space(mesh)
    petsc_row = np.asarray(mesh.dof_rows, dtype=np.int64).reshape(-1, 3)[perm].ravel()
    assembled = assemble_on_nodes(space, _law(mesh.materials))
    del space
    K = owned_rows(assembled.K, petsc_row, lo, hi, mesh.n_free)
    M = owned_rows(assembled.M, petsc_row, lo, hi, mesh.n_free)
    del assembled
    elements = int(np.count_nonzero(mesh.owned_nodes[mesh.space.element_nodes].any(axis=1)))
    if mesh.added is not None:  # its owned rows, PETSc's row and column numbers
        M = M + mesh.added
    return LocalRows(K=with_int32_indices(K), M=with_int32_indices(M), lo=lo, hi=hi,
                     n_elements=elements)


def row_ordered_space(mesh: RankMesh) -> tuple[FESpace, np.ndarray]:
    """(the part's space with its nodes in PETSc's row order, perm (n_loc,): the part's
    node of each new node). A node's place is its first free DOF's PETSc row (nodes
    held in all three directions last); the element kernels read the part's own
    geometry (``space.body``), unchanged. Where a point's free DOFs are consecutive rows
    in component order (the run's partitions, :mod:`pipeline.distributed.partition`),
    the new local DOF numbers and PETSc's rows ascend together over the free DOFs."""
    space = mesh.space
    rows = np.asarray(mesh.dof_rows, dtype=np.int64).reshape(-1, 3)
    key = np.where(rows >= 0, rows, np.iinfo(np.int64).max).min(axis=1)
    perm = np.argsort(key, kind="stable")
    inverse = np.empty_like(perm)
    inverse[perm] = np.arange(perm.size, dtype=perm.dtype)
    ordered = FESpace(None, space.order, space.node_points[perm],
                      inverse[space.element_nodes], space.edges, space.body)
    return ordered, perm


def owned_rows(A: sp.csr_matrix, petsc_row: np.ndarray, lo: int, hi: int,
               n_free: int) -> sp.csr_matrix:
    """The rows ``lo:hi`` (PETSc order) of a local-DOF CSR matrix ``A`` (sorted columns)
    as (hi - lo, n_free) CSR with PETSc's column numbers (sorted), ``petsc_row``
    (n_loc_dofs,) the PETSc row of each local DOF, -1 where held. Held rows and columns
    are dropped, and so are entries that sum to exactly zero, as the serial K's sparse
    products drop them: MUMPS' PORD ordering of the slender beam took minutes on the
    pattern with its 11k exact zeros (3x3 node blocks of axis-aligned elements), 1 s
    without.

    Where PETSc's rows ascend with the local free DOFs (:func:`row_ordered_space`) the
    owned rows are one block of A's rows and the columns stay sorted: one pass over that
    block's entries. Otherwise (the connection models' partition of every DOF, whose
    held DOFs follow a rank's free ones, :mod:`pipeline.distributed.unsupported`) the
    owned rows are picked out and each row's columns sorted."""
    free = petsc_row[petsc_row >= 0]
    if np.all(free[1:] > free[:-1]):
        first, last = np.searchsorted(free, [lo, hi])  # the owned block of free DOFs
        if last - first != hi - lo:
            raise AssertionError(f"rank's part holds {last - first} of its {hi - lo} rows")
        at = np.flatnonzero(petsc_row >= 0)
        r0, r1 = (int(at[first]), int(at[last - 1]) + 1) if hi > lo else (0, 0)
        out = _renumbered(A, r0, r1, petsc_row, petsc_row[r0:r1] < 0, n_free)
        out.has_canonical_format = True  # A's sorted distinct columns, mapped in order
        return out
    owned = np.flatnonzero((petsc_row >= lo) & (petsc_row < hi))
    owned = owned[np.argsort(petsc_row[owned], kind="stable")]
    if owned.size != hi - lo:
        raise AssertionError(f"rank's part holds {owned.size} of its {hi - lo} rows")
    rows = sp.csr_matrix(A)[owned]
    out = _renumbered(rows, 0, owned.size, petsc_row, np.zeros(owned.size, bool), n_free)
    out.has_sorted_indices = False
    out.sort_indices()
    return out


def _renumbered(A: sp.csr_matrix, r0: int, r1: int, petsc_row: np.ndarray,
                held: np.ndarray, n_free: int) -> sp.csr_matrix:
    """A's rows r0:r1 but those marked ``held`` ((r1 - r0,) bool), columns renumbered by
    ``petsc_row`` (-1: dropped), exact zeros dropped; (rows kept, n_free) CSR in A's
    column order."""
    indptr = A.indptr[r0:r1 + 1].astype(np.int64)
    s, e = int(indptr[0]), int(indptr[-1])
    index = np.int32 if n_free <= np.iinfo(np.int32).max else np.int64
    cols = petsc_row.astype(index)[A.indices[s:e]]
    keep = cols >= 0
    keep &= A.data[s:e] != 0
    if held.any():
        keep &= np.repeat(~held, np.diff(indptr))
    counts = np.zeros(e - s + 1, dtype=np.int64)
    np.cumsum(keep, out=counts[1:])
    return sp.csr_matrix((A.data[s:e][keep], cols[keep],
                          np.concatenate([[0], counts[indptr[1:] - s][~held]])),
                         shape=(int((~held).sum()), n_free))


class _Sum:
    """Running sum of CSR blocks, merged pairwise (binary counter): O(nnz log n_blocks)."""

    def __init__(self) -> None:
        self.stack: list[tuple[int, sp.csr_matrix]] = []

    def add(self, A: sp.csr_matrix) -> None:
        level = 0
        while self.stack and self.stack[-1][0] == level:
            A = self.stack.pop()[1] + A
            level += 1
        self.stack.append((level, A))

    def total(self, shape) -> sp.csr_matrix:
        out = sp.csr_matrix(shape)
        for _, A in self.stack:
            out = out + A
        out.sum_duplicates()
        out.sort_indices()
        return out


def element_share(mesh: RankMesh, n_dofs: int, chunk_size: int = 512
                  ) -> tuple[sp.csr_matrix, sp.csr_matrix]:
    """(K_r, M_r) (the connection models' unsupported ``/fe`` matrices): the upper triangles (n_dofs, n_dofs, DOF 3 p + c of mesh point p, N/m
    and kg) of the elements whose mass this rank sums (``mesh.mass_elements``: every
    element on exactly one rank), so that sum_r K_r is the unsupported body's K (its
    upper triangle) and sum_r M_r its M; each holds 1/size of the entries."""
    k_sum, m_sum = _Sum(), _Sum()
    shape = (n_dofs, n_dofs)
    for dof, block, mvals in element_blocks(mesh, mesh.mass_elements, chunk_size):
        dofs = 3 * mesh.points[dof // 3] + dof % 3  # global DOF numbers
        rows = np.broadcast_to(dofs[:, :, None, :, None], block.shape)
        cols = np.broadcast_to(dofs[:, None, :, None, :], block.shape)
        up = rows <= cols
        k_sum.add(sp.csr_matrix((block[up], (rows[up], cols[up])), shape=shape))
        rows = np.broadcast_to(dofs[:, :, None, :], mvals.shape)
        cols = np.broadcast_to(dofs[:, None, :, :], mvals.shape)
        up = rows <= cols
        m_sum.add(sp.csr_matrix((mvals[up], (rows[up], cols[up])), shape=shape))
    return k_sum.total(shape), m_sum.total(shape)


def with_int32_indices(A: sp.spmatrix) -> sp.csr_matrix:
    """``A`` as CSR with sorted int32 indices (what
    :func:`pipeline.distributed.eigen.petsc_matrix` takes)."""
    A = sp.csr_matrix(A)
    A.sum_duplicates()
    A.sort_indices()
    A.indices = A.indices.astype(np.int32, copy=False)
    A.indptr = A.indptr.astype(np.int32, copy=False)
    return A


def local_node_mass(mesh: RankMesh, elements: np.ndarray | None = None) -> sp.csr_matrix:
    """(n_loc, n_loc) node-level mass (kg) of the elements whose mass this rank sums
    (``mesh.mass_elements``, local node numbers); over the ranks every element once, so
    the ranks' rigid masses R^T N R add up to the body's (M = N (x) I_3). ``elements``:
    other elements of the part instead (local numbers)."""
    space = mesh.space
    chunk = mesh.mass_elements if elements is None else elements
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


def full_mass_rows(mesh, fields: np.ndarray) -> np.ndarray:
    """(hi - lo, k) this rank's rows (PETSc order) of M F, M the unsupported body's
    consistent mass (kg) and F (n_dofs, k) nodal fields given on the part's local nodes
    as ``fields`` (n_loc, 3, k). ``mesh``: the rank's
    :class:`~pipeline.distributed.submesh.RankMesh`; its elements that touch an owned
    node give those nodes' whole rows of N (M = N (x) I_3), held columns included."""
    en = mesh.space.element_nodes
    elements = np.flatnonzero(mesh.owned_nodes[en].any(axis=1))
    N = local_node_mass(mesh, elements)
    n_loc, _, k = fields.shape
    rows = (N @ fields.reshape(n_loc, 3 * k)).reshape(3 * n_loc, k)  # local DOF 3 i + c
    owned = (mesh.dof_rows >= mesh.lo) & (mesh.dof_rows < mesh.hi)
    out = np.zeros((mesh.hi - mesh.lo, k))
    out[mesh.dof_rows[owned] - mesh.lo] = rows[owned]
    return out


def rigid_mass_rows(mesh, point) -> np.ndarray:
    """(hi - lo, 6) this rank's rows (PETSc order) of M R_P (kg | kg m), R_P the
    rigid-body modes about ``point`` (3,) m (:func:`full_mass_rows`)."""
    points = mesh.space.node_points
    R = rigid_body_modes(points, np.asarray(point, dtype=float))
    return full_mass_rows(mesh, R.reshape(points.shape[0], 3, 6))
