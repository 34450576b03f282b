"""The ``rotation`` config section: a body spinning about a fixed axis.

```yaml
rotation: {axis: [0, 0, 1], point: [0, 0.01, 0.025], speeds_rad_s: [0, 50, 100, 150, 200],
           static_shape: false, correction_shapes: 0}
```

``axis``: the spin axis (any non-zero length; normalised); ``point`` (m): a point on
it; ``speeds_rad_s`` (rad/s): the speeds of the prestressed modal analysis, strictly
ascending, at most :data:`MAX_SPEEDS`; a negative speed is allowed (only Omega^2
enters the stiffness: it gives the frequencies of the same positive speed);
``static_shape``: add the static shape under the centrifugal load to the reduced
basis; ``correction_shapes``: add the first-order shape corrections
K^-1 (K_G1 - M_perp) phi_k of that many of the first modes (see
:mod:`pipeline.reduce.rotation`: these, not the static shape, are what keeps the reduced
frequencies of a spinning beam within 1e-4 of the full FE's at high speeds). The physics is in
:mod:`pipeline.fe.prestress`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline._util import validate as v

log = logging.getLogger(__name__)

#: the most speeds one run solves (each is a factorisation and an eigensolve)
MAX_SPEEDS = 200
#: the largest speed accepted, rad/s (a body at 1e6 rad/s has left linear elasticity)
MAX_SPEED = 1e6

#: the six entries (i, j), i <= j, of the angular-velocity tensor W = omega omega^T,
#: in the order of every stored (6, ...) array
TENSOR_ENTRIES: tuple[tuple[int, int], ...] = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))
#: their names (x, y, z components of omega)
TENSOR_NAMES: tuple[str, ...] = ("xx", "yy", "zz", "xy", "xz", "yz")


def entry_matrix(i: int, j: int) -> np.ndarray:
    """A_ij (3 x 3): the centrifugal force density per unit rho W_ij and unit distance
    (A_ii = I - e_i e_i^T; A_ij = -(e_i e_j^T + e_j e_i^T) for i != j)."""
    A = np.zeros((3, 3))
    if i == j:
        A[:] = np.eye(3)
        A[i, i] = 0.0
    else:
        A[i, j] = A[j, i] = -1.0
    return A


def tensor_weights(omega: np.ndarray) -> np.ndarray:
    """(6,) the entries W_ij = omega_i omega_j (i <= j, :data:`TENSOR_ENTRIES`) of the
    angular-velocity tensor of ``omega`` (3,) (rad/s, or a unit axis for the weights per
    unit Omega^2)."""
    omega = np.asarray(omega, dtype=float)
    return np.array([omega[i] * omega[j] for i, j in TENSOR_ENTRIES])


@dataclass(frozen=True)
class Rotation:
    """A spin about ``axis`` (3,) through ``point`` (3,) m at each of ``speeds_rad_s``
    (rad/s, strictly ascending); ``static_shape``: augment the reduced basis with the
    centrifugal static shape; ``correction_shapes``: add K^-1 (K_G1 - M_perp) phi_k for
    that many of the first modes."""

    axis: tuple[float, float, float]
    point: tuple[float, float, float]
    speeds_rad_s: tuple[float, ...]
    static_shape: bool = False
    correction_shapes: int = 0


def parse_rotation(raw: Any) -> Rotation | None:
    """The validated ``rotation`` section, or None when absent."""
    if raw is None:
        return None
    raw = v.mapping(raw, "rotation", ("axis", "point", "speeds_rad_s", "static_shape",
                                       "correction_shapes"),
                    ("axis", "point", "speeds_rad_s"))
    axis = v.vector(raw, "axis", "rotation", nonzero=True)
    point = v.vector(raw, "point", "rotation")
    speeds = raw["speeds_rad_s"]
    if not isinstance(speeds, list) or not speeds or len(speeds) > MAX_SPEEDS:
        raise v.fail("rotation.speeds_rad_s", speeds,
                     f"a list of 1 to {MAX_SPEEDS} speeds in rad/s")
    values = [v.number({f"speeds_rad_s[{n}]": s}, f"speeds_rad_s[{n}]", "rotation",
                       lo=-MAX_SPEED, hi=MAX_SPEED) for n, s in enumerate(speeds)]
    for n, (a, b) in enumerate(zip(values, values[1:])):
        if b <= a:
            raise v.fail(f"rotation.speeds_rad_s[{n + 1}]", speeds[n + 1],
                         f"a speed above the one before it ({a:g} rad/s): the speeds are "
                         "strictly ascending")
    if any(s < 0 for s in values):
        log.info("rotation.speeds_rad_s: negative speeds are allowed (the sign does not "
                 "matter: only Omega^2 enters the stiffness)")
    return Rotation(axis=axis, point=point, speeds_rad_s=tuple(values),
                    static_shape=v.boolean(raw, "static_shape", "rotation", False),
                    correction_shapes=v.integer(raw, "correction_shapes", "rotation", 0,
                                                lo=0, hi=500))
