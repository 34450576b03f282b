"""The NGSolve peer of ``bench_pipeline.py``: the same cantilever, its best variant.

Run as a child process by ``bench_pipeline.py`` (one case per process, so ru_maxrss is
the case's own peak), or by hand:

    python benchmarks/bench_ngsolve.py --maxh 0.005 [--inverse pardiso] [--vectors 30]

NGSolve's fastest correct variant on the bench machine: P2 ``VectorH1`` on an OCC box
(0.5 x 0.02 x 0.05 m, clamped at x = 0, the aluminium of ``configs/cantilever.yaml``),
stiffness and mass assembled with ``symmetric=True, symmetric_storage=True``, and
``ArnoldiSolver`` at shift 0 with 30 vectors (with 20 it returned a wrong 20th mode at
99k DOFs), whose shift-invert uses the sparse direct inverse ``--inverse``:

- ``sparsecholesky``: NGSolve's own supernodal Cholesky;
- ``pardiso``: NGSolve's built-in MKL PARDISO inverse with its default settings;
- ``pardiso_spd``: NGSolve's fastest variant on the bench machine, an MKL PARDISO SPD
  factor (mtype 2, METIS ordering, no iterative refinement) registered through
  ``ngsolve.la.RegisterInverseType``. Its factor and solves are this project's own
  PARDISO wrapper (:func:`pipeline.solve.factorization.factorize`, the settings our
  pipeline uses), so the two stacks compared differ in everything but the sparse
  factorisation. Arnoldi is complex: the real and imaginary parts of a right-hand side
  are solved as two columns of one real solve.

Prints one JSON line:
free DOFs, stage times (s), total, peak memory (MB), the lowest ``--count`` frequencies
(Hz) and their modes' accuracy from NGSolve's own K and M, measured after the timed part
as the pipeline's rows are (:func:`mode_accuracy`: the largest true relative residual and
backward error, so that "same accuracy" in the comparison is a figure, not a claim).
NGSolve is optional: ``pip install -e '.[bench]'``.
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import sys
import time


def register_pardiso_spd() -> str:
    """Register the ``pardiso_spd`` inverse of the module doc; returns its name."""
    from pathlib import Path

    import ngsolve as ngs
    import numpy as np
    import scipy.sparse as sp

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from pipeline.solve.factorization import factorize

    class PardisoSPD(ngs.la.SparseFactorizationInterface):
        def Factor(self):
            vals, indices, indptr = self.GetInnerMatrix().CSR()
            vals = np.asarray(vals)
            if np.iscomplexobj(vals):
                if np.abs(vals.imag).max(initial=0.0) > 0:
                    raise ValueError("pardiso_spd: the matrix is not real")
                vals = vals.real
            # (unsigned 64-bit from 1M DOFs: to the 32-bit indices PARDISO takes)
            itype = np.int32 if max(len(indices), len(indptr)) < 2**31 else np.int64
            indices = np.asarray(indices).astype(itype)
            indptr = np.asarray(indptr).astype(itype)
            n = indptr.size - 1
            rows = np.repeat(np.arange(n, dtype=itype), np.diff(indptr))
            lower = bool(np.all(indices <= rows))
            del rows
            A = sp.csr_matrix((vals, indices, indptr), shape=(n, n))
            del vals, indices, indptr
            if lower:  # symmetric storage: the factor needs its transpose, the upper
                A = A.T.tocsr()  # triangle, only (no full matrix: 1.22M DOFs did not fit)
            self.factor = factorize(A, "pardiso", positive_definite=True, check=False)
            del A

        def Solve(self, rhs, sol):
            b = rhs.FV().NumPy()
            if np.iscomplexobj(b):
                x = self.factor.solve(np.column_stack([b.real, b.imag]))
                sol.FV().NumPy()[:] = x[:, 0] + 1j * x[:, 1]
            else:
                sol.FV().NumPy()[:] = self.factor.solve(b)

    ngs.la.RegisterInverseType("pardiso_spd", PardisoSPD)
    return "pardiso_spd"


def mode_accuracy(a, m, fes, vecs, omega2) -> dict:
    """The accuracy of NGSolve's eigenpairs (complex vectors ``vecs``, eigenvalues
    ``omega2`` (rad^2/s^2), both ascending) measured as the pipeline's: K and M on the
    free DOFs as scipy matrices (NGSolve stores their lower triangle), each vector turned
    real by the phase of its largest entry (an eigenvector of a real symmetric pencil
    times a phase), then ``bench_pipeline.mode_accuracy``."""
    from pathlib import Path

    import numpy as np
    import scipy.sparse as sp

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_pipeline import mode_accuracy as accuracy_of

    free = np.flatnonzero(np.array(list(fes.FreeDofs()), dtype=bool))

    def full(mat) -> sp.csr_matrix:
        vals, cols, ptr = mat.CSR()
        n = len(ptr) - 1
        L = sp.csr_matrix((np.asarray(vals).real, np.asarray(cols), np.asarray(ptr)),
                          shape=(n, n))
        A = (L + L.T - sp.diags(L.diagonal())).tocsr()
        return A[free][:, free].tocsr()

    X = np.empty((free.size, len(vecs)))
    for k, v in enumerate(vecs):
        x = v.FV().NumPy()[free]
        phase = x[np.argmax(np.abs(x))]
        X[:, k] = (x * (abs(phase) / phase)).real
    return accuracy_of(full(a.mat), full(m.mat), X, np.asarray(omega2, dtype=np.float64))


def run_case(maxh: float, count: int = 20, vectors: int = 30, inverse: str = "pardiso"
             ) -> dict:
    """One NGSolve run; returns the stage times, DOFs, peak memory (before the accuracy
    check), frequencies and the modes' accuracy (:func:`mode_accuracy`)."""
    import ngsolve as ngs
    from netgen.occ import X, Box, OCCGeometry, Pnt

    if inverse == "pardiso_spd":
        register_pardiso_spd()

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
        peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
        order = sorted(range(len(lams)), key=lambda i: complex(lams[i]).real)[:count]
        omega2 = [complex(lams[i]).real for i in order]
        accuracy = mode_accuracy(a, m, fes, [gf.vecs[i] for i in order], omega2)
    freqs = [math.sqrt(max(w, 0.0)) / (2 * math.pi) for w in omega2]
    return {**accuracy, "kind": f"ngsolve ({inverse}, {vectors} vectors)", "maxh": maxh,
            "method": f"arnoldi ({vectors} vectors)",
            "n_dofs": fes.ndof, "n_free": int(sum(fes.FreeDofs())),
            "mesh": t1 - t0, "assembly": t2 - t1, "eigensolve": t3 - t2,
            "total": t3 - t0, "frequencies": freqs, "peak_mb": peak_mb}


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
