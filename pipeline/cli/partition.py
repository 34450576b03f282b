"""``python -m pipeline partition CONFIG --ranks N [-o PATH] [--set KEY=VALUE ...]``.

Rank 0's mesh phase of the distributed path for a run on N ranks, once, on one process
(:func:`pipeline.distributed.parts.write_partitioned`): the body is meshed, its regions,
supports, ports and materials evaluated, its points partitioned into N parts
(PT-Scotch through PETSc where petsc4py imports, else slabs) and every part cut out and
written to one parts file (:mod:`pipeline.distributed.parts_file`, default
``outputs/<name>-parts<N>.h5``). A run with ``--set mesh.parts=PATH`` on N ranks then
reads it, each rank its own part (docs/distributed.md).
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

log = logging.getLogger(__name__)

__all__ = ["add_partition_parser", "check_partition_destination", "default_parts_output"]


def default_parts_output(cfg, ranks: int) -> Path:
    """``outputs/<name>-parts<N>.h5`` (relative to the working directory)."""
    return Path("outputs") / f"{cfg.name}-parts{ranks}.h5"


def check_partition_destination(args: argparse.Namespace) -> None:
    """Before any work: the config (its overrides applied) is valid and partitionable
    (:func:`pipeline.distributed.parts.check_partitionable`), the rank count is at
    least 1, and the output may be written: never one of the command's inputs (the
    config, the geometry or mesh file, a parts file the config names), an existing
    file only when it is a parts file of ours or with ``--force``."""
    from pipeline._util.paths import check_output
    from pipeline.api import resolve_config
    from pipeline.distributed.parts import check_partitionable
    from pipeline.distributed.parts_file import is_parts_file
    from pipeline.errors import ConfigError

    cfg = resolve_config(args.config, args.set or [])
    if args.ranks < 1:
        raise ConfigError(f"--ranks {args.ranks}: expected a rank count of at least 1",
                          key="--ranks", value=args.ranks, expected=">= 1")
    check_partitionable(cfg)
    args.resolved_config = cfg  # a config from a pipe can be read only once
    path = Path(args.output) if args.output else default_parts_output(cfg, args.ranks)
    inputs = [args.config] + [p for p in (cfg.geometry.path, cfg.mesh.parts) if p]
    ours = path.is_file() and is_parts_file(path)
    check_output(path, inputs=inputs, force=args.force or ours, kind="h5",
                 create_parent=not args.output)
    args.parts_output = path


def cmd_partition(args: argparse.Namespace) -> int:
    from pipeline.distributed.parts import write_partitioned

    path = write_partitioned(args.resolved_config, args.ranks, args.parts_output,
                             mesh_dir=args.mesh_dir)
    print(f"wrote {path} ({args.ranks} parts); run it on {args.ranks} ranks with "
          f"--set modes.solver=slepc --set mesh.parts={path}")
    return 0


def add_partition_parser(subparsers) -> argparse.ArgumentParser:
    """``partition CONFIG --ranks N [-o PATH] [--set ...]`` on the CLI's subparsers."""
    p = subparsers.add_parser(
        "partition", help="mesh once and write each MPI rank's part to a parts file",
        description="Rank 0's mesh phase of 'run --set modes.solver=slepc' for N ranks, on "
        "one process: mesh, evaluate regions, supports, ports and materials, partition the "
        "points into N parts (PT-Scotch through PETSc where petsc4py imports, else slabs; "
        "PETSC_OPTIONS=-pipeline_partition slab forces slabs) and write every part to one "
        "HDF5 file. A run on N ranks with --set mesh.parts=FILE reads it, each rank its own "
        "part. See docs/distributed.md.")
    p.add_argument("config", help="YAML config file")
    p.add_argument("--ranks", type=int, required=True, metavar="N",
                   help="the rank count of the run that will read the file")
    p.add_argument("-o", "--output", help="parts file (default outputs/<name>-parts<N>.h5)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override a config key by its dotted path, e.g. mesh.size=0.004")
    p.add_argument("--mesh-dir", default=None,
                   help="keep the gmsh mesh there as <name>.<sha256[:12]>.msh")
    p.set_defaults(func=cmd_partition)
    return p
