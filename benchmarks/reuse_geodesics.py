"""Reuse case (b) of issue 15: heat-method geodesic distance from many sources on one shape.

Per source (:func:`nestmg.geodesics.heat_geodesic`, same matrices for every method): the heat step
``(M + t K) u = δ_s`` (``t`` = squared mean edge) and the Neumann Poisson step ``K φ = div X``. Both
matrices are fixed for all sources, so every method sets up (factorises) each matrix **once** and then
solves ``2 x sources`` systems: this is CHOLMOD's home ground (a factorisation amortised over many
triangular solves). Iterative methods start from zero and stop at ``||b - A x|| <= 1e-8 ||b||``:

``nestmg``    :func:`nestmg.problems.setup_problem` (``diffusion-neumann`` with ``λ = t``,
              ``poisson-neumann``; the pruning of :func:`nestmg.geodesics.multigrid_solve`) and
              ``Problem.multigrid()`` (project defaults), MG-PCG.
``nestmg_fast`` the same with ``Problem.multigrid(smoothing="fast")`` (textbook V(1,1) for the heat step,
              plus the boundary-layer sweeps for the pure Neumann Poisson step).
``pyamg_sa``  pyamg smoothed aggregation, CG (Poisson step: the project's CG with the constants projected).
``gamg``      PETSc CG + GAMG.  ``hypre``: PETSc CG + hypre BoomerAMG.
``cholmod``   CHOLMOD (OpenBLAS), one node pinned for the Poisson step.

Sources: ``--sources`` fine nodes drawn with a fixed seed; methods run in lock step per source.

    nice -n 10 python benchmarks/reuse_geodesics.py ZOO_DIR/bunny.off \
        --edge-length 0.0079 --out benchmarks/results/reuse

Prints JSON, writes ``reuse_geodesics.json`` and ``reuse_geodesics.png`` into ``--out``.
"""

from __future__ import annotations

import argparse
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

METHODS = ("nestmg", "nestmg_fast", "pyamg_sa", "gamg", "hypre", "cholmod")


def _timed(f):
    t0, c0 = time.perf_counter(), time.process_time()
    out = f()
    return out, time.perf_counter() - t0, time.process_time() - c0


def make_solvers(methods, h, pre) -> tuple[dict, dict]:
    """``name -> solve(A, b, kind)`` for :func:`heat_geodesic`, each set up once per matrix, and the
    setup record ``name -> {wall, cpu, ...}``."""
    from nestmg.problems import setup_problem

    solve_fns, setups = {}, {}
    mats = {"heat": pre.A_heat, "poisson": pre.K}
    for m in methods:
        rec: dict = {}
        if m in ("nestmg", "nestmg_fast"):
            kw = SolverOptions(smoothing="fast" if m == "nestmg_fast" else "robust")
            mls = {}
            for kind, name, prune in (("heat", "diffusion-neumann", 0.0), ("poisson", "poisson-neumann", 0.5)):
                prob, tp, cp = _timed(lambda name=name, prune=prune: setup_problem(h.tets, h.P, name, lam=pre.t,
                                                                                   prune=prune))
                diff = abs(prob.A - mats[kind]).max() / abs(mats[kind]).max()
                if diff > 1e-12:
                    raise RuntimeError(f"setup_problem's {kind} matrix differs from the heat method's ({diff:.2e})")
                ml, tm, cm = _timed(lambda prob=prob, kw=kw: prob.multigrid(kw))
                mls[kind] = ml
                rec[kind] = {"setup_problem": tp, "multigrid": tm, "cpu": cp + cm,
                             "operator_complexity": ml.operator_complexity()}
            rec["wall"] = sum(rec[k]["setup_problem"] + rec[k]["multigrid"] for k in mats)
            # setup_problem re-assembles K and M (already in the heat precompute): the multigrid part alone
            rec["wall_multigrid_only"] = sum(rec[k]["multigrid"] for k in mats)

            def fn(A, b, kind, mls=mls):
                x, i = mls[kind].solve(b, tol=TOL, maxiter=200, accel="cg", return_info=True)
                return x, {"iterations": i["iterations"], "final_residual": relres(A, b, x)}
        elif m == "pyamg_sa":
            import pyamg

            mls = {}
            for kind, Am in mats.items():
                mls[kind], tw, tc = _timed(lambda Am=Am: pyamg.smoothed_aggregation_solver(Am))
                rec[kind] = {"wall": tw, "cpu": tc, "operator_complexity": float(mls[kind].operator_complexity())}

            def fn(A, b, kind, mls=mls):
                x, i = pyamg_sa_solve(A, b, tol=TOL, ml=mls[kind], nullspace="constant" if kind == "poisson" else None)
                return x, {"iterations": i["iterations"], "final_residual": i["final_residual"]}
        elif m in ("gamg", "hypre"):
            amgs = {}
            for kind, Am in mats.items():
                amg = amgs[kind] = PetscAmg(m, nullspace="constant" if kind == "poisson" else None)
                _, tw, tc = _timed(lambda Am=Am, amg=amg: amg.setup(Am))
                rec[kind] = {"wall": tw, "cpu": tc}

            def fn(A, b, kind, amgs=amgs):
                x, i = amgs[kind].apply(b, tol=TOL)
                return x, {"iterations": i["iterations"], "final_residual": i["final_residual"]}
            rec["_objects"] = amgs
        elif m == "cholmod":
            chols = {}
            for kind, Am in mats.items():
                ch = chols[kind] = Cholmod(pin=0 if kind == "poisson" else None)
                (tf, cf), tw, tc = _timed(lambda Am=Am, ch=ch: ch.factor(Am))
                rec[kind] = {"wall": tw, "cpu": tc, "analyze": [ch.analyze_seconds, ch.analyze_cpu], "numeric": [tf, cf]}

            def fn(A, b, kind, chols=chols):
                x = chols[kind].solve(b)
                return x, {"iterations": 0, "final_residual": relres(A, b, x)}
        else:
            raise ValueError(f"unknown method {m!r}")
        if "wall" not in rec:
            rec["wall"] = sum(rec[k]["wall"] for k in mats)
        rec["cpu"] = sum(rec[k]["cpu"] for k in mats)
        solve_fns[m], setups[m] = fn, rec
    return solve_fns, setups


TOL = 1e-8


def run_mesh(path: Path, edge, methods, n_sources: int, seed: int, states_dir: Path | None = None) -> dict:
    from nestmg.geodesics import heat_geodesic, heat_precompute

    h, _ = cached_hierarchy(path, edge_length=edge)
    V0, T0 = h.tets[0]
    rec: dict = {"mesh": path.name, "edge_length": edge, "tets": [len(T) for _, T in h.tets],
                 "nodes": [len(V) for V, _ in h.tets], "hierarchy_seconds": h.timings}
    print(f"{path.name}: tets {rec['tets']}, nodes {rec['nodes']}", file=sys.stderr, flush=True)
    pre, tw, _ = _timed(lambda: heat_precompute(V0, T0))
    rec["heat_precompute_seconds"] = tw  # common to every method, not counted
    rec["t"] = pre.t
    solve_fns, setups = make_solvers(methods, h, pre)
    objects = [s.pop("_objects") for s in setups.values() if "_objects" in s]
    sources = np.random.default_rng(seed).choice(len(V0), size=n_sources, replace=False)
    rec["sources"] = sources.tolist()
    runs: dict = {m: [] for m in methods}
    dists: dict = {m: [] for m in methods}
    for j, s in enumerate(sources):
        dist = {}
        for m in methods:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                out, tw, tc = _timed(lambda s=s, m=m: heat_geodesic(V0, T0, int(s), pre=pre, solve=solve_fns[m]))
            dist[m] = out.distance
            dists[m].append(out.distance.astype(np.float32))
            runs[m].append({"wall": tw, "cpu": tc,
                            "iterations": [out.info["heat"]["iterations"], out.info["poisson"]["iterations"]],
                            "final_residual": max(out.info["heat"]["final_residual"],
                                                  out.info["poisson"]["final_residual"])})
        ref = dist.get("cholmod", dist[methods[0]])
        for m in methods:
            runs[m][-1].update(_diff_stats(dist[m], ref))
        print(f"  source {j + 1:2d}: " + "  ".join(f"{m} {r[-1]['cpu']:.2f}s/{r[-1]['iterations']}it"
                                                   for m, r in runs.items()), file=sys.stderr, flush=True)
    for group in objects:
        for o in group.values():
            o.destroy()
    if states_dir is not None:  # distances (float32), for cross-process comparisons (--merge)
        states_dir.mkdir(parents=True, exist_ok=True)
        for m, d in dists.items():
            np.save(states_dir / f"geo_{path.stem}_{m}.npy", np.array(d))
    rec["setups"], rec["runs"] = setups, runs
    summarize(rec)
    return rec


def _diff_stats(d: np.ndarray, ref: np.ndarray) -> dict:
    e = np.abs(np.asarray(d, dtype=np.float64) - ref) / np.abs(ref).max()
    return {"max_diff_vs_ref_rel": float(e.max()), "p99_diff_vs_ref_rel": float(np.quantile(e, 0.99)),
            "median_diff_vs_ref_rel": float(np.median(e))}


def summarize(rec: dict) -> None:
    """Per-method totals, distance differences and the break-even source count against CHOLMOD."""
    setups, runs = rec["setups"], rec["runs"]
    summary = {}
    for m, rows in runs.items():
        per = [r["wall"] for r in rows]
        summary[m] = {"setup": setups[m]["wall"], "setup_cpu": setups[m]["cpu"],
                      "per_source_median": float(np.median(per)), "sources_total": float(np.sum(per)),
                      "per_source_median_cpu": float(np.median([r["cpu"] for r in rows])),
                      "total": setups[m]["wall"] + float(np.sum(per)),
                      "cpu": setups[m]["cpu"] + float(sum(r["cpu"] for r in rows)),
                      "iterations_median": np.median([r["iterations"] for r in rows], axis=0).tolist(),
                      "max_final_residual": max(r["final_residual"] for r in rows),
                      "max_diff_vs_ref_rel": max(r["max_diff_vs_ref_rel"] for r in rows),
                      "p99_diff_vs_ref_rel_median": float(np.median([r["p99_diff_vs_ref_rel"] for r in rows])),
                      "median_diff_vs_ref_rel_median": float(np.median([r["median_diff_vs_ref_rel"] for r in rows]))}
    if "cholmod" in summary:  # sources up to which a method's CPU total stays below CHOLMOD's
        c = summary["cholmod"]
        for m, s in summary.items():
            if m == "cholmod":
                continue
            gap_setup = c["setup_cpu"] - s["setup_cpu"]  # positive: m sets up faster (CPU)
            gap_per = s["per_source_median_cpu"] - c["per_source_median_cpu"]  # positive: CHOLMOD solves faster
            s["break_even_sources_vs_cholmod"] = (gap_setup / gap_per if gap_per > 0 else float("inf")) \
                if gap_setup > 0 else 0.0
    rec["summary"] = summary


def merge(files: list[Path], states_dir: Path | None) -> dict:
    """One result from runs of the same mesh and sources with different ``--methods`` (separate processes);
    distances compared with CHOLMOD's (else nestmg's) from the saved states."""
    res = join_runs(files, ("sources", "tets"), ("setups",))
    for rec in res["meshes"]:
        ref = "cholmod" if "cholmod" in rec["runs"] else "nestmg"
        rec["reference"] = ref
        stem = Path(rec["mesh"]).stem
        if states_dir is not None and (states_dir / f"geo_{stem}_{ref}.npy").exists():
            R = np.load(states_dir / f"geo_{stem}_{ref}.npy").astype(np.float64)
            for m, rows in rec["runs"].items():
                X = np.load(states_dir / f"geo_{stem}_{m}.npy")
                for j, row in enumerate(rows):
                    row.update(_diff_stats(X[j], R[j]))
        rec["runs"] = {m: rec["runs"][m] for m in METHODS if m in rec["runs"]}
        summarize(rec)
    return res


def plot(res: dict, path: Path) -> None:
    meshes = res["meshes"]
    fig, axes = figure(1, len(meshes), figsize=(6.5 * len(meshes), 4.2), squeeze=False)
    for j, rec in enumerate(meshes):
        ax = axes[0, j]
        for m, s in rec["summary"].items():
            cum = s["setup_cpu"] + np.cumsum([r["cpu"] for r in rec["runs"][m]])
            ax.plot(np.arange(0, len(cum) + 1), np.concatenate([[s["setup_cpu"]], cum]), label=m)
        ax.set_xlabel("sources")
        ax.set_ylabel("cumulative CPU seconds (setup at 0)")
        ax.set_title(f"{rec['mesh']}: {rec['tets'][0]:,} tets, heat-method geodesics")
        ax.legend(fontsize=8)
    save_figure(fig, path)


def main(argv=None) -> int:
    global TOL
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_hierarchy_arguments(ap)
    ap.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    ap.add_argument("--sources", type=int, default=50)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--tol", type=float, default=1e-8)
    ap.add_argument("--states-dir", type=Path, default=None, help="save the distances here (for --merge)")
    ap.add_argument("--merge", type=Path, nargs="+", default=None,
                    help="merge these reuse_geodesics.json files (runs of other --methods) into --out")
    ap.add_argument("--out", type=Path, default=Path("bench_out/reuse"))
    a = ap.parse_args(argv)
    TOL = a.tol
    if a.merge:
        res = merge(a.merge, a.states_dir)
        res["params"]["command"] = " ".join(sys.argv)
        write_json(res, a.out / "reuse_geodesics.json")
        plot(res, a.out / "reuse_geodesics.png")
        print(json.dumps({r["mesh"]: r["summary"] for r in res["meshes"]}, indent=1))
        return 0
    if not a.meshes:
        ap.error("give mesh files (or --merge JSON files)")
    methods = available_methods(a.methods, METHODS)
    res = {"case": "b: heat-method geodesics from many sources",
           "params": {"sources": a.sources, "seed": a.seed, "tol": a.tol, "methods": methods,
                      "command": " ".join(sys.argv)},
           "environment": environment(), "meshes": []}
    for p, edge in hierarchies_from_args(a):
        res["meshes"].append(run_mesh(p, edge, methods, a.sources, a.seed, a.states_dir))
    res["blas"] = blas_info()
    res["environment_end"] = environment()
    write_json(res, a.out / "reuse_geodesics.json")
    plot(res, a.out / "reuse_geodesics.png")
    print(json.dumps({r["mesh"]: r["summary"] for r in res["meshes"]}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
