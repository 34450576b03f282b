"""Stress and strain in a simulation: gauge histories and the recovered stress field.

Gauge ports (``strain``, dimensionless, and ``stress``, Pa, outputs of the model file) are
rows of the plant like any displacement port, so their histories are

    y_g(t) = C_g z(t) + D_g u(t)        (the ``<gauge>/position`` rows; ``<gauge>`` signal).

The stress field at every mesh point follows from the modal coordinates with the file's
``stress_modes`` group (docs/hdf5-format.md, docs/stress.md):

    sigma(x, t) = sum_k S_k(x) eta_k(t) + sum_j R_j(x) u_j(t)      (Pa, Voigt [xx yy zz yz xz xy])

with S_k the stress of basis vector k (per unit eta_k, m kg^1/2) and R_j the stress of the
residual-flexibility shape of input j (per unit input). Von Mises stress (not linear in the
state, so post-processing only):

    sigma_vm = sqrt(((s_xx - s_yy)^2 + (s_yy - s_zz)^2 + (s_zz - s_xx)^2) / 2
                    + 3 (s_yz^2 + s_xz^2 + s_xy^2)).

:func:`peak_stress` finds, at every mesh point, the instant of its peak von Mises stress and
that peak; the hot spot is the point with the largest peak. Work is chunked over points so
memory stays at ``chunk * 6 * n_t`` floats.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from pipeline.apps.stress_fields import von_mises
from pipeline.reduce.statespace import StateSpace
from pipeline.store.read import ModelFile, StressModes, read_stress_modes

__all__ = ["GAUGE_UNITS", "von_mises", "gauge_ports", "gauge_histories", "stress_history",
           "StressPeak", "peak_stress", "stress_modes_of"]

GAUGE_UNITS = {"strain": "1", "stress": "Pa"}
#: mesh points per block of the peak search (block * 6 * n_t floats in memory)
CHUNK = 256


def gauge_ports(mf: ModelFile) -> dict[str, str]:
    """Gauge output ports of the file's config: name -> SI unit."""
    return {name: GAUGE_UNITS[p["kind"]] for name, p in mf.ports.items()
            if p.get("side") == "outputs" and p.get("kind") in GAUGE_UNITS
            and name in mf.plant.ports}


def gauge_histories(mf: ModelFile, em: StateSpace, inp: str, Z: np.ndarray, w: np.ndarray
                    ) -> dict[str, tuple[np.ndarray, str]]:
    """name -> (history (n_t,), unit) of every gauge port, for states Z (n_x, n_t) of ``em``
    driven by input ``inp`` = w (1, n_t) (the other inputs zero)."""
    j = em.col(inp)
    out = {}
    for name, unit in gauge_ports(mf).items():
        i = em.rows(name)[0]
        out[name] = (em.C[i] @ Z + em.D[i, j] * w[0], unit)
    return out


@lru_cache(maxsize=4)
def _cached(path: str, mtime: float) -> StressModes | None:
    return read_stress_modes(path)


def stress_modes_of(mf: ModelFile) -> StressModes | None:
    """The file's stress modes (None when it has none), read once per file version."""
    path = Path(mf.path)
    return _cached(str(path.resolve()), path.stat().st_mtime)


def _coordinates(sm: StressModes, em: StateSpace, inp: str, Z: np.ndarray, w: np.ndarray
                 ) -> np.ndarray | None:
    """(n_b + n_c, n_t): eta_k(t) of ``em``'s modal states, then u_j(t); None when ``em`` has
    no modal states matching the stress modes."""
    idx = em.modal_indices()
    if idx is None or len(idx[0]) != sm.n_basis:
        return None
    u = np.zeros((sm.n_correction, Z.shape[1]))
    if sm.n_correction:
        u[sm.input_names.index(inp)] = w[0]
    return np.vstack([Z[idx[0]], u])


def stress_history(sm: StressModes, q: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(len(points), 6, n_t) Pa: the stress at mesh ``points`` (indices) for coordinates q."""
    return np.einsum("pks,st->pkt", sm.stress[points], q)


@dataclass(frozen=True)
class StressPeak:
    """Peak von Mises stress over a run.

    peak (n_p,) Pa and peak_time (n_p,) s at every mesh point; hot_spot: index of the point
    with the largest peak, at ``points[hot_spot]`` (m), value ``peak[hot_spot]`` at
    ``peak_time[hot_spot]``; field_at_peak (n_p, 6) Pa: the whole stress field at that
    instant; instants (n_i,) s and fields (n_i, n_p, 6) Pa: the field at requested instants.
    """

    peak: np.ndarray
    peak_time: np.ndarray
    hot_spot: int
    point: np.ndarray
    field_at_peak: np.ndarray
    instants: np.ndarray
    fields: np.ndarray

    @property
    def value(self) -> float:
        return float(self.peak[self.hot_spot])

    @property
    def time(self) -> float:
        return float(self.peak_time[self.hot_spot])


def peak_stress(sm: StressModes, em: StateSpace, inp: str, t: np.ndarray, Z: np.ndarray,
                w: np.ndarray, instants=()) -> StressPeak | None:
    """Per-point peak von Mises stress of a run (states Z (n_x, n_t) of ``em``, input
    ``inp`` = w (1, n_t) at times t) and the fields at ``instants`` (s, nearest sample);
    None when ``em`` is not the modal plant of the stress modes."""
    q = _coordinates(sm, em, inp, Z, w)
    if q is None:
        return None
    n_p = sm.points.shape[0]
    peak, when = np.empty(n_p), np.empty(n_p, dtype=np.int64)
    for start in range(0, n_p, CHUNK):
        pts = np.arange(start, min(start + CHUNK, n_p))
        vm = von_mises(stress_history(sm, q, pts).transpose(0, 2, 1))  # (chunk, n_t)
        when[pts] = np.argmax(vm, axis=1)
        peak[pts] = vm[np.arange(pts.size), when[pts]]
    hot = int(np.argmax(peak))
    k = int(when[hot])
    at = lambda i: np.einsum("pks,s->pk", sm.stress, q[:, i])  # noqa: E731
    idx = [int(np.argmin(np.abs(t - ti))) for ti in instants]
    fields = np.stack([at(i) for i in idx]) if idx else np.zeros((0, n_p, 6))
    return StressPeak(peak, t[when], hot, sm.points[hot], at(k), t[idx] if idx else np.zeros(0),
                      fields)


def add_stress_outputs(run, mf: ModelFile, em: StateSpace, inp: str, Z: np.ndarray,
                       w: np.ndarray, instants=()) -> None:
    """Add to a step run (``run``: pipeline.apps.simulate.results.Run) the gauge histories
    (signals ``<gauge>``, unit 1 or Pa) and, when the file has stress modes, the peak von
    Mises stress: measured ``peak_von_mises`` (Pa), ``peak_von_mises_time`` (s),
    ``hot_spot_x|y|z`` (m), and ``run.info["stress_peak"]`` (:class:`StressPeak`)."""
    for name, (values, unit) in gauge_histories(mf, em, inp, Z, w).items():
        run.signals[name] = values
        run.units[name] = unit
    sm = stress_modes_of(mf)
    if sm is None:
        return
    peak = peak_stress(sm, em, inp, run.t, Z, w, instants)
    if peak is None:
        return
    run.info["stress_peak"] = peak
    run.measured.update(peak_von_mises=peak.value, peak_von_mises_time=peak.time,
                        hot_spot_x=float(peak.point[0]), hot_spot_y=float(peak.point[1]),
                        hot_spot_z=float(peak.point[2]))
    run.signals["von_mises_at_hot_spot"] = von_mises(
        stress_history(sm, _coordinates(sm, em, inp, Z, w), np.array([peak.hot_spot]))[0].T)
    run.units["von_mises_at_hot_spot"] = "Pa"


def stress_peak_datasets(group: str, peak: StressPeak) -> dict:
    """Result-file datasets of a run's stress peak under ``<group>/stress/``."""
    from pipeline.store.layout import result_stress
    from pipeline.store.tree import Dataset

    g = result_stress(group)
    a = g.attr
    attrs = {a.hot_spot_index: peak.hot_spot, a.hot_spot_point_m: peak.point.tolist(),
             a.peak_von_mises_pa: peak.value, a.peak_time_s: peak.time,
             a.voigt_order: ["xx", "yy", "zz", "yz", "xz", "xy"]}
    tree = {
        g.peak_von_mises: Dataset(peak.peak, "Pa", "largest von Mises stress of the run "
                                  "at every mesh point", attrs),
        g.peak_time: Dataset(peak.peak_time, "s", "instant of each point's peak"),
        g.field_at_hot_spot_peak: Dataset(peak.field_at_peak, "Pa", "stress field (n_points, "
                                          "6) at the instant of the hot spot's peak"),
    }
    if peak.instants.size:
        tree[g.instants] = Dataset(peak.instants, "s", "requested instants (nearest sample)")
        tree[g.fields] = Dataset(peak.fields, "Pa", "stress field (n_instants, n_points, 6)")
    return tree


def plot_stress(path: Path, scenario_result, model_path: Path | None = None) -> list[Path]:
    """``<stem>.<scenario>.stress.png``: gauge histories and the von Mises stress at the hot
    spot, its peak marked (value, place, instant); and, with the ``model_path`` and a stress
    peak, ``<stem>.<scenario>.peak_von_mises.png``: each point's peak drawn on the body.
    Nothing when the runs have neither gauges nor a stress peak."""
    runs = [r for r in scenario_result.runs
            if "stress_peak" in r.info or any(u in ("1", "Pa") for u in r.units.values())]
    if not runs:
        return []
    # deferred: heavy, only needed when plots are asked for; a Figure of its own (no
    # pyplot), so the host's matplotlib backend and open figures are left alone
    from matplotlib.figure import Figure

    from pipeline._util.atomic import atomic_path

    run = runs[0]
    gauges = [n for n, u in run.units.items() if u in ("1", "Pa") and n != "von_mises_at_hot_spot"]
    fig = Figure(figsize=(10, 6.2))
    axes = fig.subplots(2, 1, sharex=True)
    strains = [n for n in gauges if run.units[n] == "1"]
    stresses = [n for n in gauges if run.units[n] == "Pa"]
    ax_strain = axes[0]
    ax_stress = axes[0].twinx() if strains and stresses else axes[0]
    for i, n in enumerate(strains):
        ax_strain.plot(run.t, 1e6 * run.signals[n], lw=1.2, color=f"C{i}", label=n)
    for i, n in enumerate(stresses):
        ax_stress.plot(run.t, 1e-6 * run.signals[n], lw=1.0, ls="--",
                       color=f"C{i + len(strains)}", label=n)
    if strains:
        ax_strain.set_ylabel("strain gauges [micro-strain] (solid)")
    if stresses:
        ax_stress.set_ylabel("stress ports [MPa] (dashed)")
    lines = [h for ax in {ax_strain, ax_stress} for h in ax.get_lines()]
    if lines:
        axes[0].legend(lines, [h.get_label() for h in lines], fontsize=8)
    peak = run.info.get("stress_peak")
    if peak is not None:
        axes[1].plot(run.t, 1e-6 * run.signals["von_mises_at_hot_spot"], color="C3", lw=1.2)
        axes[1].plot([peak.time], [1e-6 * peak.value], "o", color="k")
        p = peak.point
        axes[1].set_title(f"hot spot ({p[0]:.4g}, {p[1]:.4g}, {p[2]:.4g}) m: peak von Mises "
                          f"{peak.value / 1e6:.4g} MPa at t = {peak.time:.4g} s", fontsize=10)
    axes[1].set_ylabel("von Mises at hot spot [MPa]")
    axes[1].set_xlabel("time [s]")
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.suptitle(f"{scenario_result.scenario.name}: stress and strain ({run.model})")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    written = [path]
    if peak is not None and model_path is not None:
        from pipeline.apps.stress_plots import plot_von_mises  # deferred: matplotlib
        from pipeline.store.read import read_stored_mesh

        written.append(plot_von_mises(
            read_stored_mesh(model_path), peak.peak, f"{scenario_result.scenario.name}: peak "
            f"von Mises over the run (hot spot at t = {peak.time:.4g} s)",
            path.with_name(path.name.replace(".stress.png", ".peak_von_mises.png"))))
    return written
