"""Build the L-bracket of configs/bracket.yaml with gmsh's OpenCASCADE kernel -> bracket.step.

Run from the repository root (needs only the ``gmsh`` wheel)::

    .venv/bin/python meshes/make_bracket.py            # writes meshes/bracket.step
    .venv/bin/python meshes/make_bracket.py -o OUT.step

The part is drawn in millimetres (the STEP file declares MILLIMETRE, so the pipeline
reads it in metres with ``scale: 1``). Coordinates::

    z
    |   wall: x 0..60, y 0..5, z 0..50, with a 6.5 mm load hole at (x 30, z 35)
    |   |
    |   |__________ base: x 0..60, y 0..40, z 0..5, two 8.5 mm (M8) bolt holes at
    +------------ y     (x 15, y 25) and (x 45, y 25); 4 mm fillet inside the bend

The base sits on the mounting face z = 0 and is bolted down through the two holes;
a pin in the wall's hole carries the load. Every dimension is a constant below, and
the numbers that configs/bracket.yaml's region selectors depend on are printed.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path

# dimensions, mm
WIDTH = 60.0            # x, both flanges
BASE_DEPTH = 40.0       # y, base flange
WALL_HEIGHT = 50.0      # z, wall
THICKNESS = 5.0         # both flanges
FILLET = 4.0            # inner bend radius
BOLT_DIAMETER = 8.5     # M8 clearance hole
BOLTS = ((15.0, 25.0), (45.0, 25.0))   # (x, y) of the bolt-hole axes (along z)
PIN_DIAMETER = 6.5      # load hole in the wall
PIN = (30.0, 35.0)      # (x, z) of the load-hole axis (along y)


def build(path: Path) -> float:
    """Make the solid and write it as STEP; returns its volume in mm^3."""
    import gmsh

    gmsh.initialize(interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("bracket")
        occ = gmsh.model.occ
        base = occ.addBox(0, 0, 0, WIDTH, BASE_DEPTH, THICKNESS)
        wall = occ.addBox(0, 0, 0, WIDTH, THICKNESS, WALL_HEIGHT)
        (body,), _ = occ.fuse([(3, base)], [(3, wall)])
        occ.synchronize()
        # the inner bend: the edge along x at y = z = THICKNESS
        bend = [tag for _, tag in occ.getEntitiesInBoundingBox(
            -1, THICKNESS - 1e-3, THICKNESS - 1e-3, WIDTH + 1, THICKNESS + 1e-3,
            THICKNESS + 1e-3, dim=1)]
        if len(bend) != 1:
            raise RuntimeError(f"expected one inner bend edge, found {bend}")
        body = occ.fillet([body[1]], bend, [FILLET])[0]
        holes = [(3, occ.addCylinder(x, y, -1, 0, 0, THICKNESS + 2, BOLT_DIAMETER / 2))
                 for x, y in BOLTS]
        holes.append((3, occ.addCylinder(PIN[0], -1, PIN[1], 0, THICKNESS + 2, 0,
                                          PIN_DIAMETER / 2)))
        out, _ = occ.cut([body], holes)
        occ.synchronize()
        if len(out) != 1:
            raise RuntimeError(f"expected one solid, got {out}")
        volume = occ.getMass(3, out[0][1])
        path.parent.mkdir(parents=True, exist_ok=True)
        # OpenCASCADE prints transfer statistics on stdout: keep them off ours
        saved = os.dup(1)
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 1)
            try:
                gmsh.write(str(path))
            finally:
                os.dup2(saved, 1)
                os.close(saved)
        return volume
    finally:
        gmsh.finalize()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-o", "--output", default=str(Path(__file__).with_name("bracket.step")))
    args = parser.parse_args(argv)
    path = Path(args.output)
    volume = build(path)
    t, r_b, r_p = THICKNESS, BOLT_DIAMETER / 2, PIN_DIAMETER / 2
    print(f"wrote {path} ({path.stat().st_size / 1024:.0f} kB): volume {volume:.2f} mm^3")
    print("region selectors (m) for configs/bracket.yaml:")
    for i, (x, y) in enumerate(BOLTS, 1):
        print(f"  bolt_{i}: sphere point [{x / 1e3:g}, {y / 1e3:g}, {t / 2e3:g}], radius "
              f"{1.001 * math.hypot(r_b, t / 2) / 1e3:.6g}")
    print(f"  pin: sphere point [{PIN[0] / 1e3:g}, {t / 2e3:g}, {PIN[1] / 1e3:g}], radius "
          f"{1.001 * math.hypot(r_p, t / 2) / 1e3:.6g}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
