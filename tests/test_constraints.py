"""Exact linear constraints u = T q (:mod:`pipeline.fe.constraints`).

Checks and their tolerances:
- T of held local directions: orthonormal columns, C T = 0 and the right number of
  coordinates (exact integers; the products to round-off, 1e-14);
- the static solve through T, X = T (T^T K T)^-1 T^T F, against an independent
  null-space basis built in the test from the geometry (``exact_radial_basis``): two
  direct solves of one SPD system, equal to the round-off of cond(K_q) eps (~1e-10 on this
  P1 shaft), bounded by 1e-8; the held components of X are zero to round-off;
- the command line end to end with a reduced model and a residual static correction
  (which runs the static solve through T): exit 0, the summary states the exact hold;
- a spinning shaft under the radial hold: the reduced prestressed frequencies against the
  full FE sweep on T^T K T (1e-3, the issue's 1 % requirement; measured 1.3e-4).
The distributed path (``modes.solver: slepc``) builds the same T on its ranks:
tests/test_mpi_constraints.py.
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import scipy.sparse as sp

from pipeline.fe.constraints import local_frame_constraint
from pipeline.fe.model import build_fe_model
from pipeline.reduce.statics import static_shapes

from test_supports import AXIS, BANDS, SHAFT, STEEL, exact_radial_basis, shaft


def test_local_frame_constraint_is_orthonormal_and_holds_the_directions():
    """Node 0: one held direction (1, 1, 0)/sqrt 2; node 1: x fixed globally and the
    direction (0, 1, 1)/sqrt 2 held; node 2 untouched: 2 + 1 + 3 coordinates."""
    s = 1 / np.sqrt(2)
    C = sp.csr_matrix(np.array([[s, s, 0, 0, 0, 0, 0, 0, 0],
                                [0, 0, 0, 0, s, s, 0, 0, 0]]))
    free = np.array([0, 1, 2, 4, 5, 6, 7, 8])  # DOF 3 (node 1, x) fixed
    con = local_frame_constraint(C, free, "test")
    T = con.T.toarray()
    assert T.shape == (8, 6) and con.held == 2
    assert np.abs(T.T @ T - np.eye(6)).max() < 1e-14
    assert np.abs(C[:, free].toarray() @ T).max() < 1e-14
    # the untouched node keeps unit columns
    assert np.abs(np.abs(T[5:]).sum(axis=1) - 1).max() < 1e-14


def test_static_solve_through_T_against_an_independent_null_space(tmp_path):
    """A tip load on a shaft clamped on one band and held radially on the other."""
    from pipeline.fe.space import region_nodes

    cfg = shaft([{"region": "band_a", "fix": "all"},
                 {"region": "band_b", "fix": ["radial"], "frame": AXIS}], order=1)
    fe = build_fe_model(cfg, tmp_path)
    rng = np.random.default_rng(0)
    F = rng.standard_normal((fe.free.size, 2))
    X = static_shapes(fe.K, F, constraint=fe.constraint.T)
    plain = build_fe_model(shaft([{"region": "band_a", "fix": "all"}], order=1), tmp_path)
    Z = exact_radial_basis(plain, region_nodes(fe.space, fe.regions["band_b"]))
    Xz = Z @ sp.linalg.spsolve((Z.T @ plain.K @ Z).tocsc(), Z.T @ F)
    assert np.abs(X - Xz).max() <= 1e-8 * np.abs(Xz).max()
    C = fe.support_stiffness.constraint[:, fe.free]
    assert np.abs(C @ X).max() <= 1e-12 * np.abs(X).max()


def run_reduced_cli(raw: dict, tmp_path) -> str:
    """``raw`` with a y force and displacement port on the tip face and a residual static
    correction, run by `python -m pipeline run` into tmp_path / reduced.h5: asserts exit 0,
    returns the log."""
    import yaml

    raw = dict(raw, reduction={"modes": 4, "static_correction": "residual"},
               ports={"inputs": [{"name": "F", "kind": "force", "region": "tip",
                                  "direction": [0, 1, 0]}],
                      "outputs": [{"name": "u", "kind": "displacement", "region": "tip",
                                   "direction": [0, 1, 0]}]})
    path = tmp_path / "reduced.yaml"
    path.write_text(yaml.safe_dump(raw))
    proc = subprocess.run([sys.executable, "-m", "pipeline", "run", str(path), "-o",
                           str(tmp_path / "reduced.h5")], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc.stdout + proc.stderr


def test_cli_reduced_model_with_a_radial_hold(tmp_path):
    """`python -m pipeline run`: a force port at the free end of the shaft, static
    correction on: exit 0, and the summary states the exact hold."""
    raw = {"name": "held", "geometry": {"kind": "box", "length": SHAFT[0],
                                        "height": SHAFT[1], "depth": SHAFT[2]},
           "mesh": {"order": 1, "size": 0.01}, "material": STEEL, "modes": {"count": 6},
           "supports": [{"region": "band_a", "fix": "all"},
                        {"region": "band_b", "fix": ["radial"], "frame": AXIS}],
           "regions": BANDS}
    assert "held exactly" in run_reduced_cli(raw, tmp_path)


def test_spinning_shaft_with_a_radial_hold(tmp_path):
    """The shaft clamped on one band, held radially on the other, spinning about its own
    axis: the prestress static solve and the full FE sweep run on T^T K T; the reduced
    model (6 modes) follows the full prestressed frequencies within 1e-3 (the issue's 1 %
    requirement; measured 1.3e-4 at 6000 rad/s) and the speed moves them."""
    from pipeline.config import config_from_dict
    from pipeline.run import run_pipeline
    from pipeline.store.read import read_rotation

    raw = {"name": "spin", "geometry": {"kind": "box", "length": SHAFT[0],
                                        "height": SHAFT[1], "depth": SHAFT[2]},
           "mesh": {"order": 1, "size": 0.01}, "material": STEEL, "modes": {"count": 6},
           "supports": [{"region": "band_a", "fix": "all"},
                        {"region": "band_b", "fix": ["radial"], "frame": AXIS}],
           "regions": BANDS, "rotation": {"axis": [1, 0, 0], "point": AXIS["point"],
                                          "speeds_rad_s": [0, 3000, 6000]}}
    run_pipeline(config_from_dict(raw), tmp_path / "spin.h5", tmp_path)
    rot = read_rotation(tmp_path / "spin.h5")
    full, reduced = rot.frequencies_hz, rot.frequencies_reduced_hz[:, :6]
    assert np.abs(reduced / full - 1).max() < 1e-3
    assert np.abs(full[2] / full[0] - 1).max() > 1e-3
