"""Benchmark: our LOBPCG and two-grid preconditioner against scipy's LOBPCG and PyAMG.

``make bench`` runs it after :mod:`bench_pipeline` (``python benchmarks/bench_solvers.py
[--sizes 100k,1M] [--problems cantilever,strip,bracket,beam]``). For every problem and
size, one child process builds K, M (free DOFs), the P1 prolongation P and the
rigid-body modes and saves them; then every case runs in its own child process, so that
its peak memory (ru_maxrss) is its own (the matrices it loads included: the ``matrices
MB`` column is the peak right after loading them):

eigenproblem, the ``count`` lowest modes of K x = omega^2 M x:

- ``factor``: the pipeline's shift-invert block Lanczos with a sparse factor of K
  (``modes.method: factor``); the reference of the agreement columns;
- ``ours LOBPCG + two-grid``: the pipeline's factor-free path
  (``modes.method: multigrid``, :mod:`pipeline.solve.lobpcg`,
  :mod:`pipeline.solve.multigrid`), start block the P1 modes;
- ``ours LOBPCG + SA``, ``scipy LOBPCG + two-grid``, ``scipy LOBPCG + SA``: the same
  start block (the P1 modes, computed once per case: ``setup s`` includes it), with
  :func:`scipy.sparse.linalg.lobpcg` and/or PyAMG's smoothed aggregation (SA, one V-cycle
  a column, the six rigid-body modes as near-null space B) as preconditioner;

static solves K X = F (F: the four body loads of gravity along x, y, z and of a spin
about x, i.e. M times rigid-body modes), to ||F - K X|| <= 1e-10 ||F||:

- ``ours PCG``/``scipy CG`` (:func:`pipeline.solve.pcg.pcg`, all columns at once;
  :func:`scipy.sparse.linalg.cg`, column by column) with the two-grid cycle or SA.

Columns: iterations (LOBPCG sweeps; CG: the most of any column), set-up and solve
seconds, peak MB, converged, and the accuracy of the result computed from K and M
(:mod:`pipeline.solve.accuracy`): for modes the largest true relative residual
||K x - w^2 M x|| / ||K x||, the largest backward error, the largest relative frequency
difference from ``factor`` and the largest subspace angle (M inner product) of the
shapes from ``factor``'s; for static solves ||F - K X|| / ||F||.

Stopping tests differ: ours stops when every wanted mode's preconditioned residual
sqrt(r^T T r / w^2) <= 1e-6 (:data:`pipeline.solve.eigen.MULTIGRID_TOLERANCE`);
scipy's when every ||r||_2 <= tol for M-normalised x, given here as
:data:`SCIPY_TOL` times w_1^2 ||M x_1|| of the lowest start vector (about ||K x_1|| of the
lowest mode). The agreement columns say whether the answers are equally good.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_pipeline import (ROOT, SIZES, check_json_option, machine, run_watched,  # noqa: E402
                            short_error, write_whole)

# problem -> (config, overrides, volume m^3): mesh.size for a target DOF count from the
# cantilever's measured 101k DOFs at 0.005 m (DOFs ~ volume / size^3)
PROBLEMS = {
    "cantilever": ("configs/cantilever.yaml", [], 0.5 * 0.02 * 0.05),
    "strip": ("configs/cantilever.yaml", ["geometry.height=0.002"], 0.5 * 0.002 * 0.05),
    "bracket": ("configs/bracket.yaml", [], 60e-3 * 40e-3 * 5e-3 + 50e-3 * 60e-3 * 5e-3),
    "beam": ("configs/slender_beam.yaml", [], 2.0 * 0.01 * 0.01),
}
TARGETS = {"20k": 2.0e4, "100k": 1.0e5, "300k": 3.0e5, "1M": 1.0e6}
CANTILEVER = (101_406, 0.005, 0.5 * 0.02 * 0.05)  # DOFs at mesh.size, volume
COUNT = 20
MG_TARGET = 1e-6  # our LOBPCG's preconditioned-residual target (the pipeline's default)
# scipy's tol (an absolute ||K x - w^2 M x||_2 of M-normalised x), relative to
# w_1^2 ||M x_1||_2 of the lowest start vector (that is, to ||K x_1|| of the lowest mode):
# the loosest decade at which its modes agree with the factor's at least as well as ours
# (the cantilever, 25k DOFs: 1e-2 -> 34 sweeps, subspace angle 4.5e-9; 1e-3 -> 36 sweeps,
# 5.4e-10; ours: 10 sweeps, 5.9e-8). Its l2 residual falls slowly on the mesh-scale
# components (see pipeline.solve.accuracy), which tightening tol pays for.
SCIPY_TOL = 1e-2
MAX_SWEEPS = 100
CG_RTOL = 1e-10
# the cases every problem runs; the rest (LOBPCG with SA: 20-30x slower than with the
# two-grid cycle, measured on the cantilever) only on --full-problems
CORE_CASES = ("factor", "ours-lobpcg+two-grid", "scipy-lobpcg+two-grid", "ours-pcg+two-grid",
              "scipy-cg+two-grid", "ours-pcg+sa", "scipy-cg+sa")
EIGEN_CASES = ("factor", "ours-lobpcg+two-grid", "ours-lobpcg+sa", "scipy-lobpcg+two-grid",
               "scipy-lobpcg+sa")
STATIC_CASES = ("ours-pcg+two-grid", "ours-pcg+sa", "scipy-cg+two-grid", "scipy-cg+sa")


def mesh_size(problem: str, label: str) -> float:
    """mesh.size (m) for about TARGETS[label] DOFs: the cantilever's measured sizes
    (bench_pipeline.SIZES), else scaled from its 100k by volume."""
    if problem == "cantilever" and label in SIZES:
        return SIZES[label]
    dofs, size, volume = CANTILEVER
    return size * (dofs * PROBLEMS[problem][2] / volume / TARGETS[label]) ** (1.0 / 3.0)


def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


# --------------------------------------------------------------------------- child side
def prepare(problem: str, size: float, folder: Path) -> dict:
    """Mesh and assemble ``problem`` at ``size``; save K, M, P, the rigid-body modes."""
    sys.path.insert(0, str(ROOT))
    from pipeline.cli import tune_process

    tune_process()
    import numpy as np
    import scipy.sparse as sp

    from pipeline.config import load_config
    from pipeline.fe.coarse import p1_prolongation
    from pipeline.fe.model import build_fe_model

    path, overrides, _ = PROBLEMS[problem]
    cfg = load_config(ROOT / path, overrides + [f"mesh.size={size}"])
    fe = build_fe_model(cfg, folder)
    P = p1_prolongation(fe.space, fe.free)
    for name, A in (("K", fe.K), ("M", fe.M), ("P", P)):
        write_whole(folder / f"{name}.npz",
                    lambda fh, A=A: sp.save_npz(fh, sp.csr_matrix(A), compressed=False))
    write_whole(folder / "free.npy", lambda fh: np.save(fh, fe.free))
    write_whole(folder / "points.npy", lambda fh: np.save(fh, fe.space.node_points))
    return {"n": int(fe.free.size), "n_full": int(fe.space.n_dofs)}


def _load(folder: Path):
    import numpy as np
    import scipy.sparse as sp

    K, M, P = (sp.load_npz(folder / f"{x}.npz").tocsr() for x in "KMP")
    return K, M, P, np.load(folder / "free.npy"), np.load(folder / "points.npy")


def rigid_body_modes(points, dofs):
    """(len(dofs), 6) translations x, y, z and rotations about x, y, z (about the
    centroid) at the DOFs ``dofs`` (3 * node + component) of nodes at ``points``."""
    import numpy as np

    node, comp = dofs // 3, dofs % 3
    xyz = points[node] - points.mean(axis=0)
    B = np.zeros((dofs.size, 6))
    B[np.arange(dofs.size), comp] = 1.0
    x, y, z = xyz.T
    B[:, 3] = np.where(comp == 1, -z, np.where(comp == 2, y, 0.0))  # about x
    B[:, 4] = np.where(comp == 0, z, np.where(comp == 2, -x, 0.0))  # about y
    B[:, 5] = np.where(comp == 0, -y, np.where(comp == 1, x, 0.0))  # about z
    return B


class SmoothedAggregation:
    """PyAMG smoothed aggregation for K (free DOFs) as a preconditioner.

    The hierarchy is built on the whole space with K's held DOFs given unit rows
    (scaled to K's median diagonal), so that every node has its 3 DOFs and A is a
    3 x 3 block (BSR) matrix whose aggregates are nodes; B: the six rigid-body modes.
    ``apply(R)``: one V-cycle per column of R (n_free, k)."""

    def __init__(self, K, free, points):
        import numpy as np
        import pyamg
        import scipy.sparse as sp

        n, n_full = K.shape[0], points.shape[0] * 3
        E = sp.csr_matrix((np.ones(n), (free, np.arange(n))), shape=(n_full, n))
        held = np.ones(n_full, dtype=bool)
        held[free] = False
        d = np.where(held, np.median(K.diagonal()), 0.0)
        A = (E @ K @ E.T + sp.diags(d)).tobsr(blocksize=(3, 3))
        B = rigid_body_modes(points, np.arange(n_full))
        self.free, self.n_full = free, n_full
        self.ml = pyamg.smoothed_aggregation_solver(A, B=B, max_coarse=500)
        self.cycle = self.ml.aspreconditioner(cycle="V")
        self.levels = len(self.ml.levels)
        self.complexity = float(self.ml.operator_complexity())

    def apply(self, R):
        import numpy as np

        R = np.asarray(R, dtype=np.float64)
        vector = R.ndim == 1
        R = R.reshape(R.shape[0], -1)
        out = np.empty_like(R)
        full = np.zeros(self.n_full)
        for j in range(R.shape[1]):
            full[:] = 0.0
            full[self.free] = R[:, j]
            out[:, j] = self.cycle.matvec(full)[self.free]
        return out[:, 0] if vector else out


def _preconditioner(name: str, K, P, free, points):
    """(apply(R), description) of ``two-grid`` (float32 cycle) or ``sa``."""
    if name == "two-grid":
        from pipeline.solve.multigrid import TwoGrid

        tg = TwoGrid(K, P)
        return tg.apply_single, f"coarse {tg.coarse_n} DOFs", tg
    sa = SmoothedAggregation(K, free, points)
    return sa.apply, f"{sa.levels} levels, complexity {sa.complexity:.2f}", sa


def _start_block(K, M, P, width):
    """The P1 modes prolonged: the start block of every LOBPCG case."""
    import numpy as np

    from pipeline.solve.blas import sparse_times_dense
    from pipeline.solve.eigen import MULTIGRID_START_TOLERANCE, solve_modes

    PT = P.T.tocsr()
    Kc, Mc = (PT @ K @ P).tocsr(), (PT @ M @ P).tocsr()
    vc = solve_modes(Kc, Mc, width, tolerance=MULTIGRID_START_TOLERANCE,
                     method="factor").shapes
    return sparse_times_dense(P, np.ascontiguousarray(vc))


def _accuracy(K, M, X, omega2, folder: Path) -> dict:
    import numpy as np

    from pipeline.solve import accuracy

    out = {"residual": float(accuracy.relative_residuals(K, M, X, omega2).max()),
           "backward": float(accuracy.backward_errors(K, M, X, omega2).max()),
           "frequencies": (np.sqrt(np.abs(omega2)) / (2 * np.pi)).tolist()}
    ref = folder / "reference.npz"
    if ref.exists():
        data = np.load(ref)
        out["freq_diff"] = accuracy.frequency_difference(out["frequencies"], data["f"])
        out["angle"] = accuracy.largest_subspace_angle(X, data["X"], M)
    return out


def run_case(case: str, folder: Path, count: int) -> dict:
    sys.path.insert(0, str(ROOT))
    from pipeline.cli import tune_process

    tune_process()
    import numpy as np
    import scipy.sparse.linalg as sla

    K, M, P, free, points = _load(folder)
    row = {"case": case, "n": K.shape[0], "matrices_mb": _peak_mb()}
    t0 = time.perf_counter()
    if case in ("factor", "ours-lobpcg+two-grid"):
        from pipeline.solve.eigen import solve_modes

        method = "factor" if case == "factor" else "multigrid"
        modes = solve_modes(K, M, count, coarse=P, method=method)
        st = modes.stats
        X, w = modes.shapes, modes.omega2
        total = time.perf_counter() - t0
        setup = st.get("setup_seconds", st.get("factor_seconds"))
        row.update(iterations=st.get("sweeps", st.get("solves")), setup_s=setup,
                   solve_s=total - (setup or 0.0), converged=True, method=st.get("method"))
        row.update(_accuracy(K, M, X, w, folder))
        if case == "factor":
            write_whole(folder / "reference.npz",
                        lambda fh: np.savez(fh, X=X, f=row["frequencies"]))
        return row
    solver, precond = case.split("+")
    apply, info, owner = _preconditioner(precond, K, P, free, points)
    row["preconditioner"] = info
    if solver.endswith("lobpcg"):
        width = min(count + max(3, count // 4), P.shape[1] // 2)
        X0 = _start_block(K, M, P, width)
        setup = time.perf_counter() - t0
        t1 = time.perf_counter()
        if solver == "ours-lobpcg":
            from pipeline.solve.lobpcg import lobpcg

            res = lobpcg(K, M, X0, apply, count, target=MG_TARGET, max_sweeps=MAX_SWEEPS)
            X, w, its, ok = res.X[:, :count], res.omega2[:count], res.sweeps, res.converged
        else:
            from pipeline.solve.blas import column_norms, sparse_times_dense

            n = K.shape[0]
            T = sla.LinearOperator((n, n), matvec=apply, matmat=apply, dtype=np.float64)
            x1 = X0[:, :1] / np.sqrt(float(X0[:, 0] @ (M @ X0[:, 0])))
            Mx1 = sparse_times_dense(M, x1)
            w1 = float(x1[:, 0] @ sparse_times_dense(K, x1)[:, 0])
            tol = SCIPY_TOL * w1 * float(column_norms(Mx1)[0])
            w, X, hist = sla.lobpcg(K, X0, B=M, M=T, tol=tol, maxiter=MAX_SWEEPS,
                                    largest=False, retResidualNormsHistory=True)
            order = np.argsort(w)[:count]
            w, X = w[order], np.ascontiguousarray(X[:, order])
            its = len(hist) - 1
            ok = bool(np.max(hist[-1][:count]) <= tol)
        row.update(iterations=int(its), setup_s=setup, solve_s=time.perf_counter() - t1,
                   converged=bool(ok))
        row.update(_accuracy(K, M, X, w, folder))
        return row
    # static solves
    B = M @ rigid_body_modes(points, free)[:, [0, 1, 2, 3]]
    setup = time.perf_counter() - t0
    t1 = time.perf_counter()
    if solver == "ours-pcg":
        from pipeline.solve.pcg import pcg

        Xs, its = pcg(K, B, apply, rtol=CG_RTOL, max_iter=500)
        ok = True
    else:
        n = K.shape[0]
        T = sla.LinearOperator((n, n), matvec=apply, dtype=np.float64)
        Xs = np.empty_like(B)
        its, ok = 0, True
        for j in range(B.shape[1]):
            count_j = [0]

            def tick(_x, c=count_j):
                c[0] += 1

            Xs[:, j], info_j = sla.cg(K, B[:, j], rtol=CG_RTOL, maxiter=500, M=T,
                                      callback=tick)
            its, ok = max(its, count_j[0]), ok and info_j == 0
    R = B - K @ Xs
    row.update(iterations=int(its), setup_s=setup, solve_s=time.perf_counter() - t1,
               converged=bool(ok),
               residual=float((np.linalg.norm(R, axis=0) / np.linalg.norm(B, axis=0)).max()))
    return row


# --------------------------------------------------------------------------- parent side
def _child(args: list[str], timeout: float, result: Path) -> dict:
    proc = run_watched([sys.executable, str(Path(__file__).resolve())] + args
                       + ["--result", str(result)], timeout)
    if proc.error:
        return {"error": proc.error, "peak_mb": proc.peak_rss_bytes / 2**20}
    if proc.returncode != 0 or not result.exists():
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
        return {"error": f"exit {proc.returncode}: {' | '.join(tail)}"}
    row = json.loads(result.read_text())
    result.unlink()
    return row


def _fmt(value, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def table(rows: list[dict]) -> str:
    lines = ["| problem | DOFs | case | iterations | set-up s | solve s | peak MB | "
             "matrices MB | converged | true rel. residual | backward error | "
             "freq. diff vs factor | subspace angle vs factor | preconditioner |",
             "|" + " --- |" * 14]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['problem']} | {r.get('n', r['label'])} | {r['case']} | "
                         f"did not finish: {short_error(r['error'])} |" + " |" * 10)
            continue
        lines.append(
            f"| {r['problem']} | {r['n']:,} | {r['case']} | {r.get('iterations', '-')} | "
            f"{_fmt(r.get('setup_s'), '.2f')} | {_fmt(r.get('solve_s'), '.2f')} | "
            f"{r['peak_mb']:,.0f} | {r['matrices_mb']:,.0f} | "
            f"{'yes' if r.get('converged') else 'no'} | {_fmt(r.get('residual'), '.1e')} | "
            f"{_fmt(r.get('backward'), '.1e')} | {_fmt(r.get('freq_diff'), '.1e')} | "
            f"{_fmt(r.get('angle'), '.1e')} | {r.get('preconditioner', r.get('method', '-'))} |")
    return "\n".join(lines)


def fits(rows: list[dict], gib: float) -> str:
    """Per case: the DOFs at which its peak memory would reach ``gib``, from the peak per
    DOF of its largest run (memory grows about linearly in the DOFs on these paths, except
    the factor's, which grows faster: its figure is an upper bound)."""
    best: dict = {}
    for r in rows:
        if "error" not in r and r["n"] >= best.get(r["case"], {}).get("n", 0):
            best[r["case"]] = r
    parts = [f"{case}: ~{gib * 2**30 / (r['peak_mb'] * 2**20 / r['n']) / 1e6:.1f}M DOFs"
             for case, r in best.items()]
    return (f"Largest size that fits {gib:.0f} GiB (linear in the peak per DOF of each "
            "case's largest run; the factor grows faster, so its figure is an upper bound): "
            + "; ".join(parts) + ".")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="100k", help="comma-separated subset of "
                    + ",".join(TARGETS) + " (default 100k)")
    ap.add_argument("--problems", default=",".join(PROBLEMS),
                    help="comma-separated subset of " + ",".join(PROBLEMS))
    ap.add_argument("--large-problems", default="cantilever",
                    help="problems run at sizes from 300k on (default cantilever)")
    ap.add_argument("--cases", default=",".join(EIGEN_CASES + STATIC_CASES),
                    help="the cases of --full-problems (default all)")
    ap.add_argument("--full-problems", default="cantilever",
                    help="problems that run every case of --cases; the others run those "
                         "of " + ",".join(CORE_CASES))
    ap.add_argument("--count", type=int, default=COUNT)
    ap.add_argument("--timeout", type=float, default=1200.0, help="seconds per case")
    ap.add_argument("--memory-gib", type=float, default=24.0,
                    help="memory of the machine the 'fits' line extrapolates to")
    ap.add_argument("--json", default=None, help="also write all rows to this file")
    ap.add_argument("--child", choices=["prepare", "case"], help=argparse.SUPPRESS)
    ap.add_argument("--folder", help=argparse.SUPPRESS)
    ap.add_argument("--problem", help=argparse.SUPPRESS)
    ap.add_argument("--size", type=float, help=argparse.SUPPRESS)
    ap.add_argument("--case", help=argparse.SUPPRESS)
    ap.add_argument("--result", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    check_json_option(ap, args.json)
    from pipeline._util.interrupts import handle_signals

    handle_signals()  # SIGTERM and SIGHUP stop the running case too (run_watched)

    if args.child:
        folder = Path(args.folder)
        row = (prepare(args.problem, args.size, folder) if args.child == "prepare"
               else run_case(args.case, folder, args.count))
        row["peak_mb"] = _peak_mb()
        write_whole(args.result, json.dumps(row))
        return 0

    labels, problems = args.sizes.split(","), args.problems.split(",")
    cases = args.cases.split(",")
    bad = ([x for x in labels if x not in TARGETS] + [x for x in problems if x not in PROBLEMS]
           + [x for x in cases if x not in EIGEN_CASES + STATIC_CASES])
    if bad:
        ap.error(f"unknown size, problem or case {bad}")
    large, full = args.large_problems.split(","), args.full_problems.split(",")
    if importlib.util.find_spec("pyamg") is None:
        print("PyAMG not installed (pip install pyamg, or the bench extra): the smoothed "
              "aggregation cases are left out", flush=True)
        cases = [c for c in cases if not c.endswith("+sa")]
    rows = []
    load_before = os.getloadavg()[0]
    for label in labels:
        for problem in problems:
            if TARGETS[label] > 1.5e5 and problem not in large:
                continue
            with tempfile.TemporaryDirectory(prefix=f"bench_solvers_{problem}_") as tmp:
                folder = Path(tmp)
                size = mesh_size(problem, label)
                print(f"preparing {problem} {label} (mesh.size {size:.5f}) ...", flush=True)
                prep = _child(["--child", "prepare", "--folder", tmp, "--problem", problem,
                               "--size", repr(size)], args.timeout, folder / "prep.json")
                if "error" in prep:
                    rows.append({"problem": problem, "label": label, "case": "prepare",
                                 "error": prep["error"]})
                    continue
                for case in (cases if problem in full else
                             [c for c in cases if c in CORE_CASES]):
                    print(f"  {case} ...", flush=True)
                    row = _child(["--child", "case", "--folder", tmp, "--case", case,
                                  "--count", str(args.count)], args.timeout,
                                 folder / "case.json")
                    row.update(problem=problem, label=label, case=case)
                    row.setdefault("n", prep["n"])
                    rows.append(row)
                    if args.json:
                        write_whole(args.json, json.dumps(rows, indent=1))
    text = "\n\n".join([
        "## Solvers: ours against scipy's LOBPCG and PyAMG",
        f"Machine: {machine()}; load average (1 min) {load_before:.1f} before and "
        f"{os.getloadavg()[0]:.1f} after; {args.count} modes; times wall clock.",
        table(rows), fits(rows, args.memory_gib)])
    print()
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
