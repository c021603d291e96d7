"""Experiment 4 (Nested Cages paper, Sec. 7): time to solution, nestmg against AMG and direct solvers.

Dirichlet Poisson on fine TetGen meshes of ~100k, ~500k and ≥1M tets, to a relative residual of 1e-8.
nestmg: nested-cage hierarchy (with 0 / 1 / 2 same-domain levels first, see ``exp_scaling.py``), CG
preconditioned by one V(1,1) cycle, Galerkin and re-discretised coarse operators; setup split into
cages (the cage backend's own time, possibly from the cache), tet layers (TetGen, uncached), prolongations
and operators (assembly + multigrid setup). Against pyamg smoothed aggregation (default and
``smooth='energy'``) and Ruge–Stüben (both CG-accelerated), SuperLU and CHOLMOD, on the same matrix
and right-hand side, all in one run.

Every solver runs in a spawned child process, so that its peak memory can be measured on its own
(``/proc/self/clear_refs`` resets the high-water mark; reported: ``VmHWM`` minus the resident size
at the start, MiB) and a runaway direct solver cannot take the benchmark down (``--timeout``).

    python benchmarks/exp_timing.py --zoo ZOO_DIR --out bench_out/exp_timing           # ~10 min
    python benchmarks/exp_timing.py --zoo ZOO_DIR --quick --out OUT                    # ~1 min

Writes ``exp_timing.json`` and ``exp_timing.png`` into ``--out``.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import sys
import time
import traceback
import warnings
from pathlib import Path

import numpy as np
from exp_common import cages, edge_for_tets, environment, figure, load_zoo, save_figure, write_json
from nestmg import MeshingOptions, SizingOptions, SolverOptions


def _status_kb(field: str) -> int:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    return 0


def _child(conn, fn, args):
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")  # reset the peak-RSS high-water mark of this process
    except OSError:
        pass
    rss0 = _status_kb("VmRSS")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            out = fn(*args)
        out["peak_mem_mib"] = (_status_kb("VmHWM") - rss0) / 1024.0
        conn.send(out)
    except Exception as exc:  # noqa: BLE001 -- any solver failure is a result row, not a crash
        conn.send({"error": f"{type(exc).__name__}: {str(exc)[:300]}", "trace": traceback.format_exc()[-800:]})
    conn.close()


def in_child(fn, *args, timeout: float = 600.0) -> dict:
    """Run ``fn(*args) -> dict`` in a fresh (spawned) process; add its extra peak memory; kill it after ``timeout`` s.

    A spawned child starts with an empty heap (a forked one would reuse the parent's freed, still
    resident memory and under-report), receives ``args`` by pickle before the baseline RSS is taken.
    """
    ctx = mp.get_context("spawn")
    parent, child = ctx.Pipe(duplex=False)
    p = ctx.Process(target=_child, args=(child, fn, args))
    t0 = time.perf_counter()
    p.start()
    child.close()
    if parent.poll(timeout):
        out = parent.recv()
    else:
        p.kill()
        out = {"error": f"timeout after {timeout:.0f} s"}
    p.join()
    out["wall_seconds"] = time.perf_counter() - t0
    return out


# ----------------------------------------------------------------------------- solver runs (in children)
def _nestmg(tets, P, coarse, tol):
    from nestmg.problems import setup_problem

    t0 = time.perf_counter()
    prob = setup_problem(tets, P, "poisson-dirichlet", coarse=coarse)
    t1 = time.perf_counter()
    ml = prob.multigrid(SolverOptions(coarse_scaling=None))
    t2 = time.perf_counter()
    x, info = ml.solve(prob.b, tol=tol, maxiter=200, accel="cg", return_info=True)
    t3 = time.perf_counter()
    rel = float(np.linalg.norm(prob.b - prob.A @ x) / np.linalg.norm(prob.b))
    return {"assembly_seconds": t1 - t0, "mg_setup_seconds": t2 - t1, "setup_seconds": t2 - t0,
            "solve_seconds": t3 - t2, "iterations": info["iterations"], "converged": info["converged"],
            "final_residual": rel, "levels": [int(L.A.shape[0]) for L in ml.levels],
            "operator_complexity": ml.operator_complexity()}


def _baseline(name, A, b, tol):
    from solvers.baselines import BASELINES

    kw = {"tol": tol} if name.startswith("pyamg") else {}
    r = BASELINES[name](A, b, **kw)
    d = r.to_dict()
    rel = float(np.linalg.norm(b - A @ r.x) / np.linalg.norm(b))
    return {"setup_seconds": d["setup_seconds"], "solve_seconds": d["solve_seconds"], "iterations": d["iterations"],
            "converged": d["converged"], "final_residual": rel,
            "info": {k: v for k, v in d["info"].items() if k != "final_true_residual"}}


# ----------------------------------------------------------------------------- experiment
def run_size(V, F, mesh, target, s, args):
    from nestmg.hierarchy import tet_hierarchy
    from nestmg.problems import setup_problem
    from solvers.baselines import cholmod_available

    h0 = edge_for_tets(V, F, target)
    surfaces, cinfo = cages(V, F, 3, "nested")
    layers = [(V, F)] * (s + 1) + list(surfaces[1:])
    t0 = time.perf_counter()
    tets, P, reps, tt = tet_hierarchy(layers, sizing=SizingOptions(edge_length=h0, coarsening=None),
                                      meshing=MeshingOptions(mesher="tetgen"), cache=False, progress=False)
    t_tets = time.perf_counter() - t0
    rec = {"mesh": mesh, "target_tets": target, "same_domain_levels": s,
           "tets": [len(T) for _, T in tets], "nodes": [len(Vk) for Vk, _ in tets],
           "n_outside": [r.n_outside for r in reps],
           "nestmg_pipeline_seconds": {"cages": float(cinfo.get("seconds", np.nan)),
                                       "cages_from_cache": bool(cinfo.get("cached", False)),
                                       "tets": float(tt.get("tets", t_tets)),
                                       "prolongation": float(tt.get("prolongation", 0.0))},
           "solvers": {}}
    print(f"{mesh} target {target}: tets {rec['tets']}, n_outside {rec['n_outside']}, "
          f"tets {rec['nestmg_pipeline_seconds']['tets']:.1f} s, P {rec['nestmg_pipeline_seconds']['prolongation']:.2f} s,"
          f" cages {rec['nestmg_pipeline_seconds']['cages']:.1f} s (cached: {rec['nestmg_pipeline_seconds']['cages_from_cache']})",
          flush=True)
    prob = setup_problem(tets[:1] + tets[1:], P, "poisson-dirichlet")
    A, b = prob.A, prob.b
    rec["unknowns"] = int(A.shape[0])
    rec["nnz"] = int(A.nnz)
    for coarse in ("galerkin", "rediscretized"):
        r = in_child(_nestmg, tets, P, coarse, args.tol, timeout=args.timeout)
        rec["solvers"][f"nestmg_{coarse}"] = r
        _report(mesh, target, f"nestmg_{coarse}", r)
    for name in ("pyamg_sa", "pyamg_sa_energy", "pyamg_rs", "cholmod", "scipy_splu"):
        if name == "cholmod" and not cholmod_available():
            rec["solvers"][name] = {"skipped": "scikit-sparse not installed"}
            continue
        if name == "scipy_splu" and A.shape[0] > args.splu_max:
            rec["solvers"][name] = {"skipped": f"{A.shape[0]} unknowns > --splu-max {args.splu_max} "
                                                "(ENVIRONMENT.md: 152 s and 9.3 GB at 135k unknowns)"}
            print(f"  {mesh:<10} {target:>8} {name:<24} skipped ({A.shape[0]} unknowns)", flush=True)
            continue
        r = in_child(_baseline, name, A, b, args.tol, timeout=args.timeout)
        rec["solvers"][name] = r
        _report(mesh, target, name, r)
    return rec


def _report(mesh, target, name, r):
    if "error" in r:
        print(f"  {mesh:<10} {target:>8} {name:<24} ERROR {r['error'][:100]}", flush=True)
        return
    tot = r["setup_seconds"] + r["solve_seconds"]
    print(f"  {mesh:<10} {target:>8} {name:<24} setup {r['setup_seconds']:7.2f} s solve {r['solve_seconds']:7.2f} s "
          f"total {tot:7.2f} s its {r['iterations']:>3} res {r['final_residual']:.1e} mem {r['peak_mem_mib']:7.0f} MiB",
          flush=True)


def plot(results, path: Path):
    names = ["nestmg_galerkin", "nestmg_rediscretized", "pyamg_sa", "pyamg_sa_energy", "pyamg_rs", "cholmod",
             "scipy_splu"]
    colors = ["k", "0.4", "tab:blue", "tab:cyan", "tab:green", "tab:red", "tab:orange"]
    fig, axes = figure(1, 3, figsize=(16, 4.5))
    recs = results["runs"]
    x = np.arange(len(recs))
    w = 0.8 / len(names)
    for i, (n, c) in enumerate(zip(names, colors)):
        for j, rec in enumerate(recs):
            r = rec["solvers"].get(n, {})
            if "setup_seconds" not in r:
                continue
            axes[0].bar(j + i * w, r["setup_seconds"], w, color=c, alpha=0.5)
            axes[0].bar(j + i * w, r["solve_seconds"], w, bottom=r["setup_seconds"], color=c,
                        label=n if j == 0 else None)
            axes[1].bar(j + i * w, r["solve_seconds"], w, color=c, label=n if j == 0 else None)
            axes[2].bar(j + i * w, max(r["peak_mem_mib"], 1.0), w, color=c, label=n if j == 0 else None)
    labels = [f"{r['mesh']}\n{r['tets'][0] / 1e3:.0f}k tets" for r in recs]
    for ax, t in zip(axes, ("setup (light) + solve seconds", "solve seconds", "extra peak memory (MiB)")):
        ax.set_xticks(x + 0.4 - w / 2)
        ax.set_xticklabels(labels, fontsize=8)
        ax.set_yscale("log")
        ax.set_title(t)
    axes[0].legend(fontsize=7)
    fig.suptitle("Dirichlet Poisson to 1e-8 (one run; ratios matter, absolute times are on a shared 2-core machine)")
    save_figure(fig, path)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--zoo", type=Path, required=True, help="folder of the dev-zoo meshes")
    ap.add_argument("--meshes", nargs="+", default=["gargo.off"])
    ap.add_argument("--sizes", type=int, nargs="+", default=[100_000, 500_000, 1_100_000])
    ap.add_argument("--tol", type=float, default=1e-8)
    ap.add_argument("--splu-max", type=int, default=100_000, help="skip SuperLU above this many unknowns")
    ap.add_argument("--timeout", type=float, default=600.0, help="seconds per solver")
    ap.add_argument("--quick", action="store_true", help="one mesh at 100k tets")
    ap.add_argument("--out", type=Path, default=Path("bench_out/exp_timing"))
    a = ap.parse_args(argv)
    if a.quick:
        a.meshes, a.sizes = a.meshes[:1], [100_000]
    import exp_common

    exp_common.ZOO = a.zoo
    res = {"params": {"sizes": a.sizes, "tol": a.tol, "problem": "poisson-dirichlet",
                      "nestmg": "CG + one V(1,1) symmetric Gauss-Seidel cycle", "splu_max": a.splu_max},
           "environment": environment(), "runs": []}
    for mesh in a.meshes:
        V, F = load_zoo(mesh)
        for n in a.sizes:
            s = 0 if n <= 150_000 else (1 if n <= 700_000 else 2)
            res["runs"].append(run_size(V, F, mesh, n, s, a))
            write_json(res, a.out / "exp_timing.json")
    plot(res, a.out / "exp_timing.png")
    print(f"wrote {a.out / 'exp_timing.json'} and {a.out / 'exp_timing.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
