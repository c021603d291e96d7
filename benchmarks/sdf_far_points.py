"""Where is an ``sdf`` cage farthest from its input, and can a cage vertex get there? (issue 17)

For each mesh, one ``sdf`` layer at the 4x level is built with the backend's defaults except
``--tighten`` (default 0: the optimised cage the tightening pass starts from). For the ``--k`` input
vertices farthest from the cage, the JSON records the distance, the position (unit-diagonal frame of the
backend), and the smallest signed distance to the input along the straight segment from the vertex to
its closest cage point (``--samples`` points): positive and tiny = the segment squeezes through a crevice
that narrow; negative = the closest cage point is behind the input (an undercut). That is the path the
pull and the tightening pass would drag a cage vertex along. The other side of the Hausdorff distance is
recorded too: the cage point farthest from the input (faces sampled on a barycentric grid), with its
face's longest edge beside the cage's median edge (a coarse cage's face spanning a concavity).

Usage::

    python benchmarks/sdf_far_points.py ZOO_DIR --meshes homer.obj --k 12 \\
        --out benchmarks/results/sdf/far_points_homer.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from exp_common import read_mesh


def far_points(V: np.ndarray, F: np.ndarray, n_faces: int, k: int, samples: int, tighten: float) -> dict:
    import igl

    from cagegen.sdf.backend import sdf_cage_layer

    c0 = time.process_time()
    U, G, info = sdf_cage_layer(V, F, n_faces, tighten=tighten)
    cpu = time.process_time() - c0
    lo, hi = V.min(0), V.max(0)
    center, unit = 0.5 * (lo + hi), float(np.linalg.norm(hi - lo))
    Vn, Un = (V - center) / unit, (U - center) / unit
    d2, _, Q = igl.point_mesh_squared_distance(Vn, Un, G)
    d = np.sqrt(d2)
    order = np.argsort(-d)[:k]
    t = np.linspace(0.05, 0.95, samples)
    rows = []
    for i in order:
        P = Vn[i] + t[:, None] * (Q[i] - Vn[i])
        s = igl.signed_distance(P, Vn, F)[0]
        rows.append({"vertex": int(i), "distance": float(d[i]), "position": np.round(Vn[i], 4).tolist(),
                     "min_signed_distance_on_path": float(s.min())})
    m = 12  # barycentric grid on every cage face for the cage-to-input side
    bc = np.array([(i / m, j / m, 1 - (i + j) / m) for i in range(m + 1) for j in range(m + 1 - i)])
    S = np.einsum("bk,fkd->fbd", bc, Un[G]).reshape(-1, 3)
    dc = np.sqrt(igl.point_mesh_squared_distance(S, Vn, F)[0])
    j = int(dc.argmax())
    f = G[j // len(bc)]
    edges = np.linalg.norm(Un[G] - Un[np.roll(G, 1, axis=1)], axis=2)
    return {"n_faces": n_faces, "tighten": tighten, "cpu_seconds": cpu, "hausdorff": info["hausdorff_relative"],
            "input_to_cage_max": float(d.max()), "beyond_1.5c": int((d > 0.015).sum()), "farthest": rows,
            "cage_to_input_max": float(dc.max()), "cage_to_input_at": np.round(S[j], 4).tolist(),
            "its_face_longest_edge": float(np.linalg.norm(Un[f] - Un[np.roll(f, 1)], axis=1).max()),
            "median_cage_edge": float(np.median(edges))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("mesh_dir")
    ap.add_argument("--meshes", nargs="+", required=True)
    ap.add_argument("--k", type=int, default=12)
    ap.add_argument("--samples", type=int, default=19)
    ap.add_argument("--tighten", type=float, default=0.0)
    ap.add_argument("--out", required=True)
    a = ap.parse_args()
    from cagegen import default_face_counts

    res = {"tighten": a.tighten, "results": {}}
    for name in a.meshes:
        V, F = read_mesh(Path(a.mesh_dir) / name)
        V, F = np.asarray(V, float), np.asarray(F, np.int64)
        res["results"][name] = far_points(V, F, default_face_counts(len(F), 2)[0], a.k, a.samples, a.tighten)
        print(json.dumps({name: res["results"][name]}, indent=1), flush=True)
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
