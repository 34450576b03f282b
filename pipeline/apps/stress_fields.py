"""Von Mises stress fields, without matplotlib: shared by the stress pictures
(:mod:`pipeline.apps.stress_plots`), a simulation's stress recovery
(:mod:`pipeline.apps.simulate.stress`) and the ParaView export
(:mod:`pipeline.apps.exports.stress_arrays`).

The static field per unit input j is rebuilt from the file's ``stress_modes`` group
(docs/stress.md): sigma = sum_k S_k eta_k + R_j with eta = -(A^-1 B)[:n_b, j] the static
modal coordinates of the plant (eta = Omega^-2 Sigma e_j) and R_j the residual shape of
input j.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.store.read import load_model, read_stress_modes

__all__ = ["von_mises", "static_von_mises"]


def von_mises(s: np.ndarray) -> np.ndarray:
    """Von Mises stress (Pa) of Voigt stresses ``s`` (..., 6) -> (...)."""
    xx, yy, zz, yz, xz, xy = (s[..., k] for k in range(6))
    return np.sqrt(0.5 * ((xx - yy) ** 2 + (yy - zz) ** 2 + (zz - xx) ** 2)
                   + 3.0 * (yz ** 2 + xz ** 2 + xy ** 2))


def static_von_mises(path: str | Path) -> dict[str, np.ndarray]:
    """input name -> (n_points,) von Mises stress (Pa per unit input) of the static response;
    empty for a file without stress modes."""
    sm = read_stress_modes(path)
    if sm is None:
        return {}
    mats = load_model(path).matrices
    Z = -np.linalg.solve(mats["A"], mats["B"])  # (n_x, n_u) static states per unit input
    out = {}
    for j, name in enumerate(sm.input_names):
        q = np.zeros(sm.stress.shape[2])
        q[:sm.n_basis] = Z[:sm.n_basis, j]
        if sm.n_correction:
            q[sm.n_basis + j] = 1.0
        out[name] = von_mises(np.einsum("pks,s->pk", sm.stress, q))
    return out
