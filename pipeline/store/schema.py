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

from pipeline.reduce.filters import check_filter, filtered_model
from pipeline.reduce.lumped import DOF_AXIS, DOF_KIND, ComparisonRow, LumpedModel
from pipeline.reduce.modal import ReducedModel, StateSpaceModel
from pipeline.reduce.models import Models
from pipeline.store.layout import (BODY, LUMPED, MATERIALS, MESH, MODES, RUN, STATESPACE,
                                   STATESPACE_FILTERED, STRESS_MODES, cells, region)
from pipeline.store.schema_interfaces import (connection_datasets, craig_bampton_datasets,
                                              csr_datasets, exudyn_datasets, ffrf_datasets)
from pipeline.store.tree import Dataset

__all__ = [
    "models_tree",
    "core_datasets",
    "core_group_attrs",
    "materials_datasets",
    "run_group_attrs",
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


# --------------------------------------------------------------------------- mesh, body, modes
#: a region's cells by their vertex count: triangles (a face), edges (a line), vertices
REGION_DESCRIPTIONS = {3: "face: boundary triangles (vertex node indices)",
                       2: "line: edges (vertex node indices)",
                       1: "point set: vertex node indices"}


def core_datasets(space, regions: Mapping[str, np.ndarray], fixed: np.ndarray, props, modes,
                  shapes: np.ndarray, labels: Sequence[str]) -> dict[str, Dataset]:
    """The ``mesh``, ``body`` and ``modes`` datasets of every result file.

    space: the FE space (node_points (n_p, 3) m, element_nodes, cell_type); regions: vertex
    cells by name, (n, 3) triangles, (n, 2) edges or (n, 1) vertices; fixed (n_c,): constrained DOFs; props: the body's
    mass (kg), center_of_mass (3,) m, inertia (3, 3) kg m^2, rigid_mass (6, 6); modes: the
    solve stage's frequencies_hz, omega2 (rad^2/s^2), residuals (n_m,); shapes (n_p, 3, n_m)
    kg^-1/2; labels (n_m,).
    """
    tree = {
        MESH.points: Dataset(space.node_points, "m", "node coordinates (vertices, then edge "
                             "midpoints for quadratic elements)"),
        cells(space.cell_type): Dataset(space.element_nodes.astype(np.int64), "1",
                                        "node indices per element, meshio order"),
        MESH.fixed_dofs: Dataset(fixed.astype(np.int64), "1",
                                 "constrained DOFs; DOF 3*node+c is component c of node"),
        BODY.mass: Dataset(np.float64(props.mass), "kg", "total mass from the FE mass matrix"),
        BODY.center_of_mass: Dataset(props.center_of_mass, "m", "centre of mass"),
        BODY.inertia: Dataset(props.inertia, "kg m^2", "inertia tensor about the centre of mass"),
        BODY.rigid_mass_matrix: Dataset(props.rigid_mass, "mixed",
                                        "R^T M R at the origin, twist order [v; omega]",
                                        {"units_blocks": "kg | kg m ; kg m | kg m^2"}),
        MODES.frequencies_hz: Dataset(modes.frequencies_hz, "Hz", "natural frequencies"),
        MODES.omega2: Dataset(modes.omega2, "rad^2/s^2", "eigenvalues omega^2"),
        MODES.labels: Dataset(list(labels), "1", "dominant motion of each mode"),
        MODES.shapes: Dataset(shapes, "kg^-1/2", "M-orthonormal mode shapes, "
                              "(n_points, 3, n_modes): displacement of every mesh point"),
        MODES.residuals: Dataset(modes.residuals, "1",
                                 "||K phi - omega^2 M phi|| / ||K phi|| per mode"),
    }
    for name, region_cells in regions.items():
        tree[region(name)] = Dataset(region_cells.astype(np.int64), "1",
                                     REGION_DESCRIPTIONS[region_cells.shape[1]])
    return tree


def core_group_attrs(space, element_order: int, n_free_dofs: int, mesh_source: str,
                     mesh_sha256: str, modes, preconditioned_residual: float | None
                     ) -> dict[str, dict[str, Any]]:
    """Attributes of ``/mesh`` and ``/modes`` (docs/hdf5-format.md): the mesh's cell type,
    order, source file and DOF counts; the modes' count, rigid modes, solver backend and
    shift (rad^2/s^2), and the two-grid solver's convergence measure when given."""
    m = MODES.attr
    modes_attrs = {m.count: int(modes.omega2.size), m.n_rigid: modes.n_rigid,
                   m.solver: modes.backend, m.shift_rad2_s2: modes.shift}
    if preconditioned_residual is not None:
        modes_attrs[m.preconditioned_residual] = float(preconditioned_residual)
    a = MESH.attr
    return {MODES.path: modes_attrs,
            MESH.path: {a.cell_type: space.cell_type, a.element_order: element_order,
                        a.source: mesh_source, a.source_sha256: mesh_sha256,
                        a.n_dofs: space.n_dofs, a.n_free_dofs: int(n_free_dofs)}}


def run_group_attrs(times: Mapping[str, float], peak_memory_mb: float, solver: str,
                    ranks: int | None = None, parts: tuple[str, str] | None = None
                    ) -> dict[str, dict[str, Any]]:
    """Attributes of ``/run``: seconds per stage (``<stage>_s``), peak memory, solver;
    ``ranks``: the number of MPI ranks of a distributed run (written only then);
    ``parts``: (path, content_sha256) of the parts file its ranks read (``mesh.parts``,
    written only then)."""
    attrs: dict[str, Any] = {f"{k}_s": v for k, v in times.items()}
    attrs[RUN.attr.peak_memory_mb] = peak_memory_mb
    attrs[RUN.attr.solver] = solver
    if ranks is not None:
        attrs[RUN.attr.ranks] = int(ranks)
    if parts is not None:
        attrs[RUN.attr.parts_file], attrs[RUN.attr.parts_sha256] = parts
    return {RUN.path: attrs}


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


def materials_datasets(materials) -> dict[str, Dataset]:
    """The ``materials`` group: the laws (names, global-frame 6x6 stiffness, density) and
    each element's law and density (:class:`pipeline.fe.materials.ElementMaterials`)."""
    return {
        MATERIALS.material_names: Dataset(list(materials.names), "1", "material names; 0: the default "
                                 "'material'"),
        MATERIALS.stiffness: Dataset(np.asarray(materials.D, float), "Pa",
                                     "6x6 stiffness of each material in the global frame, "
                                     "Voigt [xx, yy, zz, yz, xz, xy], engineering shear"),
        MATERIALS.density: Dataset(np.asarray(materials.law_rho, float), "kg/m^3",
                                   "density of each material"),
        MATERIALS.element_material: Dataset(np.asarray(materials.index, np.int64), "1",
                                            "material index of each element (cells order)"),
        MATERIALS.element_density: Dataset(np.asarray(materials.rho, float), "kg/m^3",
                                           "density of each element, with the mass per "
                                           "volume of 'masses' added"),
    }
