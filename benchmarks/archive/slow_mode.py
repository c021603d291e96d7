"""Where the default cycle's slowest error lives: error propagation of the Neumann cycle on a hierarchy.

Builds (or loads from the cache) the default hierarchy of a mesh, runs ``cycles`` applications of the default
Poisson-Neumann cycle's error propagation ``e <- e - M A e`` (mean removed) from a random error, and records
the energy-norm factor of the last ten cycles and where the surviving error sits (the cycle without the
deflation of solvers.deflation, which now corrects such modes): how many fine nodes carry
more than half of its largest magnitude, their bounding box and their distance to the input surface.

    python benchmarks/archive/slow_mode.py MESH [--cycles 40] --out FILE.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np


def slow_mode(path: Path, cycles: int) -> dict:
    import igl

    import nestmg
    from nestmg import SolverOptions

    V, F = nestmg.load_mesh(str(path))
    t = time.perf_counter()
    h = nestmg.build_hierarchy(V, F, 3, "nested", cache=True, progress=False)
    tets = h.tets_in("normalized")
    p = nestmg.setup_problem(tets, h.P, "poisson-neumann")
    A, M = p.A, p.multigrid(SolverOptions(), deflate=0).aspreconditioner()  # the cycle before deflation
    e = np.random.default_rng(0).standard_normal(A.shape[0])
    e -= e.mean()
    energy = []
    for _ in range(cycles):
        e = e - M @ (A @ e)
        e -= e.mean()
        energy.append(float(np.sqrt(e @ (A @ e))))
    mag = np.abs(e) / np.abs(e).max()
    Vf = tets[0][0][: A.shape[0]]
    Vn = nestmg.normalize(V)[0]
    d = np.sqrt(igl.point_mesh_squared_distance(Vf, Vn, np.asarray(F, dtype=np.int64))[0])
    top = mag > 0.5
    return {"mesh": path.name, "tets": [len(T) for _, T in h.tets], "certified": h.certified,
            "cycles": cycles, "energy_factor_last10": (energy[-1] / energy[-11]) ** 0.1,
            "n_fine_nodes": int(A.shape[0]), "n_top_nodes": int(top.sum()),
            "top_bbox": [Vf[top].min(axis=0).tolist(), Vf[top].max(axis=0).tolist()],
            "top_median_distance_to_surface": float(np.median(d[top])),
            "all_median_distance_to_surface": float(np.median(d)),
            "magnitude_quantiles_50_90_99": np.quantile(mag, [0.5, 0.9, 0.99]).tolist(),
            "seconds": time.perf_counter() - t}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("meshes", nargs="+", type=Path)
    ap.add_argument("--cycles", type=int, default=40)
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args(argv)
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from exp_common import git_commit, write_json

    rows = []
    for p in a.meshes:
        rows.append(slow_mode(p, a.cycles))
        print(json.dumps(rows[-1]), flush=True)
        write_json({"command": f"python benchmarks/archive/slow_mode.py MESH ... --cycles {a.cycles}",
                    "commit": git_commit(), "rows": rows}, a.out)


if __name__ == "__main__":
    main()
