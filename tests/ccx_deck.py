"""Write a CalculiX (Abaqus-style) deck of a pipeline mesh and read its results: the
independent FE check of tests/test_materials.py (``ccx`` from Debian's calculix-ccx).

Elements: C3D4 / C3D10 (the pipeline's local node order is VTK's tetra10 order, which is
also Abaqus' C3D10 order). Materials: one ELSET per law with *SOLID SECTION; isotropic
*ELASTIC, orthotropic *ELASTIC, TYPE=ENGINEERING CONSTANTS with *ORIENTATION, or
*ELASTIC, TYPE=ANISO (tensor components C_ijkl).
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import numpy as np

#: ccx ANISO order of the 21 tensor components (1-based index pairs)
ANISO = ("1111", "1122", "2222", "1133", "2233", "3333", "1112", "2212", "3312", "1212",
         "1113", "2213", "3313", "1213", "1313", "1123", "2223", "3323", "1223", "1323", "2323")


def _lines(values, per_line=8):
    values = list(values)
    return [", ".join(f"{v:.17g}" for v in values[i:i + per_line])
            for i in range(0, len(values), per_line)]


def write_deck(path: Path, space, laws, index, fixed_nodes, step: str) -> None:
    """``laws``: list of dicts {kind: isotropic|orthotropic|tensor, rho, E, nu | E, nu, G,
    axes | C (3,3,3,3)}; ``index`` (n_e,) law of each element; ``fixed_nodes`` clamped;
    ``step``: the deck's *STEP body."""
    pts = space.node_points
    en = space.element_nodes
    etype = "C3D10" if en.shape[1] == 10 else "C3D4"
    out = ["*NODE"]
    out += [f"{i + 1}, {p[0]:.17g}, {p[1]:.17g}, {p[2]:.17g}" for i, p in enumerate(pts)]
    for law in range(len(laws)):
        els = np.flatnonzero(index == law)
        if els.size == 0:
            continue
        out.append(f"*ELEMENT, TYPE={etype}, ELSET=M{law}")
        for e in els:
            nodes = [str(n + 1) for n in en[e]]
            out.append(f"{e + 1}, " + ", ".join(nodes[:8]) + ("," if len(nodes) > 8 else ""))
            if len(nodes) > 8:
                out.append(", ".join(nodes[8:]))
    for law, spec in enumerate(laws):
        if not np.any(index == law):
            continue
        out.append(f"*MATERIAL, NAME=MAT{law}")
        orient = ""
        if spec["kind"] == "isotropic":
            out += ["*ELASTIC", f"{spec['E']:.17g}, {spec['nu']:.17g}"]
        elif spec["kind"] == "orthotropic":
            E, nu, G = spec["E"], spec["nu"], spec["G"]
            out += ["*ELASTIC, TYPE=ENGINEERING CONSTANTS"]
            out += _lines([*E, *nu, G[0], G[1], G[2], 0.0])
            orient = f", ORIENTATION=OR{law}"
        else:
            C = spec["C"]
            out += ["*ELASTIC, TYPE=ANISO"]
            out += _lines([C[int(s[0]) - 1, int(s[1]) - 1, int(s[2]) - 1, int(s[3]) - 1]
                           for s in ANISO] + [0.0])
        out += ["*DENSITY", f"{spec['rho']:.17g}"]
        if orient:
            a, b = spec["axes"][0], spec["axes"][1]
            out += [f"*ORIENTATION, NAME=OR{law}, SYSTEM=RECTANGULAR",
                                   ", ".join(f"{v:.17g}" for v in (*a, *b))]
        out.append(f"*SOLID SECTION, ELSET=M{law}, MATERIAL=MAT{law}{orient}")
    out.append("*NSET, NSET=FIX")
    out += _lines([n + 1 for n in fixed_nodes], 16)
    out += ["*BOUNDARY", "FIX, 1, 3", step]
    path.write_text("\n".join(out) + "\n")


def run(deck: Path) -> str:
    """Run ccx on ``deck`` (name without .inp) and return its .dat text."""
    subprocess.run(["ccx", "-i", deck.stem], cwd=deck.parent, check=True,
                   capture_output=True, timeout=300)
    return deck.with_suffix(".dat").read_text()


def frequencies(dat: str) -> np.ndarray:
    """Frequencies (Hz) of the *FREQUENCY step's eigenvalue table."""
    block = dat.split("E I G E N V A L U E   O U T P U T")[1]
    rows = re.findall(r"^\s*(\d+)\s+(\S+)\s+(\S+)\s+(\S+)\s+(\S+)\s*$", block, re.M)
    return np.array([float(r[3]) for r in rows])


def displacements(dat: str) -> dict[int, np.ndarray]:
    """Node (0-based) -> (3,) displacement of the *NODE PRINT table."""
    out = {}
    for line in dat.split("displacements")[1].splitlines():
        parts = line.split()
        if len(parts) == 4 and parts[0].isdigit():
            out[int(parts[0]) - 1] = np.array([float(p) for p in parts[1:]])
    return out
