"""Experiment 3 (Nested Cages paper, Sec. 7): Dirichlet Poisson, mesh independence of geometric multigrid.

(a) **levels**: one fine TetGen mesh, hierarchies of 2..5 levels taken as prefixes of one chain: the
    input surface re-meshed at 2x the fine edge length (same domain, boundary kept: nothing to
    extrapolate), then three cage layers (face counts ``m/4, m/16, 100``). A 6th level would need a
    cage below 100 faces or a second same-domain level, which TetGen cannot make much coarser than the
    first: it keeps the input surface, so a same-domain level bottoms out at the surface's resolution;
(b) **fine size**: 50k .. ≥1M tets, with 0, 0, 1, 2 same-domain levels at 50k, 130k, 400k, 1M (so
    the first cage level starts near the surface's resolution), then two cage layers.

Nested cages against naive decimation (linear and closest-point extrapolation), Galerkin and
re-discretised coarse operators, V(1,1) symmetric Gauss–Seidel: the stationary convergence factor
(geometric mean of the last 5 residual ratios, ``maxiter`` cycles) and the number of CG iterations
preconditioned by one V-cycle to 1e-8.

    python benchmarks/exp_scaling.py --zoo ZOO_DIR --out bench_out/exp_scaling          # 15-40 min (1M-tet TetGen run)
    python benchmarks/exp_scaling.py --zoo ZOO_DIR --quick --out OUT                    # ~2 min

Writes ``exp_scaling.json`` and ``exp_scaling.png`` into ``--out``.
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

from exp_common import STYLES, build_pair, environment, figure, load_zoo, save_figure, write_json
from nestmg import SolverOptions

HIERARCHIES = ("nested", "naive-linear", "naive-closest_point")
#: default: closest-point extrapolation gave the same figures as linear in every row of the first run
DEFAULT_HIERARCHIES = ("nested", "naive-linear")


def _solve_all(tets, P, maxiter):
    """Stationary factor and PCG iterations, Galerkin and re-discretised (divergence is a result)."""
    from nestmg.run import solve_on_hierarchy
    from solvers import SolverError

    out = {}
    for coarse in ("galerkin", "rediscretized"):
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                st = solve_on_hierarchy(tets, P, "poisson-dirichlet", SolverOptions(coarse=coarse,
                                                                                    maxiter=maxiter),
                                        cost=False)
                cg = solve_on_hierarchy(tets, P, "poisson-dirichlet", SolverOptions(coarse=coarse, accel="cg",
                                                                                    maxiter=200), cost=False)
        except SolverError as exc:  # e.g. a large coarsest level that is singular beyond its null space
            out[coarse] = {"error": f"{type(exc).__name__}: {str(exc)[:160]}"}
            continue
        out[coarse] = {
            "factor": st["factor"], "stationary_cycles": st["iterations"], "stationary_converged": st["converged"],
            "diverged": st["diverged"], "pcg_iterations": cg["iterations"], "pcg_converged": cg["converged"],
            "pcg_diverged": cg["diverged"], "pcg_solve_seconds": cg["seconds"]["solve"],
            "levels": st["levels"], "operator_complexity": st["operator_complexity"],
        }
    return out


def _fmt(name, L, r):
    g, d = r["galerkin"], r["rediscretized"]

    def one(x):
        if "error" in x:
            return f"ERROR {x['error'][:60]}"
        f = "DIVERGES" if x["diverged"] else f"{x['factor']:.3f}"
        return f"factor {f:>8} PCG {x['pcg_iterations']:>3}{'' if x['pcg_converged'] else '!'}"

    return f"  {name:<20} L={L}  Galerkin: {one(g)}   re-discretised: {one(d)}"


def levels_sweep(mesh, fine_tets, maxiter, hierarchies=DEFAULT_HIERARCHIES, max_levels=5):
    """Factors for 2..max_levels levels: same-domain levels below three cages (4x, 16x fewer faces, 100)."""
    V, F = load_zoo(mesh)
    m = len(F)
    pair = build_pair(V, F, max_levels, fine_tets, same_domain=max_levels - 4, rules=("linear", "closest_point"),
                      face_counts=[m // 4, m // 16, 100])
    rec = {"mesh": mesh, "hierarchies": pair["info"], "runs": []}
    print(f"{mesh} levels sweep: tets per level {pair['info']['nested']['tets']} (nested), "
          f"{pair['info']['naive-linear']['tets']} (naive)", flush=True)
    for name in hierarchies:
        tets, P, _ = pair["hierarchies"][name]
        for L in range(2, max_levels + 1):
            r = _solve_all(tets[:L], P[: L - 1], maxiter)
            rec["runs"].append({"hierarchy": name, "levels": L, **r})
            print(_fmt(name, L, r), flush=True)
    return rec


def size_sweep(mesh, sizes, maxiter, hierarchies=DEFAULT_HIERARCHIES):
    V, F = load_zoo(mesh)
    rec = {"mesh": mesh, "runs": []}
    for n in sizes:
        s = 0 if n <= 150_000 else (1 if n <= 500_000 else 2)
        t0 = time.perf_counter()
        pair = build_pair(V, F, s + 3, n, same_domain=s, rules=("linear", "closest_point"))
        print(f"{mesh} fine target {n}: tets per level {pair['info']['nested']['tets']} (nested), "
              f"{pair['info']['naive-linear']['tets']} (naive), built in {time.perf_counter() - t0:.1f} s", flush=True)
        for name in hierarchies:
            tets, P, _ = pair["hierarchies"][name]
            r = _solve_all(tets, P, maxiter)
            rec["runs"].append({"hierarchy": name, "target_tets": n, "tets": pair["info"][name]["tets"],
                                "nodes": pair["info"][name]["nodes"], "same_domain_levels": s,
                                "n_outside": pair["info"][name]["n_outside"], **r})
            print(_fmt(name, s + 3, r), flush=True)
    return rec


def plot(results, path: Path):
    styles = {k: STYLES[k] for k in ("nested", "naive-linear", "naive-closest_point")}
    fig, axes = figure(2, 2, figsize=(11, 8))
    for col, (key, xkey, xlabel) in enumerate((("levels", "levels", "number of levels"),
                                               ("sizes", "fine_tets", "fine tets"))):
        for rec in results[key]:
            for name, (c, m, ls) in styles.items():
                for row, coarse in enumerate(("galerkin", "rediscretized")):
                    runs = [r for r in rec["runs"] if r["hierarchy"] == name and "error" not in r[coarse]]
                    if not runs:
                        continue
                    x = [r["levels"] if key == "levels" else r["tets"][0] for r in runs]
                    y = [min(r[coarse]["factor"], 1.5) for r in runs]
                    ax = axes[row, col]
                    ax.plot(x, y, color=c, marker=m, ls=ls, label=f"{rec['mesh']} {name}",
                            alpha=1.0 if rec["mesh"] == results[key][0]["mesh"] else 0.5)
                    ax.set_title(f"Dirichlet Poisson, {coarse}: factor vs {xlabel}")
                    ax.set_xlabel(xlabel)
                    ax.set_ylabel("V(1,1) convergence factor")
                    ax.set_ylim(0, 1.2)
                    if key == "sizes":
                        ax.set_xscale("log")
    for ax in axes.ravel():
        ax.axhline(1.0, color="gray", lw=0.8)
        ax.legend(fontsize=6)
    save_figure(fig, path)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--zoo", type=Path, required=True, help="folder of the dev-zoo meshes")
    ap.add_argument("--meshes", nargs="+", default=["gargo.off", "bunny.off"])
    ap.add_argument("--levels-tets", type=int, default=400_000, help="fine size of the levels sweep")
    ap.add_argument("--max-levels", type=int, default=5,
                    help="deepest hierarchy of the levels sweep (>= 5; levels beyond 4 are same-domain levels)")
    ap.add_argument("--sizes", type=int, nargs="+", default=[50_000, 130_000, 400_000, 1_250_000],
                    help="target fine tet counts (1.25M gives ~1.08M tets on gargo)")
    ap.add_argument("--hierarchies", nargs="+", default=list(DEFAULT_HIERARCHIES), choices=HIERARCHIES)
    ap.add_argument("--size-meshes", nargs="+", default=["gargo.off"], help="meshes of the size sweep")
    ap.add_argument("--maxiter", type=int, default=30)
    ap.add_argument("--quick", action="store_true", help="one mesh, levels sweep at 130k, sizes 50k and 130k")
    ap.add_argument("--out", type=Path, default=Path("bench_out/exp_scaling"))
    a = ap.parse_args(argv)
    if a.quick:
        a.meshes, a.levels_tets, a.sizes, a.size_meshes = a.meshes[:1], 130_000, [50_000, 130_000], a.meshes[:1]
    import exp_common

    exp_common.ZOO = a.zoo
    res = {"params": {"levels_tets": a.levels_tets, "sizes": a.sizes, "maxiter": a.maxiter,
                      "smoother": "symmetric_gauss_seidel V(1,1)", "problem": "poisson-dirichlet"},
           "environment": environment(), "levels": [], "sizes": []}
    for mesh in a.meshes:
        res["levels"].append(levels_sweep(mesh, a.levels_tets, a.maxiter, a.hierarchies, a.max_levels))
    for mesh in a.size_meshes:
        res["sizes"].append(size_sweep(mesh, a.sizes, a.maxiter, a.hierarchies))
    write_json(res, a.out / "exp_scaling.json")
    plot(res, a.out / "exp_scaling.png")
    print(f"wrote {a.out / 'exp_scaling.json'} and {a.out / 'exp_scaling.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
