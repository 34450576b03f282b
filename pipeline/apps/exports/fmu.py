"""Export to an FMI 2.0 FMU (Model Exchange and Co-Simulation in one file).

``python -m pipeline export FILE.h5 --to fmu [--model plant|filtered]`` writes
``<stem>.<model>.fmu``: a zip holding

===============================  ==========================================================
entry                            content
===============================  ==========================================================
modelDescription.xml             FMI 2.0: one ScalarVariable per state (``eta_k``,
                                 ``eta_dot_k``, filter states; initial exact, start 0),
                                 per derivative (``der(<state>)``), per input (our input
                                 name, its unit: N or N m) and per output (our output name
                                 ``<port>/position|velocity|acceleration``, unit m, m/s,
                                 m/s2 or rad, rad/s, rad/s2), and a tunable parameter
                                 ``damping_ratio_<k>`` per mode when the model is modal
binaries/<platform>/<id>.so      the model compiled at export time (``gcc``, or ``$CC``);
                                 C only: it runs without Python
sources/fmu.c, model_data.h      the C sources (the FMI 2.0 headers come from the
sources/buildDescription.xml     importing tool), so another platform's tool builds it
documentation/index.html         what the model is, its source file
===============================  ==========================================================

The model is the state space of the file (SI units)::

    x' = A x + B u,     y = C x + D u

Model Exchange: the importer integrates ``fmi2GetDerivatives`` (= A x + B u). The state
nominals (``fmi2GetNominalsOfContinuousStates``, which absolute tolerances scale with) are
``sqrt(diag W)``, W the controllability Gramian (A W + W A^T + B B^T = 0): the RMS response
of each state to unit white-noise inputs (1.0 where A is not Hurwitz).
Co-Simulation: ``fmi2DoStep(h)`` holds the inputs constant over the step and advances
exactly: x(t + h) = Phi x(t) + Gamma u with [[Phi, Gamma], [0, I]] = expm([[A, B], [0, 0]] h)
(zero-order hold), computed in C for the step size asked (kept while h and the damping
parameters stay the same). Damping parameters (a modal model only: states ``eta_k``,
``eta_dot_k``): ``A[eta_dot_k, eta_dot_k] = -2 zeta_k omega_k``, and the acceleration rows
follow as ``C_acc = C_vel A``, ``D_acc = C_vel B`` (checked on the stored model at export).
"""

from __future__ import annotations

import datetime
import hashlib
import logging
import os
import re
import shutil
import subprocess
import sys
import uuid
import zipfile
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from xml.sax.saxutils import escape, quoteattr

import numpy as np

from pipeline._util.atomic import atomic_path, private_folder
from pipeline.errors import ConfigError, FileFormatError, ResourceError
from pipeline.reduce.statespace import StateSpace
from pipeline.store.read import StoredModels, load_model

log = logging.getLogger(__name__)

__all__ = ["export_fmu", "FmuModel", "fmu_model", "fmi_headers", "platform_folder", "MODELS"]

MODELS = ("plant", "filtered")
QUANTITY_SUFFIX = {"position": "", "velocity": "/s", "acceleration": "/s2"}
#: SI base-unit exponents (kg, m, s, rad) of the units our files use
BASE_UNITS = {"m": {"m": 1}, "m/s": {"m": 1, "s": -1}, "m/s2": {"m": 1, "s": -2},
              "rad": {"rad": 1}, "rad/s": {"rad": 1, "s": -1}, "rad/s2": {"rad": 1, "s": -2},
              "N": {"kg": 1, "m": 1, "s": -2}, "N m": {"kg": 1, "m": 2, "s": -2},
              "N.m": {"kg": 1, "m": 2, "s": -2}, "1": {}}
#: relative tolerance of the structure checks behind the damping parameters
STRUCTURE_RTOL = 1e-9


@dataclass(frozen=True)
class FmuModel:
    """What goes into the FMU: ``ss`` (names from the file), one unit per input and output,
    the damping parameters (state indices of ``eta_k`` and ``eta_dot_k``, omega_k rad/s,
    zeta_k) and the (acceleration row, velocity row) pairs of C that follow A."""

    name: str
    ss: StateSpace
    input_units: tuple[str, ...]
    output_units: tuple[str, ...]
    mode_pos: tuple[int, ...]
    mode_vel: tuple[int, ...]
    omega: np.ndarray
    zeta: np.ndarray
    acc_rows: tuple[tuple[int, int], ...]
    nominals: np.ndarray


def _port_units(lm: StoredModels, ss: StateSpace) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(input units, output units) of the file's plant (one per input, one per output
    port) expanded to position/velocity/acceleration."""
    u_units, port_units = list(lm.input_units), list(lm.port_units)
    if len(u_units) != ss.B.shape[1]:
        u_units = [""] * ss.B.shape[1]
    ports = ss.ports
    per_port = dict(zip(ports, port_units)) if len(port_units) == len(ports) else {}
    y_units = []
    for name in ss.output_names:
        port, _, quantity = name.rpartition("/")
        base = per_port.get(port, "")
        y_units.append(base + QUANTITY_SUFFIX.get(quantity, "?") if base else "")
    return tuple(u_units), tuple("" if u.endswith("?") else u for u in y_units)


def _damping_structure(ss: StateSpace, zeta: np.ndarray):
    """(pos, vel, omega, zeta, acc_rows) when A is modal in (eta_k, eta_dot_k) with
    A[vel, vel] = -2 zeta omega and every acceleration row = velocity row times A (D_vel
    = 0); else None (the FMU then has no damping parameters)."""
    names = list(ss.state_names)
    A, B, C, D = ss.A, ss.B, ss.C, ss.D
    pos, vel, omega = [], [], []
    for k in range(1, zeta.size + 1):
        if f"eta_{k}" not in names or f"eta_dot_{k}" not in names:
            return None
        i, j = names.index(f"eta_{k}"), names.index(f"eta_dot_{k}")
        w2 = -A[j, i]
        if A[i, j] != 1.0 or not w2 > 0:
            return None
        w = float(np.sqrt(w2))
        if abs(A[j, j] + 2.0 * zeta[k - 1] * w) > STRUCTURE_RTOL * max(w, 1.0):
            return None
        pos.append(i), vel.append(j), omega.append(w)
    acc_rows = []
    for r, name in enumerate(ss.output_names):
        port, _, quantity = name.rpartition("/")
        if quantity != "acceleration":
            continue
        if f"{port}/velocity" not in ss.output_names:
            return None
        v = ss.output_names.index(f"{port}/velocity")
        scale_c = np.abs(C[v]) @ np.abs(A) + 1e-300
        scale_d = np.abs(C[v]) @ np.abs(B) + 1e-300
        if (np.any(D[v] != 0.0) or np.any(np.abs(C[r] - C[v] @ A) > STRUCTURE_RTOL * scale_c)
                or np.any(np.abs(D[r] - C[v] @ B) > STRUCTURE_RTOL * scale_d)):
            return None
        acc_rows.append((r, v))
    return tuple(pos), tuple(vel), np.array(omega), np.array(zeta, float), tuple(acc_rows)


def _nominals(ss: StateSpace) -> np.ndarray:
    import scipy.linalg as sla

    n = ss.A.shape[0]
    if n == 0 or not np.all(np.linalg.eigvals(ss.A).real < 0):
        return np.ones(n)
    W = sla.solve_continuous_lyapunov(ss.A, -ss.B @ ss.B.T)
    d = np.sqrt(np.clip(np.diag(W), 0.0, None))
    return np.where(np.isfinite(d) & (d > 0), d, 1.0)


def fmu_model(h5_path: str | Path, model: str = "plant") -> FmuModel:
    """The model ``model`` (``plant`` or ``filtered``) of ``h5_path`` with units and
    damping parameters, as :func:`export_fmu` writes it."""
    h5_path = Path(h5_path)
    if model not in MODELS:
        raise ConfigError(f"export --model: got {model!r}, expected one of {', '.join(MODELS)}",
                          key="--model", value=model, expected=" | ".join(MODELS))
    lm = load_model(h5_path, require_plant=True)
    ss = lm.plant if model == "plant" else lm.filtered
    if ss is None:
        raise FileFormatError(f"file '{h5_path}': holds no filtered model (the config had no "
                              "'filter' section); use --model plant", key="--model",
                              value=model, expected="plant")
    u_units, y_units = _port_units(lm, ss)
    structure = _damping_structure(ss, np.asarray(lm.damping_ratios, float))
    if structure is None:
        log.info("fmu: %s model is not modal with damping in A; no damping parameters", model)
        structure = ((), (), np.zeros(0), np.zeros(0), ())
    name = str(lm.path.stem)
    return FmuModel(name, ss, u_units, y_units, *structure, _nominals(ss))


# --------------------------------------------------------------------------- C and XML
def fmi_headers() -> Path:
    """The folder of fmpy's FMI 2.0 headers (``fmi2Functions.h``)."""
    try:
        import fmpy
    except ImportError:
        raise ResourceError("export --to fmu: needs the FMI 2.0 headers of the Python package "
                            "fmpy; install it with: pip install 'fe-reduced-body[fmu]' "
                            "(or pip install fmpy)", key="fmpy", value="not installed",
                            expected="fmpy") from None
    folder = Path(fmpy.__file__).parent / "c-code"
    if not (folder / "fmi2Functions.h").exists():
        raise ResourceError(f"export --to fmu: fmpy has no FMI headers at {folder}",
                            key="fmpy", value=str(folder), expected="c-code/fmi2Functions.h")
    return folder


def platform_folder() -> tuple[str, str]:
    """(FMI 2.0 binaries folder, shared-library ending) of this machine."""
    bits = "64" if sys.maxsize > 2 ** 32 else "32"
    if sys.platform.startswith("win"):
        return "win" + bits, ".dll"
    if sys.platform == "darwin":
        return "darwin" + bits, ".dylib"
    return "linux" + bits, ".so"


def _c_array(name: str, values, ctype: str = "double") -> str:
    values = list(np.asarray(values).ravel())
    if not values:
        values = [0]
    fmt = (lambda v: repr(float(v))) if ctype == "double" else (lambda v: str(int(v)))
    body = ",\n    ".join(", ".join(fmt(v) for v in values[i:i + 4])
                          for i in range(0, len(values), 4))
    return f"static const {ctype} {name}[] = {{\n    {body}}};\n"


def model_data_header(m: FmuModel, guid: str) -> str:
    """``model_data.h``: sizes, matrices (row major, 17 significant digits), GUID."""
    ss = m.ss
    nx, nu, ny, n_p = ss.A.shape[0], ss.B.shape[1], ss.C.shape[0], len(m.mode_pos)
    out = [f"/* model data of {m.name}: generated by pipeline.apps.exports.fmu */\n",
           f"#define MODEL_GUID \"{guid}\"\n#define NX {nx}\n#define NU {nu}\n#define NY {ny}\n",
           f"#define NP {n_p}\n#define NACC {len(m.acc_rows)}\n",
           _c_array("A0", ss.A), _c_array("B0", ss.B), _c_array("C0", ss.C), _c_array("D0", ss.D),
           _c_array("X0", np.zeros(nx)), _c_array("NOMINAL", m.nominals),
           _c_array("MODE_VEL", m.mode_vel, "int"), _c_array("OMEGA", m.omega),
           _c_array("ZETA0", m.zeta),
           _c_array("ACC_ROW", [a for a, _ in m.acc_rows], "int"),
           _c_array("VEL_ROW", [v for _, v in m.acc_rows], "int")]
    return "".join(out)


def _unit_definitions(units: set[str]) -> str:
    lines = ["  <UnitDefinitions>"]
    for u in sorted(units):
        base = BASE_UNITS.get(u)
        if base is None:
            lines.append(f"    <Unit name={quoteattr(u)}/>")
        else:
            exps = " ".join(f'{k}="{v}"' for k, v in base.items())
            lines.append(f"    <Unit name={quoteattr(u)}><BaseUnit {exps}/></Unit>"
                         if exps else f"    <Unit name={quoteattr(u)}><BaseUnit/></Unit>")
    lines.append("  </UnitDefinitions>")
    return "\n".join(lines) + "\n"


def model_description(m: FmuModel, identifier: str, guid: str, model: str,
                      source: str) -> str:
    """The FMI 2.0 modelDescription.xml (variables ordered as their value references)."""
    from pipeline._version import __version__

    ss = m.ss
    nx = ss.A.shape[0]
    freqs = m.omega / (2 * np.pi) if m.omega.size else np.abs(np.linalg.eigvals(ss.A)) / (2 * np.pi)
    freqs = freqs[freqs > 0]
    f_lo, f_hi = (float(freqs.min()), float(freqs.max())) if freqs.size else (1.0, 1.0)
    rows, index = [], 0

    def var(name, vr, attrs, real, description=""):
        nonlocal index
        index += 1
        desc = f" description={quoteattr(description)}" if description else ""
        rows.append(f"    <ScalarVariable name={quoteattr(name)} valueReference=\"{vr}\"{desc} "
                    f"{attrs}>\n      <Real{real}/>\n    </ScalarVariable>")
        return index

    def unit(u):
        return f" unit={quoteattr(u)}" if u else ""

    states = [var(s, i, 'causality="local" variability="continuous" initial="exact"',
                  ' start="0"', "state") for i, s in enumerate(ss.state_names)]
    derivs = [var(f"der({s})", nx + i, 'causality="local" variability="continuous"',
                  f' derivative="{states[i]}"') for i, s in enumerate(ss.state_names)]
    for j, (s, u) in enumerate(zip(ss.input_names, m.input_units)):
        var(s, 2 * nx + j, 'causality="input" variability="continuous"',
            unit(u) + ' start="0"', "input (held constant over a co-simulation step)")
    outputs = [var(s, 2 * nx + len(ss.input_names) + i,
                   'causality="output" variability="continuous" initial="calculated"', unit(u),
                   "output") for i, (s, u) in enumerate(zip(ss.output_names, m.output_units))]
    base = 2 * nx + len(ss.input_names) + len(ss.output_names)
    for k, z in enumerate(m.zeta):
        var(f"damping_ratio_{k + 1}", base + k,
            'causality="parameter" variability="tunable" initial="exact"',
            f' start="{float(z)!r}" min="0"',
            f"modal damping ratio of mode {k + 1} ({m.omega[k] / (2 * np.pi):.6g} Hz)")
    units = {u for u in m.input_units + m.output_units if u}
    src = '\n      <SourceFiles><File name="fmu.c"/></SourceFiles>'
    caps = ('canNotUseMemoryManagementFunctions="true" canGetAndSetFMUstate="false" '
            'canSerializeFMUstate="false" providesDirectionalDerivative="false"')
    now = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    desc = (f"{model} model of {source}: x' = A x + B u, y = C x + D u ({nx} states); "
            "co-simulation steps are exact for inputs held over the step (zero-order hold)")
    unknown = lambda idx: "\n".join(f'      <Unknown index="{i}"/>' for i in idx)  # noqa: E731
    return f"""<?xml version="1.0" encoding="UTF-8"?>
<fmiModelDescription fmiVersion="2.0" modelName={quoteattr(identifier)} guid="{guid}"
  description={quoteattr(desc)} generationTool="fe-reduced-body {escape(__version__)}"
  generationDateAndTime="{now}" variableNamingConvention="flat" numberOfEventIndicators="0">
  <ModelExchange modelIdentifier="{identifier}" {caps}>{src}
  </ModelExchange>
  <CoSimulation modelIdentifier="{identifier}" canHandleVariableCommunicationStepSize="true" canInterpolateInputs="false" {caps}>{src}
  </CoSimulation>
{_unit_definitions(units) if units else ""}  <LogCategories>
    <Category name="logStatusError"/>
  </LogCategories>
  <DefaultExperiment startTime="0" stopTime="{10.0 / f_lo:.6g}" stepSize="{1.0 / (20.0 * f_hi):.6g}"/>
  <ModelVariables>
{chr(10).join(rows)}
  </ModelVariables>
  <ModelStructure>
    <Outputs>
{unknown(outputs)}
    </Outputs>
    <Derivatives>
{unknown(derivs)}
    </Derivatives>
    <InitialUnknowns>
{unknown(outputs + derivs)}
    </InitialUnknowns>
  </ModelStructure>
</fmiModelDescription>
"""


BUILD_DESCRIPTION = """<?xml version="1.0" encoding="UTF-8"?>
<fmiBuildDescription fmiVersion="3.0">
  <BuildConfiguration modelIdentifier="{identifier}">
    <SourceFileSet language="C99">
      <SourceFile name="fmu.c"/>
    </SourceFileSet>
  </BuildConfiguration>
</fmiBuildDescription>
"""


def _compiler() -> str:
    cc = os.environ.get("CC") or "gcc"
    path = shutil.which(cc)
    if path is None:
        raise ResourceError(f"export --to fmu: needs a C compiler to build the FMU binary: "
                            f"'{cc}' not found on PATH (install gcc, or set CC)",
                            key="CC", value=cc, expected="a C compiler (gcc) on PATH")
    return path


def _identifier(name: str, model: str) -> str:
    ident = re.sub(r"[^A-Za-z0-9_]", "_", f"{name}_{model}")
    return ident if ident[0].isalpha() else "m_" + ident


def export_fmu(h5_path: str | Path, out_path: str | Path, model: str = "plant") -> Path:
    """Write the FMU of ``model`` (plant | filtered) of ``h5_path`` to ``out_path``
    (compiling its C code with gcc or ``$CC``); returns ``out_path``."""
    h5_path, out_path = Path(h5_path), Path(out_path)
    cc = _compiler()
    headers = fmi_headers()
    m = fmu_model(h5_path, model)
    identifier = _identifier(m.name, model)
    digest = hashlib.sha256()
    for a in m.ss:
        digest.update(np.ascontiguousarray(a).tobytes())
    digest.update("|".join(m.ss.input_names + m.ss.output_names + m.ss.state_names).encode())
    guid = "{" + str(uuid.UUID(bytes=digest.digest()[:16], version=4)) + "}"
    template = resources.files("pipeline.apps.exports").joinpath("fmu_template.c").read_text()
    header = model_data_header(m, guid)
    folder, ending = platform_folder()
    with private_folder("fmu_") as tmp:  # the build folder: C sources and the library
        (tmp / "fmu.c").write_text(template)
        (tmp / "model_data.h").write_text(header)
        lib = tmp / (identifier + ending)
        cmd = [cc, "-std=c99", "-O2", "-shared", "-fPIC", f"-I{headers}", "-o", str(lib),
               str(tmp / "fmu.c"), "-lm"]
        proc = subprocess.run(cmd, capture_output=True, text=True)
        if proc.returncode != 0:
            first = (proc.stderr.strip().splitlines() or ["no message"])[0]
            raise ResourceError(f"export --to fmu: the C compiler failed ({cc}): {first}",
                                key="CC", value=cc, expected="a working C99 compiler")
        entries = {
            "modelDescription.xml": model_description(m, identifier, guid, model,
                                                      str(h5_path.name)),
            "sources/fmu.c": template,
            "sources/model_data.h": header,
            "sources/buildDescription.xml": BUILD_DESCRIPTION.format(identifier=identifier),
            "documentation/index.html": (
                f"<html><body><h1>{escape(identifier)}</h1><p>{escape(model)} model of "
                f"{escape(str(h5_path.name))}, exported by fe-reduced-body: x' = A x + B u, "
                "y = C x + D u (SI units). Co-simulation steps are exact for piecewise-constant "
                "inputs (zero-order hold).</p></body></html>\n"),
        }
        with atomic_path(out_path) as part, zipfile.ZipFile(part, "w", zipfile.ZIP_DEFLATED) as z:
            for name, text in entries.items():
                z.writestr(name, text)
            z.write(lib, f"binaries/{folder}/{identifier}{ending}")
    log.info("wrote FMU %s (%s, %d states, %d inputs, %d outputs, %d damping parameters)",
             out_path, model, m.ss.A.shape[0], m.ss.B.shape[1], m.ss.C.shape[0], m.zeta.size)
    return out_path
