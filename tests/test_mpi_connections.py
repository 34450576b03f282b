"""Connection points on MPI ranks (``connections:`` with ``modes.solver: slepc``,
:mod:`pipeline.distributed.connection`).

The reference is the single-process run (PARDISO and scipy) in this interpreter; the
2-rank file must equal it with test_mpi.py's tolerances (frequencies 1e-8 relative,
every other float 1e-8 of its largest entry). The default suite runs each case at
mesh.size 0.02 (4.5k DOFs: the rank boundaries, the clamped pencil's PtAP and the
unsupported pair are the same code at any size); ``make test-all`` adds mesh.size 0.01
(16.8k DOFs). Measured on 2 ranks at 0.02 (at 0.01 in brackets): with the parent point
only, L_P and B 5e-12 (3e-12), the frequencies 1.9e-10 relative (lowest mode); with the
distributing tip child, L_P 1e-11, Phi_C and the state space's B, C, D 3e-12 (5e-12);
D_P and the mass properties 1e-15 to 1.5e-14 of each dataset's largest entry. The
floating-frame invariants of the run's modes (sums over each rank's points): 3e-12
(1e-11). The shipped config with Craig-Bampton (20 fixed-interface modes): the free
frequencies 1.1e-11 (2e-11), the basis on every point 6e-12 (1.7e-11), M 3e-12
(1.5e-11). The unsupported body's FE matrices (``/fe``) are summed from
each rank's elements and written by rank 0 a block of rows at a time: M equal to 5e-16
of its largest entry with the same stored pattern; K to 3e-16, but entries that cancel
(1e-10 N/m against 4e9 N/m, 1e-19 of the largest) are exact zeros in one summation
order and not in the other (929 and 90 of 591514 entries at 0.01), so /fe is compared as
matrices and the rest of the file with _same_file. Without MPI: each emulated rank's rows of M R_P
are the serial ones, and the partition of every DOF keeps each rank's run rows.

When the clamped pencil is not the run's (a distributing parent, other supports, added
masses: the unsupported pair of pipeline.distributed.unsupported), measured on 2 ranks:
with a distributing tip child, a point mass, 20 Craig-Bampton modes and the rotation
beside it, the basis 5e-11 (3.5e-11), the invariants 7e-12 (8e-12), the rotation's
datasets 1e-9 to 5e-9 at either size from run to run (the geometric stiffness, built
from the static shapes' small remainders: test_mpi_rotation.py); a bushing at the root
and the tip held along x, L_P 8e-12 (6e-12); no supports on 3 ranks, Phi_C and the state
space 3e-12.
"""

from __future__ import annotations

import shutil

import h5py
import numpy as np
import pytest
import scipy.sparse as sp

from conftest import ALUMINIUM, build_model
from pipeline.distributed.assemble import rigid_mass_rows
from pipeline.distributed.partition import slab_partition
from pipeline.distributed.submesh import split_mesh
from pipeline.fe.assemble import assemble_on_nodes
from pipeline.fe.body import rigid_body_modes
from pipeline.fe.materials import assign_materials
from test_mpi import _same_file, _serial_and_two_ranks

CONFIG = "configs/cantilever_connection.yaml"
PARENT_ONLY = ("connections=[{name: root, region: root, point: [0.0, 0.01, 0.025], "
               "coupling: rigid}]", "craig_bampton={modes: 0}")
#: the unsupported body's K and M: compared as matrices (:func:`_same_matrices`), their
#: stored patterns differ where entries cancel to round-off (module docstring)
NOT_ON_RANKS = ("fe",)
FE_TOL = 1e-12  # measured 5e-16 (M) and 3e-16 (K) of the largest entry
#: the mesh of every 2- and 3-rank run: 0.02 in the default suite, 0.01 (four times the
#: DOFs, three times the time) in ``make test-all`` (module docstring)
MESHES = [pytest.param("mesh.size=0.02", id="h0.02"),
          pytest.param("mesh.size=0.01", id="h0.01", marks=pytest.mark.slow)]


def _without(path, groups, out):
    """A copy of the file ``path`` at ``out`` without ``groups``."""
    shutil.copy(path, out)
    with h5py.File(out, "r+") as f:
        for g in groups:
            del f[g]
    return out


def _same_matrices(serial, dist) -> None:
    """/fe's K and M of ``dist`` equal ``serial``'s to FE_TOL of their largest entry."""
    from pipeline.store.layout import FE
    from pipeline.store.read import read_csr

    with h5py.File(serial) as a, h5py.File(dist) as b:
        for group in (FE.mass_matrix, FE.stiffness_matrix):
            A, B = read_csr(a, group), read_csr(b, group)
            assert A.shape == B.shape
            assert abs(A - B).max() <= FE_TOL * abs(A).max(), group


def test_each_ranks_rows_of_M_R_P_are_the_serial_rows(tmp_path):
    """M R_P on the free rows couples to the held DOFs: each emulated rank sums it from
    its part's elements; stacked, the rows equal the unsupported (N (x) I_3) R_P's free
    rows (a different summation order: round-off of its scale)."""
    model = build_model(tmp_path, size=0.02)
    space, free = model.space, model.free
    P = np.array([0.0, 0.01, 0.025])
    part = slab_partition(space.node_points, free, 3)
    parts = split_mesh(space, assign_materials(space, ALUMINIUM), free, part, 3)
    rows = np.vstack([rigid_mass_rows(p, P) for p in parts])
    N = assemble_on_nodes(space, ALUMINIUM).node_mass
    serial = (sp.kron(N, sp.identity(3)) @ rigid_body_modes(space.node_points, P))[free]
    serial = serial[part.order]
    assert np.abs(rows - serial).max() <= 1e-13 * np.abs(serial).max()
    # the held DOFs matter: the supported M's rows alone give another answer
    assert np.abs(model.M[part.order] @ rigid_body_modes(space.node_points, P)[free][
        part.order] - serial).max() > 1e-3 * np.abs(serial).max()


def test_the_ranks_element_shares_add_up_to_the_unsupported_matrices(tmp_path):
    """Each emulated rank's upper triangle of its own elements (every element on one
    rank) holds part of the entries; summed they are the serial unsupported K and M's
    upper triangles (a different summation order: round-off of their scale)."""
    from pipeline.distributed.assemble import element_share
    from pipeline.fe.assemble import assemble_stiffness_mass

    model = build_model(tmp_path, size=0.02)
    space, free = model.space, model.free
    part = slab_partition(space.node_points, free, 3)
    parts = split_mesh(space, assign_materials(space, ALUMINIUM), free, part, 3)
    shares = [element_share(p, space.n_dofs) for p in parts]
    for i, A in enumerate(assemble_stiffness_mass(space, ALUMINIUM)):
        upper = sp.triu(A, format="csr")
        assert all(s[i].nnz < upper.nnz for s in shares)
        total = sum(s[i] for s in shares)
        assert abs(total - upper).max() <= 1e-13 * abs(upper).max()


def test_held_partition_appends_each_ranks_held_dofs_to_its_run_rows(tmp_path):
    """The partition of every DOF keeps each rank's run rows first, in their order, then
    the held DOFs of its points: whole points per rank, every DOF once."""
    from pipeline.distributed.unsupported import held_partition

    model = build_model(tmp_path, size=0.02)
    space, free = model.space, model.free
    part = slab_partition(space.node_points, free, 3)
    full = held_partition(part, free, space.n_dofs, space.element_nodes, 3)
    assert np.array_equal(np.sort(full.order), np.arange(space.n_dofs))
    for r in range(3):
        lo, hi = full.rows(r)
        run = free[part.owned_free(r)]
        assert np.array_equal(full.order[lo:lo + run.size], run)
        points = np.unique(full.order[lo:hi] // 3)
        assert hi - lo == 3 * points.size  # whole points


@pytest.mark.mpi
@pytest.mark.parametrize("mesh", MESHES)
def test_parent_point_on_two_ranks(tmp_path, mesh):
    """The hybrid-cantilever model at the clamped root on 2 ranks equals the
    single-process one (module docstring's tolerances) with the floating-frame
    invariants and the unsupported body's K and M."""
    serial, dist = _serial_and_two_ranks(tmp_path, CONFIG, *PARENT_ONLY, mesh)
    with h5py.File(dist) as f:
        assert "connections/root/statespace/D" in f and "ffrf/inertia_second_order" in f
    _same_file(_without(serial, NOT_ON_RANKS, tmp_path / "serial_part.h5"), dist)
    _same_matrices(serial, dist)


@pytest.mark.mpi
@pytest.mark.parametrize("child, ranks", [("distributing", 2), ("rigid", 3)])
@pytest.mark.parametrize("mesh", MESHES)
def test_child_point_on_ranks(tmp_path, child, ranks, mesh):
    """A child point at the tip, a distributing (RBE3) or rigid (RBE2) coupling: the
    clamped pencil (K_c, M_c) = T_c^T (K, M) T_c by PETSc's PtAP on each rank's rows of
    T_c, its own MUMPS solve; the model (Phi_C, the 12 x 12 state space) equals the
    single-process one."""
    tip = ("connections=[{name: root, region: root, point: [0.0, 0.01, 0.025], "
           "coupling: rigid}, {name: tip, region: tip, point: [0.5, 0.01, 0.025], "
           f"coupling: {child}}}]")
    serial, dist = _serial_and_two_ranks(tmp_path, CONFIG, tip, PARENT_ONLY[1], mesh,
                                         ranks=ranks)
    with h5py.File(dist) as f:
        assert f["connections/root/Phi_C"].shape == (6, 10)
    _same_file(_without(serial, NOT_ON_RANKS, tmp_path / "serial_part.h5"), dist, ranks)
    _same_matrices(serial, dist)


@pytest.mark.mpi
@pytest.mark.parametrize("mesh", MESHES)
def test_shipped_config_with_craig_bampton_on_two_ranks(tmp_path, mesh):
    """configs/cantilever_connection.yaml as shipped (a rigid root, a distributing tip
    child, 20 fixed-interface modes): the Craig-Bampton K, M and basis on every point,
    and the floating-frame invariants of that basis, equal the single-process ones."""
    serial, dist = _serial_and_two_ranks(tmp_path, CONFIG, mesh)
    with h5py.File(dist) as f:
        assert f["craig_bampton/shapes"].shape[2] == 32 and "ffrf/modal_mass" in f
    _same_file(_without(serial, NOT_ON_RANKS, tmp_path / "serial_part.h5"), dist)
    _same_matrices(serial, dist)


#: a distributing (RBE3) parent at the root, a child at the tip
RBE3_ROOT = "{name: root, region: root, point: [0.0, 0.01, 0.025], coupling: distributing}"
RIGID_TIP = "{name: tip, region: tip, point: [0.5, 0.01, 0.025], coupling: rigid}"
DISTRIBUTING_TIP = RIGID_TIP.replace("rigid", "distributing")


@pytest.mark.mpi
@pytest.mark.parametrize("overrides", [
    (f"connections=[{RBE3_ROOT}, {DISTRIBUTING_TIP}]",
     "masses=[{name: s, mass: 0.1, point: [0.5, 0.01, 0.025], region: tip, "
     "coupling: distributing}]",
     "rotation={axis: [1, 0, 0], point: [0, 0.01, 0.025], speeds_rad_s: [0, 100, 300], "
     "static_shape: true, correction_shapes: 2}"),
    (*PARENT_ONLY, "supports=[{region: tip, fix: [x]}, {region: root, bushing: "
     "{stiffness: [0, 2.0e9, 2.0e9, 1.0e6, 1.0e6, 1.0e6]}}]"),
], ids=["distributing-parent-mass-rotation-craig-bampton", "held-elsewhere-and-bushing"])
@pytest.mark.parametrize("mesh", MESHES)
def test_unsupported_pair_on_two_ranks(tmp_path, overrides, mesh):
    """The clamped pencil is not the run's (a distributing parent; supports elsewhere,
    partial and elastic; an added mass): each rank assembles its rows of the unsupported
    K and M on the partition of every DOF, PETSc's PtAP clamps the parent, MUMPS solves
    it; Craig-Bampton (the shipped 20 modes) on the same pair, nothing lifted; a
    rotating body's connection model is the one at rest. The model, the Craig-Bampton
    data, the invariants and /fe equal the single-process ones (module docstring)."""
    serial, dist = _serial_and_two_ranks(tmp_path, CONFIG, *overrides, mesh)
    _same_file(_without(serial, NOT_ON_RANKS, tmp_path / "serial_part.h5"), dist)
    _same_matrices(serial, dist)


@pytest.mark.mpi
@pytest.mark.parametrize("mesh", MESHES)
def test_free_body_with_a_distributing_parent_on_three_ranks(tmp_path, mesh):
    """No supports: the run's K and M are the unsupported pair (no second assembly).
    The run's six rigid-body modes are any basis of their subspace (test_mpi.py's free
    body), so the shapes are compared from the seventh on; the free-free modes'
    couplings R^T M psi are zero to round-off, judged against their bound sqrt(m) and
    sqrt(I_max) (|r^T M psi| <= sqrt(r^T M r) for M-orthonormal psi)."""
    serial, dist = _serial_and_two_ranks(tmp_path, CONFIG, f"connections=[{RBE3_ROOT}, "
                                         f"{RIGID_TIP}]", "supports=[]", PARENT_ONLY[1],
                                         mesh, ranks=3)
    couplings = ("ffrf/translational_coupling", "ffrf/rotational_coupling")
    _same_file(_without(serial, NOT_ON_RANKS + ("modes/shapes",) + couplings,
                        tmp_path / "serial_part.h5"), dist, 3)
    _same_matrices(serial, dist)
    with h5py.File(serial) as a, h5py.File(dist) as b:
        assert b["modes"].attrs["n_rigid"] == 6 and b["connections/root/Phi_C"].shape == (6, 10)
        x, y = a["modes/shapes"][()][..., 6:], b["modes/shapes"][()][..., 6:]
        np.testing.assert_allclose(y, x, rtol=0, atol=1e-8 * np.abs(x).max())
        D = a["body/rigid_mass_matrix"][()]
        for name, bound in zip(couplings, (D[0, 0], np.diag(D)[3:].max())):
            np.testing.assert_allclose(b[name][()], a[name][()], rtol=0,
                                       atol=1e-8 * np.sqrt(bound), err_msg=name)
