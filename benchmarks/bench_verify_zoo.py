"""The verifier on real hierarchies from the dev mesh zoo: nested cages vs naive decimations.

For each mesh: (a) the reference wheel's nested cages (``pip install nested-cages==0.1.0``, the
``bench`` extra; skipped if absent; 30-70 s per mesh), (b) ``build_cages(method="decimate")``.
Each hierarchy goes through :func:`cagegen.verify_nesting` with exact and with fast winding numbers.
Prints one JSON object; saves ``bench_verify_zoo.png`` (fine vertices outside the next layer, per
pair) unless ``--no-plot``.

Usage: ``PYTHONPATH=. python benchmarks/bench_verify_zoo.py ZOO_DIR [--meshes gargo] [--faces 1000 500]``
(``ZOO_DIR``: the folder of the dev-zoo meshes; default ``$NESTMG_ZOO``)
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np


def pair_rows(rep) -> list[dict]:
    return [
        {
            "pair": f"{p.fine}->{p.coarse}",
            "faces": [p.n_faces_fine, p.n_faces_coarse],
            "ok": p.ok,
            "min_winding": p.min_winding,
            "n_outside_vertices": p.n_outside_vertices,
            "n_intersecting_pairs": p.n_intersecting_pairs,
            "min_gap_rel": p.min_gap_rel,
            "seconds": p.seconds,
        }
        for p in rep.pairs
    ]


def main() -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("zoo", type=Path, nargs="?", default=os.environ.get("NESTMG_ZOO"),
                    help="folder of the dev-zoo meshes (default: $NESTMG_ZOO)")
    ap.add_argument("--meshes", nargs="+", default=["gargo"])
    ap.add_argument("--faces", nargs="+", type=int, default=[1000, 500])
    ap.add_argument("--no-plot", action="store_true")
    args = ap.parse_args()
    if args.zoo is None:
        ap.error("give the mesh folder ZOO_DIR (or set NESTMG_ZOO)")

    import igl

    from cagegen import build_cages, verify_nesting

    try:
        import nested_cages
    except ImportError:
        nested_cages = None

    out: dict = {"face_counts": args.faces, "meshes": {}}
    for name in args.meshes:
        path = next(Path(args.zoo).glob(f"{name}.*"))
        V, F = igl.read_triangle_mesh(str(path))
        F = F.astype(np.int64)
        res: dict = {"faces": len(F)}
        hierarchies = {}
        if nested_cages is not None:
            t = time.perf_counter()
            cages = nested_cages.nested_cages(
                V, F, num_faces=list(args.faces), quad_order=2, energy_expansion="None",
                energy_final="Volume", regular=[True] * len(args.faces),
            )
            res["wheel_seconds"] = time.perf_counter() - t
            hierarchies["nested_cages_wheel"] = [(V, F)] + [(np.asarray(a, float), np.asarray(b, np.int64))
                                                            for a, b in cages]
        t = time.perf_counter()
        hierarchies["decimate"] = build_cages(V, F, method="decimate", face_counts=args.faces, verify=False)
        res["decimate_seconds"] = time.perf_counter() - t
        for hname, layers in hierarchies.items():
            t = time.perf_counter()
            rep = verify_nesting(layers)
            t_exact = time.perf_counter() - t
            t = time.perf_counter()
            rep_fast = verify_nesting(layers, exact_winding=False)
            t_fast = time.perf_counter() - t
            res[hname] = {
                "nested": rep.ok,
                "nested_fast_winding": rep_fast.ok,
                "verify_seconds": t_exact,
                "verify_seconds_fast": t_fast,
                "pairs": pair_rows(rep),
            }
        out["meshes"][name] = res
    print(json.dumps(out, indent=2))

    if not args.no_plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(7, 3.2))
        labels, vals = [], []
        for name, res in out["meshes"].items():
            for hname in ("nested_cages_wheel", "decimate"):
                if hname in res:
                    for p in res[hname]["pairs"]:
                        labels.append(f"{name} {hname} {p['pair']}")
                        vals.append(p["n_outside_vertices"])
        ax.barh(labels, vals, color="tab:red")
        ax.set_xlabel("fine vertices outside the next layer")
        fig.tight_layout()
        fig.savefig(Path(__file__).with_suffix(".png"), dpi=120)
    return out


if __name__ == "__main__":
    main()
