"""Where the Neumann V(1,1) loses, and what the default cycle's extra sweeps buy.

On the default hierarchy of each input (``build_hierarchy(V, F, levels=3, method="nested")``, cached;
``--max-tets`` to keep it small), for the three model problems and Galerkin coarse operators:

* the cycle variants: plain V(1,1) (one symmetric Gauss-Seidel sweep per level), ``local`` (one extra
  symmetric sweep on the boundary layer: boundary nodes + one tet ring, and the coarse nodes that
  interpolate to it), ``coarse2`` (two sweeps on the coarser levels) and ``default`` (both: what
  ``solve_on_hierarchy`` and ``Problem.multigrid()`` use) -- V-cycle factor, MG-PCG iterations to 1e-8,
  counted fine SpMV per cycle;
* the same on the top pair alone (exact coarse solve) and on the cage pair alone;
* where the error is: after 20 plain two-grid cycles on ``A x = 0`` from a random start, the share of
  the 50 largest error components that sit on boundary nodes, beside the boundary nodes' share.

    python benchmarks/archive/smoothing.py MESH [MESH ...] --max-tets 500000 \\
        --json benchmarks/results/scale/smoothing.json
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # archived: exp_common.py is in benchmarks/
from exp_common import environment, write_json  # noqa: E402

VARIANTS = {"plain": {"local": False, "coarse_nu": 1}, "local": {"coarse_nu": 1},
            "coarse2": {"local": False}, "default": {}}
PROBLEMS = ("poisson-dirichlet", "poisson-neumann", "diffusion-neumann")


def variants(tets, P, problem: str) -> dict:
    from nestmg.run import solve_on_hierarchy

    out = {}
    for name, kw in VARIANTS.items():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            v = solve_on_hierarchy(tets, P, problem, tol=1e-8, maxiter=80, cost=True, **kw)
            c = solve_on_hierarchy(tets, P, problem, tol=1e-8, accel="cg", cost=False, **kw)
        out[name] = {"factor": round(v["factor"], 4), "pcg_iterations": c["iterations"],
                     "cycle_spmv": round(v["cycle_cost"]["counted_spmv_units"], 2),
                     "pcg_seconds": round(c["seconds"]["solve"], 2)}
    return out


def error_location(tets, P) -> dict:
    """Share of the largest plain two-grid Neumann error components on boundary nodes."""
    from nestmg.problems import setup_problem
    from solvers.fem import boundary_nodes

    prob = setup_problem(tets[:2], P[:1], "poisson-neumann")
    ml = prob.multigrid(local=False, presmoother="symmetric_gauss_seidel")
    B = ml.aspreconditioner()  # one cycle from x0 = 0: the error propagates as e <- e - B A e
    x = np.random.default_rng(0).standard_normal(prob.A.shape[0])
    for _ in range(20):
        x -= B @ (prob.A @ x)
        x -= x.mean()
    top = np.argsort(-np.abs(x))[:50]
    bnd = boundary_nodes(tets[0][1])
    return {"top50_on_boundary": float(np.isin(top, bnd).mean()), "boundary_share": len(bnd) / len(tets[0][0])}


def run(mesh: str, max_tets: int | None) -> dict:
    from nestmg import SizingOptions, build_hierarchy
    from nestmg.io import load_mesh

    V, F = load_mesh(mesh)
    sizing = SizingOptions() if max_tets is None else SizingOptions(max_tets=max_tets, mesh_time_budget=None)
    h = build_hierarchy(V, F, 3, "nested", sizing=sizing, cache=True, progress=False)
    tets = h.tets_in("normalized")
    out = {"mesh": Path(mesh).name, "faces": len(F), "tets": [len(T) for _, T in h.tets],
           "n_outside": h.n_outside, "error_location": error_location(tets, h.P), "problems": {}}
    for p in PROBLEMS:
        out["problems"][p] = {"three_levels": variants(tets, h.P, p), "top_pair": variants(tets[:2], h.P[:1], p),
                              "cage_pair": variants(tets[1:], h.P[1:], p)}
        print(json.dumps({"mesh": out["mesh"], p: out["problems"][p]}), file=sys.stderr, flush=True)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("meshes", nargs="+")
    ap.add_argument("--max-tets", type=int, default=None, help="fine tets (default: the pipeline's budget)")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    out = {"command": " ".join(["python", "benchmarks/archive/smoothing.py", *sys.argv[1:]]),
           "environment": environment(), "runs": [run(m, a.max_tets) for m in a.meshes]}
    print(json.dumps(out, indent=1, default=float))
    if a.json:
        write_json(out, Path(a.json))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
