"""Reduced-model stage: the modal state space (with its filtered twin) and the lumped
chain, from the FE matrices and modes. Called by :func:`pipeline.run.run_pipeline`.

Returns HDF5 datasets (``statespace``, ``statespace_filtered``, ``lumped``) and a short
text summary for the CLI.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from pipeline.config import Config
from pipeline.store.tree import Dataset

log = logging.getLogger(__name__)


def _damping_spec(cfg: Config):
    from pipeline.reduce.modal import DampingSpec

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
    from pipeline.solve.factorize import factorize

    return lambda K: factorize(K, backend, positive_definite=True).solve


def build_statespace(cfg: Config, space, regions, K, M, free, modes, solve=None):
    """The reduced model (pipeline.reduce.modal.ReducedModel) and its filtered twin.

    ``solve``: b -> K^-1 b for this K; default: the factorisation the modes stage kept
    (``modes.solve``), else K is factorised here."""
    from pipeline.reduce.filters import filtered_model
    from pipeline.fe.ports import port_matrices
    from pipeline.reduce.modal import reduce_model

    ports = port_matrices(space, regions, cfg.ports)
    F = ports.F[free].toarray()
    T = ports.T[:, free]
    reduced = reduce_model(K, M, modes.shapes, modes.omega2, F, T, cfg.reduction.modes,
                           _damping_spec(cfg), cfg.reduction.static_correction,
                           ports.input_names, ports.output_names,
                           factorize=_factorize(cfg.modes.solver,
                                                solve if solve is not None
                                                else getattr(modes, "solve", None)))
    filtered = None
    if cfg.filter.kind != "none":
        filtered = filtered_model(reduced, cfg.filter.kind, cfg.filter.cutoff_hz)
    return ports, reduced, filtered


def _compliance_units(ports) -> str:
    kinds = {(i, o) for i in ports.input_units for o in ports.output_units}
    return f"{kinds.pop()[1]}/{next(iter(ports.input_units))}" if len(kinds) == 1 else "mixed"


def build_models(cfg: Config, space, regions, K, M, free, modes, props, labels=None,
                 solve=None
                 ) -> tuple[dict[str, Dataset], dict[str, dict[str, Any]], dict[str, Any]]:
    """All configured reduced models: (datasets, group attributes, extras for the CLI).

    ``solve``: b -> K^-1 b for this K, see :func:`build_statespace`."""
    tree: dict[str, Dataset] = {}
    attrs: dict[str, dict[str, Any]] = {}
    summary: list[str] = []
    extras: dict[str, Any] = {"summary": summary}
    fe_deflection = None
    if cfg.reduction is not None:
        from pipeline.reduce.filters import filter_datasets, filter_group_attrs
        from pipeline.reduce.modal import statespace_datasets

        ports, reduced, filtered = build_statespace(cfg, space, regions, K, M, free, modes,
                                                     solve)
        tree.update(statespace_datasets(reduced, "statespace", _compliance_units(ports)))
        attrs["statespace"] = {"static_correction": reduced.static_correction,
                               "n_modes": reduced.n_modes, "n_basis": reduced.n_basis,
                               "input_units": list(ports.input_units),
                               "output_units": list(ports.output_units)}
        if filtered is not None:
            tree.update(filter_datasets(filtered, cfg.filter.kind, cfg.filter.cutoff_hz))
            attrs.update(filter_group_attrs(cfg.filter.kind, cfg.filter.cutoff_hz))
        extras["reduced"] = reduced
        extras["filtered"] = filtered
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
        tree_l, attrs_l, lines = build_lumped(cfg, modes, labels, fe_deflection)
        tree.update(tree_l)
        attrs.update(attrs_l)
        summary.extend(lines)
    return tree, attrs, extras


def build_lumped(cfg: Config, modes, labels, fe_deflection):
    """The lumped chain of ``cfg.lumped`` and its comparison with FE and beam theory."""
    from pipeline.reduce.lumped import (box_section, comparison_table, format_comparison, lumped_datasets,
                         lumped_group_attrs, lumped_model)

    g, mat = cfg.geometry, cfg.material
    section = box_section(g.height, g.depth, centroid=(g.height / 2, g.depth / 2))
    d_in, d_out = (0.0, -1.0, 0.0), (0.0, 1.0, 0.0)
    if cfg.ports.inputs and cfg.ports.inputs[0].kind == "force":
        d_in = cfg.ports.inputs[0].direction
    if cfg.ports.outputs and cfg.ports.outputs[0].kind == "displacement":
        d_out = cfg.ports.outputs[0].direction
    ratio = cfg.damping.ratio if cfg.damping.kind == "uniform" else (
        cfg.damping.ratios[0] if cfg.damping.kind == "per_mode" else 0.0)
    model = lumped_model(section, mat.E, mat.nu, mat.rho, g.length, cfg.lumped.elements,
                         cfg.lumped.constants, ratio, input_direction=d_in,
                         output_direction=d_out)
    fe_bending = [f for f, lab in zip(modes.frequencies_hz, labels or [])
                  if lab.startswith("bending_z_")][:3]
    ns = sorted({1, 2, 3, 5, 10, 20, cfg.lumped.elements})
    rows = comparison_table(section, mat.E, mat.nu, mat.rho, g.length, ns=ns,
                            fe_frequencies_hz=fe_bending or None,
                            fe_tip_deflection=fe_deflection)
    lines = [f"lumped chain: {cfg.lumped.elements} elements, {cfg.lumped.constants} constants; "
             "x-y bending, 1 N tip force:"]
    lines += ["  " + line for line in format_comparison(rows).splitlines()]
    return lumped_datasets(model, rows), lumped_group_attrs(model), lines


def build_connection_models(cfg: Config, space, regions, K_full, M_full, modes, shapes
                            ) -> tuple[dict[str, Dataset], list[str]]:
    """Connection-point (6x6) model, Craig-Bampton (``craig_bampton.modes`` > 0), the
    floating-frame invariants and the FE matrices Exudyn needs, for ``cfg.connections``.

    K_full, M_full: matrices of the unsupported body (n_dofs x n_dofs).
    shapes: (n_points, 3, n_m) modes of the run (used for the invariants without CB).
    """
    from pipeline.reduce.connection import build_connection_model, effective_mass_table
    from pipeline.apps.exports.exudyn import exudyn_datasets
    from pipeline.reduce.ffrf import build_ffrf

    tree: dict[str, Dataset] = {}
    model, _, conn_tree = build_connection_model(
        space, regions, K_full, M_full, cfg.connections, cfg.modes.count,
        damping=_damping_spec(cfg), backend=cfg.modes.solver)
    tree.update(conn_tree)
    parent = cfg.connections[0]
    lines = [f"connection point '{parent.name}' at {list(parent.point)} ({parent.coupling}): "
             "effective modal masses (kg, kg m^2) and cumulative fractions"]
    lines += ["  " + line for line in effective_mass_table(model, cfg.modes.count)]
    cb = None
    if cfg.craig_bampton_modes > 0:
        from pipeline.reduce.craig_bampton import build_craig_bampton

        cb, cb_tree = build_craig_bampton(space, regions, K_full, M_full, cfg.connections,
                                          cfg.craig_bampton_modes, backend=cfg.modes.solver)
        tree.update(cb_tree)
        lines.append(f"Craig-Bampton: {len(cfg.connections)} interface(s), "
                     f"{cfg.craig_bampton_modes} fixed-interface modes")
    _, ffrf_tree = build_ffrf(M_full, K_full, space.node_points, cb=cb, shapes=shapes,
                              omega2=modes.omega2, n_rigid=modes.n_rigid,
                              supported=bool(cfg.supports))
    tree.update(ffrf_tree)
    tree.update(exudyn_datasets(K_full, M_full))
    return tree, lines
