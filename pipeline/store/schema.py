"""The one writer of the HDF5 layout of the reduced models (docs/hdf5-format.md; the paths
are named in :mod:`pipeline.store.layout`): every ``<group>/<name>`` dataset, its units
and attributes.

:func:`models_tree` turns the reduce stage's :class:`~pipeline.reduce.build.Models`
record into ``(datasets, group attributes)``: ``{"<group>/<name>": Dataset}`` and
``{"<group>": {attr: value}}``, what :func:`pipeline.store.h5file.write_file` writes.
The per-model functions below build one group each and are public for tests and tools
that write a partial file:

=========================  ==============================================================
``statespace``             :func:`statespace_datasets` (the modal plant, A B C D, names,
                           damping ratios, frequencies, static compliance)
``statespace_filtered``    :func:`filter_datasets`, :func:`filter_group_attrs`
``lumped``                 :func:`lumped_datasets`, :func:`lumped_group_attrs`
``connections/<parent>``   :func:`connection_datasets`
``craig_bampton``          :func:`craig_bampton_datasets`
``ffrf``                   :func:`ffrf_datasets`
``stress_modes``           :func:`stress_modes_datasets` (stress and strain of every basis
                           vector and static correction shape at the mesh points)
``fe/{mass,stiffness}_matrix``  :func:`exudyn_datasets` (CSR, :func:`csr_datasets`;
                           read back by :func:`pipeline.store.read.read_csr`)
=========================  ==============================================================

Units are SI strings per dataset (``"mixed"`` with a ``units_note`` / ``units_rule`` /
per-entry attribute where one matrix mixes them). Arrays are stored as given (float64,
int32/int64 indices), string lists as variable-length UTF-8.
"""

from __future__ import annotations

import math
from typing import Any, Mapping, Sequence

import numpy as np
import scipy.sparse as sp

from pipeline.reduce.connection import ConnectionModel
from pipeline.reduce.craig_bampton import CraigBamptonModel
from pipeline.reduce.ffrf import MODAL_UNIT, FFRFInvariants
from pipeline.reduce.filters import check_filter, filtered_model
from pipeline.reduce.interfaces import DIRECTIONS, TWIST_UNITS_BLOCKS
from pipeline.reduce.lumped import DOF_AXIS, DOF_KIND, ComparisonRow, LumpedModel
from pipeline.reduce.modal import ReducedModel, StateSpaceModel
from pipeline.reduce.models import Models
from pipeline.reduce.statespace import StateSpace
from pipeline.store.layout import (CRAIG_BAMPTON, FE, FFRF, LUMPED, STATESPACE,
                                   STATESPACE_FILTERED, STRESS_MODES, connection)
from pipeline.store.tree import Dataset

__all__ = [
    "models_tree",
    "statespace_datasets",
    "filter_datasets",
    "filter_group_attrs",
    "lumped_datasets",
    "lumped_group_attrs",
    "connection_datasets",
    "craig_bampton_datasets",
    "ffrf_datasets",
    "csr_datasets",
    "exudyn_datasets",
    "stress_modes_datasets",
    "VOIGT_ORDER",
]

#: Voigt order of the 6-component stress and strain fields (pipeline.fe.strain.VOIGT)
VOIGT_ORDER = ("xx", "yy", "zz", "yz", "xz", "xy")


# --------------------------------------------------------------------------- run file
def models_tree(models: Models) -> tuple[dict[str, Dataset], dict[str, dict[str, Any]]]:
    """The datasets and group attributes of every model in ``models``, in file order:
    statespace, statespace_filtered, lumped, connections/<parent>, craig_bampton, ffrf,
    fe/{mass,stiffness}_matrix (each only when the model is there)."""
    tree: dict[str, Dataset] = {}
    attrs: dict[str, dict[str, Any]] = {}
    reduced = models.reduced
    if reduced is not None:
        tree.update(statespace_datasets(reduced, STATESPACE.path, models.compliance_units))
        attrs[STATESPACE.path] = {"static_correction": reduced.static_correction,
                               "n_modes": reduced.n_modes, "n_basis": reduced.n_basis,
                               "input_units": list(models.input_units),
                               "output_units": list(models.output_units)}
        filtered = models.filtered
        if filtered is not None:
            tree.update(filter_datasets(filtered, filtered.filter_kind, filtered.cutoff_hz))
            attrs.update(filter_group_attrs(filtered.filter_kind, filtered.cutoff_hz))
    if models.lumped is not None:
        tree.update(lumped_datasets(models.lumped, models.comparison))
        attrs.update(lumped_group_attrs(models.lumped))
    if models.connection is not None:
        tree.update(connection_datasets(models.connection, models.connection_statespace))
    if models.craig_bampton is not None:
        tree.update(craig_bampton_datasets(models.craig_bampton))
    if models.ffrf is not None:
        tree.update(ffrf_datasets(models.ffrf))
    if models.fe_matrices is not None:
        tree.update(exudyn_datasets(*models.fe_matrices))
    return tree, attrs


# --------------------------------------------------------------------------- modal plant
_NAMES_NOTE = ("inputs in the unit of each input port (N for a force, N m for a moment); "
               "outputs position/velocity/acceleration in m, m/s, m/s^2 for a displacement "
               "port (rad, rad/s, rad/s^2 for a rotation); modal states eta in m kg^1/2, "
               "eta_dot in m kg^1/2/s (mode shapes are M-orthonormal, kg^-1/2)")


def _statespace_tree(ss: StateSpaceModel, group: str, extra_attrs: Mapping | None = None
                     ) -> dict[str, Dataset]:
    attrs = dict(extra_attrs or {})
    note = {"units_note": _NAMES_NOTE, **attrs}
    tree = {
        f"{group}/A": Dataset(ss.A, "mixed", "state matrix A of x' = A x + B u", note),
        f"{group}/B": Dataset(ss.B, "mixed", "input matrix B of x' = A x + B u", note),
        f"{group}/C": Dataset(ss.C, "mixed", "output matrix C of y = C x + D u; rows: "
                              "positions, velocities, accelerations of every port", note),
        f"{group}/D": Dataset(ss.D, "mixed", "feedthrough matrix D of y = C x + D u", note),
        f"{group}/input_names": Dataset(list(ss.input_names), "",
                                        "name of each input (columns of B, D)"),
        f"{group}/output_names": Dataset(list(ss.output_names), "",
                                         "name of each output (rows of C, D)"),
        f"{group}/state_names": Dataset(list(ss.state_names), "", "name of each state (rows of A)"),
        f"{group}/damping_ratios": Dataset(ss.damping_ratios, "1",
                                           "modal damping ratio of every mode in the model"),
        f"{group}/frequencies_hz": Dataset(ss.frequencies_hz, "Hz",
                                           "undamped natural frequency of every mode in the model",
                                           {"n_retained": int(ss.n_retained)}),
    }
    return tree


def statespace_datasets(model: ReducedModel, group: str = STATESPACE.path,
                        compliance_units: str = "m/N") -> dict[str, Dataset]:
    """HDF5 datasets of the (unfiltered) reduced model, keyed ``"<group>/<name>"``.

    A, B, C, D (units ``"mixed"``, attribute ``units_note`` says which), the names
    (string datasets), ``damping_ratios`` (1), ``frequencies_hz`` (Hz) and
    ``static_compliance`` (n_y x n_u, ``compliance_units``; "m/N" for force inputs and
    displacement outputs, pass "mixed" otherwise) when the body has statics; for
    ``residual`` also ``residual_flexibility``. A carries ``static_correction``,
    ``n_modes`` and ``n_basis`` as attributes.
    """
    ss = model.statespace
    tree = _statespace_tree(ss, group)
    a = tree[f"{group}/A"]
    tree[f"{group}/A"] = Dataset(a.data, a.units, a.description,
                                 {**a.attrs, "static_correction": model.static_correction,
                                  "n_modes": int(model.n_modes), "n_basis": int(model.n_basis)})
    if model.static_compliance is not None:
        tree[f"{group}/static_compliance"] = Dataset(
            model.static_compliance, compliance_units,
            "exact FE static compliance T K^-1 F (outputs x inputs), full solve",
            {"rows": list(ss.port_names), "columns": list(ss.input_names)})
    if model.residual is not None:
        tree[f"{group}/residual_flexibility"] = Dataset(
            model.residual, compliance_units,
            "T K^-1 F - Theta Omega2^-1 Sigma, added to the position rows of D")
    return tree


# --------------------------------------------------------------------------- stress modes
def stress_modes_datasets(stress: np.ndarray, strain: np.ndarray, model: ReducedModel,
                          input_units: Sequence[str], group: str = STRESS_MODES.path
                          ) -> dict[str, Dataset]:
    """The ``stress_modes`` group (docs/hdf5-format.md): ``stress`` (Pa per unit coordinate)
    and ``strain`` (1 per unit coordinate), each (n_points, 6, n_b + n_c), of the n_b basis
    vectors of ``model`` (the states eta of the plant) followed by its n_c static
    correction shapes (residual flexibility: one per input, per unit input); Voigt order
    VOIGT_ORDER, engineering shear strain; ``shape_names`` and ``shape_units``.
    """
    n_b = int(model.n_basis)
    n_c = stress.shape[2] - n_b
    if stress.shape != strain.shape or n_c not in (0, len(model.statespace.input_names)):
        raise ValueError(f"stress {stress.shape} / strain {strain.shape} do not match a basis "
                         f"of {n_b} and {len(model.statespace.input_names)} inputs")
    inputs = model.statespace.input_names
    names = [f"eta_{k + 1}" for k in range(n_b)] + [f"residual/{u}" for u in inputs][:n_c]
    per = ["m kg^1/2"] * n_b + [input_units[j] for j in range(n_c)]
    attrs = {"voigt_order": list(VOIGT_ORDER), "shear_strain": "engineering (gamma = 2 eps)",
             "recovery": "volume-weighted average of element-average values over the elements "
                         "around each mesh point", "n_basis": n_b, "n_correction": n_c,
             "static_correction": model.static_correction}
    return {
        f"{group}/stress": Dataset(stress, "Pa", "stress of each basis vector, then each static "
                                   "correction shape (n_points, 6, n_shapes), per unit modal "
                                   "coordinate / unit input (shape_units)", attrs),
        f"{group}/strain": Dataset(strain, "1", "strain of the same shapes (engineering shear)",
                                   attrs),
        f"{group}/shape_names": Dataset(names, "", "eta_k: basis vector k (state eta_k); "
                                        "residual/<input>: residual flexibility shape"),
        f"{group}/shape_units": Dataset(per, "", "unit of the coordinate that multiplies each "
                                        "shape (eta_k: m kg^1/2; an input: its own unit); "
                                        "stress = sum_k stress[:, :, k] coordinate_k"),
    }


# --------------------------------------------------------------------------- filtered model
def filter_group_attrs(kind: str, cutoff_hz: float | None,
                       group: str = STATESPACE_FILTERED.path) -> dict[str, dict]:
    """Group attributes ``{group: {"filter_kind": kind, "cutoff_hz": Hz}}`` (NaN: none)."""
    f_c = check_filter(kind, cutoff_hz)
    return {group: {"filter_kind": kind, "cutoff_hz": float("nan") if f_c is None else f_c}}


def filter_datasets(model: StateSpaceModel | ReducedModel, kind: str, cutoff_hz: float | None,
                    group: str = STATESPACE_FILTERED.path) -> dict[str, Dataset]:
    """HDF5 datasets of the filtered model, keyed ``"<group>/<name>"``.

    ``model`` is the plant (a :class:`ReducedModel` or its ``statespace``; it is
    filtered here with :func:`filtered_model`) or a model :func:`filtered_model`
    already returned with this same kind and cutoff. Datasets: A, B, C, D, the names,
    ``damping_ratios`` and ``frequencies_hz`` as in
    :func:`pipeline.reduce.modal.statespace_datasets`, plus ``cutoff_hz`` (Hz, NaN for
    none); A, B, C, D carry the attributes ``filter_kind`` and ``cutoff_hz``. The same
    two values as group attributes: :func:`filter_group_attrs`.
    """
    ss = model.statespace if isinstance(model, ReducedModel) else model
    f_c = check_filter(kind, cutoff_hz)
    if ss.filter_kind == "none":
        ss = filtered_model(ss, kind, f_c)
    elif ss.filter_kind != kind or not math.isclose(ss.cutoff_hz, f_c or 0.0, rel_tol=1e-12):
        raise ValueError(f"model was filtered with {ss.filter_kind} at {ss.cutoff_hz} Hz, "
                         f"not {kind} at {cutoff_hz} Hz")
    stored = float("nan") if f_c is None else f_c
    tree = _statespace_tree(ss, group, {"filter_kind": kind, "cutoff_hz": stored})
    tree[f"{group}/cutoff_hz"] = Dataset(np.float64(stored), "Hz",
                                         f"cutoff of the {kind} output filter (NaN: no filter)")
    return tree


# --------------------------------------------------------------------------- lumped chain
def _q_units(model: LumpedModel) -> list[str]:
    return ["m" if DOF_KIND[d] == "prismatic" else "rad" for d in model.dof_names]


def lumped_datasets(model: LumpedModel, comparison: Sequence[ComparisonRow] | None = None,
                    prefix: str = LUMPED.path) -> dict[str, Dataset]:
    """The HDF5 contents of the chain under ``prefix/`` (every dataset with units).

    Joint coordinates q are listed in ``stiffness.attrs['dof_names']`` (``j<joint>.<dof>``,
    joint 1-based); matrices over q carry units ``mixed`` with per-DOF units in attrs.
    ``joint_table/<column>``: one row per joint DOF, parallel arrays, directly usable by a
    rigid-body code: joint (1-based), dof, kind (revolute | prismatic), position (m,
    x y z), axis (unit vector), stiffness (N/m or N m/rad), damping (N s/m or N m s/rad).
    """
    p = prefix.rstrip("/")
    nq = model.M.shape[0]
    names = [f"j{j + 1}.{d}" for j, d in zip(model.dof_joint, model.dof_names)]
    qu = _q_units(model)
    kinds = [DOF_KIND[d] for d in model.dof_names]
    k_units = ["N/m" if k == "prismatic" else "N m/rad" for k in kinds]
    c_units = ["N s/m" if k == "prismatic" else "N m s/rad" for k in kinds]
    q_attrs = {"dof_names": names, "dof_units": qu}
    mixed_spring = {"prismatic": "N/m", "revolute": "N m/rad"}
    mixed_damper = {"prismatic": "N s/m", "revolute": "N m s/rad"}
    ss_attrs = {"input_names": list(model.input_names), "output_names": list(model.output_names),
                "state_names": list(model.state_names),
                "input_direction": model.input_direction.tolist(),
                "output_direction": model.output_direction.tolist()}
    sec = model.section
    jp = model.joint_positions
    out: dict[str, Dataset] = {
        "joint_positions": Dataset(jp, "m", "joint positions (x, y, z), on the beam axis"),
        "element_mass": Dataset(model.element_mass, "kg", "mass of each moving rigid body"),
        "element_com": Dataset(model.element_com, "m", "centre of mass of each rigid body"),
        "element_extent": Dataset(model.element_extent, "m",
                                  "x at the two ends of each rigid body (joint b to joint b+1)"),
        "element_inertia": Dataset(model.element_inertia, "kg m^2",
                                   "inertia tensor of each body about its centre of mass, x y z axes"),
        "stiffness": Dataset(model.K, "mixed", "joint stiffness matrix K (diagonal) over q",
                             {**q_attrs, **mixed_spring}),
        "mass_matrix": Dataset(model.M, "mixed", "chain mass matrix M over q: kg (m, m), "
                               "kg m (m, rad), kg m^2 (rad, rad)", q_attrs),
        "damping": Dataset(model.damping_matrix, "mixed",
                           "joint damping matrix C = beta K (diagonal) over q",
                           {**q_attrs, **mixed_damper, "rule": "stiffness-proportional",
                            "beta_s": model.damping_beta, "ratio": model.damping_ratio,
                            "reference_hz": model.damping_reference_hz}),
        "frequencies_hz": Dataset(model.frequencies_hz, "Hz", "natural frequencies of the chain"),
        "mode_labels": Dataset(list(model.mode_labels), "1",
                               "family of each mode: axial | torsion | bending_y | bending_z"),
        "mode_shapes": Dataset(model.mode_shapes, "mixed",
                               "M-normalised mode shapes over q (columns), rows in dof_names order",
                               q_attrs),
        "modal_damping_ratios": Dataset(model.modal_damping_ratios, "1",
                                        "damping ratio of each mode, xi omega_i / omega_ref"),
        "tip_compliance": Dataset(np.float64(model.tip_compliance), "m/N",
                                  "static tip displacement along the tip force per newton",
                                  {"force_direction": model.input_direction.tolist()}),
        "static_tip_deflection": Dataset(model.tip_deflection, "m",
                                         "static tip displacement (x, y, z) under the tip force",
                                         {"tip_force_N": model.tip_force,
                                          "force_direction": model.input_direction.tolist()}),
        "section/area": Dataset(np.float64(sec.area), "m^2", "section area", {"source": sec.source}),
        "section/I_y": Dataset(np.float64(sec.I_y), "m^4", "second moment about y (int z^2 dA)",
                               {"source": sec.source}),
        "section/I_z": Dataset(np.float64(sec.I_z), "m^4", "second moment about z (int y^2 dA)",
                               {"source": sec.source}),
        "section/J": Dataset(np.float64(sec.J), "m^4", "Saint-Venant torsion constant",
                             {"source": sec.source}),
        "section/I_p": Dataset(np.float64(sec.I_p), "m^4", "polar moment I_y + I_z",
                               {"source": sec.source}),
        "statespace/A": Dataset(model.A, "mixed", "state matrix, state [eta; eta'] (modal)",
                                {**ss_attrs, "units_note": "1/s^2 and 1/s entries"}),
        "statespace/B": Dataset(model.B, "mixed", "input matrix, input: tip force (N)", ss_attrs),
        "statespace/C": Dataset(model.C, "mixed",
                                "output matrix, outputs: tip position (m), velocity (m/s), "
                                "acceleration (m/s^2) along output_direction", ss_attrs),
        "statespace/D": Dataset(model.D, "mixed", "feedthrough, nonzero only in the acceleration "
                                "row: (m/s^2)/N", ss_attrs),
        "joint_table/joint": Dataset(model.dof_joint + 1, "1", "joint index (1-based, 1 at the clamp end)"),
        "joint_table/dof": Dataset(list(model.dof_names), "1", "axial | torsion | bend_y | bend_z"),
        "joint_table/kind": Dataset(kinds, "1", "revolute (about axis) | prismatic (along axis)"),
        "joint_table/position": Dataset(jp[model.dof_joint], "m", "joint position (x, y, z)"),
        "joint_table/axis": Dataset(np.array([DOF_AXIS[d] for d in model.dof_names]).reshape(nq, 3),
                                    "1", "joint axis unit vector (x, y, z)"),
        "joint_table/stiffness": Dataset(np.diag(model.K).copy(), "mixed",
                                         "spring constant of the joint DOF",
                                         {**mixed_spring, "row_units": k_units}),
        "joint_table/damping": Dataset(model.joint_damping, "mixed",
                                       "damper constant of the joint DOF",
                                       {**mixed_damper, "row_units": c_units}),
    }
    if comparison:
        count = len(comparison[0].frequencies_hz)
        out.update({
            "comparison/model": Dataset([r.model for r in comparison], "1",
                                        "beam theory | FE | simple | refined"),
            "comparison/n": Dataset(np.array([-1 if r.n is None else r.n for r in comparison]), "1",
                                    "number of elements (-1 for the references)"),
            "comparison/frequencies_hz": Dataset(
                np.array([r.frequencies_hz for r in comparison]).reshape(-1, count), "Hz",
                "lowest bending frequencies per row (NaN where absent)"),
            "comparison/tip_deflection": Dataset(np.array([r.tip_deflection for r in comparison]),
                                                 "m", "static tip deflection along the force"),
            "comparison/frequency_error": Dataset(
                np.array([r.frequency_error for r in comparison]).reshape(-1, count), "1",
                "relative error against beam theory"),
            "comparison/deflection_error": Dataset(
                np.array([r.deflection_error for r in comparison]), "1",
                "relative error against beam theory"),
        })
    return {f"{p}/{k}": v for k, v in out.items()}


def lumped_group_attrs(model: LumpedModel, prefix: str = LUMPED.path) -> dict[str, dict[str, Any]]:
    """Attributes of the ``prefix`` group: kind, n, element length, section source, damping rule."""
    return {prefix.rstrip("/"): {
        "constants": model.kind, "elements": model.n,
        "element_length_m": model.constants.element_length,
        "joint_dofs": list(model.constants.dofs), "section_source": model.section.source,
        "damping_rule": "stiffness-proportional C = beta K, beta = 2 xi / omega_ref",
        "coordinates": "joint coordinates q, joint-major; linearised about the straight beam",
    }}


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
    if include_shapes:
        n_nodes = cb.shapes.shape[0] // 3
        tree[f"{group}/shapes"] = Dataset(
            cb.shapes.reshape(n_nodes, 3, -1), "mixed",
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
    A = sp.triu(A, format="csr") if symmetric else sp.csr_matrix(A, copy=True)
    A.eliminate_zeros()  # the assembled M stores the zero off-diagonals of its 3x3 blocks
    A.sort_indices()
    itype = np.int32 if A.nnz < 2**31 - 1 else np.int64
    storage = "upper" if symmetric else "full"
    return {
        f"{group}/data": Dataset(A.data.astype(np.float64), units, description,
                                 {"storage": storage, "format": "csr"}),
        f"{group}/indices": Dataset(A.indices.astype(itype), "1", "CSR column indices"),
        f"{group}/indptr": Dataset(A.indptr.astype(np.int64), "1", "CSR row pointers"),
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
