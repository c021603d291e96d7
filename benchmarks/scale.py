"""Real inputs with the defaults: a closed surface of 20k-350k faces -> certified hierarchy -> three solves.

Runs exactly what ``nestmg solve MESH`` does without flags (``build_hierarchy(V, F, levels=3,
method="nested")`` with the default sizing budget, TetWild layers, Galerkin coarse operators) on each
input, every input in a fresh subprocess so that its peak memory is its own, and records per input:
stage seconds, peak RSS, tets / nodes / operator complexity per level, n_outside, tet quality per level
(min dihedral angle, slivers < 5 degrees), and for the three model problems the V(1,1) factor and the
MG-PCG iterations to 1e-8 (with seconds). The V(1,1) is the pipeline's default cycle (one symmetric
Gauss-Seidel sweep on the fine level, two on coarser levels, one local sweep on the Neumann boundary
layer); ``v11_plain`` is the plain V(1,1) beside it. The Neumann Poisson solve to 1e-8 is the end-to-end goal of
issue 14 (<= 10 min and <= 8 GB for a 100k-face input on 2 cores).

    python benchmarks/scale.py MESH [MESH ...] --json benchmarks/results/scale/scale.json \\
        --png benchmarks/results/scale/scale.png [--no-cache] [--levels 3]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from exp_common import run_child

_CHILD = r"""
import json, resource, sys, time
import numpy as np
args = json.loads(sys.argv[1])
t_start = time.perf_counter()
from nestmg.io import load_mesh
from nestmg import SizingOptions, SolverOptions
from nestmg.hierarchy import build_hierarchy
from nestmg.run import solve_on_hierarchy
from nestmg.tetmesh import tet_quality
from nestmg.progress import enable_stage_lines
enable_stage_lines()
V, F = load_mesh(args["mesh"])
t0 = time.perf_counter()
h = build_hierarchy(V, F, args["levels"], args["method"], cache=args["cache"], progress=False,
                    sizing=SizingOptions(**args.get("opts", {})))
t_h = time.perf_counter() - t0
rss_h = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
tets = h.tets_in("normalized")
out = {"mesh": args["mesh"], "input_faces": int(len(F)), "hierarchy_seconds": t_h,
       "hierarchy": h.to_dict(), "quality": [tet_quality(Vk, Tk) for Vk, Tk in tets], "solves": {}}
for problem in ("poisson-neumann", "poisson-dirichlet", "diffusion-neumann"):
    row = {}
    for accel in (None, "cg"):
        t1 = time.perf_counter()
        r = solve_on_hierarchy(tets, h.P, problem, SolverOptions(accel=accel, tol=1e-8, maxiter=100),
                               cost=(accel is None))
        r["wall_seconds"] = time.perf_counter() - t1
        r.pop("residuals_by_level", None)
        row["pcg" if accel else "v11"] = r
        if accel is None:  # the plain V(1,1) (no boundary-layer sweeps, one sweep on coarse levels)
            r0 = solve_on_hierarchy(tets, h.P, problem, SolverOptions(tol=1e-8, maxiter=100, local=False,
                                                                      coarse_nu=1),
                                    cost=True)
            row["v11_plain"] = {k: r0[k] for k in ("factor", "iterations", "cycle_cost", "nu", "coarse_nu")}
        if problem == "poisson-neumann" and accel == "cg":
            out["end_to_end_neumann_seconds"] = time.perf_counter() - t_start
            out["end_to_end_neumann_from_hierarchy_start"] = time.perf_counter() - t0
    out["solves"][problem] = row
out["peak_rss_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
out["peak_rss_gb_hierarchy"] = rss_h
out["total_seconds"] = time.perf_counter() - t_start
print("RESULT " + json.dumps(out, default=float))
"""


def run_one(mesh: str, levels: int, method: str, cache: bool, opts: dict) -> dict:
    """One input end to end in a fresh subprocess; stage lines pass through to stderr."""
    r = run_child(_CHILD, {"mesh": mesh, "levels": levels, "method": method, "cache": cache, "opts": opts},
                  stderr_through=True)
    return r if "error" not in r else {"mesh": mesh, **r}


def summary(r: dict) -> dict:
    """The figures of one run that the docs table shows."""
    if "error" in r:
        return {"mesh": Path(r["mesh"]).name, "error": r["error"][-300:]}
    h = r["hierarchy"]
    s = {"mesh": Path(r["mesh"]).name, "faces": r["input_faces"], "tets": h["tets"], "n_outside": h["n_outside"],
         "certified": h["certified"], "predecimated_faces": h["cage_info"].get("predecimation", {}).get("faces_out"),
         "cage_faces": h["surface_faces"], "seconds": {k: round(v, 1) for k, v in h["timings"].items()
                                                       if isinstance(v, (int, float))},
         "tet_seconds": [round(x, 1) for x in h["timings"].get("tet_seconds", [])],
         "end_to_end_neumann_s": round(r.get("end_to_end_neumann_seconds", float("nan")), 1),
         "peak_rss_gb": round(r["peak_rss_gb"], 2),
         "min_dihedral": [round(q["min_dihedral_deg"], 2) for q in r["quality"]],
         "slivers": [q["n_slivers"] for q in r["quality"]]}
    for p, row in r["solves"].items():
        s[p] = {"v11_factor": round(row["v11"]["factor"], 3), "pcg_iterations": row["pcg"]["iterations"],
                "v11_plain_factor": round(row["v11_plain"]["factor"], 3) if "v11_plain" in row else None,
                "cycle_spmv": round(row["v11"]["cycle_cost"]["counted_spmv_units"], 2),
                "operator_complexity": round(row["v11"]["operator_complexity"], 3),
                "pcg_seconds": round(row["pcg"]["seconds"]["solve"], 2)}
    return s


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = [r for r in rows if "error" not in r]
    if not ok:
        return
    fig, (a, b) = plt.subplots(1, 2, figsize=(12, 4.5))
    names = [f"{Path(r['mesh']).stem}\n{r['input_faces'] // 1000}k faces" for r in ok]
    stages = ["predecimate", "cages", "tets", "prolongation"]
    bottom = [0.0] * len(ok)
    for st in stages:
        vals = [r["hierarchy"]["timings"].get(st, 0.0) for r in ok]
        a.bar(names, vals, bottom=bottom, label=st)
        bottom = [x + y for x, y in zip(bottom, vals)]
    solve = [r.get("end_to_end_neumann_seconds", 0.0) - r["hierarchy_seconds"] for r in ok]
    a.bar(names, solve, bottom=bottom, label="Neumann solve (setup + MG-PCG)")
    a.axhline(600, color="k", ls="--", lw=1, label="10 min goal")
    a.set_ylabel("seconds (2 cores)")
    a.set_title("end to end with the defaults")
    a.legend(fontsize=8)
    x = range(len(ok))
    for p, m in (("poisson-dirichlet", "o"), ("poisson-neumann", "s"), ("diffusion-neumann", "^")):
        b.plot(x, [r["solves"][p]["v11"]["factor"] for r in ok], m + "-", label=f"{p} V(1,1)")
    b.axhline(0.2, color="C0", ls=":", lw=1)
    b.axhline(0.3, color="C1", ls=":", lw=1)
    b.set_xticks(list(x), names)
    b.set_ylabel("convergence factor per cycle")
    b.set_title("V(1,1) factors (goals: 0.2 Dirichlet, 0.3 Neumann)")
    b.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("meshes", nargs="+")
    ap.add_argument("--levels", type=int, default=3)
    ap.add_argument("--method", default="nested")
    ap.add_argument("--no-cache", action="store_true")
    ap.add_argument("--opts", default="{}", help="SizingOptions fields as JSON (build_hierarchy's sizing=)")
    ap.add_argument("--json", default=None)
    ap.add_argument("--png", default=None)
    args = ap.parse_args(argv)
    rows = []
    if args.json and Path(args.json).exists():
        rows = json.loads(Path(args.json).read_text()).get("runs", [])
    for mesh in args.meshes:
        r = run_one(mesh, args.levels, args.method, not args.no_cache, json.loads(args.opts))
        rows = [x for x in rows if x.get("mesh") != r.get("mesh")] + [r]
        print(json.dumps(summary(r)), flush=True)
        if args.json:
            Path(args.json).parent.mkdir(parents=True, exist_ok=True)
            Path(args.json).write_text(json.dumps({"runs": rows, "summary": [summary(x) for x in rows]}, indent=1,
                                                  default=float))
        if args.png:
            plot(rows, Path(args.png))
    return 0


if __name__ == "__main__":
    sys.exit(main())
