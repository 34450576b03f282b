"""What the reduce stage hands to the store: the :class:`Models` record.

One frozen record per run holding every reduced model the config asked for (each field
None or empty when not configured):

- ``reduced``: :class:`~pipeline.reduce.modal.ReducedModel`, the modal plant
  (``reduced.statespace``, a StateSpace) with its static compliance (n_y x n_u);
  ``filtered``: its output-filtered twin (a StateSpace) or None;
  ``input_units`` / ``output_units``: SI unit per input / output port;
  ``compliance_units``: unit of the static compliance (``"m/N"``, or ``"mixed"``);
- ``lumped``: :class:`~pipeline.reduce.lumped.LumpedModel`, the rigid-body chain, and
  ``comparison``: its rows against FE and beam theory;
- ``connection``: :class:`~pipeline.reduce.connection.ConnectionModel` (6x6 hybrid
  cantilever at the parent point) and ``connection_statespace`` (a StateSpace);
- ``craig_bampton``: :class:`~pipeline.reduce.craig_bampton.CraigBamptonModel`;
- ``ffrf``: :class:`~pipeline.reduce.ffrf.FFRFInvariants`;
- ``fe_matrices``: (K_full, M_full), the sparse stiffness (N/m) and mass (kg) matrices of
  the unsupported body (n_dofs x n_dofs) that the Exudyn export reads back;
- ``summary``: text lines for the CLI.

:func:`pipeline.store.schema.models_tree` is the one place that turns it into HDF5
datasets.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from pipeline.reduce.connection import ConnectionModel
from pipeline.reduce.craig_bampton import CraigBamptonModel
from pipeline.reduce.ffrf import FFRFInvariants
from pipeline.reduce.lumped import ComparisonRow, LumpedModel
from pipeline.reduce.modal import ReducedModel, StateSpaceModel
from pipeline.reduce.statespace import StateSpace

__all__ = ["Models"]


@dataclass(frozen=True, eq=False)
class Models:
    """Every reduced model of one run (see the module docstring)."""

    reduced: ReducedModel | None = None
    filtered: StateSpaceModel | None = None
    input_units: tuple[str, ...] = ()
    output_units: tuple[str, ...] = ()
    compliance_units: str = "m/N"
    lumped: LumpedModel | None = None
    comparison: tuple[ComparisonRow, ...] = ()
    connection: ConnectionModel | None = None
    connection_statespace: StateSpace | None = None
    craig_bampton: CraigBamptonModel | None = None
    ffrf: FFRFInvariants | None = None
    fe_matrices: tuple[Any, Any] | None = None
    summary: tuple[str, ...] = ()
