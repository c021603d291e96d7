"""Timing of the nesting verifier and of the intersection tests it could use, on a ~50k-face pair.

Fine layer: the genus-2 procedural shape meshed at ~51k faces; coarse layer: its iso-surface at offset
0.05 meshed at ~15k faces (procedurally nested). Prints one JSON object; saves a bar chart next to
itself (``bench_verify.png``) unless ``--no-plot``.

Measured figures:
* ``verify``: ``verify_nesting`` wall time with exact and with fast winding numbers, and per-part times;
* ``self_intersection``: CGAL ``remesh_self_intersections(detect_only=True)`` vs ipctk
  ``has_intersections`` (CollisionMesh build included) on the 51k-face layer;
* ``cross_intersection``: CGAL ``intersect_other(detect_only=True)`` vs ipctk ``has_intersections`` on
  both layers as one CollisionMesh (which also tests self-intersections, and only answers yes/no).

Usage (from the repo root, or with nestmg installed): ``PYTHONPATH=. python benchmarks/bench_verify.py [--repeat 3]``
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


def best_of(fn, repeat: int) -> tuple[float, object]:
    best, out = np.inf, None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def main() -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--no-plot", action="store_true")
    args = ap.parse_args()

    import igl
    import ipctk
    from igl.copyleft import cgal

    from cagegen import verify_nesting
    from cagegen._geometry import min_edge_edge_distance
    from nestmg.shapes import nested_isosurfaces

    (Vf, Ff), (Vc, Fc) = nested_isosurfaces("genus2", [0.0, 0.05], [126, 63])
    r = args.repeat
    res: dict = {"load_average": list(__import__("os").getloadavg()), "fine": {"vertices": len(Vf), "faces": len(Ff)}, "coarse": {"vertices": len(Vc), "faces": len(Fc)}}

    t_exact, rep = best_of(lambda: verify_nesting([(Vf, Ff), (Vc, Fc)]), r)
    t_fast, rep_fast = best_of(lambda: verify_nesting([(Vf, Ff), (Vc, Fc)], exact_winding=False), r)
    t_noself, _ = best_of(lambda: verify_nesting([(Vf, Ff), (Vc, Fc)], check_self=False), r)
    parts = {
        "winding_exact": best_of(lambda: (igl.winding_number(Vc, Fc, Vf), igl.winding_number(Vf, Ff, Vc)), r)[0],
        "winding_fast": best_of(
            lambda: (igl.fast_winding_number(Vc, Fc, Vf), igl.fast_winding_number(Vf, Ff, Vc)), r
        )[0],
        "distances": best_of(
            lambda: (igl.point_mesh_squared_distance(Vf, Vc, Fc), igl.point_mesh_squared_distance(Vc, Vf, Ff)), r
        )[0],
        "edge_edge_gap_search": best_of(
            lambda: min_edge_edge_distance(Vf, Ff, Vc, Fc, 1e-3 * np.linalg.norm(Vf.max(0) - Vf.min(0))), r
        )[0],
        "cross_cgal": best_of(lambda: cgal.intersect_other(Vf, Ff, Vc, Fc, detect_only=True), r)[0],
        "self_cgal_both": best_of(
            lambda: (cgal.remesh_self_intersections(Vf, Ff, detect_only=True),
                     cgal.remesh_self_intersections(Vc, Fc, detect_only=True)), r
        )[0],
    }
    res["verify"] = {
        "ok": rep.ok,
        "ok_fast_winding": rep_fast.ok,
        "min_winding": rep.pairs[0].min_winding,
        "min_gap_rel": rep.pairs[0].min_gap_rel,
        "seconds_exact_winding": t_exact,
        "seconds_fast_winding": t_fast,
        "seconds_without_self_check": t_noself,
        "parts": parts,
    }

    def ipc_self(V, F):
        cm = ipctk.CollisionMesh(V, ipctk.edges(F), F)
        return ipctk.has_intersections(cm, V)

    res["self_intersection"] = {
        "faces": len(Ff),
        "cgal_detect_only": best_of(lambda: cgal.remesh_self_intersections(Vf, Ff, detect_only=True), r)[0],
        "ipctk_has_intersections": best_of(lambda: ipc_self(Vf, Ff), r)[0],
    }
    V2 = np.vstack([Vf, Vc])
    F2 = np.vstack([Ff, Fc + len(Vf)])
    # a crossing pair too: the coarse layer pushed sideways by 0.2
    Vs = Vc + [0.2, 0.0, 0.0]
    V3 = np.vstack([Vf, Vs])
    t_cross_c, out_c = best_of(lambda: cgal.intersect_other(Vf, Ff, Vs, Fc, detect_only=True), r)
    res["cross_intersection"] = {
        "nested_pair": {
            "cgal_intersect_other": parts["cross_cgal"],
            "ipctk_has_intersections_combined": best_of(lambda: ipc_self(V2, F2), r)[0],
        },
        "crossing_pair": {
            "cgal_intersect_other": t_cross_c,
            "cgal_pairs_found": len(out_c[0]),
            "ipctk_has_intersections_combined": best_of(lambda: ipc_self(V3, F2), r)[0],
        },
    }
    print(json.dumps(res, indent=2))

    if not args.no_plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        labels = list(parts) + ["verify (exact)", "verify (fast)"]
        vals = list(parts.values()) + [t_exact, t_fast]
        fig, ax = plt.subplots(figsize=(7, 3.2))
        ax.barh(labels, vals, color="tab:blue")
        ax.set_xlabel(f"seconds (best of {r})")
        ax.set_title(f"verify_nesting on {len(Ff)} / {len(Fc)} faces")
        fig.tight_layout()
        fig.savefig(Path(__file__).with_suffix(".png"), dpi=120)
    return res


if __name__ == "__main__":
    main()
