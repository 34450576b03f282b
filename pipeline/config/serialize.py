"""The resolved config back to plain data and YAML (the copy stored in every HDF5 file):
``load_config`` of :func:`config_to_yaml`'s text gives back an equal :class:`Config`.
"""

from __future__ import annotations

from dataclasses import asdict, fields
from typing import Any

from pipeline.config.frames import coordinate_system_dict
from pipeline.config.materials import mass_dict, material_dict
from pipeline.config.schema import Config
from pipeline.config.supports import support_dict


#: the keys each region selector kind takes (the parser refuses the others)
SELECTOR_KEYS = {"plane": ("kind", "point", "normal", "tolerance"),
                 "box": ("kind", "lower", "upper"),
                 "sphere": ("kind", "point", "radius")}


def config_to_dict(cfg: Config) -> dict:
    """The resolved config as plain YAML-ready data (tuples become lists)."""

    def plain(value: Any) -> Any:
        if isinstance(value, tuple):
            return [plain(v) for v in value]
        if isinstance(value, dict):
            return {k: plain(v) for k, v in value.items()}
        return value

    out = {}
    for f in fields(cfg):
        if f.name == "source":
            continue
        value = getattr(cfg, f.name)
        if value is None:
            continue
        if f.name == "regions":
            value = {k: {kk: vv for kk, vv in asdict(v).items()
                         if vv is not None and kk in SELECTOR_KEYS[v.kind]}
                     for k, v in value.items()}
        elif f.name == "craig_bampton_modes":
            if value:
                out["craig_bampton"] = {"modes": value}
            continue
        elif f.name in ("materials", "masses"):
            if value:
                out[f.name] = [(material_dict if f.name == "materials" else mass_dict)(m)
                               for m in value]
            continue
        elif f.name == "coordinate_systems":
            if value:
                out[f.name] = {k: coordinate_system_dict(cs) for k, cs in value.items()}
            continue
        elif f.name == "connections":
            value = [asdict(c) for c in value]
        elif f.name == "supports":
            value = [support_dict(s) for s in value]
        elif f.name == "ports":
            value = {side: [_port_dict(p) for p in getattr(value, side)]
                     for side in ("inputs", "outputs")}
        elif f.name == "geometry":
            keep = ("kind", "length", "height", "depth") if value.kind == "box" else \
                ("kind", "path", "units" if value.units else "scale")
            value = {k: getattr(value, k) for k in keep}
        elif f.name == "mesh":
            # size and algorithm do not apply to a mesh file; parts only where set
            keep = ("order",) if cfg.geometry.kind == "mesh" else ("order", "size", "algorithm")
            value = {k: getattr(value, k) for k in keep + (("parts",) if value.parts else ())}
        elif hasattr(value, "__dataclass_fields__"):
            value = asdict(value)
        out[f.name] = plain(value)
    if cfg.damping.kind != "per_mode":
        out["damping"].pop("ratios", None)
    return out


def _port_dict(port) -> dict:
    """A port as its YAML keys: the gauge keys only where set (docs/stress.md)."""
    area = ("radius", "length", "width", "average")
    out = {k: v for k, v in asdict(port).items()
           if v is not None and k not in area and (k != "region" or v)}
    if port.point is not None and port.radius:
        out["radius"] = port.radius
    if port.length:
        out.update(length=port.length, width=port.width)
    if port.average != "surface":  # the default of every gauge with an area
        out["average"] = port.average
    return out


def config_to_yaml(cfg: Config) -> str:
    """The resolved config as YAML text; ``load`` of it gives back an equal Config."""
    import yaml  # deferred: only writing a file needs it

    return yaml.safe_dump(config_to_dict(cfg), sort_keys=False)
