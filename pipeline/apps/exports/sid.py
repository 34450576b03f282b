"""Export to SID: the standard input data of a flexible body [Wallrapp 1994; Schwertassek &
Wallrapp 1999, ch. 6], the text file (``.SID_FEM``) SIMPACK and other floating-frame codes
read.

The body moves with a reference frame (origin O, angular velocity omega) plus a small
deflection u(x) = sum_k psi_k(x) q_k in that frame; r = x - O + u is a point's position in
it. Every term is a Taylor object M(q) = M0 + sum_k M1[:, :, k] q_k (``order`` 0 or 1) of
``nrow`` x ``ncol`` with ``nq`` coordinates; ``structure`` 0 zero, 1 diagonal, 2 symmetric
(lower triangle written), 3 full. With the consistent mass every integral is a bilinear
form in the FE mass matrix (:mod:`pipeline.reduce.ffrf`, theory.md §6, §13); ~ is the
skew (cross-product) matrix, W the six products of omega in SID order
(w_x^2, w_y^2, w_z^2, w_x w_y, w_y w_z, w_x w_z):

=========  ============  ===============================================================
term       nrow x ncol   M0 ; M1[:, :, k] (coordinate q_k)
=========  ============  ===============================================================
refmod     -             mass int rho dV; nelastq; ielastq(k) = "<label> : <f> Hz"
origin     3 x 1         node position x_n - O ; the node's translation phi_n,k
phi        3 x nq        translations of the node per coordinate (order 0)
psi        3 x nq        rotations of the node per coordinate (order 0)
AP         3 x 3         I (node frames parallel to the body frame) ; skew(psi_n,k)
mdCM       3 x 1         int rho (x - O) dV = m c ; int rho psi_k dV
J          3 x 3         -int rho x~ x~ dV (inertia about O, symmetric) ;
                         -int rho (x~ psi_k~ + psi_k~ x~) dV
Ct         nq x 3        (int rho psi dV)^T (order 0)
Cr         nq x 3        (int rho x~ psi dV)^T ; row j: (int rho psi_k x psi_j dV)^T
Me         nq x nq       Psi^T M Psi (symmetric)
Gr         3 x 3 nq      block j: -2 int rho x~ psi_j~ dV ; -2 int rho psi_k~ psi_j~ dV
Ge         nq x 3 nq     block j, row i: 2 (int rho psi_j x psi_i dV)^T (order 0)
Oe         nq x 6        row i: -psi_i^T M (A_W r) per product W ; V^T (K_G,W - M_W) V
ksigma     nq x 1        zero (no reference stress at q = 0; the spin's is in Oe's M1)
Ke         nq x nq       Psi^T K Psi (symmetric)
De         nq x nq       diag(2 zeta_k w_k) (diagonal)
=========  ============  ===============================================================

Oe's M1 is the geometric stiffening of a spinning body: the modal equation holds
Oe(q) W, whose part linear in q is sum_W W (K_G,W - M_W) q, the stored ``/rotation``
terms (:class:`pipeline.reduce.spin.RotationModel`: geometric stiffness of the centrifugal
stress per unit W minus the spin-softening mass), so a code that reads the SID stiffens
the body as :func:`pipeline.reduce.spin.reduced_frequencies` does.

What the export reads (through :mod:`pipeline.store.read` only): ``/mesh`` (points,
cells, regions), ``/modes`` (shapes, frequencies, labels), the full mass and stiffness
matrices (``/fe``, or re-assembled on the stored mesh with the stored config, as for the
Exudyn export: ``fe_data``), ``/statespace`` damping ratios and ``/rotation`` (optional:
without it Oe's M1 holds the spin softening alone, and the file says the stiffening is
missing in the log). The coordinates are the body's elastic modes (rigid-body modes of a
free body dropped); a rotation basis's extra shapes (static, correction) have no nodal
fields in the file and are left out. The frame origin O is ``/rotation/point`` when
present (the centrifugal stress was computed about it), else the mesh origin; the axes are
the mesh's. One frame node per region of the mesh at its weighted centroid, moving with
the region's weighted least-squares rigid fit (RBE3; a region that cannot carry rotations,
one point or a straight line, gets psi = 0 for the rotations it cannot see).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipeline._util.atomic import write_text
from pipeline.config.rotation import TENSOR_ENTRIES, entry_matrix
from pipeline.errors import FileFormatError
from pipeline.store import layout as L
from pipeline.store.read import read_fe_model, read_rotation, read_stored_mesh

log = logging.getLogger(__name__)

__all__ = ["Taylor", "SidNode", "SidBody", "SID_PRODUCTS", "sid_body", "sid_text",
           "export_sid"]

#: SID order of the six products of omega (W columns of Oe), as (i, j) component pairs
SID_PRODUCTS: tuple[tuple[int, int], ...] = ((0, 0), (1, 1), (2, 2), (0, 1), (1, 2), (0, 2))
#: column of each SID product in our /rotation tensor order (TENSOR_ENTRIES)
_FROM_TENSOR = [TENSOR_ENTRIES.index(p) for p in SID_PRODUCTS]
#: the Levi-Civita symbol: (a x b)_c = EPS[c, a, b] a_a b_b; skew(v)[a, b] = -EPS[a, b, c] v_c
EPS = np.zeros((3, 3, 3))
EPS[0, 1, 2] = EPS[1, 2, 0] = EPS[2, 0, 1] = 1.0
EPS[0, 2, 1] = EPS[2, 1, 0] = EPS[1, 0, 2] = -1.0


@dataclass(frozen=True)
class Taylor:
    """One SID Taylor object: m0 (nrow, ncol); m1 (nrow, ncol, nq) or None (order 0);
    structure 0 zero, 1 diagonal, 2 symmetric, 3 full."""

    name: str
    m0: np.ndarray
    m1: np.ndarray | None = None
    structure: int = 3

    @property
    def order(self) -> int:
        return 0 if self.m1 is None else 1


@dataclass(frozen=True)
class SidNode:
    """A frame node: ``region`` it stands for; origin, phi, psi, AP Taylor objects."""

    region: str
    origin: Taylor
    phi: Taylor
    psi: Taylor
    ap: Taylor


@dataclass(frozen=True)
class SidBody:
    """Everything a SID file holds (module docstring): mass kg; mode_names (nq,);
    frequencies_hz (nq,); nodes; the body terms in file order; origin (3,) m: O in the
    mesh frame; stiffening: the /rotation terms are in Oe's M1."""

    mass: float
    mode_names: tuple[str, ...]
    frequencies_hz: np.ndarray
    nodes: tuple[SidNode, ...]
    terms: tuple[Taylor, ...]
    origin: np.ndarray
    stiffening: bool


# --------------------------------------------------------------------------- the terms
def _node(name: str, nodes: np.ndarray, weights: np.ndarray, x: np.ndarray,
          Psi: np.ndarray) -> SidNode:
    """The frame node of a region (``nodes``, fit ``weights``) at its weighted centroid;
    x (n_points, 3) m relative to O; Psi (3 n_points, nq)."""
    w = weights / weights.sum()
    c = w @ x[nodes]
    R = np.zeros((nodes.size, 3, 6))  # rows [I, -skew(x - c)]: a unit twist at c
    R[:, :, :3] = np.eye(3)
    R[:, :, 3:] = np.einsum("abc,nc->nab", EPS, x[nodes] - c)
    R = R.reshape(-1, 6)
    wr = np.repeat(w, 3)
    A = R.T @ (wr[:, None] * R)
    rows = np.ravel(3 * nodes[:, None] + np.arange(3))
    fit = np.linalg.lstsq(A, R.T @ (wr[:, None] * Psi[rows]), rcond=1e-10)[0]  # (6, nq)
    phi, psi = fit[:3], fit[3:]
    ap1 = -np.einsum("abc,ck->abk", EPS, psi)  # skew(psi_k)
    return SidNode(name, Taylor("origin", c[:, None], phi[:, None, :]),
                   Taylor("phi", phi), Taylor("psi", psi),
                   Taylor("AP", np.eye(3), ap1))


def _nodes(points, cells, regions, x, Psi) -> tuple[SidNode, ...]:
    from pipeline.apps.exports.exudyn import region_node_weights

    out = []
    for name, cells_r in regions.items():
        nodes, weights = region_node_weights(points, cells, cells_r)
        if nodes.size and weights.sum() > 0:
            out.append(_node(str(name), nodes, weights, x, Psi))
    return tuple(out)


def _fe_matrices(body, fe_data, h5_path) -> tuple[Any, Any, str]:
    if body.has_fe:
        return body.M, body.K, "M and K stored by the run (/fe)"
    if fe_data is not None and getattr(fe_data, "M_full", None) is not None:
        return fe_data.M_full, fe_data.K_full, fe_data.source
    raise FileFormatError(
        f"file '{h5_path}': has no /fe (the full mass matrix the SID inertia terms need); "
        "export it with 'python -m pipeline export FILE --to sid', which re-assembles it "
        "from the stored config and mesh", key="/fe", value="absent",
        expected="/fe in the file, or fe_data")


def _damping(mesh, omega: np.ndarray) -> np.ndarray:
    """(nq,) damping ratios of the modes: the stored config's uniform or Rayleigh damping,
    else the retained modes' stored ratios (zero beyond them)."""
    import yaml

    from pipeline.reduce.modal import damping_ratios

    raw = (yaml.safe_load(mesh.config_yaml) or {}) if mesh.config_yaml else {}
    damping = raw.get("damping") if isinstance(raw, dict) else None
    damping = damping if isinstance(damping, dict) else {"kind": "uniform", "ratio": 0.02}
    kind = damping.get("kind", "uniform")
    if kind in ("uniform", "rayleigh"):
        return damping_ratios(omega, kind, ratio=damping.get("ratio", 0.02),
                              alpha=damping.get("alpha", 0.0), beta=damping.get("beta", 0.0))
    zeta = np.zeros(omega.size)
    n = min(omega.size, mesh.retained_damping.size)
    zeta[:n] = mesh.retained_damping[:n]
    return zeta


def _rotation_terms(rot, n_rigid: int, n_modes: int, h5_path) -> np.ndarray:
    """(6, nq, nq) K_G,W - M_W of the elastic modes in SID product order."""
    if rot.n_modes != n_modes:
        raise FileFormatError(f"file '{h5_path}': /rotation holds {rot.n_modes} modes, "
                              f"/modes {n_modes}", key="/rotation", value=rot.n_modes,
                              expected=str(n_modes))
    keep = slice(n_rigid, n_modes)
    return (rot.geometric - rot.softening)[_FROM_TENSOR][:, keep, keep]


def sid_body(h5_path: str | Path, fe_data: Any = None) -> SidBody:
    """The SID of the result file ``h5_path`` (module docstring). ``fe_data``
    (:func:`pipeline.run.stored_fe_data`) supplies M and K for a file without ``/fe``.
    FileFormatError (one line) for a file without modes or without M."""
    body = read_fe_model(h5_path, "modes")
    mesh = read_stored_mesh(h5_path)
    n_rigid, n_modes = body.basis.n_rigid, body.basis.shapes.shape[1]
    Psi = body.basis.shapes[:, n_rigid:]
    nq = Psi.shape[1]
    if nq == 0:
        raise FileFormatError(f"file '{h5_path}': has no elastic modes (/modes holds "
                              f"{n_modes}, {n_rigid} of them rigid); SID needs at least one",
                              key=L.MODES.shapes, value=n_modes, expected="elastic modes")
    M, K, source = _fe_matrices(body, fe_data, h5_path)
    m = _scalar_mass(M, h5_path)
    rot = read_rotation(h5_path)
    O = np.zeros(3) if rot is None else np.asarray(rot.point, float)
    x = body.points - O
    P = Psi.reshape(-1, 3, nq)
    row_mass = np.asarray(m.sum(axis=1)).ravel()  # m 1 = 1^T m (symmetric)
    XP = _products(m, x[:, :, None], P)[:, :, 0, :]  # [a, b, k] = int rho x_a psi_k,b
    PP = _products(m, P, P)  # [a, b, k, l] = int rho psi_k,a psi_l,b
    XX = _products(m, x[:, :, None], x[:, :, None])[:, :, 0, 0]
    Me = np.einsum("aakl->kl", PP)
    Ke = Psi.T @ np.asarray(K @ Psi)
    Ct = np.einsum("n,nak->ak", row_mass, P)  # int rho psi_k
    Cr = np.einsum("cab,abk->ck", EPS, XP)  # int rho x x psi_k
    G = np.einsum("cab,abkl->klc", EPS, PP)  # G[k, l] = int rho psi_k x psi_l
    # int rho x~ psi_k~ = int rho (psi_k x^T - (x . psi_k) I)
    XT = XP.transpose(2, 1, 0) - np.einsum("aak->k", XP)[:, None, None] * np.eye(3)
    J1 = -(XT + XT.transpose(0, 2, 1))
    # -int rho psi_k~ psi_l~ = -(int rho psi_l psi_k^T - (psi_k . psi_l) I)
    J2 = -(PP.transpose(2, 3, 1, 0) - Me[:, :, None, None] * np.eye(3))
    A = np.stack([entry_matrix(i, j) for i, j in SID_PRODUCTS])  # (6, 3, 3)
    oe0 = -np.einsum("wab,bak->kw", A, XP)  # -int rho psi_k . A_W x
    if rot is not None:
        spin = _rotation_terms(rot, n_rigid, n_modes, h5_path)
    else:  # the spin softening alone: -int rho psi_k . A_W psi_l
        spin = -np.einsum("wab,abkl->wkl", A, PP)
        log.warning("file '%s' has no /rotation: the SID's Oe holds the spin softening only, "
                    "without the geometric stiffening of the centrifugal stress (run with a "
                    "'rotation' section to add it)", h5_path)
    omega = np.sqrt(np.maximum(np.diag(Ke), 0.0))
    zeta = _damping(mesh, 2 * np.pi * mesh.frequencies_hz[n_rigid:])
    terms = (
        Taylor("mdCM", (row_mass @ x)[:, None], Ct[:, None, :]),
        Taylor("J", np.trace(XX) * np.eye(3) - XX, J1.transpose(1, 2, 0), 2),
        Taylor("Ct", Ct.T),
        Taylor("Cr", Cr.T, G.transpose(1, 2, 0)),
        Taylor("Me", 0.5 * (Me + Me.T), structure=2),
        Taylor("Gr", -2 * XT.transpose(1, 0, 2).reshape(3, 3 * nq),
               2 * J2.transpose(2, 1, 3, 0).reshape(3, 3 * nq, nq)),
        Taylor("Ge", 2 * G.transpose(1, 0, 2).reshape(nq, 3 * nq)),
        Taylor("Oe", oe0, spin.transpose(1, 0, 2)),
        Taylor("ksigma", np.zeros((nq, 1)), structure=0),
        Taylor("Ke", 0.5 * (Ke + Ke.T), structure=2),
        Taylor("De", np.diag(2 * zeta * omega), structure=1),
    )
    names = tuple(lbl or f"mode {k + 1}" for k, lbl in enumerate(mesh.labels[n_rigid:]))
    nodes = _nodes(body.points, body.cells, body.regions, x, Psi)
    log.info("SID of %s: %d modes, frame origin %s m (%s); frame nodes: %s", h5_path, nq,
             np.array2string(O, precision=4), source,
             ", ".join(f"{n + 1} = {node.region}" for n, node in enumerate(nodes)))
    return SidBody(float(row_mass.sum()), names, mesh.frequencies_hz[n_rigid:].copy(),
                   nodes, terms, O,
                   rot is not None)


def _scalar_mass(M, h5_path):
    """m (n_p x n_p) of M = m (x) I_3 (DOF 3 node + component); FileFormatError where the
    components are coupled or differ (the SID integrals are bilinear forms in m)."""
    import scipy.sparse as sp

    M = sp.csr_matrix(M)
    m = M[0::3, 0::3]
    size = abs(m).max()
    off = max(abs(M[a::3, b::3] - (m if a == b else 0 * m)).max()
              for a in range(3) for b in range(3))
    if off > 1e-9 * size:
        raise FileFormatError(f"file '{h5_path}': the mass matrix is not m (x) I_3 (its "
                              f"components differ or couple by {off / size:.1e} of its "
                              "largest entry); the SID export needs the same mass in x, y, z",
                              key=L.FE.mass_matrix, value=off / size, expected="m (x) I_3")
    return m


def _products(m, U: np.ndarray, V: np.ndarray) -> np.ndarray:
    """(3, 3, p, r) [a, b, i, j] = int rho u_i,a v_j,b dV of nodal fields U (n_p, 3, p) and
    V (n_p, 3, r), with the scalar consistent mass m (n_p x n_p)."""
    mU = np.asarray(m @ U.reshape(U.shape[0], -1)).reshape(U.shape)
    return np.einsum("nap,nbr->abpr", mU, V)


# --------------------------------------------------------------------------- the text
def _number(v: float) -> str:
    return f"{float(v): .16E}"


def _taylor_lines(t: Taylor, nq: int, indent: str) -> list[str]:
    nrow, ncol = t.m0.shape
    out = [f"{indent}{t.name}", f"{indent}   order        = {t.order}",
           f"{indent}   nrow         = {nrow}", f"{indent}   ncol         = {ncol}",
           f"{indent}   nq           = {nq if t.order or t.name in ('phi', 'psi') else 0}",
           f"{indent}   nqn          = 0", f"{indent}   structure    = {t.structure}"]
    for i in range(nrow):
        for j in range(ncol):
            if t.structure == 0 or (t.structure == 1 and i != j) or (t.structure == 2
                                                                      and j > i):
                continue
            out.append(f"{indent}   m0( {i + 1}, {j + 1}) = {_number(t.m0[i, j])}")
    if t.m1 is not None:
        for i in range(nrow):
            for j in range(ncol):
                for k in range(nq):
                    out.append(f"{indent}   m1( {i + 1}, {j + 1}, {k + 1}) = "
                               f"{_number(t.m1[i, j, k])}")
    out.append(f"{indent}end {t.name}")
    return out


def sid_text(sid: SidBody) -> str:
    """The SID file text of ``sid``: part / new modal / refmod / frame / terms / end."""
    nq = len(sid.mode_names)
    lines = ["part", "   new modal", "      refmod",
             f"         mass           = {_number(sid.mass)}",
             f"         nelastq        = {nq}"]
    lines += [f"         ielastq({k + 1}) = {name} : {f:.10g} Hz"
              for k, (name, f) in enumerate(zip(sid.mode_names, sid.frequencies_hz))]
    lines += ["      end refmod", "      new frame"]
    for n, node in enumerate(sid.nodes):
        lines += [f"         new node = {n + 1}", "            rframe = body ref"]
        for t in (node.origin, node.phi, node.psi, node.ap):
            lines += _taylor_lines(t, nq, "            ")
        lines.append("         end node")
    lines.append("      end frame")
    for t in sid.terms:
        lines += _taylor_lines(t, nq, "      ")
    lines += ["   end modal", "end part"]
    return "\n".join(lines) + "\n"


def export_sid(h5_path: str | Path, out_path: str | Path, fe_data: Any = None) -> Path:
    """Write the SID file ``out_path`` of the result file ``h5_path`` (module docstring);
    ``fe_data`` (:func:`pipeline.run.stored_fe_data`) for a file without ``/fe``. Every
    check runs before anything is written; the file is written atomically."""
    sid = sid_body(h5_path, fe_data)
    out = write_text(Path(out_path), sid_text(sid))
    log.info("wrote SID file %s (%d modes, %d nodes; geometric stiffening %s)", out,
             len(sid.mode_names), len(sid.nodes),
             "from /rotation" if sid.stiffening else "absent: no /rotation in the file")
    return out
