"""Scenarios -> runs: each scenario stepped on the FE model (and the lumped chain), its
response measured and set beside the model's predictions; :func:`simulate`, the entry
point.

Predictions come from the matrices only: the DC gain G(0) = D - C A^-1 B of the plant
(:meth:`StateSpace.dc_gain`), the eigenvalues of the stepped system's A (damped frequency
|Im lambda| / 2 pi in Hz, damping ratio -Re lambda / |lambda|) and its static
equilibrium z_eq = -A^-1 B w.
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from pipeline.errors import ConfigError
from pipeline.reduce.statespace import StateSpace
from pipeline.store.read import ModelFile, read_model_file

from pipeline.apps.simulate.integrate import Segment, integrate, time_grid, w_series
from pipeline.apps.simulate.measure import (decay_damping_ratio, fft_peak_frequency,
                                            fit_sweep, modes_in, steady_state,
                                            zero_crossing_frequency)
from pipeline.apps.simulate.output import write_outputs
from pipeline.apps.simulate.results import Row, Run, ScenarioResult, SimulationResults
from pipeline.apps.simulate.scenarios import Scenario, as_scenarios, check_step_budget
from pipeline.apps.simulate.spinup import check_spin_budget, run_spin_up
from pipeline.apps.simulate.stress import add_stress_outputs, gauge_ports
from pipeline.apps.simulate.systems import (SteppedSystem, coupled_system, directions,
                                            filtered_for, lumped_for, mount_for, step_system,
                                            undamped)

log = logging.getLogger(__name__)

__all__ = ["scenario_ports", "run_scenario", "check_against_model", "simulate"]


def scenario_ports(mf: ModelFile, sc: Scenario) -> tuple[str, str]:
    """(input port, output port) of ``sc`` in the file: the named ones, or the model's
    only one. ConfigError naming the scenario when a port is missing or ambiguous."""
    def pick(name: str | None, names: Sequence[str], what: str, key: str) -> str:
        if name is None:
            if len(names) == 1:
                return names[0]
            raise ConfigError(f"scenario '{sc.name}'.{key} is missing: the model has "
                              f"{len(names)} {what} ports ({', '.join(names)}); name one",
                              key=f"{sc.name}.{key}", expected="one of: " + ", ".join(names))
        if name not in names:
            raise ConfigError(f"scenario '{sc.name}'.{key}: {what} port '{name}' is not in "
                              f"'{mf.path}'; it has: {', '.join(names)}",
                              key=f"{sc.name}.{key}", value=name,
                              expected="one of: " + ", ".join(names))
        return name

    gauges = gauge_ports(mf)  # strain/stress outputs are recorded, never driven or coupled
    if sc.kind == "spin_up":  # driven by the hub, not by an input port
        return ("", pick(sc.output, [p for p in mf.plant.ports if p not in gauges],
                         "motion output", "output"))
    return (pick(sc.input, list(mf.plant.input_names), "input", "input"),
            pick(sc.output, [p for p in mf.plant.ports if p not in gauges], "motion output",
                 "output"))



def make_run(model: str, key: str, sys: SteppedSystem, Z: np.ndarray, t: np.ndarray,
              w_of_t: np.ndarray, stats: dict, mass: float | None = None) -> Run:
    Y = sys.S @ Z + sys.Sw @ w_of_t
    signals = {n: Y[i] for i, n in enumerate(sys.signals)}
    units = dict(zip(sys.signals, sys.units))
    if sys.modal is not None:
        e, d = sys.modal
        om2 = -np.diag(sys.A[np.ix_(d, e)])
        signals["elastic_energy"] = 0.5 * (Z[d] ** 2).sum(axis=0) + 0.5 * (
            om2[:, None] * Z[e] ** 2).sum(axis=0)
        units["elastic_energy"] = "J"
    return Run(model, key, t, signals, units, {}, {}, dict(stats), mass)



def run_step(mf: ModelFile, sc: Scenario, em: StateSpace, key: str, inp: str, port: str
              ) -> tuple[Run, list[Row]]:
    sys = step_system(em, inp, port)
    t = time_grid(sc)
    F = np.array([sc.force])
    t_off = sc.duration if sc.t_off is None else sc.t_off
    segs = [s for s in (Segment(0.0, sc.t_on, np.zeros(1)), Segment(sc.t_on, t_off, F),
                        Segment(t_off, sc.duration, np.zeros(1))) if s.t1 > s.t0]
    if segs[-1].t1 < sc.duration:
        segs.append(Segment(segs[-1].t1, sc.duration, np.zeros(1)))
    Z, stats = integrate(sys, np.zeros(sys.A.shape[0]), segs, t, sc.integrator)
    run = make_run(em.label, key, sys, Z, t, w_series(segs, t), stats)
    if key == "fe":
        add_stress_outputs(run, mf, em, inp, Z, w_series(segs, t), sc.stress_instants)
    y = run.signals[f"{port}/position"]
    j = em.col(inp)
    ip = em.rows(port)[0]
    dc = float(em.dc_gain()[ip, j])
    z_eq = sys.equilibrium(F)
    modes = modes_in(sys, z_eq, [0])
    f_pred, zeta = (modes[0][0], modes[0][1]) if modes else (math.nan, math.nan)
    on = (t >= sc.t_on) & (t < t_off)
    free = t >= t_off
    period = 1.0 / f_pred if math.isfinite(f_pred) and f_pred > 0 else math.inf
    use_free = sc.t_off is not None and (sc.duration - t_off) >= 3 * period
    seg_t, seg_y = (t[free], y[free]) if use_free else (t[on], y[on])
    ss = steady_state(t[on], y[on])
    level = steady_state(seg_t, seg_y)
    f_zc = zero_crossing_frequency(seg_t, seg_y, level)
    f_fft, _ = fft_peak_frequency(seg_t, seg_y, level=level)
    zeta_m = decay_damping_ratio(seg_t, seg_y, level)
    run.measured.update(frequency_zc=f_zc, frequency_fft=f_fft, steady_state=ss,
                        damping_ratio=zeta_m)
    run.predicted.update(frequency=f_pred, damping_ratio=zeta, dc_gain=dc,
                         steady_state=dc * sc.force)
    run.info["frequency_window"] = "after t_off (free decay)" if use_free else "load on"
    if "elastic_energy" in run.signals and sc.t_off is not None:
        E = run.signals["elastic_energy"][free]
        if E.size and E[0] > 0:
            run.measured["energy_drift_after_off"] = float(np.abs(E / E[0] - 1.0).max())
    lab = em.label
    win = "free decay" if use_free else "load on"
    rows = [Row(sc.name, lab, f"frequency, zero crossings ({win})", f_zc, f_pred, "Hz",
                "damped mode"),
            Row(sc.name, lab, f"frequency, FFT peak ({win})", f_fft, f_pred, "Hz"),
            Row(sc.name, lab, f"damping ratio, log decrement ({win})", zeta_m, zeta, "1"),
            Row(sc.name, lab, "steady deflection (load on)", ss, dc * sc.force, "m",
                "DC gain x load")]
    return run, rows


def run_coupled(mf: ModelFile, sc: Scenario, em: StateSpace, key: str, inp: str,
                 port: str, mass: float, exact: bool, notes: list[str]
                 ) -> tuple[Run, SteppedSystem, np.ndarray]:
    d_in, d_out, s_io = directions(mf, sc, inp, port)
    g = np.zeros(3) if sc.gravity is None else np.asarray(sc.gravity, float)
    mount, Mg = (None, 0.0)
    if sc.kind == "spring_mount":
        mount, Mg = mount_for(mf, sc, key, port, d_out, g)
    sys, how = coupled_system(em, inp, port, mass, s_io, exact, mount)
    w_pre = np.array([0.0, 0.0, sc.preload])
    w_run = np.array([float(g @ d_out), Mg, 0.0])
    z0 = sys.equilibrium(w_pre) if sc.preload else np.zeros(sys.A.shape[0])
    if mount is not None and sc.initial_angle:
        z0[theta_index(sys)] += sc.initial_angle
    z_eq = sys.equilibrium(w_run)
    duration = sc.duration
    if sc.cycles is not None:
        modes = modes_in(sys, z0 - z_eq, [sys.signal("mass_displacement")])
        if modes and modes[0][0] > 0:
            duration = min(duration, sc.cycles / modes[0][0])
    t = time_grid(sc, duration)
    segs = [Segment(0.0, float(t[-1]), w_run)]
    Z, stats = integrate(sys, z0, segs, t, sc.integrator)
    stats["coupling"] = how
    run = make_run(em.label, key, sys, Z, t, w_series(segs, t), stats, mass)
    run.info["z_eq"] = z_eq
    run.info["z0"] = z0
    run.info["w_run"] = w_run
    return run, sys, z_eq


def theta_index(sys: SteppedSystem) -> int:
    r = sys.S[sys.signal("theta")]
    return int(np.flatnonzero(r)[0])


def measure_coupled(sc: Scenario, run: Run, sys: SteppedSystem, z_eq: np.ndarray,
                     port: str) -> list[Row]:
    t = run.t
    y = run.signals["mass_displacement"]
    rows: list[Row] = []
    lab = run.model + (f", m = {run.mass:g} kg" if sc.kind == "mass_sweep" else "")
    dz = run.info["z0"] - z_eq
    sig_rows = [sys.signal("mass_displacement")]
    if "theta" in sys.signals:
        sig_rows.append(sys.signal("theta"))
    modes = modes_in(sys, dz, sig_rows)
    # steady state of the signals (the w part of S is the same constant for all t > 0)
    Wc = run.info["w_run"]
    ss_pred = float(sys.S[sys.signal("mass_displacement")] @ z_eq
                    + sys.Sw[sys.signal("mass_displacement")] @ Wc)
    level = steady_state(t, y)
    if sc.kind == "spring_mount":
        two = sorted(modes[:2], key=lambda m: m[0])
        f1p = two[0][0] if two else math.nan
        f2p = two[1][0] if len(two) > 1 else math.nan
        f1_zc = zero_crossing_frequency(t, y, level)
        f1_fft, _ = fft_peak_frequency(t, y, level=level)
        th = run.signals["theta"]
        th_level = steady_state(t, th)
        f2_fft, h2 = (fft_peak_frequency(t, th, 0.75 * f2p, 1.25 * f2p, level=th_level)
                      if math.isfinite(f2p) else (math.nan, math.nan))
        th_pred = float(sys.S[sys.signal("theta")] @ z_eq + sys.Sw[sys.signal("theta")] @ Wc)
        zeta1 = decay_damping_ratio(t, y, level)
        run.measured.update(mode1_zc=f1_zc, mode1_fft=f1_fft, mode2_fft=f2_fft, mode1_damping=zeta1,
                            mode2_peak_height=h2, steady_state=level, theta_steady=th_level)
        run.predicted.update(mode1=f1p, mode2=f2p, steady_state=ss_pred, theta_steady=th_pred,
                             mode1_damping=two[0][1] if two else math.nan,
                             mode2_damping=two[1][1] if len(two) > 1 else math.nan)
        rows += [Row(sc.name, lab, "mode 1 frequency, zero crossings", f1_zc, f1p, "Hz",
                     "coupled eigenvalue"),
                 Row(sc.name, lab, "mode 1 frequency, FFT peak", f1_fft, f1p, "Hz"),
                 Row(sc.name, lab, "mode 1 damping ratio, log decrement", zeta1,
                     two[0][1] if two else math.nan, "1"),
                 Row(sc.name, lab, "mode 2 frequency, FFT of theta", f2_fft, f2p, "Hz",
                     f"peak {h2:.2g} of the largest" if math.isfinite(h2) else ""),
                 Row(sc.name, lab, "steady mass displacement", level, ss_pred, "m",
                     "static equilibrium"),
                 Row(sc.name, lab, "steady joint angle", th_level, th_pred, "rad")]
        return rows
    fp = modes[0][0] if modes else math.nan
    zeta = modes[0][1] if modes else math.nan
    f_zc = zero_crossing_frequency(t, y, level)
    f_fft, _ = fft_peak_frequency(t, y, level=level)
    zeta_m = decay_damping_ratio(t, y, level)
    run.measured.update(frequency_zc=f_zc, frequency_fft=f_fft, steady_state=level,
                        damping_ratio=zeta_m)
    run.predicted.update(frequency=fp, damping_ratio=zeta, steady_state=ss_pred)
    rows += [Row(sc.name, lab, "frequency, zero crossings", f_zc, fp, "Hz", "coupled eigenvalue"),
             Row(sc.name, lab, "frequency, FFT peak", f_fft, fp, "Hz")]
    if sc.kind == "body_load":
        rows += [Row(sc.name, lab, "damping ratio, log decrement", zeta_m, zeta, "1"),
                 Row(sc.name, lab, "steady mass displacement", level, ss_pred, "m",
                     "static equilibrium")]
    return rows


def exact_reference(mf: ModelFile, sc: Scenario, inp: str, port: str, mass: float
                     ) -> float:
    """Dominant coupled frequency of the plant with the loop solved exactly (the value a
    filtered model tends to as its cutoff grows)."""
    plant = mf.plant if sc.damping else undamped(mf.plant)
    _, d_out, s_io = directions(mf, sc, inp, port)
    g = np.zeros(3) if sc.gravity is None else np.asarray(sc.gravity, float)
    mount, Mg = (None, 0.0)
    if sc.kind == "spring_mount":
        mount, Mg = mount_for(mf, sc, "fe", port, d_out, g)
    sys, _ = coupled_system(plant, inp, port, mass, s_io, True, mount)
    w_run = np.array([float(g @ d_out), Mg, 0.0])
    z0 = sys.equilibrium(np.array([0.0, 0.0, sc.preload])) if sc.preload else np.zeros(
        sys.A.shape[0])
    if mount is not None and sc.initial_angle:
        z0[theta_index(sys)] += sc.initial_angle
    rows = [sys.signal("mass_displacement")]
    modes = modes_in(sys, z0 - sys.equilibrium(w_run), rows)
    return (modes[0][0], modes[0][1]) if modes else (math.nan, math.nan)


def check_against_model(mf: ModelFile, sc: Scenario) -> None:
    """Ports, directions, filtered model, mount geometry and the integrator's step budget
    of every FE run of ``sc`` against the file (the same checks the run makes, done up
    front, so that nothing runs when one would be refused)."""
    inp, port = scenario_ports(mf, sc)
    if sc.kind == "spin_up":
        check_spin_budget(mf, sc, port)
        return
    if sc.kind == "step_load":  # the plant is the stepped system: its budget, up front
        check_step_budget(mf.plant.A, sc.duration, sc.integrator.method, sc.name,
                          rtol=sc.integrator.rtol)
        return
    _, d_out, s_io = directions(mf, sc, inp, port)
    em = filtered_for(mf, sc, []) if sc.loop == "filtered" else mf.plant
    mount = None
    if sc.kind == "spring_mount":
        g = np.zeros(3) if sc.gravity is None else np.asarray(sc.gravity, float)
        mount, _ = mount_for(mf, sc, "fe", port, d_out, g)
    # every coupled FE system's step budget (at the full duration), before any run
    for mass in sc.masses if sc.kind == "mass_sweep" else (sc.mass,):
        sys, _ = coupled_system(em, inp, port, mass, s_io, sc.loop != "filtered", mount)
        check_step_budget(sys.A, sc.duration, sc.integrator.method, sc.name,
                          rtol=sc.integrator.rtol)


def run_scenario(mf: ModelFile, sc: Scenario) -> ScenarioResult:
    inp, port = scenario_ports(mf, sc)
    if sc.kind == "spin_up":
        return run_spin_up(mf, sc, port)
    notes: list[str] = []
    models: list[tuple[str, StateSpace, bool]] = []   # key, model, exact loop
    if sc.kind == "step_load":
        plant = mf.plant if sc.damping else undamped(mf.plant)
        models.append(("fe", plant, True))
    else:
        if sc.loop == "filtered":
            models.append(("fe", filtered_for(mf, sc, notes), False))
        else:
            models.append(("fe", mf.plant if sc.damping else undamped(mf.plant), True))
    lumped, why = lumped_for(mf, sc, inp, port)
    if lumped is not None:
        models.append(("lumped", lumped, True))
        if why:
            notes.append(why)
        if mf.in_plane:
            notes.append("the FE model is in-plane (u_z = 0, stiffer by about 1/sqrt(1 - nu^2) "
                         "in frequency); the lumped chain is plain beam theory without that "
                         "constraint, so it is expected to be softer")
        if sc.kind != "step_load":
            notes.append("lumped chain: loop solved exactly (the file has no filtered lumped "
                         "model)")
    elif why and sc.lumped:
        notes.append(f"no lumped run: {why}")
    result = ScenarioResult(sc, [], [], notes)
    for key, em, exact in models:
        if sc.kind == "step_load":
            run, rows = run_step(mf, sc, em, key, inp, port)
            result.runs.append(run)
            result.rows.extend(rows)
            continue
        masses = sc.masses if sc.kind == "mass_sweep" else (sc.mass,)
        f_meas = []
        f_pred = []
        for m in masses:
            run, sys, z_eq = run_coupled(mf, sc, em, key, inp, port, m, exact, notes)
            rows = measure_coupled(sc, run, sys, z_eq, port)
            if not exact and key == "fe" and sc.kind != "mass_sweep":
                f_ex, z_ex = exact_reference(mf, sc, inp, port, m)
                run.predicted["frequency_exact_loop"] = f_ex
                run.predicted["damping_ratio_exact_loop"] = z_ex
                meas = run.measured.get("frequency_zc", run.measured.get("mode1_zc"))
                rows.insert(1, Row(sc.name, rows[0].model, rows[0].quantity.replace(
                    "zero crossings", "z.c. vs exact-loop plant"), meas, f_ex, "Hz",
                    "cutoff-free reference"))
                zm = run.measured.get("damping_ratio", run.measured.get("mode1_damping"))
                rows.append(Row(sc.name, rows[0].model, "damping ratio vs exact-loop plant", zm,
                                z_ex, "1", "the filter lag adds ~1.5 omega/K"))
            result.runs.append(run)
            if sc.kind == "mass_sweep":
                f_meas.append(run.measured["frequency_zc"])
                f_pred.append(run.predicted["frequency"])
                result.rows.append(rows[0])
            else:
                result.rows.extend(rows)
        if sc.kind == "mass_sweep":
            fit = fit_sweep(np.asarray(masses), np.asarray(f_meas))
            fit_pred = fit_sweep(np.asarray(masses), np.asarray(f_pred))
            m0 = int(np.argmin(masses))
            f_first = f_pred[m0] if masses[m0] == 0 else math.nan
            fit.update(masses=np.asarray(masses), measured_hz=np.asarray(f_meas),
                       predicted_hz=np.asarray(f_pred), first_mode_hz=f_first,
                       fit_of_predicted=fit_pred)
            result.fits[key] = fit
            lab = em.label
            result.rows += [
                Row(sc.name, lab, "T^2 vs mass: R^2", fit["r2"], 1.0, "1", "linear fit"),
                Row(sc.name, lab, "unloaded frequency from the fit", fit["f0_hz"], f_first,
                    "Hz", "vs first mode (m = 0 eigenvalue)"),
                Row(sc.name, lab, "effective tip mass a/b", fit["effective_mass_kg"],
                    fit_pred["effective_mass_kg"], "kg", "predicted: same fit of eigenvalues")]
            if masses[m0] != 0:
                notes.append("the sweep has no zero mass: the first mode is not simulated, "
                             "compare the recovered frequency with the file's modes")
    return result


# =========================================================================== public API
def simulate(model_path: str | Path, scenario: Any, output: str | Path | None = None,
             plots: bool = True) -> SimulationResults:
    """Run scenario(s) on the model file ``model_path``.

    scenario: a scenario file path, a parsed mapping or list, a :class:`Scenario`, or a list
    of any of these. output: RESULT.h5 to write (atomically, with
    :func:`pipeline.store.h5file.write_file`), with ``<stem>.<scenario>.csv`` and, if ``plots``,
    ``<stem>.<scenario>.png`` beside it; None writes nothing.
    """
    t0 = time.perf_counter()
    scenarios = as_scenarios(scenario)
    mf = read_model_file(model_path)
    for sc in scenarios:          # refuse a bad scenario before running any
        check_against_model(mf, sc)
    results = SimulationResults(Path(model_path), [])
    for sc in scenarios:
        ts = time.perf_counter()
        results.scenarios.append(run_scenario(mf, sc))
        log.info("scenario %s: %.2f s", sc.name, time.perf_counter() - ts)
    results.wall_s = time.perf_counter() - t0
    if output is not None:
        ports = {sc.name: scenario_ports(mf, sc)[1] for sc in scenarios}
        write_outputs(results, mf, ports, Path(output), plots)
    return results


