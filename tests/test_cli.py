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


# --------------------------------------------------------------------------- issue 17
# Destinations are checked before any work (classes 1, 4, 7 of issue 17). The commands
# run in this process (``pipeline.cli.main.main``); refusals come before meshing, so each
# takes milliseconds. conftest's autouse fixture restores the handlers main() installs.
import os  # noqa: E402
import shutil  # noqa: E402
import signal  # noqa: E402
from pathlib import Path  # noqa: E402


@pytest.fixture(scope="module")
def model_file(tmp_path_factory) -> Path:
    from pipeline.config import load_config
    from pipeline.run import run_pipeline

    tmp = tmp_path_factory.mktemp("guard")
    cfg = load_config(ROOT / "configs/cantilever.yaml", ["mesh.size=0.03", "modes.count=4"])
    return run_pipeline(cfg, tmp / "model.h5").output


def cli(capsys, *args) -> tuple[int, str]:
    from pipeline.cli.main import main

    code = main([str(a) for a in args])
    err = capsys.readouterr().err
    return code, err


def digest(path: Path) -> bytes:
    import hashlib

    return hashlib.sha256(path.read_bytes()).digest()


def test_run_never_writes_over_its_config_or_a_foreign_file(tmp_path, capsys):
    """Class 1: ``run c.yaml -o c.yaml`` (on main: the config replaced by HDF5, exit 0),
    through a symlink and a hard link to it, over the geometry file, over a foreign file."""
    cfg = tmp_path / "c.yaml"
    shutil.copy(ROOT / "configs/cantilever.yaml", cfg)
    (tmp_path / "link.h5").symlink_to(cfg)
    os.link(cfg, tmp_path / "hard.h5")
    (tmp_path / "foreign.h5").write_text("someone else's file")
    before = digest(cfg)
    for out, says in ((cfg, "is the input"), (tmp_path / "link.h5", "is the input"),
                      (tmp_path / "hard.h5", "is the input"),
                      (tmp_path / "foreign.h5", "not written by this package")):
        for force in ([], ["--force"]):
            if force and says != "is the input":
                continue  # --force replaces a foreign file (not run: it would solve)
            code, err = cli(capsys, "run", cfg, "--set", "mesh.size=0.03", "-o", out, *force)
            assert code == 8 and says in err and len(err.strip().splitlines()) == 1, err
    assert digest(cfg) == before and (tmp_path / "foreign.h5").read_text() == "someone else's file"
    geo = tmp_path / "beam.geo"
    shutil.copy(ROOT / "meshes/slender_beam.geo", geo)
    slender = tmp_path / "s.yaml"
    slender.write_text((ROOT / "configs/slender_beam.yaml").read_text().replace(
        "../meshes/slender_beam.geo", str(geo)))
    code, err = cli(capsys, "run", slender, "-o", geo, "--force")
    assert code == 8 and "is the input" in err, err


def test_export_never_writes_over_its_input_or_another_model(model_file, tmp_path, capsys):
    """Class 1: ``export F.h5 --to json -o F.h5`` (on main: the model replaced by JSON);
    the XDMF data file ``<stem>.h5`` landing on another model file (on main: destroyed)."""
    f = tmp_path / "F.h5"
    g = tmp_path / "G.h5"
    shutil.copy(model_file, f)
    shutil.copy(model_file, g)
    before = digest(f)
    code, err = cli(capsys, "export", f, "--to", "json", "-o", f, "--force")
    assert code == 8 and "is the input" in err, err
    code, err = cli(capsys, "export", g, "--to", "xdmf", "-o", tmp_path / "F.xdmf")
    assert code == 8 and "XDMF data file" in err and "--force" in err, err
    assert digest(f) == before
    cfg = tmp_path / "c.yaml"
    cfg.write_text("name: x\n")
    code, err = cli(capsys, "export", f, "--to", "json", "-o", cfg)
    assert code == 8 and "not written by this package" in err, err
    assert cfg.read_text() == "name: x\n"
    # what this package wrote for the purpose is replaced without --force
    out = tmp_path / "F.json"
    assert cli(capsys, "export", f, "--to", "json", "-o", out)[0] == 0
    assert cli(capsys, "export", f, "--to", "json", "-o", out)[0] == 0
    assert cli(capsys, "export", f, "--to", "xdmf", "-o", tmp_path / "H.xdmf")[0] == 0
    assert cli(capsys, "export", f, "--to", "xdmf", "-o", tmp_path / "H.xdmf")[0] == 0


def test_destinations_are_checked_before_any_work(model_file, tmp_path, capsys,
                                                  monkeypatch):
    """Class 4: a missing folder, a directory as -o, a file as a folder, a read-only
    folder: one line, exit 8, before meshing (on main: created folders, or a traceback
    after the solve)."""
    import pipeline.fe.mesh as mesh_pkg

    def no_mesh(*a, **k):
        raise AssertionError("meshing started before the destination was checked")

    monkeypatch.setattr(mesh_pkg, "mesh_body", no_mesh)
    monkeypatch.setattr("pipeline.fe.model.mesh_body", no_mesh)
    (tmp_path / "file").write_text("x")
    (tmp_path / "dir").mkdir()
    cases = [
        (["run", ROOT / "configs/cantilever.yaml", "-o", tmp_path / "nope/out.h5"], "does not exist"),
        (["run", ROOT / "configs/cantilever.yaml", "-o", tmp_path / "dir"], "is a directory"),
        (["run", ROOT / "configs/cantilever.yaml", "-o", tmp_path / "file/out.h5"], "is a file"),
        (["run", ROOT / "configs/cantilever.yaml", "-o", tmp_path / "ok.h5", "--mesh-dir",
          tmp_path / "file"], "is a file"),
        (["simulate", model_file, ROOT / "configs/cantilever.yaml", "-o", tmp_path / "dir"],
         "is a directory"),
        (["export", model_file, "--to", "mat", "-o", tmp_path / "nope/x.mat"], "does not exist"),
        (["plot", model_file, "-o", tmp_path / "file"], "is a file"),
        (["plot", model_file, "-o", tmp_path], "not made by this package"),
    ]
    for args, says in cases:
        code, err = cli(capsys, *args)
        assert code == 8 and says in err and len(err.strip().splitlines()) == 1, (args, err)
    assert not (tmp_path / "nope").exists()


@pytest.mark.skipif(shutil.which("unshare") is None or os.geteuid() != 0,
                    reason="needs unshare (a private read-only mount)")
def test_read_only_folder_is_refused_before_work(tmp_path):
    """Class 4: a read-only folder (a read-only mount: permissions do not stop root)."""
    ro = tmp_path / "ro"
    ro.mkdir()
    script = (f"mount -t tmpfs -o ro,size=1m tmpfs {ro} && cd {ROOT} && "
              f"{sys.executable} -m pipeline run configs/cantilever.yaml -o {ro}/x.h5")
    proc = subprocess.run(["unshare", "-m", "sh", "-c", script], capture_output=True,
                          text=True, timeout=120, env={**os.environ, "PYTHONPATH": str(ROOT)})
    if "mount" in proc.stderr and "permission" in proc.stderr.lower():
        pytest.skip("mount not permitted here")
    assert proc.returncode == 8, proc.stderr
    assert "read-only" in proc.stderr and "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1


def test_region_names_that_cannot_be_keys_are_refused(tmp_path):
    """Class 7: a region (physical group) named ``a/b`` or with a newline in a user's mesh
    (on main: nested HDF5 groups, then a TypeError in an exporter)."""
    import numpy as np

    from pipeline.errors import MeshError
    from pipeline.fe.mesh import read_mesh

    import gmsh

    for bad in ("a/b", "..", "x\ty", " tip"):
        path = tmp_path / "m.msh"
        gmsh.initialize(interruptible=False)
        try:
            gmsh.option.setNumber("General.Terminal", 0)
            gmsh.model.occ.addBox(0, 0, 0, 1, 1, 1)
            gmsh.model.occ.synchronize()
            gmsh.model.addPhysicalGroup(3, [1], name="body")
            gmsh.model.addPhysicalGroup(2, [1], name=bad)
            gmsh.option.setNumber("Mesh.MeshSizeMax", 0.5)
            gmsh.model.mesh.generate(3)
            gmsh.write(str(path))
        finally:
            gmsh.finalize()
        with pytest.raises(MeshError, match="region name") as info:
            read_mesh(path)
        assert "\n" not in str(info.value)
    # the writer refuses such a key whatever its origin
    from pipeline.errors import OutputError
    from pipeline.store.h5file import write_file
    from pipeline.store.tree import Dataset

    with pytest.raises(OutputError, match="control character"):
        write_file(tmp_path / "k.h5", {"mesh/regions/a\nb": Dataset(np.zeros(3), "1", "")})
    assert not (tmp_path / "k.h5").exists()


def test_batch_names_that_cannot_be_folders_are_refused(tmp_path, capsys):
    """Class 7: a batch name with a newline or a slash never becomes a folder."""
    for bad in ('"a\\nb"', '"../up"', '"a/b"', '""'):
        f = tmp_path / "b.yaml"
        f.write_text(f"batch:\n  name: {bad}\n  base: {ROOT / 'configs/cantilever.yaml'}\n"
                     "  cases: [{mesh.size: 0.03}]\n")
        code, err = cli(capsys, "batch", f, "-o", tmp_path / "out")
        assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.yaml"]


def test_fmu_and_simscape_exports_replace_their_own_files_only(model_file, tmp_path, capsys):
    """An FMU this package exported is replaced without --force; a foreign zip of that
    name is not (its modelDescription.xml does not name us); the default FMU name follows
    --model, so the plant and the filtered FMU never replace each other."""
    import zipfile

    out = tmp_path / "m.fmu"
    assert cli(capsys, "export", model_file, "--to", "fmu", "-o", out)[0] == 0
    code, err = cli(capsys, "export", model_file, "--to", "fmu", "-o", out, "--model",
                    "filtered")
    assert code == 0, err
    foreign = tmp_path / "other.fmu"
    with zipfile.ZipFile(foreign, "w") as z:
        z.writestr("modelDescription.xml", '<fmiModelDescription generationTool="X"/>')
    before = digest(foreign)
    code, err = cli(capsys, "export", model_file, "--to", "fmu", "-o", foreign)
    assert code == 8 and "--force" in err, err
    assert digest(foreign) == before
    script = tmp_path / "s.m"
    script.write_text("disp(1)\n")
    code, err = cli(capsys, "export", model_file, "--to", "simscape", "-o", tmp_path / "s.mat")
    assert code == 8 and "Simscape .m script" in err, err
    assert script.read_text() == "disp(1)\n"


def test_stdout_holds_only_what_the_command_prints(model_file, tmp_path):
    """No stray output of a library (meshio printed an empty line for every .msh it read)
    before the summary; a reader that goes away (``| head``) gets no traceback."""
    out = tmp_path / "r.h5"
    proc = run_cli("run", "configs/cantilever.yaml", "--set", "mesh.size=0.03",
                   "--set", "modes.count=4", "-o", str(out))
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.splitlines()[0].startswith("cantilever: "), proc.stdout[:200]
    reader_gone = subprocess.Popen([sys.executable, "-m", "pipeline", "inspect", str(model_file)],
                                   cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    reader_gone.stdout.close()  # before the command has printed anything
    _, err = reader_gone.communicate(timeout=120)
    assert b"Traceback" not in err, err.decode()[-2000:]
    assert reader_gone.returncode in (0, 141), err.decode()[-2000:]


_UNHANDLED_MARK = """
import ctypes, sys
from pipeline.cli import guard
# what an extension module does when an interrupt leaves code it runs by PyRun_String
ctypes.pythonapi.PyRun_SimpleString(b"raise KeyboardInterrupt")
if sys.argv[1] == "clear":
    assert guard._forget_unhandled_interrupt()
"""


@pytest.mark.skipif(sys.implementation.name != "cpython", reason="a CPython mark")
def test_handled_interrupt_does_not_end_the_process_by_sigint():
    """An interrupt that left PyRun_String code marks CPython's exit as by SIGINT (status
    -2); the guard clears the mark, so the CLI's own exit status stands."""
    def status(mode):
        return subprocess.run([sys.executable, "-c", _UNHANDLED_MARK, mode], cwd=ROOT,
                              capture_output=True, text=True, timeout=60).returncode

    assert status("clear") == 0
    assert status("keep") == -signal.SIGINT  # the mark the guard exists for


def test_interrupt_exit_code_without_the_c_function(monkeypatch):
    """The fallback where PyRun_SimpleString cannot be reached: nothing is done, and the
    exit code is still 128 + the signal."""
    import ctypes

    from pipeline.cli import guard

    class NoSymbol:
        def __getattr__(self, name):
            raise AttributeError(name)

        def __getitem__(self, name):
            raise AttributeError(name)

    monkeypatch.setattr(ctypes, "pythonapi", NoSymbol())
    assert guard._forget_unhandled_interrupt() is False
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    try:
        assert guard.exit_code(KeyboardInterrupt("SIGINT")) == 130
    finally:
        for s, h in handlers.items():
            signal.signal(s, h)
