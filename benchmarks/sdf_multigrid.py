"""Multigrid on ``sdf`` cage hierarchies beside ``nested`` and ``decimate`` (issue 17, last item).

For each mesh and cage method,
``nestmg.build_hierarchy(V, F, levels, method, sizing=SizingOptions(max_tets=...), cache=True)``
(nestmg's defaults otherwise: TetWild, the fine level a red refinement of the input meshed
at twice the fine edge, the cages below it, ``min_gap = 2.5 epsilon`` for the certified methods), then for
Dirichlet and Neumann Poisson with Galerkin and re-discretised coarse operators
(``nestmg.run.solve_on_hierarchy`` with its defaults: the pipeline's variable V-cycle,
``nestmg.problems.DEFAULT_SMOOTHERS`` -- one symmetric Gauss–Seidel sweep before and after on the fine
level, two on the coarser ones -- plus the local boundary-layer sweeps of Neumann problems):

* the stationary V-cycle convergence factor (cycles to ``1e-8``, at most ``--cycles``),
* the MG-preconditioned CG iterations to ``1e-8``,

and per level the tets / nodes, ``n_outside`` (fine nodes outside every coarse tet: extrapolated), the
cage face counts, whether the surfaces are certified nested, and the build seconds (cached stages are
reused across runs: cages and tet meshes are keyed by their inputs, so the shared input level is meshed
once). Writes ``--out/<tag>.json`` after every hierarchy (partial results survive a cut-short run).

Usage::

    nice -n 10 python benchmarks/sdf_multigrid.py ZOO_DIR --meshes bunny.off gargo.off \\
        --methods sdf nested decimate --levels 3 --max-tets 300000 --out benchmarks/results/sdf --tag sdf_multigrid

``--levels 4`` (fine level = red refinement of the input meshed at 2h, then two cage levels) makes the
cages two of the levels.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import traceback
from pathlib import Path

import numpy as np

from nestmg import SizingOptions, SolverOptions

PROBLEMS = ("poisson-dirichlet", "poisson-neumann")
COARSE = ("galerkin", "rediscretized")


def say(msg: str) -> None:
    print(f"[sdf_multigrid] {msg}", file=sys.stderr, flush=True)


def run_one(path: Path, method: str, args) -> dict:
    from nestmg import build_hierarchy
    from nestmg.io import load_mesh
    from nestmg.run import solve_on_hierarchy

    V, F = load_mesh(path)
    F = np.asarray(F, dtype=np.int64)
    rec: dict = {"mesh": path.name, "input_faces": len(F), "method": method, "loadavg_1min": [os.getloadavg()[0]]}
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        h = build_hierarchy(V, F, args.levels, method, sizing=SizingOptions(max_tets=args.max_tets),
                            cache=True,
                            progress=False)
    except Exception as exc:  # noqa: BLE001 -- a benchmark reports any failure and goes on
        rec.update(error=f"{type(exc).__name__}: {exc}", traceback=traceback.format_exc()[-1500:],
                   build_seconds=time.perf_counter() - t0)
        return rec
    rec.update({
        "build_seconds": time.perf_counter() - t0,
        "build_cpu_seconds": time.process_time() - c0,
        "timings": {k: v for k, v in h.timings.items() if isinstance(v, (int, float))},
        "surface_faces": [len(Fk) for _, Fk in h.surfaces],
        "tets": [len(T) for _, T in h.tets],
        "nodes": [len(Vt) for Vt, _ in h.tets],
        "n_outside": [int(n) for n in h.n_outside],
        "max_extrapolation_rel": [float(r.max_distance_rel) for r in h.prolongation_reports],
        "surfaces_nested": h.surfaces_nested,
        "certified": bool(h.certified),
        "fine_level": h.options.get("fine_level"),
        "cage_min_gap": h.options.get("cages", {}).get("min_gap"),
    })
    ver = h.cage_info.get("verification") or {}
    rec["verification_min_gap_rel"] = [p.get("min_gap_rel") for p in ver.get("pairs", [])]
    backend = h.cage_info.get("backend") or {}
    if method == "sdf" and "layers" in backend:
        rec["sdf_layers"] = [{k: li.get(k) for k in ("n_faces", "c_used", "genus_fine", "genus",
                                                      "hausdorff_relative_to_input", "volume_ratio_to_input")}
                             for li in backend["layers"]]
    say(f"{path.name} {method}: tets {rec['tets']} n_outside {rec['n_outside']} certified {rec['certified']} "
        f"({rec['build_seconds']:.0f} s)")
    rec["runs"] = []
    for prob in PROBLEMS:
        for coarse in COARSE:
            row: dict = {"problem": prob, "coarse": coarse}
            try:
                st = solve_on_hierarchy(h.tets, h.P, prob, SolverOptions(coarse=coarse, maxiter=args.cycles),
                                        cost=False)
                cg = solve_on_hierarchy(h.tets, h.P, prob, SolverOptions(coarse=coarse, accel="cg",
                                                                         maxiter=200),
                                        cost=False)
                row.update(factor=st["factor"], cycles=st["iterations"], converged=st["converged"],
                           diverged=st["diverged"],
                           pcg_iterations=cg["iterations"] if cg["converged"] else None,
                           pcg_converged=cg["converged"], pcg_diverged=cg["diverged"],
                           pcg_solve_seconds=cg["seconds"]["solve"])
            except Exception as exc:  # noqa: BLE001 -- recorded
                row["error"] = f"{type(exc).__name__}: {exc}"
            rec["runs"].append(row)
            say(f"{path.name} {method:8s} {prob:18s} {coarse:13s} factor {row.get('factor', float('nan')):.3f}"
                f"{' DIVERGED' if row.get('diverged') else ''} PCG {row.get('pcg_iterations')}")
    rec["loadavg_1min"].append(os.getloadavg()[0])
    return rec


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("zoo", type=Path)
    ap.add_argument("--meshes", nargs="+", default=["bunny.off", "gargo.off"])
    ap.add_argument("--methods", nargs="+", default=["sdf", "nested", "decimate"])
    ap.add_argument("--levels", type=int, default=3)
    ap.add_argument("--max-tets", type=int, default=300_000)
    ap.add_argument("--cycles", type=int, default=60, help="stationary cycles at most (for the factor)")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/sdf"))
    ap.add_argument("--tag", default="sdf_multigrid")
    args = ap.parse_args(argv)
    from nestmg.io import json_default
    from nestmg.problems import DEFAULT_SMOOTHERS

    doc: dict = {"benchmark": "benchmarks/sdf_multigrid.py", "command": " ".join(sys.argv), "levels": args.levels,
                 "max_tets": args.max_tets, "problems": list(PROBLEMS), "coarse": list(COARSE),
                 "smoother": "symmetric_gauss_seidel, nu=1 (solve_on_hierarchy defaults)",
                 "default_smoothers": [list(s) for s in DEFAULT_SMOOTHERS], "local_sweeps": True, "tol": 1e-8, "results": []}
    args.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    c0 = time.process_time()
    for name in args.meshes:
        for m in args.methods:
            doc["results"].append(run_one(args.zoo / name, m, args))
            doc["wall_seconds"] = time.perf_counter() - t0
            doc["cpu_seconds_main_process"] = time.process_time() - c0
            (args.out / f"{args.tag}.json").write_text(json.dumps(doc, indent=1, default=json_default))
    print(json.dumps(doc, indent=1, default=json_default))
    return doc


if __name__ == "__main__":
    main()
