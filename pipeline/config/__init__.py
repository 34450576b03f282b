"""Configuration: load a YAML file, apply ``--set`` overrides, validate strictly.

This is the boundary of the pipeline: every key is checked here, once, and refused
with a :class:`~pipeline.errors.ConfigError` that names the dotted key path, the value
received and what was expected. Everything downstream receives frozen dataclasses and
trusts them. Units are SI throughout (m, kg, s, N, Pa).

- :mod:`~pipeline.config.schema`: the records and the ``Literal`` kinds;
- :mod:`~pipeline.config.parse`: :func:`load_config`, :func:`config_from_dict`;
- :mod:`~pipeline.config.overrides`: :func:`apply_overrides` (``--set``);
- :mod:`~pipeline.config.serialize`: :func:`config_to_dict`, :func:`config_to_yaml`.
"""

from __future__ import annotations

from pipeline.config.overrides import apply_overrides
from pipeline.config.parse import TOP_KEYS, config_from_dict, load_config
from pipeline.config.schema import (BOX_FACES, GEOMETRY_KINDS, SOLVERS, Config, Connection,
                                    Constraints, Damping, Filter, Geometry, Lumped, Material,
                                    MeshSpec, ModesConfig, Port, Ports, Reduction, RegionSelector,
                                    Support)
from pipeline.config.serialize import config_to_dict, config_to_yaml

__all__ = [
    "Config",
    "load_config",
    "config_from_dict",
    "apply_overrides",
    "config_to_yaml",
    "config_to_dict",
    "TOP_KEYS",
    "GEOMETRY_KINDS",
    "SOLVERS",
    "BOX_FACES",
    "Geometry",
    "MeshSpec",
    "Material",
    "Support",
    "Constraints",
    "ModesConfig",
    "RegionSelector",
    "Port",
    "Ports",
    "Damping",
    "Reduction",
    "Filter",
    "Lumped",
    "Connection",
]
