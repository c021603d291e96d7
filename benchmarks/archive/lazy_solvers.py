"""Does cage tightness matter? Multigrid on ``nested`` vs ``lazy`` hierarchies of the same node counts.

For each mesh (normalised to a unit bounding-box diagonal), with the face counts of
:func:`cagegen.default_face_counts` (3 layers):

1. cages: ``build_cages(method="nested")`` (tight) and ``build_cages(method="lazy")`` (loose); if the
   nested backend fails, the reference wheel's cages stand in (labelled ``wheel``);
2. tet layers with TetGen (boundary kept exactly, so certified surfaces give ``n_outside = 0``):
   the input at edge length ``h0`` (``--h0`` x diagonal; default: the input's mean edge), the tight
   cages at ``h0 * 2**k``; the lazy cages at edge lengths tuned so that every coarse level has the
   *same node count* (within ``--node-tol``) as the tight hierarchy's;
3. barycentric prolongations (:func:`nestmg.prolongation.prolongation`), ``n_outside`` per level;
4. for Dirichlet Poisson, Neumann Poisson and Neumann diffusion over ``λ`` (``--lams``), Galerkin and
   re-discretised coarse operators: the V(1,1) convergence factor (stationary cycles) and the number
   of MG-preconditioned CG iterations to ``1e-8`` (``nestmg.solve_on_hierarchy(accel="cg")``).

Prints one JSON object (also ``--out/lazy_solvers.json``) and saves ``--png`` (factors side by side).

Usage::

    python benchmarks/archive/lazy_solvers.py ZOO_DIR --meshes gargo 3holes \\
        --out OUT --png docs/images/lazy_solvers.png
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

PROBLEMS = ("poisson-dirichlet", "poisson-neumann", "diffusion-neumann")


def say(msg: str) -> None:
    print(f"[lazy_solvers] {msg}", file=sys.stderr, flush=True)


def cages_for(name, V, F, counts, method, out_dir):
    """Cages of ``method`` (cached as npz in ``out_dir``); returns (layers, seconds, label)."""
    from cagegen import build_cages

    f = out_dir / f"{name}_{method}_cages.npz" if out_dir else None
    if f is not None and f.exists():
        z = np.load(f)
        k = len([x for x in z.files if x.startswith("V")])
        return [(z[f"V{i}"], z[f"F{i}"]) for i in range(k)], float(z["seconds"]), str(z["label"])
    t0 = time.perf_counter()
    label = method
    try:
        layers = build_cages(V, F, face_counts=counts, method=method)
    except Exception as exc:
        if method != "nested":
            raise
        say(f"{name}: nested backend failed ({exc}); using the reference wheel's cages")
        import nested_cages

        out = nested_cages.nested_cages(V, F, num_faces=list(counts), quad_order=2, energy_expansion="None",
                                        energy_final="Volume", regular=[True] * len(counts))
        cages = [(np.asarray(a, float), np.asarray(b, np.int64)) for a, b in out]
        cages = cages[-len(counts):]
        layers, label = [(V, F)] + cages, "wheel"
    sec = time.perf_counter() - t0
    if f is not None:
        arrs = {"seconds": sec, "label": label}
        for i, (Vi, Fi) in enumerate(layers):
            arrs[f"V{i}"], arrs[f"F{i}"] = Vi, Fi
        np.savez(f, **arrs)
    return layers, sec, label


def mesh_to_nodes(V, F, n_target, h_start, tol, max_tries=6):
    """TetGen mesh of ``(V, F)`` whose node count is within ``tol`` of ``n_target`` (secant on h^-3)."""
    from nestmg.tetmesh import tetrahedralize

    h = h_start
    best = None
    for _ in range(max_tries):
        Vt, T = tetrahedralize(V, F, mesher="tetgen", edge_length_abs=h)
        err = len(Vt) / n_target - 1
        if best is None or abs(err) < abs(best[2]):
            best = (Vt, T, err, h)
        if abs(err) <= tol:
            break
        h *= (len(Vt) / n_target) ** (1 / 3)
    return best


def run_mesh(name, path, args, out_dir) -> dict:
    from cagegen import default_face_counts, verify_nesting
    from nestmg.io import load_mesh, normalize
    from nestmg.prolongation import prolongation
    from nestmg.run import solve_on_hierarchy
    from nestmg.tetmesh import tetrahedralize

    V, F = load_mesh(path)
    V = normalize(V)[0]
    F = np.asarray(F, dtype=np.int64)
    counts = default_face_counts(len(F), args.levels)
    h0 = args.h0 if args.h0 else float(np.linalg.norm(V[F[:, 1]] - V[F[:, 0]], axis=1).mean())
    res: dict = {"n_faces": len(F), "face_counts": counts, "h0": h0, "hierarchies": {}}

    tight, t_tight, label = cages_for(name, V, F, counts, "nested", out_dir)
    loose, t_loose, _ = cages_for(name, V, F, counts, "lazy", out_dir)
    say(f"{name}: cages {label} {t_tight:.1f} s, lazy {t_loose:.1f} s")

    t0 = time.perf_counter()
    fine = tetrahedralize(V, F, mesher="tetgen", edge_length_abs=h0)
    say(f"{name}: fine tets {len(fine[1])} / {len(fine[0])} nodes ({time.perf_counter() - t0:.1f} s)")
    tets_tight = [fine] + [tetrahedralize(*tight[k], mesher="tetgen", edge_length_abs=h0 * 2**k)
                           for k in range(1, len(tight))]
    tets_loose = [fine]
    for k in range(1, len(loose)):
        Vt, T, _err, h = mesh_to_nodes(*loose[k], len(tets_tight[k][0]), h0 * 2**k, args.node_tol)
        tets_loose.append((Vt, T))
    for lab, surfaces, tets, secs in ((label, tight, tets_tight, t_tight), ("lazy", loose, tets_loose, t_loose)):
        P, reps = [], []
        for k in range(len(tets) - 1):
            Pk, rk = prolongation(tets[k][0], tets[k + 1][0], tets[k + 1][1], extrapolation="clamped")
            P.append(Pk)
            reps.append(rk)
        rep = verify_nesting(surfaces)
        h: dict = {
            "cage_seconds": secs,
            "surface_faces": [len(Fs) for _, Fs in surfaces],
            "surfaces_nested": rep.ok,
            "gap_rel": [p.min_gap_rel for p in rep.pairs],
            "nodes": [len(Vt) for Vt, _ in tets],
            "tets": [len(T) for _, T in tets],
            "n_outside": [r.n_outside for r in reps],
            "runs": [],
        }
        for prob in PROBLEMS:
            lams = args.lams if prob == "diffusion-neumann" else [None]
            for lam in lams:
                for coarse in ("galerkin", "rediscretized"):
                    kw = {"lam": lam} if lam is not None else {}
                    st = solve_on_hierarchy(tets, P, prob, coarse=coarse, nu=1, maxiter=args.cycles, tol=1e-8,
                                            cost=False, **kw)
                    cg = solve_on_hierarchy(tets, P, prob, coarse=coarse, nu=1, accel="cg", maxiter=200, tol=1e-8,
                                            cost=False, **kw)
                    row = {"problem": prob, "lam": lam, "coarse": coarse,
                           "factor": st["factor"], "diverged": st["diverged"],
                           "cg_iterations": cg["iterations"] if cg["converged"] else None,
                           "cg_converged": cg["converged"], "cg_diverged": cg["diverged"],
                           "seconds_cg": cg["seconds"]["solve"]}
                    h["runs"].append(row)
                    say(f"{name} {lab:6s} {prob:18s} lam={lam} {coarse:13s} factor {row['factor']:.3f}"
                        f"{' DIVERGED' if st['diverged'] else ''} cg {row['cg_iterations']}")
        res["hierarchies"][lab] = h
    return res


def plot(results, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    meshes = list(results["meshes"])
    fig, axes = plt.subplots(len(meshes), 2, figsize=(13, 3.6 * len(meshes)), squeeze=False)
    for i, m in enumerate(meshes):
        hs = results["meshes"][m]["hierarchies"]
        for j, coarse in enumerate(("galerkin", "rediscretized")):
            ax = axes[i, j]
            for n, (lab, h) in enumerate(hs.items()):
                runs = [r for r in h["runs"] if r["coarse"] == coarse]
                xl = [r["problem"].replace("poisson-", "P-").replace("diffusion-neumann", "diff")
                      + (f" {r['lam']:g}" if r["lam"] is not None else "") for r in runs]
                vals = [min(r["factor"], 2.0) for r in runs]
                ax.bar(np.arange(len(runs)) + 0.4 * n - 0.2, vals, 0.4, label=f"{lab} ({h['nodes']} nodes)")
            ax.axhline(1.0, color="k", lw=0.8)
            ax.set_xticks(np.arange(len(xl)))
            ax.set_xticklabels(xl, rotation=30, fontsize=8)
            ax.set_ylabel("V(1,1) factor (clipped at 2)")
            ax.set_title(f"{m}: {coarse} coarse operators", fontsize=10)
            ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("zoo")
    ap.add_argument("--meshes", nargs="+", default=["gargo", "3holes"])
    ap.add_argument("--levels", type=int, default=3)
    ap.add_argument("--h0", type=float, default=None, help="fine edge length / diagonal (default: mean edge)")
    ap.add_argument("--lams", nargs="+", type=float, default=[1e-3, 1e-2, 1e-1, 1.0])
    ap.add_argument("--node-tol", type=float, default=0.05)
    ap.add_argument("--cycles", type=int, default=25, help="stationary cycles for the factor")
    ap.add_argument("--out", default=None)
    ap.add_argument("--png", default=None)
    args = ap.parse_args(argv)
    out_dir = Path(args.out) if args.out else None
    if out_dir:
        out_dir.mkdir(parents=True, exist_ok=True)
    results: dict = {"levels": args.levels, "meshes": {}}
    for name in args.meshes:
        path = next(p for p in Path(args.zoo).iterdir() if p.stem == name)
        results["meshes"][name] = run_mesh(name, path, args, out_dir)
        if out_dir:
            (out_dir / "lazy_solvers.json").write_text(json.dumps(results, indent=1, default=float))
    if args.png:
        plot(results, args.png)
    print(json.dumps(results, indent=1, default=float))
    return results


if __name__ == "__main__":
    main()
