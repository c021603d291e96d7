"""Seven part surfaces made by constructive solid geometry, written as STL: held-out CAD inputs.

    python benchmarks/csg_parts.py OUT_DIR
    OMP_NUM_THREADS=1 python benchmarks/corpus.py OUT_DIR --backends nested --out FILE.json --md FILE.md

The dev zoo's CAD parts are the ones the defaults were developed on. These are made in code by exact
booleans (``manifold3d``, a dependency), so their triangles are what a CAD export gives: long slivers across
flat faces, sharp edges, fans around holes. None of them was used to choose any default:

* ``flange``: a disc with a hub, a bore and six bolt holes (genus 7);
* ``lbracket``: an L-bracket with a gusset, two slots and a cross hole (genus 3);
* ``heatsink``: a base plate with twelve thin fins (genus 0, fins 1/40 of the length thick);
* ``pipetee``: two hollow cylinders crossing (genus 2, thin walls);
* ``lattice``: a cube pierced by 3x3 square channels along z and 3x3 narrower ones along y, crossing them;
* ``cup``: a thin-walled cylinder cup, walls 1% of its height thick (added after the first five were run);
* ``shell``: a sphere shell 2.7% of its radius thick with a square window (likewise).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def _parts() -> dict:
    """The parts as ``manifold3d.Manifold`` solids (millimetres)."""
    from manifold3d import Manifold as M

    flange = M.cylinder(10, 50, 50, 64) + M.cylinder(30, 22, 22, 64)
    flange -= M.cylinder(80, 12, 12, 48).translate((0, 0, -20))
    for a in 2 * np.pi * np.arange(6) / 6:
        flange -= M.cylinder(40, 4, 4, 24).translate((36 * np.cos(a), 36 * np.sin(a), -10))

    bracket = M.cube((80, 40, 6)) + M.cube((6, 40, 50))
    bracket += M.hull_points([(6, 17, 6), (6, 23, 6), (40, 17, 6), (40, 23, 6), (6, 17, 40), (6, 23, 40)])
    for y in (8, 32):
        bracket -= M.hull(M.cylinder(20, 3, 3, 20).translate((30, y, -5))
                          + M.cylinder(20, 3, 3, 20).translate((60, y, -5)))
    bracket -= M.cylinder(20, 5, 5, 24).rotate((0, 90, 0)).translate((-5, 20, 35))

    sink = M.cube((60, 40, 4))
    for k in range(12):
        sink += M.cube((1.5, 40, 25)).translate((2 + 4.85 * k, 0, 4))

    def tee(r: float, grow: float) -> M:
        return (M.cylinder(100 + 2 * grow, r, r, 48).translate((0, 0, -50 - grow))
                + M.cylinder(50 + 2 * grow, r, r, 48).rotate((90, 0, 0)))

    lattice = M.cube((30, 30, 30))
    for i in range(3):
        for j in range(3):
            u, v = 3 + 10 * i, 3 + 10 * j
            lattice -= M.cube((4, 4, 40)).translate((u, v, -5))
            lattice -= M.cube((3, 40, 3)).translate((u + 0.5, -5, v + 0.5))  # no wall shared with the above
    cup = M.cylinder(40, 20, 20, 96) - M.cylinder(40, 19.6, 19.6, 96).translate((0, 0, 0.4))
    shell = M.sphere(30, 96) - M.sphere(29.2, 96) - M.cube((20, 20, 20)).translate((20, -10, -10))
    return {"flange": flange, "lbracket": bracket, "heatsink": sink, "pipetee": tee(10, 0) - tee(8, 1),
            "lattice": lattice, "cup": cup, "shell": shell}


def write_parts(out: Path) -> list[Path]:
    """Write every part as ``OUT/NAME.stl``; returns the paths."""
    from nestmg.io import save_mesh

    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, solid in _parts().items():
        mesh = solid.to_mesh()
        V = np.asarray(mesh.vert_properties, dtype=float)[:, :3]
        F = np.asarray(mesh.tri_verts, dtype=np.int64)
        paths.append(out / f"{name}.stl")
        save_mesh(paths[-1], V, F)
        print(f"{paths[-1].name}: {len(F)} faces, genus {solid.genus()}")
    return paths


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("out", type=Path, help="folder the STL files are written to")
    write_parts(ap.parse_args(argv).out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
