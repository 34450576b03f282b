"""Physics of a result file: what the checksum cannot vouch for.

Anyone can recompute a checksum (:func:`pipeline.store.h5file.sign`), so a file that
passes it may still hold numbers no run of this pipeline writes. :func:`check_physics`
runs on every verified open (:func:`pipeline.store.read.open_verified`), so every
consumer (inspect, plot, every export, simulate) refuses such a file with one
:class:`~pipeline.errors.FileFormatError` line (exit code 7):

- **mesh indices**: every cell's node index in ``0 .. n_points - 1``, every region
  triangle's too, every fixed DOF in ``0 .. 3 n_points - 1`` (a cell past the node table
  would read another array's memory or crash a viewer);
- **shapes between datasets**: ``modes/shapes`` is ``(n_points, 3, n_modes)`` with one
  frequency, omega^2, label and residual per mode; ``/fe``'s matrices are
  ``3 n_points`` square;
- **signs**: masses (``mass``, ``element_mass``, ``effective_mass``, ``modal_mass``),
  frequencies, omega and omega^2, damping ratios >= 0 (scalars and vectors of those names) (the writer clips rigid modes'
  omega^2 to 0; NaN, where the layout gives it a meaning, is left to the readers);
- **symmetric positive semi-definite matrices** (inertia tensors, mass, stiffness and
  damping matrices, Craig-Bampton M and K): ``|S - S^T| <= tol max|S|`` and
  ``lambda_min >= -tol lambda_max`` with ``tol = 1e-8``. A product such as Phi^T K Phi
  over n DOFs is exact to ``n eps ||K||`` (Higham's gamma_n); at n <= 10^7 DOFs that is
  2e-9 of the largest entry, so 1e-8 passes every honest file and refuses an edit. The
  sparse ``/fe`` M and K: symmetric to the same tolerance, and a PSD matrix has
  ``M_ii > 0`` (M is positive definite), ``K_ii >= 0``;
- **stability**: a passive body's model has no growing motion. Every state-space A
  (plant, filtered, lumped chain, connection points) must have ``Re(lambda) <= tol_A``
  for all eigenvalues, with ``tol_A = 10 max(delta, sqrt(delta))``,
  ``delta = n eps ||A||_1``: LAPACK's eigenvalues of a simple eigenvalue move by about
  ``delta`` (backward stable), those of a rigid mode's 2x2 Jordan block ``[[0, 1],
  [0, 0]]`` (undamped, 0 rad/s) by ``sqrt(delta)`` (the square root of a perturbation of
  its lower-left entry, in 1/s^2, next to the unit position-velocity coupling). The
  factor 10 is margin: the cantilever's plant has ``max Re = -8.26 1/s`` against
  ``tol_A = 3e-3 1/s``, a free body's ``+1.7e-10`` against ``5e-3``.

A simulation result file (``content = "simulation results"``) holds no model: nothing is
checked. A file that passed is remembered by its content checksum, so a command that
opens one file several times checks it once.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.errors import FileFormatError
from pipeline.store import layout as L

#: relative tolerance of symmetry and semi-definiteness (see the module docstring)
SYMMETRY_TOL = 1e-8
#: margin on the eigenvalue perturbation of a stable A (see the module docstring)
STABILITY_MARGIN = 10.0
#: largest A whose eigenvalues are computed (dense O(n^3): 2.6 s at 1000 states on one
#: core); the pipeline writes at most 1000 (reduction.modes <= 500) plus filter states
MAX_STABILITY_STATES = 1200

#: dataset names (the last path component) that hold non-negative numbers
NON_NEGATIVE = ("mass", "element_mass", "effective_mass", "modal_mass", "frequencies_hz",
                "fixed_interface_frequencies_hz", "free_frequencies_hz", "omega", "omega2",
                "damping_ratios", "damping_ratio", "modal_damping_ratios")
#: dataset names that hold symmetric positive semi-definite matrices (the last two axes)
SEMI_DEFINITE = ("inertia", "inertia_G", "inertia_P", "element_inertia", "rigid_mass_matrix",
                 "mass_matrix", "stiffness", "damping", "M", "K", "modal_mass",
                 "modal_stiffness")

_passed: set[str] = set()


def check_physics(h5, path: str | Path, remember: bool = True) -> None:
    """Refuse (FileFormatError naming ``path`` and the dataset) an open model file whose
    content no run writes: see the module docstring for every check. ``remember``: the
    file's checksum was verified, so a pass is remembered by it."""
    content = _text(h5.attrs.get(L.ROOT.content, ""))
    if content == L.SIMULATION_CONTENT:
        return
    digest = _text(h5.attrs.get(L.ROOT.content_sha256, "")) if remember else ""
    if digest and digest in _passed:
        return
    names: list[str] = []
    h5.visit(lambda name: names.append(name) if hasattr(h5[name], "dtype") else None)
    n_points = _check_mesh(h5, path)
    _check_modes(h5, path, n_points)
    for name in sorted(names):
        leaf = name.rsplit("/", 1)[-1]
        dset = h5[name]
        if dset.dtype.kind not in "fiu":
            continue
        if leaf in NON_NEGATIVE and dset.ndim <= 1:  # a matrix of that name: semi-definite
            _non_negative(path, name, np.asarray(dset[()], dtype=float))
        if leaf in SEMI_DEFINITE and dset.ndim >= 2 and dset.shape[-1] == dset.shape[-2]:
            _semi_definite(path, name, np.asarray(dset[()], dtype=float))
        if leaf == "A" and dset.ndim == 2 and dset.shape[0] == dset.shape[1]:
            _stable(path, name, np.asarray(dset[()], dtype=float))
    if L.FE.path in h5:
        _check_fe(h5, path, n_points)
    if digest:
        _passed.add(digest)


def _text(value) -> str:
    return value.decode("utf-8", "replace") if isinstance(value, bytes) else str(value)


def _refuse(path, key: str, what: str, expected: str) -> FileFormatError:
    return FileFormatError(f"file '{path}': {key} {what}, expected {expected}; the file was "
                           "edited after the run (its checksum was recomputed)", key=key,
                           value=what, expected=expected)


def _check_mesh(h5, path) -> int | None:
    """Node indices of cells, region triangles and fixed DOFs inside the node table;
    returns the number of points (None without a mesh)."""
    if L.MESH.points not in h5:
        return None
    points = h5[L.MESH.points]
    n = int(points.shape[0]) if points.ndim == 2 else 0
    groups = [(L.MESH.cells, n), (L.MESH.regions, n)]
    for group, bound in groups:
        if group not in h5 or not hasattr(h5[group], "keys"):
            continue
        for key in h5[group]:
            _indices(h5, path, f"{group}/{key}", bound, "nodes")
    if L.MESH.fixed_dofs in h5:
        _indices(h5, path, L.MESH.fixed_dofs, 3 * n, "DOFs")
    return n


def _indices(h5, path, key: str, bound: int, what: str) -> None:
    dset = h5[key]
    if dset.dtype.kind not in "iu" or dset.size == 0:
        return  # the readers name a wrong dtype
    a = np.asarray(dset[()])
    lo, hi = int(a.min()), int(a.max())
    if lo < 0 or hi >= bound:
        raise _refuse(path, key, f"refers to {what} {lo}..{hi}",
                      f"{what} inside 0..{bound - 1} (the size of {L.MESH.points}"
                      + (" x 3" if what == "DOFs" else "") + ")")


def _check_modes(h5, path, n_points: int | None) -> None:
    """modes/shapes (n_points, 3, n_modes) with one value per mode in every vector."""
    if L.MODES.shapes not in h5:
        return
    shape = h5[L.MODES.shapes].shape
    if len(shape) != 3 or shape[1] != 3 or (n_points is not None and shape[0] != n_points):
        raise _refuse(path, L.MODES.shapes, f"has shape {shape}",
                      f"({n_points}, 3, n_modes) for the {n_points} mesh points")
    for key in (L.MODES.frequencies_hz, L.MODES.omega2, L.MODES.labels, L.MODES.residuals):
        if key in h5 and h5[key].shape != (shape[2],):
            raise _refuse(path, key, f"has shape {h5[key].shape}",
                          f"({shape[2]},), one value per mode of {L.MODES.shapes}")


def _non_negative(path, key: str, a: np.ndarray) -> None:
    bad = a[np.isfinite(a) & (a < 0)]
    if bad.size:
        raise _refuse(path, key, f"holds {bad.size} negative value(s) (e.g. {bad.min():.6g})",
                      "values >= 0 (masses, frequencies and damping ratios of a physical "
                      "body)")


def _semi_definite(path, key: str, a: np.ndarray) -> None:
    """Symmetric positive semi-definite within SYMMETRY_TOL, each trailing square."""
    mats = a.reshape(-1, a.shape[-1], a.shape[-1])
    for m in mats:
        if m.size == 0 or not np.all(np.isfinite(m)):
            continue  # non-finite numbers: the checksum pass refuses them where they matter
        scale = float(np.abs(m).max())
        if scale == 0.0:
            continue
        asym = float(np.abs(m - m.T).max())
        if asym > SYMMETRY_TOL * scale:
            raise _refuse(path, key, f"is not symmetric (|S - S^T| = {asym:.3g} of max "
                          f"|S| = {scale:.3g})", f"a symmetric matrix (to {SYMMETRY_TOL:g} "
                          "relative)")
        eig = np.linalg.eigvalsh(0.5 * (m + m.T))
        if eig[0] < -SYMMETRY_TOL * max(abs(eig[-1]), abs(eig[0])):
            raise _refuse(path, key, f"is indefinite (eigenvalue {eig[0]:.6g} beside "
                          f"{eig[-1]:.6g})", "a positive semi-definite matrix (inertia, "
                          "mass and stiffness of a physical body)")


def stability_tolerance(A: np.ndarray) -> float:
    """tol_A = 10 max(delta, sqrt(delta)), delta = n eps ||A||_1 (module docstring), 1/s."""
    delta = A.shape[0] * np.finfo(float).eps * float(np.abs(A).sum(axis=0).max(initial=0.0))
    return STABILITY_MARGIN * max(delta, np.sqrt(delta))


def _stable(path, key: str, A: np.ndarray) -> None:
    if A.size == 0 or A.shape[0] > MAX_STABILITY_STATES or not np.all(np.isfinite(A)):
        return
    import scipy.linalg

    worst = float(scipy.linalg.eigvals(A, check_finite=False).real.max())
    tol = stability_tolerance(A)
    if worst > tol:
        raise _refuse(path, key, f"has an eigenvalue with real part {worst:+.6g} 1/s (a "
                      "motion that grows without input)", f"a stable model (real parts <= "
                      f"{tol:.3g} 1/s: a passive body cannot gain energy; rigid modes sit "
                      "at 0)")


def _check_fe(h5, path, n_points: int | None) -> None:
    """/fe's M and K: 3 n_points square, symmetric, M_ii > 0, K_ii >= 0."""
    import scipy.sparse as sp

    for key, strict in ((L.FE.mass_matrix, True), (L.FE.stiffness_matrix, False)):
        g = L.csr_group(key)
        if g.data not in h5 or g.shape not in h5:
            continue
        shape = tuple(int(s) for s in np.asarray(h5[g.shape][()]).ravel())
        want = None if n_points is None else 3 * n_points
        if len(shape) != 2 or shape[0] != shape[1] or (want is not None and shape[0] != want):
            raise _refuse(path, key, f"has shape {shape}", f"({want}, {want}): 3 DOFs per "
                          "mesh point")
        data, indices, indptr = (np.asarray(h5[k][()]) for k in (g.data, g.indices, g.indptr))
        if indptr.size != shape[0] + 1 or (indices.size and (indices.min() < 0 or
                                                             indices.max() >= shape[1])):
            raise _refuse(path, key, "has CSR indices outside its shape",
                          f"column indices inside 0..{shape[1] - 1}")
        S = sp.csr_matrix((data, indices, indptr), shape=shape)
        if _text(h5[g.data].attrs.get(g.attr.storage, "full")) != "upper":
            scale = float(abs(S).max()) if S.nnz else 0.0
            asym = float(abs(S - S.T).max()) if S.nnz else 0.0
            if asym > SYMMETRY_TOL * scale:
                raise _refuse(path, key, f"is not symmetric (|S - S^T| = {asym:.3g} of max "
                              f"|S| = {scale:.3g})", "a symmetric matrix")
        diag = S.diagonal()
        bad = diag <= 0 if strict else diag < 0
        if np.any(bad):
            raise _refuse(path, key, f"has {int(bad.sum())} diagonal entr(ies) "
                          f"{'<= 0' if strict else '< 0'} (e.g. {diag[bad].min():.6g})",
                          "a positive " + ("definite" if strict else "semi-definite")
                          + " matrix, whose diagonal is " + ("> 0" if strict else ">= 0"))
