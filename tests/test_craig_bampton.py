"""Craig-Bampton reduction: fixed-interface modes, static constraint modes, labels,
refusal of ill-posed interface sets.

Tolerances:
- One root interface: the fixed-interface problem IS the clamped problem (same matrix
  reached by two routes, other orderings and factorisations), so its eigenvalues agree
  within conftest.eigenvalue_rtol = 2 (tau + c eps lambda_max/lambda_1) (frequencies:
  half of it); clamping the reduced model's interface rows gives diag(omega^2) back to
  round-off of the small projection (1e-8 of the largest, M = I to 1e-10).
- Constraint modes of a single interface are the rigid-body motions: a sparse static solve
  with the clamped K, forward error c eps cond(K) relative (conftest.cond_eps; was a
  fixed 1e-8, cond(K) ~ 1e6 here).
- Ritz from above: the CB frequency may fall below the free-free one only by the two
  solves' error, 0.5 eigenvalue_rtol of the free pencil (six zero eigenvalues skipped).
- Root + tip: Craig-Bampton is a Ritz approximation of the free-free modes from above;
  with 20 fixed-interface modes (up to about 1.5x the highest free-free frequency
  compared, the usual rule for a CB frequency range) the eight lowest elastic modes of the
  0.02 m mesh come within 0.5%; the issue's bound is 1%.
- K_cb is block diagonal (static modes are K-orthogonal to the fixed-interface modes) to
  1e-8 of its largest entry.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from conftest import (assert_elementwise_within, assert_relative_within, build_model,
                      cond_eps, eigenvalue_rtol, record_tolerance)
from pipeline.fe.body import rigid_body_modes
from pipeline.reduce.interfaces import make_interfaces
from pipeline.reduce.craig_bampton import craig_bampton
from pipeline.store.schema import craig_bampton_datasets
from pipeline.errors import RegionError
from pipeline.solve.eigen import solve_modes

L, H, W = 0.5, 0.02, 0.05


def conn(name, region, point, coupling="rigid"):
    return SimpleNamespace(name=name, region=region, point=point, coupling=coupling)


@pytest.fixture(scope="module")
def beam(tmp_path_factory):
    return build_model(tmp_path_factory.mktemp("cb"), L, H, W, size=0.02, supports=())


@pytest.fixture(scope="module")
def clamped(tmp_path_factory, beam):
    """The same mesh with the root clamped through the pipeline's supports."""
    from pipeline.fe.assemble import restrict
    from pipeline.config import Support
    from pipeline.fe.regions import fixed_dofs, free_dofs

    fixed = fixed_dofs(beam.space, beam.regions, [Support("root")], False)
    free = free_dofs(beam.space.n_dofs, fixed)
    K, M = restrict(beam.K_full, free), restrict(beam.M_full, free)
    return solve_modes(K, M, 8, backend="superlu"), {"eig_rtol": eigenvalue_rtol(K, M),
                                                      "cond_eps": cond_eps(K)}


@pytest.fixture(scope="module")
def free_free(beam):
    return (solve_modes(beam.K_full, beam.M_full, 14, supported=False, backend="superlu"),
            eigenvalue_rtol(beam.K_full, beam.M_full, n_zero=6))


def test_one_root_interface_reproduces_the_clamped_frequencies(beam, clamped):
    clamped, rounding = clamped
    ifs = make_interfaces(beam.space, beam.regions, [conn("root", "root", [0, 0.01, 0.025])])
    cb = craig_bampton(beam.space, beam.K_full, beam.M_full, ifs, 8, backend="superlu")
    rtol = rounding["eig_rtol"]  # two routes to the clamped eigenvalues
    assert_elementwise_within(cb.fixed_interface_omega2, clamped.omega2, rtol,
                              "test_craig_bampton::fixed_interface_omega2")
    # the reduced model with its interface clamped
    assert_elementwise_within(cb.frequencies_hz(["root"]), clamped.frequencies_hz, 0.5 * rtol,
                              "test_craig_bampton::constrained_frequencies")
    K, M, keep = cb.constrained(["root"])
    np.testing.assert_allclose(M, np.eye(8), atol=1e-10)
    np.testing.assert_allclose(K, np.diag(clamped.omega2), atol=1e-8 * clamped.omega2.max())
    # one interface: the constraint modes are the rigid-body motions about its point
    R = rigid_body_modes(beam.space.node_points, ifs[0].point)
    assert_relative_within(cb.shapes[:, :6], R, rounding["cond_eps"],
                           "test_craig_bampton::constraint_modes_are_rigid")
    # and the free reduced body has exactly six rigid-body modes
    f = cb.frequencies_hz()
    assert np.all(f[:6] == 0) and f[6] > 1.0
    assert cb.coordinate_names[:7] == ("root.x", "root.y", "root.z", "root.rx", "root.ry",
                                       "root.rz", "mode_1")
    assert cb.coordinate_units[:7] == ("m", "m", "m", "rad", "rad", "rad", "m kg^1/2")


@pytest.mark.parametrize("coupling", ["rigid", "distributing"])
def test_root_and_tip_interfaces_match_the_free_free_solve(beam, free_free, coupling):
    free_free, free_rtol = free_free
    ifs = make_interfaces(beam.space, beam.regions,
                          [conn("root", "root", [0, 0.01, 0.025], coupling),
                           conn("tip", "tip", [L, 0.01, 0.025], coupling)])
    cb = craig_bampton(beam.space, beam.K_full, beam.M_full, ifs, 20, backend="superlu")
    assert cb.M.shape == (32, 32)
    assert cb.coordinate_names[6:8] == ("tip.x", "tip.y") and cb.coordinate_names[-1] == "mode_20"
    f = cb.frequencies_hz()
    assert np.all(f[:6] == 0)
    full = free_free.frequencies_hz[6:14]
    assert cb.fixed_interface_frequencies_hz[-1] > 1.5 * full[-1]
    err = f[6:14] / full - 1
    assert np.all(np.abs(err) < 0.01), err
    # a Ritz approximation converges from above, up to the two solves' errors
    below = 0.5 * free_rtol
    record_tolerance("test_craig_bampton::ritz_from_above", max(0.0, -err.min()), below)
    assert np.all(err > -below), (err, below)
    # structure: K block diagonal, both matrices symmetric
    nb = cb.n_boundary
    coupling = np.abs(cb.K[:nb, nb:]).max() / np.abs(cb.K).max()
    record_tolerance("test_craig_bampton::K_block_diagonal", coupling, 1e-8)
    assert coupling < 1e-8
    np.testing.assert_allclose(cb.K, cb.K.T, atol=0)
    np.testing.assert_allclose(cb.M, cb.M.T, atol=0)
    # the rigid-body modes are in the basis: R_P = Psi tau exactly
    R = rigid_body_modes(beam.space.node_points, ifs[0].point)
    coef = np.linalg.lstsq(cb.shapes, R, rcond=None)[0]
    fit = np.abs(cb.shapes @ coef - R).max() / np.abs(R).max()
    record_tolerance("test_craig_bampton::rigid_in_span", fit, 1e-8)
    assert fit < 1e-8


def test_distributing_interfaces_are_softer_than_rigid_ones(beam):
    fs = {}
    for c in ("rigid", "distributing"):
        ifs = make_interfaces(beam.space, beam.regions,
                              [conn("root", "root", [0, 0.01, 0.025], c),
                               conn("tip", "tip", [L, 0.01, 0.025], c)])
        fs[c] = craig_bampton(beam.space, beam.K_full, beam.M_full, ifs, 6, backend="superlu")
    assert np.all(fs["distributing"].fixed_interface_omega2 < fs["rigid"].fixed_interface_omega2)


def test_ill_posed_interface_sets_are_refused_before_any_solve(beam, monkeypatch):
    import pipeline.reduce.connection as connection
    import pipeline.solve.eigen as modes

    def boom(*a, **k):
        raise AssertionError("an eigen-solve ran before the interfaces were checked")

    monkeypatch.setattr(modes, "solve_modes", boom)
    monkeypatch.setattr(connection, "clamped_modes", boom)
    with pytest.raises(RegionError, match="region 'top'.*overlaps region 'tip'"):
        make_interfaces(beam.space, beam.regions,
                        [conn("tip", "tip", [L, 0, 0]), conn("lid", "top", [0.25, H, 0])])
    # interfaces built one by one still get checked by craig_bampton itself
    a = make_interfaces(beam.space, beam.regions, [conn("tip", "tip", [L, 0, 0])])
    b = make_interfaces(beam.space, beam.regions, [conn("lid", "top", [0.25, H, 0])])
    with pytest.raises(RegionError, match="region 'top'.*overlaps region 'tip'"):
        craig_bampton(beam.space, beam.K_full, beam.M_full, a + b, 4)
    with pytest.raises(RegionError, match="at least one interface"):
        craig_bampton(beam.space, beam.K_full, beam.M_full, [], 4)


def test_datasets(beam):
    ifs = make_interfaces(beam.space, beam.regions, [conn("root", "root", [0, 0, 0])])
    cb = craig_bampton(beam.space, beam.K_full, beam.M_full, ifs, 3, backend="superlu")
    tree = craig_bampton_datasets(cb)
    for key in ("M", "K", "coordinate_names", "coordinate_units", "interface_names",
                "interface_points", "fixed_interface_frequencies_hz", "free_frequencies_hz",
                "shapes"):
        assert f"craig_bampton/{key}" in tree
    assert tree["craig_bampton/shapes"].data.shape == (beam.space.n_nodes, 3, 9)
    assert tree["craig_bampton/M"].attrs["coordinates"][-1] == "mode_3"
    for key, ds in tree.items():
        assert isinstance(ds.units, str) and (ds.units or "names" in key or "units" in key
                                              or "couplings" in key or "regions" in key), key
