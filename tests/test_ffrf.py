"""Floating-frame inertia invariants, checked against their definitions evaluated
directly on the deformed / moving nodes.

Tolerances: every check compares two evaluations of the same finite sums (the invariants
are exact polynomial expansions in q), so round-off only: 1e-10 relative to the largest
entry. The analytic box is integrated exactly by the consistent mass (1e-10). Free-free
modes carry no momentum (M-orthogonal to the rigid modes): their couplings vanish to the
eigensolver's orthogonality, 1e-8 relative to sqrt(m) (resp. sqrt(m) times the body size).
The modal stiffness Psi^T K Psi against the solver's omega^2: the solver's eigenvalues are
within tau + c eps lambda_max / lambda_7 of the Rayleigh quotients the projection forms
(conftest.eigenvalue_rtol with one route, the six zero eigenvalues skipped); was 1e-8.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from conftest import ALUMINIUM, assert_elementwise_within, build_model, eigenvalue_rtol
from pipeline.fe.body import rigid_body_modes
from pipeline.reduce.interfaces import make_interfaces
from pipeline.reduce.craig_bampton import craig_bampton
from pipeline.reduce.ffrf import craig_bampton_basis, ffrf_invariants, free_free_basis
from pipeline.store.schema import ffrf_datasets
from pipeline.solve.eigen import solve_modes

L, H, W = 0.5, 0.02, 0.05


@pytest.fixture(scope="module")
def beam(tmp_path_factory):
    return build_model(tmp_path_factory.mktemp("ffrf"), L, H, W, size=0.025, supports=())


@pytest.fixture(scope="module")
def free_modes(beam):
    return solve_modes(beam.K_full, beam.M_full, 12, supported=False, backend="superlu")


def _rel(a, b):
    return np.abs(np.asarray(a) - np.asarray(b)).max() / np.abs(np.asarray(b)).max()


def _rigid_mass(M, points):
    R = rigid_body_modes(points)
    return R.T @ (M @ R)


def test_rigid_invariants_match_the_analytic_box(beam, free_modes):
    Psi, keep = free_free_basis(free_modes.shapes, free_modes.omega2, free_modes.n_rigid)
    assert keep[0] == 6 and Psi.shape[1] == 6
    inv = ffrf_invariants(beam.M_full, beam.space.node_points, Psi, beam.K_full)
    m = ALUMINIUM.rho * L * H * W
    c = np.array([L, H, W]) / 2
    I_G = m / 12 * np.diag([H**2 + W**2, L**2 + W**2, L**2 + H**2])
    J0 = I_G + m * (c @ c * np.eye(3) - np.outer(c, c))
    assert abs(inv.mass / m - 1) < 1e-10
    assert _rel(inv.first_moment, m * c) < 1e-10
    assert _rel(inv.inertia, J0) < 1e-10
    np.testing.assert_allclose(inv.modal_mass, np.eye(6), atol=1e-10)
    assert_elementwise_within(np.diag(inv.modal_stiffness), free_modes.omega2[6:],
                              eigenvalue_rtol(beam.K_full, beam.M_full, n_zero=6, routes=1),
                              "test_ffrf::modal_stiffness")


def test_free_free_modes_carry_no_momentum(beam, free_modes):
    Psi, _ = free_free_basis(free_modes.shapes, free_modes.omega2, free_modes.n_rigid)
    inv = ffrf_invariants(beam.M_full, beam.space.node_points, Psi, origin=[L / 2, H / 2, W / 2])
    m = inv.mass
    assert np.abs(inv.translational_coupling).max() < 1e-8 * np.sqrt(m)
    assert np.abs(inv.rotational_coupling).max() < 1e-8 * np.sqrt(m) * L
    np.testing.assert_allclose(inv.center_of_mass, 0, atol=1e-12)


def test_deflected_inertia_and_angular_momentum_match_their_definitions(beam, free_modes):
    """J(q) = J0 + J1 q + q J2 q equals the inertia of the deflected nodes, and the angular
    momentum of the elastic motion, int rho (x + u) x u', equals (C_r + q.G) q'."""
    Psi, _ = free_free_basis(free_modes.shapes, free_modes.omega2, free_modes.n_rigid)
    O = np.array([0.0, 0.004, -0.01])
    inv = ffrf_invariants(beam.M_full, beam.space.node_points, Psi, origin=O)
    rng = np.random.default_rng(3)
    q = 0.02 * rng.standard_normal(Psi.shape[1])  # m kg^1/2: centimetre-scale deflections
    qd = rng.standard_normal(Psi.shape[1])
    x = beam.space.node_points - O
    u = (Psi @ q).reshape(-1, 3)
    J_direct = _rigid_mass(beam.M_full, x + u)[3:, 3:]
    assert _rel(inv.inertia_at(q), J_direct) < 1e-10
    assert _rel(inv.inertia_at(q), inv.inertia) > 1e-4  # the deflection matters here
    # angular momentum about O: R_r(x+u)^T M u'
    R = rigid_body_modes(x + u)
    h_direct = R[:, 3:].T @ (beam.M_full @ (Psi @ qd))
    h_inv = (inv.rotational_coupling + np.einsum("k,klc->cl", q, inv.gyroscopic_coupling)) @ qd
    assert _rel(h_inv, h_direct) < 1e-10
    # structure: G_kl = -G_lk, J2_kl = J2_lk^T, J1_k symmetric
    G = inv.gyroscopic_coupling
    np.testing.assert_allclose(G, -G.transpose(1, 0, 2), atol=1e-12 * np.abs(G).max())
    J2 = inv.inertia_second_order
    np.testing.assert_allclose(J2, J2.transpose(1, 0, 3, 2), atol=1e-12 * np.abs(J2).max())
    J1 = inv.inertia_first_order
    np.testing.assert_allclose(J1, J1.transpose(0, 2, 1), atol=1e-12 * np.abs(J1).max())


def test_craig_bampton_basis_and_datasets(beam):
    ifs = make_interfaces(beam.space, beam.regions,
                          [SimpleNamespace(name="root", region="root", point=[0, 0.01, 0.025],
                                           coupling="rigid"),
                           SimpleNamespace(name="tip", region="tip", point=[L, 0.01, 0.025],
                                           coupling="distributing")])
    cb = craig_bampton(beam.space, beam.K_full, beam.M_full, ifs, 4, backend="superlu")
    Psi, names, units = craig_bampton_basis(cb, "root")
    assert names[:2] == ["tip.x", "tip.y"] and names[-1] == "mode_4" and len(names) == 10
    inv = ffrf_invariants(beam.M_full, beam.space.node_points, Psi, beam.K_full,
                          basis_kind="craig_bampton", coordinate_names=names,
                          coordinate_units=units)
    # the reduced matrices of that basis are the CB matrices without the root rows
    K, M, _ = cb.constrained(["root"])
    assert _rel(inv.modal_mass, M) < 1e-10 and _rel(inv.modal_stiffness, K) < 1e-8
    tree = ffrf_datasets(inv, include_basis=True)
    assert tree["ffrf/modal_mass"].units == "mixed"
    assert tree["ffrf/modal_mass"].attrs["units_rule"] == "kg m^2 / (u_k u_l)"
    assert tree["ffrf/mass"].units == "kg" and tree["ffrf/inertia"].units == "kg m^2"
    modal = ffrf_datasets(ffrf_invariants(beam.M_full, beam.space.node_points, cb.shapes[:, 12:]))
    assert modal["ffrf/translational_coupling"].units == "kg^1/2"
    assert modal["ffrf/inertia_second_order"].units == "1"
    for key, ds in {**tree, **modal}.items():
        assert isinstance(ds.units, str) and (ds.units or key.endswith("_names")), key
