"""The SID export (``export --to sid``, issue 37 item 6) read back by an independent reader.

welib, the open SID implementation on PyPI, has no SID *reader* (its ``welib.yams.sid``
builds SID objects and prints them; its sdists do not build here either), so the reader
is the small parser below, written from the SID definitions [Wallrapp 1994; Schwertassek
& Wallrapp 1999, ch. 6] and not from the writer: it is not an external reader. From the
file alone it rebuilds

- the frequencies at rest from Ke, Me and at every stored speed from
  Ke + Omega^2 sum_W a_W Oe.M1[:, W, :] (a_W the SID products of the unit spin axis), against
  ``/modes`` and ``/rotation`` (reduced: round-off; full FE: the modal basis error of
  theory.md §13, 1 % at these speeds);
- mass, centre of mass and inertia about the frame origin, against the closed forms of the
  box (exact: x is in the P2 space and the mass matrix integrates it exactly);
- the identities the definitions imply between independently computed terms: the
  centrifugal modal force is the derivative of the centrifugal potential
  (Oe.M0 W = -1/2 omega^T J1_k omega), sym(Gr0_k) = J1_k, Ge = 2 Cr.M1, mdCM.M1 = Ct.M0^T;
- the tip node's slope-to-deflection ratio of the first bending mode against the
  Euler-Bernoulli cantilever mode (2 %: shear and section effects of the 3D solid).
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg as sla

from tests.test_rotation import SPIN_CONFIG, _beam_mode


#: the spinning box of tests/test_rotation.py with 3 % uniform damping
SPIN = SPIN_CONFIG.replace("rotation:", "damping: {kind: uniform, ratio: 0.03}\nrotation:") % (
    "[0, 200, 400, 800]")
L_, H, D, RHO = 0.5, 0.02, 0.05, 2700.0
POINT = np.array([0.0, 0.01, 0.025])
#: SID order of the products of omega: x^2, y^2, z^2, xy, yz, xz
PRODUCTS = ((0, 0), (1, 1), (2, 2), (0, 1), (1, 2), (0, 2))


# --------------------------------------------------------------------------- the reader
def _taylor(lines: list[str], i: int) -> tuple[dict, int]:
    """One Taylor block starting at its name line i: (dict with m0, m1, header), next i."""
    name = lines[i].strip()
    head: dict = {}
    entries0, entries1 = [], []
    i += 1
    while lines[i].strip() != f"end {name}":
        s = lines[i].strip()
        m = re.fullmatch(r"(order|nrow|ncol|nq|nqn|structure)\s*=\s*(\d+)", s)
        if m:
            head[m[1]] = int(m[2])
        elif s.startswith("m0("):
            idx, val = s[3:].split(")")
            entries0.append(([int(v) - 1 for v in idx.split(",")], float(val.split("=")[1])))
        elif s.startswith("m1("):
            idx, val = s[3:].split(")")
            entries1.append(([int(v) - 1 for v in idx.split(",")], float(val.split("=")[1])))
        else:
            raise AssertionError(f"unknown line in {name}: {s}")
        i += 1
    m0 = np.zeros((head["nrow"], head["ncol"]))
    for (r, c), v in entries0:
        m0[r, c] = v
    if head["structure"] == 2:  # the lower triangle is written
        m0 = np.tril(m0) + np.tril(m0, -1).T
    out = {"name": name, "m0": m0, **head}
    if head["order"] == 1:
        m1 = np.zeros((head["nrow"], head["ncol"], head["nq"]))
        for (r, c, k), v in entries1:
            m1[r, c, k] = v
        out["m1"] = m1
    return out, i + 1


def read_sid(path: Path) -> dict:
    """refmod (mass, names, frequencies), nodes (list of dicts of Taylor blocks), terms."""
    lines = [ln for ln in path.read_text().splitlines() if ln.strip()]
    assert [ln.strip() for ln in lines[:3]] == ["part", "new modal", "refmod"]
    assert [ln.strip() for ln in lines[-2:]] == ["end modal", "end part"]
    sid: dict = {"names": [], "freqs": [], "nodes": [], "terms": {}}
    i = 3
    while lines[i].strip() != "end refmod":
        s = lines[i].strip()
        if s.startswith("mass"):
            sid["mass"] = float(s.split("=")[1])
        elif s.startswith("nelastq"):
            sid["nq"] = int(s.split("=")[1])
        elif s.startswith("ielastq"):
            name, freq = s.split("=", 1)[1].rsplit(":", 1)
            sid["names"].append(name.strip())
            sid["freqs"].append(float(freq.replace("Hz", "")))
        i += 1
    i += 1
    assert lines[i].strip() in ("frame", "new frame")
    i += 1
    while lines[i].strip() != "end frame":
        assert lines[i].strip().startswith("new node")
        node = {"rframe": lines[i + 1].split("=")[1].strip()}
        i += 2
        while lines[i].strip() != "end node":
            t, i = _taylor(lines, i)
            node[t["name"]] = t
        sid["nodes"].append(node)
        i += 1
    i += 1
    while lines[i].strip() != "end modal":
        t, i = _taylor(lines, i)
        sid["terms"][t["name"]] = t
    return sid


# --------------------------------------------------------------------------- fixtures
def _cli(*args, cwd):
    return subprocess.run([sys.executable, "-m", "pipeline", *map(str, args)], cwd=cwd,
                          capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def spun(tmp_path_factory):
    """(result file, its SID read back) of the spinning box through the command line."""
    tmp = tmp_path_factory.mktemp("sid")
    (tmp / "spin.yaml").write_text(SPIN)
    proc = _cli("run", "spin.yaml", "-o", "spin.h5", cwd=tmp)
    assert proc.returncode == 0, proc.stderr
    proc = _cli("export", "spin.h5", "--to", "sid", cwd=tmp)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip().endswith("spin.SID_FEM")
    return tmp / "spin.h5", read_sid(tmp / "spin.SID_FEM")


def _terms(sid):
    return sid["terms"]


# --------------------------------------------------------------------------- checks
def test_frequencies_at_rest_and_spinning_rebuild_from_the_file(spun):
    from pipeline.store.read import read_rotation, read_stored_mesh

    h5, sid = spun
    T = _terms(sid)
    mesh, rot = read_stored_mesh(h5), read_rotation(h5)
    assert sid["nq"] == 4 and sid["names"] == list(mesh.labels)
    np.testing.assert_allclose(sid["freqs"], mesh.frequencies_hz, rtol=1e-9)
    Ke, Me = T["Ke"]["m0"], T["Me"]["m0"]
    # Me = I, Ke = diag(w^2) of M-orthonormal modes, to the eigensolver's residual
    np.testing.assert_allclose(Me, np.eye(4), atol=1e-9)
    f0 = np.sqrt(sla.eigh(Ke, Me, eigvals_only=True)) / (2 * np.pi)
    np.testing.assert_allclose(f0, mesh.frequencies_hz, rtol=1e-8)
    a = np.array([rot.axis[i] * rot.axis[j] for i, j in PRODUCTS])
    spin = np.einsum("w,iwk->ik", a, T["Oe"]["m1"])
    for speed, full, reduced in zip(rot.speeds_rad_s, rot.frequencies_hz,
                                    rot.frequencies_reduced_hz):
        w2 = sla.eigh(Ke + speed ** 2 * spin, Me, eigvals_only=True)
        f = np.sqrt(w2) / (2 * np.pi)
        np.testing.assert_allclose(f, reduced, rtol=1e-8)  # the same basis: round-off
        np.testing.assert_allclose(f, full, rtol=1e-2)  # theory.md §13: basis error
    assert f[0] > 1.25 * f0[0]  # 800 rad/s: w^2 = w0^2 + (S - 1) Omega^2, S - 1 = 0.19
    # damping: De = diag(2 zeta w) with the config's uniform ratio
    np.testing.assert_allclose(np.diag(T["De"]["m0"]), 2 * 0.03 * 2 * np.pi * f0, rtol=1e-8)


def test_mass_centre_and_inertia_are_the_box(spun):
    _, sid = spun
    T = _terms(sid)
    m = RHO * L_ * H * D
    assert sid["mass"] == pytest.approx(m, rel=1e-12)
    d = np.array([L_, H, D]) / 2 - POINT  # the centre relative to the frame origin
    np.testing.assert_allclose(T["mdCM"]["m0"][:, 0] / m, d, atol=1e-12)
    Jc = m / 12 * np.diag([H ** 2 + D ** 2, L_ ** 2 + D ** 2, L_ ** 2 + H ** 2])
    J = Jc + m * (d @ d * np.eye(3) - np.outer(d, d))
    np.testing.assert_allclose(T["J"]["m0"], J, rtol=1e-10, atol=1e-12 * np.abs(J).max())


def test_terms_satisfy_the_identities_of_their_definitions(spun):
    _, sid = spun
    T = _terms(sid)
    nq = sid["nq"]
    J1 = T["J"]["m1"]  # (3, 3, nq)
    scale = np.abs(J1).max()
    # centrifugal potential -1/2 omega^T J(q) omega: its modal force is -1/2 omega^T J1 omega
    for w, (i, j) in enumerate(PRODUCTS):
        expect = -0.5 * J1[i, i] if i == j else -J1[i, j]
        np.testing.assert_allclose(T["Oe"]["m0"][:, w], expect, atol=1e-10 * scale)
    Gr0 = T["Gr"]["m0"].reshape(3, nq, 3).transpose(1, 0, 2)  # block k
    for k in range(nq):
        np.testing.assert_allclose(0.5 * (Gr0[k] + Gr0[k].T), J1[:, :, k],
                                   atol=1e-10 * scale)
    Cr1 = T["Cr"]["m1"]  # (nq, 3, nq): int rho psi_l x psi_k
    np.testing.assert_allclose(Cr1, -Cr1.transpose(2, 1, 0), atol=1e-12)
    Ge = T["Ge"]["m0"].reshape(nq, nq, 3)  # [i, j, a]
    np.testing.assert_allclose(Ge, 2 * Cr1.transpose(0, 2, 1), atol=1e-12)
    np.testing.assert_allclose(T["mdCM"]["m1"][:, 0, :], T["Ct"]["m0"].T, atol=1e-14)
    assert T["ksigma"]["structure"] == 0 and T["ksigma"]["order"] == 0


def test_tip_node_moves_like_the_beam_mode(spun):
    _, sid = spun
    # the tip node: the one at x = L (frame coordinates relative to the point)
    tip = [n for n in sid["nodes"] if abs(n["origin"]["m0"][0, 0] - L_) < 1e-9
           and abs(n["origin"]["m0"][1, 0]) < 1e-9]
    assert len(tip) == 1 and tip[0]["rframe"] == "body ref"
    node = tip[0]
    phi, psi = node["phi"]["m0"], node["psi"]["m0"]
    beam_phi, beam_slope = _beam_mode(np.array([L_]))
    ratio = float(beam_slope[0] / beam_phi[0])
    # mode 1 bends in x-y (about z): slope psi_z / deflection phi_y
    assert psi[2, 0] / phi[1, 0] == pytest.approx(ratio, rel=2e-2)
    np.testing.assert_allclose(node["origin"]["m1"][:, 0, :], phi, atol=1e-15)
    for k in range(sid["nq"]):
        A = node["AP"]["m1"][:, :, k]
        np.testing.assert_allclose(A, -A.T, atol=1e-15)
        np.testing.assert_allclose([A[2, 1], A[0, 2], A[1, 0]], psi[:, k], atol=1e-15)


def test_file_without_rotation_gets_the_softening_alone(tmp_path):
    """Without /rotation Oe.M1 is the spin-softening mass alone (-V^T M_W V): about z,
    -M_perp, whose first-mode entry is -(1 - out-of-plane share of the mode's mass)."""
    (tmp_path / "box.yaml").write_text(SPIN.split("rotation:")[0])
    assert _cli("run", "box.yaml", "-o", "box.h5", cwd=tmp_path).returncode == 0
    proc = _cli("export", "box.h5", "--to", "sid", cwd=tmp_path)
    assert proc.returncode == 0 and "no /rotation" in proc.stderr, proc.stderr
    sid = read_sid(tmp_path / "box.SID_FEM")
    spin = sid["terms"]["Oe"]["m1"][:, 2, :]  # the w_z^2 column
    assert np.all(np.linalg.eigvalsh(0.5 * (spin + spin.T)) < 0)  # softening only
    assert -1.0 <= spin[0, 0] < -0.9  # mode 1 moves in x-y: nearly all its mass softens


def test_bad_files_are_refused_in_one_line(tmp_path, spun):
    """Not an HDF5 result, a file without /fe exported without re-assembly, a file without
    /modes: one line, the exit code of FileFormatError, nothing written."""
    from pipeline.apps.exports import export
    from pipeline.errors import FileFormatError

    bad = tmp_path / "bad.h5"
    bad.write_text("not hdf5")
    proc = _cli("export", bad, "--to", "sid", "-o", tmp_path / "bad.SID_FEM", cwd=tmp_path)
    assert proc.returncode == FileFormatError.exit_code, proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and str(bad) in proc.stderr
    with pytest.raises(FileFormatError, match=r"has no /fe \(the full mass matrix"):
        export(spun[0], "sid", tmp_path / "x.SID_FEM")
    # a signed file without /modes
    import h5py

    from pipeline.store import layout as L
    from pipeline.store.h5file import sign

    modeless = tmp_path / "modeless.h5"
    modeless.write_bytes(spun[0].read_bytes())
    with h5py.File(modeless, "a") as h5:
        del h5[L.MODES.path]
        sign(h5)
    proc = _cli("export", modeless, "--to", "sid", cwd=tmp_path)
    assert proc.returncode == FileFormatError.exit_code, proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and str(modeless) in proc.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.h5", "modeless.h5"]


def test_terms_equal_the_ffrf_invariants(spun):
    """The same integrals by the other route of pipeline.reduce.ffrf (skew-matrix columns
    in the full mass matrix, theory.md §6) on the same M and modes: round-off."""
    from pipeline.reduce.ffrf import ffrf_invariants
    from pipeline.run import stored_fe_data
    from pipeline.store.read import read_fe_model

    h5, sid = spun
    T = _terms(sid)
    fe, body = stored_fe_data(h5), read_fe_model(h5, "modes")
    inv = ffrf_invariants(fe.M_full, body.points, body.basis.shapes, fe.K_full, origin=POINT)
    close = dict(rtol=1e-9, atol=1e-12)
    assert sid["mass"] == pytest.approx(inv.mass, rel=1e-12)
    np.testing.assert_allclose(T["mdCM"]["m0"][:, 0], inv.first_moment, **close)
    np.testing.assert_allclose(T["J"]["m0"], inv.inertia, **close)
    np.testing.assert_allclose(T["J"]["m1"], inv.inertia_first_order.transpose(1, 2, 0), **close)
    np.testing.assert_allclose(T["Ct"]["m0"], inv.translational_coupling.T, **close)
    np.testing.assert_allclose(T["Cr"]["m0"], inv.rotational_coupling.T, **close)
    np.testing.assert_allclose(T["Cr"]["m1"], inv.gyroscopic_coupling.transpose(1, 2, 0), **close)
    nq = sid["nq"]
    Gr1 = T["Gr"]["m1"].reshape(3, nq, 3, nq)  # [a, j, b, k] = 2 J2[k, j, a, b]
    np.testing.assert_allclose(Gr1, 2 * inv.inertia_second_order.transpose(2, 1, 3, 0), **close)
    np.testing.assert_allclose(T["Ke"]["m0"], inv.modal_stiffness, rtol=1e-9,
                               atol=1e-9 * np.abs(inv.modal_stiffness).max())


def test_export_replaces_its_own_sid_but_not_a_foreign_file(spun):
    from pipeline.errors import OutputError

    folder = spun[0].parent
    assert _cli("export", "spin.h5", "--to", "sid", cwd=folder).returncode == 0
    foreign = folder / "foreign.SID_FEM"
    foreign.write_text("not ours\n")
    proc = _cli("export", "spin.h5", "--to", "sid", "-o", foreign, cwd=folder)
    assert proc.returncode == OutputError.exit_code, proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and "--force" in proc.stderr
    assert foreign.read_text() == "not ours\n"


def test_free_body_drops_its_rigid_modes_and_its_modes_carry_no_momentum(tmp_path):
    """A body without supports: the six rigid-body modes are not SID coordinates, and the
    elastic free-free modes, M-orthogonal to the rigid ones, satisfy the mean-axis
    conditions int rho psi dV = 0 and int rho x x psi dV = 0 (Ct = Cr = 0 to round-off
    relative to the size the same integrals take for a supported body's modes)."""
    text = SPIN.split("supports:")[0] + "modes: {count: 10}\n"
    (tmp_path / "free.yaml").write_text(text)
    assert _cli("run", "free.yaml", "-o", "free.h5", cwd=tmp_path).returncode == 0
    assert _cli("export", "free.h5", "--to", "sid", cwd=tmp_path).returncode == 0
    sid = read_sid(tmp_path / "free.SID_FEM")
    assert sid["nq"] == 4 and sid["freqs"][0] > 100  # first free-free bending, no 0 Hz mode
    T = sid["terms"]
    scale = np.sqrt(sid["mass"])  # |int rho psi| <= sqrt(m) for an M-normalised psi
    assert np.abs(T["Ct"]["m0"]).max() < 1e-8 * scale
    assert np.abs(T["Cr"]["m0"]).max() < 1e-8 * scale * L_
