"""The report of a batch run: ``summary.csv``, ``report.html`` and the plots as PNG.

Written by :func:`write_outputs` into the batch folder from the case records and the
HDF5 files (read-only, through :func:`pipeline.apps.batch.gains.case_models`):

* ``summary.csv``: one row per case: number, label, status and error, the value of every
  swept or overridden key (as resolved, so every row is filled), DOFs, stage times [s],
  peak memory and its estimate [MB], the frequencies (``f1_hz`` ...) and mode labels, and
  the DC gains of the reduced model (``dc_gain[input->output/position]``, from
  /statespace with python-control; the exact ``static_compliance`` when the model has
  rigid-body modes).
* the PNG plots of :mod:`pipeline.apps.batch.plots` (when matplotlib is installed);
* ``report.html``: the same plots embedded (base64), the failed cases with their
  messages, the convergence table and a table of all cases.
"""

from __future__ import annotations

import base64
import csv
import datetime as _dt
import html
import importlib.util
import io
import json
import logging
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from pipeline._version import __version__
from pipeline._util.atomic import write_bytes, write_text
from pipeline.apps.batch import plots
from pipeline.apps.batch.gains import case_models, dc_gains
from pipeline.store.read import StoredModels
from pipeline.apps.batch.outcome import BatchResult
from pipeline.apps.batch.plots import ConvergenceRow, case_values, value_text

log = logging.getLogger(__name__)

__all__ = ["PNG_PATTERNS", "STAGES", "summary_table", "write_outputs", "write_summary_csv"]

STAGES = ("mesh", "assemble", "modes", "reduce", "write")
PNG_PATTERNS = ("freq_vs_*.png", "freq_by_case.png", "convergence.png", "bode.png")


# --------------------------------------------------------------------------- summary
def summary_table(result: BatchResult
                  ) -> tuple[list[str], list[dict[str, Any]], dict[str, StoredModels]]:
    """(columns, rows, state-space models by case key) of the batch."""
    spec = result.spec
    keys = list(spec.case_keys)
    models: dict[str, StoredModels] = {}
    rows = []
    n_freq = max((len(o.record.frequencies_hz or ()) for o in result.outcomes), default=0)
    gain_cols: list[str] = []
    stage_cols = list(STAGES)
    for o in result.outcomes:
        for k in (o.record.times_s or {}):
            if k not in stage_cols:
                stage_cols.append(k)
    for o in result.outcomes:
        r = o.record
        row: dict[str, Any] = {"case": o.case.index, "label": o.case.label, "status": o.status,
                               "error": (r.error or "") if o.status in ("failed", "not run")
                               else ""}
        for k, v in case_values(o, keys).items():
            row[k] = value_text(v)
        row.update(n_dofs=r.n_dofs, n_free_dofs=r.n_free_dofs, n_elements=r.n_elements)
        times = r.times_s or {}
        for k in stage_cols:
            row[f"time_{k}_s"] = times.get(k)
        row["time_total_s"] = sum(times.values()) if times else None
        row["wall_s"] = r.wall_s
        row["peak_memory_mb"] = r.peak_memory_mb
        row["memory_estimate_mb"] = None if o.case.memory_bytes is None \
            else o.case.memory_bytes / 1e6
        row["solver"] = r.solver or ""
        freqs = r.frequencies_hz or ()
        for i in range(n_freq):
            row[f"f{i + 1}_hz"] = freqs[i] if i < len(freqs) else None
        row["mode_labels"] = ";".join(r.mode_labels or ())
        if o.h5 is not None and o.status in ("done", "cached"):
            ss = models.get(o.case.key) or case_models(o.h5)
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
    """Write the table as CSV (empty cell: no value; floats in full precision)."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(columns)
    for row in rows:
        writer.writerow([_csv_value(row.get(c)) for c in columns])
    write_bytes(path, buf.getvalue().encode("utf-8"))
    return path



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


def _html(result: BatchResult, columns: Sequence[str], rows: Sequence[dict[str, Any]],
          figures: Sequence[tuple[str, Any, str, bytes]],
          conv_rows: Sequence[ConvergenceRow]) -> str:
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
                                [[c.group, c.mode, c.dofs, c.f_hz, c.rel_change]
                                 for c in conv_rows], left=(0, 1)))
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
def write_outputs(result: BatchResult) -> dict[str, Path]:
    """Write summary.csv, the PNG plots and report.html into ``result.outdir``."""
    outdir = Path(result.outdir)
    files: dict[str, Path] = {}
    columns, rows, models = summary_table(result)
    files["summary"] = write_summary_csv(outdir / "summary.csv", columns, rows)
    for pattern in PNG_PATTERNS:
        for old in outdir.glob(pattern):
            old.unlink()
    ok = [o for o in result.outcomes if o.status in ("done", "cached")]
    figures = []
    conv_rows: list[ConvergenceRow] = []
    have_mpl = importlib.util.find_spec("matplotlib") is not None
    if not have_mpl:
        log.warning("report: matplotlib is not installed; writing the report without plots")
    if have_mpl and ok:
        made = []
        made += plots.plot_frequency_vs_parameter([o for o in ok if o.case.origin == "sweep"],
                                            result.spec.sweep_keys)
        if any(o.case.origin == "case" for o in result.outcomes):
            made.append(plots.plot_frequency_by_case(ok))
        groups = plots.convergence_groups(ok)
        conv_rows = plots.convergence_rows(groups)
        made.append(plots.plot_convergence(groups))
        made.append(plots.plot_bode(ok, models))
        for item in made:
            if item is None:
                continue
            title, fig, name = item
            png = plots.png_bytes(fig)
            write_bytes(outdir / name, png)
            files[name] = outdir / name
            figures.append((title, fig, name, png))
    text = _html(result, columns, rows, figures, conv_rows)
    write_text(outdir / "report.html", text)
    files["report"] = outdir / "report.html"
    return files
