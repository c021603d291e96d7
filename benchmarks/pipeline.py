"""Pipeline benchmark (issue 3): per-stage times, V-cycle cost in fine SpMVs, convergence factors and
n_outside per level, for every cage method, on dev-zoo meshes at a fine level of >= 300k tets.

    python benchmarks/pipeline.py ZOO_DIR --meshes bunny.off gargo.off \
        --methods decimate nested --fine-tets 300000 --out bench_out/pipeline

Prints one JSON document and writes ``pipeline.json`` and ``pipeline.png`` into ``--out``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from nestmg import SolverOptions


def _edge_for_tets(V, F, target: int) -> float:
    """Edge length of regular tets (volume h^3 / (6 sqrt 2)) filling the solid ``target`` times."""
    import trimesh

    vol = trimesh.Trimesh(V, F, process=False).volume
    return float((6 * np.sqrt(2) * vol / target) ** (1 / 3))


def run_mesh(path: Path, methods, levels, fine_tets, mesher, problems, coarse_list, smoother):
    from exp_common import try_hierarchy

    from nestmg.io import load_mesh, normalize
    from nestmg.run import solve_on_hierarchy

    V, F = load_mesh(path)
    V, _, _ = normalize(V)
    h0 = _edge_for_tets(V, F, fine_tets)
    out = {"mesh": path.name, "faces": len(F), "fine_edge_length": h0, "methods": {}}
    for m in methods:
        rec: dict = {}
        t0 = time.perf_counter()
        h = try_hierarchy(rec, f"  {path.name:<14} {m:<9}", V, F, levels, m, h0, mesher)
        if h is None:
            out["methods"][m] = rec
            continue
        rec["hierarchy"] = h.to_dict()
        rec["hierarchy"].pop("cage_info", None)
        rec["stage_seconds"] = {k: v for k, v in h.timings.items() if isinstance(v, float)}
        rec["build_seconds"] = time.perf_counter() - t0
        rec["solves"] = []
        for prob in problems:
            for coarse in coarse_list:
                r = solve_on_hierarchy(h.tets, h.P, prob, SolverOptions(coarse=coarse, smoother=smoother,
                                                                        maxiter=60))
                r.pop("residuals_full", None)
                rec["solves"].append(r)
                print(f"  {path.name:<14} {m:<9} {prob:<18} {coarse:<13} factor {r['factor']:.3f} "
                      f"its {r['iterations']:>2} {'DIVERGED' if r['diverged'] else ''} cycle="
                      f"{r['cycle_cost']['measured_spmv_units']:.1f} SpMV (counted "
                      f"{r['cycle_cost']['counted_spmv_units']:.1f})", flush=True)
        out["methods"][m] = rec
    return out


def plot(results, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = []
    for r in results:
        for m, rec in r["methods"].items():
            for s in rec.get("solves", []):
                rows.append((f"{r['mesh']}\n{m}", f"{s['problem']}/{s['coarse'][:5]}", min(s["factor"], 2.0)))
    if not rows:
        return
    labels = sorted({a for a, _, _ in rows}, key=lambda x: [a for a, _, _ in rows].index(x))
    series = sorted({b for _, b, _ in rows})
    fig, ax = plt.subplots(figsize=(max(6, 1.6 * len(labels)), 4), dpi=120)
    w = 0.8 / len(series)
    for j, s in enumerate(series):
        vals = [next((v for a, b, v in rows if a == lab and b == s), np.nan) for lab in labels]
        ax.bar(np.arange(len(labels)) + j * w, vals, w, label=s)
    ax.axhline(1.0, color="k", lw=0.8, ls="--")
    ax.set_xticks(np.arange(len(labels)) + 0.4 - w / 2, labels, fontsize=7)
    ax.set_ylabel("V-cycle convergence factor (capped at 2)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("mesh_dir", type=Path)
    ap.add_argument("--meshes", nargs="+", default=["bunny.off"])
    ap.add_argument("--methods", nargs="+", default=["decimate", "nested"])
    ap.add_argument("--levels", type=int, default=3)
    ap.add_argument("--fine-tets", type=int, default=300_000)
    ap.add_argument("--mesher", default="tetgen", choices=["tetgen", "tetwild"])
    ap.add_argument("--problems", nargs="+", default=["poisson-dirichlet", "poisson-neumann"])
    ap.add_argument("--coarse", nargs="+", default=["galerkin", "rediscretized"])
    ap.add_argument("--smoother", default="symmetric_gauss_seidel")
    ap.add_argument("--out", type=Path, default=Path("bench_out/pipeline"))
    a = ap.parse_args(argv)
    results = [run_mesh(a.mesh_dir / m, a.methods, a.levels, a.fine_tets, a.mesher, a.problems, a.coarse, a.smoother)
               for m in a.meshes]
    a.out.mkdir(parents=True, exist_ok=True)
    doc = {"args": {k: str(v) for k, v in vars(a).items()}, "results": results}
    (a.out / "pipeline.json").write_text(json.dumps(doc, indent=1, default=str))
    plot(results, a.out / "pipeline.png")
    print(json.dumps(doc, default=str)[:4000])


if __name__ == "__main__":
    main()
