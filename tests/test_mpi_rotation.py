"""Rotating and preloaded bodies on MPI ranks (``rotation:`` with ``modes.solver: slepc``,
:mod:`pipeline.distributed.prestress`).

The reference is the single-process run (PARDISO and scipy) in this interpreter; the
2-rank file must equal it with test_mpi.py's tolerances (frequencies 1e-8 relative,
every other float 1e-8 of its largest entry). Measured (2 ranks; 3 ranks the same):
the prestressed frequencies 3e-12 (cantilever) and 7e-13 (materials and masses); the
terms of the modes alone below 4e-11; the columns of the basis' centrifugal static
shape and correction shapes up to 9e-11 (cantilever) and 8e-10 (materials and masses)
of each dataset's largest entry: those shapes are static solves (each path refines to
a backward error of 1e-10, pipeline.solve.refine) of which only the small remainder
outside the modes' span is kept and normalised, which amplifies the solvers' difference
as the residual flexibility's is (test_mpi.py). A shaft held in a local frame
(u = T q) runs the static solves and the sweep on q: frequencies 4e-14, datasets 5e-11
(3 ranks the same). The refusals need no MPI.
"""

from __future__ import annotations

import os
import subprocess
import sys

import threading

import h5py
import numpy as np
import pytest

from conftest import ALUMINIUM, ROOT, build_model
from test_mpi import MPI_PYTHON, _mpiexec, _same_file, _serial_and_two_ranks

class _ThreadRank:
    """One emulated rank of ``size`` threads: ``alltoall`` as MPI's (each rank sends
    item r of its list to rank r), for the halo exchange without MPI."""

    def __init__(self, rank: int, size: int, shared: dict, barrier: threading.Barrier):
        self.rank, self.size, self.shared, self.barrier = rank, size, shared, barrier

    def alltoall(self, items):
        self.shared[self.rank] = list(items)
        self.barrier.wait()
        out = [self.shared[r][self.rank] for r in range(self.size)]
        self.barrier.wait()
        return out


def _on_ranks(size: int, work) -> list:
    """work(comm) on ``size`` emulated ranks (threads); the results in rank order."""
    shared, barrier, out, errors = {}, threading.Barrier(size), [None] * size, []

    def run(r):
        try:
            out[r] = work(_ThreadRank(r, size, shared, barrier))
        except BaseException as exc:  # noqa: BLE001 (reported below)
            errors.append(exc)
            barrier.abort()

    threads = [threading.Thread(target=run, args=(r,)) for r in range(size)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    if errors:
        raise errors[0]
    return out


def test_each_ranks_prestress_rows_are_the_serial_ones(tmp_path):
    """Without MPI, 3 emulated ranks: the halo exchange puts every free row of a block
    on the part's DOFs (its own and its neighbours'), and each rank's rows of the
    centrifugal loads, the spin-softening mass and the geometric stiffness of a
    displacement field (assembled on its part of the mesh with the serial kernels),
    stacked, are the serial matrices' rows, to round-off of the summation order."""
    from pipeline.distributed.blocks import RowBlock
    from pipeline.distributed.partition import slab_partition
    from pipeline.distributed.prestress import Halo, kernel_space
    from pipeline.distributed.submesh import split_mesh
    from pipeline.fe import prestress as ps
    from pipeline.fe.assemble import restrict
    from pipeline.fe.materials import assign_materials

    model = build_model(tmp_path, size=0.02)
    space, free = model.space, model.free
    size, point = 3, np.array([0.0, 0.01, 0.025])
    part = slab_partition(space.node_points, free, size)
    U = np.zeros((space.n_dofs, 2))
    U[free] = np.random.default_rng(1).standard_normal((free.size, 2)) * 1e-6
    m = ps.node_mass_matrix(space, ALUMINIUM.rho)
    loads = ps.centrifugal_loads(space, m, point)[free][part.order]
    soft = restrict(ps.tensor_mass(m, ps.entry_matrix(0, 1)), free)[part.order][:, part.order]
    geo = restrict(ps.geometric_stiffness(space, ALUMINIUM, U)[1], free)
    geo = geo[part.order][:, part.order]
    parts = list(split_mesh(space, assign_materials(space, ALUMINIUM), free, part, size))

    def rank_rows(comm):
        mesh = parts[comm.rank]
        halo = Halo(comm, mesh, part)
        U_local = halo.to_local(RowBlock(comm, part, U[free][part.owned_free(comm.rank)]))
        dofs = (3 * mesh.points[:, None] + np.arange(3)).ravel()  # global DOF of each
        assert np.array_equal(U_local, U[dofs])  # held DOFs: 0 on both
        local = kernel_space(mesh.space)
        m_r = ps.node_mass_matrix(local, mesh.materials.uniform.rho)
        return (halo.owned_rows(ps.centrifugal_loads(local, m_r, point)),
                halo.csr_rows(ps.tensor_mass(m_r, ps.entry_matrix(0, 1))).toarray(),
                halo.csr_rows(ps.geometric_stiffness(local, mesh.materials, U_local)[1]
                              ).toarray())

    rows = _on_ranks(size, rank_rows)
    for i, serial in enumerate((loads, soft.toarray(), geo.toarray())):
        stacked = np.vstack([r[i] for r in rows])
        np.testing.assert_allclose(stacked, serial, rtol=0, atol=1e-12 * np.abs(serial).max())


SPIN = ("rotation={axis: [0, 0, 1], point: [0, 0.01, 0.025], "
        "speeds_rad_s: [-100, 0, 100, 800], static_shape: true, correction_shapes: 2}")


@pytest.mark.mpi
def test_spinning_cantilever_on_two_ranks(tmp_path):
    """The basis of 10 modes, the centrifugal static shape and two correction shapes;
    the tip force is the preload; the full FE sweep at four speeds (a few seconds)."""
    serial, dist = _serial_and_two_ranks(tmp_path, "configs/cantilever.yaml",
                                         "mesh.size=0.02", SPIN)
    _same_file(serial, dist)
    with h5py.File(dist) as b:
        assert b["rotation"].attrs["n_basis"] == 13
        assert b["rotation/preload_stiffness"].shape == (1, 13, 13)
        f = b["rotation/frequencies_hz"][()]
        assert f.shape == (4, 10) and f[3, 0] > f[1, 0]  # stiffened at 800 rad/s


@pytest.mark.mpi
def test_spinning_cantilever_factor_free_on_two_ranks(tmp_path):
    """``modes.method: multigrid``: the static shapes by CG on the eigen solve's two-grid
    cycle, the sweep's modes by LOBPCG on the two-grid cycle of K(Omega), no factor of
    the whole K anywhere (a coarse mesh). LOBPCG runs to a preconditioned residual of
    1e-10 (24 sweeps): the static and correction columns keep only their small remainder
    outside the modes' span, which amplifies the modes' error, and K_G weighs the
    shapes' gradients (measured against the serial file, largest entry: at 1e-8 the
    Coriolis blocks between those columns 1.7e-8, at 1e-9 K_G 3.5e-8, at 1e-10 all
    within 1e-8)."""
    serial, dist = _serial_and_two_ranks(tmp_path, "configs/cantilever.yaml",
                                         "mesh.size=0.03", SPIN,
                                         distributed=("modes.method=multigrid",
                                                      "modes.tolerance=1e-10"))
    _same_file(serial, dist)
    with h5py.File(dist) as b:
        assert b["rotation"].attrs["n_basis"] == 13


@pytest.mark.mpi
def test_spinning_materials_and_masses_without_reduction_on_two_ranks(tmp_path):
    """Steel, aluminium and an orthotropic CFRP tip: each rank's stress takes its
    elements' own laws; the tip's distributing point mass adds its rigid-body load,
    softening and own geometric stiffness through its six motions summed over the
    ranks, an area mass its node mass on each rank's part; without a reduction rank 0
    makes the preload's port matrix alone (the serial stage's). A spin axis off the
    principal ones, the static and two correction shapes (a few seconds)."""
    spin = ("rotation={axis: [0, 1, 1], point: [0, 0.01, 0.025], "
            "speeds_rad_s: [-100, 0, 300], static_shape: true, correction_shapes: 2}")
    masses = ("masses=[{name: sensor, mass: 0.2, inertia: [2.0e-5, 3.0e-5, 2.0e-5, 1.0e-6, "
              "0, 0], point: [0.52, 0.01, 0.025], region: tip, coupling: distributing}, "
              "{name: paint, kind: area, density: 2.0, region: top}]")
    serial, dist = _serial_and_two_ranks(tmp_path, "configs/cantilever_materials.yaml",
                                         "mesh.size=0.02", masses, "reduction=null",
                                         "ports.outputs=[]", spin)
    _same_file(serial, dist)
    with h5py.File(dist) as b:
        assert b["rotation"].attrs["n_basis"] == 13 and "statespace" not in b


#: the command line with the reduced model's stability check stubbed out, so that the
#: full FE sweep meets the unstable speed first
FULL_SWEEP_FIRST = """\
import sys
import numpy as np
import pipeline.distributed.prestress as prestress
prestress.reduced_frequencies = lambda model: np.zeros(
    (model.speeds_rad_s.size, model.stiffness.shape[0]))
from pipeline.cli import main
sys.exit(main(sys.argv[1:]))
"""


@pytest.mark.mpi
@pytest.mark.parametrize("where", ["the reduced model", "the full FE model"])
def test_unstable_speed_on_two_ranks_is_named_and_nothing_written(tmp_path, where):
    """Spun about its own length the beam softens past its first frequency (~413 rad/s
    at this mesh): the reduced model's check names the speed before the sweep, and so
    does the full FE sweep where it comes first (MUMPS' LDL^T factors the indefinite
    K(Omega): SLEPc's negative eigenvalue), in one line, as the serial path."""
    entry = ["-m", "pipeline"]
    if where == "the full FE model":
        (tmp_path / "full_first.py").write_text(FULL_SWEEP_FIRST)
        entry = [str(tmp_path / "full_first.py")]
    spin = "rotation={axis: [1, 0, 0], point: [0, 0.01, 0.025], speeds_rad_s: [0, 300, 900]}"
    lines = _failing_run(tmp_path, entry, "rotation.speeds_rad_s", "mesh.size=0.025",
                         "modes.count=4", spin)
    assert all("900 rad/s" in ln and where in ln for ln in lines), lines


@pytest.mark.mpi
def test_partly_held_spinning_body_on_two_ranks_is_refused(tmp_path):
    """Held along x only, the body keeps three rigid motions: no static centrifugal
    stress (the serial path fails in its singular factorisation); one line, exit code 5,
    nothing written."""
    lines = _failing_run(tmp_path, ["-m", "pipeline"], "rotation with modes.solver",
                         "mesh.size=0.03", "supports=[{region: root, fix: [x]}]",
                         "rotation={axis: [0, 0, 1], point: [0, 0.01, 0.025], "
                         "speeds_rad_s: [0, 100]}")
    assert all("3 rigid-body mode(s)" in ln for ln in lines), lines


def _failing_run(tmp_path, entry, marker: str, *sets: str,
                 config: str = "configs/cantilever.yaml") -> list[str]:
    """Run ``entry`` (``-m pipeline`` or a script) on 2 ranks with the ``sets`` on
    ``config``; it must fail with exit code 5 and write nothing: the stderr lines that
    contain ``marker`` (at least one)."""
    out = tmp_path / "x.h5"
    args = [a for item in (*sets, "modes.solver=slepc") for a in ("--set", item)]
    proc = subprocess.run(
        [*_mpiexec(), str(MPI_PYTHON), *entry, "run", config, *args,
         "-o", str(out)], cwd=ROOT, capture_output=True, text=True, timeout=600,
        check=False, env={**os.environ, "PYTHONPATH": str(ROOT),
                          "OMPI_ALLOW_RUN_AS_ROOT": "1", "OMPI_ALLOW_RUN_AS_ROOT_CONFIRM": "1"})
    assert proc.returncode == 5, proc.stderr[-2000:]
    assert not out.exists()
    lines = [ln for ln in proc.stderr.splitlines() if marker in ln]
    assert lines, proc.stderr[-2000:]
    return lines


#: the square steel shaft of test_mpi_constraints.py (clamped on one band, held radially
#: in a cylindrical frame about its own axis on the other: u = T q), spun about that
#: axis, with the centrifugal static shape and two correction shapes
SHAFT_SPIN = {"axis": [1, 0, 0], "point": [0, 0.02, 0.02],
              "speeds_rad_s": [-500, 0, 500, 2000], "static_shape": True,
              "correction_shapes": 2}


def _spinning_shaft(tmp_path, **extra) -> str:
    """The spinning shaft's config file (test_mpi_constraints.SHAFT with ``extra``)."""
    from test_mpi_constraints import SHAFT, _config

    return _config(tmp_path, {**SHAFT, "name": "spinshaft", "rotation": SHAFT_SPIN, **extra})


@pytest.mark.mpi
def test_spinning_shaft_held_in_a_local_frame_on_two_ranks(tmp_path):
    """u = T q: the centrifugal, preload and correction static shapes solved on q by
    MUMPS (X = T K_q^-1 T^T F), the sweep on T^T K(Omega) T (PETSc's PtAP of the spin
    term); a 0.5 kg disc on distributing couplings at the free end (its rigid-body terms
    through its six motions). Measured against the serial file: frequencies 4e-14,
    datasets 5e-11 of their largest entry. Physics: spun about its own axis, a lateral
    motion softens by Omega^2 (-Omega^2 M_perp), the radial stress' stiffening is small:
    the two first bending frequencies at 2000 rad/s are sqrt(f_0^2 - (Omega / 2 pi)^2)
    within 1e-3 (measured 4e-4 above it)."""
    disc = {"name": "disc", "mass": 0.5, "inertia": [4.0e-4, 2.0e-4, 2.0e-4, 0, 0, 0],
            "point": [0.42, 0.02, 0.02], "region": "tip", "coupling": "distributing"}
    serial, dist = _serial_and_two_ranks(tmp_path, _spinning_shaft(tmp_path, masses=[disc]))
    _same_file(serial, dist)
    with h5py.File(dist) as b:
        assert b["rotation"].attrs["n_basis"] > b["rotation"].attrs["n_modes"]
        f = b["rotation/frequencies_hz"][()]
        speeds = b["rotation/speeds_rad_s"][()]
        labels = [x.decode() for x in b["modes/labels"][()]]
    bending = [labels.index("bending_y_1"), labels.index("bending_z_1")]
    softened = np.sqrt(f[1, bending] ** 2 - (speeds[3] / (2 * np.pi)) ** 2)
    np.testing.assert_allclose(f[3, bending], softened, rtol=1e-3)


@pytest.mark.mpi
def test_spinning_shaft_held_in_a_local_frame_factor_free_on_two_ranks(tmp_path):
    """``modes.method: multigrid`` under u = T q: the static shapes by CG on the two-grid
    cycle of K_q, the sweep's modes by LOBPCG on the two-grid cycle of T^T K(Omega) T
    with the coarse space T^T P, no factor anywhere. LOBPCG to a preconditioned residual
    of 1e-11 (16 sweeps, as at 1e-10): measured against the serial file, the first
    correction shape's column of the preload stiffness, a small remainder outside the
    modes' span (test_spinning_cantilever_factor_free_on_two_ranks), is 8.1e-9 of its
    largest entry at 1e-10, 9.8e-10 at 1e-11; frequencies 3e-14."""
    serial, dist = _serial_and_two_ranks(tmp_path, _spinning_shaft(tmp_path),
                                         distributed=("modes.method=multigrid",
                                                      "modes.tolerance=1e-11"))
    _same_file(serial, dist)


@pytest.mark.mpi
def test_unstable_speed_of_the_shaft_held_in_a_local_frame_is_named(tmp_path):
    """The full FE sweep on q first (the reduced check stubbed out): above its first
    bending frequency (1715 Hz, 10.8e3 rad/s) the shaft spun about its own axis softens
    past zero, MUMPS' LDL^T of T^T K(Omega) T has a negative eigenvalue: one line naming
    the speed, exit code 5, nothing written."""
    (tmp_path / "full_first.py").write_text(FULL_SWEEP_FIRST)
    lines = _failing_run(tmp_path, [str(tmp_path / "full_first.py")], "rotation.speeds_rad_s",
                         "rotation.speeds_rad_s=[0, 500, 12000]",
                         config=_spinning_shaft(tmp_path))
    assert all("12000 rad/s" in ln and "the full FE model" in ln for ln in lines), lines


def test_cli_refuses_a_spinning_body_with_a_rigid_coupling_before_meshing(tmp_path):
    """What stays refused on every path, ``modes.solver: slepc`` included: a rigidly
    coupled mass on a spinning body (the config's validation: exit code 2, one line
    naming the key, nothing written)."""
    out = tmp_path / "x.h5"
    mass = ("masses=[{name: m, mass: 0.3, inertia: [2e-4, 3e-4, 4e-4, 0, 0, 0], "
            "point: [0.52, 0.01, 0.025], region: tip, coupling: rigid}]")
    proc = subprocess.run([sys.executable, "-m", "pipeline", "run", "configs/cantilever.yaml",
                           "--set", "modes.solver=slepc", "--set", SPIN, "--set", mass,
                           "-o", str(out)], cwd=ROOT, capture_output=True, text=True,
                          timeout=120, check=False)
    assert proc.returncode == 2, proc.stderr
    assert "masses[0].coupling" in proc.stderr.strip().splitlines()[-1]
    assert not out.exists()
