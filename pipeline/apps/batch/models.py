"""The reduced model of a case file, as the batch report uses it: read, DC gains, Bode.

The model is ``x' = A x + B u``, ``y = C x + D u`` (SI units: inputs in N or N m, outputs
position / velocity / acceleration of every output port); ``A`` (n x n), ``B`` (n x m),
``C`` (p x n), ``D`` (p x m). DC gains and frequency responses are computed with
python-control (deferred import).
"""

from __future__ import annotations

import logging
import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

# TODO(store.read): import open_verified, read_strings from pipeline.store.read once it
# re-exports them explicitly
from pipeline.store.read import open_verified, read_strings

log = logging.getLogger(__name__)

__all__ = ["ReducedModel", "bode_magnitude", "dc_gains", "position_rows", "read_statespace"]


@dataclass(frozen=True, eq=False)
class ReducedModel:
    """A, B, C, D, port names, mode frequencies (Hz) and the exact static compliance
    (rows: output ports, columns: inputs) of a case file's reduced model."""

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray
    input_names: tuple[str, ...]
    output_names: tuple[str, ...]
    frequencies_hz: np.ndarray                  # (n_modes,), may be empty
    static_compliance: np.ndarray | None = None  # (n_ports, m)
    compliance_rows: tuple[str, ...] = ()
    input_units: tuple[str, ...] = ()   # SI unit per input (N, N m)
    output_units: tuple[str, ...] = ()  # SI unit of the position of every output port

    def ratio_unit(self, inp: str, out: str) -> str:
        """Unit of |H| from input ``inp`` to position output ``out`` ('1' if unknown)."""
        rows = [n for _, n in position_rows(self)]
        i, k = self.input_names.index(inp), rows.index(out) if out in rows else -1
        if 0 <= k < len(self.output_units) and i < len(self.input_units):
            return f"{self.output_units[k]}/{self.input_units[i]}"
        return "1"


def read_statespace(path: str | Path, group: str = "statespace") -> ReducedModel | None:
    """The reduced model of a case file, or None when it has none or cannot be read (a
    report never fails on one file: a warning names the file and the reason)."""
    try:
        with open_verified(path, verify_checksum=False) as h5:
            if group not in h5 or "A" not in h5[group]:
                return None
            g = h5[group]
            mats = {k: np.asarray(g[k][()], dtype=float) for k in ("A", "B", "C", "D")}
            freqs = np.atleast_1d(g["frequencies_hz"][()]) if "frequencies_hz" in g \
                else np.zeros(0)
            compliance, rows = None, ()
            if "static_compliance" in g:
                sc = g["static_compliance"]
                compliance = np.atleast_2d(sc[()])
                rows = tuple(read_strings(sc.attrs["rows"])) if "rows" in sc.attrs else ()
            return ReducedModel(**mats, input_names=tuple(read_strings(g["input_names"])),
                                output_names=tuple(read_strings(g["output_names"])),
                                frequencies_hz=freqs, static_compliance=compliance,
                                compliance_rows=rows,
                                input_units=tuple(read_strings(g.attrs.get("input_units", []))),
                                output_units=tuple(read_strings(g.attrs.get("output_units",
                                                                            []))))
    except Exception as exc:  # FileFormatError, or a foreign layout (KeyError, ...)
        log.warning("report: cannot read %s from %s: %s", group, path,
                    " ".join(str(exc).split())[:200])
        return None


def position_rows(ss: ReducedModel) -> list[tuple[int, str]]:
    """(row, name) of every position output."""
    return [(i, n) for i, n in enumerate(ss.output_names) if n.endswith("/position")]


def dc_gains(ss: ReducedModel) -> dict[str, float]:
    """``dc_gain[input->output/position]`` of the reduced model (python-control); where
    the model has no finite static gain (rigid-body modes) the stored exact static
    compliance is used when present."""
    import control as ct  # deferred: python-control is slow to import

    rows = position_rows(ss)
    if not rows:
        return {}
    n_out, n_in = ss.C.shape[0], ss.B.shape[1]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            gain = np.reshape(np.asarray(ct.dcgain(ct.ss(ss.A, ss.B, ss.C, ss.D)), dtype=float),
                              (n_out, n_in))
        except Exception:
            gain = np.full((n_out, n_in), np.nan)
    out = {}
    for i, name in rows:
        for j, inp in enumerate(ss.input_names):
            value = float(gain[i, j])
            if not math.isfinite(value) and ss.static_compliance is not None:
                port = name[: -len("/position")]
                if port in ss.compliance_rows:
                    value = float(ss.static_compliance[ss.compliance_rows.index(port), j])
            out[f"dc_gain[{inp}->{name}]"] = value
    return out


def bode_magnitude(ss: ReducedModel, f_hz: np.ndarray) -> dict[tuple[str, str], np.ndarray]:
    """|H(j 2 pi f)| of every (input, position output) pair (python-control)."""
    import control as ct  # deferred: python-control is slow to import

    rows = position_rows(ss)
    if not rows:
        return {}
    sys = ct.ss(ss.A, ss.B, ss.C, ss.D)
    resp = ct.frequency_response(sys, 2 * np.pi * np.asarray(f_hz), squeeze=False)
    mag = np.asarray(resp.magnitude)
    return {(inp, name): mag[i, j] for i, name in rows for j, inp in enumerate(ss.input_names)}
