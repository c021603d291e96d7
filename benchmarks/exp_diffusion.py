"""Experiment 1 (Nested Cages paper, Sec. 7): Neumann diffusion ``(λK + M) u = M f`` over several decades of λ.

Nested cages vs naive decimation with each extrapolation rule (clamped / linear / closest point /
nearest vertex), the same fine TetGen mesh, the same V(1,1) symmetric Gauss–Seidel cycle, stationary
iteration (no CG), both Galerkin and re-discretised coarse operators. Also pure Neumann Poisson
(λ → ∞). Meshes are normalised to a unit bounding-box diagonal.

    python benchmarks/exp_diffusion.py --zoo ZOO_DIR --out bench_out/exp_diffusion          # ~10 min
    python benchmarks/exp_diffusion.py --zoo ZOO_DIR --quick --out OUT                      # ~1 min

Prints a summary, writes ``exp_diffusion.json`` and ``exp_diffusion.png`` into ``--out``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from exp_common import STYLES, build_pair, environment, figure, load_zoo, save_figure, write_json
from nestmg import SolverOptions


def run(meshes, fine_tets, lams, levels, maxiter, nu):
    from nestmg.run import solve_on_hierarchy

    results = {"params": {"fine_tets": fine_tets, "lams": lams, "levels": levels, "maxiter": maxiter, "nu": nu,
                          "smoother": "symmetric_gauss_seidel", "cycle": "V", "accel": None},
               "environment": environment(), "meshes": {}}
    for mesh in meshes:
        V, F = load_zoo(mesh)
        t0 = time.perf_counter()
        pair = build_pair(V, F, levels, fine_tets)
        print(f"{mesh}: hierarchies in {time.perf_counter() - t0:.1f} s; "
              + "; ".join(f"{k} nodes {v['nodes']} n_outside {v['n_outside']}" for k, v in pair["info"].items()
                          if k in ("nested", "naive-clamped")), flush=True)
        rec = {"hierarchies": pair["info"], "runs": []}
        for name, (tets, P, _) in pair["hierarchies"].items():
            for coarse in ("galerkin", "rediscretized"):
                for lam in [*lams, None]:
                    prob = "poisson-neumann" if lam is None else "diffusion-neumann"
                    opts = SolverOptions(coarse=coarse, nu=nu, maxiter=maxiter,
                                         lam=1.0 if lam is None else lam)
                    r = solve_on_hierarchy(tets, P, prob, opts, cost=False)
                    rec["runs"].append({
                        "hierarchy": name, "coarse": coarse, "lam": lam, "problem": prob,
                        "factor": r["factor"], "iterations": r["iterations"], "converged": r["converged"],
                        "diverged": r["diverged"], "residuals": r["residuals"],
                        "setup_seconds": r["seconds"]["setup"], "solve_seconds": r["seconds"]["solve"],
                    })
                    tag = "DIVERGED" if r["diverged"] else ("" if r["converged"] else "not converged")
                    print(f"  {mesh:<10} {name:<20} {coarse:<13} λ={lam!s:<7} factor {r['factor']:.3f} "
                          f"cycles {r['iterations']:>3} {tag}", flush=True)
        results["meshes"][mesh] = rec
    return results


def plot(results, path: Path):
    meshes = list(results["meshes"])
    lams = results["params"]["lams"]
    fig, axes = figure(len(meshes), 3, figsize=(15, 4.2 * len(meshes)), squeeze=False)
    styles = STYLES
    for i, mesh in enumerate(meshes):
        runs = results["meshes"][mesh]["runs"]
        for j, coarse in enumerate(("galerkin", "rediscretized")):
            ax = axes[i, j]
            for name, (c, m, ls) in styles.items():
                pts = [(r["lam"], r["factor"]) for r in runs
                       if r["hierarchy"] == name and r["coarse"] == coarse and r["lam"] is not None]
                if pts:
                    x, y = zip(*pts)
                    ax.semilogx(x, np.minimum(y, 3.0), color=c, marker=m, ls=ls, label=name)
            ax.axhline(1.0, color="gray", lw=0.8)
            ax.set_ylim(0, 2.0)
            ax.set_xlabel("λ (diffusion coefficient, unit-diagonal mesh)")
            ax.set_ylabel("V(1,1) convergence factor (>1: diverges)")
            ax.set_title(f"{mesh}: {coarse} coarse operators")
            ax.legend(fontsize=7)
        ax = axes[i, 2]
        mid = lams[len(lams) // 2]
        for name, (c, m, ls) in styles.items():
            for coarse, lw in (("galerkin", 1.0), ("rediscretized", 2.0)):
                for r in runs:
                    if r["hierarchy"] == name and r["coarse"] == coarse and r["lam"] == mid:
                        ax.semilogy(np.minimum(r["residuals"], 1e6), color=c, ls="-" if coarse == "galerkin" else ":",
                                    lw=lw, label=f"{name} ({coarse[:5]})")
        ax.set_ylim(1e-9, 1e6)
        ax.set_xlabel("V-cycles")
        ax.set_ylabel("relative residual")
        ax.set_title(f"{mesh}: λ={mid} (solid Galerkin, dotted re-discretised)")
        ax.legend(fontsize=6, ncol=2)
    save_figure(fig, path)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--zoo", type=Path, required=True, help="folder of the dev-zoo meshes")
    ap.add_argument("--meshes", nargs="+", default=["gargo.off", "bunny.off"])
    ap.add_argument("--fine-tets", type=int, default=130_000)
    ap.add_argument("--levels", type=int, default=3)
    ap.add_argument("--lams", type=float, nargs="+", default=[1e-4, 1e-3, 1e-2, 1e-1, 1.0, 10.0])
    ap.add_argument("--maxiter", type=int, default=40)
    ap.add_argument("--nu", type=int, default=1)
    ap.add_argument("--quick", action="store_true", help="one mesh, 40k tets, three λ")
    ap.add_argument("--out", type=Path, default=Path("bench_out/exp_diffusion"))
    a = ap.parse_args(argv)
    if a.quick:
        a.meshes, a.fine_tets, a.lams, a.maxiter = a.meshes[:1], 40_000, [1e-3, 1e-1, 10.0], 25
    import exp_common

    exp_common.ZOO = a.zoo
    res = run(a.meshes, a.fine_tets, a.lams, a.levels, a.maxiter, a.nu)
    write_json(res, a.out / "exp_diffusion.json")
    plot(res, a.out / "exp_diffusion.png")
    print(f"wrote {a.out / 'exp_diffusion.json'} and {a.out / 'exp_diffusion.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
