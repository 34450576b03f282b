"""The reduced model of a spinning, preloaded body: its terms and its frequencies.

Pure numpy on the stored terms (no FE code): what :mod:`pipeline.reduce.rotation`
builds, what the ``/rotation`` group of the file holds and what
:func:`pipeline.store.read.read_rotation` returns. With the basis V (n_s x n_b) and the
terms of :class:`RotationModel`, the stiffness at the angular velocity omega (rad/s,
body frame) and the input preloads lambda_k is

    K_r(omega, lambda) = K_r + sum_{i<=j} omega_i omega_j (G_ij - S_ij) + sum_k lambda_k P_k,

and the frequencies solve K_r(omega, lambda) q = w^2 M_r q (Coriolis coupling left out).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.config.rotation import tensor_weights
from pipeline.errors import SolverError


def unit(axis) -> np.ndarray:
    """``axis`` (3,) scaled to unit length (a zero axis is refused by the config)."""
    axis = np.asarray(axis, dtype=float)
    return axis / np.linalg.norm(axis)


@dataclass(frozen=True)
class RotationModel:
    """The rotating body's results (the ``/rotation`` group of the file).

    axis (3,), point (3,) m: the spin axis of the config (axis of unit length).
    speeds_rad_s: (n_speeds,) rad/s.
    frequencies_hz: (n_speeds, n_m) full FE prestressed frequencies, ascending per speed.
    frequencies_reduced_hz: (n_speeds, n_b) the reduced model's, ascending per speed.
    stiffness, mass: (n_b, n_b) K_r (N/m) and M_r (kg) of the basis.
    geometric, softening: (6, n_b, n_b) G_ij (N/m per rad^2/s^2) and S_ij (kg), in
    :data:`~pipeline.config.rotation.TENSOR_ENTRIES` order.
    preload: (n_in, n_b, n_b) P_k (N/m per unit input); input_names: (n_in,).
    n_modes: the number of modes at the head of the basis (the rest: the centrifugal
    static shape when ``static_shape``, then the correction shapes).
    centrifugal_load: (6, n_b) V^T f_ij, the centrifugal load of the undeformed body per
    unit W_ij; euler_load: (3, n_b) E_k = V^T M (e_k x (x - point)) (kg m); coriolis:
    (3, n_b, n_b) C_k = V^T M [e_k x] V (kg, skew). The body-frame equations of a
    prescribed rotation (omega, alpha = omega') are then

        M_r q'' + 2 sum_k omega_k C_k q' + (K_r(omega) + sum_k alpha_k C_k) q
            = sum_ij W_ij f_ij - sum_k alpha_k E_k

    (None in files written before these terms were stored).
    """

    axis: np.ndarray
    point: np.ndarray
    speeds_rad_s: np.ndarray
    frequencies_hz: np.ndarray
    frequencies_reduced_hz: np.ndarray
    stiffness: np.ndarray
    mass: np.ndarray
    geometric: np.ndarray
    softening: np.ndarray
    preload: np.ndarray
    input_names: tuple[str, ...]
    n_modes: int
    static_shape: bool
    centrifugal_load: np.ndarray | None = None
    euler_load: np.ndarray | None = None
    coriolis: np.ndarray | None = None

    def stiffness_at(self, omega, preload=None) -> np.ndarray:
        """K_r(omega, lambda) (n_b, n_b) N/m at the angular velocity ``omega`` (3,) rad/s
        and the input ``preload`` values (n_in,) (None: none)."""
        K = self.stiffness + np.tensordot(tensor_weights(omega),
                                          self.geometric - self.softening, axes=1)
        if preload is not None and len(self.input_names):
            K = K + np.tensordot(np.asarray(preload, float), self.preload, axes=1)
        return K


def reduced_frequencies(model: RotationModel, speeds_rad_s=None, axis=None,
                        preload=None) -> np.ndarray:
    """(n_speeds, n_b) Hz, ascending per speed: the reduced model's frequencies at each
    spin (``speeds_rad_s`` (n_speeds,) rad/s about ``axis``; defaults: the model's),
    with the input ``preload`` values (n_in,) (None: none). A speed where the reduced
    stiffness is not positive definite raises SolverError naming it."""
    import scipy.linalg as sla  # here: the file readers import this module (0.3 s)

    speeds = model.speeds_rad_s if speeds_rad_s is None else np.asarray(speeds_rad_s, float)
    axis = unit(model.axis if axis is None else axis)
    out = np.empty((speeds.size, model.stiffness.shape[0]))
    for n, speed in enumerate(speeds):
        Ks = model.stiffness_at(speed * axis, preload)
        w2 = sla.eigh(0.5 * (Ks + Ks.T), 0.5 * (model.mass + model.mass.T), eigvals_only=True)
        if w2[0] <= 0.0:
            raise unstable(speed, "the reduced model")
        out[n] = np.sqrt(w2) / (2 * np.pi)
    return out


def unstable(speed: float, where: str) -> SolverError:
    """The one-line error for a speed at which the prestressed stiffness is indefinite."""
    return SolverError(
        f"config key 'rotation.speeds_rad_s': at {speed:g} rad/s the prestressed stiffness "
        f"K + Omega^2 (K_G - M_perp) of {where} is not positive definite (a spin-softening "
        "instability or buckling under the centrifugal stress); expected speeds below it",
        key="rotation.speeds_rad_s", value=float(speed))


