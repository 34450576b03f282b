"""Human summary of an HDF5 file (``python -m pipeline inspect FILE.h5``).

Reads only the file (verified: schema, version, checksums). Sections the file does not
hold (a modes-only run has no state space; a simulation result has no mesh) are left
out; a file whose checksum is right but whose content is inconsistent (a group the
layout requires is missing, a dataset of the wrong shape) is refused with
:class:`~pipeline.errors.FileFormatError`, never a traceback.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.errors import FileFormatError
from pipeline.store.layout import (BODY, LUMPED, LUMPED_STATESPACE, MESH, MODES, ROOT, RUN,
                                   STATESPACE, STATESPACE_FILTERED)
from pipeline.store.read import open_verified, read_names, read_strings


def _names(group, key: str) -> list[str]:
    return list(read_names(group, key))


def _text(value) -> str:
    return value.decode("utf-8", "replace") if isinstance(value, bytes) else str(value)


def _lines(h5, path) -> list[str]:
    lines = []
    a = h5.attrs
    lines.append(f"file      {path}")
    lines.append(f"schema    {_text(a[ROOT.schema])} v{int(a[ROOT.schema_version])}, pipeline "
                 f"{_text(a.get(ROOT.pipeline_version, '?'))}, created "
                 f"{_text(a.get(ROOT.created_utc, '?'))}")
    if ROOT.content in a:
        lines.append(f"content   {_text(a[ROOT.content])}")
    if BODY.path in h5:
        lines.append(f"body      {_text(a.get(ROOT.name, '?'))}: mass "
                     f"{float(h5[BODY.mass][()]):.6g} kg, centre of mass "
                     f"{np.round(h5[BODY.center_of_mass][()], 6).tolist()} m")
        inertia = np.asarray(h5[BODY.inertia][()], dtype=float).reshape(3, 3)
        moments, axes = np.linalg.eigh(inertia)
        principal = np.round(moments, 9).tolist()
        lines.append(f"          principal inertia {principal} kg m^2 (about the centre of mass)")
        lines.append("          principal axes " + ", ".join(
            f"p{k + 1} {(np.round(axes[:, k] * np.sign(axes[np.argmax(np.abs(axes[:, k])), k]), 3) + 0.0).tolist()}"
            for k in range(3)))
    if MESH.path in h5:
        m = h5[MESH.path].attrs
        cells = [f"{len(c)} {k}" for k, c in h5[MESH.cells].items()] \
            if MESH.cells in h5 else []
        regions = sorted(h5[MESH.regions]) if MESH.regions in h5 else []
        n_dofs, n_free = MESH.attr.n_dofs, MESH.attr.n_free_dofs
        dofs = (f"{int(m[n_dofs])} DOFs, {int(m[n_free])} free; "
                if n_dofs in m and n_free in m else "")
        lines.append(f"mesh      {len(h5[MESH.points])} points, {', '.join(cells) or 'no cells'}"
                     f"; {dofs}regions: {', '.join(regions) or 'none'}")
    if MODES.frequencies_hz in h5:
        freqs = np.atleast_1d(h5[MODES.frequencies_hz][()])
        labels = read_strings(h5[MODES.labels]) if MODES.labels in h5 else [""] * len(freqs)
        residual = (f", max residual {float(np.max(h5[MODES.residuals][()])):.1e}"
                    if MODES.residuals in h5 and h5[MODES.residuals].size else "")
        solver = _text(h5[MODES.path].attrs.get(MODES.attr.solver, '?'))
        lines.append(f"modes     {len(freqs)} (solver {solver}{residual})")
        lines.append(f"  {'mode':>4}  {'f [Hz]':>12}  label")  # as `run` prints them
        for i, (f, lab) in enumerate(zip(freqs, labels), 1):
            lines.append(f"  {i:4d}  {f:12.4f}  {lab}")
    # (name shown, group of its A, B, C, D)
    groups = [(STATESPACE.path, STATESPACE), (STATESPACE_FILTERED.path, STATESPACE_FILTERED),
              (LUMPED.path, LUMPED_STATESPACE)]
    models = [(name, g) for name, g in groups if name in h5]
    lines.append(f"models    {', '.join(name for name, _ in models) or 'none (modes only)'}")
    for name, g in models:
        if g.A not in h5:
            continue
        grp = h5[g.path]
        extra = ""
        kind, cutoff = STATESPACE_FILTERED.attr.filter_kind, STATESPACE_FILTERED.attr.cutoff_hz
        if kind in grp.attrs:
            at = (f" at {float(grp.attrs[cutoff]):g} Hz" if cutoff in grp.attrs else "")
            extra = f", filter {_text(grp.attrs[kind])}{at}"
        lines.append(f"  {name}: {h5[g.A].shape[0]} states, inputs "
                     f"{_names(grp, 'input_names')}, outputs "
                     f"{_names(grp, 'output_names')}{extra}")
    if RUN.path in h5:
        r = h5[RUN.path].attrs
        stages = ", ".join(f"{k[:-2]} {float(r[k]):.2f} s" for k in r if k.endswith("_s"))
        lines.append(f"run       {stages}; peak {float(r.get(RUN.attr.peak_memory_mb, 0)):.0f} MB")
    return lines


def summarize(path) -> str:
    with open_verified(path) as h5:
        try:
            lines = _lines(h5, path)
        except (KeyError, IndexError, ValueError, TypeError, OSError, RuntimeError) as exc:
            # the checksum holds, so the file was written like this: not our layout
            text = " ".join(str(exc).split())[:200]
            raise FileFormatError(f"file '{Path(path)}': inconsistent with the layout of "
                                  f"docs/hdf5-format.md ({type(exc).__name__}: {text})") from None
    return "\n".join(lines)
