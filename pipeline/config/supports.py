"""The ``supports`` section: held components (global or in a local frame), elastic
supports (springs to ground on a region) and grounded bushings.

One list item is one of::

    {region: R, fix: all | [x, y, z]}                                  # global components
    {region: R, fix: [radial, tangential, axial], frame: {kind: cylindrical,
                                                   axis: [ax, ay, az], point: [px, py, pz]}}
    {region: R, fix: [normal] | [tangential] | [normal, tangential]}   # face frame
    {region: R, spring: {per_area: [k1, k2, k3]}}   # N/m^3, in the frame's components
    {region: R, spring: {total: [k1, k2, k3]}}      # N/m in all, spread by area
    {region: R, bushing: {stiffness: [k1, k2, k3] | [k1..k6] | 6x6, point: [x, y, z]}}

Components per frame: ``global`` x, y, z; ``cylindrical`` radial, tangential, axial
(about the line through ``point`` along ``axis``); ``face`` normal, tangential (the
face's own outward normal at every node; tangential is both in-plane directions, so a
face-frame spring takes two values [k_normal, k_tangential]). A bushing's stiffness is
three translational stiffnesses (N/m), six (N/m, then N m/rad about x, y, z) or a
symmetric positive semi-definite 6x6 matrix, at ``point`` (default: the region's
centroid), tied to the region by a distributing coupling.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

from pipeline._util import validate as v

FrameKind = Literal["global", "cylindrical", "face"]
#: the components each frame kind names, in its order
FRAME_COMPONENTS = {"global": ("x", "y", "z"), "cylindrical": ("radial", "tangential", "axial"),
                    "face": ("normal", "tangential")}
#: the largest stiffness accepted (N/m, N/m^3, N m/rad): far above any solid's, and
#: small enough that a sum over a region stays finite
MAX_STIFFNESS = 1e20


@dataclass(frozen=True)
class SupportFrame:
    """The frame a support's components refer to: ``kind`` global, cylindrical (``axis``
    (3,) direction and ``point`` (3,) m on the axis) or face (the face normal)."""

    kind: FrameKind = "global"
    axis: tuple[float, float, float] | None = None
    point: tuple[float, float, float] | None = None


@dataclass(frozen=True)
class SpringSpec:
    """Springs to ground on a region: ``kind`` per_area (``values`` in N/m^3, weighted by
    the consistent area of every node) or total (N/m for the whole region, spread by
    area), one value per component of the frame."""

    kind: Literal["per_area", "total"]
    values: tuple[float, ...]


@dataclass(frozen=True)
class BushingSpec:
    """A grounded bushing: ``stiffness`` (6, 6) (N/m, N, N m/rad blocks) at ``point`` (m;
    None: the region's centroid), tied to the region by a distributing coupling."""

    stiffness: tuple[tuple[float, ...], ...]
    point: tuple[float, float, float] | None = None


def _frame(raw: Any, path: str) -> SupportFrame:
    raw = v.mapping(raw, path, ("kind", "axis", "point"), ("kind",))
    kind = v.choice(raw, "kind", path, ("global", "cylindrical", "face"))
    if kind != "cylindrical":
        extra = sorted(set(raw) - {"kind"})
        if extra:
            raise v.fail(f"{path}.{extra[0]}", raw[extra[0]],
                         f"no '{extra[0]}' for a {kind} frame (only a cylindrical frame has "
                         "axis and point)")
        return SupportFrame(kind)
    return SupportFrame(kind, axis=v.vector(raw, "axis", path, nonzero=True),
                        point=v.vector(raw, "point", path))


def _components(fix: Any, frame: SupportFrame | None, path: str) -> tuple[SupportFrame,
                                                                           tuple[str, ...]]:
    """The frame (face when ``normal`` or ``tangential`` is named without one) and the
    fixed components, in the frame's order."""
    if frame is None:
        kind = ("face" if isinstance(fix, list) and any(c in ("normal", "tangential")
                                                          for c in fix) else "global")
        frame = SupportFrame(kind)
    names = FRAME_COMPONENTS[frame.kind]
    if fix == "all":
        return frame, names
    if not (isinstance(fix, list) and fix and all(isinstance(c, str) and c in names
                                                  for c in fix)
            and len(set(fix)) == len(fix)):
        hint = (" (radial, tangential and axial need frame: {kind: cylindrical, axis: "
                "[...], point: [...]})" if frame.kind != "cylindrical" else "")
        raise v.fail(f"{path}.fix", fix, f"'all' or a list of distinct components from "
                     f"{', '.join(names)}{hint}")
    return frame, tuple(c for c in names if c in fix)


def _stiffnesses(raw: Any, path: str, count: int) -> tuple[float, ...]:
    expected = (f"a list of {count} finite stiffnesses >= 0 (at most {MAX_STIFFNESS:g}), "
                "at least one > 0")
    if not (isinstance(raw, list) and len(raw) == count
            and all(isinstance(k, (int, float)) and not isinstance(k, bool) for k in raw)):
        raise v.fail(path, raw, expected)
    try:
        values = tuple(float(k) for k in raw)
    except OverflowError:
        raise v.fail(path, raw, expected) from None
    if not (all(math.isfinite(k) and 0.0 <= k <= MAX_STIFFNESS for k in values)
            and max(values) > 0):
        raise v.fail(path, raw, expected)
    return values


def _spring(raw: Any, frame: SupportFrame, path: str) -> SpringSpec:
    raw = v.mapping(raw, path, ("per_area", "total"))
    if len(raw) != 1:
        raise v.fail(path, raw, "exactly one of per_area (N/m^3) or total (N/m)")
    kind = next(iter(raw))
    return SpringSpec(kind, _stiffnesses(raw[kind], f"{path}.{kind}",
                                         len(FRAME_COMPONENTS[frame.kind])))


def _bushing(raw: Any, path: str) -> BushingSpec:
    raw = v.mapping(raw, path, ("stiffness", "point"), ("stiffness",))
    point = v.vector(raw, "point", path, None)
    k = raw["stiffness"]
    where = f"{path}.stiffness"
    if isinstance(k, list) and len(k) in (3, 6) and not any(isinstance(r, list) for r in k):
        diag = _stiffnesses(k, where, len(k)) + (0.0,) * (6 - len(k))
        matrix = tuple(tuple(diag[i] if i == j else 0.0 for j in range(6)) for i in range(6))
        return BushingSpec(matrix, point)
    expected = ("3 translational stiffnesses (N/m), 6 (N/m, then N m/rad), or a symmetric "
                "positive semi-definite 6x6 matrix")
    if not (isinstance(k, list) and len(k) == 6 and all(
            isinstance(r, list) and len(r) == 6 and all(
                isinstance(x, (int, float)) and not isinstance(x, bool) for x in r) for r in k)):
        raise v.fail(where, k, expected)
    import numpy as np

    try:
        matrix = np.array(k, dtype=float)
    except OverflowError:
        raise v.fail(where, k, expected) from None
    if not (np.all(np.isfinite(matrix)) and np.abs(matrix).max() <= MAX_STIFFNESS
            and np.allclose(matrix, matrix.T, rtol=1e-9, atol=0.0)):
        raise v.fail(where, k, expected)
    eig = np.linalg.eigvalsh(0.5 * (matrix + matrix.T))
    if eig[-1] <= 0 or eig[0] < -1e-9 * eig[-1]:
        raise v.fail(where, k, expected)
    return BushingSpec(tuple(tuple(float(x) for x in row) for row in matrix), point)


def parse_support(item: Any, path: str) -> dict[str, Any]:
    """One ``supports`` list item as the fields of a
    :class:`pipeline.config.schema.Support` (a mapping of its keyword arguments)."""
    item = v.mapping(item, path, ("region", "fix", "frame", "spring", "bushing"), ("region",))
    region = v.name(item, "region", path)
    kinds = [k for k in ("fix", "spring", "bushing") if k in item]
    if len(kinds) > 1:
        raise v.fail(f"{path}.{kinds[1]}", item[kinds[1]],
                     f"one of fix, spring or bushing per support (this one has {kinds[0]}; "
                     "give the other as a second support on the same region)")
    frame = _frame(item["frame"], f"{path}.frame") if "frame" in item else None
    if "bushing" in item:
        if frame is not None:
            raise v.fail(f"{path}.frame", item["frame"], "no frame for a bushing (its "
                         "stiffness matrix is in global x, y, z)")
        return dict(region=region, fix=(), bushing=_bushing(item["bushing"],
                                                               f"{path}.bushing"))
    if "spring" in item:
        frame = frame or SupportFrame()
        return dict(region=region, fix=(), frame=None if frame.kind == "global" else frame,
                       spring=_spring(item["spring"], frame, f"{path}.spring"))
    frame, comps = _components(item.get("fix", "all"), frame, path)
    if frame.kind == "global":
        return dict(region=region, fix=comps)
    if comps == FRAME_COMPONENTS[frame.kind]:
        return dict(region=region, fix=("x", "y", "z"))  # every component: global
    return dict(region=region, fix=(), frame=frame, local_fix=comps)


def support_dict(support) -> dict:
    """A support as its YAML keys (what :func:`parse_support` reads back)."""
    out: dict[str, Any] = {"region": support.region}
    if support.bushing is not None:
        b = support.bushing
        out["bushing"] = {"stiffness": [list(r) for r in b.stiffness]}
        if b.point is not None:
            out["bushing"]["point"] = list(b.point)
        return out
    if support.frame is not None:
        f = support.frame
        out["frame"] = {"kind": f.kind}
        if f.kind == "cylindrical":
            out["frame"].update(axis=list(f.axis), point=list(f.point))
    if support.spring is not None:
        out["spring"] = {support.spring.kind: list(support.spring.values)}
    elif support.local_fix:
        out["fix"] = list(support.local_fix)
    else:
        out["fix"] = "all" if support.fix == ("x", "y", "z") else list(support.fix)
    return out
