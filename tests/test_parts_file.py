"""The partitioned mesh file (:mod:`pipeline.distributed.parts_file`) without MPI: every
field of every record it stores reads back identical (values, dtypes, shapes: bit for
bit, nothing is recomputed but each part's FE space from its arrays); the partition on
one process covers every free point once, balanced; the reader refuses, in one line, a
file that is not a parts file, another schema_version, another rank count, another
config in a key that enters the parts, and a failed checksum of the group it reads; the
partition command refuses what needs the whole mesh during the run before meshing,
and writes nothing then. The MPI runs from a parts file: tests/test_mpi_parts.py."""

from __future__ import annotations

import contextlib
import dataclasses
import io
from types import SimpleNamespace

import h5py
import numpy as np
import pytest
import scipy.sparse as sp

from conftest import ROOT
from pipeline.api import resolve_config
from pipeline.distributed import parts_file as pf
from pipeline.distributed.partition import RowPartition
from pipeline.distributed.parts import write_partitioned
from pipeline.distributed.whole import added_rigid_mass, mesh_whole, support_inputs
from pipeline.distributed.submesh import compact_nodes, split_mesh
from pipeline.errors import ConfigError, FileFormatError

#: the cantilever with materials, an added mass, a stress gauge and springs at the
#: root: every optional field of the records is present (added, springs, materials)
ASSEMBLY = ("configs/cantilever_materials.yaml",
            ["mesh.size=0.02",
             "supports=[{region: root, spring: {total: [1.0e9, 1.0e9, 1.0e9]}}]"])


def _same(a, b, where: str) -> None:
    """``a`` and ``b`` equal field by field: arrays and sparse matrices bit for bit with
    their dtypes and shapes, records recursively."""
    if dataclasses.is_dataclass(a) and not isinstance(a, type):
        assert type(a) is type(b), where
        for f in dataclasses.fields(a):
            _same(getattr(a, f.name), getattr(b, f.name), f"{where}.{f.name}")
    elif sp.issparse(a):
        assert sp.issparse(b) and a.format == b.format and a.shape == b.shape, where
        for part in ("data", "indices", "indptr"):
            x, y = getattr(a, part), getattr(b, part)
            assert x.dtype == y.dtype and np.array_equal(x, y), f"{where}.{part}"
    elif isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray), where
        assert a.dtype == b.dtype and a.shape == b.shape, (where, a.dtype, b.dtype)
        assert np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), where
    elif isinstance(a, dict):
        assert isinstance(b, dict) and list(a) == list(b), where
        for k in a:
            _same(a[k], b[k], f"{where}[{k}]")
    elif isinstance(a, (tuple, list)):
        assert type(a) is type(b) and len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            _same(x, y, f"{where}[{i}]")
    else:
        assert a == b and type(a) is type(b), (where, a, b)


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """(config, parts file of 3 parts, the whole mesh evaluated as rank 0 does)."""
    cfg = resolve_config(ROOT / ASSEMBLY[0], ASSEMBLY[1])
    path = write_partitioned(cfg, 3, tmp_path_factory.mktemp("parts") / "parts.h5")
    whole = mesh_whole(cfg, None, SimpleNamespace(rank=0, size=1))
    return cfg, path, whole


def test_every_field_round_trips(made):
    from pipeline.fe.body import node_volume_weights
    from pipeline.solve.labels import label_frame

    cfg, path, whole = made
    space = whole.space
    shared = pf.read_shared(path, cfg, 3)
    assert shared.mesh_sha256 == whole.mesh_sha256  # the same mesh as the file's
    assert (shared.ranks, shared.n_nodes, shared.order, shared.n_free) == \
        (3, space.n_nodes, space.order, whole.free.size)
    assert (shared.counts.n_tetrahedra, shared.counts.n_vertices) == \
        (space.body.n_tetrahedra, space.body.n_vertices)
    _same(whole.ports, shared.ports, "ports")
    _same(added_rigid_mass(space, whole.added), shared.added_rigid, "added_rigid")
    assert shared.config == pf.canonical_config(cfg) and shared.mesh_path == ""
    own = [pf.read_rank(path, r) for r in range(3)]
    # the partition the file holds, whole again: each rank's part is split_mesh's
    part = RowPartition(np.concatenate([p.order for _, p in own]), own[0][1].starts,
                        np.concatenate([p.dofs for _, p in own]))
    for r, mesh in enumerate(split_mesh(space, whole.materials, whole.free, part, 3,
                                        whole.added, whole.springs)):
        _same(mesh, own[r][0], f"rank {r}")
        _same(part.local(r), own[r][1], f"rank {r} partition")
    kept = pf.read_kept(path)
    expected = pf.Kept(space.node_points, compact_nodes(space.element_nodes, space.n_nodes),
                       dict(whole.regions), whole.materials,
                       label_frame(space.node_points, node_volume_weights(space)),
                       support_inputs(whole))
    _same(expected, kept, "kept")
    assert kept.support.springs is not None and own[0][0].added is not None


def test_the_partition_on_one_process_covers_every_free_point_once(made):
    """Slabs (no petsc4py here; PT-Scotch's: tests/test_mpi_parts.py): every point with
    a free DOF in exactly one part, the parts equal to one point (whole points: a part
    boundary falls between points)."""
    cfg, path, whole = made
    owned = [np.unique(pf.read_rank(path, r)[1].dofs // 3) for r in range(3)]
    every = np.concatenate(owned)
    assert np.array_equal(np.sort(every), np.unique(whole.free // 3))
    n = every.size
    assert all(abs(o.size - n / 3) <= 1 for o in owned), [o.size for o in owned]


def test_the_config_is_compared_key_by_key(made):
    cfg, path, _ = made
    # keys that act only after the FE stage may differ
    pf.read_shared(path, resolve_config(ROOT / ASSEMBLY[0], ASSEMBLY[1] + [
        "modes.count=6", "name=other", "damping={kind: uniform, ratio: 0.05}"]), 3)
    for override, key in (("mesh.size=0.021", "mesh.size"),
                          ("material={E: 70.0e9, nu: 0.33, rho: 2700.0}", "material.E"),
                          ("reduction={modes: 3, static_correction: residual}",
                           "reduction.modes")):
        other = resolve_config(ROOT / ASSEMBLY[0], ASSEMBLY[1] + [override])
        with pytest.raises(ConfigError) as err:
            pf.read_shared(path, other, 3)
        assert f"key '{key}' differs" in str(err.value) and "\n" not in str(err.value)


def test_another_rank_count_is_refused_naming_both(made):
    cfg, path, _ = made
    with pytest.raises(ConfigError, match="holds 3 parts, the run has 2 ranks"):
        pf.read_shared(path, cfg, 2)


def _copy(path, tmp_path, name="copy.h5"):
    out = tmp_path / name
    out.write_bytes(path.read_bytes())
    return out


def test_a_file_that_is_not_a_parts_file_or_another_version(made, tmp_path):
    cfg, path, _ = made
    text = tmp_path / "notes.h5"
    text.write_text("not hdf5")
    with pytest.raises(FileFormatError, match="not a parts file"):
        pf.read_shared(text, cfg, 3)
    other = _copy(path, tmp_path)
    with h5py.File(other, "r+") as h5:
        h5.attrs["schema"] = "fe-reduced-body"
    with pytest.raises(FileFormatError, match="not a parts file"):
        pf.read_shared(other, cfg, 3)
    newer = _copy(path, tmp_path, "newer.h5")
    with h5py.File(newer, "r+") as h5:
        h5.attrs["schema_version"] = pf.SCHEMA_VERSION + 1
    with pytest.raises(FileFormatError, match=f"schema_version {pf.SCHEMA_VERSION + 1}"):
        pf.read_rank(newer, 0)


@pytest.mark.parametrize("dataset, read", [
    ("shared/n_free", lambda p, cfg: pf.read_shared(p, cfg, 3)),
    ("ranks/1/node_volume", lambda p, cfg: pf.read_rank(p, 1)),
    ("kept/node_points", lambda p, cfg: pf.read_kept(p))], ids=["shared", "rank", "kept"])
def test_a_changed_value_fails_the_checksum_of_its_group(made, tmp_path, dataset, read):
    cfg, path, _ = made
    bad = _copy(path, tmp_path)
    with h5py.File(bad, "r+") as h5:
        d = h5[dataset]
        values = d[()]
        d[...] = values + 1 if np.ndim(values) == 0 else np.where(
            np.arange(values.size).reshape(values.shape) == 0, values * 1.5 + 1, values)
    with pytest.raises(FileFormatError, match="checksum of /"):
        read(bad, cfg)
    read(path, cfg)  # the file as written passes
    if dataset.startswith("ranks/1"):
        pf.read_rank(bad, 0)  # the other ranks' groups are not read, and pass


def _cli(args: list[str]) -> tuple[int, str]:
    from pipeline.cli import main

    err = io.StringIO()
    with contextlib.chdir(ROOT), contextlib.redirect_stdout(io.StringIO()), \
            contextlib.redirect_stderr(err):
        code = main(args)
    return code, err.getvalue()


@pytest.mark.parametrize("override, key", [
    ("connections=[{name: tip, region: tip, point: [0.5, 0.01, 0.025], coupling: rigid}]",
     "connections"),
    ("supports=[{region: root, fix: all}, {region: bottom, fix: [normal]}]",
     "supports[1].local_fix"),
    ("masses=[{name: s, mass: 0.2, point: [0.52, 0.01, 0.025], region: tip, "
     "coupling: rigid}]", "masses[0].coupling")],
    ids=["connections", "local-frame", "rigid-mass"])
def test_partition_refuses_what_needs_the_whole_mesh(tmp_path, monkeypatch, override, key):
    from pipeline.distributed import parts

    def no_meshing(*args, **kwargs):
        raise AssertionError("meshed before the refusal")

    monkeypatch.setattr(parts, "mesh_whole", no_meshing)
    out = tmp_path / "p.h5"
    code, err = _cli(["partition", "configs/cantilever.yaml", "--ranks", "2", "--set",
                      "mesh.size=0.02", "--set", override, "-o", str(out)])
    lines = [line for line in err.splitlines() if "WARNING" not in line]  # the config's
    assert code == 2 and len(lines) == 1 and f"config key '{key}'" in lines[0], err
    assert not out.exists() and not list(tmp_path.iterdir())


def test_partition_never_writes_over_its_inputs(tmp_path):
    config = tmp_path / "c.yaml"
    config.write_text((ROOT / "configs" / "cantilever.yaml").read_text())
    before = config.read_bytes()
    code, err = _cli(["partition", str(config), "--ranks", "2", "-o", str(config),
                      "--force"])
    assert code == 8 and "is the input" in err and config.read_bytes() == before


def test_mesh_parts_is_validated(made, tmp_path):
    _, path, _ = made
    base = ROOT / "configs" / "cantilever.yaml"
    with pytest.raises(ConfigError, match="only with modes.solver: slepc"):
        resolve_config(base, [f"mesh.parts={path}"])
    with pytest.raises(ConfigError, match="an existing parts file"):
        resolve_config(base, ["modes.solver=slepc", f"mesh.parts={tmp_path / 'none.h5'}"])
    cfg = resolve_config(base, ["modes.solver=slepc", f"mesh.parts={path}"])
    assert cfg.mesh.parts == str(path)
    from pipeline.config import config_from_dict, config_to_dict

    again = config_from_dict(config_to_dict(cfg))  # the result file's config_yaml
    assert again.mesh == cfg.mesh
    assert "parts" not in config_to_dict(resolve_config(base))["mesh"]


#: a spinning cantilever with a distributing point mass and an area mass (the rotating
#: body's added masses, which rank 0 evaluates on the whole mesh)
SPINNING = ["mesh.size=0.03", "reduction=null", "ports.outputs=[]",
            "rotation={axis: [0, 1, 1], point: [0, 0.01, 0.025], speeds_rad_s: [0, 300]}",
            "masses=[{name: sensor, mass: 0.2, inertia: [2.0e-5, 3.0e-5, 2.0e-5, 1.0e-6, "
            "0, 0], point: [0.52, 0.01, 0.025], region: tip, coupling: distributing}, "
            "{name: paint, kind: area, density: 2.0, region: top}]"]


def test_a_spinning_bodys_added_masses_round_trip(tmp_path):
    """The rotating body's added masses (the area masses' node mass and each
    distributing point mass's dofs, fit G, rigid mass M6 and point) come back from the
    shared group bit for bit, and with them the preload's port matrix."""
    from pipeline.distributed.prestress import rotation_masses

    cfg = resolve_config(ROOT / "configs/cantilever_materials.yaml", SPINNING)
    path = write_partitioned(cfg, 2, tmp_path / "spin.h5")
    whole = mesh_whole(cfg, None, SimpleNamespace(rank=0, size=1))
    area, points = rotation_masses(cfg, whole.space, whole.regions)
    shared = pf.read_shared(path, cfg, 2)
    got_area, got_points = shared.spin_masses
    _same(area.tocsr(), got_area.tocsr(), "area")
    assert len(points) == 1
    _same(tuple(tuple(np.asarray(x) for x in m) for m in points), got_points, "points")
    _same(whole.ports, shared.ports, "preload ports")
