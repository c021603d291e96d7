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
bounding-box centre instead of the diagonal). No retries: a crossing envelope or a stuck simplification
is recorded as such.

Usage::

    nice -n 10 python benchmarks/sdf_tightness.py /work/shared/data/meshes --meshes bunny.off gargo.off homer.obj \\
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

sys.path.insert(0, str(Path(__file__).resolve().parent))
from cages import _read


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


def run_mesh(path: Path, div: int, norm: str, pulls=(0.0,), iters: int = 15) -> dict:
    from cagegen._geometry import bbox_diagonal, cross_intersection_pairs
    from cagegen.sdf.backend import DEFAULTS, _prepass, genus
    from cagegen.sdf.envelope import build_envelope
    from cagegen.sdf.optimize import optimize_cage
    from cagegen.sdf.simplify import SimplifyStuck, constrained_simplify

    V, F = _read(path)
    Vn = (V - 0.5 * (V.min(0) + V.max(0))) / bbox_diagonal(V)  # unit diagonal, as the backend
    s = float(np.linalg.norm(Vn, axis=1).max()) if norm == "radius" else 1.0
    c, r, l, beta = DEFAULTS["c"] * s, DEFAULTS["r"] * s, DEFAULTS["l"] * s, DEFAULTS["beta"] / s
    n = int(2 * round(len(F) / div / 2))
    rec: dict = {"mesh": path.name, "input_faces": len(F), "target": n, "norm": norm, "scale": s,
                 "c": c, "r": r, "l": l, "beta": beta, "genus_input": genus(Vn, F), "phases": {},
                 "loadavg_1min": [os.getloadavg()[0]]}
    t = time.process_time()
    env = build_envelope(Vn, F, c=c, h=c, r=r, l=l, beta=beta)
    rec["phases"]["envelope"] = {**_distances(env.V, env.F, Vn, F, 1.0), "cpu_seconds": time.process_time() - t,
                                 "n_active": env.info["n_active"],
                                 "crossings": len(cross_intersection_pairs(env.V, env.F, Vn, F))}
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

    for w in pulls:  # every variant of the optimisation starts from the same simplified cage
        t = time.process_time()
        U2, G2, oi = optimize_cage(U, G, Vn, F, h=0.5 * c, dhat=0.25 * c, iters=iters, flip_rounds=1,
                                   time_limit=30.0, w_p=w, pull_target=c)
        cpu = time.process_time() - t
        rep = verify_nesting([(Vn, F), (U2, G2)])
        rec["phases"]["optimized" if w == 0 else f"optimized_pull{w:g}"] = {
            **_distances(U2, G2, Vn, F, 1.0), "cpu_seconds": cpu, "steps": oi["steps"], "flips": oi["flips"],
            "pull_weight": w, "iters": iters, "certified": bool(rep.ok), "min_gap": rep.pairs[0].min_gap}
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
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    doc = {"benchmark": "benchmarks/sdf_tightness.py", "command": " ".join(sys.argv), "results": []}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    for name in args.meshes:
        doc["results"].append(run_mesh(args.zoo / name, args.div, args.norm, args.pull, args.iters))
        args.out.write_text(json.dumps(doc, indent=1, default=float))
        r = doc["results"][-1]
        print(name, {k: (round(100 * v.get("hausdorff", float("nan")), 2), v.get("genus"), round(v["cpu_seconds"], 1))
                     for k, v in r["phases"].items()}, file=sys.stderr, flush=True)
    print(json.dumps(doc, indent=1, default=float))
    return doc


if __name__ == "__main__":
    main()
