"""Config records and parsing of the ``coordinate_systems:`` section: named rectangular
frames that a ``materials`` entry may refer to by name (``axes: <name>``) instead of
giving its material frame inline (``axes: {x, y}``).

A system is ``{x: [..], y: [..], origin: [..]}`` in global coordinates (m for the
origin): axis 1 = x / |x|, axis 2 = y / |y| (at right angles to x to 1e-9, not
orthogonalised), axis 3 = 1 x 2. The origin does not enter a material law (a rectangular
frame is the same at every point); it is kept for the record and the file's config copy.
The axes are checked exactly as an inline ``axes:`` (:func:`pipeline.config.materials.frame_axes`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

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
        item = v.mapping(item, path, ("x", "y", "origin"), ("x", "y"))
        axes = frame_axes({"x": item["x"], "y": item["y"]}, path)
        out[name] = CoordinateSystem(
            name=name, axes=axes, origin=v.vector(item, "origin", path, (0.0, 0.0, 0.0)),
            x=v.vector(item, "x", path), y=v.vector(item, "y", path))
    return out


def coordinate_system_dict(cs: CoordinateSystem) -> dict:
    """A system as its YAML keys (load of it gives back an equal system)."""
    return {"x": list(cs.x), "y": list(cs.y), "origin": list(cs.origin)}
