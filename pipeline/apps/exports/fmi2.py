"""FMI 2.0 specifics of the FMU export (:mod:`pipeline.apps.exports.fmu`): the model
description, the binaries folder and the C functions (``fmi2_api.c``).

Variables (value references in this order, as ``fmi2_api.c`` reads them): one
ScalarVariable per state (our state names: ``eta_k``, ``eta_dot_k``, filter states;
initial exact, start 0), per derivative (``der(<state>)``), per input (our input name and
unit, start 0), per output (our output name, e.g. ``<port>/position|velocity|acceleration``
in m, m/s, m/s2 or rad, rad/s, rad/s2) and per tunable parameter (``damping_ratio_<k>``,
``filter_cutoff`` in Hz).
"""

from __future__ import annotations

import datetime
import sys
from xml.sax.saxutils import escape, quoteattr

from pipeline._version import __version__
from pipeline.apps.exports.fmu import (output_description, parameters, unit_definitions,
                                        variables_section)
from pipeline.apps.exports.fmu_models import FmuModel

__all__ = ["model_description", "platform_folder", "extra_entries", "C_API"]

#: the C file of the FMI 2.0 functions (appended to fmu_core.c)
C_API = "fmi2_api.c"


def platform_folder() -> tuple[str, str]:
    """(FMI 2.0 binaries folder, shared-library ending) of this machine."""
    bits = "64" if sys.maxsize > 2 ** 32 else "32"
    if sys.platform.startswith("win"):
        return "win" + bits, ".dll"
    if sys.platform == "darwin":
        return "darwin" + bits, ".dylib"
    return "linux" + bits, ".so"


def extra_entries(m: FmuModel) -> dict[str, str]:
    """Archive entries beyond the common ones: none for FMI 2.0."""
    return {}


def model_description(m: FmuModel, identifier: str, guid: str, description: str) -> str:
    """The FMI 2.0 modelDescription.xml (variables ordered as their value references)."""
    ss = m.ss
    nx = ss.A.shape[0]
    rows, index = [], 0

    def var(name, vr, attrs, real, text=""):
        nonlocal index
        index += 1
        desc = f" description={quoteattr(text)}" if text else ""
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
                   output_description(s))
               for i, (s, u) in enumerate(zip(ss.output_names, m.output_units))]
    base = 2 * nx + len(ss.input_names) + len(ss.output_names)
    for k, (name, start, u, text) in enumerate(parameters(m)):
        var(name, base + k, 'causality="parameter" variability="tunable" initial="exact"',
            f'{unit(u)} start="{start!r}" min="0"', text)
    src = '\n      <SourceFiles><File name="fmu.c"/></SourceFiles>'
    caps = ('canNotUseMemoryManagementFunctions="true" canGetAndSetFMUstate="false" '
            'canSerializeFMUstate="false" providesDirectionalDerivative="false"')
    now = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    unknown = lambda idx: "\n".join(f'      <Unknown index="{i}"/>' for i in idx)  # noqa: E731
    return f"""<?xml version="1.0" encoding="UTF-8"?>
<fmiModelDescription fmiVersion="2.0" modelName={quoteattr(identifier)} guid="{guid}"
  description={quoteattr(description)} generationTool="fe-reduced-body {escape(__version__)}"
  generationDateAndTime="{now}" variableNamingConvention="flat" numberOfEventIndicators="0">
  <ModelExchange modelIdentifier="{identifier}" {caps}>{src}
  </ModelExchange>
  <CoSimulation modelIdentifier="{identifier}" canHandleVariableCommunicationStepSize="true" canInterpolateInputs="false" {caps}>{src}
  </CoSimulation>
{unit_definitions(m)}{variables_section(m, rows)}  <ModelStructure>
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
