"""Export to Exudyn: a file that ``exudyn.FEM.FEMinterface().LoadFromFile(path)`` reads.

What Exudyn's FEMinterface holds, and where it comes from in our HDF5 file:

===================  ==========================================================  ===================
FEMinterface         content                                                     our file
===================  ==========================================================  ===================
nodes['Position']    (n_points, 3) m, one 3-DOF node per mesh point              /mesh/points
                     (P2 edge nodes included), DOF 3*node + component
elements[0]          {'Name': 'body', 'Tet10' | 'Tet4': connectivity}            /mesh/cells/tetra10
                     (Exudyn's Tet10 order = meshio's: corners, 01 12 02 03 13 23)
massMatrix           scipy CSR (3 n_points)^2 kg, unsupported body               /fe/mass_matrix
stiffnessMatrix      scipy CSR (3 n_points)^2 N/m, unsupported body              /fe/stiffness_
                                                                                 matrix
surface[0]           {'Name': 'boundary', 'Trigs', 'Trigs6'}: outward boundary   from the cells
                     triangles (and their 6-node form for P2)
nodeSets             one per region: {'Name', 'NodeNumbers', 'NodeWeights'},     /mesh/regions/*
                     weights = consistent area weights, normalised to sum 1
modeBasis            {'matrix': (3 n_points, n), 'type': 'NormalModes' |         /modes/shapes or
                     'HCBmodes'}                                                 /craig_bampton/
                                                                                 shapes
eigenValues          (n,) rad^2/s^2 of the basis' own (K, M) projection
metaData             source, file, basis description
===================  ==========================================================  ===================

The mode basis (``basis`` argument of :func:`export_exudyn`):

- ``modes``: /modes/shapes without the rigid-body modes. For a body supported on a
  region (the cantilever clamped at its root), these are the modes clamped there, which
  is what Exudyn's Hurty-Craig-Bampton procedure gives with that region as the single
  interface: the floating frame then moves with the clamp.
- ``craig_bampton``: /craig_bampton/shapes without the six static modes of the first
  interface (Exudyn's ``excludeRigidBodyMotion``: the frame follows that interface).
- ``auto`` (default): ``craig_bampton`` when the file has it, else ``modes``.

The export reads our file in one open, through :func:`pipeline.store.read.read_fe_model`
(a :class:`~pipeline.store.records.StoredFEModel`). Exudyn computes everything else it
needs (reduced M and K, the FFRF inertia invariants) from these entries. The file format
is HDF5 tagged the way Exudyn's loader expects: every group and dataset carries ``datatype`` (``dict``, ``list``, ``csr_matrix``,
``ndarray``, ``str``, ``int``); lists are groups of ``item_<i>``; and the file name must end
in ``.hdf5``.

Our HDF5 file holds M and K only when the run added
:func:`pipeline.store.schema.exudyn_datasets` (configs with ``connections``). For any other
file ``export --to exudyn`` re-assembles them on the file's own mesh with its stored config
(:func:`pipeline.run.stored_fe_data`; no re-meshing), and says so in ``metaData/matrices``.

Statics: with a normal-mode basis of a supported body, one static mode per input port
(K_ff^-1 F, M-orthogonalised to the modes) is appended, so Exudyn's static deflection
under a port load equals the full FE's; ``metaData/statics`` says whether the statics are
exact or truncated (no ports, a free body, or a Craig-Bampton basis: exact only for loads
at the interface points).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp

from pipeline._util.atomic import atomic_path
from pipeline.errors import FileFormatError
from pipeline.store.read import BASES, StoredBasis, read_fe_model

log = logging.getLogger(__name__)

__all__ = ["export_exudyn", "boundary_faces", "region_node_weights",
           "write_tagged_hdf5"]

# local edges of a tetra10, in column order 4..9
_TET_EDGES = ((0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3))


# --------------------------------------------------------------------------- mesh helpers
def _edge_midnodes(cells: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """(sorted keys, mid node per key, key base) of every tet edge of a tetra10 mesh."""
    n = int(cells.max()) + 1
    pairs = np.concatenate([cells[:, list(e)] for e in _TET_EDGES])
    mids = np.concatenate([cells[:, 4 + i] for i in range(6)])
    pairs.sort(axis=1)
    keys = pairs[:, 0].astype(np.int64) * n + pairs[:, 1]
    keys, idx = np.unique(keys, return_index=True)
    return keys, mids[idx], n


def _mid_of(edge_map, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    keys, mids, n = edge_map
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    q = lo.astype(np.int64) * n + hi
    pos = np.searchsorted(keys, q).clip(max=keys.size - 1)
    if not np.all(keys[pos] == q):
        raise FileFormatError("mesh: an edge of a region is not an edge of any element")
    return mids[pos]


def boundary_faces(points: np.ndarray, cells: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """(Trigs (n_f, 3), Trigs6 (n_f, 6) or None): the boundary triangles of a tetrahedral
    mesh, oriented with outward normals; Trigs6 adds the edge nodes 01, 12, 20 (tetra10)."""
    corners = cells[:, :4]
    local = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])
    faces = corners[:, local].reshape(-1, 3)
    opposite = corners.reshape(-1)  # face i of a tet is opposite its vertex i
    key = np.sort(faces, axis=1).astype(np.int64)
    n = int(corners.max()) + 1
    code = (key[:, 0] * n + key[:, 1]) * n + key[:, 2]
    _, inverse, counts = np.unique(code, return_inverse=True, return_counts=True)
    boundary = counts[inverse] == 1
    faces, opposite = faces[boundary], opposite[boundary]
    a, b, c = (points[faces[:, i]] for i in range(3))
    normal = np.cross(b - a, c - a)
    inward = np.einsum("ij,ij->i", normal, points[opposite] - a) > 0
    faces[inward] = faces[inward][:, [0, 2, 1]]
    if cells.shape[1] != 10:
        return faces, None
    em = _edge_midnodes(cells)
    mids = np.stack([_mid_of(em, faces[:, 0], faces[:, 1]), _mid_of(em, faces[:, 1], faces[:, 2]),
                     _mid_of(em, faces[:, 2], faces[:, 0])], axis=1)
    return faces, np.hstack([faces, mids])


def region_node_weights(points: np.ndarray, cells: np.ndarray, region: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray]:
    """(nodes, weights) of a region given by its vertex cells (triangles (n, 3), edges
    (n, 2) or vertices (n, 1)): every node of the region (vertices, and edge nodes for
    tetra10) with its consistent weight, normalised to sum 1: area/3 per edge node for P2
    and per vertex for P1 on a face; length/6 per vertex and 2 length/3 per edge node for
    P2, length/2 per vertex for P1 on a line; equal weights on a point set."""
    reg = np.asarray(region, dtype=np.int64)
    k = reg.shape[1]
    if k == 1:
        nodes = np.unique(reg)
        return nodes, np.full(nodes.size, 1.0 / max(nodes.size, 1))
    p = [points[reg[:, i]] for i in range(k)]
    if k == 3:
        size = 0.5 * np.linalg.norm(np.cross(p[1] - p[0], p[2] - p[0]), axis=1)
        pairs = [(0, 1), (1, 2), (2, 0)]
    else:
        size = np.linalg.norm(p[1] - p[0], axis=1)
        pairs = [(0, 1)]
    carriers, carrier_w = [], []
    if cells.shape[1] == 10:
        em = _edge_midnodes(cells)
        mids = np.stack([_mid_of(em, reg[:, a], reg[:, b]) for a, b in pairs], axis=1)
        carriers.append(mids.ravel())
        carrier_w.append(np.repeat(size / 3.0 if k == 3 else 2.0 * size / 3.0, len(pairs)))
        if k == 2:
            carriers.append(reg.ravel())
            carrier_w.append(np.repeat(size / 6.0, 2))
        all_nodes = np.concatenate([reg.ravel(), mids.ravel()])
    else:
        carriers.append(reg.ravel())
        carrier_w.append(np.repeat(size / k, k))
        all_nodes = reg.ravel()
    nodes = np.unique(all_nodes)
    weights = np.zeros(nodes.size)
    np.add.at(weights, np.searchsorted(nodes, np.concatenate(carriers)),
              np.concatenate(carrier_w))
    total = weights.sum()
    return nodes, weights / total if total > 0 else weights


# --------------------------------------------------------------------------- writer
def _write(group, key: str, value: Any) -> None:
    """One entry in Exudyn's tagged-HDF5 convention."""
    import h5py

    if isinstance(value, dict):
        sub = group.create_group(key)
        sub.attrs["datatype"] = "dict"
        for k, v in value.items():
            _write(sub, k, v)
    elif isinstance(value, list):
        sub = group.create_group(key)
        sub.attrs["datatype"] = "list"
        for i, v in enumerate(value):
            _write(sub, f"item_{i}", v)
    elif sp.issparse(value):
        A = sp.csr_matrix(value)
        sub = group.create_group(key)
        sub.attrs["datatype"] = "csr_matrix"
        for part, arr in (("data", A.data), ("indices", A.indices), ("indptr", A.indptr),
                          ("shape", np.array(A.shape))):
            sub.create_dataset(part, data=arr)
            sub[part].attrs["datatype"] = "ndarray"  # Exudyn ignores it here; tagged anyway
    elif isinstance(value, np.ndarray):
        group.create_dataset(key, data=value)
        group[key].attrs["datatype"] = "ndarray"
    elif isinstance(value, str):
        group.create_dataset(key, data=value, dtype=h5py.string_dtype("utf-8"))
        group[key].attrs["datatype"] = "str"
    elif isinstance(value, (bool, int, float)):
        group.create_dataset(key, data=value)
        group[key].attrs["datatype"] = type(value).__name__
    else:
        raise TypeError(f"exudyn export: cannot write {key!r} of type {type(value).__name__}")


def write_tagged_hdf5(path: Path, data: dict[str, Any]) -> Path:
    """Write ``data`` (nested dict / list / ndarray / csr / str / int / float) to ``path``
    atomically (temporary file, then rename)."""
    import h5py

    path = Path(path)
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as h5:
        for key, value in data.items():
            _write(h5, key, value)
    return path


# --------------------------------------------------------------------------- export
def _basis(stored: StoredBasis, fixed: np.ndarray) -> tuple[np.ndarray, str, str]:
    """(matrix (n_dofs, n), Exudyn type, description) of the stored basis."""
    if stored.kind == "craig_bampton":
        first = stored.interface_names[0]
        keep = [i for i, nm in enumerate(stored.names) if not nm.startswith(first + ".")]
        return (stored.shapes[:, keep], "HCBmodes",
                f"Craig-Bampton basis without the static modes of interface '{first}' "
                "(the floating frame follows it): " + ", ".join(stored.names[i] for i in keep))
    keep = np.arange(stored.n_rigid, stored.shapes.shape[1])
    what = ("modes of the supported body (zero on its supports)" if fixed.size
            else "elastic free-free modes (rigid-body modes dropped)")
    return stored.shapes[:, keep], "NormalModes", what


def static_modes(K: sp.spmatrix, M: sp.spmatrix, Psi: np.ndarray, F: np.ndarray,
                 fixed: np.ndarray) -> np.ndarray:
    """(n_dofs, k <= n_u) static modes of the supported body: K_ff^-1 F_f per input (zero on
    the ``fixed`` DOFs), M-orthogonalised against the M-orthonormal ``Psi`` and among
    themselves, M-normalised; a load already in span(Psi) adds none."""
    from pipeline.solve.factorization import factorize

    n = K.shape[0]
    free = np.setdiff1d(np.arange(n), fixed)
    Kff = sp.csr_matrix(K)[free][:, free]
    fac = factorize(Kff)
    S = np.zeros((n, F.shape[1]))
    S[free] = np.asarray(fac.solve(np.asarray(F[free], float))).reshape(free.size, -1)
    fac.release()
    basis = [Psi]
    kept = []
    for j in range(S.shape[1]):
        s = S[:, j].copy()
        size0 = np.sqrt(s @ (M @ s))
        for _ in range(2):  # twice: classical Gram-Schmidt in the M inner product
            for B in basis:
                s -= B @ (B.T @ (M @ s))
        size = np.sqrt(s @ (M @ s))
        if size0 > 0 and size > 1e-8 * size0:
            s /= size
            basis.append(s[:, None])
            kept.append(s)
    return np.stack(kept, axis=1) if kept else np.zeros((n, 0))


def export_exudyn(h5_path: str | Path, out_path: str | Path, basis: str = "auto",
                  fe_data: Any = None) -> Path:
    """Write the Exudyn FEMinterface file ``out_path`` (must end in ``.hdf5``) from our
    HDF5 file ``h5_path``. Returns ``out_path``. See the module docstring.

    ``fe_data`` (:func:`pipeline.run.stored_fe_data`, what ``export --to exudyn`` passes):
    K_full and M_full for a file without ``/fe``, and the input-port loads F from which
    static modes are added to a normal-mode basis (its statics then equal the full FE's).
    """
    from pipeline._version import __version__

    out = Path(out_path)
    if out.suffix.lower() != ".hdf5":
        raise FileFormatError(f"exudyn export: output '{out}' must end in '.hdf5' (Exudyn "
                              "loads HDF5 only from that ending; '.h5' is read as NumPy)")
    if basis not in BASES:
        raise FileFormatError(f"exudyn export: basis {basis!r} is not one of {', '.join(BASES)}")
    body = read_fe_model(h5_path, basis)
    points, cells, fixed, regions, name = (body.points, body.cells, body.fixed_dofs,
                                           body.regions, body.name)
    cell_key, n_dofs = body.cell_type, body.n_dofs
    if body.has_fe:
        M, K, source = body.M, body.K, "M and K stored by the run (/fe)"
    elif fe_data is not None and getattr(fe_data, "K_full", None) is not None:
        K, M, source = fe_data.K_full, fe_data.M_full, fe_data.source
    else:
        raise FileFormatError(
            f"file '{h5_path}': has no /fe (the full M and K Exudyn needs; a run stores "
            "them only when the config has a 'connections' section); export it with "
            "'python -m pipeline export FILE --to exudyn', which re-assembles them from "
            "the stored config and mesh, or add 'connections:' to the config",
            key="connections", value="absent", expected="/fe in the file")
    if M.shape != (n_dofs, n_dofs) or K.shape != (n_dofs, n_dofs):
        raise FileFormatError(f"file '{h5_path}': /fe matrices are {M.shape}, {K.shape}; "
                              f"expected ({n_dofs}, {n_dofs}) for {points.shape[0]} points")
    Psi, kind, what = _basis(body.basis, fixed)
    F = getattr(fe_data, "F", None)
    n_modes = Psi.shape[1]
    if kind == "NormalModes" and F is not None and F.shape[1] and fixed.size:
        S = static_modes(K, M, Psi, F, fixed)
        Psi = np.hstack([Psi, S])
        statics = (f"exact: the basis adds {S.shape[1]} static mode(s) K^-1 F of the input "
                   f"port(s) {', '.join(fe_data.input_names)} (M-orthogonalised), so a static "
                   "load of an input port deflects the body as the full FE does")
    elif kind == "HCBmodes":
        statics = ("exact for forces and moments at the other interface points (their "
                   "constraint modes are in the basis); other loads see only the "
                   f"{n_modes} basis vectors")
    else:
        reason = ("the body is unsupported" if not fixed.size else
                  "the config has no input ports" if F is not None else
                  "no port loads were given (export with the command line adds them)")
        statics = (f"truncated: {reason}, so the basis holds the {n_modes} modes only; a "
                   "static deflection misses the flexibility of the modes left out (the full "
                   "FE is softer by that much)")
    Kr = Psi.T @ (K @ Psi)
    Mr = Psi.T @ (M @ Psi)
    import scipy.linalg as sla

    eig = sla.eigh(0.5 * (Kr + Kr.T), 0.5 * (Mr + Mr.T), eigvals_only=True)
    trigs, trigs6 = boundary_faces(points, cells)
    surface: dict[str, Any] = {"Name": "boundary", "Trigs": trigs.astype(np.int64)}
    if trigs6 is not None:
        surface["Trigs6"] = trigs6.astype(np.int64)
    node_sets = []
    for rname, tris in regions.items():
        nodes, weights = region_node_weights(points, cells, tris)
        node_sets.append({"Name": str(rname), "NodeNumbers": nodes.astype(np.int64),
                          "NodeWeights": weights})
    data = {
        "metaData": {"source": f"fe-reduced-body {__version__}", "file": str(h5_path),
                     "name": name, "basis": what, "units": "SI (m, kg, s, N)",
                     "statics": statics, "matrices": source},
        "nodes": {"Position": points},
        "elements": [{"Name": "body", "Tet10" if cell_key == "tetra10" else "Tet4": cells}],
        "massMatrix": M,
        "stiffnessMatrix": K,
        "surface": [surface],
        "nodeSets": node_sets,
        "elementSets": [],
        "modeBasis": {"matrix": np.ascontiguousarray(Psi), "type": kind},
        "eigenValues": np.abs(eig),
        "postProcessingModes": {},
        "fileVersion": 4,
        "type": "FEMinterface",
    }
    write_tagged_hdf5(out, data)
    log.info("wrote Exudyn FEMinterface file %s (%d nodes, %d %s)", out, points.shape[0],
             Psi.shape[1], kind)
    return out
