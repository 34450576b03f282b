"""Assembly stage: linear-elasticity stiffness K and consistent mass M.

scikit-fem is the finite-element engine: its mesh numbers the edges, its Lagrange
elements give the reference shape functions and its quadrature rules the points and
weights. The assembly is three steps, one module each:

- :mod:`pipeline.fe.pattern`: the node-block sparsity pattern shared by K and M (every
  pair of nodes sharing an element, the pattern of E^T E), K's CSR structure on the kept
  nodes and where each element's values go;
- :mod:`pipeline.fe.kernels`: the element kernels (on straight-sided tetrahedra the
  element matrices are one matrix product for the whole mesh);
- this module: the loop over element chunks that scatter-adds the kernels' values
  straight into K's CSR values (:func:`assemble_on_nodes`), and the restriction to the
  free DOFs (:func:`restrict`).

K is returned in CSR with full 3x3 node blocks, M with only the u_i.v_i entries (a third
of the non-zeros: M couples equal components only); both have 32-bit indices where they
fit. The result equals ``skfem.asm`` of the same forms to round-off
(:func:`assemble_reference`, ``tests/test_assemble.py``), without ever holding basis
values for the whole mesh.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from pipeline._util.resources import release_free_heap, usable_cores
from pipeline.config import Material
from pipeline.fe.kernels import (element_factors, element_factors_general, lame_parameters,
                                 reference_data, scatter_add)
from pipeline.fe.materials import ElementMaterials, voigt_to_tensor
from pipeline.fe.pattern import (INT32_MAX, BlockPattern, StiffnessLayout, block_pattern,
                                 index_dtype, mass_csr, stiffness_layout)
from pipeline.fe.space import FESpace

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Assembled:
    """K and M on the kept nodes, and the node-level mass of the whole body.

    K: (3 n_kept, 3 n_kept) CSR stiffness (N/m), full 3x3 node blocks.
    M: (3 n_kept, 3 n_kept) CSR mass (kg), only the u_i.v_i entries (M couples equal
    components: a third of K's non-zeros).
    node_mass: (n_nodes, n_nodes) CSR of the scalar m_ab of every node pair of the
    whole body (kg), so that the unsupported mass is node_mass (x) I_3; it shares the
    pattern's index arrays.
    """

    K: sp.csr_matrix
    M: sp.csr_matrix
    node_mass: sp.csr_matrix


def element_groups(space: FESpace) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Three groups of element indices (each sorted): the elements whose nodes all lie
    below the median node coordinate along the mesh's longest extent, those whose nodes
    all lie at or above it, and the rest (the elements the plane cuts).

    The first two groups touch disjoint node rows of K and M, so they can be summed
    into the same arrays side by side without a race; the third, a layer one element
    thick, is summed after them.
    """
    x = space.node_points
    axis = int(np.argmax(np.ptp(x, axis=0))) if x.shape[0] else 0
    upper = x[:, axis] >= np.median(x[:, axis]) if x.shape[0] else np.zeros(0, bool)
    side = upper[space.element_nodes]
    lower_all = ~side.any(axis=1)
    upper_all = side.all(axis=1)
    return (np.flatnonzero(lower_all), np.flatnonzero(upper_all),
            np.flatnonzero(~(lower_all | upper_all)))


def _assemble_elements(space: FESpace, R: np.ndarray, mass_ref: np.ndarray,
                       material: Material | ElementMaterials, pattern: BlockPattern,
                       layout: StiffnessLayout, elements: np.ndarray, spare: int,
                       chunk_size: int, kdata: np.ndarray, mblock: np.ndarray, progress,
                       stop) -> None:
    """Add ``elements`` into kdata (n_rows, 3) and mblock (n_blocks,); the dropped
    nodes' blocks go to kdata's row ``spare`` (one per concurrent caller). Returns early
    once the event ``stop`` is set (checked before each chunk). ``material``: one
    isotropic Material (scalar Lame parameters) or the per-element materials."""
    offsets = np.arange(3, dtype=layout.base.dtype)
    first_spare = layout.nnz // 3
    if isinstance(material, Material):
        lam, mu = lame_parameters(material)
        m_ref = material.rho * mass_ref.reshape(-1)
    else:
        C_laws = voigt_to_tensor(material.D)
    for start in range(0, elements.size, chunk_size):
        if stop.is_set():
            return
        chunk = elements[start:start + chunk_size]
        if isinstance(material, Material):
            F, vol = element_factors(space, lam, mu, chunk)
            m_e = np.outer(vol, m_ref)
        else:  # (rho_e m_ref) vol_e: the same products as the uniform path
            F, vol = element_factors_general(space, C_laws[material.index[chunk]], chunk)
            m_e = (material.rho[chunk, None] * mass_ref.reshape(1, -1)) * vol[:, None]
        block = np.matmul(R, F)  # (m, nb^2, 9): [element, pair, 3 i + j]
        del F
        slots = pattern.slots[chunk].reshape(-1)
        rows = layout.base[slots][:, None] + layout.step[slots][:, None] * offsets
        if spare != first_spare:
            rows[rows == first_spare] = spare
        scatter_add(rows.reshape(-1), block.reshape(-1, 3), kdata)
        del block, rows
        scatter_add(slots, m_e.reshape(-1, 1), mblock.reshape(-1, 1))
        if progress is not None:
            progress(chunk.size)


def assemble_on_nodes(space: FESpace, material: Material | ElementMaterials, nodes: np.ndarray | None = None,
                      pattern: BlockPattern | None = None, chunk_size: int = 2048,
                      progress=None, threads: int | None = None,
                      on_layout=None, layout: StiffnessLayout | None = None) -> Assembled:
    """K (N/m) and M (kg) on the sorted ``nodes`` (all three DOFs of each; None: every
    node), and the whole body's node-level mass (:class:`Assembled`); CSR, sorted, 32-bit
    indices where they fit. ``pattern`` defaults to :func:`block_pattern`.
    ``progress``, if given, is called with the number of elements done after each chunk.
    ``on_layout(indptr, indices)``, if given, is called with K's CSR structure as soon as
    it is known, before any value is summed (the solver can analyse the pattern
    meanwhile: :class:`pipeline.solve.backends.pardiso.PatternAnalysis`). ``layout``:
    :func:`~pipeline.fe.pattern.stiffness_layout` of ``pattern`` on ``nodes``, made
    already (the caller started the analysis from it before the slots were looked up).
    ``material``: one isotropic Material, or the per-element materials
    (:func:`pipeline.fe.materials.assign_materials`; one uniform isotropic law takes the
    single-material path, bit for bit).

    Per chunk of ``chunk_size`` elements: the element factors F_e (9 x 9), one batched
    GEMM R (nb^2 x 9) @ F_e giving each (element, pair) row its 9 values (i, j), and one
    scatter-add of 3-value rows (i, 0..2) straight into K's CSR data
    (:class:`StiffnessLayout`), so no node-block array and no BSR-to-CSR expansion
    exist. The two halves of :func:`element_groups` touch disjoint rows: with ``threads``
    >= 2 (default: the usable cores) they are summed side by side in two threads (the
    GEMM, numpy's kernels and scipy's scatter release the GIL) into the same arrays, then
    the cut layer. Every entry is summed in the same order whatever the thread count, so
    K does not depend on the machine to the last bit.
    """
    if isinstance(material, ElementMaterials) and material.uniform is not None:
        material = material.uniform
    if isinstance(material, Material):
        lame_parameters(material)  # refuse a bad material before any work
    if threads is None:
        threads = usable_cores()
    if pattern is None:
        pattern = block_pattern(space, threads)
    if layout is None:
        layout = stiffness_layout(pattern, nodes, threads)
    if on_layout is not None:
        on_layout(layout.indptr, layout.indices)
    R, mass_ref = reference_data(space.order)
    chunk_size = max(1, int(chunk_size))
    lower, upper, cut = element_groups(space)
    # three spare 3-value rows at the end take the dropped nodes' blocks, one per group
    held = [np.zeros(layout.nnz + 9)]
    kdata = held[0].reshape(-1, 3)
    mblock = np.zeros(pattern.n_blocks)
    args = (space, R, mass_ref, material, pattern, layout)

    stop = threading.Event()

    def run(group: int, elements: np.ndarray, kdata: np.ndarray = kdata) -> None:
        _assemble_elements(*args, elements, layout.nnz // 3 + group, chunk_size, kdata,
                           mblock, progress, stop)

    # threads pay off from a few chunks per half; below that the worker's malloc arena
    # (its pages kept after the run) would only add to the peak memory
    if threads < 2 or min(lower.size, upper.size) < 8 * chunk_size:
        run(0, lower)
        run(1, upper)
    else:
        from concurrent.futures import FIRST_EXCEPTION, ThreadPoolExecutor, wait

        if progress is not None:  # one caller at a time: progress counters are not atomic
            lock, report = threading.Lock(), progress

            def progress(n: int) -> None:
                with lock:
                    report(n)

        with ThreadPoolExecutor(2) as pool:
            futures = [pool.submit(run, 0, lower), pool.submit(run, 1, upper)]
            try:
                done, _ = wait(futures, return_when=FIRST_EXCEPTION)
                for f in list(done) + futures:  # a failed half raises here at once
                    f.result()
            except BaseException:  # an interrupt or a failed half: stop the other at its
                stop.set()         # next chunk instead of finishing the body
                raise
        release_free_heap()  # the threads' malloc arenas keep their temporaries' pages
    run(2, cut)
    del kdata, run  # only ``held`` refers to the values now: cut the spare rows in place
    K = sp.csr_matrix((_shrink(held, layout.nnz), layout.indices, layout.indptr),
                      shape=(layout.n, layout.n))
    K.has_sorted_indices = True
    node_mass = sp.csr_matrix((mblock, pattern.indices, pattern.indptr),
                              shape=(pattern.n_nodes, pattern.n_nodes))
    return Assembled(K, mass_csr(layout, mblock, threads), node_mass)


def assemble_stiffness_mass(space: FESpace, material: Material, chunk_size: int = 2048,
                            pattern: BlockPattern | None = None, progress=None
                            ) -> tuple[sp.csr_matrix, sp.csr_matrix]:
    """Assemble K (N/m) and M (kg), both (n_dofs x n_dofs) CSR, in the space's DOF order.

    :func:`assemble_on_nodes` on every node.
    """
    assembled = assemble_on_nodes(space, material, None, pattern, chunk_size, progress)
    return assembled.K, assembled.M


def whole_nodes(free: np.ndarray, n_nodes: int) -> np.ndarray | None:
    """The free nodes (sorted) when the sorted ``free`` DOFs are all three DOFs of each
    of them (supports that clamp whole nodes); else None."""
    free = np.asarray(free)
    if free.size % 3:
        return None
    triples = free.reshape(-1, 3)
    nodes = triples[:, 0] // 3
    if np.array_equal(triples, 3 * nodes[:, None] + np.arange(3)) and (
            nodes.size == 0 or nodes[-1] < n_nodes):
        return nodes
    return None


def assemble_reference(space: FESpace, material: Material) -> tuple[sp.csr_matrix, sp.csr_matrix]:
    """Plain scikit-fem assembly (``form.assemble(basis)``), the reference for tests.

    Holds basis values for the whole mesh at once: keep it for small meshes and the
    benchmark's "straightforward stack".
    """
    from skfem import Basis, BilinearForm
    from skfem.helpers import ddot, dot, sym_grad, trace

    lam, mu = lame_parameters(material)
    rho = material.rho

    @BilinearForm
    def stiffness(u, v, w):
        eu, ev = sym_grad(u), sym_grad(v)
        return 2.0 * mu * ddot(eu, ev) + lam * trace(eu) * trace(ev)

    @BilinearForm
    def mass(u, v, w):
        return rho * dot(u, v)

    basis = Basis(space.skfem_mesh, space.skfem_element())
    return stiffness.assemble(basis).tocsr(), mass.assemble(basis).tocsr()


def restrict(A: sp.spmatrix, keep: np.ndarray, overwrite: bool = False) -> sp.csr_matrix:
    """A[keep][:, keep] (condensation of the supports) for sorted ``keep`` indices.

    One pass over A's entries, in row chunks (scipy's A[keep][:, keep] copies the
    matrix twice). ``overwrite=True`` compacts A's own arrays in place and shrinks
    them, so a second copy of A never exists: A is emptied and must not be used
    afterwards (``K = restrict(K, free, overwrite=True)``).
    """
    # csr_matrix and csr_array alike (sp.isspmatrix_csr is False for a csr_array)
    A = A if sp.issparse(A) and A.format == "csr" else sp.csr_matrix(A)
    n = A.shape[0]
    keep = np.asarray(keep)
    if keep.size == n:
        return A if isinstance(A, sp.csr_matrix) else sp.csr_matrix(A)  # shares the arrays
    m = keep.size
    itype = A.indices.dtype if m <= INT32_MAX else np.int64
    new_index = np.full(n, -1, dtype=itype)
    new_index[keep] = np.arange(m, dtype=itype)
    row_kept = new_index >= 0
    indptr = A.indptr.astype(np.int64, copy=False)
    new_counts = np.zeros(m + 1, dtype=np.int64)
    src_data, src_indices = A.data, A.indices
    if overwrite:  # write into the source arrays (never ahead of the reading position)
        data, indices = src_data, src_indices
        A.data, A.indices = np.empty(0), np.empty(0, dtype=A.indices.dtype)
    else:
        bound = int((indptr[keep + 1] - indptr[keep]).sum())
        data = np.empty(bound, dtype=A.data.dtype)
        indices = np.empty(bound, dtype=itype)
    write = 0
    done = 0  # kept rows written so far
    step = 1 << 16  # rows per chunk
    for r0 in range(0, n, step):
        r1 = min(n, r0 + step)
        lo, hi = int(indptr[r0]), int(indptr[r1])
        sel = np.repeat(row_kept[r0:r1], np.diff(indptr[r0:r1 + 1]))
        cols = new_index[src_indices[lo:hi]]
        sel &= cols >= 0
        cs = np.zeros(hi - lo + 1, dtype=np.int64)
        np.cumsum(sel, out=cs[1:])
        local = indptr[r0:r1 + 1] - lo
        per_row = (cs[local[1:]] - cs[local[:-1]])[row_kept[r0:r1]]
        new_counts[done + 1:done + 1 + per_row.size] = per_row
        done += per_row.size
        k = int(cs[-1])
        vals = src_data[lo:hi][sel]  # copies first: safe when writing in place below
        data[write:write + k] = vals
        indices[write:write + k] = cols[sel]
        write += k
    new_indptr = np.cumsum(new_counts)
    del src_data, src_indices
    if overwrite:
        held = [data]
        del data
        data = _shrink(held, write)
        held = [indices]
        del indices
        indices = _shrink(held, write).astype(itype, copy=False)
    else:
        data, indices = data[:write], indices[:write]
    return sp.csr_matrix((data, indices, new_indptr.astype(index_dtype(max(write, m)))),
                         shape=(m, m))


def _shrink(holder: list, size: int) -> np.ndarray:
    """``arr[:size]`` of the array in ``holder``, in place when nothing else holds it."""
    arr = holder.pop()
    try:
        arr.resize(size, refcheck=True)
        return arr
    except ValueError:  # referenced elsewhere: copy the part we keep
        return arr[:size].copy()
