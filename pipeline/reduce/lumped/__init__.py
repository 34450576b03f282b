"""Lumped-parameter beam model: rigid elements joined by springs (theory.md §7, §8).

Modules: :mod:`.section` (cross-sections, beam check), :mod:`.chain` (spring constants,
the chain and its state space), :mod:`.theory` (beam theory, comparison table).

A straight beam of length ``L`` along x, clamped at x = 0, is cut into ``n`` rigid
elements of length ``l = L / n`` joined by joints with springs and dampers. The chain
is linearised about its straight, unloaded configuration, so its model is linear:
``M q'' + C q' + K q = F u``, ``y = T q``, with ``q`` the joint coordinates.

Conventions (SI units throughout: m, kg, s, N, Pa, rad):

- Section axes: ``y`` along the section ``height``, ``z`` along its ``depth``. ``I_y`` is
  the second moment about y (``int z^2 dA``, bending in the x-z plane) and ``I_z`` the one
  about z (``int y^2 dA``, bending in the x-y plane, the plane of a tip force along -y).
- Joint degrees of freedom, in this order at every joint (:data:`JOINT_DOFS`):
  ``axial`` (prismatic, stretch along x, m), ``torsion`` (revolute about x, rad),
  ``bend_y`` (revolute about y, rad), ``bend_z`` (revolute about z, rad).
  ``q`` is joint-major: ``[joint 1 dofs, joint 2 dofs, ...]``.
- Mode labels: ``axial``, ``torsion``, ``bending_y`` (rotation about y: deflection along
  z) and ``bending_z`` (rotation about z: deflection along y, the x-y plane).
- Constants (theory.md §7):
  ``refined``: joints at x = (i - 1) l, joint 1 at the clamp; extension E A / l,
  torsion 2 G J / l at joint 1 and G J / l after, bending (E I / l) 6n / (3n - 1) at
  joint 1 and E I / l after. All four joint DOFs exist.
  ``simple``: the generalised pure-bending element, two rigid halves of length l / 2
  with a revolute joint between them, welded end to end: joints at x = (i - 1/2) l,
  bending only, k = E I / l about each transverse axis. The chain is rigid in extension
  and torsion (those joint DOFs do not exist; their constants are reported as ``inf``).
  Its moving bodies are the welded halves between two joints (length l, mass m / n) and
  the last half at the tip (length l / 2); the half at the clamp is part of the ground.
- Joint damping: stiffness-proportional, ``C = beta K`` with ``beta = 2 xi / omega_ref``,
  ``omega_ref`` the chain's lowest natural frequency (or a given reference). Because ``K``
  is diagonal in joint coordinates, this is one damper per joint DOF,
  ``c_j = beta k_j`` (what a rigid-body code can model), and it is classical damping,
  so the modal state-space form of theory.md §3 is exact: mode i gets the ratio
  ``xi_i = xi omega_i / omega_ref`` (the reference mode gets ``xi``, higher modes more;
  modes with ``xi_i >= 1`` are overdamped, which the state-space form still represents).

The section is assumed doubly symmetric in the sense the chain needs: principal axes
along y and z, shear centre at the centroid. Sections whose product of area ``I_yz`` is
not negligible are refused; for a section that is not symmetric the shear centre may sit
off the centroid (bending-torsion coupling), which the chain ignores.
"""

from pipeline.reduce.lumped.chain import (DOF_AXIS, DOF_KIND, JOINT_DOFS, LumpedModel,
                                          SpringConstants, body_motion, lumped_model,
                                          spring_constants, static_response, tip_load)
from pipeline.reduce.lumped.section import (SLENDER_MIN, SLENDER_WARN, SectionProperties,
                                            box_section, check_beam, rectangle_torsion_constant,
                                            section_from_mesh)
from pipeline.reduce.lumped.theory import (ComparisonRow, beam_theory_frequencies_hz,
                                           beam_theory_tip_deflection, cantilever_beta_l,
                                           comparison_table, format_comparison)

__all__ = [
    "JOINT_DOFS",
    "DOF_KIND",
    "DOF_AXIS",
    "SLENDER_MIN",
    "SLENDER_WARN",
    "SectionProperties",
    "SpringConstants",
    "LumpedModel",
    "ComparisonRow",
    "box_section",
    "rectangle_torsion_constant",
    "section_from_mesh",
    "check_beam",
    "spring_constants",
    "lumped_model",
    "tip_load",
    "static_response",
    "body_motion",
    "beam_theory_frequencies_hz",
    "beam_theory_tip_deflection",
    "cantilever_beta_l",
    "comparison_table",
    "format_comparison",
]
