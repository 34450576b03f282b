"""Regions of every dimension: faces, lines and points from selectors and from mesh files,
supports and ports on them, checked against CalculiX and plate theory.

The plate: 0.2 m x 0.2 m x 5 mm aluminium, simply supported along its four bottom edges
(u_z = 0 on the four edge lines) with the in-plane rigid motion removed minimally (u_x,
u_y at the corner (0, 0, 0), u_y at the corner (0.2, 0, 0)).
"""

from __future__ import annotations

import logging
import math
import os
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml

from calculix import CCX, run_frequencies, write_frequency_deck
from conftest import ROOT
from pipeline.config import RegionSelector, config_from_dict
from pipeline.errors import ConfigError, RegionError
from pipeline.fe.mesh import read_mesh
from pipeline.fe.model import build_fe_model
from pipeline.fe.ports import port_matrices
from pipeline.fe.regions import select_region
from pipeline.fe.space import build_space, region_nodes, weighted_region

A, T = 0.2, 0.005  # plate side and thickness, m
E, NU, RHO = 69.0e9, 0.33, 2700.0
EPS = 1e-6  # selector margin, m (far below the element size, far above round-off)


def _edge_box(lower, upper) -> dict:
    return {"kind": "box", "lower": [c - EPS for c in lower], "upper": [c + EPS for c in upper]}


#: the four bottom edges as boxes shrunk onto them, the two corners as spheres
SELECTORS = {
    "e_y0": _edge_box([0, 0, 0], [A, 0, 0]), "e_y1": _edge_box([0, A, 0], [A, A, 0]),
    "e_x0": _edge_box([0, 0, 0], [0, A, 0]), "e_x1": _edge_box([A, 0, 0], [A, A, 0]),
    "c00": {"kind": "sphere", "point": [0, 0, 0], "radius": EPS},
    "c10": {"kind": "sphere", "point": [A, 0, 0], "radius": EPS},
}
SS_SUPPORTS = ([{"region": r, "fix": ["z"]} for r in ("e_y0", "e_y1", "e_x0", "e_x1")]
               + [{"region": "c00", "fix": ["x", "y"]}, {"region": "c10", "fix": ["y"]}])


def plate_config(size: float, **extra) -> dict:
    raw = {"name": "plate", "geometry": {"kind": "box", "length": A, "height": A, "depth": T},
           "mesh": {"order": 2, "size": size}, "material": {"E": E, "nu": NU, "rho": RHO},
           "regions": SELECTORS, "supports": SS_SUPPORTS, "modes": {"count": 4}}
    raw.update(extra)
    return raw


def kirchhoff_f11() -> float:
    """Hz: f11 = (pi / 2) (2 / a^2) sqrt(D / (rho h)), D = E h^3 / (12 (1 - nu^2)), the
    simply supported square Kirchhoff plate."""
    D = E * T**3 / (12.0 * (1.0 - NU**2))
    return math.pi / 2.0 * (2.0 / A**2) * math.sqrt(D / (RHO * T))


def geometric_fixed_dofs(points: np.ndarray) -> np.ndarray:
    """The DOFs the simply supported plate must fix, found from coordinates alone: z of
    every node on a bottom edge (vertices and mid-edge nodes), x and y at (0, 0, 0), y at
    (A, 0, 0)."""
    x, y, z = points.T
    tol = 1e-9
    on_edge = (abs(z) < tol) & ((abs(x) < tol) | (abs(x - A) < tol) | (abs(y) < tol)
                                | (abs(y - A) < tol))
    c00 = np.flatnonzero((abs(x) < tol) & (abs(y) < tol) & (abs(z) < tol))
    c10 = np.flatnonzero((abs(x - A) < tol) & (abs(y) < tol) & (abs(z) < tol))
    return np.unique(np.concatenate([3 * np.flatnonzero(on_edge) + 2, 3 * c00, 3 * c00 + 1,
                                     3 * c10 + 1]))


def run_cli(config: dict, tmp_path: Path, name: str) -> subprocess.CompletedProcess:
    cfg = tmp_path / f"{name}.yaml"
    cfg.write_text(yaml.safe_dump(config))
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-m", "pipeline", "-v", "run", str(cfg), "-o",
                           str(tmp_path / f"{name}.h5")], capture_output=True, text=True,
                          env=env, timeout=300, cwd=tmp_path)


# --------------------------------------------------------------------------- selectors
@pytest.fixture(scope="module")
def plate_model():
    cfg = config_from_dict(plate_config(0.02))
    return cfg, build_fe_model(cfg)


def test_selectors_shrunk_onto_edges_and_vertices_give_lines_and_points(plate_model):
    cfg, fe = plate_model
    space = fe.space
    for name in ("e_y0", "e_y1", "e_x0", "e_x1"):
        cells = fe.regions[name]
        assert cells.shape[1] == 2  # a line: edges
        line = weighted_region(space, name, cells)
        assert line.dimension == 1
        assert line.measure == pytest.approx(A, rel=1e-12)  # the edge's length
        assert line.weights.sum() == pytest.approx(A, rel=1e-12)
        # P2: n edges carry n + 1 vertices and n mid-edge nodes, all on the edge
        nodes = region_nodes(space, cells)
        assert nodes.size == 2 * cells.shape[0] + 1
        assert np.allclose(space.node_points[nodes, 2], 0.0, atol=1e-12)
    for name, corner in (("c00", [0, 0, 0]), ("c10", [A, 0, 0])):
        cells = fe.regions[name]
        assert cells.shape == (1, 1)  # a point: one vertex node
        assert np.allclose(space.node_points[region_nodes(space, cells)], [corner], atol=1e-12)
    # the box's own faces are still faces; a selector reaching a facet still gives a face
    assert fe.regions["root"].shape[1] == 3
    top = select_region(space, RegionSelector("plane", point=(0, 0, T), normal=(0, 0, 1)))
    assert top.shape[1] == 3
    assert weighted_region(space, "top", top).measure == pytest.approx(A * A, rel=1e-12)
    # the supports fix exactly the DOFs found from the coordinates
    np.testing.assert_array_equal(fe.fixed, geometric_fixed_dofs(space.node_points))


def test_force_on_a_point_acts_at_its_node_and_a_displacement_reads_it(plate_model):
    cfg, fe = plate_model
    node = int(region_nodes(fe.space, fe.regions["c10"])[0])
    ports = config_from_dict(plate_config(0.02, ports={
        "inputs": [{"name": "f", "region": "c10", "kind": "force", "direction": [0, 0, 2]}],
        "outputs": [{"name": "u", "region": "c10", "kind": "displacement",
                     "direction": [0, 0, 1]},
                    {"name": "w_edge", "region": "e_y1", "kind": "displacement",
                     "direction": [0, 0, 1]}]})).ports
    pm = port_matrices(fe.space, fe.regions, ports)
    f = pm.F.toarray()[:, 0]
    assert np.flatnonzero(f).tolist() == [3 * node + 2] and f[3 * node + 2] == 1.0
    assert np.flatnonzero(pm.T.toarray()[0]).tolist() == [3 * node + 2]
    # on a line: the length-weighted mean, which reads a uniform motion exactly
    u = np.zeros(fe.space.n_dofs)
    u[2::3] = 1.5
    assert pm.T.toarray()[1] @ u == pytest.approx(1.5, rel=1e-12)
    # a moment on a single node has nothing to turn: one line, naming the key
    moment = config_from_dict(plate_config(0.02, ports={"inputs": [
        {"name": "m", "region": "c10", "kind": "moment", "direction": [0, 0, 1]}]})).ports
    with pytest.raises(RegionError, match=r"ports\.inputs\[0\].*region 'c10' cannot carry"):
        port_matrices(fe.space, fe.regions, moment)


def test_the_exudyn_node_sets_weigh_lines_and_points_as_the_ports_do(plate_model):
    from pipeline.apps.exports.exudyn import region_node_weights

    _, fe = plate_model
    for name in ("e_x1", "c00", "root"):
        cells = fe.regions[name]
        nodes, weights = region_node_weights(fe.space.node_points, fe.space.element_nodes, cells)
        ref = weighted_region(fe.space, name, cells)
        keep = ref.weights > 0  # P2 face: corners weigh 0 in both, listed by the export
        np.testing.assert_array_equal(nodes[weights > 0], ref.nodes[keep])
        np.testing.assert_allclose(weights[weights > 0], ref.weights[keep] / ref.measure,
                                   rtol=1e-12)


def test_a_gauge_on_a_line_is_refused_before_assembly():
    raw = plate_config(0.02, ports={"outputs": [
        {"name": "g", "region": "e_y0", "kind": "strain", "direction": [1, 0, 0]}]})
    with pytest.raises(RegionError, match=r"ports\.outputs\[0\]\.region.*'e_y0' is a line of "
                       r"\d+ edges; expected a face region"):
        build_fe_model(config_from_dict(raw))


def test_simply_supported_plate_against_kirchhoff_theory(tmp_path):
    """The first frequency against the Kirchhoff plate's f11 = 607.1 Hz. The 3D body is a
    little softer: shear deformation and rotary inertia (Mindlin) lower f11 by about
    (1/2) (h^2/12) k^2 (1 + 2 / (kappa (1 - nu))) = 0.24 % for h/a = 1/40, k^2 = 2 (pi/a)^2,
    kappa = 5/6; and a line support on a solid's edge is a singular load whose local
    flexibility grows (logarithmically) as the mesh is refined: measured 606.38, 601.70,
    600.14 Hz at 20, 10, 5 mm. So at 10 mm the 3D frequency lies between 0.97 and 0.999
    times f11, and below the value at 20 mm."""
    out = run_cli(plate_config(0.01), tmp_path, "plate")
    assert out.returncode == 0, out.stderr[-2000:]
    assert "it is a line of 20 edges" in out.stderr and "point set of 1 vertex" in out.stderr
    with h5py.File(tmp_path / "plate.h5") as h5:
        f1 = float(h5["modes/frequencies_hz"][0])
        assert h5["mesh/regions/e_y0"].shape[1] == 2 and h5["mesh/regions/c00"].shape == (1, 1)
    assert 0.97 * kirchhoff_f11() < f1 < 0.999 * kirchhoff_f11()
    shown = subprocess.run([sys.executable, "-m", "pipeline", "inspect",
                            str(tmp_path / "plate.h5")], capture_output=True, text=True, timeout=120,
                           env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert "c00 (point)" in shown.stdout and "e_y0 (line)" in shown.stdout
    assert "root," in shown.stdout  # a face region goes unmarked
    assert f1 < 606.38


# --------------------------------------------------------------------------- mesh files
@pytest.fixture(scope="module")
def plate_msh(tmp_path_factory) -> Path:
    """A gmsh .msh of the plate (20 mm elements) with physical groups of every dimension:
    'bottom_edges' (4 curves), 'corner_a' and 'corner_b' (points), 'top' (a surface) and
    'plate' (the volume), and an unnamed group (the bottom face)."""
    import gmsh

    path = tmp_path_factory.mktemp("msh") / "plate.msh"
    gmsh.initialize(interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("plate")
        gmsh.model.occ.addBox(0, 0, 0, A, A, T)
        gmsh.model.occ.synchronize()
        box = gmsh.model.getEntitiesInBoundingBox
        edges = [t for _, t in box(-EPS, -EPS, -EPS, A + EPS, A + EPS, EPS, 1)]
        assert len(edges) == 4
        gmsh.model.addPhysicalGroup(1, edges, name="bottom_edges")
        for name, x in (("corner_a", 0.0), ("corner_b", A)):
            gmsh.model.addPhysicalGroup(0, [t for _, t in box(x - EPS, -EPS, -EPS, x + EPS, EPS,
                                                              EPS, 0)], name=name)
        gmsh.model.addPhysicalGroup(2, [t for _, t in box(-EPS, -EPS, T - EPS, A + EPS, A + EPS,
                                                          T + EPS, 2)], name="top")
        gmsh.model.addPhysicalGroup(3, [1], name="plate")
        gmsh.model.addPhysicalGroup(2, [t for _, t in box(-EPS, -EPS, -EPS, A + EPS, A + EPS,
                                                          EPS, 2)])  # no name: said, unused
        gmsh.option.setNumber("Mesh.MeshSizeMax", 0.02)
        gmsh.model.mesh.generate(3)
        gmsh.write(str(path))
    finally:
        gmsh.finalize()
    return path


def test_mesh_file_keeps_physical_groups_of_every_dimension(plate_msh, caplog):
    with caplog.at_level(logging.INFO, logger="pipeline.fe.mesh.read"):
        body = read_mesh(plate_msh)
    assert body.regions["bottom_edges"].shape[1] == 2
    assert body.regions["corner_a"].shape == (1, 1)
    assert body.regions["top"].shape[1] == 3
    assert "plate" not in body.regions and "volume group" in body.other_groups["plate"]
    assert "group 'plate' is a volume group" in caplog.text
    assert "physical groups without a name are no regions (tags by cell type: triangle: " \
        in caplog.text
    space = build_space(body, 2)
    line = weighted_region(space, "bottom_edges", body.regions["bottom_edges"])
    assert line.measure == pytest.approx(4 * A, rel=1e-12)


def mesh_plate_config(msh: Path, **extra) -> dict:
    """The plate from the mesh file: no mesh section (mesh.size does not apply), supports
    on the file's groups, and a port on a selector of the config's own regions."""
    raw = {"name": "plate_msh", "geometry": {"kind": "mesh", "path": str(msh)},
           "material": {"E": E, "nu": NU, "rho": RHO},
           "regions": {"middle": {"kind": "sphere", "point": [A / 2, A / 2, T], "radius": 0.03}},
           "supports": [{"region": "bottom_edges", "fix": ["z"]},
                        {"region": "corner_a", "fix": ["x", "y"]},
                        {"region": "corner_b", "fix": ["y"]}],
           "modes": {"count": 4},
           "ports": {"inputs": [{"name": "f", "region": "corner_b", "kind": "force",
                                 "direction": [1, 0, 0]}],
                     "outputs": [{"name": "w", "region": "middle", "kind": "displacement",
                                  "direction": [0, 0, 1]}]}}
    raw.update(extra)
    return raw


@pytest.mark.skipif(CCX is None, reason="CalculiX (ccx) is not installed")
def test_plate_from_mesh_file_groups_against_calculix(plate_msh, tmp_path):
    """The same mesh, the same node sets (found from coordinates, not from our regions) in
    CalculiX. Its C3D10 integrates the mass matrix with 4 points (a degree-2 rule for a
    degree-4 integrand) where we integrate exactly, so the two differ by a discretisation
    term that falls with the element size (measured on the box plate: 5.6e-5, 4.0e-6,
    7.2e-7 at 20, 10, 5 mm): at 20 mm, 1e-4 bounds it. The supports themselves are
    compared exactly: the fixed DOFs equal the geometric node sets."""
    out = run_cli(mesh_plate_config(plate_msh), tmp_path, "plate_msh")
    assert out.returncode == 0, out.stderr[-2000:]
    with h5py.File(tmp_path / "plate_msh.h5") as h5:
        points, cells = h5["mesh/points"][()], h5["mesh/cells/tetra10"][()]
        ours, fixed = h5["modes/frequencies_hz"][()], h5["mesh/fixed_dofs"][()]
    geo = geometric_fixed_dofs(points)
    np.testing.assert_array_equal(fixed, geo)
    sets = {f"C{c}": (np.unique(geo[geo % 3 == c] // 3), [c + 1]) for c in range(3)}
    deck = write_frequency_deck(tmp_path / "plate.inp", points, cells, E, NU, RHO, sets, 4)
    theirs = run_frequencies(deck)[:4]
    np.testing.assert_allclose(ours, theirs, rtol=1e-4)
    assert 0.95 * kirchhoff_f11() < ours[0] < 1.01 * kirchhoff_f11()


@pytest.mark.slow
@pytest.mark.skipif(CCX is None, reason="CalculiX (ccx) is not installed")
def test_plate_on_edge_selectors_against_calculix_fine_mesh(tmp_path):
    """The box plate on its selector lines at 5 mm (71k DOFs), where CalculiX's 4-point
    mass integration differs from ours by 7.2e-7 at most (see above): within 2e-6."""
    out = run_cli(plate_config(0.005), tmp_path, "fine")
    assert out.returncode == 0, out.stderr[-2000:]
    with h5py.File(tmp_path / "fine.h5") as h5:
        points, cells = h5["mesh/points"][()], h5["mesh/cells/tetra10"][()]
        ours, fixed = h5["modes/frequencies_hz"][()], h5["mesh/fixed_dofs"][()]
    np.testing.assert_array_equal(fixed, geometric_fixed_dofs(points))
    sets = {f"C{c}": (np.unique(fixed[fixed % 3 == c] // 3), [c + 1]) for c in range(3)}
    deck = write_frequency_deck(tmp_path / "fine.inp", points, cells, E, NU, RHO, sets, 4)
    np.testing.assert_allclose(ours, run_frequencies(deck)[:4], rtol=2e-6)


def test_mesh_file_errors_name_the_key_and_write_nothing(plate_msh, tmp_path):
    # a volume group as a support region: said as what it is
    raw = mesh_plate_config(plate_msh, supports=[{"region": "plate", "fix": "all"}])
    out = run_cli(raw, tmp_path, "volume")
    assert out.returncode == RegionError.exit_code
    assert ("config key 'supports[0].region': 'plate' is a volume group (" in out.stderr
            and "not a region; expected a face, line or point region" in out.stderr)
    assert not (tmp_path / "volume.h5").exists()
    # a name neither the file nor the config defines: refused before assembly
    raw = mesh_plate_config(plate_msh)
    raw["ports"]["outputs"][0]["region"] = "nowhere"
    out = run_cli(raw, tmp_path, "unknown")
    assert out.returncode == RegionError.exit_code
    assert "config key 'ports.outputs[0].region': region 'nowhere' does not exist" in out.stderr
    assert "assemble" not in out.stderr.split("does not exist")[0].split("mesh done")[-1]
    assert not (tmp_path / "unknown.h5").exists()


def test_mesh_size_does_not_apply_to_a_mesh_file(plate_msh, caplog):
    raw = mesh_plate_config(plate_msh)
    assert config_from_dict(raw).geometry.kind == "mesh"  # no mesh section needed
    raw["mesh"] = {"order": 1, "size": 0.5}
    with caplog.at_level(logging.WARNING, logger="pipeline.config.parse"):
        cfg = config_from_dict(raw)
    assert cfg.mesh.order == 1
    assert "'mesh.size' does not apply to geometry.kind 'mesh'" in caplog.text


# --------------------------------------------------------------------------- Abaqus, Nastran
@pytest.fixture(scope="module")
def abaqus_plate(plate_msh, tmp_path_factory):
    """The quadratic plate mesh as an Abaqus/CalculiX deck in mm-t-s (MPa, t/mm^3): C3D10
    elements in the element set EALL, node sets C0, C1, C2 holding the nodes (mid-edge
    nodes included) whose x, y, z the simply supported plate fixes, found from the
    coordinates; with CalculiX's frequencies of it (None without ccx)."""
    space = build_space(read_mesh(plate_msh), 2)
    points = space.node_points
    fixed = geometric_fixed_dofs(points)
    sets = {f"C{c}": (np.unique(fixed[fixed % 3 == c] // 3), [c + 1]) for c in range(3)}
    folder = tmp_path_factory.mktemp("inp")
    deck = write_frequency_deck(folder / "plate.inp", points * 1e3, space.element_nodes,
                                E * 1e-6, NU, RHO * 1e-12, sets, 4)
    return deck, (run_frequencies(deck)[:4] if CCX else None)


def abaqus_config(deck: Path, **geometry) -> dict:
    return {"name": "plate_inp", "geometry": {"kind": "mesh", "path": str(deck), **geometry},
            "material": {"E": E, "nu": NU, "rho": RHO},  # SI, whatever the file's units
            "supports": [{"region": f"C{c}", "fix": [xyz]} for c, xyz in enumerate("xyz")],
            "modes": {"count": 4},
            "ports": {"inputs": [{"name": "f", "region": "C0", "kind": "force",
                                  "direction": [0, 0, 1]}]}}


def test_abaqus_node_sets_are_regions_and_units_convert(abaqus_plate, tmp_path):
    """The deck's node sets carry the supports by name: C2 (the four bottom edges, with
    their mid-edge nodes) becomes a line region that takes no triangle across a corner,
    C0 the corner's point; the mm coordinates become m. The same fixed DOFs as found from
    the coordinates, and CalculiX's frequencies of the same deck within 1e-4 (its 4-point
    mass integration, see above)."""
    deck, theirs = abaqus_plate
    out = run_cli(abaqus_config(deck, units="mm-t-s"), tmp_path, "plate_inp")
    assert out.returncode == 0, out.stderr[-2000:]
    assert "node set 'C2': a line of" in out.stderr
    assert "group 'EALL' is a volume group" in out.stderr
    with h5py.File(tmp_path / "plate_inp.h5") as h5:
        points = h5["mesh/points"][()]
        ours, fixed = h5["modes/frequencies_hz"][()], h5["mesh/fixed_dofs"][()]
        assert h5["mesh/regions/C2"].shape[1] == 2 and h5["mesh/regions/C0"].shape == (1, 1)
    assert np.ptp(points, axis=0) == pytest.approx([A, A, T], rel=1e-12)
    np.testing.assert_array_equal(fixed, geometric_fixed_dofs(points))
    if theirs is not None:
        np.testing.assert_allclose(ours, theirs, rtol=1e-4)


def test_units_are_refused_in_one_line(abaqus_plate):
    deck, _ = abaqus_plate
    with pytest.raises(ConfigError, match=r"geometry\.units.*'furlong-s'.*one of m-kg-s"):
        config_from_dict(abaqus_config(deck, units="furlong-s"))
    with pytest.raises(ConfigError, match=r"geometry\.scale.*no scale with geometry\.units"):
        config_from_dict(abaqus_config(deck, units="mm-t-s", scale=0.001))
    # the file in mm read as metres: the unit slip is named, with the fix
    with pytest.raises(ConfigError, match=r"geometry\.scale.*did you mean scale: 0\.001"):
        build_fe_model(config_from_dict(abaqus_config(deck)))


def test_a_nastran_file_reads_as_the_same_mesh(plate_msh, tmp_path):
    """Nastran bulk data (GRID, CTETRA) in mm, through meshio: the same vertices in m as
    the .msh it was written from. Its sets are not named (regions come from selectors)."""
    import meshio

    msh = meshio.read(plate_msh)
    tets = [b for b in msh.cells if b.type == "tetra"]
    nas = tmp_path / "plate.nas"
    meshio.write(nas, meshio.Mesh(msh.points * 1e3, tets), file_format="nastran")
    cfg = config_from_dict({"name": "nas", "geometry": {"kind": "mesh", "path": str(nas),
                                                        "units": "mm-t-s"},
                            "material": {"E": E, "nu": NU, "rho": RHO},
                            "regions": SELECTORS, "supports": SS_SUPPORTS})
    fe = build_fe_model(cfg)
    ref = read_mesh(plate_msh)
    assert fe.space.body.n_tetrahedra == ref.n_tetrahedra
    np.testing.assert_allclose(np.sort(fe.space.body.vertices, axis=0),
                               np.sort(ref.vertices, axis=0), rtol=0, atol=1e-12)
    np.testing.assert_array_equal(fe.fixed, geometric_fixed_dofs(fe.space.node_points))
