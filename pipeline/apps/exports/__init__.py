"""Exporters: write one of our HDF5 files in the format another tool loads.

A small registry. Each entry of :data:`EXPORTERS` maps a format name to an
:class:`Exporter`: ``write(h5_path, out_path) -> Path`` reads our (verified) file and
writes ``out_path``; ``suffix`` is the default file ending. :func:`export` is what the
CLI calls (``python -m pipeline export FILE.h5 --to FORMAT [-o OUT]``). To add a format,
write its module here and add one line to :data:`EXPORTERS`.

Exporters read the file through the typed readers of :mod:`pipeline.store.read` (the
full FE body with ``/fe``'s M and K: :func:`pipeline.store.read.read_fe_model`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from pipeline.errors import ConfigError

__all__ = ["Exporter", "EXPORTERS", "export", "default_output"]


@dataclass(frozen=True)
class Exporter:
    """write(h5_path, out_path) -> the path written; suffix: default ending; description."""

    write: Callable[..., Path]
    suffix: str
    description: str
    options: tuple[str, ...] = ()  # keyword options write() takes (e.g. fmu's ``model``)


def _exudyn(h5_path: Path, out_path: Path, **options) -> Path:
    from pipeline.apps.exports.exudyn import export_exudyn

    return export_exudyn(h5_path, out_path, **options)


def _lazy(module: str, func: str = "export") -> Callable[[Path, Path], Path]:
    """A writer that imports ``pipeline.apps.exports.<module>`` only when it runs."""

    def write(h5_path: Path, out_path: Path, **options) -> Path:
        from importlib import import_module

        return getattr(import_module(f"{__name__}.{module}"), func)(h5_path, out_path, **options)

    return write


EXPORTERS: dict[str, Exporter] = {
    "exudyn": Exporter(_exudyn, ".exudyn.hdf5",
                       "Exudyn FEMinterface file (nodes, elements, M, K, mode basis, node "
                       "sets) for ObjectFFRFreducedOrder; load with fem.LoadFromFile(path)",
                       options=("basis", "fe_data")),
    "mat": Exporter(_lazy("mat"), ".mat",
                    "MATLAB v5 .mat: A, B, C, D of the reduced, filtered and lumped models, "
                    "names, units, frequencies; Simulink State-Space block, GNU Octave"),
    "vtu": Exporter(_lazy("vtu", "export_vtu"), ".vtu",
                    "VTK unstructured grid for ParaView: mesh, every mode shape as point data, "
                    "frequencies as field data"),
    "xdmf": Exporter(_lazy("vtu", "export_xdmf"), ".modes.xdmf",
                     "XDMF (+ <stem>.modes.h5) for ParaView: mesh and every mode shape"),
    "json": Exporter(_lazy("summary_json"), ".json",
                     "small JSON summary: frequencies, labels, ports, DC gains"),
    "simscape": Exporter(_lazy("simscape"), "_simscape.mat",
                         "Simscape Multibody Reduced Order Flexible Solid parameters (.mat + "
                         ".m script): interface frame origins, Craig-Bampton K, M, damping"),
    "fmu": Exporter(_lazy("fmu", "export_fmu"), ".fmu",
                    "FMI 2.0 or 3.0 (--fmi-version) FMU (Model Exchange + Co-Simulation, C "
                    "sources inside) of any model of the file (--model); compiled with gcc "
                    "at export", options=("model", "fmi_version")),
    "sid": Exporter(_lazy("sid", "export_sid"), ".SID_FEM",
                    "SID standard input data (SIMPACK and other FFRF codes): mass, inertia "
                    "invariants, modal mass and stiffness, frame nodes per region, "
                    "centrifugal stiffening from /rotation", options=("fe_data",)),
}


def default_output(h5_path: str | Path, fmt: str, model: str | None = None) -> Path:
    """``<h5 stem>[.<model>]<suffix of fmt>`` beside the input file."""
    h5_path = Path(h5_path)
    middle = "." + model.replace("/", "_") if model else ""
    return h5_path.with_name(h5_path.stem + middle + EXPORTERS[fmt].suffix)


def export(h5_path: str | Path, fmt: str, out_path: str | Path | None = None,
           **options) -> Path:
    """Export ``h5_path`` (a file written by :func:`pipeline.run.run_pipeline`) to format
    ``fmt`` (a key of :data:`EXPORTERS`) at ``out_path`` (default :func:`default_output`).
    ``options`` (None values dropped) go to formats that take them (``model`` for fmu).
    Returns the path written."""
    if fmt not in EXPORTERS:
        raise ConfigError(f"export format: got {fmt!r}, expected one of "
                          f"{', '.join(sorted(EXPORTERS))}")
    options = {k: v for k, v in options.items() if v is not None}
    extra = sorted(set(options) - set(EXPORTERS[fmt].options))
    if extra:
        flag = extra[0].replace("_", "-")
        raise ConfigError(f"export --{flag}: does not apply to --to {fmt} (it applies to "
                          + (", ".join(f for f, e in EXPORTERS.items() if extra[0] in e.options)
                             or "no format") + ")", key=f"--{flag}",
                          value=options[extra[0]], expected="not given")
    out = (Path(out_path) if out_path is not None
           else default_output(h5_path, fmt, options.get("model")))
    return EXPORTERS[fmt].write(Path(h5_path), out, **options)
