"""Reduced models of flexible bodies from 3D finite elements.

Data flow, one subpackage per stage::

    config -> fe (mesh, space, regions, assemble, body, ports) -> solve (factorise,
    eigenmodes) -> reduce (StateSpace models) -> store (the HDF5 file)

:mod:`pipeline.run` chains the stages; :mod:`pipeline.apps` (simulate, batch, plots,
exports, summary) uses a result file through :mod:`pipeline.store.read` only; the CLI
(``python -m pipeline``, :mod:`pipeline.cli`) calls the same functions.

The public API
--------------

- :func:`run_config`: run a config (a YAML path, a mapping or a :class:`Config`) as
  ``python -m pipeline run`` does; returns a :class:`RunResult` and writes the HDF5 file.
- :func:`load_model`: read every reduced model of a result file.
- :class:`Config`: the validated configuration (:mod:`pipeline.config`).
- :class:`RunResult`: what one run produced (:mod:`pipeline.run`).
- The errors, one per kind of failure, each with the command line's exit code:
  :class:`PipelineError` and its subclasses :class:`ConfigError`, :class:`MeshError`,
  :class:`RegionError`, :class:`SolverError`, :class:`ResourceError`,
  :class:`FileFormatError`, :class:`OutputError`.

``import pipeline`` is light (no numpy) and changes nothing in the calling process:
no environment variable, thread pool, allocator setting or matplotlib backend. The
command line tunes its own process (:mod:`pipeline.cli.process`).

A config is validated before any work; a bad key is refused with the key, the value
and what was expected:

>>> import pipeline
>>> pipeline.run_config({"name": "beam", "geometry": {"kind": "box", "length": 0.5,
...     "height": 0.02, "depth": 0.05}, "mesh": {"size": 0.01},
...     "material": {"E": -1, "nu": 0.3, "rho": 2700}})
Traceback (most recent call last):
...
pipeline.errors.ConfigError: config key 'material.E': got -1.0, expected a number in (0, 1e+13]

Running it, and reading the result back::

    result = pipeline.run_config("configs/cantilever.yaml", output="out.h5",
                                 overrides=["mesh.size=0.01"])
    print(result.frequencies_hz)
    model = pipeline.load_model(result.output)
"""

from __future__ import annotations

from pipeline._version import __version__  # noqa: E402

from pipeline.errors import (
    ConfigError,
    FileFormatError,
    MeshError,
    OutputError,
    PipelineError,
    RegionError,
    ResourceError,
    SolverError,
)

#: public names imported on first use (module, name), so ``import pipeline`` stays light
_LAZY = {"run_config": "pipeline.api", "Config": "pipeline.config",
         "RunResult": "pipeline.run"}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'pipeline' has no attribute '{name}'")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))


def load_model(path, require_plant: bool = False):
    """Load every reduced model of an HDF5 file (see :func:`pipeline.store.read.load_model`).

    Imported on first use, so ``import pipeline`` stays light (no h5py, no control)."""
    from pipeline.store.read import load_model as _load

    return _load(path, require_plant=require_plant)


__all__ = [
    "run_config",
    "load_model",
    "Config",
    "RunResult",
    "__version__",
    "ConfigError",
    "FileFormatError",
    "MeshError",
    "OutputError",
    "PipelineError",
    "RegionError",
    "ResourceError",
    "SolverError",
]
