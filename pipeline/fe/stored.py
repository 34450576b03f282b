"""The finite-element matrices of a stored result, rebuilt from the file's own mesh.

Exports that need the full M and K (Exudyn) read them from ``/fe`` where a run stored
them (configs with ``connections``). For any other file they are assembled again here
from what every file holds: the mesh (``/mesh/points``, ``/mesh/cells``,
``/mesh/regions``) and the stored config (material, element order, ports). No mesh
generator runs: the space is built on the stored vertices and tetrahedra, and its node
positions are checked against the stored ones (the same edge numbering), so the DOF
order is the file's.

:func:`matrices_of_stored_mesh` returns a :class:`StoredFE`: K_full (N/m) and M_full (kg),
(3 n_points)^2 CSR of the unsupported body, and F (3 n_points, n_u), the nodal loads of
a unit value of each input port (zero columns: none).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Mapping

import numpy as np
import scipy.sparse as sp

from pipeline.config import Config, Ports
from pipeline.errors import MeshError
from pipeline.fe.added_mass import added_mass_matrix
from pipeline.fe.assemble import assemble_stiffness_mass
from pipeline.fe.materials import config_materials
from pipeline.fe.mesh.common import BodyMesh
from pipeline.fe.ports import port_matrices
from pipeline.fe.space import build_space

log = logging.getLogger(__name__)

__all__ = ["StoredFE", "matrices_of_stored_mesh"]


@dataclass(frozen=True, eq=False)
class StoredFE:
    """K_full, M_full (n_dofs, n_dofs) CSR; F (n_dofs, n_u) loads per unit input;
    input_names (n_u,); source: how they were obtained (a sentence)."""

    K_full: sp.csr_matrix | None
    M_full: sp.csr_matrix | None
    F: np.ndarray
    input_names: tuple[str, ...]
    source: str


def matrices_of_stored_mesh(cfg: Config, points: np.ndarray, cells: np.ndarray,
                            regions: Mapping[str, np.ndarray], what: str,
                            assemble: bool = True, materials=None) -> StoredFE:
    """Assemble K and M of the unsupported body on the stored mesh (``points`` (n_p, 3),
    ``cells`` (n_t, 4 | 10) meshio order, boundary ``regions``) with ``cfg``'s material
    (None, None without ``assemble``), and the port loads of ``cfg.ports.inputs``.
    ``what`` names the file in errors. ``materials``: the file's per-element materials
    (:class:`pipeline.fe.materials.ElementMaterials`; None: resolve ``cfg``'s on the mesh)."""
    n_vertices = int(cells[:, :4].max()) + 1
    body = BodyMesh(np.asarray(points[:n_vertices], float), np.asarray(cells[:, :4], np.int64),
                    {k: np.asarray(v, np.int64) for k, v in regions.items()}, what)
    order = 2 if cells.shape[1] == 10 else 1
    space = build_space(body, order)
    if space.node_points.shape != points.shape or not np.array_equal(space.node_points, points):
        raise MeshError(f"{what}: the stored mesh does not rebuild to the same nodes (edge "
                        "nodes in another order); cannot re-assemble its matrices",
                        key=what, value="different node order",
                        expected="the pipeline's own edge numbering")
    materials = materials if materials is not None else config_materials(space, cfg)
    K, M = (assemble_stiffness_mass(space, materials) if assemble
            else (None, None))
    added = added_mass_matrix(space, regions, cfg.masses) if assemble else None
    if added is not None:
        M = (M + added).tocsr()
    n_u = len(cfg.ports.inputs)
    F = np.zeros((space.n_dofs, 0))
    names: tuple[str, ...] = ()
    if n_u:
        # the input loads only: the stored output rows are the file's own (a gauge's row
        # depends on the version that placed it)
        ports = port_matrices(space, regions, Ports(inputs=cfg.ports.inputs))
        F, names = ports.F.toarray(), tuple(ports.input_names)
    if assemble:
        log.info("re-assembled K and M of %s on its stored mesh (%d DOFs)", what, space.n_dofs)
    return StoredFE(K, M, F, names,
                    "M and K re-assembled from the stored config and mesh at export" if assemble
                    else "M and K stored by the run (/fe)")
