"""What a file holds, in brief: the reader behind ``inspect``, ``export --to json`` and the
batch cache's check of a cached result.

:func:`read_summary` opens a file once (verified, through
:func:`pipeline.store.read.open_verified`) and returns a :class:`FileSummary`: the root
attributes, and for each section the file holds (body, mesh, modes, each state-space model,
run) its sizes, names and small arrays. Sections a file does not hold are None (a
modes-only run has no state space; a simulation result has no mesh), so the reader takes
every file of :mod:`pipeline.store.layout`'s schema; a caller that needs a section says so
with :meth:`FileSummary.require`. Content that is there but off the layout (a body without
its inertia, a model group whose ``A`` has no names) is one FileFormatError line.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.store import layout as L
from pipeline.store.read import layout_error, open_verified, read_names, read_strings

__all__ = ["FileSummary", "BodySummary", "MeshSummary", "ModesSummary", "ModelSummary",
           "RunSummary", "read_summary"]


def _text(value: Any) -> str:
    return value.decode("utf-8", "replace") if isinstance(value, bytes) else str(value)


def _opt_text(attrs, key: str) -> str | None:
    return _text(attrs[key]) if key in attrs else None


def _floats(dset) -> np.ndarray:
    return np.array(dset[()], dtype=np.float64)


@dataclass(frozen=True, eq=False)
class BodySummary:
    """``/body``: mass (kg), center_of_mass (3,) m, inertia (3, 3) kg m^2 about it."""

    mass: float
    center_of_mass: np.ndarray
    inertia: np.ndarray


@dataclass(frozen=True, eq=False)
class MeshSummary:
    """``/mesh``: n_points; cells: element count by cell type in file order (None without
    ``/mesh/cells``); regions: region names, sorted; n_dofs, n_free_dofs: DOF counts
    (None in a file without them); region_dimensions: name -> 2 (face), 1 (line) or 0
    (point set), from each region dataset's column count."""

    n_points: int
    cells: dict[str, int] | None
    regions: tuple[str, ...]
    n_dofs: int | None
    n_free_dofs: int | None
    region_dimensions: dict[str, int] = field(default_factory=dict)


@dataclass(frozen=True, eq=False)
class ModesSummary:
    """``/modes``: frequencies_hz (n_m,) Hz; labels (n_m,) or None without them;
    residuals (n_m,) or None; solver: the eigensolver's name, or None."""

    frequencies_hz: np.ndarray
    labels: tuple[str, ...] | None
    residuals: np.ndarray | None
    solver: str | None


@dataclass(frozen=True, eq=False)
class ModelSummary:
    """One state-space group (``/statespace``, ``/statespace_filtered`` or the lumped
    chain's ``/lumped/statespace``), shown under ``name``.

    n_states: rows of A, None when the group has no A (then no names, no matrices);
    input_names (n_u,), output_names (n_y,); input_units, output_units (SI unit per input
    and per output port); filter_kind, cutoff_hz (Hz): of a filtered model, else None;
    static_correction: of the plant, else None; damping_ratios (n_r,) and
    static_compliance (n_y_pos, n_u) m/N, the full FE's T K^-1 F: of the plant, else None;
    matrices: A, B, C, D as float arrays of the plant and the filtered model (not of the
    lumped chain), else None.
    """

    name: str
    n_states: int | None
    input_names: tuple[str, ...] = ()
    output_names: tuple[str, ...] = ()
    input_units: tuple[str, ...] = ()
    output_units: tuple[str, ...] = ()
    filter_kind: str | None = None
    cutoff_hz: float | None = None
    static_correction: str | None = None
    damping_ratios: np.ndarray | None = None
    static_compliance: np.ndarray | None = None
    matrices: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None


@dataclass(frozen=True, eq=False)
class RunSummary:
    """``/run``: times_s: seconds per stage (attribute order); peak_memory_mb: peak RSS of
    the run (MB) or None; solver: the eigensolver used, or None; ranks: the MPI ranks of
    a distributed run, or None; parts_file: the partitioned mesh file its ranks read
    (``mesh.parts``), or None."""

    times_s: dict[str, float]
    peak_memory_mb: float | None
    solver: str | None
    ranks: int | None = None
    parts_file: str | None = None


@dataclass(frozen=True, eq=False)
class FileSummary:
    """What one result file holds, in brief (see :func:`read_summary`).

    schema, schema_version: of the file (checked on opening); pipeline_version,
    created_utc, content, name, config_yaml: root attributes, None where absent;
    body, mesh, modes, run: their sections or None; models: each state-space group the
    file holds (``statespace``, ``statespace_filtered``, ``lumped``, then
    ``connection/<name>`` and ``craig_bampton`` (n_states None: it stores M and K); none in
    a modes-only file), in that order, by name; lumped_frequencies_hz: the chain's first frequencies
    (Hz) or None.
    """

    path: Path
    schema: str
    schema_version: int
    pipeline_version: str | None
    created_utc: str | None
    content: str | None
    name: str | None
    config_yaml: str | None
    body: BodySummary | None
    mesh: MeshSummary | None
    modes: ModesSummary | None
    models: dict[str, ModelSummary]
    lumped_frequencies_hz: np.ndarray | None
    run: RunSummary | None

    @property
    def plant(self) -> ModelSummary | None:
        """The modal plant (``/statespace``), or None."""
        return self.models.get(L.STATESPACE.path)

    @property
    def filtered(self) -> ModelSummary | None:
        """The filtered model (``/statespace_filtered``), or None."""
        return self.models.get(L.STATESPACE_FILTERED.path)

    @property
    def lumped(self) -> ModelSummary | None:
        """The lumped chain's model (``/lumped/statespace``, shown as ``lumped``), or None."""
        return self.models.get(L.LUMPED.path)

    def require(self, *sections: str) -> FileSummary:
        """This summary when it holds every one of ``sections`` (``body``, ``mesh``,
        ``modes``, ``run``), else the FileFormatError that names the first missing one."""
        for section in sections:
            if getattr(self, section) is None:
                raise layout_error(self.path, KeyError(f"/{section} missing"))
        return self


def read_summary(path: str | Path, verify_checksum: bool = True) -> FileSummary:
    """The :class:`FileSummary` of ``path`` (one verified open; ``verify_checksum`` False
    skips only the checksums). FileFormatError for a file that is not ours, corrupt, or
    whose sections are off the layout."""
    path = Path(path)
    with open_verified(path, verify_checksum) as h5:
        a = h5.attrs
        return FileSummary(
            path=path, schema=_text(a[L.ROOT.schema]),
            schema_version=int(a[L.ROOT.schema_version]),
            pipeline_version=_opt_text(a, L.ROOT.pipeline_version),
            created_utc=_opt_text(a, L.ROOT.created_utc), content=_opt_text(a, L.ROOT.content),
            name=_opt_text(a, L.ROOT.name), config_yaml=_opt_text(a, L.ROOT.config_yaml),
            body=_body(h5), mesh=_mesh(h5), modes=_modes(h5), models=_models(h5),
            lumped_frequencies_hz=(_floats(h5[L.LUMPED.frequencies_hz])
                                   if L.LUMPED.frequencies_hz in h5 else None),
            run=_run(h5))


def _body(h5) -> BodySummary | None:
    if L.BODY.path not in h5:
        return None
    return BodySummary(float(h5[L.BODY.mass][()]), _floats(h5[L.BODY.center_of_mass]),
                       _floats(h5[L.BODY.inertia]).reshape(3, 3))


def _mesh(h5) -> MeshSummary | None:
    if L.MESH.path not in h5:
        return None
    m = h5[L.MESH.path].attrs
    cells = ({k: len(c) for k, c in h5[L.MESH.cells].items()} if L.MESH.cells in h5
             else None)
    regions = tuple(sorted(h5[L.MESH.regions])) if L.MESH.regions in h5 else ()
    n_dofs, n_free = L.MESH.attr.n_dofs, L.MESH.attr.n_free_dofs
    shapes = {name: h5[L.region(name)].shape for name in regions}
    return MeshSummary(len(h5[L.MESH.points]), cells, regions,
                       int(m[n_dofs]) if n_dofs in m else None,
                       int(m[n_free]) if n_free in m else None,
                       {name: s[1] - 1 for name, s in shapes.items() if len(s) == 2})


def _modes(h5) -> ModesSummary | None:
    if L.MODES.frequencies_hz not in h5:
        return None
    freqs = np.atleast_1d(_floats(h5[L.MODES.frequencies_hz]))
    labels = tuple(read_strings(h5[L.MODES.labels])) if L.MODES.labels in h5 else None
    residuals = (np.atleast_1d(_floats(h5[L.MODES.residuals])) if L.MODES.residuals in h5
                 else None)
    solver = (_opt_text(h5[L.MODES.path].attrs, L.MODES.attr.solver)
              if L.MODES.path in h5 else None)
    return ModesSummary(freqs, labels, residuals, solver)


#: the state-space groups a summary shows: (its section, shown by this name; the group of
#: its A, B, C, D)
_GROUPS = ((L.STATESPACE.path, L.STATESPACE),
           (L.STATESPACE_FILTERED.path, L.STATESPACE_FILTERED),
           (L.LUMPED.path, L.LUMPED_STATESPACE))

def _models(h5) -> dict[str, ModelSummary]:
    out: dict[str, ModelSummary] = {}
    for name, g in _GROUPS:
        if name not in h5:
            continue
        if g.A not in h5:
            out[name] = ModelSummary(name, None)
            continue
        grp = h5[g.path]
        at = L.STATESPACE_FILTERED.attr
        cutoff = float(grp.attrs[at.cutoff_hz]) if at.cutoff_hz in grp.attrs else None
        units = {k: tuple(read_strings(grp.attrs[getattr(L.STATESPACE.attr, k)]))
                 if getattr(L.STATESPACE.attr, k) in grp.attrs else ()
                 for k in ("input_units", "output_units")}
        plant = g is L.STATESPACE
        matrices = (tuple(np.atleast_2d(_floats(h5[g.dataset(k)])) for k in "ABCD")
                    if g is not L.LUMPED_STATESPACE else None)
        out[name] = ModelSummary(
            name, int(h5[g.A].shape[0]), read_names(grp, "input_names"),
            read_names(grp, "output_names"), **units,
            filter_kind=_opt_text(grp.attrs, at.filter_kind), cutoff_hz=cutoff,
            static_correction=(_opt_text(grp.attrs, L.STATESPACE.attr.static_correction)
                               if plant else None),
            damping_ratios=(_floats(h5[L.STATESPACE.damping_ratios])
                            if plant and L.STATESPACE.damping_ratios in h5 else None),
            static_compliance=(np.atleast_2d(_floats(h5[L.STATESPACE.static_compliance]))
                               if plant and L.STATESPACE.static_compliance in h5 else None),
            matrices=matrices)
    # the connection-point and Craig-Bampton models, named as load_model(...).models and
    # the FMU export's --model name them (the Craig-Bampton body stores M and K, no A)
    if L.CONNECTIONS.path in h5:
        for cname in sorted(h5[L.CONNECTIONS.path]):
            g = L.connection_statespace(cname)
            if g.A in h5:
                grp = h5[g.path]
                out[f"connection/{cname}"] = ModelSummary(
                    f"connection/{cname}", int(h5[g.A].shape[0]),
                    *(read_names(grp, k) for k in ("input_names", "output_names",
                                                   "input_units", "output_units")))
    if L.CRAIG_BAMPTON.M in h5:
        out["craig_bampton"] = ModelSummary("craig_bampton", None)
    return out


def _run(h5) -> RunSummary | None:
    if L.RUN.path not in h5:
        return None
    r = h5[L.RUN.path].attrs
    peak = L.RUN.attr.peak_memory_mb
    ranks = L.RUN.attr.ranks
    return RunSummary({k[:-2]: float(r[k]) for k in r if k.endswith("_s")},
                      float(r[peak]) if peak in r else None, _opt_text(r, L.RUN.attr.solver),
                      int(r[ranks]) if ranks in r else None,
                      _opt_text(r, L.RUN.attr.parts_file))

