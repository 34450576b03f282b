"""Craig-Bampton reduction of a body with several interfaces.

Each interface ties a region to a point with six DOFs q_k, rigidly (RBE2) or by a
distributing coupling (RBE3); see :mod:`pipeline.reduce.connection` for both couplings and the
change of coordinates s = N z + sum_k E_k q_k that they define. In those coordinates
(K_T = T^T K T, M_T = T^T M T, blocks z and q = [q_1; ...; q_k]):

- fixed-interface modes: K_zz phi = omega^2 M_zz phi (every interface point clamped),
  the lowest N, M-orthonormal (Phi, kg^-1/2);
- static constraint modes: for a unit q_k,j with every other interface DOF fixed, the
  interior takes its static shape z = -K_zz^-1 K_zq q (Psi, one per interface DOF);
- the basis s = [Psi, Phi] [q; eta] reduces K and M to

      K_cb = [[K_bb, 0], [0, diag(omega^2)]],  K_bb = K_qq - K_qz K_zz^-1 K_zq
      M_cb = [[M_bb, M_be], [M_eb, I]]

  with reduced coordinates [q_1 (6); ...; q_k (6); eta_1 .. eta_N], each labelled
  ``<interface>.<x|y|z|rx|ry|rz>`` (m, rad) or ``mode_<i>`` (m kg^1/2).

With one interface, the constraint modes are the rigid-body motions of the body about
the interface point, and the fixed-interface modes are the modes clamped there. With a
free body (no support), K_bb has six zero eigenvalues (the rigid motions) and the
lowest nonzero eigenvalues of (K_cb, M_cb) approximate the free-free modes.

Interface sets are checked before any solve (:func:`pipeline.reduce.interfaces.make_interfaces`):
a region that cannot carry six DOFs, or two interfaces sharing nodes, raise RegionError
naming the region.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from pipeline.errors import RegionError
from pipeline.reduce import connection  # module, so clamped_modes is looked up at call time
from pipeline.reduce.interfaces import (DIRECTIONS, Interface, check_interfaces,
                                        interface_transformation, make_interfaces, project)
from pipeline.solve.factorization import factorize

log = logging.getLogger(__name__)

__all__ = ["CraigBamptonModel", "craig_bampton", "build_craig_bampton", "coordinate_labels"]

COORD_UNITS = {"x": "m", "y": "m", "z": "m", "rx": "rad", "ry": "rad", "rz": "rad"}
MODAL_UNITS = "m kg^1/2"


@dataclass(frozen=True)
class CraigBamptonModel:
    """Reduced model in the coordinates [q_1; ...; q_k; eta].

    interfaces: in coordinate order. M, K: (n_b + N) square, symmetric.
    coordinate_names / coordinate_units: one per reduced coordinate.
    shapes: (n_dofs, n_b + N) the basis on every DOF of the body (constraint modes, then
    fixed-interface modes). fixed_interface_omega2: (N,) rad^2/s^2.
    residuals: eigen-residuals of the fixed-interface solve.
    """

    interfaces: tuple[Interface, ...]
    M: np.ndarray
    K: np.ndarray
    coordinate_names: tuple[str, ...]
    coordinate_units: tuple[str, ...]
    shapes: np.ndarray
    fixed_interface_omega2: np.ndarray
    residuals: np.ndarray

    @property
    def n_boundary(self) -> int:
        return 6 * len(self.interfaces)

    @property
    def n_modes(self) -> int:
        return int(self.fixed_interface_omega2.size)

    @property
    def fixed_interface_frequencies_hz(self) -> np.ndarray:
        return np.sqrt(np.maximum(self.fixed_interface_omega2, 0.0)) / (2 * np.pi)

    def interface_columns(self, name: str) -> slice:
        for k, iface in enumerate(self.interfaces):
            if iface.name == name:
                return slice(6 * k, 6 * k + 6)
        raise RegionError(f"craig_bampton: no interface named '{name}'; expected one of "
                          f"{', '.join(i.name for i in self.interfaces)}")

    def constrained(self, fixed: Sequence[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(K, M, kept column indices) with the interfaces named in ``fixed`` clamped."""
        drop = set()
        for name in fixed:
            sl = self.interface_columns(name)
            drop.update(range(sl.start, sl.stop))
        keep = np.array([i for i in range(self.K.shape[0]) if i not in drop], dtype=np.int64)
        return self.K[np.ix_(keep, keep)], self.M[np.ix_(keep, keep)], keep

    def eigen(self, fixed: Sequence[str] = ()) -> tuple[np.ndarray, np.ndarray]:
        """(omega2 ascending, vectors) of the reduced model with ``fixed`` interfaces
        clamped (default: none, the free body). Round-off rigid-body eigenvalues (below
        1e-9 of the largest) are set to 0."""
        K, M, _ = self.constrained(fixed)
        w, v = sla.eigh(K, M)
        w = np.where(np.abs(w) < 1e-9 * np.abs(w).max(), 0.0, w)
        return w, v

    def frequencies_hz(self, fixed: Sequence[str] = ()) -> np.ndarray:
        w, _ = self.eigen(fixed)
        return np.sqrt(np.maximum(w, 0.0)) / (2 * np.pi)


def craig_bampton(space, K_full: sp.spmatrix, M_full: sp.spmatrix,
                  interfaces: Sequence[Interface], n_modes: int | None, backend: str = "auto",
                  tolerance: float = 0.0) -> CraigBamptonModel:
    """Craig-Bampton reduction with ``interfaces`` and ``n_modes`` fixed-interface modes.

    ``space``: the FESpace (or the node coordinates (n_nodes, 3)). ``K_full``, ``M_full``:
    (n_dofs x n_dofs) matrices of the UNSUPPORTED body (before support condensation).
    ``interfaces``: from :func:`pipeline.reduce.interfaces.make_interfaces` (at least one).
    ``backend``: auto | pardiso | superlu (shift-invert eigsh), or ``dense`` for small
    models (``n_modes=None`` then keeps every fixed-interface mode).
    """
    interfaces = tuple(interfaces)
    if not interfaces:
        raise RegionError("craig_bampton: expected at least one interface (connections)")
    check_interfaces(interfaces, "craig_bampton interfaces")
    node_points = space.node_points if hasattr(space, "node_points") else np.asarray(space)
    n_dofs = 3 * node_points.shape[0]
    tr = interface_transformation(n_dofs, node_points, interfaces)
    nz, nb = tr.n_z, 6 * len(interfaces)
    Kt = project(K_full, tr.T)
    Mt = project(M_full, tr.T)
    Kzz, Mzz = Kt[:nz, :nz].tocsr(), Mt[:nz, :nz].tocsr()
    omega2, Phi, residuals = connection.clamped_modes(Kzz, Mzz, n_modes, backend, tolerance)
    n_modes = omega2.size
    fact = factorize(Kzz, "superlu" if backend == "dense" else backend, positive_definite=True)
    try:
        # Fortran order: the PARDISO backend reads a multi-column right-hand side by columns
        X = -np.asarray(fact.solve(np.asfortranarray(Kt[:nz, nz:].toarray())))
    finally:
        fact.release()
    X = X.reshape(nz, nb)
    B = np.zeros((nz + nb, nb + n_modes))
    B[:nz, :nb] = X
    B[nz:, :nb] = np.eye(nb)
    B[:nz, nb:] = Phi
    Kr = B.T @ (Kt @ B)
    Mr = B.T @ (Mt @ B)
    Kr, Mr = 0.5 * (Kr + Kr.T), 0.5 * (Mr + Mr.T)
    shapes = np.asarray(tr.T @ B)
    names, units = coordinate_labels(interfaces, n_modes)
    log.info("Craig-Bampton: %d interface(s), %d boundary + %d modal coordinates",
             len(interfaces), nb, n_modes)
    return CraigBamptonModel(interfaces, Mr, Kr, names, units, shapes, omega2, residuals)


def coordinate_labels(interfaces: Sequence[Interface], n_modes: int
                      ) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(names, units) of the reduced coordinates [q_1; ...; q_k; eta_1 .. eta_N]."""
    names, units = [], []
    for iface in interfaces:
        names += [f"{iface.name}.{d}" for d in DIRECTIONS]
        units += [COORD_UNITS[d] for d in DIRECTIONS]
    names += [f"mode_{i + 1}" for i in range(n_modes)]
    units += [MODAL_UNITS] * n_modes
    return tuple(names), tuple(units)


def build_craig_bampton(space, regions, K_full: sp.spmatrix, M_full: sp.spmatrix,
                        connections, n_modes: int, backend: str = "auto") -> CraigBamptonModel:
    """Everything for ``/craig_bampton``, in one call: one interface per record of
    ``connections`` (name, region, point, coupling), checked before any solve;
    ``n_modes`` fixed-interface modes; matrices of the unsupported body."""
    interfaces = make_interfaces(space, regions, connections)
    cb = craig_bampton(space, K_full, M_full, interfaces, n_modes, backend=backend)
    return cb
