"""Measure what gmsh makes (tetrahedra, vertices, P2 nodes, boundary triangles) for a
config's body at several mesh sizes, beside the estimate of
:mod:`pipeline.fe.mesh.estimate` and its relative error.

    python benchmarks/mesh_counts.py configs/cantilever.yaml 0.005 0.003
    python benchmarks/mesh_counts.py configs/cantilever.yaml geometry.height=0.002 0.005
    python benchmarks/mesh_counts.py configs/bracket.yaml 0.0013 0.001

Arguments: a config, ``key=value`` overrides, then the sizes (m). One JSON line per size.
Meshing only (no solve); the refusal before meshing is switched off here, so run a large
size under ``flock /tmp/bigrun.lock`` on a shared machine. The fit of the module doc of
:mod:`pipeline.fe.mesh.estimate` was made from these lines for the cantilever, the
cantilever with height 0.002 (the strip), a 0.1 m cube, the bracket and the slender beam.
"""

from __future__ import annotations

import json
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pipeline.config import MeshSpec, load_config  # noqa: E402
from pipeline.fe.mesh import body_shape, estimate as est  # noqa: E402
from pipeline.fe.mesh import box as box_mod, cad as cad_mod, geo as geo_mod, common  # noqa: E402
from pipeline.fe.mesh.registry import SOURCES  # noqa: E402


def counts(tets: np.ndarray) -> dict:
    """Tetrahedra, vertices, edges, P2 nodes and boundary triangles of (n, 4) tetrahedra."""
    t = np.sort(tets, axis=1)
    m = int(t.max()) + 1
    n_v = int(np.unique(t).size)
    key = np.concatenate([t[:, i].astype(np.int64) * m + t[:, j]
                          for i, j in ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))])
    n_e = int(np.unique(key).size)
    del key
    fk = np.concatenate([(t[:, a].astype(np.int64) * m + t[:, b]) * m + t[:, c]
                         for a, b, c in ((0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3))])
    _, c = np.unique(fk, return_counts=True)
    return {"tets": int(t.shape[0]), "vertices": n_v, "edges": n_e,
            "p2_nodes": n_v + n_e, "boundary_triangles": int((c == 1).sum())}


def main() -> None:
    overrides = [a for a in sys.argv[2:] if "=" in a]
    sizes = [float(a) for a in sys.argv[2:] if "=" not in a]
    cfg = load_config(Path(sys.argv[1]), overrides)
    geometry = cfg.geometry
    shape = body_shape(geometry)
    real = (est.check_mesh_fits, common.check_size)
    box_mod.check_mesh_fits = est.check_mesh_fits = lambda *a, **k: None  # no refusal
    cad_mod.check_size = geo_mod.check_size = common.check_size = lambda *a, **k: None
    try:
        for size in sizes:
            spec = MeshSpec(order=2, size=size, algorithm=cfg.mesh.algorithm)
            with tempfile.TemporaryDirectory() as work:
                t0 = time.perf_counter()
                body, _ = SOURCES[geometry.kind](geometry, spec, Path(work) / "m.msh")
                seconds = time.perf_counter() - t0
            row = {"config": sys.argv[1], "overrides": overrides, "size": size,
                   "seconds": round(seconds, 1), **counts(body.tetrahedra)}
            e = est.estimate_mesh(shape, size, 2)
            row.update(est_tets=round(e.n_tetrahedra), est_p2_nodes=round(e.n_nodes),
                       err_tets=round(e.n_tetrahedra / row["tets"] - 1, 3),
                       err_p2_nodes=round(e.n_nodes / row["p2_nodes"] - 1, 3),
                       maxrss_gb=round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
                                       / 1e6, 2))
            print(json.dumps(row), flush=True)
            del body
    finally:
        est.check_mesh_fits = box_mod.check_mesh_fits = real[0]
        common.check_size = cad_mod.check_size = geo_mod.check_size = real[1]


if __name__ == "__main__":
    main()
