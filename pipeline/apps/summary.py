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
from pipeline.store.read import open_verified, read_strings


def _names(group, key: str) -> list[str]:
    """Port/state names stored as a string dataset or as an attribute of A."""
    if key in group:
        return read_strings(group[key])
    return read_strings(group["A"].attrs.get(key, []))


def _text(value) -> str:
    return value.decode("utf-8", "replace") if isinstance(value, bytes) else str(value)


def _lines(h5, path) -> list[str]:
    lines = []
    a = h5.attrs
    lines.append(f"file      {path}")
    lines.append(f"schema    {_text(a['schema'])} v{int(a['schema_version'])}, pipeline "
                 f"{_text(a.get('pipeline_version', '?'))}, created "
                 f"{_text(a.get('created_utc', '?'))}")
    if "content" in a:
        lines.append(f"content   {_text(a['content'])}")
    if "body" in h5:
        lines.append(f"body      {_text(a.get('name', '?'))}: mass "
                     f"{float(h5['body/mass'][()]):.6g} kg, centre of mass "
                     f"{np.round(h5['body/center_of_mass'][()], 6).tolist()} m")
        inertia = np.asarray(h5["body/inertia"][()], dtype=float).reshape(3, 3)
        moments, axes = np.linalg.eigh(inertia)
        principal = np.round(moments, 9).tolist()
        lines.append(f"          principal inertia {principal} kg m^2 (about the centre of mass)")
        lines.append("          principal axes " + ", ".join(
            f"p{k + 1} {(np.round(axes[:, k] * np.sign(axes[np.argmax(np.abs(axes[:, k])), k]), 3) + 0.0).tolist()}"
            for k in range(3)))
    if "mesh" in h5:
        m = h5["mesh"].attrs
        cells = [f"{len(h5['mesh/cells'][k])} {k}" for k in h5["mesh/cells"]] \
            if "mesh/cells" in h5 else []
        regions = sorted(h5["mesh/regions"]) if "mesh/regions" in h5 else []
        dofs = (f"{int(m['n_dofs'])} DOFs, {int(m['n_free_dofs'])} free; "
                if "n_dofs" in m and "n_free_dofs" in m else "")
        lines.append(f"mesh      {len(h5['mesh/points'])} points, {', '.join(cells) or 'no cells'}"
                     f"; {dofs}regions: {', '.join(regions) or 'none'}")
    if "modes/frequencies_hz" in h5:
        freqs = np.atleast_1d(h5["modes/frequencies_hz"][()])
        labels = read_strings(h5["modes/labels"]) if "modes/labels" in h5 else [""] * len(freqs)
        residual = (f", max residual {float(np.max(h5['modes/residuals'][()])):.1e}"
                    if "modes/residuals" in h5 and h5["modes/residuals"].size else "")
        lines.append(f"modes     {len(freqs)} (solver {_text(h5['modes'].attrs.get('solver', '?'))}"
                     f"{residual})")
        lines.append(f"  {'mode':>4}  {'f [Hz]':>12}  label")  # as `run` prints them
        for i, (f, lab) in enumerate(zip(freqs, labels), 1):
            lines.append(f"  {i:4d}  {f:12.4f}  {lab}")
    models = [g for g in ("statespace", "statespace_filtered", "lumped") if g in h5]
    lines.append(f"models    {', '.join(models) or 'none (modes only)'}")
    for g in models:
        grp = h5[g] if g != "lumped" else h5["lumped/statespace"] if "lumped/statespace" in h5 \
            else None
        if grp is None or "A" not in grp:
            continue
        extra = ""
        if "filter_kind" in grp.attrs:
            cutoff = (f" at {float(grp.attrs['cutoff_hz']):g} Hz" if "cutoff_hz" in grp.attrs
                      else "")
            extra = f", filter {_text(grp.attrs['filter_kind'])}{cutoff}"
        lines.append(f"  {g}: {grp['A'].shape[0]} states, inputs "
                     f"{_names(grp, 'input_names')}, outputs "
                     f"{_names(grp, 'output_names')}{extra}")
    if "run" in h5:
        r = h5["run"].attrs
        stages = ", ".join(f"{k[:-2]} {float(r[k]):.2f} s" for k in r if k.endswith("_s"))
        lines.append(f"run       {stages}; peak {float(r.get('peak_memory_mb', 0)):.0f} MB")
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
