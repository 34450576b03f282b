"""Connection-point (hybrid-cantilever, 6x6) models: rigid-body properties, clamped modes,
participation factors, effective masses, residual mass and the state-space model.

Tolerances:
- Identities that hold exactly in exact arithmetic on the same matrices (D_P two ways,
  sums over ALL modes of a dense solve, G(0) = D_P, poles vs eigenvalues): round-off of
  double-precision dense linear algebra on matrices with condition ~1e6..1e9, so 1e-8
  relative (the issue's bound), 1e-10 where no eigen-solve is involved.
- D_P against the analytic box: the consistent P2 (and P1) mass integrates the quadratic
  integrands of R^T M R exactly on straight tetrahedra, so 1e-10 relative.
- Clamped modes from the RBE2 elimination against the pipeline's support condensation:
  the same eigenproblem reached by two routes (other orderings, other factors), so
  conftest.eigenvalue_rtol of the clamped pencil, 2 (tau + c eps lambda_max/lambda_1);
  the poles (square roots, dense eigvals of the well-separated modal 2x2 blocks) half of
  it plus 1e-12. Was a fixed 1e-8, below c eps lambda_max/lambda_1 for this K (~3e8).
- Frequency response of the multi-point model (all modes, undamped) against a direct
  solve of the full clamped system: 2 c eps cond(s^2 M + K) of the largest entry, cond of
  the test's own dense matrix at that s (was a fixed 1e-7, below 2 c eps cond when cond
  ~1e8).
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import scipy.linalg as sla
import scipy.sparse as sp

from conftest import (ALUMINIUM, assert_elementwise_within, assert_relative_within, build_model,
                      cond_eps, eigenvalue_rtol)
from pipeline.fe.body import rigid_body_modes, skew
from pipeline.store.schema import connection_datasets
from pipeline.reduce.connection import (check_residual_mass, connection_model,
                                        connection_model_from_modes, connection_statespace,
                                        effective_mass_table)
from pipeline.reduce.interfaces import (check_interface, interface_transformation,
                                        make_interface, make_interfaces, project, rbe3_matrix,
                                        rigid_properties_at, twist_transform)
from pipeline.errors import RegionError, SolverError
from pipeline.solve.eigen import solve_modes

L, H, W = 0.5, 0.02, 0.05


def conn(name, region, point, coupling="rigid"):
    return SimpleNamespace(name=name, region=region, point=point, coupling=coupling)


@pytest.fixture(scope="module")
def beam(tmp_path_factory):
    """The reference cantilever geometry, coarse (about 4.5k DOFs), unsupported."""
    return build_model(tmp_path_factory.mktemp("beam"), L, H, W, size=0.02, supports=())


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """A small P2 block for dense all-mode solves (under 1.5k DOFs)."""
    m = build_model(tmp_path_factory.mktemp("tiny"), 0.1, 0.02, 0.03, size=0.02, supports=())
    assert m.space.n_dofs < 1500
    return m


@pytest.fixture(scope="module")
def tiny_p1(tmp_path_factory):
    """A small P1 block (its row-sum lumped mass matrix is positive)."""
    return build_model(tmp_path_factory.mktemp("tiny1"), 0.1, 0.02, 0.03, size=0.01, order=1,
                       supports=())


# --------------------------------------------------------------------------- rigid body
def test_D_P_equals_tau_formula_and_the_analytic_box(beam):
    P = np.array([0.0, 0.003, 0.041])  # an arbitrary point, off every symmetry plane
    rp = rigid_properties_at(beam.M_full, beam.space.node_points, P)
    m = ALUMINIUM.rho * L * H * W
    G = np.array([L, H, W]) / 2
    I_G = m / 12 * np.diag([H**2 + W**2, L**2 + W**2, L**2 + H**2])
    np.testing.assert_allclose(rp.mass, m, rtol=1e-10)
    np.testing.assert_allclose(rp.center_of_mass, G, rtol=1e-10)
    np.testing.assert_allclose(rp.inertia_G, I_G, rtol=1e-10, atol=1e-10 * I_G.max())
    # D_P = R_P^T M R_P (as computed) equals tau_GP^T diag(m I, I_G) tau_GP
    tau = twist_transform(P, rp.center_of_mass)  # tau_GP of theory.md §5
    np.testing.assert_allclose(tau[0:3, 3:6], skew(P - rp.center_of_mass))
    D_formula = tau.T @ sla.block_diag(m * np.eye(3), rp.inertia_G) @ tau
    np.testing.assert_allclose(rp.D_P, D_formula, rtol=0, atol=1e-10 * np.abs(D_formula).max())
    # and the parallel-axis theorem for the inertia at P
    d = rp.center_of_mass - P
    np.testing.assert_allclose(rp.inertia_P, I_G + m * (d @ d * np.eye(3) - np.outer(d, d)),
                               atol=1e-10 * I_G.max())


def test_twist_transform_moves_a_rigid_velocity():
    A, B = np.array([0.1, -0.2, 0.3]), np.array([-0.4, 0.5, 0.25])
    v, w = np.array([1.0, 2.0, -3.0]), np.array([0.3, -0.7, 0.2])
    out = twist_transform(A, B) @ np.r_[v, w]
    np.testing.assert_allclose(out[:3], v + np.cross(w, B - A))
    np.testing.assert_allclose(out[3:], w)


# --------------------------------------------------------------------------- all modes
def _all_modes_rigid_root(model):
    root = make_interface(model.space, model.regions, "root", "root", [0, 0.0, 0.0])
    cm = connection_model(model.space, model.K_full, model.M_full, [root], None,
                          backend="dense")
    free = np.setdiff1d(np.arange(model.space.n_dofs),
                        (3 * root.nodes[:, None] + np.arange(3)).ravel())
    return root, cm, free


def test_effective_masses_over_all_modes_lumped_mass(tiny_p1):
    """With a diagonal (lumped) mass matrix, the effective masses summed over ALL clamped
    modes equal the rigid mass matrix restricted to the free nodes, R_f^T M_ff R_f."""
    Ml = sp.diags(np.asarray(tiny_p1.M_full.sum(axis=1)).ravel()).tocsr()
    assert Ml.diagonal().min() > 0
    model = SimpleNamespace(space=tiny_p1.space, regions=tiny_p1.regions,
                            K_full=tiny_p1.K_full, M_full=Ml)
    root, cm, free = _all_modes_rigid_root(model)
    assert cm.omega2.size == free.size  # every mode of the clamped body
    R = rigid_body_modes(tiny_p1.space.node_points, root.point)
    expected = R[free].T @ (Ml[free][:, free] @ R[free])
    summed = cm.L_P.T @ cm.L_P
    np.testing.assert_allclose(summed, expected, rtol=0, atol=1e-8 * np.abs(expected).max())
    np.testing.assert_allclose(cm.effective_mass.sum(0), np.diag(expected), rtol=1e-8)
    # the residual mass is then exactly the rigid mass of the region's own nodes
    rr = np.setdiff1d(np.arange(tiny_p1.space.n_dofs), free)
    np.testing.assert_allclose(cm.D_P0, R[rr].T @ (Ml[rr][:, rr] @ R[rr]),
                               atol=1e-8 * np.abs(cm.D_P).max())


def test_effective_masses_over_all_modes_consistent_mass(tiny):
    """Consistent mass: sum_i L_i^T L_i = (M R)_f^T M_ff^-1 (M R)_f, the rigid mass of the
    free nodes including their mass coupling with the region; D_P0 is the Schur
    complement of the mass at the region (positive definite); fractions rise."""
    root, cm, free = _all_modes_rigid_root(tiny)
    R = rigid_body_modes(tiny.space.node_points, root.point)
    MR = (tiny.M_full @ R)[free]
    Mff = tiny.M_full[free][:, free].toarray()
    expected = MR.T @ np.linalg.solve(Mff, MR)
    np.testing.assert_allclose(cm.L_P.T @ cm.L_P, expected, rtol=0,
                               atol=1e-8 * np.abs(expected).max())
    frac = cm.effective_mass_cumulative_fraction
    assert np.all(np.diff(frac, axis=0) >= -1e-15)
    assert np.all(frac[-1] < 1.0)  # the region's own mass is never reached by a mode
    eig = np.linalg.eigvalsh(cm.D_P0)
    assert eig.min() > 0, eig
    np.testing.assert_allclose(cm.D_P0, cm.D_P0.T, atol=0)


def test_truncated_model_and_refusal_of_a_non_spd_residual_mass(beam):
    root = make_interface(beam.space, beam.regions, "root", "root", [0, 0, 0])
    cm = connection_model(beam.space, beam.K_full, beam.M_full, [root], 8, backend="superlu")
    assert np.linalg.eigvalsh(cm.D_P0).min() > 0
    frac = cm.effective_mass_cumulative_fraction
    assert np.all(np.diff(frac, axis=0) >= 0)
    # modes scaled wrongly (not M-orthonormal) give an indefinite D_P0: refused
    with pytest.raises(SolverError, match="root.*not symmetric positive definite|root.*non-pos"):
        connection_model_from_modes(root, beam.space.node_points, beam.M_full,
                                    3.0 * cm.shapes, cm.omega2)
    with pytest.raises(SolverError, match="D_P0"):
        check_residual_mass(np.diag([1.0, 1, 1, 1, 1, -1e-3]), "root")


# --------------------------------------------------------------------------- 6x6 model
def test_statespace_dc_gain_is_D_P_and_poles_are_the_clamped_modes(beam):
    from pipeline.config import Support
    from pipeline.fe.assemble import restrict
    from pipeline.fe.regions import fixed_dofs, free_dofs

    root = make_interface(beam.space, beam.regions, "root", "root", [0, 0.01, 0.025])
    cm = connection_model(beam.space, beam.K_full, beam.M_full, [root], 8, backend="superlu")
    # the same clamped modes through the pipeline's own support condensation
    fixed = fixed_dofs(beam.space, beam.regions, [Support("root")], False)
    free = free_dofs(beam.space.n_dofs, fixed)
    K, M = restrict(beam.K_full, free), restrict(beam.M_full, free)
    ref = solve_modes(K, M, 8, backend="superlu")
    rtol = eigenvalue_rtol(K, M)
    assert_elementwise_within(cm.omega2, ref.omega2, rtol, "test_connection::clamped_omega2")
    xi = np.linspace(0.01, 0.05, 8)
    ss = connection_statespace(cm, xi)
    assert ss.A.shape == (16, 16) and ss.B.shape == (16, 6) and ss.D.shape == (6, 6)
    # zero frequency: the body is a rigid body, W_P = D_P a_P
    np.testing.assert_allclose(ss.dc_gain(), cm.D_P, rtol=0, atol=1e-10 * np.abs(cm.D_P).max())
    np.testing.assert_allclose(ss.D, cm.D_P0)
    # poles: -xi w +/- i w sqrt(1 - xi^2) of every clamped mode
    poles = np.linalg.eigvals(ss.A)
    w = np.sqrt(ref.omega2)
    expected = np.concatenate([-xi * w + 1j * w * np.sqrt(1 - xi**2),
                               -xi * w - 1j * w * np.sqrt(1 - xi**2)])
    got = np.sort_complex(poles)
    assert_elementwise_within(got, np.sort_complex(expected), 0.5 * rtol + 1e-12,
                              "test_connection::poles")
    assert ss.input_names[0] == "root.ax" and ss.output_names[3] == "root.Tx"
    assert ss.output_units[:4] == ("N", "N", "N", "N m")


def test_child_point_model_matches_a_direct_frequency_response(tiny):
    """Parent root (rigid) + child tip (distributing): G(s) of the state-space model with
    every clamped mode equals the direct solve of the clamped FE system at s = i w."""
    ifs = make_interfaces(tiny.space, tiny.regions,
                          [conn("root", "root", [0, 0.01, 0.015]),
                           conn("tip", "tip", [0.1, 0.01, 0.015], "distributing")])
    cm = connection_model(tiny.space, tiny.K_full, tiny.M_full, ifs, None, backend="dense")
    ss = connection_statespace(cm, 0.0)
    assert ss.B.shape[1] == 12 and ss.C.shape[0] == 12
    assert ss.output_names[6:9] == ("tip.ax", "tip.ay", "tip.az")
    # direct: coordinates [z; q_tip] with q_root prescribed
    tr = interface_transformation(tiny.space.n_dofs, tiny.space.node_points, (ifs[1], ifs[0]))
    n_c = tr.n_z + 6
    Tc = tr.T[:, :n_c]
    Kc = project(tiny.K_full, Tc).toarray()
    Mc = project(tiny.M_full, Tc).toarray()
    R_P = rigid_body_modes(tiny.space.node_points, ifs[0].point)
    M_TR = np.asarray(Tc.T @ (tiny.M_full @ R_P))
    tau = twist_transform(ifs[0].point, ifs[1].point)
    s = 1j * 2 * np.pi * 700.0  # between resonances of this small block
    rng = np.random.default_rng(7)
    u = rng.standard_normal(12)
    a_P, W_C = u[:6], u[6:]
    F = np.zeros(n_c)
    F[tr.n_z:] = W_C
    X = np.linalg.solve(s**2 * Mc + Kc, F - M_TR @ a_P)
    W_P = cm.D_P @ a_P + s**2 * (M_TR.T @ X) - tau.T @ W_C
    a_C = tau @ a_P + s**2 * X[tr.n_z:]
    direct = np.concatenate([W_P, a_C])
    model = ss.frequency_response(s) @ u
    # two routes through (s^2 M + K) (a dense solve here, the all-mode modal sum there):
    # each with a forward error c eps cond(s^2 M + K), cond of this very matrix
    bound = 2 * cond_eps(s**2 * Mc + Kc)
    assert_relative_within(model, direct, bound, "test_connection::frequency_response")
    # statics: a wrench at the child is carried to the parent; no acceleration
    G0 = ss.dc_gain()
    np.testing.assert_allclose(G0[:6, 6:], -tau.T, atol=1e-8)
    np.testing.assert_allclose(G0[6:, 6:], 0, atol=1e-8 * np.abs(ss.D[6:, 6:]).max())
    np.testing.assert_allclose(G0[6:, :6], tau, atol=1e-8)


def test_distributing_coupling_does_not_stiffen(beam):
    ifs = [make_interface(beam.space, beam.regions, "root", "root", [0, 0.01, 0.025], c)
           for c in ("rigid", "distributing")]
    rigid, dist = (connection_model(beam.space, beam.K_full, beam.M_full, [i], 6,
                                    backend="superlu") for i in ifs)
    assert np.all(dist.omega2 < rigid.omega2)
    np.testing.assert_allclose(dist.D_P, rigid.D_P, rtol=1e-12)
    # RBE3: the region deforms in the clamped modes, but its weighted rigid fit is zero
    G = rbe3_matrix(ifs[1], beam.space.node_points)
    dofs = (3 * ifs[1].nodes[:, None] + np.arange(3)).ravel()
    assert np.abs(dist.shapes[dofs]).max() > 1e-3 * np.abs(dist.shapes).max()
    np.testing.assert_allclose(G @ dist.shapes[dofs], 0, atol=1e-10 * np.abs(dist.shapes).max())
    R = rigid_body_modes(beam.space.node_points[ifs[1].nodes], ifs[1].point)
    np.testing.assert_allclose(G @ R, np.eye(6), atol=1e-10)
    # RBE2: the region does not move at all
    np.testing.assert_allclose(rigid.shapes[dofs], 0, atol=0)


# --------------------------------------------------------------------------- refusals
def test_ill_posed_interfaces_are_refused_naming_the_region(beam):
    with pytest.raises(RegionError, match="region 'bottom'.*overlaps region 'root'"):
        make_interfaces(beam.space, beam.regions,
                        [conn("root", "root", [0, 0, 0]), conn("floor", "bottom", [0.25, 0, 0])])
    with pytest.raises(RegionError, match="'root'.*same region"):
        make_interfaces(beam.space, beam.regions,
                        [conn("a", "root", [0, 0, 0]), conn("b", "root", [0, 0, 0])])
    with pytest.raises(RegionError, match="region 'nowhere' does not exist"):
        make_interface(beam.space, beam.regions, "x", "nowhere", [0, 0, 0])
    # a region whose nodes lie on a line cannot carry rotations about that line
    root = make_interface(beam.space, beam.regions, "root", "root", [0, 0, 0])
    x = beam.space.node_points
    on_edge = root.nodes[(np.abs(x[root.nodes, 1]) < 1e-12) & (np.abs(x[root.nodes, 0]) < 1e-12)]
    assert on_edge.size >= 2
    line = type(root)("edge", "root_edge", root.point, "rigid", on_edge, np.ones(on_edge.size))
    with pytest.raises(RegionError, match="region 'root_edge'.*line"):
        check_interface(line, x, "connections[0]")


def test_datasets_carry_units_and_the_table_prints(beam):
    ifs = make_interfaces(beam.space, beam.regions, [conn("root", "root", [0, 0, 0]),
                                                     conn("tip", "tip", [L, 0.01, 0.025])])
    cm = connection_model(beam.space, beam.K_full, beam.M_full, ifs, 4, backend="superlu")
    tree = connection_datasets(cm, connection_statespace(cm, 0.02), include_shapes=True)
    for key in ("D_P", "L_P", "D_P0", "omega", "damping_ratio", "effective_mass",
                "effective_mass_cumulative_fraction", "statespace/A", "statespace/B",
                "statespace/C", "statespace/D", "statespace/input_names",
                "statespace/output_names", "statespace/state_names", "shapes"):
        assert f"connections/root/{key}" in tree, key
    for key, ds in tree.items():
        assert isinstance(ds.units, str), key
        assert ds.units or key.endswith(("_names", "_units")), key
    assert tree["connections/root/shapes"].data.shape == (beam.space.n_nodes, 3, 4)
    lines = effective_mass_table(cm)
    assert len(lines) == 2 + 4 + 2 and "cum_y" in lines[0]


def test_one_call_builders_write_a_valid_file(beam, tmp_path):
    """The integration entry points with the config's Connection records: every dataset
    they return is written by pipeline.store.h5file and carries its units."""
    from pipeline.config import Connection
    from pipeline.reduce.connection import build_connection_model
    from pipeline.reduce.craig_bampton import build_craig_bampton
    from pipeline.reduce.ffrf import build_ffrf
    from pipeline.reduce.modal import DampingSpec
    from pipeline.store.h5file import open_verified, write_file
    from pipeline.store.schema import craig_bampton_datasets, ffrf_datasets

    conns = (Connection("root", "root", (0.0, 0.0, 0.0), "rigid"),
             Connection("tip", "tip", (L, 0.01, 0.025), "distributing"))
    model, ss = build_connection_model(beam.space, beam.regions, beam.K_full,
                                             beam.M_full, conns, 4,
                                             DampingSpec("uniform", ratio=0.02),
                                             backend="superlu")
    tree = connection_datasets(model, ss)
    np.testing.assert_allclose(ss.attrs["damping_ratio"], 0.02)
    cb = build_craig_bampton(beam.space, beam.regions, beam.K_full, beam.M_full,
                             conns, 4, backend="superlu")
    cb_tree = craig_bampton_datasets(cb)
    inv = build_ffrf(beam.M_full, beam.K_full, beam.space.node_points, cb=cb)
    ffrf_tree = ffrf_datasets(inv)
    assert inv.n == 6 + 4 and "tip" in inv.basis_kind + inv.coordinate_names[0]
    path = write_file(tmp_path / "c.h5", {**tree, **cb_tree, **ffrf_tree})
    with open_verified(path) as h5:
        names = []
        h5.visititems(lambda n, o: names.append(n) if hasattr(o, "dtype") else None)
        assert all("units" in h5[n].attrs for n in names)
        assert h5["connections/root/statespace/A"].shape == (8, 8)
        assert h5["connections/root/statespace/B"].shape == (8, 12)
        assert h5["craig_bampton/M"].shape == (16, 16)
        assert h5["ffrf/inertia_second_order"].shape == (10, 10, 3, 3)
