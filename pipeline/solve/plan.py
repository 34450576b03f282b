"""Which eigensolver the modes stage runs, decided from plain numbers: the plan.

:func:`plan_modes` is pure: from the problem (free DOFs, number of modes, shift, the
options of the ``modes`` config section, whether a coarse space exists) and the machine
(usable memory, what the chosen factorisation backend offers) it returns a frozen
:class:`EigenPlan`: the method, the shift, the Lanczos block size, the backend, whether
the factor is kept, the sweep budget of a multigrid trial, and the problem to plan again
if the chosen path gives up. :func:`pipeline.solve.eigen.solve_modes` executes it.

The methods (see :mod:`pipeline.solve.eigen` for the algorithms):

``dense``
    a dense generalized ``eigh``, up to :data:`DENSE_MAX` free DOFs (up to
    :data:`DENSE_WIDE_MAX` when the modes asked for are a large fraction of them);
``lanczos``
    shift-invert block Lanczos on a factor with forward and backward half-solves;
``arpack``
    ARPACK's shift-invert mode on any other factor;
``mixed``
    block Lanczos on a float32 factor, refined in double (:mod:`pipeline.solve.mixed`);
``multigrid``
    factor-free LOBPCG with a two-grid preconditioner (needs a coarse space).

Why ``auto`` switches to multigrid at a size: the factor path's flops grow like n^2 for
a 3D body and its factor like n^(4/3), the two-grid path about linearly in n, and on the
cantilever they cross near :data:`~pipeline._util.resources.MULTIGRID_AUTO_DOFS` free
DOFs (with half the peak memory at 1M). The two-grid cycle is not robust for every body
(nearly incompressible materials, thin walls and slender beams lock the P1 coarse space),
so under ``auto`` it runs as a trial on a budget of :data:`MULTIGRID_AUTO_SWEEPS`
sweeps, given up for the factor path when it projects more (when a factor fits).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Literal

from pipeline._util.resources import MULTIGRID_AUTO_DOFS, factor_path_bytes
from pipeline.config.schema import PRECISIONS
from pipeline.errors import ConfigError, SolverError

Method = Literal["dense", "lanczos", "arpack", "mixed", "multigrid"]
#: the values of ``modes.method`` (and of the ``method`` argument of ``solve_modes``)
METHODS = ("auto", "lanczos", "arpack", "dense", "factor", "multigrid")

DENSE_MAX = 600  # up to this many free DOFs, a dense generalized eigh
#: and up to this many when the modes asked for are more than DENSE_FRACTION of the free
#: DOFs: block Lanczos needs a Krylov space several times the modes wanted, which then
#: spans most of the space, and it stalls (500 modes of 795 DOFs: 149 steps, residual
#: 0.64, 32 s); a dense eigh of 4000 DOFs takes seconds and 3 x 128 MB
DENSE_WIDE_MAX = 4000
DENSE_FRACTION = 0.1


def dense_wanted(n: int, count: int) -> bool:
    """Whether ``auto`` solves ``count`` modes of ``n`` free DOFs with a dense eigh."""
    return n <= DENSE_MAX or (n <= DENSE_WIDE_MAX and count > DENSE_FRACTION * n)


# under method auto: the two-grid trial is given up for the factor path as soon as it
# projects more sweeps than this (5 times the cantilever's 8). At 1M DOFs the two paths
# break even near 22 sweeps; 40 lets a body that converges steadily but slowly
# (nu = 0.49: 24 sweeps, with half the factor path's memory) finish, and still gives up
# early on nu = 0.499 and a 0.5 mm strip (projected 44-53 sweeps after 7-10).
MULTIGRID_AUTO_SWEEPS = 40


@dataclass(frozen=True)
class EigenProblem:
    """What is asked: ``n`` free DOFs, the ``count`` lowest modes, the shift ``shift``
    (rad^2/s^2; 0 for a supported body), and the ``modes`` options: ``method`` (one of
    :data:`METHODS`), ``precision`` (double, mixed, auto), ``tolerance`` (0: the method's
    default), ``block_size`` and ``max_basis`` (None: the defaults), ``keep`` (hand the
    factor of K on), ``has_coarse`` (a coarse space for multigrid exists)."""

    n: int
    count: int
    shift: float = 0.0
    supported: bool = True
    method: str = "auto"
    precision: str = "double"
    tolerance: float = 0.0
    block_size: int | None = None
    max_basis: int | None = None
    keep: bool = False
    has_coarse: bool = False


@dataclass(frozen=True)
class Machine:
    """Where it runs: ``usable_bytes`` of host memory for the solver (beside K and M),
    the resolved factorisation ``backend`` and what it offers (``half_solves``: forward
    and backward substitutions; ``gpu``: its factor lives in GPU memory)."""

    usable_bytes: float
    backend: str
    half_solves: bool = False
    gpu: bool = False


@dataclass(frozen=True)
class EigenPlan:
    """How to solve it.

    method: the algorithm (module doc); shift: rad^2/s^2; backend: the factorisation
    (of K - shift M, or of the coarse operator for multigrid); block_size: Lanczos block;
    max_basis: Lanczos basis cap (None: its default); tolerance: as asked (0: default);
    keep_factor: hand the factor of K on (shift 0 only); multigrid_budget: sweeps after
    which a multigrid trial gives up (None: no trial); fallback: the problem to plan again
    when this path gives up (a slow trial, or a factor that does not fit), or None.
    """

    method: Method
    shift: float
    backend: str
    block_size: int
    max_basis: int | None
    tolerance: float
    keep_factor: bool
    multigrid_budget: int | None = None
    fallback: EigenProblem | None = None


def check_problem(problem: EigenProblem) -> None:
    """Refuse what no plan can solve: too many modes, an unknown method or precision,
    multigrid without a coarse space."""
    if problem.count >= problem.n - 1:
        raise SolverError(f"config key 'modes.count': got {problem.count}, expected fewer "
                          f"than the {problem.n - 1} free degrees of freedom of this mesh "
                          "(refine the mesh)")
    if problem.method not in METHODS:
        raise ValueError(f"method '{problem.method}': expected auto, lanczos, arpack, dense, "
                         "factor or multigrid")
    if problem.method == "multigrid" and not problem.has_coarse:
        raise ConfigError.field("modes.method", "multigrid", "'auto' or 'factor' (the "
                                "multigrid solver needs a quadratic mesh: mesh.order 2)")
    if problem.precision not in PRECISIONS:
        raise ConfigError.field("modes.precision", problem.precision, "double, mixed or auto")


def default_block_size(count: int, supported: bool = True) -> int:
    """Lanczos block size: up to 4 for a supported body, 8 for a free one.

    A block of b vectors costs one pass over the factor plus b vectors' arithmetic;
    larger blocks need more vectors in all before the wanted modes converge (20 modes of
    the cantilever: b = 4: 68 vectors in 17 blocks; 8: 104 in 13; 20: 180 in 9), so
    small blocks win as soon as the arithmetic per vector dominates, which it does at
    100k DOFs and more. A free body needs b >= 7: its six rigid-body modes share one
    eigenvalue, and a block Krylov space holds at most b copies of one eigenvalue.
    """
    return int(min(max(count, 1), 4)) if supported else 8


def plan_modes(problem: EigenProblem, machine: Machine) -> EigenPlan:
    """The plan for ``problem`` on ``machine`` (pure; :func:`check_problem` first)."""
    check_problem(problem)
    p = problem
    method, precision = p.method, p.precision
    dense = method == "dense" or (method in ("auto", "factor") and dense_wanted(p.n, p.count))
    # a GPU factor lives in GPU memory, checked by its backend: no host-memory rule
    # applies, and no multigrid trial (its factor is fast)
    gpu = not dense and method != "multigrid" and machine.gpu
    if gpu and precision == "auto":
        precision = "double"
    any_factor_fits = factor_path_bytes(p.n, p.count, single=True) <= machine.usable_bytes
    if (not dense and precision == "auto"
            and factor_path_bytes(p.n, p.count) > machine.usable_bytes):
        precision = "mixed"  # the estimate already says a double factor will not fit
        if method == "auto" and p.has_coarse and not any_factor_fits:
            method = "multigrid"  # nor a float32 one
    budget = None
    if (method == "auto" and p.has_coarse and not dense and p.n >= MULTIGRID_AUTO_DOFS
            and precision != "mixed" and p.tolerance == 0.0 and not gpu):
        method = "multigrid"  # a trial, given up for a factor if it converges slowly
        budget = MULTIGRID_AUTO_SWEEPS if any_factor_fits else None
    block = p.block_size or default_block_size(p.count, p.supported)
    plan = dict(shift=p.shift, backend=machine.backend, block_size=block,
                max_basis=p.max_basis, tolerance=p.tolerance,
                keep_factor=p.keep and p.shift == 0.0)
    if method == "multigrid":
        fallback = (dataclasses.replace(p, method="factor", precision=precision,
                                        has_coarse=False) if budget is not None else None)
        return EigenPlan(method="multigrid", multigrid_budget=budget, fallback=fallback,
                         **plan)
    if not dense and precision == "mixed":
        fallback = (dataclasses.replace(p, method="multigrid", precision="double")
                    if method == "auto" and p.has_coarse else None)
        return EigenPlan(method="mixed", fallback=fallback, **plan)
    if dense:
        return EigenPlan(method="dense", **{**plan, "keep_factor": False})
    lanczos = method == "lanczos" or (method in ("auto", "factor") and machine.half_solves)
    if lanczos and not machine.half_solves:
        raise SolverError(f"method 'lanczos' needs a symmetric factor; backend "
                          f"'{machine.backend}' has none (use method 'arpack')")
    # PARDISO's exact size after its analysis may still not fit: mixed precision then
    fallback = dataclasses.replace(p, precision="mixed") if precision == "auto" else None
    return EigenPlan(method="lanczos" if lanczos else "arpack", fallback=fallback, **plan)


def factor_expected(problem: EigenProblem, machine: Machine) -> bool:
    """Whether the plan for a supported body will factorise K itself with PARDISO at
    shift 0, judged before the values exist (so that a pattern analysis started during
    the assembly is used); a wrong guess costs only that background analysis."""
    p = problem
    return (p.supported and not dense_wanted(p.n, p.count) and p.precision != "mixed"
            and (p.method == "factor" or (p.method == "auto" and p.n < MULTIGRID_AUTO_DOFS))
            and machine.backend == "pardiso"
            and factor_path_bytes(p.n, p.count) <= machine.usable_bytes)
