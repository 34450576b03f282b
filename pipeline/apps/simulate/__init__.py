"""Reference stepper: replay the classic flexible-cantilever experiments from the HDF5 file.

``python -m pipeline simulate MODEL.h5 SCENARIO.yaml [...] [-o RESULT.h5]`` and
:func:`simulate`. The model is read from the file only
(:func:`pipeline.store.read.read_model_file`), never from the mesh or the FE code,
coupled with rigid bodies where a scenario asks, and integrated in time with
:func:`scipy.integrate.solve_ivp`. Everything is linear (small motions), so every
scenario is one LTI system

    z' = Abar z + Bbar w(t),     signals = S z + Sw w(t),

with ``w`` piecewise constant (loads switched on and off). ``Abar`` is assembled from the
file's A, B, C, D and the rigid-body equations; the algebraic loop of a rigid mass on a
force-in/motion-out model is broken either by the file's filtered model (``loop:
filtered``: its D = 0, the mass force is an explicit function of the state) or solved
exactly (``loop: exact``: a small linear solve built into Abar; with a residual-flexibility
feedthrough in the position output, the force becomes a state, see docs/simulate.md).

Scenarios (docs/simulate.md lists every key):

- ``step_load``: a force on an input port switched on at ``t_on`` and off at ``t_off``;
- ``body_load``: a rigid mass welded to an output port, under gravity or released from a
  preload;
- ``mass_sweep``: the body load for several masses, T^2 fitted against the mass;
- ``spring_mount``: the body's root on a revolute joint about z with a torsional spring,
  the tip mass on; planar rotation coupled to the elastic model (the elastic input is the
  tip reaction force in the rotating body frame);
- ``spin_up``: a hub spun up through a prescribed speed ramp, the body's modal model with
  and without geometric stiffening in the hub frame, and the lumped chain with its
  nonlinear planar kinematics (time-varying, not LTI: stepped by :mod:`.spinup` and
  :mod:`.spinchain` with solve_ivp alone).

Each runs on the FE model and, when the file has one and its tip matches the ports, on the
lumped chain too. Measured (from the response: zero crossings, FFT peak refined by
Gaussian interpolation, steady state by Aitken extrapolation of the half-cycle extremes)
and predicted values (DC gain, eigenvalues of Abar) are reported side by side.

Modules (each one job): :mod:`.scenarios` (Scenario records, parsing and validation),
:mod:`.systems` (model algebra: undamped, refilter, filtered/lumped model choice,
coupled and mount systems), :mod:`.integrate` (exact propagation and solve_ivp),
:mod:`.measure` (steady state, damping from decay, zero-crossing and FFT frequencies),
:mod:`.spinup` (the spin_up scenario: hub profile, rotating-frame modal equations),
:mod:`.results` (Run, Row, ScenarioResult, SimulationResults), :mod:`.run` (scenarios ->
runs, checks against the model, :func:`simulate`), :mod:`.output` (HDF5 results tree,
CSV, plots). The command line is :mod:`pipeline.cli.simulate`.
"""

from __future__ import annotations

from pipeline.apps.simulate.measure import (decay_damping_ratio, fft_peak_frequency,
                                            steady_state, zero_crossing_frequency)
from pipeline.apps.simulate.results import Row, Run, ScenarioResult, SimulationResults
from pipeline.apps.simulate.run import simulate
from pipeline.apps.simulate.scenarios import (KINDS, LOOPS, METHODS, Integrator, Scenario,
                                              load_scenarios, parse_scenarios)

__all__ = [
    "KINDS",
    "METHODS",
    "LOOPS",
    "Integrator",
    "Scenario",
    "Run",
    "Row",
    "ScenarioResult",
    "SimulationResults",
    "load_scenarios",
    "parse_scenarios",
    "simulate",
    "zero_crossing_frequency",
    "fft_peak_frequency",
    "steady_state",
    "decay_damping_ratio",
]
