"""Export the mesh and every mode shape for ParaView: VTU (``.vtu``) or XDMF (``.xdmf``).

``python -m pipeline export FILE.h5 --to vtu`` (or ``--to xdmf``) writes, with meshio:

- the mesh: /mesh/points and the /mesh/cells (``tetra10``: ParaView draws the quadratic
  cells; or ``tetra``);
- point data ``mode_NN_<label>_<f>Hz`` (n_points x 3, e.g. ``mode_01_bending_z_1_65.63Hz``):
  the M-orthonormal shape of mode NN, one array per mode (in ParaView: *Warp By Vector*
  with that array, and colour by it);
- the suggested display scale of every mode, ``display_scale`` [m sqrt(kg)] (the
  scale factor for *Warp By Vector*): 0.1 x the body's largest dimension / the mode's largest
  displacement, so the warped body moves a tenth of its size (a mass-normalised shape
  of a 0.5 m aluminium beam at scale 1 throws its tip 1.7 m);
- point data ``stress_eta_NN``, ``stress_residual_<input>`` (n_points x 6, ParaView's
  tensor order) and ``von_mises_static_<input>`` where the file has stress modes
  (:mod:`pipeline.apps.exports.stress_arrays`);
- point data ``fixed_components`` (0..3: how many displacement components the supports
  fix at each point) and ``region_<name>`` (1 on the points of each named region);
- the frequencies: in the VTU as field data ``frequencies_hz`` (all modes, Hz),
  ``mode_numbers`` and ``display_scale`` (meshio does not write field data, so it is
  added to the XML here); XDMF has no field data that meshio and ParaView both read, so
  there the frequencies are in the array names, and frequencies and scales in the
  datasets ``/frequencies_hz`` and ``/display_scale`` of the sidecar file.

XDMF keeps its arrays in a sidecar HDF5 file named like the ``.xdmf`` with ``.h5``:
that is why the default name is ``<stem>.modes.xdmf`` (sidecar ``<stem>.modes.h5``),
and an output whose sidecar would overwrite the input file is refused.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from pipeline._util.atomic import atomic_path, private_folder
from pipeline.errors import ConfigError
from pipeline.apps.exports.stress_arrays import stress_point_data
from pipeline.store.read import read_stored_mesh

log = logging.getLogger(__name__)

__all__ = ["export", "export_vtu", "export_xdmf", "mode_mesh", "mode_array_name",
           "display_scales"]


#: the warped body moves this fraction of its largest dimension at the suggested scale
DISPLAY_FRACTION = 0.1


def mode_array_name(index: int, frequency_hz: float, label: str = "") -> str:
    """Point-data name of mode ``index`` (0-based), e.g. ``mode_01_bending_z_1_65.75Hz``
    (``mode_01_65.75Hz`` without a label)."""
    f = f"{frequency_hz:.1f}" if abs(frequency_hz) >= 100 else f"{frequency_hz:.4g}"
    label = "".join(c if c.isalnum() or c == "_" else "_" for c in label)
    return f"mode_{index + 1:02d}_{label + '_' if label else ''}{f}Hz"


def display_scales(points: np.ndarray, shapes: np.ndarray) -> np.ndarray:
    """(n_modes,) factor that makes each mode's largest displacement
    :data:`DISPLAY_FRACTION` of the body's largest dimension (0 for a zero shape)."""
    size = float(np.ptp(points, axis=0).max())
    peak = np.linalg.norm(shapes, axis=1).max(axis=0)  # (n_modes,)
    return np.where(peak > 0, DISPLAY_FRACTION * size / np.where(peak > 0, peak, 1.0), 0.0)


def mode_mesh(h5_path: str | Path):
    """A :class:`meshio.Mesh` of ``h5_path`` (verified) with every mode as point data."""
    import meshio

    modes = read_stored_mesh(h5_path)
    points, kind, cells, shapes = modes.points, modes.cell_type, modes.cells, modes.shapes
    freqs, labels, fixed, regions = (modes.frequencies_hz, modes.labels, modes.fixed_dofs,
                                     modes.regions)
    point_data: dict[str, np.ndarray] = {}
    for i, f in enumerate(freqs):
        label = labels[i] if i < len(labels) else ""
        point_data[mode_array_name(i, f, label)] = np.ascontiguousarray(shapes[:, :, i])
    point_data["fixed_components"] = np.bincount(fixed // 3, minlength=points.shape[0]
                                                 ).astype(np.int32)[:points.shape[0]]
    for name, tris in regions.items():
        mask = np.zeros(points.shape[0], dtype=np.int32)
        mask[np.unique(tris)] = 1
        point_data[f"region_{name}"] = mask
    point_data.update(stress_point_data(h5_path))  # stress modes, where the file has them
    log.debug("mode labels: %s", ", ".join(labels))
    return meshio.Mesh(points, [(kind, cells)], point_data=point_data,
                       field_data={"frequencies_hz": freqs,
                                   "mode_numbers": np.arange(1, freqs.size + 1, dtype=np.int32),
                                   "display_scale": display_scales(points, shapes)})


def export_vtu(h5_path: str | Path, out_path: str | Path) -> Path:
    """Write a VTU file (binary, zlib-compressed) of ``h5_path``; returns its path."""
    import meshio

    out_path = Path(out_path)
    mesh = mode_mesh(h5_path)
    with atomic_path(out_path) as tmp:
        meshio.write(tmp, mesh, file_format="vtu", binary=True, compression="zlib")
        _add_field_data(tmp, mesh.field_data)
    log.info("wrote %s (%d points, %d modes; ParaView: Warp By Vector, scale factor "
             "display_scale = %s)", out_path, len(mesh.points),
             len(mesh.field_data["frequencies_hz"]),
             ", ".join(f"{v:.3g}" for v in mesh.field_data["display_scale"]))
    return out_path


def _add_field_data(path: Path, field_data: dict[str, np.ndarray]) -> None:
    """Insert ``<FieldData>`` (ASCII arrays) into a VTU file written by meshio."""
    arrays = []
    for name, data in field_data.items():
        data = np.asarray(data).ravel()
        if data.dtype.kind == "f":
            vtk_type, text = "Float64", " ".join(f"{v:.17g}" for v in data)
        else:
            vtk_type, text = "Int32", " ".join(str(int(v)) for v in data)
        arrays.append(f'<DataArray type="{vtk_type}" Name="{name}" NumberOfTuples="{data.size}" '
                      f'format="ascii">{text}</DataArray>')
    block = ("<FieldData>" + "".join(arrays) + "</FieldData>").encode()
    raw = path.read_bytes()
    tag = b"<UnstructuredGrid>"
    at = raw.find(tag)
    if at < 0:  # pragma: no cover - meshio always writes it
        raise RuntimeError(f"'{path}': no <UnstructuredGrid> element to add field data to")
    at += len(tag)
    path.write_bytes(raw[:at] + block + raw[at:])


def export_xdmf(h5_path: str | Path, out_path: str | Path) -> Path:
    """Write an XDMF file (+ its ``<stem>.h5`` sidecar) of ``h5_path``; returns the .xdmf."""
    import meshio

    out_path = Path(out_path)
    if out_path.suffix.lower() != ".xdmf":
        raise ConfigError(f"export output: got '{out_path}', expected a name ending in .xdmf")
    sidecar = out_path.with_suffix(".h5")
    if sidecar.resolve() == Path(h5_path).resolve():
        raise ConfigError(f"export output: '{out_path}' would write its data to '{sidecar}', "
                          "the input file itself; expected another name (the default is "
                          "<stem>.modes.xdmf)")
    import h5py

    mesh = mode_mesh(h5_path)
    # meshio names the sidecar after the .xdmf, so both are made under their final names
    # in a private folder beside the target, then each is moved into place through the
    # atomic writer (sidecar first: a .xdmf under its final name always finds its data)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    with private_folder(f".{out_path.name}.partial.", out_path.parent) as work:
        meshio.write(work / out_path.name, mesh, file_format="xdmf")
        with h5py.File(work / sidecar.name, "a") as side:
            side.create_dataset("frequencies_hz", data=mesh.field_data["frequencies_hz"])
            side.create_dataset("display_scale", data=mesh.field_data["display_scale"])
        for final in (sidecar, out_path):
            with atomic_path(final) as tmp:
                os.replace(work / final.name, tmp)
    log.info("wrote %s and %s", out_path, sidecar)
    return out_path


def export(h5_path: str | Path, out_path: str | Path) -> Path:
    """VTU or XDMF by the ending of ``out_path`` (.vtu | .xdmf)."""
    suffix = Path(out_path).suffix.lower()
    if suffix == ".xdmf":
        return export_xdmf(h5_path, out_path)
    if suffix == ".vtu":
        return export_vtu(h5_path, out_path)
    raise ConfigError(f"export output: got '{out_path}', expected a name ending in .vtu or .xdmf")
