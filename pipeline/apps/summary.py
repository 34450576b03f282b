"""Human summary of an HDF5 file (``python -m pipeline inspect FILE.h5``).

Reads only the file (verified: schema, version, checksums). Sections the file does not
hold (a modes-only run has no state space; a simulation result has no mesh) are left
out; a file whose checksum is right but whose content is inconsistent (a group the
layout requires is missing, a dataset of the wrong shape) is refused with
:class:`~pipeline.errors.FileFormatError`, never a traceback.
"""

from __future__ import annotations

import numpy as np

from pipeline.apps.campbell import campbell_lines
from pipeline.store.read import LAYOUT_ERRORS, layout_error, read_rotation
from pipeline.store.summary import FileSummary, read_summary


def _or(text: str | None) -> str:
    return "?" if text is None else text


def _lines(s: FileSummary, path) -> list[str]:
    lines = []
    lines.append(f"file      {path}")
    lines.append(f"schema    {s.schema} v{s.schema_version}, pipeline "
                 f"{_or(s.pipeline_version)}, created {_or(s.created_utc)}")
    if s.content is not None:
        lines.append(f"content   {s.content}")
    if s.body is not None:
        b = s.body
        lines.append(f"body      {_or(s.name)}: mass {b.mass:.6g} kg, "
                     f"centre of mass {np.round(b.center_of_mass, 6).tolist()} m")
        moments, axes = np.linalg.eigh(b.inertia)
        principal = np.round(moments, 9).tolist()
        lines.append(f"          principal inertia {principal} kg m^2 (about the centre of mass)")
        lines.append("          principal axes " + ", ".join(
            f"p{k + 1} {(np.round(axes[:, k] * np.sign(axes[np.argmax(np.abs(axes[:, k])), k]), 3) + 0.0).tolist()}"
            for k in range(3)))
    if s.mesh is not None:
        m = s.mesh
        cells = [f"{n} {k}" for k, n in (m.cells or {}).items()]
        dofs = (f"{m.n_dofs} DOFs, {m.n_free_dofs} free; "
                if m.n_dofs is not None and m.n_free_dofs is not None else "")
        # a line or point region says so; a face region (the usual kind) goes unmarked
        kinds = {1: " (line)", 0: " (point)"}
        names = [r + kinds.get(m.region_dimensions.get(r, 2), "") for r in m.regions]
        lines.append(f"mesh      {m.n_points} points, {', '.join(cells) or 'no cells'}"
                     f"; {dofs}regions: {', '.join(names) or 'none'}")
    if s.modes is not None:
        freqs = s.modes.frequencies_hz
        labels = s.modes.labels if s.modes.labels is not None else [""] * len(freqs)
        res = s.modes.residuals
        residual = f", max residual {float(np.max(res)):.1e}" if res is not None and res.size \
            else ""
        lines.append(f"modes     {len(freqs)} (solver {_or(s.modes.solver)}{residual})")
        lines.append(f"  {'mode':>4}  {'f [Hz]':>12}  label")  # as `run` prints them
        for i, (f, lab) in enumerate(zip(freqs, labels), 1):
            lines.append(f"  {i:4d}  {f:12.4f}  {lab}")
    lines.append(f"models    {', '.join(s.models) or 'none (modes only)'}")
    for name, model in s.models.items():
        if model.n_states is None:
            continue
        extra = ""
        if model.filter_kind is not None:
            at = f" at {model.cutoff_hz:g} Hz" if model.cutoff_hz is not None else ""
            extra = f", filter {model.filter_kind}{at}"
        lines.append(f"  {name}: {model.n_states} states, inputs "
                     f"{list(model.input_names)}, outputs "
                     f"{list(model.output_names)}{extra}")
    if s.run is not None:
        stages = ", ".join(f"{k} {t:.2f} s" for k, t in s.run.times_s.items())
        peak = s.run.peak_memory_mb
        where = "" if s.run.ranks is None else f"; {s.run.ranks} MPI ranks"
        if s.run.parts_file:
            where += f", each reading its part of {s.run.parts_file}"
        lines.append(f"run       {stages}; peak {peak if peak is not None else 0:.0f} MB{where}")
    return lines


def summarize(path) -> str:
    """The text ``inspect`` prints for ``path`` (one verified read; FileFormatError for a
    file that is not ours, corrupt, or off the layout)."""
    summary = read_summary(path)
    try:
        lines = _lines(summary, path)
        rotation = read_rotation(path)
        if rotation is not None:
            lines += campbell_lines(rotation)
    except LAYOUT_ERRORS as exc:  # e.g. a non-finite inertia: the checksum holds, not our layout
        raise layout_error(path, exc) from None
    return "\n".join(lines)
