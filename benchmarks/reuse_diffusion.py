"""Reuse case (a) of issue 15: implicit diffusion time stepping with a time step that changes every step.

``(M + Δt_k K) u_k = M u_{k-1}``, k = 1..steps (natural boundary, P1 stiffness ``K``, lumped mass ``M``),
``Δt_k`` log-uniform in ``[dt_min, dt_max] x diag²`` (fixed seed; ``diag`` = bounding-box diagonal).
Every method solves the same matrix and right-hand side in lock step (the shared state ``u_{k-1}`` is the
CHOLMOD solution when CHOLMOD is available, else nestmg's) and iterative ones start from ``u_{k-1}`` and
stop at ``||b - A u|| <= 1e-8 ||b||``:

``nestmg``          Galerkin ``PᵀMP``, ``PᵀKP`` once (:class:`solvers.shifted.ShiftedGalerkin`); per step
                    the sparse sum, smoothers and coarsest factorisation, MG-PCG (the stepper's default
                    cycle, ``smoothing="fast"``: textbook V(1,1)).
``nestmg_robust``   nestmg with ``smoothing="robust"`` (the pipeline's variable V-cycle + boundary-layer sweeps).
``nestmg_rap``      nestmg with the Galerkin products recomputed every step (what the sum saves).
``pyamg_sa``        pyamg smoothed aggregation set up again every step, CG.
``gamg``            PETSc CG + GAMG, new matrix and full setup every step.
``gamg_reuse``      PETSc GAMG keeping its prolongators (``-pc_gamg_reuse_interpolation``): AMG's reuse.
``hypre``           PETSc CG + hypre BoomerAMG, full setup every step.
``cholmod``         CHOLMOD numeric re-factorisation every step, symbolic analysis once (OpenBLAS).

The goal compares nestmg with the best method that re-factors or re-sets up per step (all but
``gamg_reuse``, which is reported beside it).

    nice -n 10 python benchmarks/reuse_diffusion.py ZOO_DIR/bunny.off \
        ZOO_DIR/gargo.off --edge-length 0.0079 0.0067 --out benchmarks/results/reuse

Prints JSON, writes ``reuse_diffusion.json`` and ``reuse_diffusion.png`` into ``--out``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np
from exp_common import (
    Cholmod,
    PetscAmg,
    add_hierarchy_arguments,
    available_methods,
    blas_info,
    cached_hierarchy,
    environment,
    figure,
    hierarchies_from_args,
    join_runs,
    pyamg_sa_solve,
    relres,
    save_figure,
    write_json,
)
from nestmg import SolverOptions

METHODS = ("nestmg", "nestmg_robust", "nestmg_rap", "pyamg_sa", "gamg", "gamg_reuse", "hypre", "cholmod")
RESETUP = ("nestmg_rap", "pyamg_sa", "gamg", "hypre", "cholmod")  # re-factor / re-set up every step


def time_steps(n: int, dt_min: float, dt_max: float, diag: float, seed: int) -> np.ndarray:
    """``n`` time steps, log-uniform in ``[dt_min, dt_max] * diag**2`` (seeded)."""
    rng = np.random.default_rng(seed)
    return diag**2 * 10.0 ** rng.uniform(np.log10(dt_min), np.log10(dt_max), size=n)


def run_mesh(path: Path, edge: float | None, methods, steps: int, dt_min: float, dt_max: float, seed: int,
             tol: float, steps_for: dict | None = None, states_dir: Path | None = None) -> dict:
    from nestmg.timestepping import diffusion_stepper

    h, load_s = cached_hierarchy(path, edge_length=edge)
    V0 = h.tets[0][0]
    diag = float(np.linalg.norm(V0.max(axis=0) - V0.min(axis=0)))
    rec: dict = {"mesh": path.name, "edge_length": edge, "tets": [len(T) for _, T in h.tets],
                 "nodes": [len(V) for V, _ in h.tets],
                 "hierarchy_seconds": h.timings, "hierarchy_load_seconds": load_s, "diag": diag}
    print(f"{path.name}: tets {rec['tets']}, nodes {rec['nodes']}", file=sys.stderr, flush=True)
    # K and M are given to every method (a simulation code's own matrices); their assembly is not counted
    from solvers.fem import boundary_layer_nodes, mass_matrix, stiffness_matrix

    t0 = time.perf_counter()
    K, M = stiffness_matrix(*h.tets[0]), mass_matrix(*h.tets[0])
    rec["assembly_seconds"] = time.perf_counter() - t0
    t0, c0 = time.perf_counter(), time.process_time()
    st = diffusion_stepper(h.tets, h.P, K=K, M=M)
    rec["nestmg_once_seconds"] = dict(st.setup_seconds, total=time.perf_counter() - t0,
                                     total_cpu=time.process_time() - c0)
    st_robust = dataclasses.replace(st, smoothing="robust", problem=dataclasses.replace(
        st.problem, local_nodes=boundary_layer_nodes(h.tets[0][1], rings=1, n=len(V0))))
    dts = time_steps(steps, dt_min, dt_max, diag, seed)
    rec["dts"] = dts.tolist()
    # initial state: a Gaussian bump (σ = 0.1 diag) around the top-most node
    c = V0[np.argmax(V0[:, 2])]
    u = np.exp(-np.sum((V0 - c) ** 2, axis=1) / (2 * (0.1 * diag) ** 2))
    solvers = {}
    if "gamg" in methods:
        solvers["gamg"] = PetscAmg("gamg")
    if "gamg_reuse" in methods:
        solvers["gamg_reuse"] = PetscAmg("gamg", reuse_interpolation=True)
    if "hypre" in methods:
        solvers["hypre"] = PetscAmg("hypre")
    chol = Cholmod() if "cholmod" in methods else None
    runs: dict = {m: [] for m in methods}
    steps_for = {m: min(steps, (steps_for or {}).get(m, steps)) for m in methods}
    states: dict = {m: [] for m in methods}
    for k, dt in enumerate(dts):
        A = st.family.operators(1.0, dt)[0]
        b = st.M @ u
        sol = {}
        active = [m for m in methods if k < steps_for[m]]
        if not active:
            break
        for m in active:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                if m in ("nestmg", "nestmg_robust"):
                    x, i = (st if m == "nestmg" else st_robust).step(u, dt, tol=tol)
                    w, c = i["seconds"], i["cpu_seconds"]
                    row = {"setup": w["operators"] + w["setup"], "solve": w["solve"],
                           "setup_cpu": c["operators"] + c["setup"], "solve_cpu": c["solve"],
                           "iterations": i["iterations"], "final_residual": i["final_residual"],
                           "operators": w["operators"], "operators_cpu": c["operators"]}
                elif m == "nestmg_rap":
                    t0, c0 = time.perf_counter(), time.process_time()
                    prob = dataclasses.replace(st.problem, A=A, b=b, coarse="galerkin")
                    ml = prob.multigrid(SolverOptions(smoothing=st.smoothing))
                    t1, c1 = time.perf_counter(), time.process_time()
                    x, i = ml.solve(b, x0=u, tol=tol, maxiter=200, accel="cg", return_info=True)
                    t2, c2 = time.perf_counter(), time.process_time()
                    row = {"setup": t1 - t0, "solve": t2 - t1, "setup_cpu": c1 - c0, "solve_cpu": c2 - c1,
                           "iterations": i["iterations"], "final_residual": relres(A, b, x)}
                elif m == "pyamg_sa":
                    x, row = pyamg_sa_solve(A, b, x0=u, tol=tol)
                    row.pop("ml")
                elif m in solvers:
                    x, row = solvers[m].solve(A, b, x0=u, tol=tol)
                elif m == "cholmod":
                    tf, cf = chol.factor(A)
                    t0, c0 = time.perf_counter(), time.process_time()
                    x = chol.solve(b)
                    row = {"setup": tf, "solve": time.perf_counter() - t0, "setup_cpu": cf,
                           "solve_cpu": time.process_time() - c0, "iterations": 0, "final_residual": relres(A, b, x)}
                else:
                    raise ValueError(f"unknown method {m!r}")
            sol[m] = x
            runs[m].append(row)
            states[m].append(x)
        # the shared state: CHOLMOD's solution, else the first active method's (nestmg's when it runs)
        ref = sol.get("cholmod", sol[active[0]])
        for m in active:
            runs[m][-1]["max_diff_vs_ref_rel"] = float(np.abs(sol[m] - ref).max() / np.abs(ref).max())
        print(f"  step {k + 1:2d} dt {dt / diag**2:.2e} diag²: "
              + "  ".join(f"{m} {runs[m][-1]['setup_cpu'] + runs[m][-1]['solve_cpu']:.2f}s/{runs[m][-1]['iterations']}it"
                          for m in active), file=sys.stderr, flush=True)
        u = ref
    for s in solvers.values():
        s.destroy()
    once_nestmg = rec["nestmg_once_seconds"]["galerkin"] + rec["nestmg_once_seconds"]["problem"]
    once_nestmg_cpu = st.setup_seconds["cpu"]["galerkin"] + st.setup_seconds["cpu"]["problem"]
    once = {"nestmg": once_nestmg, "nestmg_robust": once_nestmg, "cholmod": chol.analyze_seconds if chol else 0.0}
    once_cpu = {"nestmg": once_nestmg_cpu, "nestmg_robust": once_nestmg_cpu,
                "cholmod": chol.analyze_cpu if chol else 0.0}
    rec["runs"], rec["once"], rec["once_cpu"] = runs, once, once_cpu
    rec["reference"] = "cholmod" if "cholmod" in methods else methods[0]
    if states_dir is not None:  # the states, for cross-process comparisons (--merge)
        states_dir.mkdir(parents=True, exist_ok=True)
        for m, xs in states.items():
            np.save(states_dir / f"{path.stem}_{m}.npy", np.array(xs))
    summarize(rec)
    return rec


def summarize(rec: dict) -> None:
    """Per-method totals and the speed-ups; a method run on fewer steps than ``dts`` (``--steps-for``) gets
    its measured per-step mean scaled to all steps (``*_extrapolated``, flagged ``steps_measured``)."""
    n_steps = len(rec["dts"])
    summary = {}
    for m, rows in rec["runs"].items():
        k = len(rows)
        once, once_cpu = rec["once"].get(m, 0.0), rec["once_cpu"].get(m, 0.0)
        setup, solve = sum(r["setup"] for r in rows), sum(r["solve"] for r in rows)
        setup_cpu, solve_cpu = sum(r["setup_cpu"] for r in rows), sum(r["solve_cpu"] for r in rows)
        summary[m] = {"steps_measured": k, "once": once, "setup": setup, "solve": solve, "total": once + setup + solve,
                      "once_cpu": once_cpu, "setup_cpu": setup_cpu, "solve_cpu": solve_cpu,
                      "cpu": once_cpu + setup_cpu + solve_cpu,
                      "cpu_per_step": (setup_cpu + solve_cpu) / k,
                      "cpu_all_steps": once_cpu + (setup_cpu + solve_cpu) * n_steps / k,
                      "wall_all_steps": once + (setup + solve) * n_steps / k,
                      "extrapolated": k < n_steps,
                      "iterations": [r["iterations"] for r in rows],
                      "max_final_residual": max(r["final_residual"] for r in rows),
                      "max_diff_vs_ref_rel": max(r["max_diff_vs_ref_rel"] for r in rows)}
    rec["summary"] = summary
    alts = [m for m in RESETUP if m in summary and m != "nestmg_rap"]
    if "nestmg" in summary and alts:
        best = min(alts, key=lambda m: summary[m]["wall_all_steps"])
        rec["best_resetup_alternative"] = best
        rec["speedup_vs_best_resetup"] = summary[best]["wall_all_steps"] / summary["nestmg"]["wall_all_steps"]
        best_cpu = min(alts, key=lambda m: summary[m]["cpu_all_steps"])
        rec["best_resetup_alternative_cpu"] = best_cpu
        rec["speedup_vs_best_resetup_cpu"] = summary[best_cpu]["cpu_all_steps"] / summary["nestmg"]["cpu_all_steps"]
    if "nestmg" in summary and "gamg_reuse" in summary:
        rec["speedup_vs_gamg_reuse_cpu"] = summary["gamg_reuse"]["cpu_all_steps"] / summary["nestmg"]["cpu_all_steps"]


def merge(files: list[Path], states_dir: Path | None) -> dict:
    """One result from runs of the same meshes with different ``--methods`` (separate processes): runs are
    joined per mesh, the states compared with the reference's (CHOLMOD, else nestmg) step by step."""
    res = join_runs(files, ("dts", "tets"), ("once", "once_cpu"))
    for rec in res["meshes"]:
        ref = "cholmod" if "cholmod" in rec["runs"] else "nestmg"
        rec["reference"] = ref
        if states_dir is not None and (states_dir / f"{Path(rec['mesh']).stem}_{ref}.npy").exists():
            R = np.load(states_dir / f"{Path(rec['mesh']).stem}_{ref}.npy")
            for m, rows in rec["runs"].items():
                X = np.load(states_dir / f"{Path(rec['mesh']).stem}_{m}.npy")
                for k in range(min(len(X), len(R))):
                    rows[k]["max_diff_vs_ref_rel"] = float(np.abs(X[k] - R[k]).max() / np.abs(R[k]).max())
        # only the runs' own methods' one-time costs
        rec["once"] = {k: v for k, v in rec["once"].items() if k in rec["runs"]}
        rec["once_cpu"] = {k: v for k, v in rec["once_cpu"].items() if k in rec["runs"]}
        rec["runs"] = {m: rec["runs"][m] for m in METHODS if m in rec["runs"]}
        summarize(rec)
    return res


def plot(res: dict, path: Path) -> None:
    meshes = res["meshes"]
    fig, axes = figure(1, 2 * len(meshes), figsize=(7 * len(meshes), 4.2), squeeze=False)
    for j, rec in enumerate(meshes):
        ax = axes[0, 2 * j]
        sm = rec["summary"]
        ms = list(sm)
        scale = [len(rec["dts"]) / sm[m]["steps_measured"] for m in ms]  # > 1: extrapolated from fewer steps
        once = [sm[m]["once_cpu"] for m in ms]
        setup = [sm[m]["setup_cpu"] * f for m, f in zip(ms, scale)]
        solve = [sm[m]["solve_cpu"] * f for m, f in zip(ms, scale)]
        ms = [m if f == 1 else f"{m}*" for m, f in zip(ms, scale)]
        ax.bar(ms, once, color="0.6", label="once (Galerkin M, K / CHOLMOD analysis)")
        ax.bar(ms, setup, bottom=once, color="tab:orange", label="per-step setup / factorisation")
        ax.bar(ms, solve, bottom=np.add(once, setup), color="tab:blue", label="per-step solve")
        ax.set_ylabel(f"CPU seconds for {len(rec['dts'])} steps (*: per-step mean x {len(rec['dts'])})")
        ax.set_title(f"{rec['mesh']}: {rec['tets'][0]:,} tets, diffusion steps")
        ax.tick_params(axis="x", rotation=30)
        ax.legend(fontsize=7)
        ax = axes[0, 2 * j + 1]
        x = np.array(rec["dts"]) / rec["diag"] ** 2
        for m in sm:
            y = np.array([r["setup_cpu"] + r["solve_cpu"] for r in rec["runs"][m]])
            xm = x[: len(y)]
            o = np.argsort(xm)
            ax.loglog(xm[o], y[o], marker="o", ms=3, label=m)
        ax.set_xlabel("Δt / diag²")
        ax.set_ylabel("CPU seconds per step")
        ax.set_title(f"{rec['mesh']}: per step")
        ax.legend(fontsize=7)
    save_figure(fig, path)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_hierarchy_arguments(ap)
    ap.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--dt-min", type=float, default=1e-4, help="smallest Δt / diag²")
    ap.add_argument("--dt-max", type=float, default=1e-2, help="largest Δt / diag²")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--tol", type=float, default=1e-8)
    ap.add_argument("--steps-for", nargs="+", default=[], metavar="METHOD=N",
                    help="run METHOD on the first N steps only (its 20-step cost is then extrapolated, flagged)")
    ap.add_argument("--states-dir", type=Path, default=None, help="save every method's states here (for --merge)")
    ap.add_argument("--merge", type=Path, nargs="+", default=None,
                    help="merge these reuse_diffusion.json files (runs of other --methods) into --out")
    ap.add_argument("--out", type=Path, default=Path("bench_out/reuse"))
    a = ap.parse_args(argv)
    if not a.merge and not a.meshes:
        ap.error("give mesh files (or --merge JSON files)")
    if a.merge:
        res = merge(a.merge, a.states_dir)
        res["params"]["command"] = " ".join(sys.argv)
        write_json(res, a.out / "reuse_diffusion.json")
        plot(res, a.out / "reuse_diffusion.png")
        print(json.dumps({r["mesh"]: {"speedup_vs_best_resetup_cpu": r.get("speedup_vs_best_resetup_cpu"),
                                      "best_resetup_alternative_cpu": r.get("best_resetup_alternative_cpu")}
                          for r in res["meshes"]}, indent=1))
        return 0
    steps_for = {k: int(v) for k, v in (x.split("=") for x in a.steps_for)}
    methods = available_methods(a.methods, METHODS)
    res = {"case": "a: implicit diffusion, changing time step",
           "params": {"steps": a.steps, "dt_range_over_diag2": [a.dt_min, a.dt_max], "seed": a.seed, "tol": a.tol,
                      "methods": methods, "steps_for": steps_for, "command": " ".join(sys.argv)},
           "environment": environment(), "meshes": []}
    for p, edge in hierarchies_from_args(a):
        res["meshes"].append(run_mesh(p, edge, methods, a.steps, a.dt_min, a.dt_max, a.seed, a.tol, steps_for,
                                      a.states_dir))
    res["blas"] = blas_info()
    write_json(res, a.out / "reuse_diffusion.json")
    plot(res, a.out / "reuse_diffusion.png")
    print(json.dumps({r["mesh"]: {"summary": {m: {k: v for k, v in sm.items() if k != "iterations"}
                                              for m, sm in r["summary"].items()},
                                  "speedup_vs_best_resetup": r.get("speedup_vs_best_resetup"),
                                  "speedup_vs_best_resetup_cpu": r.get("speedup_vs_best_resetup_cpu"),
                                  "best_resetup_alternative": r.get("best_resetup_alternative")}
                      for r in res["meshes"]}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
