"""Export for Simscape Multibody's Reduced Order Flexible Solid block (Craig-Bampton form).

``python -m pipeline export FILE.h5 --to simscape`` writes ``<stem>_simscape.mat`` and,
beside it, the script ``<stem>_simscape.m`` (MATLAB or GNU Octave) that loads it, makes the
checks the block makes and leaves the block's parameters in the workspace:

=====================  ===================================================================
variable               content (SI units: m, kg, s, rad)
=====================  ===================================================================
origins                (k, 3) m: origin of each interface frame (one per Craig-Bampton
                       interface, in coordinate order); frames aligned with the body's axes
K, M                   (6 k + N, 6 k + N) symmetric stiffness (PSD: six rigid-body zeros)
                       and mass (PD) in Craig-Bampton form: Tx Ty Tz Rx Ry Rz of each
                       interface frame first (m, rad), then the N fixed-interface modal
                       DOFs (m kg^1/2, M block = I, K block = diag omega^2)
C                      (6 k + N)^2 damping matrix: the file's damping applied to the free
                       modes of (K, M) -- uniform or per-mode ratios: C = M Phi diag(2 zeta_i
                       omega_i) Phi^T M over the elastic modes (Phi M-orthonormal, rigid
                       modes undamped); Rayleigh: C = alpha M + beta K
damping_ratio          the uniform modal damping ratio (block's "Uniform modal" damping),
                       NaN for another damping kind
interface_names        cell (k, 1); coordinate_names, coordinate_units cell (6 k + N, 1)
n_modes                N; fixed_interface_frequencies_hz (N, 1), free_frequencies_hz
                       (6 k + N, 1): what eig(K_mm, M_mm) and eig(K, M) give
=====================  ===================================================================

Block dialog (Simscape Multibody > Body Elements > Reduced Order Flexible Solid):
Origins = ``origins``, Stiffness Matrix = ``K``, Mass Matrix = ``M``, Damping = Custom with
``C`` (or Uniform Modal with ``damping_ratio``). K and M are symmetrised exactly,
(K + K^T) / 2, before writing.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Any

import numpy as np
import scipy.linalg as sla

from pipeline._util.atomic import atomic_path, write_text
from pipeline.apps.exports.mat import cell_array
from pipeline.errors import FileFormatError
from pipeline.store.layout import CRAIG_BAMPTON
from pipeline.store.read import load_model

log = logging.getLogger(__name__)

__all__ = ["export", "simscape_variables", "damping_matrix", "script_path"]

#: an eigenvalue of (K, M) below this fraction of the largest is a rigid-body mode
RIGID_RTOL = 1e-9


def _config_damping(config_yaml: str) -> dict[str, Any]:
    """The ``damping`` section of the stored config ``config_yaml`` (empty when none)."""
    import yaml

    try:
        cfg = yaml.safe_load(config_yaml) or {}
    except yaml.YAMLError:
        return {}
    damping = cfg.get("damping") if isinstance(cfg, dict) else None
    return damping if isinstance(damping, dict) else {}


def damping_matrix(K: np.ndarray, M: np.ndarray, damping: dict[str, Any]
                   ) -> tuple[np.ndarray, float]:
    """(C, uniform ratio or NaN) for the config's ``damping`` section (see the module
    docstring); no section: C = 0."""
    kind = str(damping.get("kind", "uniform")) if damping else "none"
    if kind == "rayleigh":
        return float(damping.get("alpha", 0.0)) * M + float(damping.get("beta", 0.0)) * K, np.nan
    w2, phi = sla.eigh(K, M)
    elastic = w2 > RIGID_RTOL * np.abs(w2).max()
    omega = np.sqrt(w2[elastic])
    if kind == "uniform":
        ratio = float(damping.get("ratio", 0.0))
        zeta = np.full(omega.size, ratio)
    elif kind == "per_mode":
        ratios = [float(r) for r in damping.get("ratios") or [0.0]]
        zeta = np.array([ratios[min(i, len(ratios) - 1)] for i in range(omega.size)])
        ratio = np.nan
    else:
        zeta, ratio = np.zeros(omega.size), np.nan
    Mphi = M @ phi[:, elastic]
    C = Mphi @ np.diag(2.0 * zeta * omega) @ Mphi.T
    return 0.5 * (C + C.T), ratio


def simscape_variables(h5_path: str | Path) -> dict[str, Any]:
    """The variables :func:`export` writes (see the module docstring)."""
    h5_path = Path(h5_path)
    try:
        lm = load_model(h5_path)
    except FileFormatError as exc:
        if exc.value != "no /statespace":
            raise
        lm = None  # modes only
    cb = None if lm is None else lm.craig_bampton
    if cb is None:
        raise FileFormatError(f"file '{h5_path}': has no Craig-Bampton model (/craig_bampton); "
                              "the Simscape export needs one: add a 'craig_bampton' section "
                              "(and 'connections', its interfaces) to the config",
                              key=CRAIG_BAMPTON.path, value="absent",
                              expected="a run with craig_bampton and connections")
    k = len(cb.interface_names)
    n = cb.M.shape[0]
    n_modes = n - 6 * k
    if n_modes < 0 or [c.split(".")[-1] for c in cb.coordinate_names[:6 * k]] != \
            ["x", "y", "z", "rx", "ry", "rz"] * k:
        raise FileFormatError(f"file '{h5_path}': {CRAIG_BAMPTON.coordinate_names} do not "
                              "start with x y z rx ry rz of every interface",
                              key=CRAIG_BAMPTON.coordinate_names,
                              value=list(cb.coordinate_names[:6]), expected="x y z rx ry rz")
    K = 0.5 * (cb.K + cb.K.T)
    M = 0.5 * (cb.M + cb.M.T)
    origins = cb.interface_points.reshape(k, 3)
    free, name = cb.free_frequencies_hz, lm.name
    C, ratio = damping_matrix(K, M, _config_damping(lm.config_yaml))
    return {
        "origins": origins, "K": K, "M": M, "C": C, "damping_ratio": ratio,
        "interface_names": cell_array(cb.interface_names),
        "coordinate_names": cell_array(cb.coordinate_names),
        "coordinate_units": cell_array(cb.coordinate_units),
        "n_modes": float(n_modes),
        "fixed_interface_frequencies_hz": cb.fixed_interface_frequencies_hz.reshape(-1, 1),
        "free_frequencies_hz": free.reshape(-1, 1),
        "model_name": name, "source_file": str(h5_path),
        "description": ("Reduced Order Flexible Solid parameters (Craig-Bampton, SI units): "
                        "DOFs Tx Ty Tz Rx Ry Rz per interface frame (rows of origins), then "
                        "the modal DOFs. Exported by fe-reduced-body."),
    }


def script_path(mat_path: str | Path) -> Path:
    """The ``.m`` script beside ``mat_path`` (its stem made a MATLAB identifier)."""
    mat_path = Path(mat_path)
    stem = re.sub(r"[^A-Za-z0-9_]", "_", mat_path.stem)
    return mat_path.with_name((stem if stem[:1].isalpha() else "m_" + stem) + ".m")


SCRIPT = """\
% {script}: parameters of Simscape Multibody's Reduced Order Flexible Solid block
% from {source} (exported by fe-reduced-body; SI units). Run it before the model:
% it loads {mat} from this folder, checks what the block checks, and leaves
%   rofs_origins (k x 3, m)   -> Origins (frames: {frames})
%   rofs_K, rofs_M            -> Stiffness Matrix, Mass Matrix (Tx Ty Tz Rx Ry Rz per frame, then modes)
%   rofs_C                    -> Damping: Custom (or rofs_damping_ratio -> Uniform Modal)
here = fileparts(mfilename('fullpath'));
S = load(fullfile(here, '{mat}'));
rofs_origins = S.origins; rofs_K = S.K; rofs_M = S.M; rofs_C = S.C;
rofs_damping_ratio = S.damping_ratio; rofs_frames = S.interface_names;
n = 6 * size(rofs_origins, 1) + S.n_modes;
assert(isequal(size(rofs_K), [n n]) && isequal(size(rofs_M), [n n]) && isequal(size(rofs_C), [n n]), ...
       'K, M, C must be %d x %d', n, n);
assert(isequal(rofs_K, rofs_K.') && isequal(rofs_M, rofs_M.') && isequal(rofs_C, rofs_C.'), ...
       'K, M, C must be symmetric');
[~, p] = chol(rofs_M);
assert(p == 0, 'M must be positive definite');
ev = eig(rofs_K);
assert(min(ev) >= -1e-9 * max(abs(ev)), 'K must be positive semidefinite');
fprintf('%s: %d interface frames, %d modal DOFs: Reduced Order Flexible Solid parameters ready\\n', ...
        '{name}', size(rofs_origins, 1), S.n_modes);
"""


def export(h5_path: str | Path, out_path: str | Path) -> Path:
    """Write ``out_path`` (.mat, MATLAB v5) and its ``.m`` script; returns the .mat path."""
    from scipy.io import savemat

    out_path = Path(out_path)
    variables = simscape_variables(h5_path)
    script = script_path(out_path)
    with atomic_path(out_path) as tmp, open(tmp, "wb") as fh:
        savemat(fh, variables, format="5", do_compression=True, oned_as="column")
    frames = ", ".join(str(c[0]) for c in variables["interface_names"])
    write_text(script, SCRIPT.format(script=script.name, source=Path(h5_path).name,
                                     mat=out_path.name, frames=frames,
                                     name=variables["model_name"].replace("'", "")))
    log.info("wrote %s and %s (%d interface frames, %d modes)", out_path, script,
             variables["origins"].shape[0], int(variables["n_modes"]))
    return out_path
