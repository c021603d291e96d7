"""The verifier's edge-edge search: per-edge ball queries (before) against pairs of length-grouped k-d trees.

    OMP_NUM_THREADS=1 python benchmarks/archive/edge_edge_search.py ZOO_DIR/homer.obj ZOO_DIR/pepper.ply \
        --repeats 5 --out benchmarks/results/audit/edge_edge_search.json

For each mesh: its default nested cages (``build_cages(V, F, 3, "nested", min_gap=0.0025)``), then for each
consecutive pair the search at the verifier's bound (the vertex-face gap, as in ``cagegen.verify``), both ways
interleaved, median CPU seconds of ``--repeats``; the two results must agree to round-off.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import time
from pathlib import Path

import igl
import numpy as np
from scipy.spatial import cKDTree

from cagegen import build_cages
from cagegen._geometry import bbox_diagonal, min_edge_edge_distance, segment_segment_sqdist
from nestmg.io import load_mesh


def ball_queries(VA, FA, VB, FB, bound: float, chunk: int = 2_000_000) -> float:
    """The search as it was before: the stored edges grouped by length, one ball query per query edge."""
    def unique_edges(F):
        return np.unique(np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1), axis=0)

    EA, EB = unique_edges(FA), unique_edges(FB)
    A0, A1, B0, B1 = VA[EA[:, 0]], VA[EA[:, 1]], VB[EB[:, 0]], VB[EB[:, 1]]
    hA, hB = 0.5 * np.linalg.norm(A1 - A0, axis=1), 0.5 * np.linalg.norm(B1 - B0, axis=1)
    if hB.max() > hA.max():
        A0, A1, B0, B1, hA, hB = B0, B1, A0, A1, hB, hA
    best = float(bound) ** 2
    edges = 2.0 * max(float(np.median(hB)), 1e-300) * 2.0 ** np.arange(64)
    cls = np.searchsorted(edges, hB)
    mA = 0.5 * (A0 + A1)
    for c in np.unique(cls):
        sel = np.flatnonzero(cls == c)
        b0, b1, hb = B0[sel], B1[sel], hB[sel]
        mB = 0.5 * (b0 + b1)
        tree = cKDTree(mB)
        radius = min(float(bound), np.sqrt(best)) + hA + hb.max()
        counts = tree.query_ball_point(mA, r=radius, return_length=True)
        ends, start = np.cumsum(counts), 0
        while start < len(A0):
            base = ends[start - 1] if start else 0
            stop = max(start + 1, int(np.searchsorted(ends, base + chunk, side="right")))
            if ends[stop - 1] > base:
                lists = tree.query_ball_point(mA[start:stop], r=radius[start:stop])
                lens = np.fromiter((len(x) for x in lists), dtype=np.int64, count=len(lists))
                ia = np.repeat(np.arange(start, stop), lens)
                ib = np.concatenate([np.asarray(x, dtype=np.int64) for x in lists if len(x)])
                dm = np.linalg.norm(mA[ia] - mB[ib], axis=1)
                near = dm < np.sqrt(best) + hA[ia] + hb[ib]
                ia, ib = ia[near], ib[near]
                if len(ia):
                    best = min(best, float(segment_segment_sqdist(A0[ia], A1[ia], b0[ib], b1[ib]).min()))
            start = stop
    return float(np.sqrt(best))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("meshes", nargs="+", type=Path)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    rows = []
    for mesh in args.meshes:
        V, F = load_mesh(mesh)
        layers = build_cages(V, F, 3, "nested", min_gap=0.0025)
        diag = bbox_diagonal(layers[0][0])
        for k in range(len(layers) - 1):
            (Vf, Ff), (Vc, Fc) = layers[k], layers[k + 1]
            g_v = float(np.sqrt(min(igl.point_mesh_squared_distance(Vf, Vc, Fc)[0].min(),
                                    igl.point_mesh_squared_distance(Vc, Vf, Ff)[0].min())))
            bound = min(g_v, 0.01 * diag)
            t = {"ball_queries": [], "tree_pairs": []}
            got = {}
            for _ in range(args.repeats):
                for name, fn in (("ball_queries", ball_queries), ("tree_pairs", min_edge_edge_distance)):
                    c = time.process_time()
                    got[name] = fn(Vf, Ff, Vc, Fc, bound)
                    t[name].append(time.process_time() - c)
            assert abs(got["ball_queries"] - got["tree_pairs"]) <= 1e-12 * diag, got
            rows.append({"mesh": mesh.name, "pair": [k, k + 1], "faces": [len(Ff), len(Fc)],
                         "bound_rel": bound / diag, "gap_rel": got["tree_pairs"] / diag,
                         **{f"{n}_cpu_median": float(np.median(v)) for n, v in t.items()},
                         "ratio": float(np.median(t["ball_queries"]) / np.median(t["tree_pairs"]))})
            print(rows[-1], flush=True)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=False).stdout.strip()
    args.out.write_text(json.dumps({"command": "OMP_NUM_THREADS=1 python benchmarks/archive/edge_edge_search.py "
                                    "ZOO_DIR/homer.obj ZOO_DIR/pepper.ply --repeats 5 --out FILE",
                                    "commit": commit, "clock": "process_time", "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
