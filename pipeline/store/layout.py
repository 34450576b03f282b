"""Every path and attribute name of the HDF5 file, named once: the mirror of
docs/hdf5-format.md, section by section.

The one writer (:mod:`pipeline.store.schema`) and the readers (:mod:`pipeline.store.read`)
spell paths through these records, so a renamed dataset is one edit here (and a
``schema_version`` step in the doc). A :class:`Group` answers the full path of one of its
datasets as an attribute (``MODES.frequencies_hz == "modes/frequencies_hz"``) and the name
of one of its attributes under ``attr`` (``MODES.attr.solver == "solver"``); a name the
layout does not list raises AttributeError, so a typo fails where it is written.
``tests/test_store_layout.py`` checks that this module and the doc list the same names and
that a written file holds every dataset the doc promises.
"""

from __future__ import annotations

from typing import Iterator

__all__ = ["Group", "Names", "ROOT", "MESH", "BODY", "MODES", "STATESPACE",
           "STATESPACE_FILTERED", "STRESS_MODES", "LUMPED", "RUN", "CONNECTIONS",
           "CRAIG_BAMPTON", "FFRF", "FE", "MATERIALS", "GROUPS", "connection", "csr_group",
           "STATESPACE_DATASETS", "CELL_TYPES", "cells", "region",
           "connection_statespace", "LUMPED_STATESPACE", "CSR_DATASETS", "SIMULATION_CONTENT",
           "RESULT_ROOT", "RESULT_SUMMARY", "result_run", "result_stress", "result_fit",
           "ROTATION"]


class Names:
    """Validated names: ``names.x`` is ``prefix + "x"`` for a listed ``x``."""

    __slots__ = ("_prefix", "_names")

    def __init__(self, prefix: str, names: tuple[str, ...]) -> None:
        object.__setattr__(self, "_prefix", prefix)
        object.__setattr__(self, "_names", tuple(names))

    def __getattr__(self, name: str) -> str:
        if name.startswith("_"):  # dunder and slot look-ups (copy, pickle): not a name
            raise AttributeError(name)
        if name in self._names:
            return self._prefix + name
        raise AttributeError(f"'{name}' is not in the layout under '{self._prefix or '/'}' "
                             f"(docs/hdf5-format.md lists {', '.join(self._names)})")

    def __setattr__(self, name: str, value) -> None:
        raise AttributeError("the layout is read-only")

    def __reduce__(self):
        return Names, (self._prefix, self._names)

    def __copy__(self):
        return self  # immutable

    def __deepcopy__(self, memo):
        return self

    def __iter__(self) -> Iterator[str]:
        return (self._prefix + n for n in self._names)

    def __contains__(self, name: str) -> bool:
        return name in self._names

    @property
    def names(self) -> tuple[str, ...]:
        """The listed names, without the prefix."""
        return self._names


class Group(Names):
    """One group of the file: ``path``; its datasets (attribute access gives their full
    paths; a dataset below a sub-group is named with ``__`` for ``/``, e.g.
    ``LUMPED.section__I_y == "lumped/section/I_y"``); ``attr``: its attribute names;
    ``optional``: datasets a file may lack (written only in some configurations)."""

    __slots__ = ("path", "attr", "optional")

    def __init__(self, path: str, datasets: tuple[str, ...], attrs: tuple[str, ...] = (),
                 optional: tuple[str, ...] = ()) -> None:
        super().__init__(path + "/", datasets)
        object.__setattr__(self, "path", path)
        object.__setattr__(self, "attr", Names("", attrs))
        object.__setattr__(self, "optional", tuple(optional))

    def __getattr__(self, name: str) -> str:
        return super().__getattr__(name.replace("__", "/"))

    def __reduce__(self):
        return Group, (self.path, self._names, self.attr.names, self.optional)

    def dataset(self, name: str) -> str:
        """The full path of the listed dataset ``name`` (which may contain ``/``)."""
        return self.__getattr__(name)

    def required(self) -> tuple[str, ...]:
        """Full paths of the datasets every file with this group has."""
        return tuple(self._prefix + n for n in self._names if n not in self.optional)

    def __repr__(self) -> str:
        return f"Group({self.path!r})"


# --------------------------------------------------------------------------- root
#: attributes of the file's root (the group "/")
ROOT = Names("", ("schema", "schema_version", "pipeline_version", "created_utc", "name",
                  "config_yaml", "content_sha256", "content_index", "attrs_sha256", "content"))

# --------------------------------------------------------------------------- /mesh
#: element types a file may hold under ``mesh/cells`` (quadratic first)
CELL_TYPES = ("tetra10", "tetra")
MESH = Group("mesh", ("points", "cells", "regions", "fixed_dofs"),
             attrs=("cell_type", "element_order", "source", "source_sha256", "n_dofs",
                    "n_free_dofs"),
             optional=("regions", "fixed_dofs"))


def cells(kind: str) -> str:
    """Path of the connectivity of element type ``kind`` (one of CELL_TYPES)."""
    if kind not in CELL_TYPES:
        raise ValueError(f"cell type {kind!r} is not one of {CELL_TYPES}")
    return f"{MESH.cells}/{kind}"


def region(name: str) -> str:
    """Path of the vertex cells of region ``name`` (triangles, edges or vertices)."""
    return f"{MESH.regions}/{name}"


# --------------------------------------------------------------------------- /body, /modes
BODY = Group("body", ("mass", "center_of_mass", "inertia", "rigid_mass_matrix"))
MODES = Group("modes", ("frequencies_hz", "omega2", "labels", "shapes", "residuals"),
              attrs=("count", "n_rigid", "solver", "shift_rad2_s2", "preconditioned_residual"))

# --------------------------------------------------------------------------- state spaces
#: datasets of every state-space group (names may instead be attributes of ``A``)
STATESPACE_DATASETS = ("A", "B", "C", "D", "input_names", "output_names", "state_names")
_MODAL = STATESPACE_DATASETS + ("frequencies_hz", "damping_ratios")
#: attributes naming what A's rows and B's columns are, and their units
_SS_ATTRS = ("input_names", "output_names", "state_names", "input_units", "output_units",
             "units_note", "static_correction", "n_modes", "n_basis", "filter_kind",
             "cutoff_hz", "input_direction", "output_direction", "rows", "columns")

STATESPACE = Group("statespace", _MODAL + ("static_compliance", "residual_flexibility"),
                   attrs=_SS_ATTRS, optional=("static_compliance", "residual_flexibility"))
STATESPACE_FILTERED = Group("statespace_filtered", _MODAL + ("cutoff_hz",), attrs=_SS_ATTRS)

# --------------------------------------------------------------------------- /stress_modes
STRESS_MODES = Group("stress_modes", ("stress", "strain", "shape_names", "shape_units"),
                     attrs=("voigt_order", "shear_strain", "recovery", "n_basis",
                            "n_correction", "static_correction"))

# --------------------------------------------------------------------------- /lumped
_LUMPED_SECTION = ("area", "I_y", "I_z", "J", "I_p")
_JOINT_TABLE = ("joint", "dof", "kind", "position", "axis", "stiffness", "damping")
_COMPARISON = ("model", "n", "frequencies_hz", "tip_deflection", "frequency_error",
               "deflection_error")
LUMPED = Group(
    "lumped",
    ("joint_positions", "element_mass", "element_com", "element_inertia", "element_extent",
     "stiffness", "mass_matrix", "damping", "frequencies_hz", "mode_labels", "mode_shapes",
     "modal_damping_ratios", "tip_compliance", "static_tip_deflection")
    + tuple(f"section/{k}" for k in _LUMPED_SECTION)
    + tuple(f"statespace/{k}" for k in "ABCD")
    + tuple(f"joint_table/{k}" for k in _JOINT_TABLE)
    + tuple(f"comparison/{k}" for k in _COMPARISON),
    attrs=("constants", "elements", "element_length_m", "joint_dofs", "section_source",
           "damping_rule", "coordinates"),
    optional=tuple(f"comparison/{k}" for k in _COMPARISON))
#: the chain's state space (names and port directions are attributes of its ``A``)
LUMPED_STATESPACE = Group(f"{LUMPED.path}/statespace", tuple("ABCD"), attrs=_SS_ATTRS)

# --------------------------------------------------------------------------- /run
RUN = Group("run", (), attrs=("mesh_s", "assemble_s", "modes_s", "reduce_s", "write_s",
                              "peak_memory_mb", "solver", "rotation_s", "ranks",
                              "parts_file", "parts_sha256"))

# --------------------------------------------------------------------------- connections
CONNECTIONS = Group("connections", ())
_CONNECTION = ("point", "region_nodes", "mass", "center_of_mass", "inertia_G", "inertia_P",
               "D_P", "L_P", "D_P0", "omega", "frequencies_hz", "damping_ratio",
               "effective_mass", "effective_mass_cumulative_fraction", "shapes",
               "child_names", "child_points", "tau_C", "Phi_C")
_CONNECTION_SS = STATESPACE_DATASETS + ("input_units", "output_units")


def connection(name: str) -> Group:
    """The group ``connections/<name>`` of the connection-point model ``name``."""
    return Group(f"{CONNECTIONS.path}/{name}", _CONNECTION, attrs=("region", "coupling"),
                 optional=("shapes", "child_names", "child_points", "tau_C", "Phi_C",
                           "damping_ratio"))


def connection_statespace(name: str) -> Group:
    """The group ``connections/<name>/statespace``."""
    return Group(f"{CONNECTIONS.path}/{name}/statespace", _CONNECTION_SS, attrs=_SS_ATTRS)


# --------------------------------------------------------------------------- Craig-Bampton, FFRF
CRAIG_BAMPTON = Group(
    "craig_bampton",
    ("M", "K", "coordinate_names", "coordinate_units", "interface_names", "interface_regions",
     "interface_couplings", "interface_points", "fixed_interface_frequencies_hz",
     "free_frequencies_hz", "shapes"),
    attrs=("coordinates", "coordinate_units"), optional=("shapes",))
FFRF = Group(
    "ffrf",
    ("origin", "coordinate_names", "mass", "first_moment", "center_of_mass", "inertia",
     "translational_coupling", "rotational_coupling", "modal_mass", "modal_stiffness",
     "inertia_first_order", "inertia_second_order", "gyroscopic_coupling", "basis"),
    attrs=("basis", "coordinates", "coordinate_units", "units_rule"),
    optional=("modal_stiffness", "basis"))

# --------------------------------------------------------------------------- /fe
#: the arrays of one CSR matrix (``data`` carries the attribute ``storage``)
CSR_DATASETS = ("data", "indices", "indptr", "shape")
FE = Group("fe", ("mass_matrix", "stiffness_matrix"))


def csr_group(path: str) -> Group:
    """The CSR arrays of the sparse matrix stored under ``path`` (e.g. ``FE.mass_matrix``)."""
    return Group(path, CSR_DATASETS, attrs=("storage", "format"))


# --------------------------------------------------------------------------- /rotation
ROTATION = Group(
    "rotation",
    ("axis", "point", "speeds_rad_s", "frequencies_hz", "frequencies_reduced_hz",
     "tensor_entries", "basis_stiffness", "basis_mass", "geometric_stiffness",
     "spin_softening", "preload_stiffness", "input_names", "centrifugal_load",
     "euler_load", "coriolis"),
    attrs=("n_modes", "n_basis", "static_shape", "correction_shapes"),
    optional=("preload_stiffness", "input_names", "centrifugal_load", "euler_load",
              "coriolis"))

# --------------------------------------------------------------------------- simulation results
# A simulation's RESULT.h5 (docs/simulate.md, "RESULT.h5 layout"), written through the same
# atomic, signed writer; its groups are named after the scenarios and models it ran.
#: the root attribute ``content`` of a simulation result
SIMULATION_CONTENT = "simulation results"
#: root attributes of a simulation result
RESULT_ROOT = Names("", ("content", "model_file", "model_content_sha256", "scenarios_yaml"))
#: one row per compared quantity
RESULT_SUMMARY = Group("summary", ("scenario", "model", "quantity", "units", "measured",
                                   "predicted"))


def result_run(scenario: str, key: str, run: int | None = None) -> Group:
    """The group of one run, ``<scenario>/<key>[/run_NN]`` (``run``: the index of a mass
    sweep's run): ``time`` (s), ``signals/<name>`` (SI), ``stress/...``."""
    path = f"{scenario}/{key}" + ("" if run is None else f"/run_{run:02d}")
    return Group(path, ("time", "signals", "stress"), attrs=("model", "mass_kg"),
                 optional=("stress",))


def result_stress(run_path: str) -> Group:
    """The stress peak of a run (``<run>/stress``), for a model file with stress modes."""
    return Group(f"{run_path}/stress", ("peak_von_mises", "peak_time", "field_at_hot_spot_peak",
                                        "instants", "fields"),
                 attrs=("hot_spot_index", "hot_spot_point_m", "peak_von_mises_pa",
                        "peak_time_s", "voigt_order"), optional=("instants", "fields"))


def result_fit(scenario: str, key: str) -> Group:
    """The fit of a mass sweep, ``<scenario>/<key>/fit``."""
    return Group(f"{scenario}/{key}/fit", ("masses", "measured_frequency",
                                           "predicted_frequency", "period_squared"))


# --------------------------------------------------------------------------- every group
#: every fixed group, in the doc's order (connections/<name> are made by :func:`connection`)
# --------------------------------------------------------------------------- /materials
#: the material of every element (present when the config has ``materials`` or ``masses``)
MATERIALS = Group("materials", ("material_names", "stiffness", "density", "element_material",
                                "element_density"))

GROUPS: tuple[Group, ...] = (MESH, BODY, MODES, STATESPACE, STRESS_MODES, STATESPACE_FILTERED,
                             LUMPED, RUN, CONNECTIONS, CRAIG_BAMPTON, FFRF, FE, MATERIALS,
                             ROTATION)
