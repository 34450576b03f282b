"""The in-memory form of what a stage contributes to the HDF5 file.

Stages do not open files. Each returns a flat mapping ``{path: Dataset}`` (paths
relative to the file root, e.g. ``"modes/frequencies_hz"``) and, optionally, a mapping
``{group path: {attribute: value}}``. :mod:`pipeline.store.h5file` writes them all at once,
atomically, and documents the layout (``docs/hdf5-format.md``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np


@dataclass(frozen=True)
class Dataset:
    """One HDF5 dataset: its value, its units and a one-line description.

    ``data`` is a numpy array (any shape, numeric) or a sequence of ``str`` (stored
    as variable-length UTF-8 strings). ``units`` is an SI unit string such as
    ``"Hz"``, ``"kg m^2"``, ``"1"`` for dimensionless numbers or ``"mixed"`` when the
    entries of a matrix carry different units (the ``attrs`` then say which).
    """

    data: Any
    units: str
    description: str = ""
    attrs: Mapping[str, Any] = field(default_factory=dict)

    @property
    def written_in_blocks(self) -> bool:
        """``data`` is too large for one process (the distributed path's mode shapes): an
        object with ``shape``, ``dtype`` and ``blocks()``, which yields (first row, rows)
        along the first axis for the writer to store one block at a time."""
        return hasattr(self.data, "blocks")

    def as_array(self) -> np.ndarray:
        if isinstance(self.data, (list, tuple)) and (
            len(self.data) == 0 or isinstance(self.data[0], str)
        ):
            return np.asarray(self.data, dtype=object)
        return np.asarray(self.data)


Tree = dict[str, Dataset]
GroupAttrs = dict[str, dict[str, Any]]
