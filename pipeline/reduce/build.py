"""Reduced-model stage: from the FE matrices and modes to the :class:`Models` record.
Called by :func:`pipeline.run.run_pipeline`.

:func:`build_models`: the modal state space (with its filtered twin) and the lumped
chain; :func:`build_connection_models`: the connection-point model, Craig-Bampton, the
floating-frame invariants and the FE matrices of the unsupported body. Both return a
:class:`~pipeline.reduce.models.Models` record (with text summary lines for the CLI);
:func:`pipeline.store.schema.models_tree` turns it into HDF5 datasets.
"""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np

from pipeline.config import Config
from pipeline.errors import ConfigError
from pipeline.fe.materials import config_materials
from pipeline.fe.ports import port_matrices
from pipeline.reduce.connection import (ConnectionModel, build_connection_model,
                                        connection_statespace, effective_mass_table)
from pipeline.reduce.craig_bampton import build_craig_bampton
from pipeline.reduce.ffrf import build_ffrf
from pipeline.reduce.filters import filtered_model
from pipeline.reduce.lumped import (box_section, comparison_table, format_comparison,
                                    lumped_model)
from pipeline.reduce.modal import DampingSpec, reduce_model
from pipeline.reduce.models import Models
from pipeline.reduce.statespace import StateSpace
from pipeline.solve.factorization import factorize

log = logging.getLogger(__name__)

__all__ = ["Models", "build_models", "build_statespace", "static_loads", "build_lumped",
           "build_connection_models", "connection_lines", "connection_outputs", "craig_bampton_line"]


def _damping_spec(cfg: Config) -> DampingSpec:
    d = cfg.damping
    if d.kind == "uniform":
        return DampingSpec("uniform", ratio=d.ratio)
    if d.kind == "per_mode":
        return DampingSpec("per_mode", ratios=tuple(d.ratios))
    return DampingSpec("rayleigh", alpha=d.alpha, beta=d.beta)


def _factorize(backend: str, solve=None):
    """K -> (b -> K^-1 b): ``solve`` when one is handed in (the modes stage's kept
    factorisation of this K, owned and freed by the caller), else a new factorisation."""
    if solve is not None:
        return lambda K: solve
    return lambda K: factorize(K, backend, positive_definite=True).solve


def check_ports_act(cfg: Config, ports, F_free: np.ndarray, T_free) -> None:
    """Refuse a port that loads or measures nothing once the supports and constraints
    have removed the fixed DOFs (a port on the clamped face, or along z under
    constraints.in_plane): its model row or column would be all zero (a "+nan" DC gain
    error), so the port is named with the reason.

    F_free: (n_free, n_u) loads on the free DOFs; T_free: (n_y, n_free) sensors."""
    F_all = ports.F
    T_all = ports.T
    checks = [("input", name, np.abs(F_free[:, j]).max(initial=0.0),
               abs(F_all[:, j]).max(), cfg.ports.inputs[j])
              for j, name in enumerate(ports.input_names)]
    T_free = T_free.tocsr() if hasattr(T_free, "tocsr") else T_free
    checks += [("output", name, abs(T_free[i]).max(), abs(T_all[i]).max(),
                cfg.ports.outputs[i])
               for i, name in enumerate(ports.output_names)]
    for side, name, on_free, on_all, port in checks:
        if on_all > 0 and on_free > 1e-12 * on_all:
            continue
        supported = {sup.region for sup in cfg.supports}
        if on_all == 0:
            why = f"it acts on no DOF of region '{port.region}'"
        elif port.region in supported:
            why = f"region '{port.region}' is held by the supports"
        elif cfg.constraints.in_plane:
            why = "its direction is removed by constraints.in_plane (u_z = 0)"
        else:
            why = "every DOF it acts on is fixed by the supports"
        raise ConfigError(
            f"config key 'ports.{side}s' ({side} port '{name}'): this port "
            + ("loads" if side == "input" else "measures") + f" nothing ({why}); put it on "
            "a region that can move, along a direction the supports and constraints leave "
            "free", key=f"ports.{side}s", value=name)


def static_loads(cfg: Config, space, regions, free) -> np.ndarray | None:
    """The loads F (n_free, n_u) of the input ports, whose static shapes K^-1 F
    :func:`build_statespace` will solve for, or None without a reduced model: the modes
    stage can start that solve early (:class:`pipeline.solve.stage.ModesInput`'s
    ``loads``). The same array :func:`build_statespace` makes."""
    if cfg.reduction is None or not cfg.ports.inputs:
        return None
    ports = port_matrices(space, regions, cfg.ports, material=config_materials(space, cfg))
    return ports.F[free].toarray()


def build_statespace(cfg: Config, space, regions, K, M, free, modes, solve=None):
    """The ports, the reduced model (pipeline.reduce.modal.ReducedModel) and its filtered
    twin (None without a filter).

    ``solve``: b -> K^-1 b for this K; default: the factorisation the modes stage kept
    (``modes.solve``), else K is factorised here."""
    ports = port_matrices(space, regions, cfg.ports, material=config_materials(space, cfg))
    F = ports.F[free].toarray()
    T = ports.T[:, free]
    check_ports_act(cfg, ports, F, T)
    reduced = reduce_model(K, M, modes.shapes, modes.omega2, F, T, cfg.reduction.modes,
                           _damping_spec(cfg), cfg.reduction.static_correction,
                           ports.input_names, ports.output_names,
                           factorize=_factorize(cfg.modes.solver,
                                                solve if solve is not None
                                                else getattr(modes, "solve", None)),
                           n_rigid=getattr(modes, "n_rigid", None),
                           inertia_relief=bool(cfg.supports),
                           constraint=getattr(modes, "constraint", None))
    filtered = None
    if cfg.filter.kind != "none":
        filtered = filtered_model(reduced, cfg.filter.kind, cfg.filter.cutoff_hz)
    return ports, reduced, filtered


def _compliance_units(ports) -> str:
    kinds = {(i, o) for i in ports.input_units for o in ports.output_units}
    return f"{kinds.pop()[1]}/{next(iter(ports.input_units))}" if len(kinds) == 1 else "mixed"


def build_models(cfg: Config, space, regions, K, M, free, modes, props, labels=None,
                 solve=None, statespace=None) -> Models:
    """All configured reduced models of ``cfg.reduction`` and ``cfg.lumped``.

    ``solve``: b -> K^-1 b for this K, see :func:`build_statespace`; ``statespace``: a
    function with the signature of :func:`build_statespace` that makes the state space
    instead (the distributed path's, on distributed mode shapes)."""
    fields: dict = {}
    summary: list[str] = []
    fe_deflection = None
    if cfg.reduction is not None:
        ports, reduced, filtered = (statespace or build_statespace)(
            cfg, space, regions, K, M, free, modes, solve)
        fields.update(reduced=reduced, filtered=filtered,
                      input_units=tuple(ports.input_units),
                      output_units=tuple(ports.output_units),
                      compliance_units=_compliance_units(ports))
        exact = reduced.static_compliance
        dc = reduced.dc_gain_position if exact is not None else None
        summary.append(f"reduced model: {reduced.n_modes} modes ({reduced.n_basis} basis "
                       f"vectors), static correction {reduced.static_correction}, "
                       f"{reduced.statespace.n_states} states"
                       + (f"; filtered: {cfg.filter.kind} at {cfg.filter.cutoff_hz:g} Hz, "
                          f"{filtered.n_states} states" if filtered is not None else ""))
        if dc is None:
            summary.append("  floating model (rigid-body modes retained): no static gain")
        for i, out in enumerate(ports.output_names if dc is not None else ()):
            for j, inp in enumerate(ports.input_names):
                line = f"  DC gain {inp} -> {out}: {dc[i, j]:.6e}"
                if exact is not None:
                    line += f" (full FE {exact[i, j]:.6e}, {dc[i, j] / exact[i, j] - 1:+.2e})"
                summary.append(line)
        if exact is not None and cfg.ports.inputs[0].kind == "force" \
                and cfg.ports.outputs[0].kind == "displacement":
            d_in = np.asarray(cfg.ports.inputs[0].direction, float)
            d_out = np.asarray(cfg.ports.outputs[0].direction, float)
            cos = d_in @ d_out / np.linalg.norm(d_in) / np.linalg.norm(d_out)
            if abs(abs(cos) - 1) < 1e-12:
                fe_deflection = float(exact[0, 0] * cos)
    if cfg.lumped is not None:
        lumped, rows, lines = build_lumped(cfg, modes, labels, fe_deflection)
        fields.update(lumped=lumped, comparison=tuple(rows))
        summary.extend(lines)
    return Models(**fields, summary=tuple(summary))


def build_lumped(cfg: Config, modes, labels, fe_deflection):
    """The lumped chain of ``cfg.lumped``, its comparison rows with FE and beam theory,
    and the summary lines."""
    g, mat = cfg.geometry, cfg.material
    section = box_section(g.height, g.depth, centroid=(g.height / 2, g.depth / 2))
    d_in, d_out = (0.0, -1.0, 0.0), (0.0, 1.0, 0.0)
    if cfg.ports.inputs and cfg.ports.inputs[0].kind == "force":
        d_in = cfg.ports.inputs[0].direction
    if cfg.ports.outputs and cfg.ports.outputs[0].kind == "displacement":
        d_out = cfg.ports.outputs[0].direction
    ratio = cfg.damping.ratio if cfg.damping.kind == "uniform" else (
        cfg.damping.ratios[0] if cfg.damping.kind == "per_mode" else 0.0)
    # point masses on the axis (the config refuses others with a chain)
    masses = tuple((m.point[0], m.mass, m.inertia[:3]) for m in cfg.masses)
    model = lumped_model(section, mat.E, mat.nu, mat.rho, g.length, cfg.lumped.elements,
                         cfg.lumped.constants, ratio, input_direction=d_in,
                         output_direction=d_out, point_masses=masses)
    fe_bending = [f for f, lab in zip(modes.frequencies_hz, labels or [])
                  if lab.startswith("bending_z_")][:3]
    ns = sorted({1, 2, 3, 5, 10, 20, cfg.lumped.elements})
    rows = comparison_table(section, mat.E, mat.nu, mat.rho, g.length, ns=ns,
                            fe_frequencies_hz=fe_bending or None,
                            fe_tip_deflection=fe_deflection, point_masses=masses)
    lines = [f"lumped chain: {cfg.lumped.elements} elements, {cfg.lumped.constants} constants; "
             "x-y bending, 1 N tip force:"]
    lines += ["  " + line for line in format_comparison(rows).splitlines()]
    return model, rows, lines


def connection_lines(cfg: Config, model: ConnectionModel) -> list[str]:
    """The summary lines of the connection model at ``cfg.connections[0]``: its effective
    modal masses (kg, kg m^2) and their cumulative fractions."""
    parent = cfg.connections[0]
    lines = [f"connection point '{parent.name}' at {list(parent.point)} ({parent.coupling}): "
             "effective modal masses (kg, kg m^2) and cumulative fractions"]
    return lines + ["  " + line for line in effective_mass_table(model, cfg.modes.count)]


def craig_bampton_line(cfg: Config) -> str:
    """The summary line of the Craig-Bampton data of ``cfg.connections``."""
    return (f"Craig-Bampton: {len(cfg.connections)} interface(s), "
            f"{cfg.craig_bampton_modes} fixed-interface modes")


def connection_outputs(cfg: Config, model: ConnectionModel) -> tuple[StateSpace, list[str]]:
    """The state space of ``model`` with the config's damping at its clamped frequencies
    (:func:`pipeline.reduce.connection.connection_statespace`) and its summary lines."""
    xi = _damping_spec(cfg).ratios_for(np.sqrt(np.maximum(model.omega2, 0.0)))
    return connection_statespace(model, xi), connection_lines(cfg, model)


def build_connection_models(cfg: Config, space, regions, K_full, M_full, modes, shapes,
                            models: Models | None = None) -> Models:
    """Connection-point (6x6) model, Craig-Bampton (``craig_bampton.modes`` > 0), the
    floating-frame invariants and the FE matrices Exudyn needs, for ``cfg.connections``:
    ``models`` (default empty) with those fields set and the summary lines appended.

    K_full, M_full: matrices of the unsupported body (n_dofs x n_dofs).
    shapes: (n_points, 3, n_m) modes of the run (used for the invariants without CB).
    """
    models = models if models is not None else Models()
    model, ss = build_connection_model(
        space, regions, K_full, M_full, cfg.connections, cfg.modes.count,
        damping=_damping_spec(cfg), backend=cfg.modes.solver)
    lines = connection_lines(cfg, model)
    cb = None
    if cfg.craig_bampton_modes > 0:
        cb = build_craig_bampton(space, regions, K_full, M_full, cfg.connections,
                                 cfg.craig_bampton_modes, backend=cfg.modes.solver)
        lines.append(craig_bampton_line(cfg))
    inv = build_ffrf(M_full, K_full, space.node_points, cb=cb, shapes=shapes,
                     omega2=modes.omega2, n_rigid=modes.n_rigid, supported=bool(cfg.supports))
    return replace(models, connection=model, connection_statespace=ss, craig_bampton=cb,
                   ffrf=inv, fe_matrices=(K_full, M_full),
                   summary=models.summary + tuple(lines))
