"""Export one model of a result file as an FMU: FMI 2.0 (default) or FMI 3.0, Model
Exchange and Co-Simulation in one archive.

``python -m pipeline export FILE.h5 --to fmu [--model NAME] [--fmi-version 2|3]`` writes
``<stem>.<model>.fmu`` (``/`` of ``connection/<name>`` becomes ``_``): a zip holding

===============================  ==========================================================
entry                            content
===============================  ==========================================================
modelDescription.xml             the variables (:mod:`.fmi2`, :mod:`.fmi3`): states (FMI 2.0
                                 one ScalarVariable each, FMI 3.0 the array ``x``), their
                                 derivatives, the inputs and outputs (our names, SI units),
                                 the tunable parameters ``damping_ratio_<k>`` and
                                 ``filter_cutoff`` (Hz) where the model allows them
                                 (:mod:`.fmu_models`)
binaries/<platform>/<id>.so      the model compiled at export time (``gcc``, or ``$CC``);
                                 C only: it runs without Python
sources/fmu.c, model_data.h      the C sources (the FMI headers come from the importing
sources/buildDescription.xml     tool), so another platform's tool builds it
documentation/index.html         what the model is, its source file
terminalsAndIcons/...xml         FMI 3.0: one terminal per mechanical port (:mod:`.fmi3`)
===============================  ==========================================================

The model is the state space of the file (SI units)::

    x' = A x + B u,     y = C x + D u

``fmu.c`` is ``fmu_core.c`` (the model, the parameters, the exact zero-order-hold step
[[Phi, Gamma], [0, I]] = expm([[A, B], [0, 0]] h)) followed by ``fmi2_api.c`` or
``fmi3_api.c`` (the FMI functions); ``model_data.h`` holds this model's matrices.
Model Exchange: the importer integrates A x + B u; the state nominals are the RMS
response of each state to unit white-noise inputs (:func:`.fmu_models._nominals`).
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
import shutil
import subprocess
import uuid
import zipfile
from importlib import import_module, resources
from pathlib import Path
from xml.sax.saxutils import escape, quoteattr

import numpy as np

from pipeline._util.atomic import atomic_path, private_folder
from pipeline.apps.exports.fmu_models import FmuModel, check_model_name, fmu_model
from pipeline.errors import ConfigError, ResourceError

log = logging.getLogger(__name__)

__all__ = ["export_fmu", "FmuModel", "fmu_model", "fmi_headers", "FMI_VERSIONS",
           "parameters", "unit_definitions", "default_experiment", "variables_section",
           "output_description",
           "identifier"]

#: FMI versions written: the module of each (model description, C functions, platform)
FMI_VERSIONS = {"2": "fmi2", "3": "fmi3"}
#: SI base-unit exponents (kg, m, s, rad) of the units our files use
BASE_UNITS = {"m": {"m": 1}, "m/s": {"m": 1, "s": -1}, "m/s2": {"m": 1, "s": -2},
              "m/s^2": {"m": 1, "s": -2}, "rad": {"rad": 1}, "rad/s": {"rad": 1, "s": -1},
              "rad/s2": {"rad": 1, "s": -2}, "rad/s^2": {"rad": 1, "s": -2},
              "N": {"kg": 1, "m": 1, "s": -2}, "N m": {"kg": 1, "m": 2, "s": -2},
              "N.m": {"kg": 1, "m": 2, "s": -2}, "Hz": {"s": -1}, "s": {"s": 1}, "1": {}}


def check_fmi_version(version) -> str:
    """``version`` as ``"2"`` or ``"3"``; ConfigError naming ``--fmi-version`` else."""
    text = str(version).strip()
    text = {"2.0": "2", "3.0": "3"}.get(text, text)
    if text not in FMI_VERSIONS:
        raise ConfigError(f"export --fmi-version: got {version!r}, expected 2 or 3 (the FMI "
                          "versions this export writes)", key="--fmi-version", value=version,
                          expected="2 | 3")
    return text


# --------------------------------------------------------------------------- shared parts
def parameters(m: FmuModel) -> list[tuple[str, float, str, str]]:
    """(name, start, unit, description) of each tunable parameter, in C order."""
    out = []
    if m.damping is not None:
        d = m.damping
        for k, (mode, w, z) in enumerate(zip(d.mode, d.omega, d.zeta)):
            out.append((f"damping_ratio_{mode}", float(z), "",
                        f"modal damping ratio of mode {mode} ({w / (2 * np.pi):.6g} Hz)"))
    if m.filter is not None:
        out.append(("filter_cutoff", m.filter.cutoff_hz, "Hz",
                    f"cut-off frequency of the {m.filter.kind.replace('_', '-')} output filter"))
    return out


def unit_definitions(m: FmuModel, extra: tuple[str, ...] = ()) -> str:
    """The <UnitDefinitions> element of the units the model uses and ``extra`` ('' without
    any)."""
    units = {u for u in m.input_units + m.output_units + extra if u}
    units |= {p[2] for p in parameters(m) if p[2]}
    if not units:
        return ""
    lines = ["  <UnitDefinitions>"]
    for u in sorted(units):
        base = BASE_UNITS.get(u)
        exps = " ".join(f'{k}="{v}"' for k, v in (base or {}).items())
        lines.append(f"    <Unit name={quoteattr(u)}/>" if base is None else
                     f"    <Unit name={quoteattr(u)}><BaseUnit {exps}/></Unit>" if exps else
                     f"    <Unit name={quoteattr(u)}><BaseUnit/></Unit>")
    lines.append("  </UnitDefinitions>")
    return "\n".join(lines) + "\n"


def default_experiment(m: FmuModel) -> str:
    """<DefaultExperiment>: 10 periods of the lowest frequency, 20 steps per period of
    the highest (frequencies of A's eigenvalues, Hz; 1 Hz without any)."""
    freqs = np.abs(np.linalg.eigvals(m.ss.A)) / (2 * np.pi)
    freqs = freqs[freqs > 1e-6 * max(float(freqs.max(initial=0.0)), 1e-300)]
    f_lo, f_hi = (float(freqs.min()), float(freqs.max())) if freqs.size else (1.0, 1.0)
    return (f'  <DefaultExperiment startTime="0" stopTime="{10.0 / f_lo:.6g}" '
            f'stepSize="{1.0 / (20.0 * f_hi):.6g}"/>\n')


def variables_section(m: FmuModel, rows: list[str]) -> str:
    """<LogCategories>, <DefaultExperiment> and <ModelVariables> (the ``rows``): the part
    of the model description FMI 2.0 and 3.0 write alike."""
    return ('  <LogCategories>\n    <Category name="logStatusError"/>\n  </LogCategories>\n'
            + default_experiment(m) + "  <ModelVariables>\n" + "\n".join(rows)
            + "\n  </ModelVariables>\n")


#: what the connection-point model's signal suffixes are
_SIGNALS = {"a": "acceleration", "alpha": "angular acceleration", "F": "force", "T": "moment"}


def output_description(name: str) -> str:
    """A short description of the output ``name``: ``<port>/<quantity>`` (and the lumped
    chain's ``<port>_<quantity>``) -> ``<quantity> of <port>``; the connection model's
    ``<point>.<signal><axis>`` -> ``<signal> <axis> at <point>``."""
    port, sep, quantity = name.rpartition("/")
    if sep:
        return f"{quantity} of {port}"
    port, sep, quantity = name.rpartition("_")  # the lumped chain: tip_position ...
    if sep and quantity in ("position", "velocity", "acceleration"):
        return f"{quantity} of {port}"
    point, sep, signal = name.rpartition(".")
    kind = next((v for k, v in _SIGNALS.items() if signal.rstrip("xyz_") == k), None)
    return f"{kind} {signal[-1]} at {point}" if sep and kind else "output"


def description(m: FmuModel, source: str) -> str:
    nx = m.ss.A.shape[0]
    return (f"{m.model} model of {source}: x' = A x + B u, y = C x + D u ({nx} states); "
            "co-simulation steps are exact for inputs held over the step (zero-order hold)")


def identifier(name: str, model: str) -> str:
    """The modelIdentifier (a C name) of ``model`` of the file ``name``."""
    ident = re.sub(r"[^A-Za-z0-9_]", "_", f"{name}_{model}")
    return ident if ident[0].isalpha() else "m_" + ident


def _c_array(name: str, values, ctype: str = "double") -> str:
    values = list(np.asarray(values).ravel())
    if not values:
        values = [0]
    fmt = (lambda v: repr(float(v))) if ctype == "double" else (lambda v: str(int(v)))
    body = ",\n    ".join(", ".join(fmt(v) for v in values[i:i + 4])
                          for i in range(0, len(values), 4))
    return f"static const {ctype} {name}[] = {{\n    {body}}};\n"


def model_data_header(m: FmuModel, guid: str) -> str:
    """``model_data.h``: sizes, matrices (row major, 17 significant digits), the token."""
    ss, p, d, f = m.ss, m.plant, m.damping, m.filter
    nx, nu, ny = ss.A.shape[0], ss.B.shape[1], ss.C.shape[0]
    nxp, nyp = p.A.shape[0], p.C.shape[0]
    nz = 0 if d is None else len(d.vcol)
    nf = 0 if f is None else f.A_f1.shape[0]
    A_base, C_base = (p.A, p.C) if d is None else (d.A_base, d.C_base)
    out = [f"/* model data of {m.name} ({m.model}): generated by pipeline.apps.exports.fmu */\n",
           f"#define MODEL_GUID \"{guid}\"\n#define NX {nx}\n#define NU {nu}\n#define NY {ny}\n",
           f"#define NXP {nxp}\n#define NYP {nyp}\n#define NZ {nz}\n#define NF {nf}\n",
           f"#define NFIN {0 if f is None else len(f.rows)}\n",
           _c_array("A_BASE", A_base), _c_array("B_P", p.B), _c_array("C_BASE", C_base),
           _c_array("D_P", p.D), _c_array("GA", np.zeros(0) if d is None else d.GA),
           _c_array("GC", np.zeros(0) if d is None else d.GC),
           _c_array("VCOL", () if d is None else d.vcol, "int"),
           _c_array("PAR0", [v for _, v, _, _ in parameters(m)]),
           _c_array("AF1", np.zeros(0) if f is None else f.A_f1),
           _c_array("BF1", np.zeros(0) if f is None else f.B_f1),
           _c_array("CF1", np.zeros(0) if f is None else f.C_f1),
           _c_array("CF_POW", () if f is None else f.pow, "int"),
           _c_array("FIN_ROW", () if f is None else f.rows, "int"),
           _c_array("X0", np.zeros(nx)), _c_array("NOMINAL", m.nominals)]
    return "".join(out)


BUILD_DESCRIPTION = """<?xml version="1.0" encoding="UTF-8"?>
<fmiBuildDescription fmiVersion="3.0">
  <BuildConfiguration modelIdentifier="{identifier}">
    <SourceFileSet language="C99">
      <SourceFile name="fmu.c"/>
    </SourceFileSet>
  </BuildConfiguration>
</fmiBuildDescription>
"""


# --------------------------------------------------------------------------- build
def fmi_headers(version: str = "2") -> Path:
    """The folder of fmpy's FMI headers (``fmi2Functions.h``, ``fmi3Functions.h``)."""
    try:
        import fmpy
    except ImportError:
        raise ResourceError("export --to fmu: needs the FMI headers of the Python package "
                            "fmpy; install it with: pip install 'fe-reduced-body[fmu]' "
                            "(or pip install fmpy)", key="fmpy", value="not installed",
                            expected="fmpy") from None
    folder = Path(fmpy.__file__).parent / "c-code"
    header = f"fmi{version}Functions.h"
    if not (folder / header).exists():
        raise ResourceError(f"export --to fmu: fmpy has no FMI headers at {folder}",
                            key="fmpy", value=str(folder), expected=f"c-code/{header}")
    return folder


def _compiler() -> str:
    cc = os.environ.get("CC") or "gcc"
    path = shutil.which(cc)
    if path is None:
        raise ResourceError(f"export --to fmu: needs a C compiler to build the FMU binary: "
                            f"'{cc}' not found on PATH (install gcc: Debian/Ubuntu 'apt install "
                            "gcc' or build-essential; or set CC)",
                            key="CC", value=cc, expected="a C compiler (gcc) on PATH")
    return path


def export_fmu(h5_path: str | Path, out_path: str | Path, model: str = "plant",
               fmi_version: str | int = "2") -> Path:
    """Write the FMU (FMI ``fmi_version`` 2 or 3) of ``model`` (any name
    :func:`.fmu_models.fmu_model` takes) of ``h5_path`` to ``out_path``, compiling its C code
    with gcc or ``$CC``; returns ``out_path``. Bad input (version, model, compiler, a file
    without the model) is refused before anything is written."""
    h5_path, out_path = Path(h5_path), Path(out_path)
    version = check_fmi_version(fmi_version)
    check_model_name(model)
    fmi = import_module(f"{__package__}.{FMI_VERSIONS[version]}")
    cc = _compiler()
    headers = fmi_headers(version)
    m = fmu_model(h5_path, model)
    ident = identifier(m.name, m.model)
    digest = hashlib.sha256(version.encode())
    for a in m.ss:
        digest.update(np.ascontiguousarray(a).tobytes())
    digest.update("|".join(m.ss.input_names + m.ss.output_names + m.ss.state_names).encode())
    guid = "{" + str(uuid.UUID(bytes=digest.digest()[:16], version=4)) + "}"
    files = resources.files(__package__)
    source = files.joinpath("fmu_core.c").read_text() + files.joinpath(fmi.C_API).read_text()
    header = model_data_header(m, guid)
    folder, ending = fmi.platform_folder()
    with private_folder("fmu_") as tmp:  # the build folder: C sources and the library
        (tmp / "fmu.c").write_text(source)
        (tmp / "model_data.h").write_text(header)
        lib = tmp / (ident + ending)
        cmd = [cc, "-std=c99", "-O2", "-shared", "-fPIC", f"-I{headers}", "-o", str(lib),
               str(tmp / "fmu.c"), "-lm"]
        proc = subprocess.run(cmd, capture_output=True, text=True)
        if proc.returncode != 0:
            first = (proc.stderr.strip().splitlines() or ["no message"])[0]
            raise ResourceError(f"export --to fmu: the C compiler failed ({cc}): {first}",
                                key="CC", value=cc, expected="a working C99 compiler")
        entries = {
            "modelDescription.xml": fmi.model_description(m, ident, guid, description(
                m, h5_path.name)),
            "sources/fmu.c": source,
            "sources/model_data.h": header,
            "sources/buildDescription.xml": BUILD_DESCRIPTION.format(identifier=ident),
            "documentation/index.html": (
                f"<html><body><h1>{escape(ident)}</h1><p>{escape(m.model)} model of "
                f"{escape(h5_path.name)}, exported by fe-reduced-body as an FMI {version}.0 "
                "FMU: x' = A x + B u, y = C x + D u (SI units). Co-simulation steps are exact "
                "for piecewise-constant inputs (zero-order hold).</p></body></html>\n"),
            **fmi.extra_entries(m),
        }
        with atomic_path(out_path) as part, zipfile.ZipFile(part, "w", zipfile.ZIP_DEFLATED) as z:
            for name, text in entries.items():
                z.writestr(name, text)
            z.write(lib, f"binaries/{folder}/{ident}{ending}")
    log.info("wrote FMU %s (FMI %s.0, %s, %d states, %d inputs, %d outputs, %d parameters)",
             out_path, version, m.model, m.ss.A.shape[0], m.ss.B.shape[1], m.ss.C.shape[0],
             m.n_parameters)
    return out_path
