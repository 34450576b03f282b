"""Config records and parsing of the ``coordinate_systems:`` section: named frames that a
``materials`` entry may refer to by name (``axes: <name>``) instead of giving its
material frame inline (``axes: {x, y}``).

``kind: cylindrical`` with ``axis`` and ``point`` (m) is a frame that varies with the
position: at a point x with r = (x - point) - ((x - point) . a) a (a = axis / |axis|),
material axis 1 = r / |r| (radial), 2 = a x 1 (hoop), 3 = a (axial), the order of the
cylindrical support frames (pipeline.config.supports). A material in it takes the frame
at each element's centroid (:mod:`pipeline.fe.materials`); a centroid on the axis has no
radial direction and is refused there.

A system is ``{x: [..], y: [..], origin: [..]}`` in global coordinates (m for the
origin): axis 1 = x / |x|, axis 2 = y / |y| (at right angles to x to 1e-9, not
orthogonalised), axis 3 = 1 x 2. The origin does not enter a material law (a rectangular
frame is the same at every point); it is kept for the record and the file's config copy.
The axes are checked exactly as an inline ``axes:`` (:func:`pipeline.config.materials.frame_axes`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from pipeline._util import validate as v
from pipeline.config.materials import frame_axes


@dataclass(frozen=True)
class CoordinateSystem:
    """One named rectangular system: ``axes`` rows = unit axes 1, 2, 3 in global
    coordinates (right-handed), ``origin`` (m)."""

    name: str
    axes: tuple[tuple[float, float, float], ...]
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    x: tuple[float, float, float] = (1.0, 0.0, 0.0)  # as given (for the YAML copy)
    y: tuple[float, float, float] = (0.0, 1.0, 0.0)
    kind: str = "rectangular"  # or "cylindrical": axis (unit) and point (m) below
    axis: tuple[float, float, float] | None = None
    point: tuple[float, float, float] | None = None


def parse_coordinate_systems(raw: Any) -> dict[str, CoordinateSystem]:
    """The ``coordinate_systems:`` mapping (None: none), name -> system."""
    if raw is None:
        return {}
    if not isinstance(raw, Mapping):
        raise v.fail("coordinate_systems", raw, "a mapping of names to {x: [..], y: [..], "
                     "origin: [..]}")
    out = {}
    for name, item in raw.items():
        if not isinstance(name, str) or not v.NAME_RE.fullmatch(name):
            raise v.fail("coordinate_systems", name, "system names of letters, digits, '_', "
                         "'-' or '.'")
        path = f"coordinate_systems.{name}"
        kind = v.choice(v.mapping(item, path, ("kind", "x", "y", "origin", "axis", "point")),
                        "kind", path, ("rectangular", "cylindrical"), "rectangular")
        if kind == "cylindrical":
            item = v.mapping(item, path, ("kind", "axis", "point"), ("axis", "point"))
            axis = np.array(v.vector(item, "axis", path, nonzero=True))
            out[name] = CoordinateSystem(
                name=name, axes=frame_axes(None, path), kind=kind,
                axis=tuple(float(c) for c in axis / np.linalg.norm(axis)),
                point=v.vector(item, "point", path))
            continue
        item = v.mapping(item, path, ("kind", "x", "y", "origin"), ("x", "y"))
        axes = frame_axes({"x": item["x"], "y": item["y"]}, path)
        out[name] = CoordinateSystem(
            name=name, axes=axes, origin=v.vector(item, "origin", path, (0.0, 0.0, 0.0)),
            x=v.vector(item, "x", path), y=v.vector(item, "y", path))
    return out


def coordinate_system_dict(cs: CoordinateSystem) -> dict:
    """A system as its YAML keys (load of it gives back an equal system)."""
    if cs.kind == "cylindrical":
        return {"kind": "cylindrical", "axis": list(cs.axis), "point": list(cs.point)}
    return {"x": list(cs.x), "y": list(cs.y), "origin": list(cs.origin)}
