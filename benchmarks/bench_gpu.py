"""A GPU eigensolve measured beside the CPU pipeline: cuDSS Cholesky on the GPU.

Not part of the pipeline or its tests: it runs where CuPy and nvmath-python (cuDSS) are
installed, on a machine with an NVIDIA GPU, and prints one JSON record per mesh.

For each mesh (an ``.npz`` with ``vertices`` (n_v, 3) m, ``tetrahedra`` (n_t, 4) and the
``root`` face's triangles, exported from a pipeline run of ``configs/cantilever.yaml``):

1. the FE space (P2) and K, M on the free DOFs, by the pipeline's own assembly (CPU);
2. K to the GPU (cuSPARSE CSR), cuDSS analysis (reordering, symbolic), Cholesky (SPD);
3. the 20 lowest modes by ARPACK in shift-invert mode (``scipy.sparse.linalg.eigsh``,
   sigma = 0), the solves with the GPU factor, M products and ARPACK's own work on the
   CPU, so the figure is what a GPU factor gives this pipeline with its CPU-side code;
4. the time of one solve with the factor, GPU arrays in and out;
5. the residuals ||K x - lambda M x|| / ||K x|| of the modes, in double on the CPU;
6. the same through the pipeline (``solve_modes(..., backend="cudss")``, the factor kept
   for a refined static solve, as the reduce stage does), against the direct run.

Usage: ``python benchmarks/bench_gpu.py MESH.npz [MESH.npz ...] [--modes 20]``; the
meshes are made where gmsh is (the GPU machine needs none):
``python benchmarks/bench_gpu.py --export 0.00211 cantilever_1m.npz`` (mesh.size in m;
0.00211 gives 996k free DOFs, 0.00146 2.83M).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def assemble(mesh_path: Path):
    """(K, M, seconds) of the clamped cantilever on ``mesh_path``'s mesh."""
    from pipeline.config import load_config
    from pipeline.fe.assemble import assemble_on_nodes
    from pipeline.fe.mesh.common import BodyMesh
    from pipeline.fe.space import build_space

    cfg = load_config(Path(__file__).resolve().parents[1] / "configs" / "cantilever.yaml")
    data = np.load(mesh_path)
    body = BodyMesh(data["vertices"], data["tetrahedra"].astype(np.int64),
                    {"root": data["root"].astype(np.int64)})
    t0 = time.perf_counter()
    space = build_space(body, 2)
    x_root = float(body.vertices[np.unique(data["root"]), 0].mean())
    extent = float(np.ptp(body.vertices[:, 0]))
    fixed = np.abs(space.node_points[:, 0] - x_root) <= 1e-9 * extent
    nodes = np.flatnonzero(~fixed)
    asm = assemble_on_nodes(space, cfg.material, nodes)
    return asm.K, asm.M, time.perf_counter() - t0


def gpu_modes(K, M, count: int) -> dict:
    import cupy as cp
    import cupyx.scipy.sparse as csp
    import nvmath
    import scipy.sparse.linalg as sla
    from nvmath.bindings import cudss

    n = K.shape[0]
    rec: dict = {"dofs": n, "nnz_K": int(K.nnz)}
    t0 = time.perf_counter()
    Kg = csp.csr_matrix(K)
    b = cp.zeros((n, 1), order="F")
    cp.cuda.Device().synchronize()
    rec["upload_s"] = time.perf_counter() - t0
    # cuDSS's reordering runs on the CPU; its threading layer (libcudss_mtlayer_gomp, in
    # the cuDSS wheel) is named by CUDSS_MT_LIB, else it runs on one core
    options = nvmath.sparse.advanced.DirectSolverOptions(
        sparse_system_type=cudss.MatrixType.SPD,
        multithreading_lib=os.environ.get("CUDSS_MT_LIB") or None)
    rec["reordering_threads"] = "CUDSS_MT_LIB" if os.environ.get("CUDSS_MT_LIB") else 1
    solver = nvmath.sparse.advanced.DirectSolver(Kg, b, options=options)
    t0 = time.perf_counter()
    solver.plan()
    cp.cuda.Device().synchronize()
    rec["analysis_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    solver.factorize()
    cp.cuda.Device().synchronize()
    rec["factorisation_s"] = time.perf_counter() - t0
    free, total = cp.cuda.Device().mem_info
    rec["gpu_memory_used_gb"] = (total - free) / 1e9

    solves = [0]

    def solve_host(x: np.ndarray) -> np.ndarray:
        rhs = cp.asarray(np.asarray(x, dtype=np.float64).reshape(n, -1), order="F")
        solver.reset_operands(b=rhs)
        out = solver.solve()
        solves[0] += rhs.shape[1]
        return cp.asnumpy(out).reshape(np.shape(x))

    # one right-hand side, GPU arrays in and out (the factor's own speed)
    rhs = cp.asarray(np.random.default_rng(1).standard_normal((n, 1)), order="F")
    solver.reset_operands(b=rhs)
    solver.solve()
    cp.cuda.Device().synchronize()
    t0 = time.perf_counter()
    for _ in range(5):
        solver.solve()
    cp.cuda.Device().synchronize()
    rec["solve_one_rhs_s"] = (time.perf_counter() - t0) / 5

    op = sla.LinearOperator((n, n), matvec=solve_host, dtype=np.float64)
    t0 = time.perf_counter()
    lam, X = sla.eigsh(K, k=count, M=M, sigma=0.0, OPinv=op, which="LM", tol=1e-10)
    rec["eigsh_s"] = time.perf_counter() - t0
    rec["eigsh_solves"] = solves[0]
    order = np.argsort(lam)
    lam, X = lam[order], X[:, order]
    rec["frequencies_hz"] = (np.sqrt(np.abs(lam)) / (2 * np.pi)).tolist()
    KX = K @ X
    rec["max_relative_residual"] = float(np.max(
        np.linalg.norm(KX - (M @ X) * lam, axis=0) / np.linalg.norm(KX, axis=0)))
    solver.free()
    return rec


def pipeline_modes(K, M, count: int, reference_hz) -> dict:
    """The pipeline's own eigensolver with ``modes.solver: cudss`` (factor kept, then one
    static solve with it, as the reduce stage does), against the direct run above."""
    from pipeline.solve.eigen import solve_modes
    from pipeline.solve.refine import refined_solve

    t0 = time.perf_counter()
    modes = solve_modes(K, M, count, backend="cudss", keep=True)
    rec = {"pipeline_modes_s": time.perf_counter() - t0,
           "pipeline_backend": modes.stats.get("backend"),
           "pipeline_method": modes.stats.get("method"),
           "pipeline_max_relative_residual": float(np.max(modes.residuals)),
           "pipeline_vs_direct_max_rel": float(np.max(np.abs(
               modes.frequencies_hz - np.asarray(reference_hz)) / np.asarray(reference_hz)))}
    F = np.zeros((K.shape[0], 2))
    F[-3:, 0] = 1.0  # the last node: a small load
    F[-2, 1] = 1.0
    t0 = time.perf_counter()
    X, report = refined_solve(K, modes.factorization.solve, F)
    rec["static_solve_s"] = time.perf_counter() - t0
    rec["static_backward_error"] = float(np.max(report.backward_error))
    modes.release_factorization()
    return rec


def _release_gpu_memory() -> None:
    """Return what the last solver left in CuPy's pool, so the next one sees the whole GPU."""
    import gc

    import cupy as cp

    gc.collect()
    cp.get_default_memory_pool().free_all_blocks()
    try:
        pool = cp.cuda.runtime.deviceGetDefaultMemPool(cp.cuda.Device().id)
        cp.cuda.runtime.memPoolTrimTo(pool, 0)
    except Exception:
        pass
    print(f"GPU memory free: {cp.cuda.Device().mem_info[0] / 1e9:.1f} GB", file=sys.stderr)


def export_mesh(size: str, out: Path) -> None:
    """Mesh configs/cantilever.yaml at ``mesh.size = size`` with the pipeline (gmsh) and
    save what :func:`assemble` reads."""
    import tempfile

    from pipeline._util.atomic import atomic_path
    from pipeline.config import load_config
    from pipeline.fe.mesh import mesh_body

    cfg = load_config(Path(__file__).resolve().parents[1] / "configs" / "cantilever.yaml",
                      [f"mesh.size={size}"])
    with tempfile.TemporaryDirectory() as folder:
        body, _, _ = mesh_body(cfg.geometry, cfg.mesh, folder, cfg.name)
    with atomic_path(out) as tmp, open(tmp, "wb") as fh:  # whole or not at all
        np.savez_compressed(fh, vertices=body.vertices,
                            tetrahedra=body.tetrahedra.astype(np.int32),
                            root=body.regions["root"].astype(np.int32))
    print(f"{out}: {len(body.vertices)} vertices, {len(body.tetrahedra)} tetrahedra")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("meshes", nargs="*", type=Path)
    parser.add_argument("--modes", type=int, default=20)
    parser.add_argument("--export", nargs=2, metavar=("SIZE", "OUT.npz"),
                        help="mesh the cantilever at mesh.size SIZE (m) into OUT.npz")
    args = parser.parse_args()
    if args.export:
        export_mesh(args.export[0], Path(args.export[1]))
        return 0
    if not args.meshes:
        parser.error("no MESH.npz given")
    for path in args.meshes:
        t0 = time.perf_counter()
        K, M, t_asm = assemble(path)
        rec = {"mesh": path.name, "assembly_s": t_asm}
        rec.update(gpu_modes(K, M, args.modes))
        _release_gpu_memory()
        rec.update(pipeline_modes(K, M, args.modes, rec["frequencies_hz"]))
        _release_gpu_memory()
        rec["total_s"] = time.perf_counter() - t0
        print(json.dumps(rec), flush=True)
        del K, M
    return 0


if __name__ == "__main__":
    sys.exit(main())
