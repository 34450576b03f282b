"""Exporters: write one of our HDF5 files in the format another tool loads.

A small registry. Each entry of :data:`EXPORTERS` maps a format name to an
:class:`Exporter`: ``write(h5_path, out_path) -> Path`` reads our (verified) file and
writes ``out_path``; ``suffix`` is the default file ending. :func:`export` is what the
CLI calls (``python -m pipeline export FILE.h5 --to FORMAT [-o OUT]``). To add a format,
write its module here and add one line to :data:`EXPORTERS`.

Helpers shared by exporters: :func:`read_csr` reads a sparse matrix stored by
:func:`csr_datasets` (e.g. ``/fe/mass_matrix``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import scipy.sparse as sp

from pipeline.errors import ConfigError, FileFormatError
from pipeline.store.tree import Dataset

__all__ = ["Exporter", "EXPORTERS", "export", "default_output", "csr_datasets", "read_csr"]


@dataclass(frozen=True)
class Exporter:
    """write(h5_path, out_path) -> the path written; suffix: default ending; description."""

    write: Callable[[Path, Path], Path]
    suffix: str
    description: str


def _exudyn(h5_path: Path, out_path: Path) -> Path:
    from pipeline.apps.exports.exudyn import export_exudyn

    return export_exudyn(h5_path, out_path)


def _lazy(module: str, func: str = "export") -> Callable[[Path, Path], Path]:
    """A writer that imports ``pipeline.apps.exports.<module>`` only when it runs."""

    def write(h5_path: Path, out_path: Path) -> Path:
        from importlib import import_module

        return getattr(import_module(f"{__name__}.{module}"), func)(h5_path, out_path)

    return write


EXPORTERS: dict[str, Exporter] = {
    "exudyn": Exporter(_exudyn, ".exudyn.hdf5",
                       "Exudyn FEMinterface file (nodes, elements, M, K, mode basis, node "
                       "sets) for ObjectFFRFreducedOrder; load with fem.LoadFromFile(path)"),
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
}


def default_output(h5_path: str | Path, fmt: str) -> Path:
    """``<h5 stem><suffix of fmt>`` beside the input file."""
    h5_path = Path(h5_path)
    return h5_path.with_name(h5_path.stem + EXPORTERS[fmt].suffix)


def export(h5_path: str | Path, fmt: str, out_path: str | Path | None = None) -> Path:
    """Export ``h5_path`` (a file written by :func:`pipeline.run.run_pipeline`) to format
    ``fmt`` (a key of :data:`EXPORTERS`) at ``out_path`` (default :func:`default_output`).
    Returns the path written."""
    if fmt not in EXPORTERS:
        raise ConfigError(f"export format: got {fmt!r}, expected one of "
                          f"{', '.join(sorted(EXPORTERS))}")
    out = Path(out_path) if out_path is not None else default_output(h5_path, fmt)
    return EXPORTERS[fmt].write(Path(h5_path), out)


# --------------------------------------------------------------------------- sparse I/O
def csr_datasets(A: sp.spmatrix, group: str, units: str, description: str,
                 symmetric: bool = True) -> dict[str, Dataset]:
    """A sparse matrix as CSR arrays ``<group>/{data, indices, indptr, shape}``.

    Explicit zeros are dropped. ``symmetric``: store only the upper triangle (diagonal
    included); the ``data``
    dataset then carries ``storage = "upper"`` (else ``"full"``). :func:`read_csr`
    restores the full matrix.
    """
    A = sp.triu(A, format="csr") if symmetric else sp.csr_matrix(A, copy=True)
    A.eliminate_zeros()  # the assembled M stores the zero off-diagonals of its 3x3 blocks
    A.sort_indices()
    itype = np.int32 if A.nnz < 2**31 - 1 else np.int64
    storage = "upper" if symmetric else "full"
    return {
        f"{group}/data": Dataset(A.data.astype(np.float64), units, description,
                                 {"storage": storage, "format": "csr"}),
        f"{group}/indices": Dataset(A.indices.astype(itype), "1", "CSR column indices"),
        f"{group}/indptr": Dataset(A.indptr.astype(np.int64), "1", "CSR row pointers"),
        f"{group}/shape": Dataset(np.array(A.shape, dtype=np.int64), "1", "(rows, columns)"),
    }


def read_csr(h5, group: str) -> sp.csr_matrix:
    """The full sparse matrix stored at ``group`` of an open h5py file by
    :func:`csr_datasets`. Raises FileFormatError if it is missing."""
    if group not in h5 or "data" not in h5[group]:
        raise FileFormatError(f"file '{h5.filename}': has no sparse matrix /{group}")
    g = h5[group]
    shape = tuple(int(v) for v in g["shape"][()])
    A = sp.csr_matrix((g["data"][()], g["indices"][()], g["indptr"][()]), shape=shape)
    storage = g["data"].attrs.get("storage", "full")
    if isinstance(storage, bytes):
        storage = storage.decode()
    if storage == "upper":
        A = (A + sp.triu(A, k=1, format="csr").T).tocsr()
    return A
