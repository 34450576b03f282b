"""CalculiX (``ccx``) as an independent referee: write a tetrahedral mesh as a CalculiX
input deck, run a ``*FREQUENCY`` step and read the natural frequencies back.

CalculiX's C3D10 node order (corners, then edges 1-2, 2-3, 3-1, 1-4, 2-4, 3-4) is
meshio's ``tetra10`` order, which the pipeline stores in ``/mesh/cells/tetra10``, so the
stored cells are written as they are (node numbers + 1); C3D4 likewise. A test using it
skips where ``shutil.which("ccx")`` is None.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

CCX = shutil.which("ccx")


def _lines(values: np.ndarray, per_line: int = 8) -> str:
    """Comma-separated integers, at most ``per_line`` per line (ccx's card length)."""
    v = [str(int(x)) for x in values]
    return "\n".join(", ".join(v[i:i + per_line]) + "," for i in range(0, len(v), per_line))


def write_frequency_deck(path: Path, points: np.ndarray, cells: np.ndarray, E: float, nu: float,
                         rho: float, fixed: Mapping[str, tuple[np.ndarray, Sequence[int]]],
                         n_modes: int) -> Path:
    """Write ``path`` (.inp): nodes ``points`` (n_p, 3) m, elements ``cells`` (n_t, 4 | 10)
    0-based meshio order, one isotropic material (Pa, -, kg/m^3), and for every name of
    ``fixed`` an *NSET of its 0-based nodes held in the components (1 = x, 2 = y, 3 = z)
    given; one *FREQUENCY step for the lowest ``n_modes``."""
    kind = "C3D10" if cells.shape[1] == 10 else "C3D4"
    out = ["*HEADING", "pipeline test deck", "*NODE"]
    out += [f"{i + 1}, {x:.17g}, {y:.17g}, {z:.17g}" for i, (x, y, z) in enumerate(points)]
    out.append(f"*ELEMENT, TYPE={kind}, ELSET=EALL")
    for i, c in enumerate(cells + 1):
        ids = [str(i + 1)] + [str(int(n)) for n in c]
        out.append(", ".join(ids[:8]) + ("," if len(ids) > 8 else ""))
        if len(ids) > 8:
            out.append(", ".join(ids[8:]))
    for name, (nodes, _) in fixed.items():
        out += [f"*NSET, NSET={name}", _lines(np.asarray(nodes) + 1)]
    out += ["*MATERIAL, NAME=MAT", "*ELASTIC", f"{E:.12g}, {nu:.12g}", "*DENSITY", f"{rho:.12g}",
            "*SOLID SECTION, ELSET=EALL, MATERIAL=MAT", "*STEP", "*FREQUENCY", f"{n_modes}",
            "*BOUNDARY"]
    for name, (_, comps) in fixed.items():
        out += [f"{name}, {c}, {c}" for c in comps]
    out.append("*END STEP")
    path.write_text("\n".join(out) + "\n")
    return path


def run_frequencies(deck: Path, timeout: float = 300.0) -> np.ndarray:
    """Run ccx on ``deck`` (.inp) in its folder; the frequencies (Hz) of its .dat file."""
    job = deck.with_suffix("")
    subprocess.run([CCX, "-i", job.name], cwd=deck.parent, capture_output=True, text=True,
                   timeout=timeout, check=True, env={"OMP_NUM_THREADS": "1", "PATH": "/usr/bin"})
    text = job.with_suffix(".dat").read_text()
    block = text.split("E I G E N V A L U E   O U T P U T")[1]
    block = block.split("P A R T I C I P A T I O N")[0]
    # MODE NO, EIGENVALUE, omega (rad/time), f (cycles/time), imaginary part: 7 digits
    rows = re.findall(r"^\s*\d+\s+(\S+)\s+(\S+)\s+(\S+)\s+(\S+)\s*$", block, re.M)
    return np.array([float(r[2]) for r in rows])
