"""The lumped chain of a file spun up with its full rigid-body kinematics (``spin_up``).

The chain (``/lumped``: rigid bodies joined by springs along x, theory.md §7) moves in the
plane normal to the spin axis a (a normal to x): only its revolute joints about a are
free (angles phi_l, l = 1..n, springs k_l, dampers c_l from the joint table); its axial,
torsion and out-of-plane joints are held rigid. Plane coordinates: e1 = x, e2 = a x e1,
positions relative to the hub point p. With the hub angle theta(t) prescribed (the
Kane-Ryan-Banerjee ramp of :mod:`.spinup`), the absolute angle of link j (from joint j
to joint j + 1, the last to the tip) is psi_j = theta + sum_{l<=j} phi_l, and the
centre of mass of body b on link i(b) is

    r_b = R(theta) P_1 + sum_{j<i(b)} R(psi_j) d_j + R(psi_i(b)) c_b,

P_1 the first joint, d_j = P_{j+1} - P_j, c_b = (its centre) - P_i(b) in the straight
chain. Kane's equations, nonlinear and exact for rigid links (no linearisation):

    sum_b m_b v_bl . r_b'' + I_b psi_i(b)'' [l <= i(b)] + c_l phi_l' + k_l phi_l = 0,

v_bl = d r_b' / d phi_l' = sum_{j>=l} k x u_bj (u_bj the terms of r_b), I_b the body's
inertia about a through its centre. The centrifugal stiffening of the chain comes out
of its kinematics (the Mitiguy-Banerjee property). Bodies before the first joint turn
with the hub. Recorded: the tip's deflection along e2 in the hub frame.
"""

from __future__ import annotations

import time

import numpy as np
from scipy.integrate import solve_ivp

from pipeline.errors import SolverError
from pipeline.store.read import ModelFile

from pipeline.apps.simulate.integrate import time_grid
from pipeline.apps.simulate.scenarios import Scenario

__all__ = ["PlanarChain", "planar_chain", "step_chain"]


def _perp(u: np.ndarray) -> np.ndarray:
    """k x u for planar vectors (..., 2)."""
    return np.stack([-u[..., 1], u[..., 0]], axis=-1)


def _rotate(angle, u: np.ndarray) -> np.ndarray:
    """R(angle) u, angle (...,) and u (..., 2)."""
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([c * u[..., 0] - s * u[..., 1], s * u[..., 0] + c * u[..., 1]], axis=-1)


class PlanarChain:
    """The chain's planar data (SI): root (2,) P_1 - p; links d (n, 2); bodies: mass
    (B,), inertia (B,) about a, link (B,) index, offset c (B, 2); springs k (n,) N m/rad,
    dampers c (n,) N m s/rad; sign: the output direction's component along e2."""

    def __init__(self, root, links, mass, inertia, link, offset, k, c, sign):
        self.root, self.links = root, links
        self.mass, self.inertia, self.link, self.offset = mass, inertia, link, offset
        self.k, self.c, self.sign = k, c, sign
        n = links.shape[0]
        # u_bj uses d_j for j < i(b), c_b for j = i(b), nothing after
        self.before = np.arange(n)[None, :] < link[:, None]  # (B, n)
        self.at = np.arange(n)[None, :] == link[:, None]
        self.upto = np.arange(n)[None, :] <= link[:, None]  # psi_i(b)'' holds phi_l'', l<=i

    def accelerations(self, theta, omega, alpha, phi, dphi) -> np.ndarray:
        """phi'' (n,) from Kane's equations (module docstring)."""
        psi = theta + np.cumsum(phi)
        dpsi = omega + np.cumsum(dphi)
        d = _rotate(psi, self.links)  # (n, 2)
        cb = _rotate(psi[self.link], self.offset)  # (B, 2)
        u = self.before[:, :, None] * d[None] + self.at[:, :, None] * cb[:, None, :]
        p1 = _rotate(theta, self.root)
        v = _perp(np.cumsum(u[:, ::-1], axis=1)[:, ::-1])  # (B, n, 2): sum_{j>=l}
        r = p1 + u.sum(axis=1)
        rest = alpha * _perp(r) - omega ** 2 * p1 - np.einsum("j,bjc->bc", dpsi ** 2, u)
        M = self._mass(v)
        f = -(np.einsum("b,blc,bc->l", self.mass, v, rest)
              + self.upto.T.astype(float) @ (self.inertia * alpha))
        return np.linalg.solve(M, f - self.k * phi - self.c * dphi)

    def _mass(self, v: np.ndarray) -> np.ndarray:
        up = self.upto.astype(float)
        return np.einsum("b,blc,bkc->lk", self.mass, v, v) + (up.T * self.inertia) @ up

    def jacobian(self, theta, phi) -> np.ndarray:
        """d(phi', phi'')/d(phi, phi') with the springs and dampers only (the inertia
        terms' derivatives left out): the Newton matrix of an implicit step, whose
        stiffness comes from the joint springs."""
        n = phi.size
        psi = theta + np.cumsum(phi)
        d = _rotate(psi, self.links)
        cb = _rotate(psi[self.link], self.offset)
        u = self.before[:, :, None] * d[None] + self.at[:, :, None] * cb[:, None, :]
        Minv = np.linalg.inv(self._mass(_perp(np.cumsum(u[:, ::-1], axis=1)[:, ::-1])))
        J = np.zeros((2 * n, 2 * n))
        J[:n, n:] = np.eye(n)
        J[n:, :n] = -Minv * self.k
        J[n:, n:] = -Minv * self.c
        return J

    def tip_deflection(self, phi) -> float:
        """Deflection of the chain's end along e2 in the hub frame (m), signed for the port."""
        turned = _rotate(np.cumsum(phi), self.links)
        return self.sign * float((turned[:, 1] - self.links[:, 1]).sum())


def planar_chain(mf: ModelFile, axis: np.ndarray, point: np.ndarray, port: str,
                 damping: bool) -> tuple[PlanarChain | None, str]:
    """The :class:`PlanarChain` of the file's lumped chain for a spin about ``axis``
    through ``point``, or (None, why not)."""
    lp = mf.lumped
    if lp is None:
        return None, "the file has no lumped model"
    need = ("joint_table", "element_mass", "element_com", "element_inertia",
            "element_extent", "joint_positions")
    if any(k not in lp for k in need):
        return None, "the file's lumped chain lacks its rigid bodies or joint table"
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    e1 = np.array([1.0, 0.0, 0.0])
    if abs(a @ e1) > 1e-9:
        return None, "the spin axis is not normal to the chain (x)"
    e2 = np.cross(a, e1)
    info = mf.ports.get(port) or {}
    if info.get("region") != "tip" or info.get("direction") is None \
            or abs(abs(info["direction"] @ e2) - 1.0) > 1e-9:
        return None, (f"the output port '{port}' is not on the tip along the plane of "
                      "rotation, the only motion the planar chain has")
    table = lp["joint_table"]
    free = [i for i, dof in enumerate(table["dof"]) if dof.startswith("bend")
            and abs(abs(table["axis"][i] @ a) - 1.0) < 1e-9]
    if not free:
        return None, "the lumped chain has no bending joint about the spin axis"
    joints = np.asarray(lp["joint_positions"], float)
    order = np.argsort(table["joint"][free])
    rows = np.asarray(free)[order]
    joint_x = joints[table["joint"][rows].astype(int) - 1]

    def plane(x):
        x = np.atleast_2d(np.asarray(x, float)) - point
        return np.column_stack([x @ e1, x @ e2])

    tip = joint_x[-1].copy()
    tip[0] = float(np.max(lp["element_extent"][:, 1]))
    pts = plane(np.vstack([joint_x, tip]))
    com = plane(lp["element_com"])
    link = np.searchsorted(joint_x[:, 0], lp["element_com"][:, 0], side="right") - 1
    moving = link >= 0  # bodies before the first joint turn with the hub
    link = link[moving]
    inertia = np.einsum("i,bij,j->b", a, lp["element_inertia"][moving], a)
    chain = PlanarChain(pts[0], np.diff(pts, axis=0), lp["element_mass"][moving], inertia,
                        link, com[moving] - pts[link], table["stiffness"][rows],
                        table["damping"][rows] if damping else np.zeros(len(rows)),
                        float(np.sign(info["direction"] @ e2)))
    return chain, ""


def step_chain(chain: PlanarChain, sc: Scenario, profile, limit: float, scale: float,
               rate: float) -> tuple[np.ndarray, np.ndarray, dict]:
    """Integrate the chain from rest on the scenario's grid; ``profile(t)`` gives (Omega,
    alpha, theta) of the hub. Returns (t, tip deflection (m), statistics); stops when
    |deflection| exceeds ``limit`` (m). The absolute tolerances are the integrator's
    ``atol`` times the joint angle of a deflection ``scale`` (m) spread over the chain
    and times ``rate`` (1/s, the first frequency) for the joint rates."""
    n = chain.links.shape[0]
    t = time_grid(sc)

    def rhs(time_s, z):
        speed, alpha, angle = (float(x) for x in profile(time_s))
        return np.concatenate([z[n:], chain.accelerations(angle, speed, alpha, z[:n], z[n:])])

    def runaway(_t, z):
        return limit - abs(chain.tip_deflection(z[:n]))
    runaway.terminal = True

    start = time.perf_counter()
    length = float(np.linalg.norm(chain.links.sum(axis=0)))
    angle = max(abs(scale), 1e-12 * length) / length
    scale = np.concatenate([np.full(n, angle), np.full(n, angle * rate)])
    kw = {"jac": lambda time_s, z: chain.jacobian(float(profile(time_s)[2]), z[:n])} \
        if sc.integrator.method in ("Radau", "BDF", "LSODA") else {}
    sol = solve_ivp(rhs, (0.0, float(t[-1])), np.zeros(2 * n), method=sc.integrator.method,
                    t_eval=t, rtol=sc.integrator.rtol, atol=sc.integrator.atol * scale,
                    events=runaway, **kw)
    stats = {"nfev": int(sol.nfev), "njev": int(sol.njev), "nlu": int(sol.nlu),
             "method": sc.integrator.method, "rtol": sc.integrator.rtol,
             "atol": sc.integrator.atol, "wall_s": time.perf_counter() - start}
    if sol.status == 1 and sol.t_events[0].size:
        stats["runaway_s"] = float(sol.t_events[0][0])
    if sol.status == -1:
        raise SolverError(f"scenario '{sc.name}': solve_ivp ({sc.integrator.method}) "
                          f"failed on the lumped chain: {sol.message}")
    y = np.array([chain.tip_deflection(sol.y[:n, k]) for k in range(sol.t.size)])
    return sol.t, y, stats
