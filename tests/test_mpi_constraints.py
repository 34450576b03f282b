"""The exact constraint u = T q on MPI ranks (:mod:`pipeline.distributed.constraints`):
components held in a local frame and rigid (RBE2) mass couplings with
``modes.solver: slepc``.

Without MPI: each emulated rank's rows of T, built from what rank 0 sends it, stacked
and renumbered to the serial order, are the serial T (:func:`pipeline.fe.constraints.
build_constraint`) exactly (the same formulas on the same numbers), also where a rank
boundary cuts a held node's DOFs and a coupling's slaves.

With ``make mpi-env``: 2 ranks give the single-process file, judged by
``tests/test_mpi.py``'s ``_same_file`` (frequencies to 1e-8 relative, every stored float
to 1e-8 of its largest entry; measured: frequencies 1e-13 (local frame) and 1e-10 (rigid
coupling, MUMPS against PARDISO on K_q), datasets 2e-11, the rigid coupling's static
compliance 2.3e-10). A partly held body with a rigid coupling floats and stores no
compliance: its residual flexibility R (4.7e-3 of the inertia-relief compliance it is
part of on the cantilever below, 1 elastic mode retained) is judged against that
compliance, as ``_same_file`` judges R of a held body against the static compliance
(measured 1.3e-10 of it; 2.7e-8 of R itself). A free body's rigid shapes are any basis
of the six motions: only its elastic shapes are compared.
"""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
import scipy.sparse as sp

import test_mpi
from pipeline.distributed.constraints import constraint_sources, rank_entries, rows_of_T
from pipeline.distributed.partition import RowPartition, slab_partition
from pipeline.fe.model import build_fe_model, constraint_inputs, mesh_config
from test_mpi import CARRY_R, FREQUENCY_TOL, DATASET_TOL, _same_file, _serial_and_two_ranks

#: a square steel shaft along x (axis through (y, z) = (0.02, 0.02)), clamped on one
#: band and held radially (cylindrical frame) on the other; a force and a displacement
#: port at its free end
AXIS = {"kind": "cylindrical", "axis": [1, 0, 0], "point": [0, 0.02, 0.02]}
SHAFT = {
    "name": "radial", "geometry": {"kind": "box", "length": 0.4, "height": 0.04, "depth": 0.04},
    "mesh": {"order": 2, "size": 0.015}, "material": {"E": 210.0e9, "nu": 0.3, "rho": 7800.0},
    "regions": {"band_a": {"kind": "box", "lower": [0.005, -1, -1], "upper": [0.045, 1, 1]},
                "band_b": {"kind": "box", "lower": [0.355, -1, -1], "upper": [0.395, 1, 1]}},
    "supports": [{"region": "band_a", "fix": "all"},
                 {"region": "band_b", "fix": ["radial"], "frame": AXIS}],
    "modes": {"count": 8},
    "ports": {"inputs": [{"name": "tip_force_y", "region": "tip", "kind": "force",
                          "direction": [0, -1, 0]}],
              "outputs": [{"name": "tip_y", "region": "tip", "kind": "displacement",
                           "direction": [0, 1, 0]}]},
    "damping": {"kind": "uniform", "ratio": 0.02},
    "reduction": {"modes": 4, "static_correction": "residual"},
    "filter": {"kind": "third_order", "cutoff_hz": 50000}}
#: the aluminium cantilever (a coarse mesh) with a 0.3 kg mass rigidly coupled to its
#: tip face, its point beyond the face and off its centre
CANTILEVER = {
    **SHAFT, "name": "rigidtip",
    "geometry": {"kind": "box", "length": 0.5, "height": 0.02, "depth": 0.05},
    "mesh": {"order": 2, "size": 0.02}, "material": {"E": 69.0e9, "nu": 0.33, "rho": 2700.0},
    "regions": {}, "supports": [{"region": "root", "fix": "all"}],
    "masses": [{"name": "m", "mass": 0.3, "inertia": [2e-4, 3e-4, 4e-4, 0, 0, 0],
                "point": [0.53, 0.012, 0.03], "region": "tip", "coupling": "rigid"}],
    "filter": {"kind": "third_order", "cutoff_hz": 5000}}


def _config(tmp_path, raw: dict) -> str:
    """``raw`` as a config file (JSON is YAML) in ``tmp_path``; its path."""
    path = tmp_path / f"{raw['name']}.yaml"
    path.write_text(json.dumps(raw))
    return str(path)


def _emulated_T(cfg, tmp_path, size: int, cut: bool = False):
    """(serial T, the emulated ranks' rows of T stacked in the serial order): rank 0's
    sources, each rank's entries, the gathered column keys, each rank's rows. With
    ``cut``, a rank boundary is moved between the first and second DOF of a
    held or coupled node, so that its DOFs lie on two ranks."""
    fe = build_fe_model(cfg, tmp_path)
    meshed = mesh_config(cfg, tmp_path)
    inputs = constraint_inputs(meshed.space, meshed.regions, cfg, fe.free, meshed.supports)
    part = slab_partition(fe.space.node_points, fe.free, size)
    if cut:  # a row of T that is not one unit entry: a held or coupled DOF
        T = fe.constraint.T
        plain = (np.diff(T.indptr) == 1) & (np.abs(T.data[T.indptr[:-1]]) == 1.0)
        node = fe.free[np.flatnonzero(~plain)[0]] // 3
        row = int(np.flatnonzero(fe.free[part.order] // 3 == node)[1])
        starts = part.starts.copy()
        starts[max(1, int(np.searchsorted(starts, row, "right")) - 1)] = row
        part = RowPartition(part.order, starts)
    sources = constraint_sources(*inputs, meshed.space.n_dofs, fe.free, part)
    entries = [rank_entries(sources[r], fe.free, part, r) for r in range(size)]
    keys = np.concatenate([e[3] for e in entries])
    rows = [rows_of_T(*entries[r][:3], part.owned_free(r), keys) for r in range(size)]
    order = rows[0][1]
    assert all(np.array_equal(r[1], order) for r in rows)
    assert np.array_equal(np.sort(order), np.arange(order.size))
    T = sp.vstack([r[0] for r in rows]).tocsr()
    back = np.empty_like(part.order)
    back[part.order] = np.arange(part.order.size)
    return fe.constraint.T, sp.csr_matrix(T[back][:, np.argsort(order)])


@pytest.mark.parametrize("raw", [SHAFT, CANTILEVER], ids=["local-frame", "rigid-coupling"])
def test_each_ranks_rows_of_T_stack_to_the_serial_T(tmp_path, raw):
    """3 emulated ranks, also with a boundary inside a held node or a slave node: the
    stacked rows, in the serial row and column order, are the serial T (exact: the same
    formulas on the same numbers)."""
    from pipeline.config import config_from_dict

    cfg = config_from_dict(raw)
    for cut in (False, True):
        serial, stacked = _emulated_T(cfg, tmp_path, 3, cut)
        assert stacked.shape == serial.shape
        assert abs(stacked - serial).max() == 0.0


def _same_floating_file(serial, dist, monkeypatch) -> None:
    """``_same_file`` for a floating body (no static compliance): the datasets carrying R
    are judged against the inertia-relief compliance R + Theta_e Omega_e^-2 Sigma_e (the
    retained elastic modes' part, from the stored modal state space: its position
    outputs C[:, :n] = Theta, its velocity rows B[n:] = Sigma)."""
    monkeypatch.setattr(test_mpi, "SKIPPED", test_mpi.SKIPPED | set(CARRY_R))
    _same_file(serial, dist)
    with h5py.File(serial) as a, h5py.File(dist) as b:
        assert "statespace/static_compliance" not in a
        R = a["statespace/residual_flexibility"][()]
        n = a["statespace/A"].shape[0] // 2
        w2 = (2 * np.pi * a["statespace/frequencies_hz"][()]) ** 2
        Theta, Sigma = a["statespace/C"][:, :n], a["statespace/B"][n:]
        elastic = w2 > 0
        relief = R + Theta[:, elastic] @ (Sigma[elastic] / w2[elastic, None])
        scale = np.abs(relief).max()
        for name in CARRY_R:
            if name in a:
                np.testing.assert_allclose(b[name][()], a[name][()], rtol=0,
                                           atol=DATASET_TOL * scale, err_msg=name)


@pytest.mark.mpi
@pytest.mark.parametrize("raw, overrides", [
    (SHAFT, ()),
    (CANTILEVER, ()),
    # radially held on both bands: translation along and rotation about the axis stay
    # free (inertia relief, a floating model)
    (SHAFT, ("supports=[{region: band_a, fix: [radial], frame: " + json.dumps(AXIS) + "}, "
             "{region: band_b, fix: [radial], frame: " + json.dumps(AXIS) + "}]",))],
    ids=["local-frame", "rigid-coupling", "local-frame-partly-held"])
def test_exact_constraints_on_two_ranks(tmp_path, raw, overrides):
    """The same file as the single-process run (a few seconds each)."""
    serial, dist = _serial_and_two_ranks(tmp_path, _config(tmp_path, raw), *overrides)
    with h5py.File(dist) as b:
        assert b["modes"].attrs["n_rigid"] == (2 if overrides else 0)
    _same_file(serial, dist)


@pytest.mark.mpi
def test_both_constraints_on_three_ranks_with_the_augmented_basis(tmp_path):
    """The shaft held radially with a mass rigidly coupled to its free end, on 3 ranks
    (PT-Scotch's parts), ``static_correction: augment`` (the Ritz basis of [Phi, X] with
    X = T K_q^-1 T^T F): the same file."""
    mass = ("masses=[{name: m, mass: 2.0, inertia: [1e-3, 2e-3, 2e-3, 0, 0, 0], "
            "point: [0.45, 0.02, 0.02], region: tip, coupling: rigid}]")
    serial, dist = _serial_and_two_ranks(tmp_path, _config(tmp_path, SHAFT), mass,
                                         "reduction.static_correction=augment", ranks=3)
    _same_file(serial, dist, ranks=3)


@pytest.mark.mpi
def test_partly_held_body_with_a_rigid_coupling_on_two_ranks(tmp_path, monkeypatch):
    """The cantilever held along x at its root, the mass rigidly coupled to its tip:
    three rigid motions (translation y, z, rotation x) in q's coordinates
    ((T^T T)^-1 T^T R on each rank), the inertia relief solved on T^T K T, T^T M T. The
    same file (R judged against the relief compliance, module)."""
    serial, dist = _serial_and_two_ranks(tmp_path, _config(tmp_path, CANTILEVER),
                                         "supports=[{region: root, fix: [x]}]")
    with h5py.File(serial) as a:
        assert a["modes"].attrs["n_rigid"] == 3
    _same_floating_file(serial, dist, monkeypatch)


@pytest.mark.mpi
def test_free_body_with_a_rigid_coupling_on_two_ranks(tmp_path):
    """No supports: the coupling removes no rigid motion; SLEPc at the serial shift
    finds six at 0 Hz and the same elastic modes (rigid shapes: any basis of the six)."""
    serial, dist = _serial_and_two_ranks(tmp_path, _config(tmp_path, CANTILEVER),
                                         "supports=[]", "reduction.static_correction=none")
    with h5py.File(serial) as a, h5py.File(dist) as b:
        assert a["modes"].attrs["n_rigid"] == b["modes"].attrs["n_rigid"] == 6
        np.testing.assert_allclose(b["modes/frequencies_hz"][()],
                                   a["modes/frequencies_hz"][()], rtol=FREQUENCY_TOL, atol=0)
        x, y = a["modes/shapes"][()][..., 6:], b["modes/shapes"][()][..., 6:]
        np.testing.assert_allclose(y, x, rtol=0, atol=DATASET_TOL * np.abs(x).max())
        assert list(a["modes/labels"][()]) == list(b["modes/labels"][()])


@pytest.mark.mpi
@pytest.mark.parametrize("raw", [SHAFT, CANTILEVER], ids=["local-frame", "rigid-coupling"])
def test_factor_free_path_with_exact_constraints_on_two_ranks(tmp_path, raw):
    """``modes.method: multigrid``: LOBPCG on the two-grid cycle of K_q, its coarse
    space T^T P (the serial path's), to a preconditioned residual of 1e-8 (as in
    tests/test_mpi.py). The same file."""
    _same_file(*_serial_and_two_ranks(tmp_path, _config(tmp_path, raw),
                                      distributed=("modes.method=multigrid",
                                                   "modes.tolerance=1e-8")))


def test_the_distributed_path_accepts_exact_constraints():
    """Local-frame supports and rigid couplings pass the distributed path's check."""
    from pipeline.config import config_from_dict
    from pipeline.distributed.stage import check_supported

    for raw in (SHAFT, CANTILEVER):
        check_supported(config_from_dict({**raw, "modes": {"count": 8, "solver": "slepc"}}))
