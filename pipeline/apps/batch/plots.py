"""The plots of a batch report (matplotlib, Agg canvas, no pyplot state), as PNG bytes.

* ``freq_vs_<key>.png`` for each swept key: one panel per combination of the other swept
  keys (at most ``MAX_PANELS``), one line per mode label, frequency [Hz] on a log scale;
* ``freq_by_case.png`` when the batch lists explicit cases;
* ``convergence.png``: cases that differ only in ``mesh.*``: each frequency relative to
  the finest mesh (%) and the relative change |f_i - f_(i-1)| / f_i between successive
  meshes, against DOFs (log scales);
* ``bode.png``: |H(j 2 pi f)| of every reduced model, position outputs, overlaid (at most
  ``MAX_PAIRS`` input/output pairs).

Modes are matched across cases by their label (``bending_y_1``...), not their index, so
a mode that appears only in some variants (in-plane constraint) does not shift the rest.
Each plot function takes the finished :class:`~pipeline.apps.batch.outcome.CaseOutcome`
list and returns ``(title, figure, file name)`` or None.
"""

from __future__ import annotations

import io
import json
import logging
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline.apps.batch.cache import CaseRecord
from pipeline.apps.batch.gains import bode_magnitude, position_rows, ratio_unit
from pipeline.store.read import StoredModels
from pipeline.apps.batch.outcome import CaseOutcome
from pipeline.config import config_to_dict

log = logging.getLogger(__name__)

__all__ = [
    "ConvergenceRow",
    "Figure",
    "case_values",
    "convergence_groups",
    "convergence_rows",
    "label_order",
    "lookup",
    "mode_frequencies",
    "plot_bode",
    "plot_convergence",
    "plot_frequency_by_case",
    "plot_frequency_vs_parameter",
    "png_bytes",
    "value_text",
]

MAX_PANELS = 6
MAX_PAIRS = 4
Figure = tuple[str, Any, str]  # (title, matplotlib Figure, PNG file name)


# --------------------------------------------------------------------------- values
def lookup(data: Any, path: str) -> Any:
    """The value at a dotted key path (``supports[0].fix``, ``mesh.size``) of plain data;
    None when absent."""
    node = data
    for part in [p for p in re.split(r"\.|\[(\d+)\]", path) if p]:
        if isinstance(node, dict):
            node = node.get(part)
        elif isinstance(node, list) and part.isdigit() and int(part) < len(node):
            node = node[int(part)]
        else:
            return None
        if node is None:
            return None
    return node


def value_text(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, str):
        return value
    return json.dumps(value)


def is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def case_values(outcome: CaseOutcome, keys: Sequence[str]) -> dict[str, Any]:
    """The resolved value of every dotted key of ``keys`` in the case's config."""
    data = config_to_dict(outcome.case.config)
    return {k: lookup(data, k) for k in keys}


def mode_frequencies(record: CaseRecord) -> dict[str, float]:
    """Frequency (Hz) of every mode, keyed by label (label#2 for a repeated label)."""
    freqs = record.frequencies_hz or ()
    labels = record.mode_labels or [f"mode_{i + 1}" for i in range(len(freqs))]
    out: dict[str, float] = {}
    for f, lab in zip(freqs, labels):
        name, n = lab, 2
        while name in out:
            name, n = f"{lab}#{n}", n + 1
        out[name] = float(f)
    return out


def label_order(records: Iterable[CaseRecord]) -> list[str]:
    """Mode labels of all records, lowest mean frequency first."""
    seen: dict[str, list[float]] = {}
    for r in records:
        for lab, f in mode_frequencies(r).items():
            seen.setdefault(lab, []).append(f)
    return sorted(seen, key=lambda k: float(np.mean(seen[k])))



# --------------------------------------------------------------------------- plots
def _figure(ncols: int, nrows: int = 1, width: float = 4.6, height: float = 3.6):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(max(6.0, width * ncols), height * nrows), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, squeeze=False)
    return fig, axes


def _colors(n: int):
    from matplotlib import colormaps

    cmap = colormaps["tab10" if n <= 10 else "tab20"]
    return [cmap(i % cmap.N) for i in range(n)]


def group_title(values: dict[str, Any]) -> str:
    return ", ".join(f"{k}={value_text(v)}" for k, v in values.items()) or "all cases"


def plot_frequency_vs_parameter(ok: list[CaseOutcome], sweep_keys: Sequence[str]) -> list[Figure]:
    """One figure per swept key: modes (by label) against its value; one panel per
    combination of the other swept keys."""
    figures: list[Figure] = []
    if not ok:
        return figures
    labels = label_order(o.record for o in ok)
    colors = dict(zip(labels, _colors(len(labels))))
    for key in sweep_keys:
        others = [k for k in sweep_keys if k != key]
        groups: dict[str, list] = {}
        titles: dict[str, str] = {}
        for o in ok:
            vals = case_values(o, list(sweep_keys))
            gid = json.dumps([vals[k] for k in others])
            groups.setdefault(gid, []).append((vals[key], o))
            titles[gid] = group_title({k: vals[k] for k in others})
        gids = list(groups)[:MAX_PANELS]
        fig, axes = _figure(len(gids))
        for ax, gid in zip(axes[0], gids):
            points = groups[gid]
            numeric = all(is_number(x) for x, _ in points)
            if numeric:
                xs = [float(x) for x, _ in points]
                positive = min(xs) > 0
                if positive and max(xs) / min(xs) >= 4:
                    ax.set_xscale("log")
            else:
                cats = list(dict.fromkeys(value_text(x) for x, _ in points))
                xs = [cats.index(value_text(x)) for x, _ in points]
                ax.set_xticks(range(len(cats)), cats)
            order = np.argsort(xs, kind="stable")
            for lab in labels:
                pts = [(xs[i], mode_frequencies(points[i][1].record).get(lab)) for i in order]
                pts = [(x, f) for x, f in pts if f is not None]
                if pts:
                    ax.plot(*zip(*pts), "o-", color=colors[lab], label=lab, ms=4, lw=1.2)
            ax.set_xlabel(key_label(key))
            ax.set_ylabel("f [Hz]")
            ax.set_yscale("log")
            ax.grid(True, which="both", alpha=0.3)
            ax.set_title(titles[gid], fontsize=9)
        _legend(fig, axes)
        fig.suptitle(f"Natural frequencies against {key}", fontsize=11)
        name = "freq_vs_" + re.sub(r"[^A-Za-z0-9_.-]+", "_", key) + ".png"
        figures.append((f"Frequencies against {key}", fig, name))
        if len(groups) > MAX_PANELS:
            log.info("report: %s: showing %d of %d panels", name, MAX_PANELS, len(groups))
    return figures


#: SI unit of a swept config key, by its last part (geometry.height -> m)
KEY_UNITS = {"length": "m", "height": "m", "depth": "m", "width": "m", "radius": "m",
             "thickness": "m", "size": "m", "scale": "1", "E": "Pa", "nu": "1",
             "rho": "kg/m^3", "ratio": "1", "alpha": "1/s", "beta": "s", "cutoff_hz": "Hz",
             "count": "1", "order": "1", "modes": "1", "elements": "1", "tolerance": "1"}


def key_label(key: str) -> str:
    """Axis label of a swept config key: ``geometry.height [m]``."""
    unit = KEY_UNITS.get(key.rsplit(".", 1)[-1].split("[")[0])
    return f"{key} [{unit}]" if unit else key


def plot_frequency_by_case(ok: list[CaseOutcome]) -> Figure | None:
    if not ok:
        return None
    labels = label_order(o.record for o in ok)
    colors = dict(zip(labels, _colors(len(labels))))
    fig, axes = _figure(1, width=max(6.0, 0.55 * len(ok) + 3))
    ax = axes[0][0]
    for lab in labels:
        pts = [(i, mode_frequencies(o.record).get(lab)) for i, o in enumerate(ok)]
        pts = [(x, f) for x, f in pts if f is not None]
        if pts:
            ax.plot(*zip(*pts), "o", color=colors[lab], label=lab, ms=5)
    ax.set_xticks(range(len(ok)), [f"{o.case.index}: {o.case.label}" for o in ok], rotation=30,
                  ha="right", fontsize=8)
    ax.set_yscale("log")
    ax.set_ylabel("f [Hz]")
    ax.grid(True, which="both", alpha=0.3)
    _legend(fig, axes)
    fig.suptitle("Natural frequencies of every case", fontsize=11)
    return ("Frequencies by case", fig, "freq_by_case.png")


def convergence_groups(ok: list[CaseOutcome]) -> list[tuple[str, list[CaseOutcome]]]:
    """Cases that differ only in ``mesh.*`` (at least two distinct DOF counts), each
    sorted by DOFs, titled by what sets the group apart."""
    groups: dict[str, list] = {}
    for o in ok:
        data = config_to_dict(o.case.config)
        data.pop("mesh", None)
        groups.setdefault(json.dumps(data, sort_keys=True, default=str), []).append(o)
    out = []
    for members in groups.values():
        dofs = {o.record.n_dofs for o in members}
        if len(dofs) < 2:
            continue
        members = sorted(members, key=lambda o: o.record.n_dofs or 0)
        first = members[0]
        items = [(k, v) for k, v in first.case.overrides if not k.startswith("mesh.")]
        out.append((group_title(dict(items)), members))
    return out


@dataclass(frozen=True)
class ConvergenceRow:
    """One mode of a convergence group: its frequency on the finest mesh and the relative
    change |f_finest - f_previous| / f_finest from the previous mesh (None: not there)."""

    group: str
    mode: str
    f_hz: float
    dofs: int | None
    rel_change: float | None


def convergence_rows(groups: list[tuple[str, list[CaseOutcome]]]) -> list[ConvergenceRow]:
    """Per group and mode: frequency on the finest mesh and its relative change from the
    previous mesh."""
    rows = []
    for title, members in groups:
        labels = label_order(o.record for o in members)
        fine, prev = members[-1], members[-2]
        for lab in labels:
            f1 = mode_frequencies(fine.record).get(lab)
            f0 = mode_frequencies(prev.record).get(lab)
            if f1 is None:
                continue
            rows.append(ConvergenceRow(title, lab, f1, fine.record.n_dofs,
                                       None if f0 is None else abs(f1 - f0) / abs(f1)))
    return rows


def plot_convergence(groups: list[tuple[str, list[CaseOutcome]]]) -> Figure | None:
    """Per group: each frequency relative to the finest mesh (%) and the relative change
    between successive meshes, against DOFs (log)."""
    if not groups:
        return None
    groups = groups[:MAX_PANELS]
    labels = label_order(o.record for _, members in groups for o in members)
    colors = dict(zip(labels, _colors(len(labels))))
    fig, axes = _figure(len(groups), 2, height=3.3)
    for col, (title, members) in enumerate(groups):
        top, bottom = axes[0][col], axes[1][col]
        bottom.sharex(top)
        dofs = [float(o.record.n_dofs) for o in members]
        for lab in labels:
            f = [mode_frequencies(o.record).get(lab) for o in members]
            if f[-1] is not None:
                dev = [(n, 100.0 * (v / f[-1] - 1.0)) for n, v in zip(dofs, f) if v is not None]
                top.plot(*zip(*dev), "o-", color=colors[lab], label=lab, ms=4, lw=1.2)
            rel = [(dofs[i], max(abs(f[i] - f[i - 1]) / abs(f[i]), 1e-12))
                   for i in range(1, len(f)) if f[i] is not None and f[i - 1] is not None]
            if rel:
                bottom.plot(*zip(*rel), "o-", color=colors[lab], label=lab, ms=4, lw=1.2)
        top.set_xscale("log")
        top.set_title(title, fontsize=9)
        top.set_ylabel("f / f(finest mesh) - 1 [%]")
        bottom.set_yscale("log")
        bottom.set_xlabel("DOFs [1]")
        bottom.set_ylabel("|f - f(previous mesh)| / f [1]")
        for ax in (top, bottom):
            ax.grid(True, which="both", alpha=0.3)
        _ticks_at(bottom, dofs)
        top.tick_params(labelbottom=False)
    _legend(fig, axes)
    fig.suptitle("Convergence with mesh refinement", fontsize=11)
    return ("Convergence with mesh refinement", fig, "convergence.png")


def plot_bode(ok: list[CaseOutcome], models: dict[str, StoredModels]) -> Figure | None:
    cases = [o for o in ok if o.case.key in models and position_rows(models[o.case.key])]
    if not cases:
        return None
    retained = [models[o.case.key].retained_frequencies_hz for o in cases]
    f_lo = min(float(np.min(f)) if f.size else 1.0 for f in retained)
    f_hi = max(float(np.max(f)) if f.size else 1e3 for f in retained)
    f = np.logspace(np.log10(max(f_lo / 10, 1e-3)), np.log10(f_hi * 3), 600)
    pairs: list[tuple[str, str]] = []
    curves = []
    for o in cases:
        mags = bode_magnitude(models[o.case.key], f)
        curves.append((o, mags))
        pairs += [p for p in mags if p not in pairs]
    pairs = pairs[:MAX_PAIRS]
    longest = max(len(f"{o.case.index}: {o.case.label}") for o in cases)
    fig, axes = _figure(len(pairs), width=max(4.6, (4.0 + 0.13 * longest) / len(pairs)))
    colors = _colors(len(cases))
    for ax, pair in zip(axes[0], pairs):
        for i, (color, (o, mags)) in enumerate(zip(colors, curves)):
            if pair in mags:  # dashes tell apart models that lie on one another
                ax.loglog(f, mags[pair], color=color, lw=1.2, ls=("-", "--", ":", "-.")[i % 4],
                          label=f"{o.case.index}: {o.case.label}")
        ax.set_title(f"{pair[0]} -> {pair[1]}", fontsize=9)
        ax.set_xlabel("f [Hz]")
        units = {ratio_unit(models[o.case.key], *pair) for o, mags in curves if pair in mags}
        ax.set_ylabel(f"|H| [{units.pop() if len(units) == 1 else 'SI output/input'}]")
        ax.grid(True, which="both", alpha=0.3)
    _legend(fig, axes, fontsize=7 if len(cases) > 8 else 8, ncols=2 if len(pairs) == 1 else 3)
    fig.suptitle("Reduced models: Bode magnitude (position outputs)", fontsize=11)
    return ("Reduced models: Bode magnitude", fig, "bode.png")


def _legend(fig, axes, fontsize: int = 8, ncols: int = 5) -> None:
    handles, labels = {}, []
    for ax in np.ravel(axes):
        for h, lab in zip(*ax.get_legend_handles_labels()):
            if lab not in handles:
                handles[lab] = h
                labels.append(lab)
    if labels:
        fig.legend([handles[k] for k in labels], labels, loc="outside lower center",
                   fontsize=fontsize, ncols=max(1, min(ncols, len(labels))), frameon=False)


def _ticks_at(ax, values: Sequence[float]) -> None:
    """x ticks at the data (DOF counts), labelled as plain integers; no minor labels."""
    from matplotlib.ticker import NullFormatter

    values = sorted(set(values))
    ax.set_xticks(values, [f"{int(v)}" for v in values], rotation=30, ha="right", fontsize=8)
    ax.xaxis.set_minor_formatter(NullFormatter())


def png_bytes(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    return buf.getvalue()

