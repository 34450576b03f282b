"""Human summary of an HDF5 file (``python -m pipeline inspect FILE.h5``).

Reads only the file (verified: schema, version, checksum).
"""

from __future__ import annotations

import numpy as np

from .store import open_verified, read_strings


def _names(group, key: str) -> list[str]:
    """Port/state names stored as a string dataset or as an attribute of A."""
    if key in group:
        return read_strings(group[key])
    return read_strings(group["A"].attrs.get(key, []))


def summarize(path) -> str:
    lines = []
    with open_verified(path) as h5:
        a = h5.attrs
        lines.append(f"file      {path}")
        lines.append(f"schema    {a['schema']} v{int(a['schema_version'])}, pipeline "
                     f"{a['pipeline_version']}, created {a['created_utc']}")
        lines.append(f"body      {a.get('name', '?')}: mass {float(h5['body/mass'][()]):.6g} kg, "
                     f"centre of mass {np.round(h5['body/center_of_mass'][()], 6).tolist()} m")
        inertia = h5["body/inertia"][()]
        lines.append(f"          principal inertia {np.round(np.linalg.eigvalsh(inertia), 9).tolist()}"
                     " kg m^2 (about the centre of mass)")
        m = h5["mesh"].attrs
        cells = [f"{len(h5['mesh/cells'][k])} {k}" for k in h5["mesh/cells"]]
        regions = sorted(h5["mesh/regions"]) if "mesh/regions" in h5 else []
        lines.append(f"mesh      {len(h5['mesh/points'])} points, {', '.join(cells)}; "
                     f"{int(m['n_dofs'])} DOFs, {int(m['n_free_dofs'])} free; regions: "
                     f"{', '.join(regions) or 'none'}")
        freqs = h5["modes/frequencies_hz"][()]
        labels = read_strings(h5["modes/labels"])
        lines.append(f"modes     {len(freqs)} (solver {h5['modes'].attrs.get('solver', '?')}, "
                     f"max residual {float(np.max(h5['modes/residuals'][()])):.1e})")
        for i, (f, lab) in enumerate(zip(freqs, labels), 1):
            lines.append(f"  {i:3d}  {f:12.4f} Hz  {lab}")
        models = [g for g in ("statespace", "statespace_filtered", "lumped") if g in h5]
        lines.append(f"models    {', '.join(models) or 'none (modes only)'}")
        for g in models:
            grp = h5[g] if g != "lumped" else h5["lumped/statespace"] if "lumped/statespace" in h5 \
                else None
            if grp is None or "A" not in grp:
                continue
            extra = ""
            if "filter_kind" in grp.attrs:
                extra = f", filter {grp.attrs['filter_kind']} at {float(grp.attrs['cutoff_hz']):g} Hz"
            lines.append(f"  {g}: {grp['A'].shape[0]} states, inputs "
                         f"{_names(grp, 'input_names')}, outputs "
                         f"{_names(grp, 'output_names')}{extra}")
        if "run" in h5:
            r = h5["run"].attrs
            stages = ", ".join(f"{k[:-2]} {float(r[k]):.2f} s" for k in r if k.endswith("_s"))
            lines.append(f"run       {stages}; peak {float(r.get('peak_memory_mb', 0)):.0f} MB")
    return "\n".join(lines)
