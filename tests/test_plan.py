"""The eigensolver plan is a pure function of plain numbers: no matrices here."""

from __future__ import annotations

import dataclasses

import pytest

from pipeline._util.resources import MULTIGRID_AUTO_DOFS, factor_path_bytes
from pipeline.errors import ConfigError, SolverError
from pipeline.solve.plan import (DENSE_MAX, MULTIGRID_AUTO_SWEEPS, EigenPlan, EigenProblem,
                                 Machine, factor_expected, plan_modes)

ROOMY = Machine(usable_bytes=1e15, backend="pardiso", half_solves=True)
N = 100_000


def test_a_small_problem_is_solved_dense():
    plan = plan_modes(EigenProblem(n=DENSE_MAX, count=4), ROOMY)
    assert plan.method == "dense" and not plan.keep_factor


def test_a_factor_with_half_solves_runs_block_lanczos_and_is_kept_at_shift_zero():
    plan = plan_modes(EigenProblem(n=N, count=20, keep=True), ROOMY)
    assert isinstance(plan, EigenPlan)
    assert (plan.method, plan.backend, plan.block_size, plan.keep_factor) == (
        "lanczos", "pardiso", 4, True)
    assert plan.fallback is None  # precision double: nothing to fall back to
    free = plan_modes(EigenProblem(n=N, count=20, shift=-1.0, supported=False, keep=True),
                      ROOMY)
    assert free.block_size == 8 and not free.keep_factor  # 6 rigid modes; K - sigma M


def test_a_factor_without_half_solves_runs_arpack_and_lanczos_is_refused():
    lu = Machine(usable_bytes=1e15, backend="superlu")
    assert plan_modes(EigenProblem(n=N, count=10), lu).method == "arpack"
    with pytest.raises(SolverError, match="'lanczos' needs a symmetric factor"):
        plan_modes(EigenProblem(n=N, count=10, method="lanczos"), lu)


def test_auto_precision_falls_back_to_mixed_and_then_to_multigrid():
    problem = EigenProblem(n=N, count=10, precision="auto", has_coarse=True)
    plan = plan_modes(problem, ROOMY)
    assert plan.method == "lanczos"
    assert plan.fallback == dataclasses.replace(problem, precision="mixed")
    # the estimate says a double factor does not fit, a float32 one does
    tight = Machine(usable_bytes=0.5 * (factor_path_bytes(N, 10)
                                        + factor_path_bytes(N, 10, single=True)),
                    backend="pardiso", half_solves=True)
    mixed = plan_modes(problem, tight)
    assert mixed.method == "mixed"
    assert mixed.fallback.method == "multigrid" and mixed.fallback.precision == "double"
    # nothing fits: multigrid at once, with no trial budget (no factor to go back to)
    none = plan_modes(problem, Machine(usable_bytes=1.0, backend="pardiso", half_solves=True))
    assert none.method == "multigrid" and none.multigrid_budget is None


def test_auto_tries_multigrid_from_its_size_on_a_budget_with_the_factor_behind():
    problem = EigenProblem(n=MULTIGRID_AUTO_DOFS, count=20, has_coarse=True)
    plan = plan_modes(problem, ROOMY)
    assert plan.method == "multigrid" and plan.multigrid_budget == MULTIGRID_AUTO_SWEEPS
    assert plan.fallback.method == "factor"
    assert plan_modes(plan.fallback, ROOMY).method == "lanczos"
    # no coarse space, a tolerance asked for, or a GPU factor: the factor path
    for other in (dataclasses.replace(problem, has_coarse=False),
                  dataclasses.replace(problem, tolerance=1e-9)):
        assert plan_modes(other, ROOMY).method == "lanczos"
    gpu = Machine(usable_bytes=1.0, backend="cudss", gpu=True)
    on_gpu = plan_modes(dataclasses.replace(problem, precision="auto"), gpu)
    assert on_gpu.method == "arpack" and on_gpu.fallback is None  # double, no host rule


def test_what_no_plan_can_solve_is_refused():
    with pytest.raises(SolverError, match="modes.count"):
        plan_modes(EigenProblem(n=10, count=9), ROOMY)
    with pytest.raises(ConfigError, match="mesh.order 2"):
        plan_modes(EigenProblem(n=N, count=4, method="multigrid"), ROOMY)
    with pytest.raises(ConfigError, match="modes.precision"):
        plan_modes(EigenProblem(n=N, count=4, precision="half"), ROOMY)
    with pytest.raises(ValueError, match="method 'fast'"):
        plan_modes(EigenProblem(n=N, count=4, method="fast"), ROOMY)


def test_factor_expected_follows_the_plan_rules():
    assert factor_expected(EigenProblem(n=N, count=20), ROOMY)
    assert not factor_expected(EigenProblem(n=N, count=20, supported=False), ROOMY)
    assert not factor_expected(EigenProblem(n=N, count=20),
                               dataclasses.replace(ROOMY, backend="superlu"))
    assert not factor_expected(EigenProblem(n=MULTIGRID_AUTO_DOFS, count=20), ROOMY)
