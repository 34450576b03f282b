"""The report of a batch run: ``summary.csv``, ``report.html`` and the plots as PNG.

Written by :func:`write_outputs` into the batch folder from the case records and the
HDF5 files (read-only):

* ``summary.csv``: one row per case: number, label, status and error, the value of every
  swept or overridden key (as resolved, so every row is filled), DOFs, stage times, peak
  memory and its estimate, the frequencies (``f1_hz`` ...) and mode labels, and the DC
  gains of the reduced model (``dc_gain[input->output/position]``, from /statespace with
  python-control; the exact ``static_compliance`` when the model has rigid-body modes).
* PNG plots (matplotlib, Agg canvas, no pyplot state): ``freq_vs_<key>.png`` for each
  swept key (one panel per combination of the other swept keys, one line per mode
  label), ``freq_by_case.png`` when the batch lists explicit cases, ``convergence.png``
  (cases that differ only in ``mesh.*``: frequency and relative change between
  successive meshes against DOFs, log scales), ``bode.png`` (magnitude of every reduced
  model, position outputs, overlaid).
* ``report.html``: the same plots embedded (base64), the failed cases with their
  messages, the convergence table and a table of all cases.

Modes are matched across cases by their label (``bending_y_1``...), not their index, so
a mode that appears only in some variants (in-plane constraint) does not shift the rest.
"""

from __future__ import annotations

import base64
import csv
import datetime as _dt
import html
import io
import json
import logging
import math
import re
import warnings
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

log = logging.getLogger(__name__)

__all__ = ["write_outputs", "summary_table", "read_statespace", "dc_gains", "bode_magnitude"]

STAGES = ("mesh", "assemble", "modes", "reduce", "write")
PNG_PATTERNS = ("freq_vs_*.png", "freq_by_case.png", "convergence.png", "bode.png")
MAX_PANELS = 6
MAX_PAIRS = 4


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


def _value_text(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, str):
        return value
    return json.dumps(value)


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _case_values(outcome, keys: Sequence[str]) -> dict[str, Any]:
    from pipeline.config import config_to_dict

    data = config_to_dict(outcome.case.config)
    return {k: lookup(data, k) for k in keys}


def _modes(record: dict) -> dict[str, float]:
    """Frequency (Hz) of every mode, keyed by label (label#2 for a repeated label)."""
    freqs = record.get("frequencies_hz") or []
    labels = record.get("mode_labels") or [f"mode_{i + 1}" for i in range(len(freqs))]
    out: dict[str, float] = {}
    for f, lab in zip(freqs, labels):
        name, n = lab, 2
        while name in out:
            name, n = f"{lab}#{n}", n + 1
        out[name] = float(f)
    return out


def _label_order(records: Iterable[dict]) -> list[str]:
    """Mode labels of all records, lowest mean frequency first."""
    seen: dict[str, list[float]] = {}
    for r in records:
        for lab, f in _modes(r).items():
            seen.setdefault(lab, []).append(f)
    return sorted(seen, key=lambda k: float(np.mean(seen[k])))


# --------------------------------------------------------------------------- models
def read_statespace(path: str | Path, group: str = "statespace") -> dict | None:
    """A, B, C, D, names and static compliance of a case file's reduced model, or None."""
    from pipeline.store.h5file import open_verified, read_strings

    try:
        with open_verified(path, verify_checksum=False) as h5:
            if group not in h5 or "A" not in h5[group]:
                return None
            g = h5[group]
            out = {k: np.asarray(g[k][()], dtype=float) for k in ("A", "B", "C", "D")}
            out["input_names"] = read_strings(g["input_names"])
            out["output_names"] = read_strings(g["output_names"])
            out["frequencies_hz"] = np.atleast_1d(g["frequencies_hz"][()]) \
                if "frequencies_hz" in g else np.zeros(0)
            if "static_compliance" in g:
                sc = g["static_compliance"]
                out["static_compliance"] = np.atleast_2d(sc[()])
                out["compliance_rows"] = read_strings(sc.attrs["rows"]) if "rows" in sc.attrs \
                    else []
            return out
    except Exception as exc:  # a report never fails on one unreadable file
        log.warning("report: cannot read %s from %s: %s", group, path, exc)
        return None


def _position_rows(ss: dict) -> list[tuple[int, str]]:
    return [(i, n) for i, n in enumerate(ss["output_names"]) if n.endswith("/position")]


def dc_gains(ss: dict) -> dict[str, float]:
    """``dc_gain[input->output/position]`` of the reduced model (python-control); where
    the model has no finite static gain (rigid-body modes) the stored exact static
    compliance is used when present."""
    import control as ct

    rows = _position_rows(ss)
    if not rows:
        return {}
    n_out, n_in = ss["C"].shape[0], ss["B"].shape[1]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            gain = np.reshape(np.asarray(ct.dcgain(ct.ss(ss["A"], ss["B"], ss["C"], ss["D"])),
                                         dtype=float), (n_out, n_in))
        except Exception:
            gain = np.full((n_out, n_in), np.nan)
    out = {}
    for i, name in rows:
        for j, inp in enumerate(ss["input_names"]):
            value = float(gain[i, j])
            if not math.isfinite(value) and "static_compliance" in ss:
                port = name[: -len("/position")]
                names = ss.get("compliance_rows") or []
                if port in names:
                    value = float(ss["static_compliance"][names.index(port), j])
            out[f"dc_gain[{inp}->{name}]"] = value
    return out


def bode_magnitude(ss: dict, f_hz: np.ndarray) -> dict[tuple[str, str], np.ndarray]:
    """|H(j 2 pi f)| of every (input, position output) pair (python-control)."""
    import control as ct

    rows = _position_rows(ss)
    if not rows:
        return {}
    sys = ct.ss(ss["A"], ss["B"], ss["C"], ss["D"])
    resp = ct.frequency_response(sys, 2 * np.pi * np.asarray(f_hz), squeeze=False)
    mag = np.asarray(resp.magnitude)
    return {(inp, name): mag[i, j] for i, name in rows
            for j, inp in enumerate(ss["input_names"])}


# --------------------------------------------------------------------------- summary
def summary_table(result) -> tuple[list[str], list[dict[str, Any]], dict[str, dict]]:
    """(columns, rows, state-space models by case key) of the batch."""
    spec = result.spec
    keys = list(spec.case_keys)
    models: dict[str, dict] = {}
    rows = []
    n_freq = max((len(o.record.get("frequencies_hz") or []) for o in result.outcomes), default=0)
    gain_cols: list[str] = []
    stage_cols = list(STAGES)
    for o in result.outcomes:
        for k in (o.record.get("times_s") or {}):
            if k not in stage_cols:
                stage_cols.append(k)
    for o in result.outcomes:
        r = o.record
        row: dict[str, Any] = {"case": o.case.index, "label": o.case.label, "status": o.status,
                               "error": r.get("error", "") if o.status in ("failed", "not run")
                               else ""}
        for k, v in _case_values(o, keys).items():
            row[k] = _value_text(v)
        row.update(n_dofs=r.get("n_dofs"), n_free_dofs=r.get("n_free_dofs"),
                   n_elements=r.get("n_elements"))
        times = r.get("times_s") or {}
        for k in stage_cols:
            row[f"time_{k}_s"] = times.get(k)
        row["time_total_s"] = sum(times.values()) if times else None
        row["wall_s"] = r.get("wall_s")
        row["peak_memory_mb"] = r.get("peak_memory_mb")
        row["memory_estimate_mb"] = None if o.case.memory_bytes is None \
            else o.case.memory_bytes / 1e6
        row["solver"] = r.get("solver", "")
        freqs = r.get("frequencies_hz") or []
        for i in range(n_freq):
            row[f"f{i + 1}_hz"] = freqs[i] if i < len(freqs) else None
        row["mode_labels"] = ";".join(r.get("mode_labels") or [])
        if o.h5 is not None and o.status in ("done", "cached"):
            ss = models.get(o.case.key) or read_statespace(o.h5)
            if ss is not None:
                models[o.case.key] = ss
                for col, value in dc_gains(ss).items():
                    row[col] = value
                    if col not in gain_cols:
                        gain_cols.append(col)
        row["key"] = o.case.key
        row["file"] = f"cases/{o.case.key}.h5" if o.h5 is not None else ""
        rows.append(row)
    columns = (["case", "label", "status", "error"] + keys
               + ["n_dofs", "n_free_dofs", "n_elements"] + [f"time_{k}_s" for k in stage_cols]
               + ["time_total_s", "wall_s", "peak_memory_mb", "memory_estimate_mb", "solver"]
               + [f"f{i + 1}_hz" for i in range(n_freq)] + ["mode_labels"] + gain_cols
               + ["key", "file"])
    return columns, rows, models


def _csv_value(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return "" if math.isnan(value) else repr(value)
    return str(value)


def write_summary_csv(path: Path, columns: Sequence[str], rows: Sequence[dict]) -> Path:
    from pipeline._util.atomic import write_bytes

    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(columns)
    for row in rows:
        writer.writerow([_csv_value(row.get(c)) for c in columns])
    write_bytes(path, buf.getvalue().encode("utf-8"))
    return path


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


def _group_title(values: dict[str, Any]) -> str:
    return ", ".join(f"{k}={_value_text(v)}" for k, v in values.items()) or "all cases"


def plot_frequency_vs_parameter(ok: list, sweep_keys: Sequence[str]) -> list[tuple[str, Any, str]]:
    """One figure per swept key: modes (by label) against its value; one panel per
    combination of the other swept keys."""
    figures: list[tuple[str, Any, str]] = []
    if not ok:
        return figures
    labels = _label_order(o.record for o in ok)
    colors = dict(zip(labels, _colors(len(labels))))
    for key in sweep_keys:
        others = [k for k in sweep_keys if k != key]
        groups: dict[str, list] = {}
        titles: dict[str, str] = {}
        for o in ok:
            vals = _case_values(o, list(sweep_keys))
            gid = json.dumps([vals[k] for k in others])
            groups.setdefault(gid, []).append((vals[key], o))
            titles[gid] = _group_title({k: vals[k] for k in others})
        gids = list(groups)[:MAX_PANELS]
        fig, axes = _figure(len(gids))
        for ax, gid in zip(axes[0], gids):
            points = groups[gid]
            numeric = all(_is_number(x) for x, _ in points)
            if numeric:
                xs = [float(x) for x, _ in points]
                positive = min(xs) > 0
                if positive and max(xs) / min(xs) >= 4:
                    ax.set_xscale("log")
            else:
                cats = list(dict.fromkeys(_value_text(x) for x, _ in points))
                xs = [cats.index(_value_text(x)) for x, _ in points]
                ax.set_xticks(range(len(cats)), cats)
            order = np.argsort(xs, kind="stable")
            for lab in labels:
                pts = [(xs[i], _modes(points[i][1].record).get(lab)) for i in order]
                pts = [(x, f) for x, f in pts if f is not None]
                if pts:
                    ax.plot(*zip(*pts), "o-", color=colors[lab], label=lab, ms=4, lw=1.2)
            ax.set_xlabel(key)
            ax.set_ylabel("frequency [Hz]")
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


def plot_frequency_by_case(ok: list) -> tuple[str, Any, str] | None:
    if not ok:
        return None
    labels = _label_order(o.record for o in ok)
    colors = dict(zip(labels, _colors(len(labels))))
    fig, axes = _figure(1, width=max(6.0, 0.55 * len(ok) + 3))
    ax = axes[0][0]
    for lab in labels:
        pts = [(i, _modes(o.record).get(lab)) for i, o in enumerate(ok)]
        pts = [(x, f) for x, f in pts if f is not None]
        if pts:
            ax.plot(*zip(*pts), "o", color=colors[lab], label=lab, ms=5)
    ax.set_xticks(range(len(ok)), [f"{o.case.index}: {o.case.label}" for o in ok], rotation=30,
                  ha="right", fontsize=8)
    ax.set_yscale("log")
    ax.set_ylabel("frequency [Hz]")
    ax.grid(True, which="both", alpha=0.3)
    _legend(fig, axes)
    fig.suptitle("Natural frequencies of every case", fontsize=11)
    return ("Frequencies by case", fig, "freq_by_case.png")


def convergence_groups(ok: list) -> list[tuple[str, list]]:
    """Cases that differ only in ``mesh.*`` (at least two distinct DOF counts), each
    sorted by DOFs, titled by what sets the group apart."""
    from pipeline.config import config_to_dict

    groups: dict[str, list] = {}
    for o in ok:
        data = config_to_dict(o.case.config)
        data.pop("mesh", None)
        groups.setdefault(json.dumps(data, sort_keys=True, default=str), []).append(o)
    out = []
    for members in groups.values():
        dofs = {o.record.get("n_dofs") for o in members}
        if len(dofs) < 2:
            continue
        members = sorted(members, key=lambda o: o.record.get("n_dofs") or 0)
        first = members[0]
        items = [(k, v) for k, v in first.case.overrides if not k.startswith("mesh.")]
        out.append((_group_title(dict(items)), members))
    return out


def convergence_rows(groups: list[tuple[str, list]]) -> list[dict[str, Any]]:
    """Per group and mode: frequency on the finest mesh and its relative change from the
    previous mesh."""
    rows = []
    for title, members in groups:
        labels = _label_order(o.record for o in members)
        fine, prev = members[-1], members[-2]
        for lab in labels:
            f1, f0 = _modes(fine.record).get(lab), _modes(prev.record).get(lab)
            if f1 is None:
                continue
            rows.append({"group": title, "mode": lab, "f_hz": f1,
                         "dofs": fine.record.get("n_dofs"),
                         "rel_change": None if f0 is None else abs(f1 - f0) / abs(f1)})
    return rows


def plot_convergence(groups: list[tuple[str, list]]) -> tuple[str, Any, str] | None:
    """Per group: each frequency relative to the finest mesh (%) and the relative change
    between successive meshes, against DOFs (log)."""
    if not groups:
        return None
    groups = groups[:MAX_PANELS]
    labels = _label_order(o.record for _, members in groups for o in members)
    colors = dict(zip(labels, _colors(len(labels))))
    fig, axes = _figure(len(groups), 2, height=3.3)
    for col, (title, members) in enumerate(groups):
        top, bottom = axes[0][col], axes[1][col]
        bottom.sharex(top)
        dofs = [float(o.record["n_dofs"]) for o in members]
        for lab in labels:
            f = [_modes(o.record).get(lab) for o in members]
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
        bottom.set_xlabel("DOFs")
        bottom.set_ylabel("|f - f(previous mesh)| / f")
        for ax in (top, bottom):
            ax.grid(True, which="both", alpha=0.3)
        _ticks_at(bottom, dofs)
        top.tick_params(labelbottom=False)
    _legend(fig, axes)
    fig.suptitle("Convergence with mesh refinement", fontsize=11)
    return ("Convergence with mesh refinement", fig, "convergence.png")


def plot_bode(ok: list, models: dict[str, dict]) -> tuple[str, Any, str] | None:
    cases = [o for o in ok if o.case.key in models and _position_rows(models[o.case.key])]
    if not cases:
        return None
    f_lo = min(float(np.min(models[o.case.key]["frequencies_hz"])) if
               models[o.case.key]["frequencies_hz"].size else 1.0 for o in cases)
    f_hi = max(float(np.max(models[o.case.key]["frequencies_hz"])) if
               models[o.case.key]["frequencies_hz"].size else 1e3 for o in cases)
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
        ax.set_xlabel("frequency [Hz]")
        ax.set_ylabel("|H| [output/input, SI]")
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


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    return buf.getvalue()


# --------------------------------------------------------------------------- html
_CSS = """body{font-family:system-ui,sans-serif;margin:2em;max-width:1400px;color:#222}
table{border-collapse:collapse;font-size:13px;margin:0.5em 0 1.5em}
th,td{border:1px solid #ccc;padding:3px 7px;text-align:right}
th{background:#f0f0f0}td.l,th.l{text-align:left}
tr.failed td{background:#fde8e8}tr.cached td{color:#555}
img{max-width:100%;border:1px solid #eee;margin:0.5em 0}
.err{font-family:monospace;white-space:pre-wrap;text-align:left}
.muted{color:#666}"""


def _fmt(value: Any, digits: int = 5) -> str:
    if value is None or value == "":
        return ""
    if isinstance(value, float):
        if math.isnan(value):
            return ""
        return f"{value:.{digits}g}"
    return str(value)


def _table(head: Sequence[str] | None, body: Sequence[Sequence[Any]], left: Sequence[int] = (),
           row_class: Sequence[str] | None = None) -> str:
    h = "".join(f"<th{' class=l' if i in left else ''}>{html.escape(str(c))}</th>"
                for i, c in enumerate(head or ()))
    rows = []
    for r, cells in enumerate(body):
        cls = f" class={row_class[r]}" if row_class and row_class[r] else ""
        tds = "".join(f"<td{' class=l' if i in left else ''}>{html.escape(_fmt(c))}</td>"
                      for i, c in enumerate(cells))
        rows.append(f"<tr{cls}>{tds}</tr>")
    head_row = f"<tr>{h}</tr>" if head else ""
    return f"<table>{head_row}{''.join(rows)}</table>"


def _html(result, columns, rows, figures, conv_rows) -> str:
    from pipeline import __version__

    spec = result.spec
    counts = {s: result.count(s) for s in ("done", "cached", "failed", "not run")}
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>Batch "
             f"{html.escape(spec.name)}</title><style>{_CSS}</style></head><body>",
             f"<h1>Batch {html.escape(spec.name)}</h1>"]
    if spec.description:
        parts.append(f"<p>{html.escape(spec.description)}</p>")
    meta = [("batch file", str(spec.path)), ("base config", spec.base),
            ("overrides for every case", ", ".join(
                f"{k}={v if isinstance(v, str) else json.dumps(v)}" for k, v in spec.common)
             or "none"),
            ("sweep", (", ".join(spec.sweep_keys) + f" ({spec.combine})") if spec.sweep_keys
             else "none"),
            ("cases", f"{len(result.outcomes)}: {counts['done']} computed, {counts['cached']} "
                      f"cached, {counts['failed']} failed"
                      + (f", {counts['not run']} not run" if counts["not run"] else "")),
            ("ran on", result.workers), ("wall time", f"{result.wall_s:.1f} s"),
            ("pipeline", __version__),
            ("written", _dt.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z"))]
    parts.append(_table(None, meta, left=(0, 1)))
    failed = [r for r in rows if r["status"] in ("failed", "not run")]
    parts.append("<h2>Failed cases</h2>")
    if failed:
        parts.append(_table(["case", "label", "status", "error"],
                            [[r["case"], r["label"], r["status"], r["error"]] for r in failed],
                            left=(1, 2, 3)).replace("<td class=l>", "<td class='l err'>"))
    else:
        parts.append("<p class=muted>None: every case finished.</p>")
    for title, _, name, png in figures:
        parts.append(f"<h2>{html.escape(title)}</h2><p class=muted>{html.escape(name)}</p>"
                     f"<img alt='{html.escape(title)}' src='data:image/png;base64,"
                     f"{base64.b64encode(png).decode()}'>")
        if name == "convergence.png" and conv_rows:
            parts.append("<p>Relative change of each frequency between the two finest "
                         "meshes of each group (an estimate of the remaining "
                         "discretisation error):</p>")
            parts.append(_table(["group", "mode", "DOFs", "f [Hz]", "relative change"],
                                [[c["group"], c["mode"], c["dofs"], c["f_hz"],
                                  c["rel_change"]] for c in conv_rows], left=(0, 1)))
    if not figures:
        parts.append("<p class=muted>No plots (no finished case, or matplotlib is not "
                     "installed).</p>")
    show = [c for c in columns if c in ("case", "label", "status") or c in spec.case_keys
            or c in ("n_dofs", "time_total_s", "wall_s", "peak_memory_mb",
                     "memory_estimate_mb", "f1_hz", "f2_hz", "f3_hz")
            or c.startswith("dc_gain[")]
    parts.append("<h2>All cases</h2><p class=muted>Every column is in "
                 "<a href='summary.csv'>summary.csv</a>.</p>")
    parts.append(_table(show, [[r.get(c) for c in show] for r in rows],
                        left=tuple(i for i, c in enumerate(show) if c in ("label", "status")
                                   or c in spec.case_keys),
                        row_class=[{"failed": "failed", "not run": "failed",
                                    "cached": "cached"}.get(r["status"], "") for r in rows]))
    parts.append("</body></html>")
    return "\n".join(parts)


# --------------------------------------------------------------------------- entry
def write_outputs(result) -> dict[str, Path]:
    """Write summary.csv, the PNG plots and report.html into ``result.outdir``."""
    from pipeline._util.atomic import write_bytes

    outdir = Path(result.outdir)
    files: dict[str, Path] = {}
    columns, rows, models = summary_table(result)
    files["summary"] = write_summary_csv(outdir / "summary.csv", columns, rows)
    for pattern in PNG_PATTERNS:
        for old in outdir.glob(pattern):
            old.unlink()
    ok = [o for o in result.outcomes if o.status in ("done", "cached")]
    figures = []
    conv_rows: list[dict] = []
    import importlib.util

    have_mpl = importlib.util.find_spec("matplotlib") is not None
    if not have_mpl:
        log.warning("report: matplotlib is not installed; writing the report without plots")
    if have_mpl and ok:
        made = []
        made += plot_frequency_vs_parameter([o for o in ok if o.case.origin == "sweep"],
                                            result.spec.sweep_keys)
        if any(o.case.origin == "case" for o in result.outcomes):
            made.append(plot_frequency_by_case(ok))
        groups = convergence_groups(ok)
        conv_rows = convergence_rows(groups)
        made.append(plot_convergence(groups))
        made.append(plot_bode(ok, models))
        for item in made:
            if item is None:
                continue
            title, fig, name = item
            png = _png(fig)
            write_bytes(outdir / name, png)
            files[name] = outdir / name
            figures.append((title, fig, name, png))
    text = _html(result, columns, rows, figures, conv_rows)
    write_bytes(outdir / "report.html", text.encode("utf-8"))
    files["report"] = outdir / "report.html"
    return files
