"""Stress and strain from the FE model and the reduced model (pipeline.fe.strain, gauge
ports, the stress_modes group).

Tolerances:
- linear displacement fields: the P1/P2 strain of u = G x is exact, so element values,
  nodal recovery and gauges agree with sym(G) to round-off (1e-10 of |G|: a few hundred
  operations of eps on O(1) reference gradients);
- beam theory: the Saint-Venant flexure solution of an end-loaded prismatic cantilever has
  sigma_xx = P (L - x) y_c / I exactly away from the ends, so the mid-span difference is
  discretisation error only; P2 stresses converge as h^2 (a halving of h divides the
  error by >= 4) -- measured 1.4 % at h = 20 mm and 0.02 % at h = 10 mm;
- reduced static outputs against a separate full FE solve: both are K^-1 F through
  different factorisations, so |row . (x1 - x2)| <= ||row|| ||x|| * c cond(K) eps; we take
  c = 10 with cond(K) = lambda_max / lambda_min measured with eigsh;
- frequency response: the residual correction replaces each truncated mode k (term t_k =
  theta_k sigma_k / omega_k^2) by its static value; the error per mode is
  |t_k| |omega^2 - i omega gamma_k| / |omega_k^2 - omega^2 + i omega gamma_k|
  <= |t_k| (rho + omega alpha / omega_k^2 + omega beta) / (1 - rho), rho = omega^2 /
  omega_{n+1}^2, summed over the computed truncated modes plus the remainder
  |R - sum t_k| for the modes above them (bounded with the same factor, rho being largest
  for mode n + 1).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.sparse.linalg as spla

from conftest import ALUMINIUM, build_model
from pipeline.config import Port, Ports, config_from_dict, config_to_yaml
from pipeline.errors import ConfigError, RegionError
from pipeline.fe import strain
from pipeline.fe.ports import port_matrices
from pipeline.reduce.modal import DampingSpec, reduce_model

EPS = np.finfo(float).eps
L, H, B = 0.5, 0.02, 0.05
I_Z = B * H ** 3 / 12.0


def _hooke(eps_tensor):
    lam = ALUMINIUM.E * ALUMINIUM.nu / ((1 + ALUMINIUM.nu) * (1 - 2 * ALUMINIUM.nu))
    mu = ALUMINIUM.E / (2 * (1 + ALUMINIUM.nu))
    return lam * np.trace(eps_tensor) * np.eye(3) + 2 * mu * eps_tensor


@pytest.fixture(scope="module")
def coarse(tmp_path_factory):
    return build_model(tmp_path_factory.mktemp("stress"), size=0.02)


@pytest.fixture(scope="module")
def beam(tmp_path_factory):
    """The cantilever, P2 at h = 20 mm (4.5k DOFs), with its 10 lowest modes."""
    model = build_model(tmp_path_factory.mktemp("stress"), size=0.02)
    w2, phi = spla.eigsh(model.K, k=10, M=model.M, sigma=0.0)
    order = np.argsort(w2)
    return model, w2[order], phi[:, order]


@pytest.mark.parametrize("order", [1, 2])
def test_linear_field_gives_exact_strain_everywhere(tmp_path, order):
    model = build_model(tmp_path, size=0.02, order=order)
    space = model.space
    G = np.array([[1e-3, 2e-4, -1e-4], [3e-4, -3e-4, 5e-4], [1e-4, -2e-4, 2e-4]])
    U = (space.node_points @ G.T).ravel()
    e = 0.5 * (G + G.T)
    voigt = np.array([e[0, 0], e[1, 1], e[2, 2], 2 * e[1, 2], 2 * e[0, 2], 2 * e[0, 1]])
    tol = 1e-10 * np.abs(G).max()
    E, vol = strain.element_strain_operator(space)
    assert np.abs((E @ U).reshape(-1, 6) - voigt).max() < tol
    assert vol.sum() == pytest.approx(L * H * B, rel=1e-12)
    fields = strain.stress_fields(space, ALUMINIUM, U)
    assert np.abs(fields.strain[:, :, 0] - voigt).max() < tol
    sig = _hooke(e)
    sig_voigt = np.array([sig[0, 0], sig[1, 1], sig[2, 2], sig[1, 2], sig[0, 2], sig[0, 1]])
    assert np.abs(fields.stress[:, :, 0] - sig_voigt).max() < 1e-10 * np.abs(sig).max()
    d1, d2 = np.array([1.0, 1.0, 0.0]) / math.sqrt(2), np.array([0.0, 0.0, 1.0])
    expected = {"strain": (d1 @ e @ d1, d1 @ e @ d2), "stress": (d1 @ sig @ d1, d1 @ sig @ d2)}
    for kind, (normal, shear) in expected.items():
        scale = np.abs(sig).max() if kind == "stress" else np.abs(e).max()
        where = [dict(point=(0.2, 0.01, 0.02)),                    # at a point
                 dict(point=(0.2, 0.02, 0.02), radius=0.015),      # a disc on the surface
                 dict(point=(0.2, 0.02, 0.02), length=0.01, width=0.004),  # a grid
                 dict(triangles=model.regions["top"]),             # a boundary region
                 dict(point=(0.2, 0.02, 0.02), radius=0.015, average="volume"),  # a sphere
                 dict(triangles=model.regions["top"], average="volume")]
        for loc in where:
            row = strain.gauge_row(space, ALUMINIUM, kind, d1, **loc)
            assert row @ U == pytest.approx(normal, abs=1e-10 * scale)
            row = strain.gauge_row(space, ALUMINIUM, kind, d1, d2, **loc)
            assert row @ U == pytest.approx(shear, abs=1e-10 * scale)


@pytest.mark.parametrize("order", [1, 2])
def test_element_nodal_strains_equal_scikit_fems_basis(tmp_path, order):
    """The element-nodal strains from reference gradients times J^-1 equal scikit-fem's
    own basis evaluated at each element's nodes, for random (non-polynomial) nodal
    displacements: the same local node order, the same Voigt convention, to round-off."""
    space = build_model(tmp_path, size=0.02, order=order).space
    n_loc = space.element_nodes.shape[1]
    U = np.random.default_rng(7).standard_normal((space.n_dofs, 2))
    X = space.skfem_element().elem.doflocs.T
    for sel, values in strain._element_nodal_chunks(space, U):
        basis = strain._basis(space, sel, quadrature=(X, np.full(n_loc, 1.0 / n_loc)))
        G = strain._voigt_gradients(basis)  # (3 n_loc, 6, n_sel, n_loc points)
        ref = np.einsum("dkeq,des->eqks", G, U[basis.element_dofs])
        assert np.abs(values - ref).max() <= 1e-10 * np.abs(ref).max()


def test_nodal_strains_in_two_halves_equal_the_one_pass(coarse, monkeypatch):
    """Large meshes recover the nodal strains in two mesh halves side by side, then the
    layer between them (strain.THREADED_ELEMENTS): the same element contributions summed
    in another order, so equal to the one pass to round-off of a node's sum (at most
    ~30 terms: 64 eps of the largest value), with and without per-element laws."""
    space = coarse.space
    U = np.random.default_rng(11).standard_normal((space.n_dofs, 3))
    one = strain.nodal_strains(space, U)
    D = strain.isotropic_stiffness(ALUMINIUM)
    monkeypatch.setattr(strain, "THREADED_ELEMENTS", 1)
    halves = strain.nodal_strains(space, U)
    tol = 64 * np.finfo(float).eps * np.abs(one).max()
    assert np.abs(halves - one).max() <= tol

    def element_D(sel):
        return np.broadcast_to(D, (np.size(sel), 6, 6))

    halves_D = strain.nodal_strains(space, U, element_D)
    monkeypatch.setattr(strain, "THREADED_ELEMENTS", 10**12)
    one_D = strain.nodal_strains(space, U, element_D)
    assert np.abs(halves_D - one_D).max() <= 64 * np.finfo(float).eps * np.abs(one_D).max()


def test_gauge_outside_body_or_empty_is_refused(coarse):
    with pytest.raises(RegionError, match="outside the mesh"):
        strain.gauge_row(coarse.space, ALUMINIUM, "strain", (1, 0, 0), point=(1.0, 0, 0),
                         key="ports.outputs[1]")
    with pytest.raises(RegionError, match="no element centroid"):
        strain.gauge_row(coarse.space, ALUMINIUM, "strain", (1, 0, 0), point=(0.25, 0.02, 0),
                         radius=1e-5, average="volume")


def _tip_load(model):
    ports = Ports(inputs=(Port("f", "tip", "force", (0, -1, 0)),), outputs=())
    return port_matrices(model.space, model.regions, ports).F.toarray()[model.free]


def _static(model, F):
    u = np.zeros((model.space.n_dofs, F.shape[1]))
    u[model.free] = spla.splu(model.K.tocsc()).solve(F)
    return u


def test_bending_stress_matches_beam_theory_and_converges_as_h2(tmp_path):
    x = L / 2
    exact = 1.0 * (L - x) * (H / 2) / I_Z  # P = 1 N down: top fibre in tension, Pa
    errors, nodal_errors = [], []
    for size in (0.02, 0.01):
        model = build_model(tmp_path, size=size)
        u = _static(model, _tip_load(model))[:, 0]
        top = strain.gauge_row(model.space, ALUMINIUM, "stress", (1, 0, 0), point=(x, H, B / 2))
        bottom = strain.gauge_row(model.space, ALUMINIUM, "stress", (1, 0, 0),
                                  point=(x, 0.0, B / 2))
        errors.append(max(abs(top @ u / exact - 1), abs(bottom @ u / -exact - 1)))
        fields = strain.stress_fields(model.space, ALUMINIUM, u)
        p = model.space.node_points
        on_line = np.flatnonzero(np.isclose(p[:, 0], x) & np.isclose(p[:, 1], H))
        assert on_line.size
        nodal_errors.append(abs(fields.stress[on_line, 0, 0].mean() / exact - 1))
    # P2: second-order stresses; measured 1.4 % and 0.02 %
    assert errors[0] < 0.03 and errors[1] < 0.005
    assert errors[1] < errors[0] / 4
    # nodal recovery from element-nodal values: measured 0.16 % and 0.03 %
    assert max(nodal_errors) < 0.01


_COND: dict[int, tuple] = {}


def _cond(K):
    """cond_2(K) = lambda_max / lambda_min (K symmetric positive definite), cached per K."""
    if id(K) in _COND and _COND[id(K)][0] is K:  # the entry holds K: its id is not reused
        return _COND[id(K)][1]
    lmax = spla.eigsh(K, k=1, which="LM", return_eigenvectors=False, tol=1e-3)[0]
    lmin = spla.eigsh(K, k=1, sigma=0.0, return_eigenvectors=False)[0]
    _COND[id(K)] = (K, lmax / lmin)
    return lmax / lmin


GAUGES = (Port("tip_y", "tip", "displacement", (0, 1, 0)),
          Port("root_gauge", "", "strain", (1, 0, 0), point=(0.02, H, B / 2), radius=0.01),
          Port("mid_sxx", "", "stress", (1, 0, 0), point=(L / 2, H, B / 2)),
          Port("top_sxx", "top", "stress", (1, 0, 0)),
          Port("mid_shear", "", "stress", (1, 0, 0), (0, 1, 0), point=(L / 2, H / 2, B / 2)))


def _rows(model):
    ports = Ports(inputs=(Port("f", "tip", "force", (0, -1, 0)),), outputs=GAUGES)
    pm = port_matrices(model.space, model.regions, ports, material=ALUMINIUM)
    return pm.F.toarray()[model.free], pm.T[:, model.free]


@pytest.mark.parametrize("correction", ["residual", "augment"])
def test_reduced_static_stress_equals_full_fe(beam, correction):
    model, w2, phi = beam
    F, T = _rows(model)
    reduced = reduce_model(model.K, model.M, phi, w2, F, T, 4, DampingSpec("uniform", 0.02),
                           correction, ["f"], [p.name for p in GAUGES])
    x = spla.spsolve(model.K.tocsc(), F[:, 0])  # a different factorisation (SuperLU COLAMD)
    full = T @ x
    bound = 10 * _cond(model.K) * EPS * np.linalg.norm(x) * \
        np.asarray(np.sqrt(T.multiply(T).sum(axis=1))).ravel()
    dc = reduced.dc_gain_position[:, 0]
    assert np.all(np.abs(dc - full) <= bound), (dc, full, bound)
    # and the values are not trivially small: beam theory at mid-span within 3 % (the
    # discretisation error at h = 20 mm, test_bending_stress_matches_beam_theory...)
    assert dc[2] == pytest.approx((L - L / 2) * (H / 2) / I_Z, rel=0.03)


def test_stress_needs_more_modes_than_displacement_without_correction(beam):
    """Static error of the uncorrected model vs the number of modes: stresses converge
    slower than the tip displacement (local high-mode content)."""
    model, w2, phi = beam
    F, T = _rows(model)
    full = T @ spla.spsolve(model.K.tocsc(), F[:, 0])
    # the uncorrected model's DC gain with n modes is sum_{k<=n} theta_k sigma_k / omega_k^2
    partial = np.cumsum((T @ phi) * (phi.T @ F[:, 0]) / w2, axis=1)  # (n_y, 10)
    r = reduce_model(model.K, model.M, phi, w2, F, T, 4, DampingSpec("uniform", 0.02),
                     "none", ["f"], [p.name for p in GAUGES])
    assert r.dc_gain_position[:, 0] == pytest.approx(partial[:, 3], rel=1e-10)
    err = list(np.abs(partial / full[:, None] - 1).T)
    err = np.array(err)  # (n_modes, n_outputs)
    need = [int(np.argmax(err[:, j] < 0.01)) + 1 if (err[:, j] < 0.01).any() else 99
            for j in range(len(GAUGES))]
    # measured (h = 10 mm): tip displacement 3 % with 1 mode, 0.5 % with 3; root strain
    # gauge 12 % / 3.3 %, 1 % first at 8 modes; mid-span sigma_xx 1 % first at ~15 modes
    # (30 computed), the shear stress on the neutral axis 3 % at 30 modes
    assert need[0] <= 3
    assert all(need[j] > need[0] for j in range(1, len(GAUGES)))
    assert np.all(err[3, 1:] > 5 * err[3, 0])


def test_stress_frequency_response_matches_full_harmonic_solve(beam):
    model, w2, phi = beam
    F, T = _rows(model)
    alpha, beta = 5.0, 1e-6  # Rayleigh: C = alpha M + beta K (modal: 2 xi w = alpha + beta w^2)
    n = 4
    reduced = reduce_model(model.K, model.M, phi, w2, F, T, n,
                           DampingSpec("rayleigh", alpha=alpha, beta=beta), "residual", ["f"],
                           [p.name for p in GAUGES])
    ss = reduced.statespace
    rows = ss.output_rows("position")
    Kc, Mc = model.K.tocsc(), model.M.tocsc()
    C = alpha * Mc + beta * Kc
    theta, sigma = T @ phi, phi.T @ F[:, 0]
    t = theta * sigma / w2  # (n_y, 10): static share of each computed mode
    tail = reduced.residual[:, 0] - t[:, n:].sum(axis=1)
    w_next = math.sqrt(w2[n])
    for f_hz in (20.0, 150.0, 300.0, 700.0):  # below the filter cutoffs in use, off resonance
        w = 2 * math.pi * f_hz
        x = spla.spsolve((Kc - w ** 2 * Mc + 1j * w * C).tocsc(), F[:, 0].astype(complex))
        full = T @ x
        G = ss.C[rows] @ np.linalg.solve(1j * w * np.eye(ss.n_states) - ss.A, ss.B[:, 0]) \
            + ss.D[rows, 0]
        rho = w ** 2 / w_next ** 2
        factor = (rho + w * alpha / w_next ** 2 + w * beta) / (1 - rho)
        bound = factor * (np.abs(t[:, n:]).sum(axis=1) + np.abs(tail)) + 1e-9 * np.abs(full)
        assert np.all(np.abs(G - full) <= bound), (f_hz, np.abs(G - full), bound)


# --------------------------------------------------------------------------- config
def _cfg(outputs):
    return {"name": "g", "geometry": {"kind": "box", "length": L, "height": H, "depth": B},
            "mesh": {"order": 2, "size": 0.01}, "material": {"E": 69e9, "nu": 0.33, "rho": 2700},
            "supports": [{"region": "root", "fix": "all"}],
            "ports": {"inputs": [{"name": "f", "region": "tip", "kind": "force",
                                  "direction": [0, -1, 0]}], "outputs": outputs}}


def test_gauge_ports_parse_and_round_trip():
    outputs = [{"name": "g1", "kind": "strain", "point": [0.1, 0.02, 0.025], "radius": 0.004,
                "direction": [1, 0, 0]},
               {"name": "s1", "kind": "stress", "region": "top", "direction": [1, 0, 0],
                "direction2": [0, 0, 1]},
               {"name": "s2", "kind": "stress", "point": [0.1, 0.01, 0.025],
                "direction": [0, 1, 0]},
               {"name": "y", "region": "tip", "kind": "displacement", "direction": [0, 1, 0]}]
    cfg = config_from_dict(_cfg(outputs))
    g1, s1, s2, _ = cfg.ports.outputs
    assert (g1.region, g1.point, g1.radius) == ("", (0.1, 0.02, 0.025), 0.004)
    assert s1.direction2 == (0.0, 0.0, 1.0) and s2.radius == 0.0
    import yaml
    assert config_from_dict(yaml.safe_load(config_to_yaml(cfg))) == cfg


@pytest.mark.parametrize("port, message", [
    ({"name": "g", "kind": "strain", "direction": [1, 0, 0]}, "exactly one of 'region'"),
    ({"name": "g", "kind": "strain", "direction": [1, 0, 0], "region": "top",
      "point": [0, 0, 0]}, "exactly one of 'region'"),
    ({"name": "g", "kind": "strain", "direction": [1, 0, 0], "region": "top", "radius": 0.1},
     "no radius with 'region'"),
    ({"name": "g", "kind": "stress", "direction": [1, 0, 0], "direction2": [1, 1, 0],
      "region": "top"}, "orthogonal"),
    ({"name": "g", "kind": "stress", "direction": [1, 0, 0], "point": [0, 0, 0],
      "radius": -1.0}, "ports.outputs\\[0\\].radius"),
    ({"name": "g", "kind": "strain", "direction": [1, 0, 0], "region": "nowhere"},
     "ports.outputs\\[0\\].region"),
    ({"name": "g", "kind": "strain", "direction": [1, 0, 0], "region": "top", "gain": 2},
     "gain"),
])
def test_bad_gauge_ports_are_refused_naming_the_key(port, message):
    with pytest.raises(ConfigError, match=message):
        config_from_dict(_cfg([port]))


def test_gauge_as_input_is_refused():
    raw = _cfg([{"name": "y", "region": "tip", "kind": "displacement", "direction": [0, 1, 0]}])
    raw["ports"]["inputs"].append({"name": "g", "kind": "strain", "region": "top",
                                   "direction": [1, 0, 0]})
    with pytest.raises(ConfigError, match=r"ports.inputs\[1\].kind"):
        config_from_dict(raw)


# --------------------------------------------------------------------------- file and simulate
@pytest.fixture(scope="module")
def gauge_file(tmp_path_factory):
    """configs/cantilever_gauges.yaml at h = 20 mm through the pipeline, and its FE model."""
    from pathlib import Path

    from pipeline.config import load_config
    from pipeline.fe.model import build_fe_model
    from pipeline.run import run_pipeline

    tmp = tmp_path_factory.mktemp("gauges")
    root = Path(__file__).resolve().parents[1]
    cfg = load_config(root / "configs" / "cantilever_gauges.yaml", ["mesh.size=0.02"])
    out = tmp / "gauges.h5"
    run_pipeline(cfg, out, mesh_dir=tmp)
    fe = build_fe_model(cfg, tmp)
    pm = port_matrices(fe.space, fe.regions, cfg.ports, material=cfg.material)
    x = np.zeros(fe.space.n_dofs)
    x[fe.free] = spla.spsolve(fe.K.tocsc(), pm.F.toarray()[fe.free, 0])
    static = strain.stress_fields(fe.space, cfg.material, x)
    # two factorisations of K agree to about cond(K) eps relative (normwise); the stress is a
    # linear image of the solution, so we allow 10 cond(K) eps of the largest stress
    # (cond ~ 2e8 here: 0.1 Pa of 184 kPa per N; measured difference 1e-5 Pa)
    bound = 10 * _cond(fe.K) * EPS * np.abs(static.stress).max()
    return cfg, out, static, pm.T @ x, bound


def test_stress_modes_in_file_rebuild_the_full_fe_static_field(gauge_file):
    import h5py

    from pipeline.store.read import load_model, read_stress_modes

    cfg, out, static, _, bound = gauge_file
    sm = read_stress_modes(out)
    assert sm.n_basis == cfg.reduction.modes and sm.n_correction == 1
    assert sm.shape_names[-1] == "residual/tip_force_y" and sm.voigt_order[3] == "yz"
    mats = load_model(out).matrices
    z = -np.linalg.solve(mats["A"], mats["B"][:, 0])  # static states for 1 N
    q = np.concatenate([z[:sm.n_basis], [1.0]])
    sigma = np.einsum("pks,s->pk", sm.stress, q)
    eps = np.einsum("pks,s->pk", sm.strain, q)
    assert np.abs(sigma - static.stress[:, :, 0]).max() <= bound
    assert np.abs(eps - static.strain[:, :, 0]).max() <= bound / np.abs(static.stress).max() \
        * np.abs(static.strain).max()
    with h5py.File(out) as h5:
        assert h5["stress_modes/stress"].attrs["units"] == "Pa"
    # without the residual shape the static field is visibly wrong (the correction matters)
    sigma_modes = np.einsum("pks,s->pk", sm.stress[:, :, :-1], q[:-1])
    assert np.abs(sigma_modes - static.stress[:, :, 0]).max() > 100 * bound


def test_simulate_records_gauges_and_recovers_the_static_field(gauge_file, tmp_path):
    from pipeline.apps.simulate import simulate

    cfg, out, static, gauges_static, _ = gauge_file
    force = 50.0
    scenario = {"name": "hold", "kind": "step_load", "input": "tip_force_y", "output": "tip_y",
                "force": force, "duration": 2.0, "output_rate": 500.0, "lumped": False,
                "stress_instants": [2.0]}
    res = simulate(out, scenario, tmp_path / "sim.h5", plots=True)
    run = res["hold"].run("fe")
    # transient left at t = 2 s: exp(-xi omega_1 t) = exp(-0.02 * 2 pi 65.7 * 2) = 7e-8 of
    # the static response, plus the integrator's rtol 1e-8: 1e-6 relative
    names = [p.name for p in cfg.ports.outputs]
    for name in ("gauge_top_mid", "sxx_top_mid", "gauge_root", "sxx_top_mean"):
        assert run.units[name] == ("Pa" if name.startswith("sxx") else "1")
        expected = force * gauges_static[names.index(name)]
        assert run.signals[name][-1] == pytest.approx(expected, rel=1e-6)
    peak = run.info["stress_peak"]
    field = peak.fields[0]
    scale = np.abs(static.stress).max() * force
    assert np.abs(field - force * static.stress[:, :, 0]).max() <= 1e-6 * scale
    assert run.measured["peak_von_mises"] == pytest.approx(peak.peak.max())
    # the hot spot's peak is the largest von Mises over points and time, and at least the
    # static value there (a step response overshoots)
    from pipeline.apps.simulate.stress import von_mises

    vm_static = von_mises(force * static.stress[:, :, 0])
    assert peak.value >= vm_static.max() * (1 - 1e-6)
    assert any(str(f).endswith(".stress.png") for f in res.files)
    import h5py

    with h5py.File(tmp_path / "sim.h5") as h5:
        assert h5["hold/fe/stress/peak_von_mises"].shape == (static.stress.shape[0],)
        assert h5["hold/fe/signals/sxx_top_mid"].attrs["units"] == "Pa"


@pytest.mark.slow
def test_bracket_fillet_gauge_reads_the_full_fe_static_value(tmp_path):
    """configs/bracket_gauges.yaml (STEP geometry, h = 4 mm): the reduced model's static
    fillet strain and stresses equal a separate full FE solve through the same rows (one
    mesh, built once: meshing the STEP file again would only cost time)."""
    from pathlib import Path

    from pipeline.config import load_config
    from pipeline.fe.model import build_fe_model

    root = Path(__file__).resolve().parents[1]
    cfg = load_config(root / "configs" / "bracket_gauges.yaml", ["mesh.size=0.004"])
    fe = build_fe_model(cfg, tmp_path)
    pm = port_matrices(fe.space, fe.regions, cfg.ports, material=cfg.material)
    F, T = pm.F.toarray()[fe.free], pm.T[:, fe.free]
    w2, phi = spla.eigsh(fe.K, k=cfg.reduction.modes, M=fe.M, sigma=0.0)
    reduced = reduce_model(fe.K, fe.M, phi, w2, F, T, cfg.reduction.modes,
                           DampingSpec("uniform", 0.02), "residual", pm.input_names,
                           pm.output_names)
    dc = reduced.dc_gain_position
    X = np.column_stack([spla.spsolve(fe.K.tocsc(), F[:, j]) for j in range(F.shape[1])])
    full = T @ X
    # |row . dx| <= ||row|| ||dx||, ||dx|| <= 10 cond(K) eps ||x||
    row_norm = np.sqrt(np.asarray(T.multiply(T).sum(axis=1))).ravel()
    bound = 10 * _cond(fe.K) * EPS * row_norm[:, None] * np.linalg.norm(X, axis=0)[None, :]
    assert np.all(np.abs(dc - full) <= bound)
    g = list(pm.output_names).index("fillet_gauge")
    # a push on the pin away from the base (+y) opens the bend: the inner fillet is in
    # compression along its arc
    assert full[g, 0] < 0 and abs(full[g, 0]) > 1e-8


def test_exports_and_pictures_carry_the_stress_fields(gauge_file, tmp_path):
    import meshio

    from pipeline.apps.exports.vtu import export_vtu
    from pipeline.apps.simulate.stress import von_mises
    from pipeline.apps.stress_plots import plot_static_von_mises
    from pipeline.store.read import read_stress_modes

    cfg, out, static, _, bound = gauge_file
    sm = read_stress_modes(out)
    mesh = meshio.read(export_vtu(out, tmp_path / "g.vtu"))
    # ParaView's symmetric tensor order xx yy zz xy yz xz from the file's xx yy zz yz xz xy
    assert np.array_equal(mesh.point_data["stress_eta_01"], sm.stress[:, [0, 1, 2, 5, 3, 4], 0])
    assert "stress_residual_tip_force_y" in mesh.point_data
    vm = mesh.point_data["von_mises_static_tip_force_y"]
    # von Mises is 1-Lipschitz in the max-norm of the components up to a factor sqrt(6)
    assert np.abs(vm - von_mises(static.stress[:, :, 0])).max() <= 3 * bound
    pics = plot_static_von_mises(out, tmp_path)
    assert [p.name for p in pics] == ["static_von_mises_tip_force_y.png"]
    assert pics[0].stat().st_size > 10_000


def test_scenario_output_defaults_to_the_only_motion_port_and_refuses_a_gauge(gauge_file,
                                                                               tmp_path):
    from pipeline.apps.simulate import simulate

    _, out, _, _, _ = gauge_file
    base = {"name": "s", "kind": "step_load", "force": 1.0, "duration": 0.05,
            "output_rate": 2000.0, "lumped": False}
    res = simulate(out, base, None, plots=False)  # output: the file's only displacement port
    assert "tip_y/position" in res["s"].run("fe").signals
    with pytest.raises(ConfigError, match="motion output port 'sxx_top_mid' is not in"):
        simulate(out, {**base, "output": "sxx_top_mid"}, None, plots=False)
