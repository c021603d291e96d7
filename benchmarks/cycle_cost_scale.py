"""Cycle cost, MG-PCG cost and ``setup_problem`` cost at >= 1M tets (issue 15, items 2 and 3).

    nice -n 10 python benchmarks/cycle_cost_scale.py ZOO_DIR/bunny.off \
        --fine-tets 1150000 --out benchmarks/results/cycle_cost_scale

Builds (or loads from the cache) a 4-level hierarchy: TetGen (opt-in, for the measurement only) of the
input at ~``--fine-tets`` tets, one same-domain level, two nested cages. Then, on the fine mesh:

* setup: ``igl.cotmatrix`` vs ``nestmg.problems.setup_problem`` (Dirichlet and Neumann), best of
  ``--repeat``;
* for Galerkin and weighted coarse operators and two smoothers -- symmetric Gauss–Seidel before and
  after (4 sweeps per level visit) and forward before / backward after (2 sweeps, still a symmetric
  cycle) -- the cost of one V-cycle in fine SpMVs (counted, and measured by CPU time, best of
  ``--repeat``), MG-PCG iterations to 1e-8, and the solve's CPU time in fine SpMVs.

CPU (process) time, not wall time, is the unit: robust to other jobs on a shared machine (all kernels
are single-threaded). Prints one JSON document and writes ``cycle_cost_scale.json`` into ``--out``.
"""

from __future__ import annotations

import argparse
import json
import time
import warnings
from pathlib import Path

import numpy as np

from nestmg import MeshingOptions, SizingOptions, SolverOptions

SMOOTHERS = {
    "sgs/sgs": (("gauss_seidel", {"sweep": "symmetric", "iterations": 1}), None),
    "fgs/bgs": (("gauss_seidel", {"sweep": "forward", "iterations": 1}), None),  # post = adjoint = backward
}
#: ``--presets``: the two cycles of ``Problem.multigrid(smoothing=...)`` instead of the two smoothers above,
#: plus, where the problem has boundary-layer nodes (Neumann), both with one-way local sweeps
PRESETS = ("robust", "fast")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("mesh", type=Path)
    ap.add_argument("--fine-tets", type=int, default=1_150_000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", type=Path, default=Path("bench_out/cycle_cost_scale"))
    ap.add_argument("--edge-length", type=float, default=None,
                    help="use the 3-level TetWild hierarchy of the reuse benchmarks (exp_common.cached_hierarchy, "
                         "this fine edge / diagonal) instead of the 4-level TetGen one")
    ap.add_argument("--presets", action="store_true",
                    help="compare Problem.multigrid(smoothing='robust'|'fast') (Galerkin only) instead of the smoothers")
    ap.add_argument("--setup-only", action="store_true", help="stop after the setup_problem / cotmatrix timing")
    args = ap.parse_args(argv)

    import igl
    from exp_common import best_cpu_time as best
    from exp_common import edge_for_tets

    from nestmg.hierarchy import build_hierarchy
    from nestmg.io import json_default, load_mesh, normalize
    from nestmg.problems import FAST_SMOOTHERS, setup_problem, volume_fractions

    V, F = load_mesh(args.mesh)
    V, _, _ = normalize(V)
    t0 = time.perf_counter()
    if args.edge_length is not None:
        from exp_common import cached_hierarchy

        h, _ = cached_hierarchy(args.mesh, edge_length=args.edge_length)
    else:
        h = build_hierarchy(V, F, 4, "nested", meshing=MeshingOptions(mesher="tetgen"), progress=False,
                            sizing=SizingOptions(edge_length=edge_for_tets(V, F, args.fine_tets),
                                                 same_domain_levels=1))
    doc: dict = {"benchmark": "cycle_cost_scale", "mesh": args.mesh.name, "build_seconds": time.perf_counter() - t0,
                 "tets": [len(T) for _, T in h.tets], "nodes": [len(Vk) for Vk, _ in h.tets],
                 "n_outside": [int(x) for x in h.n_outside]}
    print(json.dumps({k: doc[k] for k in ("tets", "n_outside")}), flush=True)
    V0, T0 = (np.asarray(a) for a in h.tets[0])
    V0 = np.ascontiguousarray(V0, dtype=np.float64)
    T0 = np.ascontiguousarray(T0, dtype=np.int64)
    # interleaved repetitions (cotmatrix, Dirichlet, Neumann, cotmatrix, ...), best of each: the machine's
    # speed drifts by up to ~30 % between minutes, so timing one after the other biases the ratio
    names = ("poisson-dirichlet", "poisson-neumann")
    times: dict = {"cot": [], **{p: [] for p in names}}
    for _ in range(args.repeat):
        times["cot"].append(best(lambda: igl.cotmatrix(V0, T0), 1))
        for prob in names:
            times[prob].append(best(lambda: setup_problem(h.tets[:1], [], prob), 1))  # noqa: B023
    t_cot = min(times["cot"])
    doc["setup"] = {"cotmatrix_seconds": t_cot, "all_seconds": times}
    for prob in names:
        t = min(times[prob])
        doc["setup"][prob] = {"setup_problem_seconds": t, "ratio_to_cotmatrix": t / t_cot}
        print(f"setup {prob}: cotmatrix {t_cot:.2f} s, setup_problem {t:.2f} s ({t / t_cot:.2f}x)", flush=True)
    if args.setup_only:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "setup_cost.json").write_text(json.dumps(doc, indent=1, default=json_default))
        print(json.dumps({"written": str(args.out / "setup_cost.json")}))
        return
    t0 = time.perf_counter()
    fr = volume_fractions(h.tets)
    doc["fractions_seconds"] = time.perf_counter() - t0
    doc["runs"] = []
    for prob in ("poisson-dirichlet", "poisson-neumann"):
        for coarse in ("galerkin",) if args.presets else ("galerkin", "weighted"):
            t0 = time.perf_counter()
            pr = setup_problem(h.tets, h.P, prob, coarse=coarse, fractions=fr)
            t_prob = time.perf_counter() - t0
            A = pr.A
            x = np.random.default_rng(0).standard_normal(A.shape[0])
            t_spmv = best(lambda: [A @ x for _ in range(20)], args.repeat) / 20  # noqa: B023
            # on pure Neumann "fast" adds boundary-layer sweeps (FAST_NEUMANN_SMOOTHERS); "fast-textbook"
            # is the plain V(1,1) it replaced
            one_way = {"robust+one-way-local": (SolverOptions(), {"local_sweep": "one-way"}),
                       "fast-textbook": (SolverOptions(smoothing="fast", local=False),
                                         {"presmoother": FAST_SMOOTHERS})}
            variants = ({**{p: (SolverOptions(smoothing=p), {}) for p in PRESETS},
                         **(one_way if pr.local_nodes is not None else {})}
                        if args.presets else
                        {k: (None, {"presmoother": pre, "postsmoother": post})
                         for k, (pre, post) in SMOOTHERS.items()})
            for sname, (opts, kw) in variants.items():
                t0 = time.perf_counter()
                ml = pr.multigrid(opts, **kw)
                t_setup = time.perf_counter() - t0
                M = ml.aspreconditioner()
                t_cyc = best(lambda: M.matvec(x), args.repeat)  # noqa: B023
                c_all, w_all = [], []
                for _ in range(args.repeat):  # best of --repeat solves (the VM's speed drifts)
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")
                        c0, w0 = time.process_time(), time.perf_counter()
                        _, info = ml.solve(pr.b, tol=1e-8, maxiter=100, accel="cg", return_info=True)
                        c_all.append(time.process_time() - c0)
                        w_all.append(time.perf_counter() - w0)
                c_solve, w_solve = min(c_all), min(w_all)
                rec = {"problem": prob, "coarse": coarse, "smoother": sname, "coarse_scaling": ml.coarse_scaling,
                       "operator_complexity": ml.operator_complexity(), "problem_seconds": t_prob,
                       "solver_setup_seconds": t_setup, "spmv_cpu_seconds": t_spmv,
                       "cycle_counted_spmv": ml.cycle_complexity("V"), "cycle_measured_spmv": t_cyc / t_spmv,
                       "pcg_iterations": info["iterations"], "pcg_converged": info["converged"],
                       "solve_cpu_seconds": c_solve, "solve_wall_seconds": w_solve,
                       "solve_spmv": c_solve / t_spmv, "solve_wall_spmv": w_solve / t_spmv,
                       "solve_cpu_seconds_all": c_all,
                       "local_nodes": int(ml.levels[0].presmoother.params.get("local_nodes", 0)),
                       "local_sweep": ml.levels[0].presmoother.params.get("local_sweep")}
                doc["runs"].append(rec)
                print(f"{prob:18s} {coarse:9s} {sname}: opc {rec['operator_complexity']:.2f} cycle "
                      f"{rec['cycle_measured_spmv']:.1f} SpMV (counted {rec['cycle_counted_spmv']:.1f}); PCG "
                      f"{info['iterations']} it = {rec['solve_spmv']:.0f} SpMV; setup {t_prob:.2f}+{t_setup:.2f} s",
                      flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "cycle_cost_scale.json").write_text(json.dumps(doc, indent=1, default=json_default))
    print(json.dumps({"written": str(args.out / "cycle_cost_scale.json")}))


if __name__ == "__main__":
    main()
