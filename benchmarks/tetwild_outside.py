"""fTetWild's cost against the box it meshes: a uniform box, or a coarse outside (``outer_edge_factor``).

fTetWild meshes and optimises the whole bounding box at the target edge and drops the outside at the end,
so its time follows the box's volume rather than the solid's. For each mesh this script does what
``build_hierarchy`` does before its fine tet mesh (normalise, plan the sizes with the defaults,
predecimate) and meshes the same surface at the same edge twice, in the same process, with one thread
and no time limit: uniform (``outer_edge_factor=1``) and graded (``outer_edge_factor=F``). CPU seconds,
tets and the box / solid volume ratio go to the JSON (``benchmarks/results/tetwild/``).

    python benchmarks/tetwild_outside.py ZOO_DIR/homer.obj ZOO_DIR/bunny.off ... --out OUT.json
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from exp_common import cpu_seconds, mesh_rows_main, read_mesh


def _meshed_surface(path: Path) -> tuple[np.ndarray, np.ndarray, float, dict]:
    """The surface and edge the pipeline's fine TetWild call gets with the defaults (normalised frame)."""
    from cagegen import normalize
    from nestmg import SizingOptions
    from nestmg.hierarchy import _plan, predecimate

    V, F = read_mesh(path)
    Vn = normalize(V)[0]
    plan = _plan(Vn, F, 3, SizingOptions(), "tetwild", True)
    h = 2.0 * plan.edge_length  # the default fine level is one red refinement of the mesh at 2h
    S, G, pre = predecimate(Vn, F, h, max_error=max(1e-3, 0.25 * h))
    return S, G, h, {"faces_in": len(F), "faces_meshed": len(G), "edge": h, "rule": plan.rule}


def timed_mesh(S: np.ndarray, G: np.ndarray, h: float, label: str, **options) -> dict:
    """One thread, no time limit: CPU and wall seconds, tets and the smallest dihedral angle (printed
    after ``label``)."""
    from nestmg.tetmesh import tet_quality, tetrahedralize

    c, t = cpu_seconds(), time.perf_counter()
    Vt, T = tetrahedralize(S, G, edge_length_abs=h, threads=1, time_limit=None, **options)
    q = tet_quality(Vt, T)
    row = {"cpu_seconds": cpu_seconds() - c, "wall_seconds": time.perf_counter() - t, "tets": int(len(T)),
           "min_dihedral_deg": float(q.get("min_dihedral_deg", np.nan))}
    print(f"{label}: {row['cpu_seconds']:.1f} CPU s, {row['tets']:,} tets", flush=True)
    return row


def measure(path: Path, factor: float) -> dict:
    from nestmg.memory import enclosed_volume
    from nestmg.sizing import expected_tets
    from nestmg.tetmesh import box_ratio

    S, G, h, row = _meshed_surface(path)
    row.update(mesh=path.name, box_ratio=box_ratio(S, G),
               expected_solid_tets=expected_tets(enclosed_volume(S, G), h))
    for f in (1.0, factor):
        key = "uniform" if f == 1.0 else "graded"
        row[key] = {"factor": f, **timed_mesh(S, G, h, f"{path.name}: {key}", outer_edge_factor=f)}
    row["cpu_ratio_graded_over_uniform"] = row["graded"]["cpu_seconds"] / row["uniform"]["cpu_seconds"]
    return row


def main(argv: list[str] | None = None) -> None:
    mesh_rows_main("tetwild_outside.py", __doc__.splitlines()[0], measure,
                   ("factor", 3.0, "outer_edge_factor of the graded run"), argv)


if __name__ == "__main__":
    sys.exit(main())
