"""Experiment 2 (Nested Cages paper, Sec. 7): smooth geodesic distance by the heat method, by multigrid.

Two solves on the fine tet mesh (:mod:`nestmg.geodesics`): the heat step ``(M + tK) u = δ`` (``t`` =
squared mean edge length) and the Neumann Poisson step ``K φ = div X``. Each is solved by stationary
V(ν,ν) cycles (symmetric Gauss–Seidel, ν = 1..5) to a relative residual of 1e-8 on the nested and the
naive hierarchies (every extrapolation rule), Galerkin and re-discretised coarse operators. The
distance is compared with the one from direct solves (same discretisation).

    python benchmarks/exp_geodesics.py --zoo ZOO_DIR --out bench_out/exp_geodesics          # ~10 min
    python benchmarks/exp_geodesics.py --zoo ZOO_DIR --quick --out OUT                      # ~1 min

Writes ``exp_geodesics.json`` and ``exp_geodesics.png`` into ``--out``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from exp_common import STYLES, build_pair, environment, figure, load_zoo, save_figure, write_json


def run(meshes, fine_tets, levels, nus, maxiter, tol, hierarchies):
    from nestmg.geodesics import heat_geodesic, heat_precompute, multigrid_solve
    from solvers import DivergenceError

    results = {"params": {"fine_tets": fine_tets, "levels": levels, "nus": nus, "maxiter": maxiter, "tol": tol,
                          "t": "squared mean edge length", "cycle": "V", "accel": None},
               "environment": environment(), "meshes": {}}
    for mesh in meshes:
        V, F = load_zoo(mesh)
        pair = build_pair(V, F, levels, fine_tets)
        Vf, Tf = pair["hierarchies"]["nested"][0][0]
        pre = heat_precompute(Vf, Tf)
        src = int(np.argmax(Vf[:, 2]))  # the top-most fine node (on the boundary)
        t0 = time.perf_counter()
        ref = heat_geodesic(Vf, Tf, src, pre=pre).distance
        t_direct = time.perf_counter() - t0
        rec = {"hierarchies": pair["info"], "source": src, "nodes": len(Vf), "tets": len(Tf),
               "t": pre.t, "direct_seconds": t_direct, "max_distance": float(ref.max()), "runs": []}
        print(f"{mesh}: {len(Vf)} nodes, direct heat method {t_direct:.2f} s, max distance {ref.max():.3f}",
              flush=True)
        for name in hierarchies:
            tets, P, _ = pair["hierarchies"][name]
            for coarse in ("galerkin", "rediscretized"):
                for nu in nus:
                    solve = multigrid_solve(tets, P, t=pre.t, coarse=coarse, nu=nu, accel=None, tol=tol,
                                            maxiter=maxiter)
                    row = {"hierarchy": name, "coarse": coarse, "nu": nu}
                    t0 = time.perf_counter()
                    try:
                        import warnings

                        with warnings.catch_warnings():
                            warnings.simplefilter("ignore")
                            out = heat_geodesic(Vf, Tf, src, pre=pre, solve=solve)
                        err = float(np.abs(out.distance - ref).max() / ref.max())
                        for step in ("heat", "poisson"):
                            i = out.info[step]
                            row[step] = {"cycles": i["iterations"], "converged": i["converged"],
                                         "factor": i["factor"], "residuals": i["residuals"]}
                        row["diverged"] = False
                        row["max_error_vs_direct_rel"] = err
                    except DivergenceError as exc:
                        row.update(diverged=True, message=str(exc)[:200], max_error_vs_direct_rel=None)
                    row["seconds"] = time.perf_counter() - t0
                    rec["runs"].append(row)
                    if row["diverged"]:
                        msg = "DIVERGED"
                    else:
                        msg = (f"heat {row['heat']['cycles']:>3} cycles ({row['heat']['factor']:.2f}) "
                               f"poisson {row['poisson']['cycles']:>3} cycles ({row['poisson']['factor']:.2f})"
                               f"{'' if row['poisson']['converged'] else ' NOT CONVERGED'} "
                               f"err {row['max_error_vs_direct_rel']:.1e}")
                    print(f"  {mesh:<10} {name:<20} {coarse:<13} ν={nu} {msg} [{row['seconds']:.1f} s]", flush=True)
        results["meshes"][mesh] = rec
    return results


def plot(results, path: Path):
    meshes = list(results["meshes"])
    maxiter = results["params"]["maxiter"]
    fig, axes = figure(len(meshes), 2, figsize=(11, 4.0 * len(meshes)), squeeze=False)
    styles = STYLES
    for i, mesh in enumerate(meshes):
        runs = results["meshes"][mesh]["runs"]
        for j, coarse in enumerate(("galerkin", "rediscretized")):
            ax = axes[i, j]
            for name, (c, m, ls) in styles.items():
                pts = []
                for r in runs:
                    if r["hierarchy"] == name and r["coarse"] == coarse:
                        ok = not r["diverged"] and r["poisson"]["converged"]
                        pts.append((r["nu"], r["poisson"]["cycles"] if ok else maxiter * 1.1))
                if pts:
                    x, y = zip(*pts)
                    ax.plot(x, y, color=c, marker=m, ls=ls, label=name)
            ax.axhline(maxiter * 1.1, color="gray", lw=0.8)
            ax.text(1, maxiter * 1.12, "diverged / not converged", fontsize=7, color="gray")
            ax.set_ylim(0, maxiter * 1.25)
            ax.set_xlabel("ν (sweeps before and after)")
            ax.set_ylabel("V(ν,ν) cycles to 1e-8 (Poisson step)")
            ax.set_title(f"{mesh}: heat-method geodesics, {coarse}")
            ax.legend(fontsize=7)
    save_figure(fig, path)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--zoo", type=Path, required=True, help="folder of the dev-zoo meshes")
    ap.add_argument("--meshes", nargs="+", default=["gargo.off", "bunny.off"])
    ap.add_argument("--fine-tets", type=int, default=80_000)
    ap.add_argument("--hierarchies", nargs="+",
                    default=["nested", "naive-linear", "naive-closest_point", "naive-nearest_vertex"])
    ap.add_argument("--levels", type=int, default=3)
    ap.add_argument("--nus", type=int, nargs="+", default=[1, 2, 3, 4, 5])
    ap.add_argument("--maxiter", type=int, default=60)
    ap.add_argument("--tol", type=float, default=1e-8)
    ap.add_argument("--quick", action="store_true", help="one mesh, 40k tets, ν = 1, 3")
    ap.add_argument("--out", type=Path, default=Path("bench_out/exp_geodesics"))
    a = ap.parse_args(argv)
    if a.quick:
        a.meshes, a.fine_tets, a.nus, a.maxiter = a.meshes[:1], 40_000, [1, 3], 40
    import exp_common

    exp_common.ZOO = a.zoo
    res = run(a.meshes, a.fine_tets, a.levels, a.nus, a.maxiter, a.tol, a.hierarchies)
    write_json(res, a.out / "exp_geodesics.json")
    plot(res, a.out / "exp_geodesics.png")
    print(f"wrote {a.out / 'exp_geodesics.json'} and {a.out / 'exp_geodesics.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
