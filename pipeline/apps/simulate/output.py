"""Outputs of a simulation: the HDF5 results tree, one CSV and one plot per scenario.

``RESULT.h5`` is written atomically by :func:`pipeline.store.h5file.write_file`:
``<scenario>/<model key>[/run_<i>]/time`` (s) and ``.../signals/<name>`` (SI units,
per-run measured_* / predicted_* / integrator_* attributes), ``.../stress/*`` (peak von
Mises per mesh point, its instant, fields; pipeline.apps.simulate.stress) for a file with
stress modes, ``<scenario>/<key>/fit`` for
a mass sweep, and ``summary/*`` (one entry per summary row). Beside it,
``<stem>.<scenario>.csv`` (every run's signals as columns) and ``<stem>.<scenario>.png``,
both through :func:`pipeline._util.atomic.atomic_path`.
"""

from __future__ import annotations

import csv
import math
import re
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import yaml

from pipeline._util.atomic import atomic_path
from pipeline.store.h5file import write_file
from pipeline.store.layout import (RESULT_ROOT, RESULT_SUMMARY, SIMULATION_CONTENT,
                                   result_fit, result_run)
from pipeline.store.read import ModelFile
from pipeline.store.tree import Dataset

from pipeline.apps.simulate.results import ScenarioResult, SimulationResults
from pipeline.apps.simulate.spinup import plot_spin_up
from pipeline.apps.simulate.stress import plot_stress, stress_peak_datasets

__all__ = ["slug", "results_tree", "write_csv", "plot", "write_outputs"]


def slug(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.\-]", "_", name)


def results_tree(res: SimulationResults, scenarios_yaml: str):
    tree: dict[str, Dataset] = {}
    attrs: dict[str, dict[str, Any]] = {}
    for s in res.scenarios:
        sname = slug(s.scenario.name)
        attrs[sname] = {"kind": s.scenario.kind, "notes": list(s.notes) or ["none"]}
        for i, run in enumerate(s.runs):
            group = result_run(sname, run.key, None if run.mass is None
                               or s.scenario.kind != "mass_sweep" else i)
            grp = group.path
            tree[group.time] = Dataset(run.t, "s", "sample times")
            for name, values in run.signals.items():
                tree[f"{group.signals}/{name}"] = Dataset(values, run.units[name],
                                                          f"{name} of the {run.model} model")
            a: dict[str, Any] = {"model": run.model}
            if run.mass is not None:
                a["mass_kg"] = float(run.mass)
            for k, v in run.measured.items():
                a[f"measured_{k}"] = float(v)
            for k, v in run.predicted.items():
                a[f"predicted_{k}"] = float(v)
            for k, v in run.info.items():
                if isinstance(v, (int, float, str)):
                    a[f"integrator_{k}" if k in ("nfev", "njev", "nlu", "wall_s", "method",
                                                 "rtol", "atol") else k] = v
                elif k == "deviation_from_exact":
                    for sig, dev in v.items():
                        a[f"deviation_from_exact/{sig}"] = float(dev)
            attrs[grp] = a
            if run.info.get("stress_peak") is not None:
                tree.update(stress_peak_datasets(grp, run.info["stress_peak"]))
        for key, fit in s.fits.items():
            g = result_fit(sname, key)
            tree[g.masses] = Dataset(fit["masses"], "kg", "tip masses of the sweep")
            tree[g.measured_frequency] = Dataset(fit["measured_hz"], "Hz",
                                                 "zero-crossing frequency per mass")
            tree[g.predicted_frequency] = Dataset(fit["predicted_hz"], "Hz",
                                                  "coupled eigenvalue per mass")
            tree[g.period_squared] = Dataset(1.0 / fit["measured_hz"] ** 2, "s^2",
                                             "measured T^2 per mass")
            attrs[g.path] = {k: float(v) for k, v in fit.items()
                        if isinstance(v, (int, float)) and not isinstance(v, bool)}
    rows = res.rows
    sm = RESULT_SUMMARY
    tree[sm.scenario] = Dataset([r.scenario for r in rows], "1", "scenario name")
    tree[sm.model] = Dataset([r.model for r in rows], "1", "model")
    tree[sm.quantity] = Dataset([r.quantity for r in rows], "1", "what is compared")
    tree[sm.units] = Dataset([r.units for r in rows], "1", "unit of measured/predicted")
    tree[sm.measured] = Dataset(np.array([r.measured for r in rows]), "mixed",
                                f"value measured from the response (units: {sm.units})")
    tree[sm.predicted] = Dataset(np.array([r.predicted for r in rows]), "mixed",
                                 "analytic prediction from the matrices")
    return tree, attrs


def write_csv(path: Path, s: ScenarioResult) -> Path:
    """Time series of every run as columns ``<model>[ m=<kg>]:<signal> [unit]`` (runs of
    a sweep may be shorter than the longest; their cells past the end are empty)."""
    cols: list[tuple[str, np.ndarray]] = []
    t = max((r.t for r in s.runs), key=len)
    for run in s.runs:
        tag = run.key + ("" if run.mass is None or s.scenario.kind != "mass_sweep"
                         else f" m={run.mass:g}kg")
        for name, values in run.signals.items():
            cols.append((f"{tag}:{name} [{run.units[name]}]", values))
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["time [s]"] + [c[0] for c in cols])
        for i, ti in enumerate(t):
            w.writerow([f"{ti:.10g}"] + [f"{c[1][i]:.10g}" if i < c[1].size else ""
                                         for c in cols])
    return path


def plot(path: Path, s: ScenarioResult, port: str) -> Path:
    # deferred: heavy, only needed when plots are asked for; a Figure of its own (no
    # pyplot), so the host's matplotlib backend and open figures are left alone
    from matplotlib.figure import Figure

    sc = s.scenario
    if sc.kind == "spin_up":
        return plot_spin_up(path, s, port)
    style = {"fe": dict(color="C0", lw=1.4), "lumped": dict(color="C3", lw=1.0, ls="--")}
    if sc.kind == "mass_sweep":
        fig = Figure(figsize=(11, 4.2))
        ax1, ax2 = fig.subplots(1, 2)
        for key, fit in s.fits.items():
            st = style[key]
            m = fit["masses"]
            mm = np.linspace(0, m.max(), 100)
            ax1.plot(m, 1e3 / fit["measured_hz"] ** 2, "o" if key == "fe" else "s",
                     color=st["color"], mfc="none", label=f"{key}: measured")
            ax1.plot(mm, 1e3 * (fit["a_s2"] + fit["b_s2_per_kg"] * mm), color=st["color"],
                     ls=st.get("ls", "-"), lw=1,
                     label=f"{key}: fit, R$^2$={fit['r2']:.6f}, f0={fit['f0_hz']:.2f} Hz")
            ax2.plot(m, fit["measured_hz"], "o" if key == "fe" else "s", color=st["color"],
                     mfc="none", label=f"{key}: measured")
            ax2.plot(m, fit["predicted_hz"], "x", color=st["color"], label=f"{key}: eigenvalue")
        ax1.set_xlabel("tip mass [kg]")
        ax1.set_ylabel("T$^2$ [ms$^2$]")
        ax1.set_title("squared period vs load mass")
        ax2.set_xlabel("tip mass [kg]")
        ax2.set_ylabel("frequency [Hz]")
        ax2.set_yscale("log")
        from matplotlib.ticker import ScalarFormatter

        ax2.yaxis.set_major_formatter(ScalarFormatter())
        ax2.yaxis.set_minor_formatter(ScalarFormatter())
        ax2.set_title("first coupled mode")
        for ax in (ax1, ax2):
            ax.grid(alpha=0.3)
            ax.legend(fontsize=8)
    else:
        n = 3 if sc.kind == "spring_mount" else 2
        fig = Figure(figsize=(10, 2.8 * n + 0.6))
        axes = fig.subplots(n, 1, sharex=sc.kind != "spring_mount")
        sig = f"{port}/position" if sc.kind == "step_load" else "mass_displacement"
        force = sc.input if sc.input else None
        for run in s.runs:
            st = style.get(run.key, {})
            axes[0].plot(run.t, 1e3 * run.signals[sig], label=run.model, **st)
            if sc.kind == "spring_mount":
                axes[1].plot(run.t, 1e3 * run.signals["theta"], label=run.model, **st)
            else:
                name = [k for k in run.signals if run.units[k] == "N" and k != "mass_force"][0]
                force = name
                axes[1].plot(run.t, run.signals[name], label=run.model, **st)
            ss = run.predicted.get("steady_state")
            if ss is not None and math.isfinite(ss):
                axes[0].axhline(1e3 * ss, color=st.get("color", "k"), ls=":", lw=0.8)
        axes[0].set_ylabel(("tip" if sc.kind == "step_load" else "mass") + " displacement [mm]")
        if sc.kind == "step_load":
            axes[0].axvspan(sc.t_on, sc.duration if sc.t_off is None else sc.t_off,
                            color="0.9", zorder=0, label="load on")
        axes[0].legend(fontsize=8, loc="best")
        if sc.kind == "spring_mount":
            axes[1].set_ylabel("joint angle [mrad]")
            axes[1].set_xlabel("time [s]")
            for run in s.runs:
                st = style.get(run.key, {})
                th = run.signals["theta"]
                n_ = th.size
                nfft = 1 << int(math.ceil(math.log2(8 * n_)))
                X = np.abs(np.fft.rfft((th - th.mean()) * np.hanning(n_), nfft))
                f = np.fft.rfftfreq(nfft, run.t[1] - run.t[0])
                axes[2].semilogy(f, X / X.max(), label=f"{run.model}: |FFT(theta)|", **st)
                for k in ("mode1", "mode2"):
                    v = run.predicted.get(k)
                    if v is not None and math.isfinite(v):
                        axes[2].axvline(v, color=st.get("color", "k"), ls=":", lw=0.8)
            f2 = max((r.predicted.get("mode2", 0) for r in s.runs), default=0)
            axes[2].set_xlim(0, 2.0 * f2 if f2 and math.isfinite(f2) else None)
            axes[2].set_ylim(1e-5, 2)
            axes[2].set_xlabel("frequency [Hz] (dotted: coupled eigenvalues)")
            axes[2].set_ylabel("normalised magnitude")
            axes[2].legend(fontsize=8)
        else:
            axes[1].set_ylabel(f"{force} [N]")
            axes[1].set_xlabel("time [s]")
        for ax in axes:
            ax.grid(alpha=0.3)
    lines = []
    for r in s.rows:
        if "frequency" in r.quantity and "FFT" not in r.quantity and "exact" not in r.quantity \
                and sc.kind != "mass_sweep":
            lines.append(f"{r.model.split(' (')[0]}: {r.measured:.4g} Hz "
                         f"(predicted {r.predicted:.4g})")
    fig.suptitle(f"{sc.name} ({sc.kind})" + ("\n" + "; ".join(lines) if lines else ""),
                 fontsize=10)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    return path



def write_outputs(results: SimulationResults, mf: ModelFile, output_ports: Mapping[str, str],
                  output: Path, plots: bool) -> None:
    """Write ``output`` (HDF5), and the CSV and (if ``plots``) PNG files beside it; add
    their paths to ``results.files``. ``output_ports``: scenario name -> output port."""
    scenarios = [s.scenario for s in results.scenarios]
    output.parent.mkdir(parents=True, exist_ok=True)
    doc = yaml.safe_dump([s.as_dict() for s in scenarios], sort_keys=False)
    tree, attrs = results_tree(results, doc)
    root = RESULT_ROOT
    write_file(output, tree, attrs, {root.content: SIMULATION_CONTENT,
                                     root.model_file: str(mf.path.resolve()),
                                     root.model_content_sha256: mf.sha256,
                                     root.scenarios_yaml: doc})
    results.output = output
    results.files.append(output)
    stem = output.with_suffix("")
    for s in results.scenarios:
        port = output_ports[s.scenario.name]
        results.files.append(write_csv(Path(f"{stem}.{slug(s.scenario.name)}.csv"), s))
        if plots:
            results.files.append(plot(Path(f"{stem}.{slug(s.scenario.name)}.png"), s, port))
            results.files.extend(plot_stress(Path(f"{stem}.{slug(s.scenario.name)}.stress.png"),
                                             s, mf.path))

