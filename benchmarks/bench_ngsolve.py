"""The NGSolve peer of ``bench_pipeline.py``: the same cantilever, its best variant.

Run as a child process by ``bench_pipeline.py`` (one case per process, so ru_maxrss is
the case's own peak), or by hand:

    python benchmarks/bench_ngsolve.py --maxh 0.005 [--inverse pardiso] [--vectors 30]

The variant the issue names as NGSolve's best correct one: P2 ``VectorH1`` on an OCC box
(0.5 x 0.02 x 0.05 m, clamped at x = 0, the aluminium of ``configs/cantilever.yaml``),
stiffness and mass assembled with ``symmetric=True, symmetric_storage=True``, and
``ArnoldiSolver`` at shift 0 with 30 vectors (with 20 it returned a wrong 20th mode at
99k DOFs), whose shift-invert uses the sparse direct inverse ``--inverse`` (``pardiso``
when NGSolve was built with MKL, else its own ``sparsecholesky``). Prints one JSON line:
free DOFs, stage times (s), total, peak memory (MB) and the lowest ``--count`` frequencies
(Hz). NGSolve is optional: ``pip install -e '.[bench]'``.
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import sys
import time


def run_case(maxh: float, count: int = 20, vectors: int = 30, inverse: str = "pardiso"
             ) -> dict:
    """One NGSolve run; returns the stage times, DOFs, peak memory and frequencies."""
    import ngsolve as ngs
    from netgen.occ import X, Box, OCCGeometry, Pnt

    ngs.SetNumThreads(2)
    E, nu, rho = 69.0e9, 0.33, 2700.0
    mu, lam = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))
    t0 = time.perf_counter()
    box = Box(Pnt(0, 0, 0), Pnt(0.5, 0.02, 0.05))
    box.faces.Min(X).name = "root"
    mesh = ngs.Mesh(OCCGeometry(box).GenerateMesh(maxh=maxh))
    t1 = time.perf_counter()
    with ngs.TaskManager():
        fes = ngs.VectorH1(mesh, order=2, dirichlet="root", complex=True)  # Arnoldi is complex
        u, v = fes.TnT()
        eps_u, eps_v = ngs.Sym(ngs.Grad(u)), ngs.Sym(ngs.Grad(v))
        a = ngs.BilinearForm(fes, symmetric=True, symmetric_storage=True)
        a += (2 * mu * ngs.InnerProduct(eps_u, eps_v) + lam * ngs.Trace(eps_u)
              * ngs.Trace(eps_v)) * ngs.dx
        m = ngs.BilinearForm(fes, symmetric=True, symmetric_storage=True)
        m += rho * u * v * ngs.dx
        a.Assemble()
        m.Assemble()
        t2 = time.perf_counter()
        gf = ngs.GridFunction(fes, multidim=vectors)
        lams = ngs.ArnoldiSolver(a.mat, m.mat, fes.FreeDofs(), list(gf.vecs), shift=0.0,
                                 inverse=inverse)
        t3 = time.perf_counter()
    omega2 = sorted(float(x.real) for x in lams)[:count]
    freqs = [math.sqrt(max(w, 0.0)) / (2 * math.pi) for w in omega2]
    return {"kind": f"ngsolve ({inverse}, {vectors} vectors)", "maxh": maxh,
            "n_dofs": fes.ndof, "n_free": int(sum(fes.FreeDofs())),
            "mesh": t1 - t0, "assembly": t2 - t1, "eigensolve": t3 - t2,
            "total": t3 - t0, "frequencies": freqs,
            "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}


def available() -> bool:
    """True when ngsolve imports (the optional ``bench`` extra)."""
    try:
        import ngsolve  # noqa: F401
    except Exception:
        return False
    return True


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--maxh", type=float, required=True, help="NGSolve mesh size (m)")
    ap.add_argument("--count", type=int, default=20)
    ap.add_argument("--vectors", type=int, default=30)
    ap.add_argument("--inverse", default="pardiso")
    args = ap.parse_args(argv)
    row = run_case(args.maxh, args.count, args.vectors, args.inverse)
    sys.stdout.write(json.dumps(row) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
