"""A run whose ranks read their parts from a partitioned mesh file (``mesh.parts``, made
by ``python -m pipeline partition``; issue 38: "each rank meshes or reads its part").

With ``make mpi-env``: the cantilever on 2 ranks from a parts file (PT-Scotch's
partition on one process) gives the single-process file (tests/test_mpi.py's
``_same_file`` and its tolerances), with MUMPS' factor and factor-free; no rank runs
gmsh and no rank but 0 receives a whole-length array (tests/mpi_ranks.py asserts both
on every rank); the file records the parts file and its signature in ``/run``. The
path that meshes in the run and the parts path give the same file with the same
(slab) partition: the same rows on the same ranks, assembled from the same elements
in the same order, so the mesh, the held DOFs and the mass properties are the same bit
for bit, and the solver's results to the tolerances of ``_same_file``. A parts
file that does not fit the run is refused in one line before any assembly, nothing
written. PT-Scotch's partition into N parts on one process covers every free point
once and is balanced. Without MPI: tests/test_parts_file.py.
"""

from __future__ import annotations

import os
import re
import subprocess

import h5py
import numpy as np
import pytest

from conftest import ROOT, rank_error_lines
from test_mpi import (MPI_PYTHON, _mpiexec, _run, _run_here, _same_file,
                      _serial_and_two_ranks)

pytestmark = pytest.mark.mpi


def _partition(tmp_path, ranks: int, *overrides: str, name: str = "parts.h5",
               config: str = "configs/cantilever.yaml"):
    """``python -m pipeline partition CONFIG --ranks N`` (in .venv-mpi: PT-Scotch
    through PETSc); the parts file."""
    out = tmp_path / name
    args = [a for item in overrides for a in ("--set", item)]
    proc = subprocess.run([str(MPI_PYTHON), "-m", "pipeline", "partition",
                           config, "--ranks", str(ranks), *args, "-o",
                           str(out)], cwd=ROOT, capture_output=True, text=True, timeout=300,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out


@pytest.mark.parametrize("method, size", [("factor", 0.01), ("multigrid", 0.03)],
                         ids=["mumps", "factor-free"])
def test_two_ranks_from_a_parts_file_give_the_single_process_file(tmp_path, method, size):
    mpiexec = _mpiexec()
    parts = _partition(tmp_path, 2, f"mesh.size={size}")
    with h5py.File(parts) as h5:
        assert h5["shared/partition"].asstr()[()] == "graph"
        signature = h5.attrs["content_sha256"]
    serial, dist = tmp_path / "serial.h5", tmp_path / "mpi.h5"
    _run_here(["run", "configs/cantilever.yaml", "--set", f"mesh.size={size}", "-o",
               str(serial)])
    proc = _run([*mpiexec, str(MPI_PYTHON), str(ROOT / "tests" / "mpi_ranks.py"), str(dist),
                 f"mesh.size={size}", f"modes.method={method}", f"mesh.parts={parts}",
                 *(["modes.tolerance=1e-8"] if method == "multigrid" else [])],
                tmp_path, timeout=600)
    held = sorted(m.split() for m in re.findall(
        r"rank \d+ rows \d+ of \d+ points \d+ of \d+ gmsh \d+ part \d+ of \d+ "
        r"elements \d+ of \d+", proc.stdout))
    assert [h[1] for h in held] == ["0", "1"], proc.stdout[-2000:]
    assert [int(h[11]) for h in held] == [0, 0], held  # no rank meshed
    _same_file(serial, dist)
    with h5py.File(dist) as h5:
        assert h5["run"].attrs["parts_file"] == str(parts)
        assert h5["run"].attrs["parts_sha256"] == signature
    from pipeline.apps.summary import summarize

    run_line = next(x for x in summarize(dist).splitlines() if x.startswith("run "))
    assert run_line.endswith(f"; 2 MPI ranks, each reading its part of {parts}"), run_line


def test_the_run_that_meshes_and_the_parts_path_write_the_same_file(tmp_path, monkeypatch):
    mpiexec = _mpiexec()
    monkeypatch.setenv("PETSC_OPTIONS", "-pipeline_partition slab")  # every process here
    parts = _partition(tmp_path, 2, "mesh.size=0.02")
    with h5py.File(parts) as h5:
        assert h5["shared/partition"].asstr()[()] == "slab"
    args = ["-m", "pipeline", "run", "configs/cantilever.yaml", "--set", "mesh.size=0.02",
            "--set", "modes.solver=slepc"]
    meshed, read = tmp_path / "meshed.h5", tmp_path / "read.h5"
    for out, extra in ((meshed, []), (read, ["--set", f"mesh.parts={parts}"])):
        _run([*mpiexec, "-x", "PETSC_OPTIONS", str(MPI_PYTHON), *args, *extra, "-o",
              str(out)], tmp_path, timeout=600)
    _same_file(meshed, read, ranks=2)
    # what is made before the eigensolver exactly: the mesh, its regions, the held DOFs
    # and the body's mass properties (summed over the same rows in the same order);
    # the solver's results differ at round-off (two runs of either path differ by
    # 1e-12 of the shapes: MUMPS' parallel factorisation is not bit-reproducible)
    with h5py.File(meshed) as a, h5py.File(read) as b:
        names = []
        a.visititems(lambda n, o: names.append(n) if isinstance(o, h5py.Dataset) else None)
        exact = [n for n in names if n.startswith(("mesh/", "body/"))]
        assert any(n.startswith("body/") for n in exact) and "mesh/fixed_dofs" in exact
        for name in exact:
            assert np.array_equal(a[name][()], b[name][()]), name
        assert "parts_file" not in a["run"].attrs and "parts_file" in b["run"].attrs


@pytest.fixture(scope="module")
def small_parts(tmp_path_factory):
    """A parts file of the cantilever (mesh.size 0.03) for 2 ranks, made in this process
    (slabs: no petsc4py here), and its folder."""
    from pipeline.api import resolve_config
    from pipeline.distributed.parts import write_partitioned

    folder = tmp_path_factory.mktemp("refusals")
    cfg = resolve_config(ROOT / "configs" / "cantilever.yaml", ["mesh.size=0.03"])
    return write_partitioned(cfg, 2, folder / "parts.h5"), folder


def _spoil(kind: str, parts, folder):
    """A copy of ``parts`` spoilt as ``kind`` says, and the overrides of the run."""
    bad = folder / f"{kind}.h5"
    overrides = ["mesh.size=0.03"]
    if kind == "text":
        bad.write_text("not a parts file")
        return bad, overrides
    bad.write_bytes(parts.read_bytes())
    with h5py.File(bad, "r+") as h5:
        if kind == "version":
            h5.attrs["schema_version"] = 99
        elif kind == "ranks":
            h5.attrs["ranks"] = 3
        elif kind == "checksum":
            d = h5["ranks/1/node_volume"]
            d[0] = d[0] * 2
    if kind == "config":
        overrides = ["mesh.size=0.025"]
    return bad, overrides


@pytest.mark.parametrize("kind, code, text", [
    ("text", 7, "not a parts file"), ("version", 7, "schema_version 99"),
    ("ranks", 2, "holds 3 parts, the run has 2 ranks"),
    ("config", 2, "key 'mesh.size' differs"), ("checksum", 7, "checksum of /ranks/1 fails")])
def test_a_parts_file_that_does_not_fit_is_refused_in_one_line(small_parts, kind, code, text):
    mpiexec = _mpiexec()
    parts, folder = small_parts
    bad, overrides = _spoil(kind, parts, folder)
    out = folder / f"{kind}-result.h5"
    args = [a for item in overrides + ["modes.solver=slepc", f"mesh.parts={bad}"]
            for a in ("--set", item)]
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMPI_ALLOW_RUN_AS_ROOT": "1",
           "OMPI_ALLOW_RUN_AS_ROOT_CONFIRM": "1"}
    proc = subprocess.run([*mpiexec, str(MPI_PYTHON), "-m", "pipeline", "run",
                           "configs/cantilever.yaml", *args, "-o", str(out)], cwd=ROOT,
                          env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == code, proc.stderr[-2000:]
    # the rank that refuses says why; a rank stopped meanwhile says SIGTERM (the
    # abort of tests/test_mpi.py's failing rank); nothing assembled, nothing written
    lines = rank_error_lines(proc.stderr)
    why = [line for line in lines if text in line]
    assert len(why) == 1 and all(line in why or line.endswith("SIGTERM") for line in lines), \
        proc.stderr[-2000:]
    assert "assemble ..." not in proc.stderr and not out.exists()


def test_the_n_part_partition_on_one_process_is_balanced(tmp_path):
    """PT-Scotch through PETSc on COMM_SELF into 4 parts: every point with a free DOF in
    exactly one part, each part within 2% of the mean (PETSc's PT-Scotch load imbalance
    tolerance is 1% by default, -mat_partitioning_ptscotch_imbalance; twice that, as
    Scotch's bound is on the strategy's target, not guaranteed), and the host's
    options untouched (none set after the command)."""
    _mpiexec()  # skips without the MPI environment
    parts = _partition(tmp_path, 4, "mesh.size=0.01")
    with h5py.File(parts) as h5:
        assert h5["shared/partition"].asstr()[()] == "graph"
        owned = [np.unique(h5[f"ranks/{r}/row_dofs"][()] // 3) for r in range(4)]
        n_free = int(h5["shared/n_free"][()])
    every = np.concatenate(owned)
    assert every.size == np.unique(every).size == n_free // 3  # the cantilever: whole points
    mean = every.size / 4
    assert all(abs(o.size - mean) <= 0.02 * mean for o in owned), [o.size for o in owned]


def test_a_spinning_body_with_added_masses_from_a_parts_file(tmp_path):
    """A rotating body reads its preloads (port matrices) and its added masses (the
    area masses' node mass, the distributing point mass's fit) from the parts file's
    shared group: steel, aluminium and CFRP, a point and an area mass, a spin axis off
    the principal ones, the static and two correction shapes; 2 ranks from the parts
    file give the single-process file (tests/test_mpi_rotation.py's case, read from a
    parts file)."""
    config = "configs/cantilever_materials.yaml"
    spin = ("rotation={axis: [0, 1, 1], point: [0, 0.01, 0.025], "
            "speeds_rad_s: [-100, 0, 300], static_shape: true, correction_shapes: 2}")
    masses = ("masses=[{name: sensor, mass: 0.2, inertia: [2.0e-5, 3.0e-5, 2.0e-5, 1.0e-6, "
              "0, 0], point: [0.52, 0.01, 0.025], region: tip, coupling: distributing}, "
              "{name: paint, kind: area, density: 2.0, region: top}]")
    overrides = ("mesh.size=0.02", masses, "reduction=null", "ports.outputs=[]", spin)
    parts = _partition(tmp_path, 2, *overrides, config=config)
    serial, dist = _serial_and_two_ranks(tmp_path, config, *overrides,
                                         distributed=(f"mesh.parts={parts}",))
    _same_file(serial, dist)
    with h5py.File(dist) as b:
        assert b["rotation"].attrs["n_basis"] == 13 and "statespace" not in b
        assert b["run"].attrs["parts_file"] == str(parts)
