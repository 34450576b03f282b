"""The Python entry point: run a config as ``python -m pipeline run`` does.

:func:`run_config` takes the config as a YAML path, a mapping or a :class:`Config`,
applies ``--set``-style overrides, checks the destinations and runs
:func:`pipeline.run.run_pipeline`: the same validation, the same errors
(:class:`~pipeline.errors.ConfigError`, :class:`~pipeline.errors.OutputError`, ...) and
the same HDF5 file as the command line, which calls :func:`resolve_config` and
:func:`check_run_destinations` itself. Nothing here changes the calling process (see
:mod:`pipeline.cli.process` for what the command line tunes in its own).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

from pipeline.errors import ConfigError

if TYPE_CHECKING:  # the config and run modules load numpy and the FE stack
    from pipeline.config import Config
    from pipeline.run import RunResult

__all__ = ["check_run_destinations", "default_output", "resolve_config", "run_config"]

def resolve_config(config: str | Path | Mapping[str, Any] | Config,
                   overrides: Sequence[str] = ()) -> Config:
    """The validated :class:`~pipeline.config.Config` of ``config``: a YAML file's path, a
    mapping of config keys (as the YAML holds them) or a ``Config``; ``overrides`` are
    ``KEY=VALUE`` texts as ``--set`` takes them (``"mesh.size=0.004"``).

    Raises :class:`~pipeline.errors.ConfigError` naming the key, the value and what was
    expected (for a file, prefixed with its path, as the command line prints it)."""
    from pipeline.config import (Config, apply_overrides, config_from_dict, config_to_dict,
                                 load_config)

    overrides = list(overrides or ())
    if isinstance(config, (str, Path)):
        return load_config(config, overrides)
    if isinstance(config, Config):
        if not overrides:
            return config
        return config_from_dict(apply_overrides(config_to_dict(config), overrides),
                                source=config.source)
    if isinstance(config, Mapping):
        return config_from_dict(apply_overrides(dict(config), overrides))
    raise ConfigError(f"config: got {type(config).__name__}, expected a YAML file path, a "
                      "mapping of config keys or a pipeline.config.Config")


def default_output(cfg: Config) -> Path:
    """Where a run writes without ``output``: ``outputs/<name>.h5`` (relative to the
    working directory)."""
    return Path("outputs") / f"{cfg.name}.h5"


def check_run_destinations(cfg: Config, output: str | Path | None = None, *,
                           config_path: str | Path | None = None,
                           mesh_dir: str | Path | None = None, force: bool = False) -> Path:
    """Check, before any work, that the run may write its file; returns the output path.

    The file must not be one of the run's inputs (``config_path``, the geometry file),
    nor an existing file this package did not write unless ``force``; a default
    destination's folder is created on writing. ``mesh_dir``, if given, must be a
    folder that can be written. Raises :class:`~pipeline.errors.OutputError`."""
    from pipeline._util.paths import check_output, check_output_dir

    path = Path(output) if output is not None else default_output(cfg)
    inputs = ([config_path] if config_path is not None else []) + (
        [cfg.geometry.path] if getattr(cfg.geometry, "path", None) else [])
    check_output(path, inputs=inputs, force=force, kind="h5", create_parent=output is None)
    if mesh_dir:
        check_output_dir(mesh_dir, marker=lambda p: True, what="mesh folder")
    return path


def run_config(config: str | Path | Mapping[str, Any] | Config, *,
               output: str | Path | None = None, overrides: Sequence[str] = (),
               mesh_dir: str | Path | None = None, force: bool = False,
               progress: Callable[[str, int | None, str], Any] | None = None) -> RunResult:
    """Run every stage for ``config`` and write its HDF5 file; returns the
    :class:`~pipeline.run.RunResult` (frequencies, labels, times, the output path...).

    Parameters
    ----------
    config
        A YAML config file's path, a mapping of config keys or a
        :class:`~pipeline.config.Config` (see :func:`resolve_config`).
    output
        The HDF5 file to write (default ``outputs/<name>.h5``).
    overrides
        ``KEY=VALUE`` texts, as ``python -m pipeline run --set`` takes them.
    mesh_dir
        Keep the gmsh mesh there (default: not kept; the mesh is in the file).
    force
        Replace an existing file this package did not write (``--force``); an input is
        never written over.
    progress
        ``progress(desc, total, unit)``: a context manager yielding ``update(n)``
        (default: none).

    Raises the command line's errors: :class:`~pipeline.errors.ConfigError` for a bad key
    or value, :class:`~pipeline.errors.OutputError` for a destination that may not be
    written (checked before any work), and the stages' own errors.
    """
    from pipeline.run import run_pipeline

    cfg = resolve_config(config, overrides)
    path = check_run_destinations(
        cfg, output, config_path=config if isinstance(config, (str, Path)) else None,
        mesh_dir=mesh_dir, force=force)
    return run_pipeline(cfg, path, mesh_dir=mesh_dir, progress=progress)
