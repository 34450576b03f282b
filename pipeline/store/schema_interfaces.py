"""The writer of the groups of the connection-point, Craig-Bampton and floating-frame
models and of the FE matrices the Exudyn export reads (docs/hdf5-format.md, second part;
paths in :mod:`pipeline.store.layout`). :mod:`pipeline.store.schema` assembles the file
from these and its own groups; the functions are public for tests and tools that write a
partial file.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from pipeline.reduce.connection import ConnectionModel
from pipeline.reduce.craig_bampton import CraigBamptonModel
from pipeline.reduce.ffrf import MODAL_UNIT, FFRFInvariants
from pipeline.reduce.interfaces import DIRECTIONS, TWIST_UNITS_BLOCKS
from pipeline.reduce.statespace import StateSpace
from pipeline.store.layout import CRAIG_BAMPTON, FE, FFRF, connection
from pipeline.store.tree import Dataset

__all__ = ["connection_datasets", "craig_bampton_datasets", "ffrf_datasets", "csr_datasets",
           "exudyn_datasets"]


# --------------------------------------------------------------------------- connection point
def connection_datasets(model: ConnectionModel, ss: StateSpace | None = None,
                        group: str | None = None, include_shapes: bool = False
                        ) -> dict[str, Dataset]:
    """HDF5 datasets of one connection model, keyed ``"<group>/<name>"`` with group
    ``connections/<parent name>`` by default (see docs/hdf5-format.md)."""
    p = model.parent
    g = group or connection(p.name).path
    blocks = {"units_blocks": TWIST_UNITS_BLOCKS, "order": list(DIRECTIONS)}
    tree = {
        f"{g}/point": Dataset(p.point, "m", "connection point P",
                              {"region": p.region, "coupling": p.coupling}),
        f"{g}/region_nodes": Dataset(p.nodes, "1", "nodes of the region tied to P"),
        f"{g}/mass": Dataset(np.float64(model.rigid.mass), "kg", "body mass from R_P^T M R_P"),
        f"{g}/center_of_mass": Dataset(model.rigid.center_of_mass, "m", "centre of mass G"),
        f"{g}/inertia_G": Dataset(model.rigid.inertia_G, "kg m^2", "inertia about G"),
        f"{g}/inertia_P": Dataset(model.rigid.inertia_P, "kg m^2", "inertia about P"),
        f"{g}/D_P": Dataset(model.D_P, "mixed", "rigid-body mass matrix at P, R_P^T M R_P "
                            "= tau_GP^T diag(m I, I_G) tau_GP, twist order [v; omega]", blocks),
        f"{g}/L_P": Dataset(model.L_P, "mixed", "modal participation factors Phi_c^T M R_P "
                            "(clamped modes x 6)", {"units_columns": "kg^1/2 (x,y,z) | "
                                                    "kg^1/2 m (rx,ry,rz)",
                                                    "columns": list(DIRECTIONS)}),
        f"{g}/D_P0": Dataset(model.D_P0, "mixed", "residual mass D_P - L_P^T L_P "
                             "(symmetric positive definite)", blocks),
        f"{g}/omega": Dataset(np.sqrt(np.maximum(model.omega2, 0.0)), "rad/s",
                              "circular frequencies of the modes clamped at P"),
        f"{g}/frequencies_hz": Dataset(model.frequencies_hz, "Hz",
                                       "frequencies of the modes clamped at P"),
        f"{g}/effective_mass": Dataset(model.effective_mass, "mixed",
                                       "effective modal mass L_P[i, d]^2 per mode and direction",
                                       {"units_columns": "kg (x,y,z) | kg m^2 (rx,ry,rz about P)",
                                        "columns": list(DIRECTIONS)}),
        f"{g}/effective_mass_cumulative_fraction": Dataset(
            model.effective_mass_cumulative_fraction, "1",
            "cumulative effective mass of modes 1..i divided by diag(D_P)",
            {"columns": list(DIRECTIONS)}),
    }
    if model.children:
        tree[f"{g}/child_names"] = Dataset([c.name for c in model.children], "",
                                           "child connection points, in input/output order")
        tree[f"{g}/child_points"] = Dataset(np.array([c.point for c in model.children]), "m",
                                            "child points C_k")
        tree[f"{g}/tau_C"] = Dataset(model.tau_C, "mixed", "twist transport P -> C_k, "
                                     "stacked (6 n_c x 6)", {"units_blocks": "1 | m ; 0 | 1"})
        tree[f"{g}/Phi_C"] = Dataset(model.Phi_C, "mixed", "clamped modes at the child "
                                     "coordinates (6 n_c x N)",
                                     {"units_rows": "m kg^-1/2 | rad kg^-1/2"})
    if include_shapes:
        n_nodes = model.shapes.shape[0] // 3
        tree[f"{g}/shapes"] = Dataset(model.shapes.reshape(n_nodes, 3, -1), "kg^-1/2",
                                      "M-orthonormal modes clamped at P, (n_points, 3, N)")
    if ss is not None:
        s = f"{g}/statespace"
        note = {"units_note": "inputs " + ", ".join(f"{n} [{u}]" for n, u in
                                                     zip(ss.input_names, ss.input_units))
                + "; outputs " + ", ".join(f"{n} [{u}]" for n, u in
                                           zip(ss.output_names, ss.output_units))
                + "; states eta [m kg^1/2], eta_dot [m kg^1/2 / s]"}
        tree.update({
            f"{g}/damping_ratio": Dataset(ss.attrs["damping_ratio"], "1", "modal damping ratio xi_i"),
            f"{s}/A": Dataset(ss.A, "mixed", "state matrix of x' = A x + B u, x = [eta; eta']",
                              note),
            f"{s}/B": Dataset(ss.B, "mixed", "input matrix: inputs [a_P; W_children]", note),
            f"{s}/C": Dataset(ss.C, "mixed", "output matrix: outputs [W_P; a_children]", note),
            f"{s}/D": Dataset(ss.D, "mixed", "feedthrough; top-left block D_P0", note),
            f"{s}/input_names": Dataset(list(ss.input_names), "", "name of each input"),
            f"{s}/input_units": Dataset(list(ss.input_units), "", "SI unit of each input"),
            f"{s}/output_names": Dataset(list(ss.output_names), "", "name of each output"),
            f"{s}/output_units": Dataset(list(ss.output_units), "", "SI unit of each output"),
            f"{s}/state_names": Dataset(list(ss.state_names), "", "name of each state"),
        })
    return tree


# --------------------------------------------------------------------------- Craig-Bampton
def craig_bampton_datasets(cb: CraigBamptonModel, group: str = CRAIG_BAMPTON.path,
                           include_shapes: bool = True) -> dict[str, Dataset]:
    """HDF5 datasets of the reduced model (see docs/hdf5-format.md)."""
    note = {"coordinates": list(cb.coordinate_names), "coordinate_units": list(cb.coordinate_units)}
    w_free = cb.frequencies_hz()
    tree = {
        f"{group}/M": Dataset(cb.M, "mixed", "reduced mass matrix; entry (i, j) in "
                              "kg m^2 / (u_i u_j), u the coordinate units", note),
        f"{group}/K": Dataset(cb.K, "mixed", "reduced stiffness matrix; entry (i, j) in "
                              "N m / (u_i u_j), u the coordinate units", note),
        f"{group}/coordinate_names": Dataset(list(cb.coordinate_names), "",
                                             "label of each reduced coordinate"),
        f"{group}/coordinate_units": Dataset(list(cb.coordinate_units), "",
                                             "SI unit of each reduced coordinate"),
        f"{group}/interface_names": Dataset([i.name for i in cb.interfaces], "",
                                            "interfaces in coordinate order"),
        f"{group}/interface_regions": Dataset([i.region for i in cb.interfaces], "",
                                              "region of each interface"),
        f"{group}/interface_couplings": Dataset([i.coupling for i in cb.interfaces], "",
                                                "rigid (RBE2) or distributing (RBE3)"),
        f"{group}/interface_points": Dataset(np.array([i.point for i in cb.interfaces]), "m",
                                             "point of each interface"),
        f"{group}/fixed_interface_frequencies_hz": Dataset(
            cb.fixed_interface_frequencies_hz, "Hz", "modes with every interface clamped"),
        f"{group}/free_frequencies_hz": Dataset(
            w_free, "Hz", "eigenfrequencies of (K, M), the free reduced body (6 rigid zeros)"),
    }
    if include_shapes:  # (n_dofs, n) or, from MPI ranks, a block-written (n_points, 3, n)
        shapes = (cb.shapes if hasattr(cb.shapes, "blocks")
                  else cb.shapes.reshape(cb.shapes.shape[0] // 3, 3, -1))
        tree[f"{group}/shapes"] = Dataset(
            shapes, "mixed",
            "basis on every mesh point (n_points, 3, n_coordinates): constraint modes "
            "(m/m, m/rad), then fixed-interface modes (kg^-1/2)", note)
    return tree


# --------------------------------------------------------------------------- FFRF invariants
_FFRF_UNITS = {
    "translational_coupling": ("kg^1/2", "kg m / u_k"),
    "rotational_coupling": ("kg^1/2 m", "kg m^2 / u_k"),
    "modal_mass": ("1", "kg m^2 / (u_k u_l)"),
    "modal_stiffness": ("rad^2/s^2", "N m / (u_k u_l)"),
    "inertia_first_order": ("kg^1/2 m", "kg m^2 / u_k"),
    "inertia_second_order": ("1", "kg m^2 / (u_k u_l)"),
    "gyroscopic_coupling": ("1", "kg m^2 / (u_k u_l)"),
    "basis": ("kg^-1/2", "m / u_k"),
}


def ffrf_datasets(inv: FFRFInvariants, group: str = FFRF.path, include_basis: bool = False
                  ) -> dict[str, Dataset]:
    """HDF5 datasets of the invariants (see docs/hdf5-format.md, section ffrf).

    Units: for modal coordinates (every u_k = m kg^1/2) the simplified unit; otherwise
    ``mixed`` with the attribute ``units_rule`` in terms of ``coordinate_units``.
    """
    attrs = {"coordinates": list(inv.coordinate_names), "basis": inv.basis_kind,
             "coordinate_units": list(inv.coordinate_units)}
    modal = all(u == MODAL_UNIT for u in inv.coordinate_units)

    def units(term: str) -> str:
        return _FFRF_UNITS[term][0] if modal else "mixed"

    def at(term: str) -> dict:
        return attrs if modal else {**attrs, "units_rule": _FFRF_UNITS[term][1]}
    tree = {
        f"{group}/origin": Dataset(inv.origin, "m", "frame origin O the invariants refer to",
                                   {"basis": inv.basis_kind}),
        f"{group}/coordinate_names": Dataset(list(inv.coordinate_names), "",
                                             "elastic coordinate of each basis column"),
        f"{group}/mass": Dataset(np.float64(inv.mass), "kg", "total mass, int rho dV"),
        f"{group}/first_moment": Dataset(inv.first_moment, "kg m", "int rho x dV = m c (about O)"),
        f"{group}/center_of_mass": Dataset(inv.center_of_mass, "m", "c, relative to O"),
        f"{group}/inertia": Dataset(inv.inertia, "kg m^2",
                                    "J0 = -int rho x~ x~ dV, inertia tensor about O"),
        f"{group}/translational_coupling": Dataset(
            inv.translational_coupling, units("translational_coupling"),
            "C_t = int rho psi_k dV (3 x n)", at("translational_coupling")),
        f"{group}/rotational_coupling": Dataset(
            inv.rotational_coupling, units("rotational_coupling"),
            "C_r = int rho x x psi_k dV (3 x n)", at("rotational_coupling")),
        f"{group}/modal_mass": Dataset(inv.modal_mass, units("modal_mass"),
                                       "Psi^T M Psi (n x n)", at("modal_mass")),
        f"{group}/inertia_first_order": Dataset(
            inv.inertia_first_order, units("inertia_first_order"),
            "J1_k = -int rho (x~ psi_k~ + psi_k~ x~) dV, (n, 3, 3)", at("inertia_first_order")),
        f"{group}/inertia_second_order": Dataset(
            inv.inertia_second_order, units("inertia_second_order"),
            "J2_kl = -int rho psi_k~ psi_l~ dV, (n, n, 3, 3)", at("inertia_second_order")),
        f"{group}/gyroscopic_coupling": Dataset(
            inv.gyroscopic_coupling, units("gyroscopic_coupling"),
            "G_kl = int rho psi_k x psi_l dV, (n, n, 3)", at("gyroscopic_coupling")),
    }
    if inv.modal_stiffness is not None:
        tree[f"{group}/modal_stiffness"] = Dataset(inv.modal_stiffness,
                                                   units("modal_stiffness"),
                                                   "Psi^T K Psi (n x n)", at("modal_stiffness"))
    if include_basis:
        n_nodes = inv.basis.shape[0] // 3
        tree[f"{group}/basis"] = Dataset(inv.basis.reshape(n_nodes, 3, -1), units("basis"),
                                         "Psi on every mesh point (n_points, 3, n)", at("basis"))
    return tree


# --------------------------------------------------------------------------- FE matrices (CSR)
def csr_datasets(A: sp.spmatrix, group: str, units: str, description: str,
                 symmetric: bool = True) -> dict[str, Dataset]:
    """A sparse matrix as CSR arrays ``<group>/{data, indices, indptr, shape}``.

    Explicit zeros are dropped. ``symmetric``: store only the upper triangle (diagonal
    included); the ``data`` dataset then carries ``storage = "upper"`` (else ``"full"``).
    :func:`pipeline.store.read.read_csr` restores the full matrix.
    """
    if hasattr(A, "csr_parts"):  # from MPI ranks: the (upper) arrays, block-written
        data, indices, indptr = A.csr_parts()
    else:
        A = sp.triu(A, format="csr") if symmetric else sp.csr_matrix(A, copy=True)
        A.eliminate_zeros()  # the assembled M stores the zero off-diagonals of its 3x3 blocks
        A.sort_indices()
        itype = np.int32 if A.nnz < 2**31 - 1 else np.int64
        data, indices, indptr = (A.data.astype(np.float64), A.indices.astype(itype),
                                 A.indptr.astype(np.int64))
    storage = "upper" if symmetric else "full"
    return {
        f"{group}/data": Dataset(data, units, description,
                                 {"storage": storage, "format": "csr"}),
        f"{group}/indices": Dataset(indices, "1", "CSR column indices"),
        f"{group}/indptr": Dataset(indptr, "1", "CSR row pointers"),
        f"{group}/shape": Dataset(np.array(A.shape, dtype=np.int64), "1", "(rows, columns)"),
    }


def exudyn_datasets(K_full: sp.spmatrix, M_full: sp.spmatrix) -> dict[str, Dataset]:
    """What the export needs beyond the core file: the assembled M and K of the
    unsupported body (before support condensation), as upper-triangle CSR arrays
    ``fe/mass_matrix/*`` (kg) and ``fe/stiffness_matrix/*`` (N/m)."""
    tree = csr_datasets(M_full, FE.mass_matrix, "kg",
                        "consistent mass matrix of the unsupported body, DOF 3*node+c")
    tree.update(csr_datasets(K_full, FE.stiffness_matrix, "N/m",
                             "stiffness matrix of the unsupported body, DOF 3*node+c"))
    return tree
