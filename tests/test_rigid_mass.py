"""Rigid (RBE2) coupling of an added point mass (``masses[].coupling: rigid``): the region's
nodes follow the six motions of the mass's point exactly (u = T q,
:mod:`pipeline.fe.constraints`), the point's 6 x 6 rigid mass on those motions.

Checks and their tolerances:
- against CalculiX on the same mesh: *RIGID BODY (REF NODE, ROT NODE) over the region's
  nodes and the mass's own nodes, the mass and its rotary inertia as seven MASS elements
  (m_c at the point, six at +-a along the axes, which give the same inertia tensor
  exactly: see ``inertia_masses``), on the same P2 mesh (C3D10), frequencies to 4 x
  CalculiX's printed digits (7 significant: 5e-7 relative each; measured 4.5e-7). An
  independent dense null-space solve (slave rows u_s - R_s q_P = 0 on [u; q_P], M6 on
  q_P) agreed to 1e-9 while this was built;
- the limit: on a tip region made 145 times stiffer than the beam, the rigid and the
  distributing couplings agree (the region then barely deforms; the gap falls with the
  stiffness ratio: measured 3.4e-5 in the 4 lowest frequencies, bounded by 1e-4), while
  on the plain beam they differ (the rigid coupling stiffens the tip face: measured
  4e-3, asserted above 1e-3); the rigid frequencies are never below the distributing
  ones (a constraint only adds stiffness);
- mass properties exact: the body's mass and rigid mass matrix gain exactly the point's
  own (1e-12 relative, round-off); and the modes are M-orthonormal on the free DOFs;
- the factor-free solver (LOBPCG, coarse space T^T P) against the factor path on the
  same constrained pencil: 1e-8 (measured 9e-12);
- a region held by the supports: refused in one line naming the key, RegionError's exit
  code, nothing written; the end-to-end run with a reduced model, whose Exudyn export
  (the unconstrained body's matrices) is refused in one line.
"""

from __future__ import annotations

import shutil
import subprocess
import sys

import numpy as np
import pytest

from pipeline.config import config_from_dict
from pipeline.fe.model import build_fe_model
from pipeline.solve.stage import ModesInput, compute_modes

ALU = {"E": 69e9, "nu": 0.33, "rho": 2700.0}
BEAM = {"kind": "box", "length": 0.2, "height": 0.02, "depth": 0.02}
POINT = [0.23, 0.012, 0.009]  # beyond the tip face (x = 0.2), off its centre
MASS = 0.3  # kg, about 1.4 times the beam's
INERTIA = [2e-4, 3e-4, 4e-4, 0.0, 0.0, 0.0]  # kg m^2 about POINT
#: CalculiX prints 7 significant digits: its values carry a relative error up to 5e-7
CCX_DIGITS = 5e-7


def config(coupling="rigid", region="tip", count=4, **extra):
    raw = {"name": "rb", "geometry": BEAM, "mesh": {"order": 2, "size": 0.01},
           "material": ALU, "supports": [{"region": "root", "fix": "all"}],
           "modes": {"count": count},
           "masses": [{"name": "m", "mass": MASS, "inertia": INERTIA, "point": POINT,
                       "region": region, "coupling": coupling}]}
    raw.update(extra)
    return raw


def solve(raw, tmp_path):
    cfg = config_from_dict(raw)
    fe = build_fe_model(cfg, tmp_path)
    modes = compute_modes(ModesInput.from_fe(fe, cfg.modes, supported=bool(cfg.supports)),
                          cfg.modes, keep=False)
    return fe, modes


def inertia_masses(mass, inertia, a):
    """(points (7, 3) offsets from the mass's point, masses (7,)): m_c at the point and
    m_k at +-a e_k, with 2 a^2 (m_y + m_z) = Ixx, 2 a^2 (m_x + m_z) = Iyy,
    2 a^2 (m_x + m_y) = Izz and m_c + 2 (m_x + m_y + m_z) = m (a diagonal inertia)."""
    Ixx, Iyy, Izz = inertia[:3]
    s = (Ixx + Iyy + Izz) / (4 * a * a)  # m_x + m_y + m_z
    mk = np.array([s - Ixx / (2 * a * a), s - Iyy / (2 * a * a), s - Izz / (2 * a * a)])
    assert (mk > 0).all() and mass - 2 * s > 0
    offsets = np.vstack([np.zeros(3), *(sign * a * np.eye(3)[k] for k in range(3)
                                        for sign in (1, -1))])
    return offsets, np.r_[mass - 2 * s, np.repeat(mk, 2)]


def calculix_frequencies(fe, count, folder):
    import ccx_deck

    from pipeline.fe.space import region_nodes

    space = fe.space
    offsets, masses = inertia_masses(MASS, INERTIA, 0.05)
    n0, n_e = space.n_nodes, space.body.n_tetrahedra
    mass_nodes = n0 + 1 + np.arange(7)
    ref, rot = n0 + 8, n0 + 9
    lines = ["*NODE"] + [f"{n}, " + ", ".join(f"{float(c)!r}" for c in np.add(POINT, o))
                         for n, o in zip(mass_nodes, offsets)]
    lines += [f"{ref}, " + ", ".join(f"{float(c)!r}" for c in POINT),
              f"{rot}, " + ", ".join(f"{float(c)!r}" for c in POINT)]
    slaves = [int(n) + 1 for n in region_nodes(space, fe.regions["tip"])] + list(mass_nodes)
    lines += ["*NSET, NSET=RB"] + [", ".join(str(n) for n in slaves[i:i + 12])
                                   for i in range(0, len(slaves), 12)]
    lines += [f"*RIGID BODY, NSET=RB, REF NODE={ref}, ROT NODE={rot}"]
    for k, (n, m) in enumerate(zip(mass_nodes, masses)):
        lines += [f"*ELEMENT, TYPE=MASS, ELSET=PM{k}", f"{n_e + 1 + k}, {n}",
                  f"*MASS, ELSET=PM{k}", f"{float(m)!r}"]
    step = "\n".join(lines) + f"\n*STEP\n*FREQUENCY\n{count}\n*END STEP"
    deck = folder / "rb.inp"
    ccx_deck.write_deck(deck, space, [{"kind": "isotropic", **ALU}],
                        np.zeros(n_e, dtype=int), np.unique(fe.fixed // 3), step)
    return ccx_deck.frequencies(ccx_deck.run(deck))[:count]


@pytest.mark.skipif(shutil.which("ccx") is None, reason="CalculiX (ccx) is not installed")
def test_rigid_tip_mass_against_calculix(tmp_path):
    fe, modes = solve(config(), tmp_path)
    f_ccx = calculix_frequencies(fe, 4, tmp_path)
    np.testing.assert_allclose(modes.frequencies_hz, f_ccx, rtol=4 * CCX_DIGITS)


def test_rigid_and_distributing_agree_on_a_stiff_region(tmp_path):
    """The last 2 cm of the beam 145 times stiffer (E at the validator's 1e13 Pa limit): the tip face barely deforms, so
    holding it rigid changes little; on the plain beam the rigid coupling stiffens the
    face and raises the frequencies measurably."""
    stiff = {"materials": [{"name": "stiff", "E": 1e13, "nu": 0.33, "rho": 2700.0,
                            "elements": {"kind": "box", "lower": [0.18, -1, -1],
                                         "upper": [1, 1, 1]}}]}
    gaps = {}
    for name, extra in (("plain", {}), ("stiff", stiff)):
        _, rigid = solve(config(**extra), tmp_path)
        _, dist = solve(config("distributing", **extra), tmp_path)
        gaps[name] = np.abs(rigid.frequencies_hz / dist.frequencies_hz - 1).max()
        assert (rigid.frequencies_hz >= dist.frequencies_hz * (1 - 1e-12)).all()  # a constraint
    assert gaps["plain"] > 1e-3 and gaps["stiff"] < 1e-4, gaps


def test_mass_properties_and_orthonormal_modes(tmp_path):
    """The body's rigid mass matrix gains exactly the point's (shifted to the origin),
    the modes are M-orthonormal on the free DOFs and follow the point rigidly on the
    region."""
    from pipeline.fe.added_mass import point_rigid_mass
    from pipeline.fe.body import skew
    from pipeline.fe.space import region_nodes

    fe, modes = solve(config(), tmp_path)
    plain, _ = solve(config(masses=[]), tmp_path)
    S = np.eye(6)
    S[:3, 3:] = -skew(np.asarray(POINT))  # twist at the origin -> motion of the point
    want = plain.props.rigid_mass + S.T @ point_rigid_mass(MASS, INERTIA) @ S
    np.testing.assert_allclose(fe.props.rigid_mass, want, rtol=0,
                               atol=1e-12 * np.abs(want).max())
    assert abs(fe.props.mass - plain.props.mass - MASS) <= 1e-12 * fe.props.mass
    Phi = modes.shapes
    np.testing.assert_allclose(Phi.T @ (fe.M @ Phi), np.eye(Phi.shape[1]), atol=1e-9)
    # each mode moves the region's nodes as one rigid body: a rigid fit leaves nothing
    nodes = region_nodes(fe.space, fe.regions["tip"])
    pos = np.full(fe.space.n_dofs, -1)
    pos[fe.free] = np.arange(fe.free.size)
    U = Phi[pos[(3 * nodes[:, None] + np.arange(3)).ravel()]]
    d = fe.space.node_points[nodes] - np.asarray(POINT)
    R = np.concatenate([np.hstack([np.eye(3), -skew(x)]) for x in d])
    fit = R @ np.linalg.lstsq(R, U, rcond=None)[0]
    assert np.abs(U - fit).max() <= 1e-10 * np.abs(U).max()


def test_cli_refuses_a_rigid_coupling_on_a_held_region(tmp_path):
    import yaml

    path = tmp_path / "rb.yaml"
    path.write_text(yaml.safe_dump(config(region="root")))
    out = tmp_path / "rb.h5"
    proc = subprocess.run([sys.executable, "-m", "pipeline", "run", str(path), "-o", str(out)],
                          capture_output=True, text=True)
    from pipeline.errors import RegionError

    assert proc.returncode == RegionError.exit_code, proc.stderr[-2000:]
    # the log of the mesh stage, then one error line (refused before K is assembled)
    lines = [line for line in proc.stderr.splitlines() if line.startswith("error")]
    assert len(lines) == 1 and "masses[0].region" in lines[0] and "held" in lines[0]
    assert not out.exists()


def test_cli_runs_a_rigid_tip_mass_end_to_end(tmp_path):
    from test_constraints import run_reduced_cli

    assert "rigid mass coupling" in run_reduced_cli(config(count=6), tmp_path)
    # the Exudyn export's matrices (the unconstrained body's) cannot carry the rigid
    # region: refused in one line, nothing written
    target = tmp_path / "rb_exudyn.npz"
    proc = subprocess.run([sys.executable, "-m", "pipeline", "export",
                           str(tmp_path / "reduced.h5"), "--to", "exudyn", "-o", str(target)],
                          capture_output=True, text=True)
    assert proc.returncode == 2, proc.stderr[-2000:]
    err = [line for line in proc.stderr.splitlines() if line.startswith("error")]
    assert len(err) == 1 and "masses[0].coupling" in err[0] and not target.exists()


def test_free_body_with_a_rigid_mass_keeps_six_rigid_modes(tmp_path):
    """No supports: the rigid coupling removes no rigid-body motion (they satisfy it), so
    the eigensolver on T^T K T, T^T M T finds six at 0 Hz, M-orthonormal with the rest."""
    fe, modes = solve(config(supports=[], count=8), tmp_path)
    assert modes.n_rigid == 6 and modes.frequencies_hz[6] > 100.0
    Phi = modes.shapes
    np.testing.assert_allclose(Phi.T @ (fe.M @ Phi), np.eye(8), atol=1e-9)


def test_the_factor_free_solver_runs_on_the_constrained_pencil(tmp_path):
    """``modes.method: multigrid`` (LOBPCG with the coarse space T^T P) and the factor
    path solve the same T^T K T, T^T M T: the frequencies agree to the solvers'
    tolerances (measured 9e-12; eigenvalue residuals of 1e-10 bound it at ~1e-10,
    asserted 1e-8)."""
    f = {}
    for method in ("factor", "multigrid"):
        raw = config()
        raw["modes"] = {"count": 4, "method": method}
        _, modes = solve(raw, tmp_path)
        assert (modes.stats["method"] == "multigrid-lobpcg") == (method == "multigrid")
        f[method] = modes.frequencies_hz
    np.testing.assert_allclose(f["multigrid"], f["factor"], rtol=1e-8)
