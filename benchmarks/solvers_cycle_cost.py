"""Cost of one multigrid cycle in units of one fine SpMV, and solver comparison, on a Kuhn cube.

Dirichlet Poisson on the unit cube, Kuhn tets, ``n`` cells per side (n=48: 103,823 unknowns),
exactly nested hierarchy halving n per level. Prints one JSON object and saves a PNG of the
residual histories. Run (from the repo root, or with nestmg installed):

    PYTHONPATH=. python benchmarks/solvers_cycle_cost.py [--n 48] [--levels 5] [--out benchmarks/solvers_cycle_cost.png]

SpMV-unit costs use process CPU time (robust to preemption on a shared machine); solve/setup
times are wall-clock. ``loadavg`` is recorded before and after.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

from solvers import MultigridSolver, convergence_factor, fem, restrict_prolongations
from solvers.baselines import pyamg_sa
from solvers.gallery import kuhn_cube_hierarchy
from solvers.smoothing import make_smoother


def median_time(f, repeat: int) -> float:
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        f()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts))


def in_spmv(f, spmv, repeat: int, block: int = 5) -> tuple[float, float, float]:
    """Cost of ``f`` in fine SpMVs.

    Blocks of ``block`` calls of ``f`` alternate with blocks of ``4*block`` SpMVs; both are timed in
    process CPU time (``time.process_time``), which is not inflated when other jobs preempt us on a
    shared machine (cache/memory-bandwidth contention still is). Returns (median ratio, best-of
    ratio = min f / min SpMV, median CPU seconds of one ``f``).
    """
    tf, ts = [], []
    for _ in range(repeat):
        t0 = time.process_time()
        for _k in range(4 * block):
            spmv()
        t1 = time.process_time()
        for _k in range(block):
            f()
        t2 = time.process_time()
        ts.append((t1 - t0) / (4 * block))
        tf.append((t2 - t1) / block)
    tf, ts = np.array(tf), np.array(ts)
    return float(np.median(tf / ts)), float(tf.min() / ts.min()), float(np.median(tf))


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=48)
    ap.add_argument("--levels", type=int, default=5)
    ap.add_argument("--repeat", type=int, default=9)
    ap.add_argument("--out", default="benchmarks/solvers_cycle_cost.png")
    args = ap.parse_args(argv)

    t0 = time.perf_counter()
    meshes, Ps = kuhn_cube_hierarchy(args.n, args.levels)
    V, T = meshes[0]
    K, M = fem.stiffness_matrix(V, T), fem.mass_matrix(V, T)
    ds = fem.eliminate_dirichlet(K, fem.load_vector(M, 1.0), fem.boundary_nodes(T))
    Pf, _ = restrict_prolongations(Ps, ds.free)
    t_assembly = time.perf_counter() - t0
    A, b = ds.A, ds.b
    x = np.random.default_rng(0).standard_normal(A.shape[0])

    out: dict = {
        "problem": f"Dirichlet Poisson, Kuhn cube n={args.n}",
        "unknowns": int(A.shape[0]),
        "nnz": int(A.nnz),
        "levels": args.levels,
        "assembly_seconds": t_assembly,
        "loadavg_before": os.getloadavg(),
    }
    t_spmv = median_time(lambda: A @ x, 5 * args.repeat)
    out["spmv_seconds"] = t_spmv
    spmv = lambda: A @ x

    # smoother sweeps alone, in SpMV units
    sweeps = {}
    for name, spec in [
        ("symmetric_gauss_seidel", "symmetric_gauss_seidel"),
        ("forward_gauss_seidel", "gauss_seidel"),
        ("jacobi", "jacobi"),
        ("chebyshev_deg3", "chebyshev"),
    ]:
        sm = make_smoother(A, spec)
        y = x.copy()
        med, best, _ = in_spmv(lambda sm=sm, y=y: sm(A, y, b), spmv, args.repeat)
        sweeps[name] = {"median": med, "best": best}
    out["smoother_sweep_in_spmv"] = sweeps

    cycles = {}
    histories = {}
    for label, spec in [("V(1,1) SGS", "symmetric_gauss_seidel"), ("V(1,1) Chebyshev", "chebyshev"),
                        ("V(1,1) Jacobi", "jacobi")]:
        t0 = time.perf_counter()
        ml = MultigridSolver(A, Pf, presmoother=spec)
        setup = time.perf_counter() - t0
        for cyc in ("V", "W", "F") if spec == "symmetric_gauss_seidel" else ("V",):
            prec = ml.aspreconditioner(cyc)
            med, best, t_cycle = in_spmv(lambda prec=prec: prec @ b, spmv, args.repeat)
            res = []
            t0 = time.perf_counter()
            ml.solve(b, tol=1e-8, cycle=cyc, residuals=res)
            t_solve = time.perf_counter() - t0
            key = label.replace("V(", f"{cyc}(")
            cycles[key] = {
                "setup_seconds": setup,
                "cycle_seconds": t_cycle,
                "cycle_in_spmv_measured_median": med,
                "cycle_in_spmv_measured_best": best,
                "cycle_complexity_model": ml.cycle_complexity(cyc),
                "factor": convergence_factor(res),
                "cycles_to_1e-8": len(res) - 1,
                "solve_seconds": t_solve,
            }
            histories[f"{key} stationary"] = res
        res = []
        t0 = time.perf_counter()
        ml.solve(b, tol=1e-8, accel="cg", residuals=res)
        cycles[label]["pcg_iterations"] = len(res) - 1
        cycles[label]["pcg_seconds"] = time.perf_counter() - t0
        histories[f"{label} + CG"] = res
        if spec == "symmetric_gauss_seidel":
            out["repr"] = repr(ml)
            out["operator_complexity"] = ml.operator_complexity()
    out["cycles"] = cycles

    for smooth in ("default", "energy"):
        r = pyamg_sa(A, b, tol=1e-8, smooth=smooth)
        out[r.name] = r.to_dict()
        histories[f"{r.name} + CG"] = r.residuals
    out["loadavg_after"] = os.getloadavg()

    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(7, 4.5))
        for name, h in histories.items():
            ax.semilogy(h, marker=".", label=name)
        ax.set_xlabel("cycle / CG iteration")
        ax.set_ylabel("relative residual")
        ax.set_title(f"Dirichlet Poisson, Kuhn cube, {A.shape[0]} unknowns, {args.levels} levels")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(args.out, dpi=120)
        out["plot"] = args.out
    except (ImportError, RuntimeError, OSError) as e:  # plotting is optional
        out["plot_error"] = str(e)
    print(json.dumps(out, indent=2, default=float))
    return out


if __name__ == "__main__":
    main()
