"""Coarse operators compared (issue 15, item 1): Galerkin, re-discretised, volume-fraction weighted,
sparsified Galerkin (``solvers.reroute_to_pattern`` onto the coarse meshes' sparsity), each with and without the energy-optimal scaling of the coarse correction, on nested and naive
(``method="decimate"``) hierarchies of dev-zoo meshes.

    nice -n 10 python benchmarks/coarse_operators.py ZOO_DIR \
        --meshes gargo.off bunny.off 3holes.off --methods nested decimate --mesher tetgen \
        --fine-tets 200000 --out benchmarks/results/coarse_operators

Per hierarchy and problem (Dirichlet Poisson, Neumann Poisson, Neumann diffusion λ = 1e-2): the V(1,1)
convergence factor (symmetric Gauss–Seidel, stationary cycles to 1e-8, geometric mean of the last 5
ratios), MG-PCG iterations to 1e-8, operator complexity, and the seconds of problem setup (assembly +
volume fractions) and solver setup. Prints one JSON document and writes ``coarse_operators.json`` and
``coarse_operators.png`` into ``--out``.
"""

from __future__ import annotations

import argparse
import json
import time
import warnings
from pathlib import Path

import numpy as np

from nestmg import SolverOptions

VARIANTS = (  # (coarse, coarse_scaling)
    ("galerkin", None),
    ("rediscretized", None),
    ("rediscretized", "energy"),
    ("weighted", None),
    ("weighted", "energy"),
    ("sparsified", None),
    ("sparsified", "energy"),
)
PROBLEMS = ("poisson-dirichlet", "poisson-neumann", "diffusion-neumann")


def _solve(prob, scaling, maxiter):
    from solvers import DivergenceError

    t0 = time.perf_counter()
    ml = prob.multigrid(SolverOptions(coarse_scaling=scaling))
    t_setup = time.perf_counter() - t0
    rec = {"setup_seconds": t_setup, "operator_complexity": ml.operator_complexity(),
           "levels": [{"n": int(L.A.shape[0]), "nnz": int(L.A.nnz)} for L in ml.levels]}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            t0 = time.perf_counter()
            _, info = ml.solve(prob.b, tol=1e-8, maxiter=maxiter, return_info=True)
            rec.update(factor=info["factor"], cycles=info["iterations"], converged=info["converged"],
                       cycle_seconds=time.perf_counter() - t0, diverged=False)
        except DivergenceError as exc:
            rec.update(factor=float("inf"), cycles=exc.cycle, converged=False, diverged=True)
        try:
            t0 = time.perf_counter()
            _, info = ml.solve(prob.b, tol=1e-8, maxiter=maxiter, accel="cg", return_info=True)
            rec.update(pcg_iterations=info["iterations"], pcg_converged=info["converged"],
                       pcg_seconds=time.perf_counter() - t0)
        except DivergenceError:
            rec.update(pcg_iterations=None, pcg_converged=False)
    return rec


def run_mesh(path: Path, methods, levels, fine_tets, mesher, maxiter, edge_length=None):
    from exp_common import edge_for_tets, try_hierarchy

    from nestmg.io import load_mesh, normalize
    from nestmg.problems import setup_problem, volume_fractions

    V, F = load_mesh(path)
    V, _, _ = normalize(V)
    h0 = edge_length if edge_length else (edge_for_tets(V, F, fine_tets) if mesher == "tetgen" else None)
    out = {"mesh": path.name, "faces": len(F), "methods": {}}
    for m in methods:
        rec: dict = {}
        t0 = time.perf_counter()
        h = try_hierarchy(rec, f"  {path.name:<12} {m:<9}", V, F, levels, m, h0, mesher)
        if h is None:
            out["methods"][m] = rec
            continue
        rec["build_seconds"] = time.perf_counter() - t0
        rec["tets"] = [len(T) for _, T in h.tets]
        rec["n_outside"] = [int(x) for x in h.n_outside]
        t0 = time.perf_counter()
        fr = volume_fractions(h.tets)
        rec["fractions_seconds"] = time.perf_counter() - t0
        rec["fraction_mean"] = [float(np.mean(w)) for w in fr[1:]]
        rec["runs"] = []
        for prob_name in PROBLEMS:
            probs = {}
            for coarse, scaling in VARIANTS:
                if coarse not in probs:
                    t0 = time.perf_counter()
                    probs[coarse] = setup_problem(h.tets, h.P, prob_name, coarse=coarse, fractions=fr)
                    t_prob = time.perf_counter() - t0
                r = _solve(probs[coarse], scaling, maxiter)
                r.update(problem=prob_name, coarse=coarse, coarse_scaling=scaling, problem_seconds=t_prob)
                rec["runs"].append(r)
                print(f"  {path.name:<12} {m:<9} {prob_name:<18} {coarse:<13} {scaling!s:<6} factor "
                      f"{r['factor']:.3f} ({r['cycles']:>2} cycles)  PCG {r['pcg_iterations']} it  "
                      f"opc {r['operator_complexity']:.2f}", flush=True)
        out["methods"][m] = rec
    return out


def plot(results, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = [f"{c}{'+α' if s else ''}" for c, s in VARIANTS]
    cases = []
    for res in results:
        for m, rec in res["methods"].items():
            if "runs" in rec:
                cases.append((f"{res['mesh'].split('.')[0]}/{m}", rec))
    fig, axes = plt.subplots(1, len(PROBLEMS), figsize=(5 * len(PROBLEMS), 4), sharey=True)
    w = 0.8 / len(VARIANTS)
    for ax, prob in zip(np.atleast_1d(axes), PROBLEMS):
        for j, (c, s) in enumerate(VARIANTS):
            vals = []
            for _, rec in cases:
                r = [x for x in rec["runs"] if x["problem"] == prob and x["coarse"] == c and x["coarse_scaling"] == s]
                vals.append(min(r[0]["factor"], 1.0) if r else np.nan)
            ax.bar(np.arange(len(cases)) + j * w, vals, w, label=labels[j])
        ax.set_xticks(np.arange(len(cases)) + 0.4 - w / 2)
        ax.set_xticklabels([n for n, _ in cases], rotation=45, ha="right", fontsize=8)
        ax.set_title(prob)
        ax.set_ylim(0, 1)
    np.atleast_1d(axes)[0].set_ylabel("V(1,1) convergence factor (capped at 1)")
    np.atleast_1d(axes)[-1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("mesh_dir", type=Path)
    ap.add_argument("--meshes", nargs="+", default=["gargo.off", "bunny.off", "3holes.off"])
    ap.add_argument("--methods", nargs="+", default=["nested", "decimate"])
    ap.add_argument("--levels", type=int, default=3)
    ap.add_argument("--fine-tets", type=int, default=200_000)
    ap.add_argument("--mesher", default="tetgen", choices=["tetgen", "tetwild"])
    ap.add_argument("--maxiter", type=int, default=80)
    ap.add_argument("--edge-length", type=float, default=None,
                    help="fine edge length (unit bounding-box diagonal); default from --fine-tets (TetGen)")
    ap.add_argument("--out", type=Path, default=Path("bench_out/coarse_operators"))
    args = ap.parse_args(argv)
    from nestmg.io import json_default

    results = [run_mesh(args.mesh_dir / name, args.methods, args.levels, args.fine_tets, args.mesher, args.maxiter,
                        args.edge_length) for name in args.meshes]
    doc = {"benchmark": "coarse_operators", "mesher": args.mesher, "fine_tets": args.fine_tets,
           "edge_length": args.edge_length,
           "levels": args.levels, "results": results}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "coarse_operators.json").write_text(json.dumps(doc, indent=1, default=json_default))
    plot(results, args.out / "coarse_operators.png")
    print(json.dumps({"written": str(args.out / "coarse_operators.json")}))


if __name__ == "__main__":
    main()
