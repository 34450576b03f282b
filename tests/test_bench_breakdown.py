"""The bench's time breakdown (benchmarks/bench_pipeline.py): where a case's seconds go.

Synthetic rows only (the bench itself runs the pipeline); the sums are exact, so the
checks are equalities to round-off."""

import pytest

from conftest import bench_module


@pytest.fixture(scope="module")
def bench():
    with bench_module("bench_pipeline") as module:
        yield module


def _row(bench, stats: dict) -> dict:
    times = {"mesh": 0.5, "assemble": 1.0, "modes": 3.0, "reduce": 0.25, "write": 0.125}
    seconds = bench.stage_seconds(times, stats, imports_s=0.75)
    return {"kind": "pipeline", "label": "100k", "n_dofs": 101_406, "total": sum(times.values()),
            "process_s": 6.0, "seconds": seconds}


def _cells(table: str) -> dict:
    head, _, row = table.splitlines()
    names = [c.strip() for c in head.strip("|").split("|")]
    return dict(zip(names, [c.strip() for c in row.strip("|").split("|")]))


def test_factor_path_splits_the_modes_stage(bench):
    stats = {"analysis_seconds": 0.4, "analysis_ahead": True, "numeric_seconds": 1.0,
             "solve_seconds": 1.25, "mass_seconds": 0.0625, "orthogonalisation_seconds": 0.25,
             "rayleigh_ritz_seconds": 0.125, "eigensolver_seconds": 1.6, "steps": 16}
    cells = _cells(bench.breakdown([_row(bench, stats)]))
    assert cells["imports"] == "0.75"
    assert cells["ordering"] == "(0.40 beside)"  # off the critical path: not subtracted
    assert cells["factorisation (multigrid: set-up)"] == "1.00"
    assert cells["passes over the factor"] == "1.25"
    # 3.0 - (1.0 + 1.25 + 0.0625 + 0.25 + 0.125) = 0.3125
    assert cells["modes, other"] == "0.31"
    # 6.0 - 0.75 - 4.875: no checks_s (an earlier JSON's row): all of it in the last
    assert cells["bench's checks"] == "-"
    assert cells["start, exit"] == "0.38"
    row = dict(_row(bench, stats), checks_s=0.25)
    cells = _cells(bench.breakdown([row]))
    assert cells["bench's checks"] == "0.25"
    assert cells["start, exit"] == "0.12"  # 0.375 - 0.25
    assert cells["refinement"] == "-"


def test_multigrid_path_has_its_set_up(bench):
    stats = {"setup_seconds": 1.5, "eigensolver_seconds": 2.5, "rayleigh_ritz_seconds": 0.25}
    cells = _cells(bench.breakdown([_row(bench, stats)]))
    assert cells["factorisation (multigrid: set-up)"] == "1.50"
    assert cells["passes over the factor"] == "-"
    assert cells["modes, other"] == "1.25"  # LOBPCG's sweeps


def test_rows_without_a_breakdown_are_left_out(bench):
    assert "no pipeline case" in bench.breakdown([{"kind": "straightforward", "label": "20k"}])


def _peer_rows(bench) -> list[dict]:
    freqs = [65.6, 162.6, 408.2, 974.5, 1011.1]
    ours = {"kind": "pipeline", "label": "100k", "n_dofs": 101_406, "peak_mb": 850.0,
            "frequencies": freqs, "mesh": 0.25, "assembly": 0.5, "eigensolve": 3.25,
            "reduction": 0.5, "write": 0.5, "total": 5.0}
    peer = {"kind": "ngsolve (pardiso_spd)", "label": "100k", "n_dofs": 88_008,
            "peak_mb": 1100.0, "frequencies": [f * 1.001 for f in freqs], "mesh": 1.0,
            "assembly": 1.0, "eigensolve": 10.0, "total": 12.0}
    return [bench.median_row([ours]), bench.median_row([peer])]


def test_peer_comparison_prints_both_ratios(bench):
    text = bench.peer_comparison(_peer_rows(bench))
    cells = _cells("\n".join(text.splitlines()[:3]))
    assert cells["NGSolve / pipeline time"] == "2.40x"  # 12 / 5: whole runs
    assert cells["pipeline mesh + assembly + eigensolve s"] == "4.0"
    assert cells["same work: NGSolve / pipeline"] == "3.00x"  # 12 / (0.25 + 0.5 + 3.25)
    assert cells["true rel. residual: pipeline, NGSolve"] == "-, -"  # not measured here
    assert "same work: mesh + assembly + eigensolve" in text


def test_peer_comparison_has_a_line_for_the_factor_path_beside_the_factor_free_one(bench):
    """At the sizes where the default path is factor-free, ``--also-factor``'s row is
    compared with NGSolve too, each line with the residuals it is at."""
    ours, peer = _peer_rows(bench)
    ours.update(method="multigrid-lobpcg", true_residual=6.1e-3)
    peer.update(true_residual=3.5e-8)
    factor = bench.median_row([dict(ours, kind="pipeline (factor)", method="block-lanczos",
                                    total=8.0, eigensolve=6.25, true_residual=9.0e-8,
                                    same_work=None)])
    mixed = dict(ours, kind="pipeline (mixed)", total=1.0)  # not a compared kind
    lines = bench.peer_comparison([ours, factor, mixed, peer]).splitlines()
    head = [c.strip() for c in lines[0].strip("|").split("|")]
    rows = [dict(zip(head, [c.strip() for c in line.strip("|").split("|")]))
            for line in lines[2:] if line.startswith("| 100k")]
    assert [r["pipeline"] for r in rows] == ["multigrid-lobpcg", "block-lanczos"]
    assert rows[1]["NGSolve / pipeline time"] == "1.50x"  # 12 / 8
    assert rows[1]["same work: NGSolve / pipeline"] == "1.71x"  # 12 / (0.25 + 0.5 + 6.25)
    assert rows[0]["true rel. residual: pipeline, NGSolve"] == "6.1e-03, 3.5e-08"
    assert rows[1]["true rel. residual: pipeline, NGSolve"] == "9.0e-08, 3.5e-08"


def test_same_work_is_the_median_over_runs(bench):
    runs = [{"kind": "pipeline", "total": t, "process_s": t, "peak_mb": 1.0, "mesh": 0.0,
             "assembly": 0.0, "eigensolve": e} for t, e in ((5.0, 1.0), (4.0, 3.0), (6.0, 2.0))]
    assert bench.median_row(runs)["same_work"] == 2.0
    assert bench.same_work({"mesh": 1.0, "assembly": None, "eigensolve": 1.0}) is None


def test_host_speed_is_each_figures_median_and_shown_per_case(bench):
    runs = [dict(_row(bench, {}), host_speed=speed)
            for speed in ((14.0, 90.0), (9.0, 120.0), (11.0, 100.0))]
    row = bench.median_row(runs)
    assert row["host_speed"] == [11.0, 100.0]  # per figure, not one run's pair
    cells = _cells(bench.breakdown([row]))
    assert (cells["host GB/s"], cells["host GFlop/s"]) == ("11.0", "100")
    line = bench._speed_line(runs)
    assert "9.0-14.0 GB/s" in line and "90-120 GFlop/s" in line
    assert bench._speed_line([_row(bench, {})]) == "Host speed: not measured."
    # a case without a probe (--no-probe) keeps its other columns
    cells = _cells(bench.breakdown([_row(bench, {})]))
    assert cells["host GB/s"] == "-" and cells["modes, other"] == "3.00"


def test_host_speed_probe_runs(bench):
    speed = bench.host_speed()
    assert speed is not None and speed[0] > 0.1 and speed[1] > 0.1


def test_accuracy_table_shows_ngsolve_measured_like_the_pipeline(bench):
    rows = [{"kind": "pipeline", "n_dofs": 101_406, "method": "block-lanczos",
             "true_residual": 3.7e-8, "backward_error": 5.0e-13},
            {"kind": "ngsolve (pardiso_spd)", "n_dofs": 98_142,
             "method": "arnoldi (30 vectors)", "true_residual": 4.0e-8,
             "backward_error": 4.9e-14},
            {"kind": "ngsolve (pardiso)", "n_dofs": 98_142, "error": "exit 1"}]
    table = [line for line in bench.accuracy_table(rows).splitlines()
             if line.startswith("| ngsolve")]
    assert len(table) == 1  # the failed variant has no row
    cells = [c.strip() for c in table[0].strip("|").split("|")]
    assert cells[:5] == ["ngsolve (pardiso_spd)", "98,142", "arnoldi (30 vectors)",
                         "4.0e-08", "4.9e-14"]


class _Vec:  # the parts of NGSolve's vectors, matrices and spaces mode_accuracy reads
    def __init__(self, x):
        self.x = x

    def FV(self):
        return self

    def NumPy(self):
        return self.x


class _Mat:
    def __init__(self, A):
        import scipy.sparse as sp

        L = sp.tril(A).tocsr().astype(complex)  # NGSolve's symmetric storage, complex
        self.csr = (L.data, L.indices, L.indptr)

    def CSR(self):
        return self.csr

    @property
    def mat(self):  # a bilinear form's matrix: the form stands in for itself
        return self


@pytest.fixture()
def ngs_bench():
    with bench_module("bench_ngsolve") as module:
        yield module


def test_ngsolve_accuracy_reads_its_lower_triangle_and_complex_vectors(ngs_bench):
    """bench_ngsolve.mode_accuracy on a small pencil stored as NGSolve stores it (lower
    triangle, complex) with one Dirichlet DOF: exact eigenvectors times arbitrary phases
    measure at round-off, a perturbed one at its perturbation."""
    import numpy as np
    import scipy.linalg as la
    import scipy.sparse as sp

    n = 30
    K = sp.diags([-np.ones(n - 1), 2.0 + np.linspace(0, 1, n), -np.ones(n - 1)],
                 [-1, 0, 1]).tocsr()
    M = sp.diags([np.full(n - 1, 0.1), np.full(n, 1.0), np.full(n - 1, 0.1)],
                 [-1, 0, 1]).tocsr()
    free = np.ones(n, dtype=bool)
    free[0] = False  # a held DOF: rows and columns left out
    fes = type("Fes", (), {"FreeDofs": lambda self: free})()
    w, V = la.eigh(K[1:, 1:].toarray(), M[1:, 1:].toarray())
    phases = np.exp(1j * np.random.default_rng(0).uniform(0, 2 * np.pi, 4))
    vecs = [_Vec(np.concatenate([[0.0], V[:, k]]) * phases[k]) for k in range(4)]
    exact = ngs_bench.mode_accuracy(_Mat(K), _Mat(M), fes, vecs, w[:4])
    # eigh's pairs are backward stable: a residual of a few eps times ||K|| (about 4),
    # far below what an unmirrored triangle (the missing upper band, order 1) gives
    assert exact["true_residual"] < 1e-13 and exact["backward_error"] < 1e-14
    vecs[2].x[5] += 1e-6 * phases[2]
    assert ngs_bench.mode_accuracy(_Mat(K), _Mat(M), fes, vecs, w[:4])["true_residual"] > 1e-8


def test_short_error_ends_at_a_clause_and_says_it_was_cut(bench):
    text = ("exit 1:     raise ResourceError( | pipeline.errors.ResourceError: the sparse "
            "factorisation of the 2323056-DOF stiffness matrix needs 29.0 GB, more than the "
            "4.11 GB usable (90% of the 4.57 GB available); a mesh.size about 1.71 times "
            "larger would fit")
    short = bench.short_error(text)
    assert short.endswith("(90% of the 4.57 GB available) (...)") and len(short) <= 160
    assert bench.short_error("exit 1: | ValueError: bad") == "bad"


def test_a_refused_case_keeps_its_variant_in_the_row_name(bench, monkeypatch):
    """A child that exits with an error (the factor path refused at 3M by the memory
    estimate) is named as its finished rows are: ``pipeline (factor)``, not the default
    path's ``pipeline``."""
    import types

    refused = types.SimpleNamespace(error=None, returncode=1, stdout="",
                                    stderr="error: needs about 31.1 GB")
    monkeypatch.setattr(bench, "run_watched", lambda cmd, timeout: refused)
    rows = {variant: bench._run_child("pipeline", "3M", 20, 1.0, variant)
            for variant in ("auto", "factor", "mixed")}
    assert [r["kind"] for r in rows.values()] == ["pipeline", "pipeline (factor)",
                                                  "pipeline (mixed)"]
    assert rows["factor"]["error"] == "exit 1: error: needs about 31.1 GB"
    straightforward = bench._run_child("straightforward", "3M", 20, 1.0)
    assert straightforward["kind"] == "straightforward"


def test_a_write_cut_short_leaves_the_old_file_whole(bench, tmp_path):
    """The bench's JSON and page writes go through the atomic writer: a write that fails
    halfway (an interrupt, a full disk) leaves the previous file as it was and no
    temporary beside it."""
    target = tmp_path / "rows.json"
    bench.write_whole(target, '{"rows": [1]}')
    assert target.read_text() == '{"rows": [1]}'

    def half_then_fail(fh):
        fh.write(b'{"rows": [1, 2')
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        bench.write_whole(target, half_then_fail)
    assert target.read_text() == '{"rows": [1]}'
    assert [p.name for p in tmp_path.iterdir()] == ["rows.json"]
