"""The typed records the readers of :mod:`pipeline.store.read` return.

One record per question a tool asks of a result file:

===========================  ================================================================
:class:`StoredModels`        every reduced model of a file (what ``pipeline.load_model`` gives)
:class:`StoredCraigBampton`  the Craig-Bampton reduced M and K as stored (read side of
                             :class:`pipeline.reduce.craig_bampton.CraigBamptonModel`)
:class:`ModelFile`           the models plus what a simulation needs: ports, supports, body
:class:`StoredMesh`          the mesh and the mode shapes: pictures and mesh exports
:class:`StoredFEModel`       the mesh, the full M and K (``/fe``) and one mode basis: what
                             an export of the full FE body (Exudyn) needs
:class:`StressModes`         stress and strain per unit coordinate at the mesh points
===========================  ================================================================

Each holds its arrays once; derived views (the python-control system, the plant's raw
matrices) are built from them on use. No record imports :mod:`pipeline.fe`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.errors import FileFormatError
from pipeline.reduce.statespace import StateSpace

__all__ = ["StoredModels", "StoredCraigBampton", "ModelFile", "StoredMesh", "StoredBasis",
           "StoredFEModel", "StressModes", "to_control"]


def to_control(model: StateSpace):
    """``model`` as a python-control StateSpace with its names (deferred import)."""
    import control

    return control.ss(model.A, model.B, model.C, model.D,
                      inputs=list(model.input_names) or None,
                      outputs=list(model.output_names) or None,
                      states=list(model.state_names) or None)


@dataclass(frozen=True, eq=False)
class StoredCraigBampton:
    """The Craig-Bampton model as a file stores it: M q'' + K q = f.

    M, K (n, n): entries in kg m^2 / (u_i u_j) and N m / (u_i u_j), u the coordinate units;
    coordinate_names, coordinate_units (n,); interface_names (k,); interface_points (k, 3) m;
    fixed_interface_frequencies_hz (N,) Hz; free_frequencies_hz (n,) Hz (empty when the file
    lacks them)."""

    M: np.ndarray
    K: np.ndarray
    coordinate_names: tuple[str, ...]
    coordinate_units: tuple[str, ...]
    interface_names: tuple[str, ...]
    fixed_interface_frequencies_hz: np.ndarray
    interface_points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    free_frequencies_hz: np.ndarray = field(default_factory=lambda: np.zeros(0))


@dataclass(frozen=True, eq=False)
class StoredModels:
    """Every reduced model of one result file, as :class:`StateSpace` (the plant held once).

    plant: the modal model of ``/statespace`` (inputs ``input_names``; outputs position,
    velocity and acceleration of every output port), or None in a file without it
    (connection-point or Craig-Bampton models only); filtered: its loop-breaking filtered
    twin (D = 0), or None; lumped: the lumped chain's model; connections: connection-point
    models by name; craig_bampton: the stored reduced M and K.
    frequencies_hz (n_m,) Hz, labels (n_m,): every mode of the file; damping_ratios and
    retained_frequencies_hz (n_r,): of the modes in the plant; static_compliance (n_y, n_u):
    the full-FE T K^-1 F (rows ``compliance_rows``), or None; input_units (n_u,) and
    port_units (n_y,): SI unit of each input and of each output port's position; name: the
    config's name; mass: the body's mass (kg, NaN when the file lacks ``/body``);
    config_yaml: the stored config (YAML text, empty when absent).

    ``ss`` / ``ss_filtered`` (python-control) and ``matrices`` / ``matrices_filtered``
    (the raw A, B, C, D) are views built from the plant on use.
    :attr:`models` lists every model by name; :meth:`model` picks one.
    """

    path: Path
    frequencies_hz: np.ndarray
    labels: tuple[str, ...]
    plant: StateSpace | None = None
    filtered: StateSpace | None = None
    damping_ratios: np.ndarray = field(default_factory=lambda: np.zeros(0))
    retained_frequencies_hz: np.ndarray = field(default_factory=lambda: np.zeros(0))
    static_compliance: np.ndarray | None = None
    compliance_rows: tuple[str, ...] = ()
    input_units: tuple[str, ...] = ()
    port_units: tuple[str, ...] = ()
    lumped: StateSpace | None = None
    connections: dict[str, StateSpace] = field(default_factory=dict)
    craig_bampton: StoredCraigBampton | None = None
    name: str = ""
    mass: float = math.nan
    config_yaml: str = ""

    # ------------------------------------------------------------------ plant views
    @cached_property
    def ss(self):
        """The plant as a python-control StateSpace (None without a plant)."""
        return None if self.plant is None else to_control(self.plant)

    @cached_property
    def ss_filtered(self):
        """The filtered model as a python-control StateSpace, or None."""
        return None if self.filtered is None else to_control(self.filtered)

    @property
    def matrices(self) -> dict[str, np.ndarray]:
        """The plant's A, B, C, D (read-only arrays; empty without a plant)."""
        return {} if self.plant is None else dict(zip("ABCD", self.plant))

    @property
    def matrices_filtered(self) -> dict[str, np.ndarray] | None:
        """The filtered model's A, B, C, D, or None."""
        return None if self.filtered is None else dict(zip("ABCD", self.filtered))

    @property
    def input_names(self) -> tuple[str, ...]:
        return () if self.plant is None else self.plant.input_names

    @property
    def output_names(self) -> tuple[str, ...]:
        return () if self.plant is None else self.plant.output_names

    @property
    def state_names(self) -> tuple[str, ...]:
        return () if self.plant is None else self.plant.state_names

    @property
    def filter_kind(self) -> str:
        """The output filter of the filtered model (``"none"`` without one)."""
        return "none" if self.filtered is None else self.filtered.filter_kind

    @property
    def cutoff_hz(self) -> float | None:
        """The filter's cutoff (Hz), or None."""
        return None if self.filtered is None else self.filtered.cutoff_hz

    # ------------------------------------------------------------------ by name
    @property
    def models(self) -> dict[str, Any]:
        """Every model in the file by name: ``plant``, ``filtered``, ``lumped``,
        ``connection/<name>`` (StateSpace) and ``craig_bampton`` (StoredCraigBampton)."""
        out: dict[str, Any] = {"plant": self.plant, "filtered": self.filtered,
                               "lumped": self.lumped}
        out.update({f"connection/{k}": v for k, v in self.connections.items()})
        out["craig_bampton"] = self.craig_bampton
        return {k: v for k, v in out.items() if v is not None}

    def model(self, name: str):
        """One model of :attr:`models` by name; FileFormatError naming what the file has."""
        try:
            return self.models[name]
        except KeyError:
            raise FileFormatError(f"file '{self.path}': holds no '{name}' model; it holds "
                                  f"{', '.join(self.models) or 'none'}", key=str(self.path),
                                  value=name, expected="one of " + ", ".join(self.models)
                                  ) from None


@dataclass(frozen=True, eq=False)
class ModelFile:
    """What a simulation reads from one model file: its models (read once, in ``models``)
    and the ports, supports and body data of the stored config and mesh.

    plant / filtered: the models of ``models`` (labelled ``FE`` / ``FE filtered``);
    ports: name -> {side, kind, region, direction (unit vector or None)};
    region_centroids (3,) m by region; body_mass kg, body_com (3,) m, body_inertia (3, 3)
    kg m^2 (NaN where the file lacks them); lumped: the chain's A, B, C, D, names, port
    directions and rigid bodies (element_* and joint_positions arrays), or None.
    """

    path: Path
    sha256: str
    models: StoredModels
    ports: dict[str, dict[str, Any]]
    support_regions: tuple[str, ...]
    region_centroids: dict[str, np.ndarray]
    body_mass: float
    body_com: np.ndarray
    body_inertia: np.ndarray
    lumped: dict[str, Any] | None
    in_plane: bool = False

    @property
    def plant(self) -> StateSpace:
        return self.models.plant

    @property
    def filtered(self) -> StateSpace | None:
        return self.models.filtered

    @property
    def frequencies_hz(self) -> np.ndarray:
        return self.models.frequencies_hz

    @property
    def labels(self) -> tuple[str, ...]:
        return self.models.labels


@dataclass(frozen=True, eq=False)
class StoredMesh:
    """The mesh and the mode shapes of a file: what pictures and mesh exports need.

    points (n_p, 3) m; cells (n_t, 4 | 10) node indices in meshio order, of ``cell_type``;
    shapes (n_p, 3, n_m) kg^-1/2; frequencies_hz (n_m,); labels (n_m,); fixed_dofs (n_c,)
    (DOF 3 node + component); regions: vertex cells by name ((n, 3) face, (n, 2) line,
    (n, 1) point set);
    retained_damping: damping ratios of the modes in ``/statespace`` (empty without it);
    config_yaml: the stored config (YAML text, empty when absent); has_fe: the file holds
    the full M and K (``/fe``).
    """

    name: str
    points: np.ndarray
    cell_type: str
    cells: np.ndarray
    shapes: np.ndarray
    frequencies_hz: np.ndarray
    labels: tuple[str, ...]
    fixed_dofs: np.ndarray
    regions: dict[str, np.ndarray]
    retained_damping: np.ndarray
    has_statespace: bool
    config_yaml: str = ""
    has_fe: bool = False

    @property
    def fixed_nodes(self) -> np.ndarray:
        """Nodes with at least one constrained DOF."""
        return np.unique(self.fixed_dofs // 3)


@dataclass(frozen=True, eq=False)
class StoredBasis:
    """One mode basis of a file, on every DOF of the mesh (DOF 3 node + component).

    kind: ``"modes"`` (``/modes/shapes``, M-orthonormal, kg^-1/2) or ``"craig_bampton"``
    (``/craig_bampton/shapes``, per unit coordinate); shapes (n_dofs, n); names (n,): the
    Craig-Bampton coordinate names (empty for modes); n_rigid: the leading rigid-body
    modes (0 for a Craig-Bampton basis); interface_names: the Craig-Bampton interfaces in
    stored order (empty for modes).
    """

    kind: str
    shapes: np.ndarray
    names: tuple[str, ...]
    n_rigid: int = 0
    interface_names: tuple[str, ...] = ()


@dataclass(frozen=True, eq=False)
class StoredFEModel:
    """The full finite-element body of a file: what an export of it (Exudyn) reads.

    name: the config's name (the file's stem when absent); points (n_p, 3) m; cells
    (n_t, 4 | 10) node indices in meshio order, of ``cell_type``; fixed_dofs (n_c,);
    regions: vertex cells by name ((n, 3) face, (n, 2) line, (n, 1) point set); M, K (3 n_p, 3 n_p) CSR of the
    unsupported body in kg and N/m from ``/fe``, or None in a file without it (then
    :class:`pipeline.fe.stored.StoredFE` re-assembles them); basis: the mode basis asked for.
    """

    name: str
    points: np.ndarray
    cell_type: str
    cells: np.ndarray
    fixed_dofs: np.ndarray
    regions: dict[str, np.ndarray]
    M: Any
    K: Any
    basis: StoredBasis

    @property
    def has_fe(self) -> bool:
        """The file holds the full M and K (``/fe``)."""
        return self.M is not None and self.K is not None

    @property
    def n_dofs(self) -> int:
        return 3 * self.points.shape[0]


@dataclass(frozen=True)
class StressModes:
    """The ``stress_modes`` group (docs/hdf5-format.md): stress and strain at the mesh points
    of each basis vector of the plant (coordinate eta_k, m kg^1/2) and of each residual
    flexibility shape (coordinate: input j, in its unit).

    stress (n_p, 6, n_b + n_c) Pa per unit coordinate; strain (n_p, 6, n_b + n_c) 1 per unit
    coordinate, engineering shear; Voigt order ``voigt_order``; shape_names, shape_units;
    n_basis n_b, n_correction n_c; input_names: the plant's inputs (the residual shapes);
    points (n_p, 3) m, the mesh points the fields are given at.
    """

    points: np.ndarray
    stress: np.ndarray
    strain: np.ndarray
    shape_names: tuple[str, ...]
    shape_units: tuple[str, ...]
    voigt_order: tuple[str, ...]
    n_basis: int
    n_correction: int
    input_names: tuple[str, ...]


@dataclass(frozen=True, eq=False)
class StoredMaterials:
    """The material of every element of a file (``/materials``): names (n_laws,),
    stiffness (n_laws, 6, 6) Pa global frame (Voigt, engineering shear), density
    (n_laws,) kg/m^3, element_material (n_t,) index, element_density (n_t,) kg/m^3."""

    names: tuple[str, ...]
    stiffness: np.ndarray
    density: np.ndarray
    element_material: np.ndarray
    element_density: np.ndarray
