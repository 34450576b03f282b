"""FMI 3.0 specifics of the FMU export (:mod:`pipeline.apps.exports.fmu`): the model
description, the binaries folder (platform tuple) and the C functions (``fmi3_api.c``).

Variables (value references as ``fmi3_api.c`` reads them):

== ================ =================================================================
vr name             what
== ================ =================================================================
0  time             the independent variable (s)
1  x                the state vector, a Float64 array of n_x (``<Dimension>``); its
                    description lists the state names in order (``eta_k``,
                    ``eta_dot_k``, filter states, ...); initial exact, start 0
2  der(x)           its derivative (``derivative="1"``), the ContinuousStateDerivative
3  <input>          one per input: our name, SI unit, start 0
.. <output>         one per output: our name, SI unit (m, m/s, m/s2, rad, N, N m, ...)
.. damping_ratio_k  tunable parameters (:mod:`.fmu_models`), then filter_cutoff (Hz)
== ================ =================================================================

Model Exchange and Co-Simulation share the binary; Scheduled Execution, clocks,
directional derivatives and FMU states are not provided (the capability flags say so).

``terminalsAndIcons/terminalsAndIcons.xml`` groups the variables of each mechanical port
into one terminal (a connector a tool can wire as one): every input and output named
``<port>/<member>`` or ``<port>.<member>`` (``tip_y/position``; the connection model's
``root.ax`` ... ``root.Fx``; the Craig-Bampton body's ``root.Fx`` and ``root.x/position``)
is a member ``<member>`` of the terminal ``<port>`` (matchingRule ``bus``: members match by
name; variableKind ``signal``).
"""

from __future__ import annotations

import datetime
import platform
import sys
from xml.sax.saxutils import escape, quoteattr

from pipeline._version import __version__
from pipeline.apps.exports.fmu import (output_description, parameters, unit_definitions,
                                        variables_section)
from pipeline.apps.exports.fmu_models import FmuModel

__all__ = ["model_description", "platform_folder", "terminals", "extra_entries", "C_API"]

#: the C file of the FMI 3.0 functions (appended to fmu_core.c)
C_API = "fmi3_api.c"
_MACHINES = {"amd64": "x86_64", "x86_64": "x86_64", "arm64": "aarch64", "aarch64": "aarch64",
             "i386": "x86", "i686": "x86", "x86": "x86"}


def platform_folder() -> tuple[str, str]:
    """(FMI 3.0 platform tuple ``<arch>-<os>``, shared-library ending) of this machine."""
    arch = _MACHINES.get(platform.machine().lower(), platform.machine().lower())
    if sys.platform.startswith("win"):
        return f"{arch}-windows", ".dll"
    if sys.platform == "darwin":
        return f"{arch}-darwin", ".dylib"
    return f"{arch}-linux", ".so"


def terminals(m: FmuModel) -> str:
    """terminalsAndIcons.xml: one terminal per port (module docstring); '' without any."""
    ports: dict[str, list[tuple[str, str]]] = {}
    for name in m.ss.input_names + m.ss.output_names:
        cut = min((i for i in (name.find("/"), name.find(".")) if i > 0), default=-1)
        if cut > 0:
            ports.setdefault(name[:cut], []).append((name, name[cut + 1:]))
    if not ports:
        return ""
    rows = []
    for port, members in ports.items():
        rows.append(f'    <Terminal name={quoteattr(port)} matchingRule="bus" '
                    f'description={quoteattr(f"port {port}: its inputs and outputs")}>')
        rows += [f'      <TerminalMemberVariable variableName={quoteattr(v)} '
                 f'memberName={quoteattr(member)} variableKind="signal"/>'
                 for v, member in members]
        rows.append("    </Terminal>")
    return ('<?xml version="1.0" encoding="UTF-8"?>\n<fmiTerminalsAndIcons fmiVersion="3.0">\n'
            "  <Terminals>\n" + "\n".join(rows) + "\n  </Terminals>\n</fmiTerminalsAndIcons>\n")


def extra_entries(m: FmuModel) -> dict[str, str]:
    """The archive entries FMI 3.0 adds: the terminals of the ports."""
    text = terminals(m)
    return {"terminalsAndIcons/terminalsAndIcons.xml": text} if text else {}


def model_description(m: FmuModel, identifier: str, guid: str, description: str) -> str:
    """The FMI 3.0 modelDescription.xml."""
    ss = m.ss
    nx, nu = ss.A.shape[0], ss.B.shape[1]

    def unit(u):
        return f" unit={quoteattr(u)}" if u else ""

    rows = ['    <Float64 name="time" valueReference="0" causality="independent" '
            'variability="continuous" description="time" unit="s"/>',
            f'    <Float64 name="x" valueReference="1" causality="local" variability="continuous"'
            f' initial="exact" start="{" ".join(["0"] * nx)}" description='
            f'{quoteattr("state vector: " + ", ".join(ss.state_names))}>\n'
            f'      <Dimension start="{nx}"/>\n    </Float64>',
            '    <Float64 name="der(x)" valueReference="2" causality="local" '
            'variability="continuous" derivative="1" description="derivative of the state '
            f'vector">\n      <Dimension start="{nx}"/>\n    </Float64>']
    for j, (s, u) in enumerate(zip(ss.input_names, m.input_units)):
        rows.append(f'    <Float64 name={quoteattr(s)} valueReference="{3 + j}" causality="input"'
                    f' variability="continuous"{unit(u)} start="0" description="input (held '
                    'constant over a co-simulation step)"/>')
    outputs = list(range(3 + nu, 3 + nu + ss.C.shape[0]))
    for vr, s, u in zip(outputs, ss.output_names, m.output_units):
        rows.append(f'    <Float64 name={quoteattr(s)} valueReference="{vr}" causality="output"'
                    f' variability="continuous"{unit(u)} '
                    f'description={quoteattr(output_description(s))}/>')
    base = 3 + nu + ss.C.shape[0]
    for k, (name, start, u, text) in enumerate(parameters(m)):
        rows.append(f'    <Float64 name={quoteattr(name)} valueReference="{base + k}" '
                    f'causality="parameter" variability="tunable"{unit(u)} start="{start!r}" '
                    f'min="0" description={quoteattr(text)}/>')
    caps = ('canGetAndSetFMUState="false" canSerializeFMUState="false" '
            'providesDirectionalDerivatives="false" providesAdjointDerivatives="false"')
    now = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    structure = ([f'    <Output valueReference="{vr}"/>' for vr in outputs]
                 + ['    <ContinuousStateDerivative valueReference="2"/>']
                 + [f'    <InitialUnknown valueReference="{vr}"/>' for vr in outputs + [2]])
    return f"""<?xml version="1.0" encoding="UTF-8"?>
<fmiModelDescription fmiVersion="3.0" modelName={quoteattr(identifier)}
  instantiationToken="{guid}" description={quoteattr(description)}
  generationTool="fe-reduced-body {escape(__version__)}" generationDateAndTime="{now}"
  variableNamingConvention="flat">
  <ModelExchange modelIdentifier="{identifier}" needsCompletedIntegratorStep="false" {caps}/>
  <CoSimulation modelIdentifier="{identifier}" canHandleVariableCommunicationStepSize="true" hasEventMode="false" providesIntermediateUpdate="false" canReturnEarlyAfterIntermediateUpdate="false" {caps}/>
{unit_definitions(m, ('s',))}{variables_section(m, rows)}  <ModelStructure>
{chr(10).join(structure)}
  </ModelStructure>
</fmiModelDescription>
"""
