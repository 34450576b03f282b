"""Ports: named loads (F) and sensors (T) on regions of the body.

An input distributes a unit force or moment over a region's nodes like a
distributing coupling (RBE3): nodal weights are the integrals of the shape functions
over the region (:func:`pipeline.fe.space.weighted_region`), so

- a unit force along d gives f_i = (w_i / A) d: resultant d, zero moment about the
  region's centroid c;
- a unit moment about d gives f_i = w_i (alpha x r_i), r_i = x_i - c, with
  alpha = J^-1 d and J = sum_i w_i (|r_i|^2 I - r_i r_i^T): resultant 0, moment d.

An output is the adjoint: a displacement output is the area-weighted mean motion of
the region along d; a rotation output is the least-squares small rotation of the
region about d (theta = J^-1 sum_i w_i r_i x u_i).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
import scipy.sparse as sp

from pipeline.config import Material, Port, Ports
from pipeline.config.schema import GAUGE_KINDS
from pipeline.errors import RegionError
from pipeline.fe.space import FESpace, WeightedRegion, weighted_region
from pipeline.fe.regions import get_region
from pipeline.fe.strain import gauge_row

UNITS = {"force": "N", "moment": "N m", "displacement": "m", "rotation": "rad",
         "strain": "1", "stress": "Pa"}


@dataclass(frozen=True)
class PortMatrices:
    """F (n_dofs x n_u) nodal loads per unit input; T (n_y x n_dofs) sensors.

    input_names / output_names: port names; input_units / output_units: their SI units.
    """

    F: sp.csc_matrix
    T: sp.csr_matrix
    input_names: tuple[str, ...]
    output_names: tuple[str, ...]
    input_units: tuple[str, ...]
    output_units: tuple[str, ...]


def _rotation_weights(region: WeightedRegion, points: np.ndarray, direction: np.ndarray,
                      key: str) -> np.ndarray:
    """(n_r, 3): w_i (alpha x r_i) with alpha = J^-1 d (see the module docstring)."""
    r = points[region.nodes] - region.centroid
    w = region.weights
    J = (w * (r * r).sum(1)).sum() * np.eye(3) - (w[:, None, None] * r[:, :, None]
                                                   * r[:, None, :]).sum(0)
    eig = np.linalg.eigvalsh(J)
    if eig[0] <= 1e-10 * max(eig[-1], 1e-300):
        raise RegionError(f"config key '{key}': region '{region.name}' cannot carry a rotation "
                          "about every axis (its nodes lie on a line or a point); expected a "
                          "surface region")
    alpha = np.linalg.solve(J, direction)
    return w[:, None] * np.cross(alpha, r)


def port_vector(space: FESpace, region: WeightedRegion, port: Port, key: str) -> np.ndarray:
    """(n_dofs,) nodal load of a unit input, or sensor row of an output, on ``region``."""
    d = np.asarray(port.direction, dtype=float)
    d = d / np.linalg.norm(d)
    if port.kind in ("force", "displacement"):
        per_node = (region.weights / region.measure)[:, None] * d
    else:
        per_node = _rotation_weights(region, space.node_points, d, key)
    vec = np.zeros((space.n_nodes, 3))
    vec[region.nodes] = per_node
    return vec.ravel()


def _gauge_row(space: FESpace, regions: Mapping[str, np.ndarray], port: Port,
               material: Material | None, key: str) -> np.ndarray:
    """(n_dofs,) sensor row of the gauge output ``port`` (config key ``key``)."""
    tris = get_region(regions, port.region, f"{key}.region") if port.region else None
    return gauge_row(space, material, port.kind, port.direction, port.direction2, tris,
                     port.point, port.radius, key, port.length, port.width, port.average)


def port_matrices(space: FESpace, regions: Mapping[str, np.ndarray], ports: Ports,
                  material: Material | None = None) -> PortMatrices:
    """Assemble F and T for the configured ports (``material``: for stress outputs, a
    Material or the per-element :class:`~pipeline.fe.materials.ElementMaterials`)."""
    cache: dict[str, WeightedRegion] = {}

    def columns(items: Sequence[Port], side: str) -> sp.csc_matrix:
        cols = []
        for i, port in enumerate(items):
            key = f"ports.{side}[{i}]"
            if port.kind in GAUGE_KINDS:
                cols.append(sp.csc_matrix(_gauge_row(space, regions, port, material, key)[:, None]))
                continue
            if port.region not in cache:
                cache[port.region] = weighted_region(
                    space, port.region, get_region(regions, port.region, f"{key}.region"))
            cols.append(sp.csc_matrix(port_vector(space, cache[port.region], port, key)[:, None]))
        if not cols:
            return sp.csc_matrix((space.n_dofs, 0))
        return sp.hstack(cols, format="csc")

    F = columns(ports.inputs, "inputs")
    T = columns(ports.outputs, "outputs").T.tocsr()
    return PortMatrices(F, T, tuple(p.name for p in ports.inputs),
                        tuple(p.name for p in ports.outputs),
                        tuple(UNITS[p.kind] for p in ports.inputs),
                        tuple(UNITS[p.kind] for p in ports.outputs))


def check_gauges(space: FESpace, regions: Mapping[str, np.ndarray], ports: Ports,
                 material: Material | None = None) -> None:
    """Place every gauge output (its point, or the surface it covers) on the mesh, so that
    a gauge off the surface or outside the body stops a run in one line before the long
    stages; the rows are built again with the other ports after the modes (cheap)."""
    for i, port in enumerate(ports.outputs):
        if port.kind in GAUGE_KINDS:
            _gauge_row(space, regions, port, material, f"ports.outputs[{i}]")
