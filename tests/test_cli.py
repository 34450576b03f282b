"""The command line: exit codes and one clear message per error."""

from __future__ import annotations

import subprocess
import sys

import pytest

from conftest import ROOT


def run_cli(*args, cwd=ROOT):
    return subprocess.run([sys.executable, "-m", "pipeline", *args], cwd=cwd,
                          capture_output=True, text=True, timeout=300)


def test_run_and_inspect(tmp_path):
    out = tmp_path / "c.h5"
    proc = run_cli("-q", "run", "configs/cantilever_inplane.yaml", "--set", "mesh.size=0.02",
                   "-o", str(out), "--mesh-dir", str(tmp_path))
    assert proc.returncode == 0, proc.stderr
    assert "bending_z_1" in proc.stdout and out.exists()
    proc = run_cli("inspect", str(out))
    assert proc.returncode == 0, proc.stderr
    assert "cantilever_inplane" in proc.stdout and "Hz" in proc.stdout


@pytest.mark.parametrize("args, code, message", [
    (["run", "configs/cantilever.yaml", "--set", "material.E=-5"], 2,
     "error: configs/cantilever.yaml: config key 'material.E': got -5.0"),
    (["run", "configs/cantilever.yaml", "--set", "materail.E=1"], 2,
     "config key 'materail' is not known"),
    (["run", "configs/cantilever.yaml", "--set", "mesh.size=9"], 2, "config key 'mesh.size'"),
    (["run", "configs/nope.yaml"], 2, "config file 'configs/nope.yaml': not found"),
    (["inspect", "configs/cantilever.yaml"], 7, "not a readable HDF5 file"),
])
def test_errors_exit_non_zero_with_one_message(args, code, message):
    proc = run_cli(*args)
    assert proc.returncode == code, (proc.returncode, proc.stderr)
    assert message in proc.stderr
    assert "Traceback" not in proc.stderr


def test_mesh_failure_is_an_error_not_a_crash(tmp_path):
    from pipeline.config import Geometry, MeshSpec
    from pipeline.errors import MeshError
    from pipeline.fe.mesh import generate_mesh, read_mesh

    with pytest.raises(MeshError, match="gmsh could not mesh"):
        generate_mesh(Geometry("box", 0.0, 0.02, 0.05), MeshSpec(size=0.01), tmp_path / "x.msh")
    assert not (tmp_path / "x.msh").exists()
    junk = tmp_path / "junk.msh"
    junk.write_text("not a mesh")
    with pytest.raises(MeshError, match="junk.msh': meshio cannot read it"):
        read_mesh(junk)


def test_degenerate_and_non_tetrahedral_meshes_are_refused(tmp_path):
    import meshio
    import numpy as np

    from pipeline.errors import MeshError
    from pipeline.fe.mesh import read_mesh

    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.5, 0.5, 0.0]], float)
    flat = tmp_path / "flat.vtu"
    meshio.write(flat, meshio.Mesh(pts, [("tetra", np.array([[0, 1, 2, 3]]))]))
    with pytest.raises(MeshError, match="zero volume"):
        read_mesh(flat)
    tri = tmp_path / "tri.vtu"
    meshio.write(tri, meshio.Mesh(pts, [("triangle", np.array([[0, 1, 2]]))]))
    with pytest.raises(MeshError, match="has no tetrahedra"):
        read_mesh(tri)


def test_stale_mesh_temporaries_of_dead_processes_are_removed(tmp_path):
    from pipeline._util.atomic import host_tag
    from pipeline.config import Geometry, MeshSpec
    from pipeline.fe.mesh import generate_mesh

    dead = tmp_path / f".box.msh.{host_tag()}.999999999.partial.msh"  # no such pid
    dead.write_text("partial")
    alive = tmp_path / f".box.msh.{host_tag()}.1.partial.msh"  # pid 1 always exists
    alive.write_text("in progress")
    generate_mesh(Geometry("box", 0.1, 0.02, 0.02), MeshSpec(size=0.02), tmp_path / "box.msh")
    assert not dead.exists() and alive.exists() and (tmp_path / "box.msh").exists()


def test_run_prints_a_short_summary_and_stage_lines_when_piped(tmp_path):
    out = tmp_path / "c.h5"
    args = ("run", "configs/cantilever.yaml", "--set", "mesh.size=0.01", "-o", str(out),
            "--mesh-dir", str(tmp_path))
    proc = run_cli(*args)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    first = [i for i, line in enumerate(lines) if line.startswith("cantilever: ")][0]
    assert lines[first + 1].split() == ["mode", "f", "[Hz]", "label"]
    assert "bending_z_1" in proc.stdout and "reduced model: 4 modes" in proc.stdout
    # the lumped chain's comparison table only with -v
    assert "(table with -v)" in proc.stdout and "refined        1" not in proc.stdout
    assert lines[-2:] == [f"look at it: python -m pipeline inspect {out}",
                          f"            python -m pipeline plot {out}"]
    # stderr is not a terminal: one line per stage start and end, with the time taken
    assert "pipeline.progress: assemble done in" in proc.stderr
    assert "pipeline.run: modes done in" in proc.stderr
    assert "Lanczos started (" in proc.stderr or "ARPACK done" in proc.stderr
    verbose = run_cli("-v", *args)
    assert verbose.returncode == 0, verbose.stderr
    assert "refined        1" in verbose.stdout and "(table with -v)" not in verbose.stdout
