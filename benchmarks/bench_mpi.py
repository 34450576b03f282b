"""Benchmark of the distributed path (``modes.solver: slepc``): wall time and peak memory
per rank on 1, 2 and 4 MPI ranks, and the per-rank memory model extrapolated to a large body.

``make bench`` runs it when the MPI environment exists (``make mpi-env``), with MUMPS'
factor and then factor-free (``--method multigrid``: the two-grid LOBPCG, whose only
factor is the P1 coarse problem's), so that the extrapolations say which solver takes
fewer nodes; by hand:
``.venv-mpi/bin/python benchmarks/bench_mpi.py [--size 0.005] [--ranks 1,2,4]``.

Each case is ``mpiexec -n P python benchmarks/bench_mpi.py --worker``: the pipeline on
``configs/cantilever.yaml`` (``modes.count`` 10, the shipped config's), then every rank
reports its peak resident memory (the largest of its steps' peaks), its resident memory,
its peak so far and its peak within the step at the end of each stage and step (VmRSS,
VmHWM, reset at each step), and the memory it had after loading the stack (the
interpreter, the pipeline's modules, numpy, scikit-fem, h5py, gmsh, petsc4py and
slepc4py with PETSc's, MUMPS' and MPI's libraries initialised: a constant per rank).

The memory model per rank, at N free DOFs on P ranks, fitted to the cases at N0 (free
DOFs, ``--size``) on 1, 2 and 4 ranks, at a second size on 2 and 4 ranks
(``--split-size``) and MUMPS' own figures at several sizes:

    m(P, N) = c + r0 + r N / N0 + [rank 0, P > 1] (w0 + w N / N0) + ((s + l) N / N0 + k F(N)) / P

c: the stack (measured); r0 + r N / N0 = R(N): what every rank holds whatever P is, its
constant and linear parts; w0 + w N / N0: what rank 0 alone holds besides during the
assembly, the solve and the reduce stage when P > 1 (on one rank the whole mesh is its
part): w, counted, the whole mesh's points and elements it keeps for the writer (24
bytes a point, 4 bytes a node of an element: int32,
:func:`pipeline.distributed.stage.handed_off`), and w0 the rest of rank 0's peak over
the others' mean (gmsh's library state after meshing, a constant, and MUMPS' shares,
which differ between ranks by tens of MB). Rank 0's mesh phase comes before that and
apart from it: it meshes the body with gmsh, builds the whole FE space to evaluate
regions, ports and the partition and cuts out the parts; its peak until the parts are
sent (the peak at the "parts sent" step) is fitted as M(N, P) = c + m0 + (m + mp / P) N
/ N0 on the cases of more than one rank (:func:`mesh_phase_fit`: m what it holds of the
whole mesh, mp / P its share of the partitioner's graph) and extrapolated beside the
solve phase. ``--mesh-phase SIZES`` measures that phase alone (the FE stage on 2 and 4
ranks at each mesh.size), rank 0's peak within each step (VmHWM is reset at each of
:func:`pipeline.distributed.mpi.log_resident`'s steps) in MB and bytes a free DOF;
with ``--parts`` also the partition command (one process: its peak, stack and time,
:func:`partition_worker`) and the FE stage read from its parts file (``mesh.parts``),
rank 0's peak up to the hand-off's end both ways (:func:`parts_table`).
R and the divided part d at N come from the ranks other than 0 on 2
and 4 ranks (each peaks at c + R + d / P: :func:`rank_split`; 4 ranks oversubscribe the
2 cores, which moves their times, not their memory): rank 0 is left out, so w does not
leak into R, and the 1-rank case is the check (c + R + d against its peak). R at two
sizes splits into r0 and r. d at N0 is MUMPS' factor F(N0), the mode shapes s and the
rest l (each rank's part of the mesh and FE space, its rows of K and M: linear in N).
F(N): what MUMPS allocated for the factor on all ranks (INFOG(19) MB,
which is its estimate after the analysis, INFOG(17); :mod:`pipeline.distributed.factor_memory`
logs it), measured on 2 ranks at the bench's sizes (``--fit-sizes`` besides ``--size``)
and fitted as F = alpha N^(4/3) + beta N (:func:`factor_fit`: a nested-dissection
factor's top separators and the levels below them; the single power law's exponent
and the local ones between sizes are printed beside it); k = 2 INFOG(18) / INFOG(19), the
largest rank's share over the mean. s, counted: the Rayleigh-Ritz step holds three
blocks of the shapes' rows (Phi, K Phi, M Phi: 3 x 8 N m / P bytes). Before MUMPS'
figures, all of d was extrapolated as N^(4/3) (an upper bound for a factor in nested
dissection order); the figures measured are in docs/distributed.md, "Measured scaling".
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from itertools import islice
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_pipeline import check_json_option, write_whole  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "cantilever.yaml"
NODE_GB = 24.0
NODE_USABLE = 0.8  # of a node's memory for the ranks (the OS, MPI buffers)
TARGET_DOFS = 10e6


def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


class _MumpsFigures(logging.Handler):
    """Collects MUMPS' figures after each numeric factorisation of the run (the records
    of :func:`pipeline.distributed.factor_memory.analysed_setup`)."""

    def __init__(self):
        super().__init__(logging.INFO)
        self.factors = []

    def emit(self, record) -> None:
        done = getattr(record, "mumps_factor", None)
        if done is not None:
            self.factors.append({"of": record.mumps_of, "entries": done.entries,
                                 "max_mb": done.max_bytes / 1e6,
                                 "sum_mb": done.sum_bytes / 1e6,
                                 "max_used_mb": done.max_used_bytes / 1e6,
                                 "sum_used_mb": done.sum_used_bytes / 1e6})


def _status_mb() -> dict[str, float]:
    """This process's resident memory now and its peak so far (VmRSS, VmHWM; MB)."""
    out = {}
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(("VmRSS:", "VmHWM:")):
                out[line[:5]] = int(line.split()[1]) / 1024.0
    return out


def _reset_peak() -> bool:
    """Reset this process's VmHWM to its VmRSS (``/proc/self/clear_refs`` 5), so that
    the next reading is the peak since now; False where the kernel refuses."""
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return True
    except OSError:
        return False


class _StageMemory(logging.Handler):
    """Each stage's resident memory at its end, the peak so far and the peak since the
    step before (VmRSS, VmHWM; MB), from the records of
    :func:`pipeline.run.run_pipeline` ("<stage> done in ...") and at the FE stage's
    steps (:func:`pipeline.distributed.mpi.log_resident`'s DEBUG records of
    :mod:`pipeline.distributed.stage`: "mesh read", "space built", "partitioned",
    "parts sent" ...). VmHWM is reset at each record (:func:`_reset_peak`), so the run's
    peak is the largest of the steps' (:meth:`peak_mb`): ru_maxrss follows the reset."""

    def __init__(self):
        super().__init__(logging.DEBUG)
        self.stages = []
        self.peak = 0.0
        self.resets = _reset_peak()

    def emit(self, record) -> None:
        if record.msg.startswith("%s done in"):
            name = record.args[0]
        elif record.msg.startswith("rank %d at %s: resident"):
            name = record.args[1]
        else:
            return
        now = _status_mb()
        step = now["VmHWM"]
        self.peak = max(self.peak, step)
        self.stages.append([name, round(now["VmRSS"]), round(self.peak),
                            round(step) if self.resets else None])
        self.resets = _reset_peak()

    def peak_mb(self) -> float:
        """This process's peak resident memory so far (MB)."""
        return max(self.peak, _status_mb()["VmHWM"])


def _load_stack() -> None:
    """Import and initialise what every rank loads whatever the problem (the pipeline's
    modules, scikit-fem, h5py, gmsh, petsc4py and slepc4py with PETSc's, MUMPS' and MPI's
    libraries), so that the memory measured after it (c) is the constant part."""
    import gmsh  # noqa: F401
    import h5py  # noqa: F401
    import skfem  # noqa: F401
    import pipeline.distributed.stage  # noqa: F401
    import pipeline.run  # noqa: F401
    from pipeline.distributed.mpi import petsc, world

    PETSc, _ = petsc()
    world().Barrier()


def worker(size: float, output: str, method: str, fe_only: bool = False,
           parts: str | None = None) -> None:
    """One MPI case: every rank runs the pipeline (``fe_only``: its FE stage alone, rank
    0's mesh phase and every rank's assembly; ``parts``: from that parts file,
    ``mesh.parts``); rank 0 prints a JSON line (with MUMPS' figures of each factor the
    run made, which rank 0 logs, and every rank's memory at the end of each stage and
    step)."""
    from pipeline.distributed.mpi import world
    from pipeline.api import run_config

    comm = world()
    _load_stack()
    base = _peak_mb()
    figures = _MumpsFigures()
    logger = logging.getLogger("pipeline.distributed.factor_memory")
    logger.addHandler(figures)
    logger.setLevel(logging.INFO)
    stages = _StageMemory()
    run_log = logging.getLogger("pipeline.run")
    run_log.addHandler(stages)
    run_log.setLevel(logging.INFO)
    step_log = logging.getLogger("pipeline.distributed.stage")
    step_log.addHandler(stages)
    step_log.setLevel(logging.DEBUG)
    overrides = [f"mesh.size={size}", "modes.solver=slepc", f"modes.method={method}"]
    overrides += [f"mesh.parts={parts}"] if parts else []
    t0 = time.perf_counter()
    if fe_only:
        result = _fe_stage(overrides)
    else:
        result = run_config(CONFIG, output=output, overrides=overrides)
    wall = time.perf_counter() - t0
    peaks = comm.gather(stages.peak_mb(), root=0)
    bases = comm.gather(base, root=0)
    by_stage = comm.gather(stages.stages, root=0)
    if comm.rank == 0:
        print("BENCH " + json.dumps({
            "ranks": comm.size, "n_free": result.n_free, "wall_s": wall,
            "kept_mb": kept_mb(result.n_dofs // 3, result.n_elements,
                               result.config.mesh.order),
            "times": result.times, "peak_mb": peaks, "import_mb": bases,
            "stages_mb": by_stage, "fe_only": fe_only,
            "f1_hz": None if fe_only else float(result.frequencies_hz[0]),
            "mumps": figures.factors}),
            flush=True)


def partition_worker(size: float, ranks: int, output: str) -> None:
    """``python -m pipeline partition`` of the cantilever at ``size`` for ``ranks`` ranks
    in this process (PT-Scotch where petsc4py imports): prints a JSON line with its
    wall time, its peak resident memory (VmHWM) and the stack's before it (MB), the
    file's size (MB) and the free DOFs."""
    from pipeline.config import load_config
    from pipeline.distributed.parts import write_partitioned

    import gmsh  # noqa: F401
    import h5py
    import skfem  # noqa: F401
    try:
        from pipeline.distributed.mpi import petsc

        petsc()
    except Exception:  # no petsc4py: the slab partition
        pass
    base = _status_mb()["VmHWM"]
    cfg = load_config(CONFIG, [f"mesh.size={size}"])
    t0 = time.perf_counter()
    write_partitioned(cfg, ranks, output)
    wall = time.perf_counter() - t0
    with h5py.File(output) as h5:
        n_free, kind = int(h5["shared/n_free"][()]), h5["shared/partition"].asstr()[()]
    print("BENCH " + json.dumps({"ranks": ranks, "n_free": n_free, "wall_s": wall,
                                 "peak_mb": _status_mb()["VmHWM"], "import_mb": base,
                                 "file_mb": Path(output).stat().st_size / 2**20,
                                 "partition": kind}), flush=True)


def _fe_stage(overrides: list[str]):
    """The distributed FE stage of the config alone (what :func:`worker` reports of a
    full run: free DOFs, DOFs, elements, the config, the stage times)."""
    import contextlib
    from types import SimpleNamespace

    from pipeline.config import load_config
    from pipeline.distributed.stage import build_fe_model

    cfg = load_config(CONFIG, overrides)
    fe = build_fe_model(cfg, None, lambda name: contextlib.nullcontext())
    return SimpleNamespace(n_free=fe.free.size, n_dofs=fe.space.n_dofs,
                           n_elements=fe.n_elements, config=cfg, times={})


def kept_mb(n_points: int, n_elements: int, order: int) -> float:
    """MB (2^20 bytes, as the peaks) of the whole mesh that rank 0 keeps for the writer
    from the hand-off on: the points (float64) and the elements (int32)."""
    nodes = 10 if order == 2 else 4
    return (24.0 * n_points + 4.0 * nodes * n_elements) / 2**20


def stage_mb(row: dict, rank: int, name: str) -> tuple[int, int] | None:
    """(VmRSS, VmHWM) MB of ``rank`` at the step or stage end ``name`` of a case (VmHWM:
    the peak so far), or None."""
    return next(((st[1], st[2]) for st in row.get("stages_mb", [[]] * (rank + 1))[rank]
                 if st[0] == name), None)


def step_peaks(row: dict, rank: int) -> list[tuple[str, int, int | None]]:
    """(step, VmRSS at its end, the peak since the step before or None) MB of ``rank``,
    in the run's order."""
    return [(st[0], st[1], st[3] if len(st) > 3 else None)
            for st in row.get("stages_mb", [[]] * (rank + 1))[rank]]


#: rank 0's steps up to and including the mesh phase's end
MESH_PHASE_END = "parts sent"
#: the step both ways of the mesh phase end with (meshing in the run, or reading a parts
#: file): every rank holds its part and the small results
HANDOFF_END = "small results sent"


def handoff_peak_mb(row: dict) -> float | None:
    """Rank 0's peak (MB, the stack included) over its steps up to :data:`HANDOFF_END`."""
    peaks = []
    for name, _, peak in step_peaks(row, 0):
        if peak is not None:
            peaks.append(peak)
        if name == HANDOFF_END:
            return max(peaks) if peaks else None
    return None


def mesh_phase_fit(rows: list[dict], n0: int | None = None) -> dict | None:
    """Rank 0's mesh phase (its peak until the parts are sent, less the stack c) on the
    cases of more than one rank, fitted by least squares as m0 + (m + mp / P) N / N0
    ({"m0", "m", "mp", "points"}: m what rank 0 holds of the whole mesh, mp / P its
    share of the partitioner's graph; N0: ``n0`` or the 1-rank case's size; mp = 0
    where every case has the same rank count), or None without two sizes."""
    import numpy as np

    n0 = n0 or next(r["n_free"] for r in rows if r["ranks"] == 1)
    points = sorted((r["n_free"], r["ranks"],
                     stage_mb(r, 0, MESH_PHASE_END)[1] - max(r["import_mb"]))
                    for r in rows if r["ranks"] > 1 and stage_mb(r, 0, MESH_PHASE_END))
    if len({n for n, _, _ in points}) < 2:
        return None
    n = np.array([p[0] for p in points], float) / n0
    ranks = np.array([p[1] for p in points], float)
    m = np.array([p[2] for p in points], float)
    columns = [np.ones_like(n), n] + ([n / ranks] if len(set(ranks)) > 1 else [])
    coef, *_ = np.linalg.lstsq(np.stack(columns, axis=1), m, rcond=None)
    return {"m0": float(coef[0]), "m": float(coef[1]),
            "mp": float(coef[2]) if len(coef) > 2 else 0.0, "points": points}


def mesh_phase_mb(mesh: dict, s: float, ranks: int) -> float:
    """Rank 0's mesh phase above the stack (MB) at s = N / N0 on ``ranks`` ranks."""
    return mesh["m0"] + (mesh["m"] + mesh["mp"] / ranks) * s


def mesh_phase_table(rows: list[dict]) -> list[str]:
    """Lines: rank 0's peak in each step of the FE stage above the stack c (MB and bytes
    a free DOF), per case, and the largest other rank's; then the mesh phase's fit."""
    lines = ["rank 0's FE stage by step (peak within the step above the stack c: MB, "
             "bytes a free DOF), the largest other rank's beside it"]
    for r in rows:
        c = max(r["import_mb"])
        cells = []
        for name, _, peak in step_peaks(r, 0):
            if peak is None:
                continue
            others = [p for k in range(1, r["ranks"]) for n, _, p in step_peaks(r, k)
                      if n == name and p is not None]
            cells.append(f"{name} {peak - c:.0f} MB {(peak - c) * 2**20 / r['n_free']:.0f} B"
                         + (f" ({max(others) - c:.0f} MB)" if others else ""))
        lines.append(f"{r['ranks']} ranks, {r['n_free']} free DOFs, c = {c:.0f} MB: "
                     + "; ".join(cells))
    fit = mesh_phase_fit(rows, max(r["n_free"] for r in rows))
    if fit:
        n0 = max(r["n_free"] for r in rows)
        per = 2**20 / n0
        lines.append(f"rank 0's mesh phase (peak until the parts are sent, less c) = m0 + "
                     f"(m + mp / P) N / N0, N0 = {n0}: m0 = {fit['m0']:.0f} MB, "
                     f"m = {fit['m'] * per:.0f} and mp = {fit['mp'] * per:.0f} bytes a "
                     "free DOF; measured " + ", ".join(f"{n} on {p}: {v:.0f} MB"
                                                       for n, p, v in fit["points"]))
    return lines


#: the partition comparison (``--cuts``): the slender cantilever and a compact cube
CUT_CASES = {"cantilever": [], "cube": ["geometry={kind: box, length: 0.1, height: 0.1, "
                                         "depth: 0.1}"]}
#: the partitions compared: slabs, PT-Scotch on the point graph and on the vertex graph
CUT_KINDS = ("slab", "points", "vertices")


def cut_worker(size: float, case: str) -> None:
    """Mesh and partition ``case`` both ways (no solve); rank 0 prints a JSON line with
    every rank's cut entries and halo columns of K (partition.cut_measures)."""
    from pipeline.config import load_config
    from pipeline.distributed.assemble import local_rows
    from pipeline.distributed.mpi import petsc, world
    from pipeline.distributed.partition import cut_measures, graph_partition, slab_partition
    from pipeline.distributed.submesh import split_mesh
    from pipeline.fe.materials import config_materials
    from pipeline.fe.mesh import mesh_body
    from pipeline.fe.regions import fixed_dofs, free_dofs, resolve_regions
    from pipeline.fe.space import build_space

    PETSc, _ = petsc()
    comm = world()
    cfg = load_config(CONFIG, [f"mesh.size={size}", *CUT_CASES[case]])
    body, _, _ = mesh_body(cfg.geometry, cfg.mesh, None, cfg.name)
    space = build_space(body, cfg.mesh.order)
    regions = resolve_regions(space, cfg.regions)
    free = free_dofs(space.n_dofs, fixed_dofs(space, regions, cfg.supports, False))
    out = {"case": case, "ranks": comm.size, "n_free": int(free.size)}
    options = PETSc.Options()
    for kind in CUT_KINDS:
        t0 = time.perf_counter()
        if kind == "slab":
            part = slab_partition(space.node_points, free, comm.size)
        else:  # the vertex graph (the default) or the point graph
            options.setValue("pipeline_partition_graph", kind)
            part = comm.bcast(graph_partition(PETSc, comm, space.element_nodes,
                                              space.node_points, free), root=0)  # rank 0's
            options.delValue("pipeline_partition_graph")
        seconds = time.perf_counter() - t0
        mesh = next(islice(split_mesh(space, config_materials(space, cfg), free, part,
                                      comm.size), comm.rank, None))
        rows = local_rows(mesh)
        out[kind] = {"cut": comm.gather(cut_measures(rows.K, rows.lo, rows.hi), root=0),
                     "rows": comm.gather(rows.hi - rows.lo, root=0), "seconds": seconds}
    if comm.rank == 0:
        print("BENCH " + json.dumps(out), flush=True)


def _mpiexec(ranks: int, args: list[str], timeout: float) -> dict:
    """``mpiexec -n ranks`` of this script with ``args`` (``ranks`` 0: one process
    without mpiexec); its JSON line."""
    mpiexec = shutil.which("mpiexec")
    root = ["--allow-run-as-root"] if os.geteuid() == 0 else []
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMPI_ALLOW_RUN_AS_ROOT": "1",
           "OMPI_ALLOW_RUN_AS_ROOT_CONFIRM": "1"}
    launch = [mpiexec, *root, "--oversubscribe", "-n", str(ranks), "-x", "PYTHONPATH"] \
        if ranks else []
    argv = [*launch, sys.executable, str(Path(__file__).resolve()), *args]
    proc = subprocess.run(argv, cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=timeout)
    for line in proc.stdout.splitlines():
        if line.startswith("BENCH "):
            return json.loads(line[6:])
    raise RuntimeError(f"{ranks} ranks failed (exit {proc.returncode}): "
                       f"{proc.stderr.strip().splitlines()[-1:]}")


def cut_table(size: float, ranks: list[int], timeout: float) -> list[str]:
    """Lines: the slab partition and the graph partitions of the point graph and the
    vertex graph (the default), per case and rank count: the largest cut and halo of any
    rank, the rows' imbalance (max / mean - 1) and the partition's seconds."""
    lines = [f"partitions (mesh.size {size} m): max over ranks of cut K entries / halo "
             "columns, row imbalance, seconds",
             f"{'case':>10} {'ranks':>5} {'free DOFs':>9}"
             + "".join(f" {kind + ' cut/halo':>21} {'imb':>5} {'s':>5}" for kind in CUT_KINDS)]
    for case in CUT_CASES:
        for p in ranks:
            r = _mpiexec(p, ["--cut-worker", "--case", case, "--size", str(size)], timeout)
            cells = []
            for kind in CUT_KINDS:
                cut = max(c[0] for c in r[kind]["cut"])
                halo = max(c[1] for c in r[kind]["cut"])
                imb = max(r[kind]["rows"]) / (sum(r[kind]["rows"]) / p) - 1
                cells.append(f" {f'{cut}/{halo}':>21} {imb:>5.1%} {r[kind]['seconds']:>5.2f}")
            lines.append(f"{case:>10} {p:>5} {r['n_free']:>9}" + "".join(cells))
    return lines


def run_case(ranks: int, size: float, method: str, timeout: float) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        return _mpiexec(ranks, ["--worker", "--size", str(size), "--method", method,
                                "--output", str(Path(tmp) / "bench.h5")], timeout)


#: mode shapes per case (the shipped config's modes.count plus SLEPc's one extra) and the
#: blocks of them the Rayleigh-Ritz step holds (Phi, K Phi, M Phi)
MODES, SHAPE_BLOCKS = 11, 3


def mumps_mb(row: dict) -> tuple[float, float]:
    """(all ranks' MB, the largest rank's MB) that MUMPS allocated for the largest factor
    of a case (INFOG(19), INFOG(18): its in-core estimate after the analysis)."""
    top = max(row["mumps"], key=lambda f: f["sum_mb"])
    return top["sum_mb"], top["max_mb"]


def factor_fit(rows: list[dict]) -> dict:
    """MUMPS' in-core data of the factor on all ranks (MB) against the free DOFs N over the
    2-rank cases: F = alpha N^(4/3) + beta N (non-negative least squares of F_fit / F - 1:
    a nested-dissection factor of a 3D mesh, its top separators N^(4/3), the levels below
    them N), and for comparison the single power law F = a N^b (least squares in log-log)
    with the local exponents between neighbouring sizes."""
    import numpy as np
    from scipy.optimize import nnls

    pts = sorted((r["n_free"], mumps_mb(r)[0]) for r in rows if r["ranks"] == 2 and r["mumps"])
    n, f = np.array([p[0] for p in pts], float), np.array([p[1] for p in pts], float)
    basis = np.stack([n ** (4.0 / 3.0), n], axis=1)
    (alpha, beta), _ = nnls(basis / f[:, None], np.ones(f.size))
    b, loga = np.polyfit(np.log(n), np.log(f), 1) if n.size > 1 else (4.0 / 3.0, 0.0)
    local = np.diff(np.log(f)) / np.diff(np.log(n))
    return {"alpha": float(alpha), "beta": float(beta), "b": float(b), "a": float(np.exp(loga)),
            "local": [float(x) for x in local], "points": pts,
            "misfit": float(np.abs(basis @ [alpha, beta] / f - 1).max())}


def rank_split(rows: list[dict], n_free: int) -> tuple[float, float] | None:
    """(R, D) MB at ``n_free`` from the 2- and 4-rank cases there, or None: the ranks other
    than 0 peak at c + R + D / P (their mean), so R = 2 m(4) - m(2) - c, D = 4 (m(2) - m(4))."""
    peak = {r["ranks"]: sum(r["peak_mb"][1:]) / (r["ranks"] - 1) for r in rows
            if r["n_free"] == n_free and r["ranks"] in (2, 4)}
    if len(peak) < 2:
        return None
    c = max(max(r["import_mb"]) for r in rows if r["n_free"] == n_free)
    return 2.0 * peak[4] - peak[2] - c, 4.0 * (peak[2] - peak[4])


def memory_model(rows: list[dict]) -> dict:
    """c, r0, r, w0, w, d, s, l (MB), k, MUMPS' fit (:func:`factor_fit`) and rank 0's
    mesh phase (:func:`mesh_phase_fit`, or None) of the module's
    model. At N0 (the 1-rank case's size) the ranks other than 0 on 2 and 4 ranks give what
    every rank holds, R(N0) = r0 + r, and the divided part d (:func:`rank_split`; rank 0
    is left out: it holds the whole mesh besides, but only when P > 1, so the 1-rank case
    cannot separate w from R); at a second size N1 with 2- and 4-rank cases R(N1) =
    r0 + r N1 / N0 splits R into its constant and linear parts (without one, all of R is
    taken as linear). w: the whole mesh rank 0 keeps at N0, counted (``kept_mb``); w0:
    rank 0's peak over the mean of the others' on 2 and 4 ranks (their mean; MUMPS'
    shares differ between ranks by tens of MB), less w. Of d, F(N0) is
    MUMPS' (2 ranks) and s the mode shapes'. ``one_mb``: the model's 1-rank peak
    (c + R + d) beside the measured ``one_measured_mb``."""
    one = next(r for r in rows if r["ranks"] == 1)
    n0 = one["n_free"]
    two = next(r for r in rows if r["ranks"] == 2 and r["n_free"] == n0)
    c = max(max(r["import_mb"]) for r in rows if r["n_free"] == n0)
    split = rank_split(rows, n0)
    if split is None:
        raise ValueError("the memory model needs the 2- and 4-rank cases at --size")
    R, d = split
    split_rows = [r for r in rows if r["n_free"] == n0 and r["ranks"] in (2, 4)]
    other = [rank_split(rows, r["n_free"]) + (r["n_free"],) for r in rows
             if r["ranks"] == 4 and r["n_free"] != n0]
    if other:
        R1, _, n1 = other[0]
        r = max((R - R1) / (n0 - n1) * n0, 0.0)
    else:
        R1, n1, r = None, None, max(R, 0.0)
    shapes = SHAPE_BLOCKS * 8.0 * n0 * MODES / 2**20
    fit = factor_fit(rows)
    total, largest = mumps_mb(two)
    factor = total / 2**20 * 1e6  # MiB, as the peaks
    return {"c": c, "r0": max(R - r, 0.0), "r": r, "R": R, "R1": R1, "n1": n1,
            "w": two["kept_mb"],
            "w0": max(sum(r["peak_mb"][0] - sum(r["peak_mb"][1:]) / (r["ranks"] - 1)
                          for r in split_rows) / len(split_rows) - two["kept_mb"], 0.0),
            "mesh": mesh_phase_fit(rows),
            "d": max(d, shapes + factor), "s": shapes,
            "l": max(d - shapes - factor, 0.0), "k": 2.0 * largest / total,
            "fit": fit, "factor": factor, "n0": n0, "one_mb": c + R + d,
            "one_measured_mb": max(one["peak_mb"])}


def mumps_factor_mb(model: dict, n: float) -> float:
    """MUMPS' in-core data of the factor on all ranks at n free DOFs (MiB, the fit
    alpha n^(4/3) + beta n)."""
    fit = model["fit"]
    return (fit["alpha"] * n ** (4.0 / 3.0) + fit["beta"] * n) * 1e6 / 2**20


def extrapolate(model: dict, n: float) -> list[str]:
    """Lines: per-rank memory at n DOFs against the rank count, and the nodes needed (the
    node of rank 0, which holds the whole mesh besides, is the one that must fit)."""
    s = n / model["n0"]
    fixed = model["c"] + model["r0"] + model["r"] * s
    whole = model.get("w0", 0.0) + model.get("w", 0.0) * s
    factor = model["k"] * mumps_factor_mb(model, n)
    shared = (model["s"] + model["l"]) * s + factor
    usable = NODE_GB * 1024 * NODE_USABLE
    lines = [f"model per rank at {n / 1e6:.0f}M DOFs: {fixed / 1024:.1f} GB on every rank "
             f"(imports {model['c'] / 1024:.2f} GB + a constant {model['r0'] / 1024:.2f} GB + "
             f"replicated {model['r'] * s / 1024:.1f} GB) "
             f"+ {shared / 1024:.0f} GB / P divided among P ranks (of it MUMPS' factor "
             f"{factor / 1024:.0f} GB / P, the mode shapes {model['s'] * s / 1024:.1f} GB / P),"
             f" rank 0 {whole / 1024:.2f} GB more (the whole mesh's points and elements "
             f"{model.get('w', 0.0) * s / 1024:.2f} GB)"]
    mesh = model.get("mesh")
    if mesh:
        mesh.setdefault("mp", 0.0)
        phase = model["c"] + mesh_phase_mb(mesh, s, 2)
        least = model["c"] + mesh_phase_mb(mesh, s, 10**9)
        lines.append(f"  rank 0's mesh phase (gmsh, the whole FE space, the partition, "
                     f"cutting the parts; before the assembly): {phase / 1024:.1f} GB on 2 "
                     f"ranks, {least / 1024:.1f} GB on many (its graph share divides; "
                     "fitted here on 2 and 4 ranks, measured at or below the fit on 8 and "
                     "16: docs/distributed.md), beside the other ranks' stack on its node"
                     + ("" if phase < usable else ": more than a node holds on 2 ranks"))
    for ranks_per_node in (1, 2, 4, 8):
        if ranks_per_node * fixed + whole >= usable:
            lines.append(f"  {ranks_per_node} rank(s) per {NODE_GB:g} GB node: the replicated "
                         "part alone does not fit")
            continue
        nodes = 1
        while ranks_per_node * (fixed + shared / (nodes * ranks_per_node)) + whole > usable:
            nodes += 1
        ranks = nodes * ranks_per_node
        phase = "" if not mesh else \
            f", its mesh phase {(model['c'] + mesh_phase_mb(mesh, s, ranks)) / 1024:.1f} GB"
        lines.append(f"  {ranks_per_node} rank(s) per {NODE_GB:g} GB node: {nodes} nodes "
                     f"({ranks} ranks, {fixed / 1024 + shared / 1024 / ranks:.1f} GB per rank, "
                     f"rank 0 {(fixed + whole) / 1024 + shared / 1024 / ranks:.1f} GB{phase})")
    return lines


def _run_cases(args) -> list[dict] | None:
    """The cases of ``main``'s arguments (None: no mpiexec, or ``--cuts`` only)."""
    if shutil.which("mpiexec") is None:
        print("bench_mpi: no mpiexec (make mpi-env)", file=sys.stderr)
        return None
    for line in ([] if args.no_cuts else cut_table(args.cut_size, [2, 4], args.timeout)):
        print(line)
    if args.cuts:
        return None
    rows = [run_case(int(p), args.size, args.method, args.timeout)
            for p in args.ranks.split(",")]
    rows += [run_case(2, float(h), args.method, args.timeout)
             for h in args.fit_sizes.split(",") if h and float(h) != args.size]
    if args.split_size and float(args.split_size) != args.size:
        if float(args.split_size) not in [float(h) for h in args.fit_sizes.split(",") if h]:
            rows.append(run_case(2, float(args.split_size), args.method, args.timeout))
        rows.append(run_case(4, float(args.split_size), args.method, args.timeout))
    return rows


def mesh_phase_main(args) -> int:
    """``--mesh-phase``: the FE stage alone at each size on each rank count (default 2
    and 4), rank 0's peak by step and the mesh phase's fit (:func:`mesh_phase_table`)."""
    if shutil.which("mpiexec") is None:
        print("bench_mpi: no mpiexec (make mpi-env)", file=sys.stderr)
        return 1
    if args.from_json:
        rows = json.loads(Path(args.from_json).read_text())
    else:
        ranks = [int(p) for p in (args.ranks if args.ranks != "1,2,4" else "2,4").split(",")]
        rows = [_mpiexec(p, ["--worker", "--fe-only", "--size", size, "--method",
                             args.method], args.timeout)
                for size in args.mesh_phase.split(",") for p in ranks]
        if args.json:
            write_whole(args.json, json.dumps(rows, indent=1))
    print(f"rank 0's mesh phase, cantilever mesh.size {args.mesh_phase} m")
    for line in mesh_phase_table(rows):
        print(line)
    if args.parts is not None:
        for line in parts_table(args, rows, ranks if not args.from_json else []):
            print(line)
    return 0


def parts_table(args, rows: list[dict], ranks: list[int]) -> list[str]:
    """``--mesh-phase ... --parts``: at each size and rank count the partition command
    (one process) and the FE stage from its parts file; lines comparing rank 0's peak
    up to the hand-off's end (:func:`handoff_peak_mb`) with the run that meshes."""
    lines = ["rank 0's peak up to the hand-off's end (MB, the stack included), meshing in "
             "the run / reading a parts file; the partition command's peak, stack and "
             "time (one process)",
             f"{'size m':>7} {'ranks':>5} {'free DOFs':>9} {'meshing':>8} {'parts':>6} "
             f"{'partition peak':>14} {'its stack':>9} {'time s':>7} {'file MB':>8}"]
    meshed = {(r["n_free"], r["ranks"]): r for r in rows}
    with tempfile.TemporaryDirectory() as tmp:
        for size in args.mesh_phase.split(","):
            for p in ranks:
                path = str(Path(tmp) / f"parts-{size}-{p}.h5")
                made = _mpiexec(0, ["--partition-worker", "--size", size, "--ranks", str(p),
                                    "--output", path], args.timeout)
                read = _mpiexec(p, ["--worker", "--fe-only", "--size", size, "--method",
                                    args.method, "--parts", path], args.timeout)
                Path(path).unlink()
                inrun = meshed.get((read["n_free"], p))
                lines.append(
                    f"{size:>7} {p:>5} {read['n_free']:>9} "
                    f"{handoff_peak_mb(inrun) if inrun else float('nan'):>8.0f} "
                    f"{handoff_peak_mb(read):>6.0f} {made['peak_mb']:>14.0f} "
                    f"{made['import_mb']:>9.0f} {made['wall_s']:>7.1f} {made['file_mb']:>8.1f}")
                lines.append("        rank 0's steps from the parts file: " + "; ".join(
                    f"{name} {peak:.0f}" for name, _, peak in step_peaks(read, 0)
                    if peak is not None))
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=float, default=0.005, help="mesh.size, m (0.005: 100k DOFs)")
    ap.add_argument("--ranks", default="1,2,4",
                    help="rank counts at --size (the model needs 1, 2 and 4; 4 ranks "
                         "oversubscribe 2 cores: their memory counts, not their time)")
    ap.add_argument("--fit-sizes", default="0.01,0.007,0.004",
                    help="further mesh.size values (m) run on 2 ranks for MUMPS' factor fit")
    ap.add_argument("--split-size", default="0.01",
                    help="mesh.size (m) also run on 4 ranks: what every rank holds, split "
                         "into its constant and linear parts ('' for none)")
    ap.add_argument("--method", default="factor", choices=["factor", "multigrid"])
    ap.add_argument("--timeout", type=float, default=1800.0)
    ap.add_argument("--json", default=None, help="also write the rows to this file")
    ap.add_argument("--from-json", default=None,
                    help="no runs: tabulate and fit the rows an earlier --json wrote")
    ap.add_argument("--cuts", action="store_true",
                    help="only compare the slab and graph partitions (no solve)")
    ap.add_argument("--cut-size", type=float, default=0.01, help="mesh.size of --cuts, m")
    ap.add_argument("--no-cuts", action="store_true",
                    help="skip the partition comparison (a second method's run)")
    ap.add_argument("--mesh-phase", default=None, metavar="SIZES",
                    help="only rank 0's mesh phase: the FE stage alone at these mesh.size "
                         "values (m, comma-separated) on --ranks (default 2,4 here), its "
                         "peak by step and the fit m0 + (m + mp / P) N / N0")
    ap.add_argument("--parts", nargs="?", const="", default=None, metavar="PATH",
                    help="with --mesh-phase: also the partition command and the FE stage "
                         "read from its parts file (mesh.parts), rank 0's peak both ways")
    ap.add_argument("--partition-worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--fe-only", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--cut-worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--case", default="cantilever", help=argparse.SUPPRESS)
    ap.add_argument("--output", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    check_json_option(ap, args.json)
    if args.worker:
        worker(args.size, args.output, args.method, args.fe_only, args.parts or None)
        return 0
    if args.partition_worker:
        partition_worker(args.size, int(args.ranks), args.output)
        return 0
    if args.mesh_phase:
        return mesh_phase_main(args)
    if args.cut_worker:
        cut_worker(args.size, args.case)
        return 0
    if args.from_json:
        rows = json.loads(Path(args.from_json).read_text())
    else:
        rows = _run_cases(args)
        if rows is None:
            return 1 if shutil.which("mpiexec") is None else 0
        if args.json:  # before the tables: a fit that fails keeps the runs
            write_whole(args.json, json.dumps(rows, indent=1))
    print(f"distributed path (SLEPc, {args.method}), cantilever mesh.size {args.size} m")
    print(f"{'ranks':>5} {'free DOFs':>10} {'assemble s':>10} {'modes s':>8} {'total s':>8} "
          f"{'peak MB per rank':>20} {'MUMPS entries':>13} {'MUMPS MB all/max':>16}")
    for r in rows:
        peaks = "/".join(f"{p:.0f}" for p in r["peak_mb"])
        top = max(r["mumps"], key=lambda f: f["sum_mb"]) if r["mumps"] else None
        mumps = (f"{top['entries']:>13.4g} {top['sum_mb']:>9.0f}/{top['max_mb']:<6.0f}"
                 if top else f"{'-':>13} {'-':>16}")
        print(f"{r['ranks']:>5} {r['n_free']:>10} {r['times'].get('assemble', 0):>10.1f} "
              f"{r['times'].get('modes', 0):>8.1f} {r['wall_s']:>8.1f} {peaks:>20} {mumps}")
    print("resident memory per rank at the end of each stage (MB; rank 0 / the largest "
          "other / the peak so far of the largest rank)")
    for r in rows:
        names = [st[0] for st in r.get("stages_mb", [[]])[0]]  # rank 0's steps: all of them
        cells = []
        for name in names:
            ranks = [stage_mb(r, k, name) for k in range(r["ranks"])]
            others = max((x[0] for x in ranks[1:] if x), default=0)
            cells.append(f"{name} {ranks[0][0]}/{others}/{max(x[1] for x in ranks if x)}")
        print(f"{r['ranks']:>5} {r['n_free']:>10}  " + ", ".join(cells))
    if {1, 2, 4} <= {r["ranks"] for r in rows} and all(r["mumps"] for r in rows):
        model = memory_model(rows)
        fit = model["fit"]
        print(f"MUMPS' factor on 2 ranks (INFOG(19), MB) at N = "
              + ", ".join(f"{n}: {f:.0f}" for n, f in fit["points"])
              + f": F(N) = {fit['alpha']:.3g} N^(4/3) + {fit['beta']:.3g} N (worst misfit "
              f"{fit['misfit']:.0%}); one power law N^{fit['b']:.3f}, the local exponents "
              + ", ".join(f"{x:.2f}" for x in fit["local"])
              + f"; the largest rank {model['k']:.2f} times the mean (INFOG(18))")
        split = (f"R = {model['R']:.0f} MB at {model['n0']} and {model['R1']:.0f} MB at "
                 f"{model['n1']} free DOFs" if model["n1"] else f"R = {model['R']:.0f} MB")
        print(f"what every rank holds (2 and 4 ranks, the ranks other than 0): {split}; "
              f"the model's 1-rank peak {model['one_mb']:.0f} MB, measured "
              f"{model['one_measured_mb']:.0f} MB")
        print(f"fit: c = {model['c']:.0f} MB (imports), r0 = {model['r0']:.0f} MB (constant), "
              f"r = {model['r']:.0f} MB (replicated, linear in N), "
              f"w0 = {model['w0']:.0f} MB and w = {model['w']:.1f} MB (rank 0's constant "
              f"and its whole mesh's points and elements), d = {model['d']:.0f} MB "
              f"(divided: MUMPS' factor {model['factor']:.0f} MB, the mode shapes "
              f"{model['s']:.0f} MB, the rest l = {model['l']:.0f} MB) at {model['n0']} free DOFs")
        if model["mesh"]:
            mesh = model["mesh"]
            print("rank 0's mesh phase (peak until the parts are sent, less c; MB) at "
                  "(N, P) = " + ", ".join(f"({n}, {p}): {m:.0f}" for n, p, m in mesh["points"])
                  + f": m0 = {mesh['m0']:.0f} MB, m = {mesh['m']:.1f} MB and "
                  f"mp = {mesh['mp']:.1f} MB at N0 (m0 + (m + mp / P) N / N0)")
        for line in extrapolate(model, TARGET_DOFS):
            print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
