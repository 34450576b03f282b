"""The modes stage of the pipeline: the lowest modes of the supported (or free) body,
their shapes on every mesh point and their labels.

The stage is a function of two frozen records: :class:`ModesInput` (what it needs from
the FE stage's :class:`~pipeline.fe.model.FEModel`: plain arrays and sparse matrices, no
finite-element objects) and the config's :class:`~pipeline.config.schema.ModesConfig`;
it returns :class:`~pipeline.solve.modes.Modes`. DOF 3*p+c is component c of mesh point
p throughout.

Four points along x, point 0 clamped, its 9 free DOFs a spring chain (K =
tridiag(-1, 2, -1) * 1e4 N/m, unit masses):

>>> import numpy as np, scipy.sparse as sp
>>> from pipeline.config.schema import ModesConfig
>>> n = 9
>>> K = sp.diags([-1.0, 2.0, -1.0], [-1, 0, 1], shape=(n, n), format="csr") * 1e4
>>> body = ModesInput(K=K, M=sp.identity(n, format="csr"), free=np.arange(3, 12),
...                   node_points=np.c_[np.arange(4.0), np.zeros(4), np.zeros(4)])
>>> modes = compute_modes(body, ModesConfig(count=2, solver="superlu"), keep=False)
>>> modes.shapes_full.shape, len(modes.labels)
((4, 3, 2), 2)
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from typing import Callable

import numpy as np
import scipy.sparse as sp

from pipeline.config.schema import ModesConfig
from pipeline.fe.body import node_volume_weights
from pipeline.fe.coarse import p1_prolongation
from pipeline.fe.model import FEModel
from pipeline.errors import ConfigError, SolverError
from pipeline.solve.blas import constraint_coordinates
from pipeline.solve.eigen import factor_expected, solve_modes
from pipeline.solve.labels import label_modes
from pipeline.solve.modes import Modes

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ModesInput:
    """What the modes stage needs from the FE stage.

    K, M: (n_free, n_free) stiffness (N/m) and mass (kg) on the free DOFs.
    free: (n_free,) sorted free DOF indices into the 3 * n_points DOFs of the body.
    node_points: (n_points, 3) point coordinates, m.
    node_weights: (n_points,) positive point weights for the labels (m^3: the volume
    each point stands for), or None (equal weights).
    supported: False for a free body (the eigensolver then shifts below the rigid modes).
    coarse: (n_free, n_coarse) prolongation from a coarse space onto the free DOFs
    (:func:`pipeline.fe.coarse.p1_prolongation`), which the multigrid solver needs, or
    None.
    rigid: (n_free, n_rigid) the rigid-body motions a partly held body keeps (exact null
    vectors of K, :func:`pipeline.fe.supports.rigid_freedoms`) and ``rigid_names`` theirs,
    or None: they replace the eigensolver's zero-frequency modes, M-orthonormalised, and
    name them.
    constraint: (n_free, n_q) T of an exact constraint u = T q
    (:mod:`pipeline.fe.constraints`), or None: the eigensolver then
    runs on T^T K T, T^T M T and the shapes are mapped back, phi = T psi.
    loads: (n_free, n_u) the right-hand sides F of the static solves K X = F that will
    follow with the kept solver (the reduce stage's input loads), or None: the
    factor-free solver runs their conjugate gradients inside its LOBPCG sweeps
    (:meth:`pipeline.solve.multigrid.TwoGrid.ride`).
    """

    K: sp.spmatrix
    M: sp.spmatrix
    free: np.ndarray
    node_points: np.ndarray
    node_weights: np.ndarray | None = None
    supported: bool = True
    coarse: sp.spmatrix | None = None
    rigid: np.ndarray | None = None
    rigid_names: tuple[str, ...] = ()
    constraint: sp.spmatrix | None = None
    loads: np.ndarray | None = None

    @classmethod
    def from_fe(cls, fe: FEModel, config: ModesConfig, *, supported: bool,
                loads: np.ndarray | None = None) -> ModesInput:
        """The input of the modes stage for ``fe``: the volume weights of its points and,
        unless ``config.method`` is ``factor``, the P1 prolongation of a P2 space.

        ``supported``: whether the config names supports (``bool(cfg.supports)``); the
        body is solved as a free one when they leave rigid-body modes (``fe.n_rigid``),
        and a partly held body's rigid motions are passed on (``rigid``). ``loads``: see
        the class.
        Hold the record no longer than the call it is built for: it keeps K alive.
        """
        partly = supported and fe.n_rigid > 0 and fe.rigid is not None
        return cls(K=fe.K, M=fe.M, free=fe.free, node_points=fe.space.node_points,
                   node_weights=node_volume_weights(fe.space),
                   supported=supported and fe.n_rigid == 0,
                   coarse=None if config.method == "factor"
                   else p1_prolongation(fe.space, fe.free),
                   rigid=fe.rigid.fields[fe.free] if partly else None,
                   rigid_names=fe.rigid.names if partly else (),
                   constraint=None if fe.constraint is None else fe.constraint.T,
                   loads=loads)


def expects_factor(n_free: int, config: ModesConfig, *, supported: bool) -> bool:
    """Whether :func:`compute_modes` will factorise K itself with PARDISO at shift 0 for
    ``n_free`` free DOFs under ``config`` (:func:`pipeline.solve.eigen.factor_expected`),
    so that a :class:`~pipeline.solve.backends.pardiso.PatternAnalysis` of K's pattern
    started during the assembly will be used."""
    return factor_expected(n_free, config.count, supported=supported, backend=config.solver,
                           method=config.method, precision=config.precision)


def full_shapes(shapes: np.ndarray, free: np.ndarray, n_points: int) -> np.ndarray:
    """(n_points, 3, n_m) shapes from (n_free, n_m) ones, zero on the fixed DOFs."""
    full = np.zeros((3 * n_points, shapes.shape[1]))
    full[free] = shapes
    return full.reshape(n_points, 3, -1)


def compute_modes(body: ModesInput, config: ModesConfig, *, keep: bool = True,
                  progress: Callable[[int], None] | None = None,
                  analysis=None) -> Modes:
    """The ``config.count`` lowest modes of (``body.K``, ``body.M``) with ``shapes_full``
    ((n_points, 3, n_m), zero on the fixed DOFs) and ``labels`` filled in.

    ``config`` picks the factorisation (``solver``), ``method``, ``precision`` and
    ``tolerance`` (see :func:`pipeline.solve.eigen.solve_modes`). The run-time handles:
    ``keep``: keep the factorisation of K in the result (supported bodies solved by
    factorisation), see :class:`pipeline.solve.modes.Modes` for who frees it;
    ``progress``, if given, is called with the number of right-hand sides of every solve;
    ``analysis``: a :class:`~pipeline.solve.backends.pardiso.PatternAnalysis` of K's
    pattern started during the assembly, or None.
    """
    if body.rigid is not None:
        check_count_above_rigid(config.count, body.rigid.shape[1], body.rigid_names)
    K, M, rigid, coarse, T = body.K, body.M, body.rigid, body.coarse, body.constraint
    if T is not None:  # u = T q: an ordinary SPD pencil on q (pipeline.fe.constraints)
        K, M = (T.T @ (K @ T)).tocsr(), (T.T @ (M @ T)).tocsr()
        rigid = None if rigid is None else constraint_coordinates(T, rigid)
        coarse = None if coarse is None else (T.T @ coarse).tocsr()
    modes = solve_modes(K, M, config.count, supported=body.supported,
                        backend=config.solver, tolerance=config.tolerance,
                        progress=progress, keep=keep, precision=config.precision,
                        method=config.method, coarse=coarse, analysis=analysis,
                        expected_rigid=0 if rigid is None else rigid.shape[1],
                        loads=body.loads if T is None and rigid is None else None)
    try:
        names = ()
        if rigid is not None:
            modes = with_rigid_motions(modes, M, rigid, body.rigid_names)
            names = tuple(f"rigid_{n}" for n in body.rigid_names)
        if T is not None:
            modes = dataclasses.replace(modes, shapes=np.asarray(T @ modes.shapes),
                                        constraint=T)
        shapes = full_shapes(modes.shapes, body.free, body.node_points.shape[0])
        labels = label_modes(body.node_points, shapes, modes.n_rigid, body.node_weights)
        labels[:len(names)] = names
    except BaseException:
        modes.release_factorization()
        raise
    for f, lab in zip(modes.frequencies_hz, labels):
        log.info("mode %-14s %12.4f Hz", lab, f)
    return dataclasses.replace(modes, shapes_full=shapes, labels=tuple(labels))


def with_rigid_motions(modes: Modes, M: sp.spmatrix, rigid: np.ndarray,
                       names: tuple[str, ...]) -> Modes:
    """``modes`` with its first r = rigid.shape[1] modes replaced by the rigid motions
    ``rigid`` (n_free, r), M-orthonormalised in their order (Gram-Schmidt keeps the
    first ones pure), at omega^2 = 0, and the elastic modes projected M-orthogonal to
    them and renormalised.

    Refuses (SolverError) more zero-frequency modes than r: a mechanism inside the mesh
    that the supports analysis cannot see; and fewer than r modes clearly below the
    first elastic one (the predicted motions are not null vectors of K).
    """
    r = rigid.shape[1]
    w = modes.omega2
    check_rigid_found(modes.n_rigid, w, r, names)
    R = np.array(rigid, dtype=float)
    MR = M @ R
    G = R.T @ MR
    L = np.linalg.cholesky(0.5 * (G + G.T))
    R = np.linalg.solve(L, R.T).T  # R L^-T: M-orthonormal, Gram-Schmidt order
    phi = np.array(modes.shapes[:, r:], dtype=float)
    phi -= R @ (R.T @ (M @ phi))
    phi /= np.sqrt(np.einsum("ij,ij->j", phi, M @ phi))
    omega2 = np.concatenate([np.zeros(r), w[r:]])
    return dataclasses.replace(modes, shapes=np.hstack([R, phi]), omega2=omega2,
                               frequencies_hz=np.sqrt(omega2) / (2 * np.pi), n_rigid=r)


def check_count_above_rigid(count: int, r: int, names: tuple[str, ...]) -> None:
    """Refuse (ConfigError, before the solve) ``modes.count`` not above the r rigid-body
    motions the supports leave (``names``)."""
    if count <= r:
        raise ConfigError.field("modes.count", count,
                                f"more than the {r} rigid-body mode(s) the "
                                f"supports leave ({', '.join(names)})")


def check_rigid_found(n_found: int, omega2: np.ndarray, r: int,
                      names: tuple[str, ...]) -> None:
    """Refuse (SolverError) an eigensolution whose zero-frequency modes do not match the
    r rigid-body motions the supports leave (``names``): more of them (``n_found``, a
    mechanism the supports analysis cannot see), or fewer than r of ``omega2`` (n_m,
    rad^2/s^2, ascending) clearly below the first elastic one."""
    w = omega2
    if n_found > r:
        raise SolverError(
            f"the stiffness system is singular: {n_found} zero-frequency modes where "
            f"the supports leave {r} rigid-body motion(s) ({', '.join(names)}): a mechanism "
            "inside the mesh (parts joined only at an edge or a point?)")
    if w.size <= r or (r and w[r - 1] > 1e-6 * w[r]):
        raise SolverError(
            f"the supports leave {r} rigid-body motion(s) ({', '.join(names)}), but the "
            f"eigensolver found {int(np.count_nonzero(w <= 1e-6 * w[-1]))} modes at ~0 Hz "
            f"among {w.size}; expected modes.count > {r} and the first {r} at ~0 Hz")
