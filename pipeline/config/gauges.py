"""The area keys of a gauge output (docs/stress.md): ``radius``, ``length`` and
``width`` (m) and ``average`` ("surface" | "volume").

A gauge on a ``region`` covers the region; one at a ``point`` covers a disc of
``radius``, or a ``length`` x ``width`` grid (the length along its direction), or
nothing (no radius or radius 0, no grid: the value at the point). ``average`` says what
a gauge with an area averages: the strain on the surface it covers (the default), or the
element averages of the elements around it ("volume", with a region or a radius only).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, get_args

from pipeline._util import validate as v
from pipeline.config.schema import GaugeAverage

#: the keys of a gauge output that :func:`gauge_area` reads
AREA_KEYS = ("radius", "length", "width", "average")


def gauge_area(item: Mapping[str, Any], path: str) -> dict[str, Any]:
    """The Port fields radius, length, width (m) and average of a gauge output ``item``
    that holds exactly one of 'region' and 'point' (checked by the caller)."""
    on_region = "region" in item
    for key in ("radius", "length", "width"):
        if on_region and key in item:
            raise v.fail(f"{path}.{key}", item[key], f"no {key} with 'region' (a {key} goes "
                         "with 'point'; the region is the gauge's area)")
    if "radius" in item and ("length" in item or "width" in item):
        raise v.fail(f"{path}.radius", item["radius"], "either a 'radius' (a round gauge) or "
                     "a 'length' and 'width' (a grid), not both")
    grid = "length" in item or "width" in item
    length = v.number(item, "length", path, lo=0.0, lo_open=True) if grid else 0.0
    width = v.number(item, "width", path, lo=0.0, lo_open=True) if grid else 0.0
    radius = v.number(item, "radius", path, 0.0, lo=0.0) if not on_region else 0.0
    average = v.choice(item, "average", path, get_args(GaugeAverage), "surface")
    if "average" in item and not (on_region or grid or radius > 0):
        raise v.fail(f"{path}.average", average, "no 'average' for a value at a point (it "
                     "applies to a gauge with a 'radius', a 'length' and 'width', or a "
                     "'region')")
    if grid and average == "volume":
        raise v.fail(f"{path}.average", average, "'surface' for a grid (length and width); "
                     "'volume' goes with a 'radius' or a 'region'")
    return {"radius": radius, "length": length, "width": width, "average": average}
