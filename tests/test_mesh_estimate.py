"""The size estimate before meshing (pipeline.fe.mesh.estimate) against what gmsh makes.

The estimate decides what runs (a refusal before gmsh, the memory estimate, the solver
path), so it must be within 20 % of the mesh gmsh then makes (issue 39). Checked on five
bodies (a box, the 2 mm strip, a cube, the bracket STEP, the slender-beam .geo) at sizes
that give 20k-60k tetrahedra (seconds to mesh) and, marked slow, at 0.7M-1.3M. 20 % is
the issue's bound; the fit's largest deviation on the 23 meshes it was made from is 12 %
(tetrahedra) and 9 % (P2 nodes), so the bound leaves room for gmsh's run-to-run and
version-to-version changes of a few per cent.
"""

from __future__ import annotations

import pytest

from conftest import ROOT
from pipeline.config import Geometry, MeshSpec
from pipeline.fe.mesh import body_shape, generate_mesh, mesh_geometry, read_mesh
from pipeline.fe.mesh.estimate import BodyShape, estimate_mesh, smallest_size
from pipeline.fe.space import build_space

BOUND = 0.20
BODIES = {
    "box": Geometry(kind="box", length=0.5, height=0.02, depth=0.05),
    "strip": Geometry(kind="box", length=0.5, height=0.002, depth=0.05),
    "cube": Geometry(kind="box", length=0.1, height=0.1, depth=0.1),
    "bracket": Geometry(kind="step", path=str(ROOT / "meshes/bracket.step")),
    "slender": Geometry(kind="geo", path=str(ROOT / "meshes/slender_beam.geo"), scale=0.001),
}


def check_estimate(tmp_path, body: str, size: float) -> None:
    geometry, spec = BODIES[body], MeshSpec(order=2, size=size)
    if geometry.kind == "box":  # gmsh alone: no refusal by the memory this machine has
        mesh = read_mesh(generate_mesh(geometry, spec, tmp_path / "m.msh"))
    else:
        mesh, _ = mesh_geometry(geometry, spec, tmp_path / "m.msh")
    shape = body_shape(geometry)
    for order in (1, 2):
        est = estimate_mesh(shape, size, order)
        nodes = build_space(mesh, order).n_nodes
        assert abs(est.n_nodes / nodes - 1) < BOUND, (body, size, order, est.n_nodes, nodes)
    assert abs(est.n_tetrahedra / mesh.n_tetrahedra - 1) < BOUND, \
        (body, size, est.n_tetrahedra, mesh.n_tetrahedra)


@pytest.mark.parametrize("body,size", [("box", 0.004), ("strip", 0.003), ("cube", 0.005),
                                       ("bracket", 0.0013), ("slender", 0.003)])
def test_estimate_within_20_percent_of_gmsh(tmp_path, body, size):
    check_estimate(tmp_path, body, size)


@pytest.mark.slow
@pytest.mark.parametrize("body,size", [("box", 0.00146), ("strip", 0.0007),
                                       ("bracket", 0.0006), ("box", 0.00116)])
def test_estimate_within_20_percent_of_gmsh_on_large_meshes(tmp_path, body, size):
    check_estimate(tmp_path, body, size)


def test_estimate_of_the_cantilever_runs_of_issue_39():
    """gmsh's counts for the cantilever (benchmarks/mesh_counts.py): 333,081 P2 nodes at
    2.11 mm (999k DOFs), 945,641 at 1.46 mm, 1,842,724 at 1.16 mm (5.5M DOFs; the old
    estimate said 1e7 DOFs). Within 3 % each: what the fit gave."""
    shape = BodyShape.box(0.5, 0.02, 0.05)
    for size, nodes in ((0.00211, 333_081), (0.00146, 945_641), (0.00116, 1_842_724)):
        assert abs(estimate_mesh(shape, size, 2).n_nodes / nodes - 1) < 0.03


def test_thin_plates_count_one_element_through_the_thickness():
    """A plate thinner than the size: the volume term counts h^2 t per element, so
    halving the thickness at a fixed size leaves the element count nearly unchanged
    (the surface mesh, not the volume, sets it)."""
    thick = estimate_mesh(BodyShape.box(0.5, 0.002, 0.05), 0.005, 2).n_tetrahedra
    thin = estimate_mesh(BodyShape.box(0.5, 0.001, 0.05), 0.005, 2).n_tetrahedra
    assert thin == pytest.approx(thick, rel=0.05)


def test_smallest_size_inverts_the_estimate():
    shape = BodyShape.box(0.5, 0.02, 0.05)
    h = smallest_size(shape, 2, 1e6, "n_nodes", start=0.001)
    assert estimate_mesh(shape, h, 2).n_nodes == pytest.approx(1e6, rel=1e-6)
