"""Shared helpers for the tests: build and solve small real FE models."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from pipeline.fe.assemble import assemble_stiffness_mass, restrict
from pipeline.config import Geometry, Material, MeshSpec, Support
from pipeline.fe.space import FESpace, build_space
from pipeline.fe.mesh import generate_mesh, read_mesh
from pipeline.fe.regions import fixed_dofs, free_dofs, resolve_regions

ROOT = Path(__file__).resolve().parents[1]
ALUMINIUM = Material(E=69.0e9, nu=0.33, rho=2700.0)


@dataclass
class FEModel:
    space: FESpace
    regions: dict
    K_full: object
    M_full: object
    free: np.ndarray
    K: object
    M: object


def build_model(tmp_path: Path, length=0.5, height=0.02, depth=0.05, size=0.01, order=2,
                supports=("root",), in_plane=False, material=ALUMINIUM) -> FEModel:
    """Mesh a box, assemble K and M, and condense the supports."""
    geometry = Geometry("box", length, height, depth)
    path = generate_mesh(geometry, MeshSpec(order=order, size=size, algorithm="delaunay"),
                         tmp_path / f"box_{length}_{height}_{depth}_{size}_{order}.msh")
    space = build_space(read_mesh(path), order)
    regions = resolve_regions(space, {})
    K, M = assemble_stiffness_mass(space, material)
    fixed = fixed_dofs(space, regions, [Support(r) for r in supports], in_plane)
    free = free_dofs(space.n_dofs, fixed)
    return FEModel(space, regions, K, M, free, restrict(K, free), restrict(M, free))


@pytest.fixture(scope="session")
def session_tmp(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("shared")


def add_reliability_counts(prefix: str, counts) -> None:
    """Add ``counts`` (what a reliability test file tried) to the JSON file named by
    $RELIABILITY_COUNTS, keys ``<prefix>.<name>``; ``make test-reliability`` prints it."""
    import json
    import os

    target = os.environ.get("RELIABILITY_COUNTS")
    if not target:
        return
    path = Path(target)
    old = json.loads(path.read_text()) if path.exists() else {}
    for key, value in counts.items():
        old[f"{prefix}.{key}"] = old.get(f"{prefix}.{key}", 0) + value
    path.write_text(json.dumps(old, indent=1, sort_keys=True))
