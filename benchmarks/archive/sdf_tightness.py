"""Where does the ``sdf`` cage's distance to the input come from? One layer, phase by phase (issue 17).

For each mesh, one ``sdf`` layer at ``n / --div`` faces is built phase by phase with the backend's own
functions and defaults (envelope, plain-QEM pre-pass, constrained simplification, optimisation), and after
every phase the JSON records both one-sided distances over the input's bounding-box diagonal -- cage
vertices to the input (``cage_to_input``) and input vertices to the cage (``input_to_cage``: large where
the cage bridges a concavity) -- with the point where each is largest, the genus, the face count and the
CPU seconds of the phase. ``--pull w1 w2 ...`` optimises the same simplified cage once per weight of the
input-to-cage pull (``optimize_cage(..., w_p=w, pull_target=c)``; 0 = the paper's energy), each result
certified by ``verify_nesting``. ``--norm radius`` scales ``c``, ``r``, ``l`` and ``1/beta`` as the paper's
normalisation "into unit circle" does (lengths relative to the largest distance of a vertex from the
bounding-box centre instead of the diagonal). ``--dhat d1 d2 ...`` adds one optimised cage per barrier
activation distance (units of ``c``; default: the backend's), ``--concave t`` builds the envelope with
``build_envelope(..., concave=t)``, ``--h-div k`` on a grid of spacing ``c / k`` (the backend's refined grids),
``--bridges`` records where the envelope and each optimised cage bridge the input (clusters of input
vertices farther than 1.5 ``c``, each with the width of the outside channel toward the cage), and ``--gaps``
how far apart the nearly-touching parts are (at the active points) on the input and on each optimised cage. No retries: a
crossing envelope or a stuck simplification is recorded as such.

Usage::

    nice -n 10 python benchmarks/archive/sdf_tightness.py ZOO_DIR --meshes bunny.off gargo.off homer.obj \\
        --norm diagonal --out benchmarks/results/sdf/tightness_diagonal.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # archived: exp_common.py is in benchmarks/
from exp_common import read_mesh  # noqa: E402


def _default(name):
    import inspect

    from cagegen.sdf.backend import sdf_cage_layer

    return inspect.signature(sdf_cage_layer).parameters[name].default


_DHAT = _default("dhat")  # the backend's barrier activation distance (units of c); the JSON key has no suffix


def _distances(U, G, V, F, diag) -> dict:
    import igl

    from cagegen.sdf.backend import _min_angle_deg, genus
    from cagegen.sdf.optimize import mips

    dc = np.sqrt(igl.point_mesh_squared_distance(U, V, F)[0])
    di = np.sqrt(igl.point_mesh_squared_distance(V, U, G)[0])
    return {"faces": len(G), "genus": genus(U, G),
            "cage_to_input_max": float(dc.max()) / diag, "cage_to_input_argmax": U[int(np.argmax(dc))].tolist(),
            "input_to_cage_max": float(di.max()) / diag, "input_to_cage_argmax": V[int(np.argmax(di))].tolist(),
            "hausdorff": float(igl.hausdorff(U, G, V, F)) / diag,
            "min_angle_deg": _min_angle_deg(U, G), "mips_mean": float(mips(U, G).mean())}


def _bridges(U, G, V, F, c, top: int = 6) -> list:
    """Where the cage bridges the input: clusters (edge-connected) of input vertices farther than 1.5 ``c`` from
    the cage, largest distance first. Per cluster: size, largest distance (in ``c``), that vertex, and the
    *channel profile* between it and its closest cage point: 2 x the signed distance to the input at 5
    points of that segment (t = 0.1 ... 0.9, in ``c``) -- the width of the outside channel the cage would
    have to enter (a slit: small and constant; a wedge: growing toward the cage; negative: the segment
    passes through the input, an undercut)."""
    import igl
    from scipy.sparse.csgraph import connected_components

    from cagegen.sdf.envelope import _edge_graph, _signed

    d2, _, Q = igl.point_mesh_squared_distance(V, U, G)
    d = np.sqrt(d2)
    far = np.flatnonzero(d > 1.5 * c)
    if len(far) == 0:
        return []
    n, lab = connected_components(_edge_graph(V, F)[far][:, far], directed=False)
    out = []
    for k in range(n):
        ids = far[lab == k]
        j = int(ids[np.argmax(d[ids])])
        t = np.array([0.1, 0.3, 0.5, 0.7, 0.9])
        P = V[j] + t[:, None] * (Q[j] - V[j])
        sd = _signed(P, V, F, 10 * c)[0]
        out.append({"n_vertices": len(ids), "max_c": float(d[j] / c), "vertex": V[j].tolist(),
                    "channel_width_c": (2 * sd / c).round(2).tolist()})
    out.sort(key=lambda x: -x["max_c"])
    return out[:top]


def _part_gaps(V, F, r: float, l: float) -> dict:
    """How far apart the nearly-touching parts are: for each active vertex ``p`` (the paper's criterion,
    :func:`cagegen.sdf.envelope.active_points`), the distance to the nearest triangle within ``r`` none of
    whose corners is within ``l`` of ``p`` along the surface. Two nested layers with offsets ``o1``, ``o2``
    keep two parts separated only if that gap exceeds about ``2 (o1 + o2)``."""
    from scipy.sparse.csgraph import dijkstra
    from scipy.spatial import cKDTree

    from cagegen.sdf.envelope import _edge_graph, active_points
    from cagegen.sdf.simplify import _point_triangle_sqdist

    A = active_points(V, F, r, l)
    if len(A) == 0:
        return {"n_active": 0}
    G = _edge_graph(V, F)
    cen = V[F].mean(axis=1)
    rad = float(np.linalg.norm(V[F] - cen[:, None, :], axis=2).max())
    tree = cKDTree(cen)
    gaps = np.full(len(A), np.inf)
    D = dijkstra(G, directed=False, indices=A, limit=l)
    for k, p in enumerate(A):
        f = np.asarray(tree.query_ball_point(V[p], r + rad), dtype=np.int64)
        if len(f) == 0:
            continue
        f = f[~np.isfinite(D[k][F[f]]).any(axis=1)]
        if len(f):
            X = V[F[f]]
            gaps[k] = np.sqrt(_point_triangle_sqdist(np.repeat(V[p][None], len(f), 0), X[:, 0], X[:, 1], X[:, 2]).min())
    ok = np.isfinite(gaps)
    j = int(A[np.argmin(gaps)])
    return {"n_active": int(len(A)), "gap_min": float(gaps[ok].min()), "gap_median": float(np.median(gaps[ok])),
            "gap_min_vertex": V[j].tolist()}


def run_mesh(path: Path, div: int, norm: str, pulls=(0.0,), iters: int = 15, concave: float = 0.0,
             h_div: float = 1.0, bridges: bool = False, dhats=(_DHAT,), gaps: bool = False) -> dict:
    from cagegen._geometry import bbox_diagonal, cross_intersection_pairs
    from cagegen.sdf.backend import DEFAULTS, _prepass, genus
    from cagegen.sdf.envelope import build_envelope
    from cagegen.sdf.optimize import optimize_cage
    from cagegen.sdf.simplify import SimplifyStuck, constrained_simplify

    V, F = read_mesh(path)
    Vn = (V - 0.5 * (V.min(0) + V.max(0))) / bbox_diagonal(V)  # unit diagonal, as the backend
    s = float(np.linalg.norm(Vn, axis=1).max()) if norm == "radius" else 1.0
    c, r, l, beta = DEFAULTS["c"] * s, DEFAULTS["r"] * s, DEFAULTS["l"] * s, DEFAULTS["beta"] / s
    n = int(2 * round(len(F) / div / 2))
    rec: dict = {"mesh": path.name, "input_faces": len(F), "target": n, "norm": norm, "scale": s,
                 "c": c, "r": r, "l": l, "beta": beta, "concave": concave, "h": c / h_div,
                 "genus_input": genus(Vn, F), "phases": {},
                 "loadavg_1min": [os.getloadavg()[0]]}
    t = time.process_time()
    env = build_envelope(Vn, F, c=c, h=c / h_div, r=r, l=l, beta=beta, concave=concave)
    rec["phases"]["envelope"] = {**_distances(env.V, env.F, Vn, F, 1.0), "cpu_seconds": time.process_time() - t,
                                 "n_active": env.info["n_active"], "concave": env.info.get("concave"),
                                 "crossings": len(cross_intersection_pairs(env.V, env.F, Vn, F))}
    if bridges:
        rec["phases"]["envelope"]["bridges"] = _bridges(env.V, env.F, Vn, F, c)
    if gaps:
        rec["part_gaps_input"] = _part_gaps(Vn, F, r, l)
    t = time.process_time()
    U, G, pre = _prepass(env.V, env.F, Vn, F, n)
    rec["phases"]["prepass"] = {**_distances(U, G, Vn, F, 1.0), "cpu_seconds": time.process_time() - t,
                                "steps": [(p["faces"], p["ok"]) for p in pre]}
    t = time.process_time()
    try:
        U, G, si = constrained_simplify(U, G, Vn, F, n, env.sdf, margin=0.3 * c)
    except SimplifyStuck as exc:
        rec["phases"]["simplified"] = {"error": str(exc), "cpu_seconds": time.process_time() - t}
        return rec
    rec["phases"]["simplified"] = {**_distances(U, G, Vn, F, 1.0), "cpu_seconds": time.process_time() - t,
                                   "collapses": si["collapses"]}
    from cagegen import verify_nesting

    for w, dh in [(w, dh) for w in pulls for dh in dhats]:  # every variant starts from the same simplified cage
        t = time.process_time()
        U2, G2, oi = optimize_cage(U, G, Vn, F, h=0.5 * c, dhat=dh * c, iters=iters, flip_rounds=1,
                                   time_limit=30.0, w_p=w, pull_target=c)
        cpu = time.process_time() - t
        rep = verify_nesting([(Vn, F), (U2, G2)])
        key = ("optimized" if w == 0 else f"optimized_pull{w:g}") + ("" if dh == _DHAT else f"_dhat{dh:g}")
        rec["phases"][key] = {
            **_distances(U2, G2, Vn, F, 1.0), "cpu_seconds": cpu, "steps": oi["steps"], "flips": oi["flips"],
            "pull_weight": w, "dhat_c": dh, "iters": iters, "certified": bool(rep.ok), "min_gap": rep.pairs[0].min_gap}
        if bridges:
            rec["phases"][key]["bridges"] = _bridges(U2, G2, Vn, F, c)
        if gaps:  # the optimised cage as the next layer's input
            rec["phases"][key]["part_gaps"] = _part_gaps(U2, G2, r, l)
    rec["cpu_seconds"] = sum(p["cpu_seconds"] for p in rec["phases"].values())
    rec["loadavg_1min"].append(os.getloadavg()[0])
    return rec


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("zoo", type=Path)
    ap.add_argument("--meshes", nargs="+", default=["bunny.off", "gargo.off", "homer.obj"])
    ap.add_argument("--div", type=int, default=4, help="cage faces = input faces / div")
    ap.add_argument("--norm", choices=("diagonal", "radius"), default="diagonal")
    ap.add_argument("--pull", type=float, nargs="+", default=[0.0],
                    help="weights of the input-to-cage pull in the optimisation (0 = the paper's energy); one "
                         "optimised cage per weight, all from the same simplified cage")
    ap.add_argument("--iters", type=int, default=15, help="descent steps per round (the backend's opt_iters)")
    ap.add_argument("--concave", type=float, default=0.0,
                    help="build_envelope's concave threshold in units of c (0 = off, the paper's envelope)")
    ap.add_argument("--h-div", type=float, default=1.0, help="grid spacing h = c / H_DIV (the backend refines "
                    "the grid by 2 or 4 when the envelope's genus is wrong)")
    ap.add_argument("--bridges", action="store_true", help="record where the envelope and the optimised cage "
                    "bridge the input (clusters of input vertices > 1.5 c away, with the channel's width)")
    ap.add_argument("--dhat", type=float, nargs="+", default=[_DHAT],
                    help="barrier activation distances of the optimisation, in units of c (the backend's default "
                         "0.25); one optimised cage per (pull, dhat)")
    ap.add_argument("--gaps", action="store_true", help="record how far apart the nearly-touching parts (active "
                    "points) are, on the input and on each optimised cage (the next layer's input)")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    doc = {"benchmark": "benchmarks/archive/sdf_tightness.py", "command": " ".join(sys.argv), "results": []}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    for name in args.meshes:
        doc["results"].append(run_mesh(args.zoo / name, args.div, args.norm, args.pull, args.iters,
                                        args.concave, args.h_div, args.bridges,
                                        args.dhat, args.gaps))
        args.out.write_text(json.dumps(doc, indent=1, default=float))
        r = doc["results"][-1]
        print(name, {k: (round(100 * v.get("hausdorff", float("nan")), 2), v.get("genus"), round(v["cpu_seconds"], 1))
                     for k, v in r["phases"].items()}, file=sys.stderr, flush=True)
    print(json.dumps(doc, indent=1, default=float))
    return doc


if __name__ == "__main__":
    main()
