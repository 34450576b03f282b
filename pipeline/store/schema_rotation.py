"""The writer of the ``/rotation`` group (docs/hdf5-format.md, "/rotation"): the
prestressed frequencies of a spinning body and the reduced terms of geometric
stiffening (:class:`pipeline.reduce.rotation.RotationModel`)."""

from __future__ import annotations

from typing import Any

import numpy as np

from pipeline.fe.prestress import TENSOR_NAMES
from pipeline.reduce.rotation import RotationModel
from pipeline.store.layout import ROTATION
from pipeline.store.tree import Dataset


def rotation_tree(model: RotationModel) -> tuple[dict[str, Dataset], dict[str, dict[str, Any]]]:
    """(datasets, group attributes) of the ``/rotation`` group for ``model``."""
    R = ROTATION
    n_b = model.stiffness.shape[0]
    tree = {
        R.axis: Dataset(model.axis, "1", "unit vector of the spin axis (body frame)"),
        R.point: Dataset(model.point, "m", "a point on the spin axis; the centrifugal load "
                         "acts on x - point"),
        R.speeds_rad_s: Dataset(model.speeds_rad_s, "rad/s", "spin speeds Omega (the sign "
                                "does not matter: only Omega^2 enters)"),
        R.frequencies_hz: Dataset(model.frequencies_hz, "Hz", "full FE prestressed "
                                  "frequencies (n_speeds, n_modes), ascending per speed: "
                                  "(K + Omega^2 (K_G1 - M_perp)) phi = w^2 M phi"),
        R.frequencies_reduced_hz: Dataset(model.frequencies_reduced_hz, "Hz", "the reduced "
                                          "model's (n_speeds, n_basis), ascending per speed"),
        R.tensor_entries: Dataset(list(TENSOR_NAMES), "", "the entries W_ij = omega_i "
                                  "omega_j of the first axis of geometric_stiffness and "
                                  "spin_softening"),
        R.basis_stiffness: Dataset(model.stiffness, "N/m", "V^T K V (n_basis, n_basis); "
                                   "diag(omega^2) for the modes alone (rad^2/s^2 per kg)"),
        R.basis_mass: Dataset(model.mass, "kg", "V^T M V (n_basis, n_basis); I for the "
                              "modes alone"),
        R.geometric_stiffness: Dataset(model.geometric, "N/m per rad^2/s^2", "V^T K_G,ij V "
                                       "(6, n_basis, n_basis): geometric stiffness of the "
                                       "centrifugal stress per unit W_ij"),
        R.spin_softening: Dataset(model.softening, "kg", "V^T (m (x) A_ij) V (6, n_basis, "
                                  "n_basis): spin-softening mass per unit W_ij"),
    }
    if model.input_names:
        tree[R.preload_stiffness] = Dataset(model.preload, "N/m per input unit",
                                            "V^T K_G(sigma(F_k)) V (n_inputs, n_basis, "
                                            "n_basis) per unit value of input port k")
        tree[R.input_names] = Dataset(list(model.input_names), "", "the input ports of "
                                      "preload_stiffness")
    if model.centrifugal_load is not None:
        tree[R.centrifugal_load] = Dataset(model.centrifugal_load, "N per rad^2/s^2",
                                           "V^T f_ij (6, n_basis): the centrifugal load of "
                                           "the undeformed body per unit W_ij")
        tree[R.euler_load] = Dataset(model.euler_load, "kg m", "E_k = V^T M (e_k x (x - "
                                     "point)) (3, n_basis): the load of an angular "
                                     "acceleration alpha is -sum_k alpha_k E_k")
        tree[R.coriolis] = Dataset(model.coriolis, "kg", "C_k = V^T M [e_k x] V (3, "
                                   "n_basis, n_basis), skew: Coriolis force -2 sum_k "
                                   "omega_k C_k q'")
    attrs = {R.path: {R.attr.n_modes: np.int64(model.n_modes), R.attr.n_basis: np.int64(n_b),
                      R.attr.static_shape: np.bool_(model.static_shape),
                      R.attr.correction_shapes: np.int64(n_b - model.n_modes
                                                         - int(model.static_shape))}}
    return tree, attrs
