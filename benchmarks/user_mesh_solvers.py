"""nestmg vs pyamg SA vs PETSc GAMG on a user's own mesh and matrix (issue 31).

The path a user's matrix takes: a tet mesh file from the user's mesher (TetGen or TetWild stand in),
:func:`nestmg.load_tet_mesh` (meshio), :func:`nestmg.hierarchy_from_tets`, a P1 matrix assembled on the
user's nodes (libigl cotangent stiffness + lumped mass), then ``MultigridSolver(A, P)`` with its defaults
and MG-PCG, against pyamg smoothed aggregation + CG and PETSc GAMG + CG (1 rank) on the same matrix and
right-hand side, to ``--tol``. Two stages::

    # once per case: mesh, write the file, read it, build and save the hierarchy (under WORK, not the repo)
    python benchmarks/user_mesh_solvers.py build ZOO_DIR/bunny.off --mesher tetgen --fine-tets 1000000 \\
        --work WORK/bunny-tetgen
    # the solver comparison on saved cases: setup + solve, interleaved repeats, medians
    OMP_NUM_THREADS=1 python benchmarks/user_mesh_solvers.py run WORK/bunny-tetgen WORK/spot-tetwild ... \\
        --repeats 3 --json benchmarks/results/user_mesh/solvers.json
    # where the default cycle is slow (Neumann on TetGen meshes) and what helps: iterations, one run each
    OMP_NUM_THREADS=1 python benchmarks/user_mesh_solvers.py diagnose WORK/bunny-tetgen ... \
        --json benchmarks/results/user_mesh/neumann_diagnosis.json

``build`` writes ``user_mesh.vtu`` (the user's file) and ``hierarchy/`` (:func:`nestmg.save_hierarchy`) in
its work directory and is skipped when they exist.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from exp_common import cpu_times
from solvers.ordering import index_spread


def build(args) -> dict:
    """Mesh the surface (the user's mesher), write + read the file, build and save the hierarchy."""
    import trimesh

    from nestmg import (MeshingOptions, hierarchy_from_tets, load_mesh, load_tet_mesh, save_hierarchy,
                        save_tet_mesh, tetrahedralize)
    from nestmg.refine import refine_tets

    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    mesh_file = work / "user_mesh.vtu"
    info: dict = {"surface": Path(args.surface).name, "mesher": args.mesher,
                  "fine_tets_target": args.fine_tets}
    if not mesh_file.exists():
        V, F = load_mesh(args.surface)
        vol = trimesh.Trimesh(V, F, process=False).volume
        # TetGen's quality meshes come out ~1.8x denser than regular tets of edge h; TetWild's ~1x
        fill = 1.8 if args.mesher == "tetgen" else 1.0
        h = float((6 * np.sqrt(2) * vol * fill / args.fine_tets) ** (1 / 3))
        t = time.perf_counter()
        Vu, Tu = tetrahedralize(V, F, mesher=args.mesher, edge_length_abs=h * 2**args.refine, time_limit=None)
        info["user_mesher_seconds"] = time.perf_counter() - t
        info["mesher_tets"] = len(Tu)
        for _ in range(args.refine):  # the user refines the mesher's output uniformly (8x tets each time)
            Vu, Tu, _P = refine_tets(Vu, Tu)
        info["refined"] = args.refine
        save_tet_mesh(mesh_file, Vu, Tu)
    t = time.perf_counter()
    V0, T0 = load_tet_mesh(mesh_file)
    info.update(read_seconds=time.perf_counter() - t, nodes=len(V0), tets=len(T0))
    if not (work / "hierarchy" / "hierarchy.npz").exists():
        t = time.perf_counter()
        H = hierarchy_from_tets(V0, T0, args.levels, meshing=MeshingOptions(mesher=args.coarse_mesher),
                                progress=True)
        info["hierarchy_seconds"] = time.perf_counter() - t
        save_hierarchy(work / "hierarchy", H)
        info["hierarchy"] = {"tets": [len(T) for _, T in H.tets], "n_outside": H.n_outside,
                             "certified": H.certified}
    (work / "build.json").write_text(json.dumps(info, indent=1))
    print(json.dumps(info))
    return info


#: nestmg cycles compared by ``run --variants`` (the default cycle of ``MultigridSolver(A, P)`` is "default")
VARIANTS = {
    "default": {},
    "symmetric_gs": {"presmoother": ("gauss_seidel", {"sweep": "symmetric", "iterations": 1})},
    "forward_gs": {"presmoother": ("gauss_seidel", {"sweep": "forward", "iterations": 1})},
    # an explicit spec equal to the default: two sweeps on every level (no one-sweep dense levels)
    "forward_gs2_uniform": {"presmoother": ("gauss_seidel", {"sweep": "forward", "iterations": 2})},
    "chebyshev3": {"presmoother": ("chebyshev", {"degree": 3})},
    # natural (Neumann, diffusion) boundaries only: one forward / backward sweep over the fine boundary layer
    # (solvers.fem.boundary_layer_nodes)
    "boundary_layer": {"local_sweep": "one-way", "local_levels": 1},
    "forward_gs_coarse2": {"presmoother": [("gauss_seidel", {"sweep": "forward", "iterations": 1}),
                                           ("gauss_seidel", {"sweep": "forward", "iterations": 2})]},
    # three forward / backward sweeps on the fine level, one on the (dense) coarse levels
    "fine3": {"presmoother": [("gauss_seidel", {"sweep": "forward", "iterations": 3}),
                              ("gauss_seidel", {"sweep": "forward", "iterations": 1})]},
    # the coarse-level deflation probe (solvers.deflation) that was the constructor's default before
    "deflate8": {"deflate": 8},
    # the default cycle without the pre-smoother's cheap residual (Smoother.smooth_residual: a half sweep
    # from zero, the residual from the strict upper triangle): the residual as a full product, as before
    "plain_residual": {"_plain_residual": True},
    # the finest level's cheap slow-region probe (two V-cycles, solvers.subdomain.power_probe) and its
    # exact subdomain solve
    "local_probe2": {"local_probe": 2},
    "local_probe1": {"local_probe": 1},
    "local_probe3": {"local_probe": 3},
    # the default without the exact solve on the finest level's strongly coupled unknowns (the default
    # before it, solvers.subdomain.strongly_coupled)
    "no_strong_blocks": {"strong_blocks": None},
}

#: ``nestmg.setup_problem`` names of the benchmark's problems (``problem_multigrid``: ``Problem.multigrid()``)
PROBLEM_NAMES = {"dirichlet": "poisson-dirichlet", "neumann": "poisson-neumann",
                 "diffusion": "diffusion-neumann"}


def load_case(work: Path, problems=()) -> dict:
    """The user's mesh (read back from its file), the saved hierarchy, the matrices and right-hand sides;
    for each name in ``problems`` also the pipeline's :class:`nestmg.problems.Problem` (under the key
    ``"problem:" + name``) holding the same matrix and right-hand side."""
    from nestmg import load_hierarchy, load_tet_mesh
    from solvers import restrict_prolongations
    from solvers.fem import boundary_layer_nodes, boundary_nodes, mass_matrix, stiffness_matrix

    V, T = load_tet_mesh(work / "user_mesh.vtu")
    H = load_hierarchy(work / "hierarchy")
    if not (np.array_equal(H.tets[0][0], V) and np.array_equal(H.tets[0][1], T)):
        raise SystemExit(f"{work}: the hierarchy's fine level is not the user's mesh")
    K = stiffness_matrix(V, T)
    M = mass_matrix(V, T)
    d = np.linalg.norm(V.max(axis=0) - V.min(axis=0))
    f = 1.0 + np.sin(3 * V[:, 0] / d) * np.cos(2 * V[:, 1] / d) + V[:, 2] / d
    b = M @ f
    interior = np.setdiff1d(np.arange(len(V)), boundary_nodes(T))
    Pf, _ = restrict_prolongations(H.P, interior)
    m = M.diagonal()
    info = json.loads((work / "build.json").read_text())
    mesher = {"tetgen": "TetGen", "tetwild": "TetWild"}[info["mesher"]]
    if info.get("refined"):
        mesher += f" {info.get('mesher_tets', 0) / 1e3:.0f}k tets, red-refined x{info['refined']}"
    case = {
        "name": work.name, "label": f"{info['surface']}, {mesher}", "tets": len(T), "nodes": len(V),
        "build": info,
        "level_tets": [len(t) for _, t in H.tets],
        "n_outside": list(H.n_outside),
        "dirichlet": (sp_csr(K[interior][:, interior]), b[interior], Pf, None),
        "neumann": (K, b - m * (b.sum() / m.sum()), list(H.P), "constant"),
        # Neumann diffusion (λK + M) u = M f, λ = (d/10)², d the bounding-box diagonal (an implicit step)
        "diffusion": (sp_csr((d / 10) ** 2 * K + M), b, list(H.P), None),
        "boundary_layer": boundary_layer_nodes(T, 1),
    }
    for prob in problems:
        case["problem:" + prob] = pipeline_problem(H, case[prob], prob, (d / 10) ** 2)
    return case


def pipeline_problem(H, system, prob: str, lam: float):
    """``nestmg.setup_problem`` on the hierarchy (its pruned prolongations, boundary layer, defaults) with the
    benchmark's matrix and right-hand side put in (the assembly is the same: checked)."""
    import dataclasses

    from nestmg import setup_problem

    A, b, _Ps, _ns = system
    pr = setup_problem(H.tets, H.P, PROBLEM_NAMES[prob], lam=lam)
    if pr.A.shape != A.shape or abs(pr.A - A).max() > 1e-10 * abs(A).max():
        raise SystemExit(f"{prob}: setup_problem's matrix is not the benchmark's")
    return dataclasses.replace(pr, A=A, b=b)


def sp_csr(A):
    import scipy.sparse as sp

    A = sp.csr_matrix(A)
    A.sort_indices()
    return A


def run_nestmg(A, b, Ps, nullspace, tol, opts, problem=None) -> dict:
    """``MultigridSolver(A, Ps, **opts)`` (or ``problem.multigrid(**opts)``) + MG-PCG; set-up wall and CPU
    time."""
    from solvers import MultigridSolver

    opts = dict(opts)
    plain = opts.pop("_plain_residual", False)
    t, c = time.perf_counter(), time.process_time()
    ml = (problem.multigrid(**opts) if problem is not None
          else MultigridSolver(A, Ps, nullspace=nullspace, **opts))
    setup, setup_cpu = time.perf_counter() - t, time.process_time() - c
    for L in ml.levels[:-1] if plain else ():
        L.presmoother.smooth_residual = None  # the cycle's plain path: apply, then b - A x
    c = time.process_time()
    _, r = ml.solve(b, tol=tol, accel="cg", return_info=True)
    solve_cpu = time.process_time() - c
    return {"setup_seconds": setup, "setup_cpu_seconds": setup_cpu, "solve_seconds": r["seconds"],
            "solve_cpu_seconds": solve_cpu,
            "iterations": r["iterations"],
            "final_residual": float(np.linalg.norm(b - A @ _) / np.linalg.norm(b)),
            "deflated": [d["vectors"] for d in ml.deflation],
            "local_probe": getattr(ml, "local_probe", None),
            "strong_blocks": getattr(ml, "strong_blocks", None),
            "operator_complexity": ml.operator_complexity(), "cycle_complexity": ml.cycle_complexity(),
            "level_unknowns": [L.A.shape[0] for L in ml.levels],
            "level_nnz_per_row": [L.A.nnz / L.A.shape[0] for L in ml.levels],
            "reordered": ml.perm is not None,
            "spmv_internal_seconds": spmv_seconds(ml.levels[0].A, 10),
            "spmv_internal_cpu_seconds": spmv_seconds(ml.levels[0].A, 10, time.process_time)}


def run_sa(A, b, nullspace, tol) -> dict:
    """pyamg SA (defaults) as CG's preconditioner. Dirichlet: pyamg's own CG (``solvers.baselines.pyamg_sa``).
    Neumann: the same SA V-cycle inside :func:`solvers.krylov.pcg` with the iterates, the right-hand side and
    the preconditioned residual kept at zero mean, as nestmg's MG-PCG does: pyamg's CG on the singular
    matrix drifts along the constant null space (on these meshes it aborted as "indefinite" or ran to 500
    iterations in some repeats)."""
    import pyamg
    import scipy.sparse.linalg as spla

    from solvers.baselines import _pyamg_run  # pyamg_sa's runner (CG restarts on the true residual)
    from solvers.krylov import pcg

    if nullspace is None:
        cpu = {}

        def builder(A, **kw):  # pyamg_sa's own builder, with its CPU time kept
            c = time.process_time()
            ml = pyamg.smoothed_aggregation_solver(A, **kw)
            cpu["setup"] = time.process_time() - c
            return ml

        c = time.process_time()
        r = _pyamg_run("pyamg_sa", builder, A, b, tol, 500, "cg", nullspace)
        total_cpu = time.process_time() - c
        return {"setup_seconds": r.setup_seconds, "setup_cpu_seconds": cpu["setup"],
                "solve_seconds": r.solve_seconds, "solve_cpu_seconds": total_cpu - cpu["setup"],
                "iterations": r.iterations,
                "final_residual": r.info["final_true_residual"],
                "operator_complexity": r.info["operator_complexity"]}
    t, c = time.perf_counter(), time.process_time()
    ml = pyamg.smoothed_aggregation_solver(A)
    setup, setup_cpu = time.perf_counter() - t, time.process_time() - c
    M0 = ml.aspreconditioner(cycle="V")

    def mv(r):
        z = M0.matvec(r - r.mean())
        return z - z.mean()

    M = spla.LinearOperator(A.shape, matvec=mv, dtype=np.float64)
    c = time.process_time()
    res = pcg(A, b, M=M, tol=tol, maxiter=500, nullspace="constant")
    solve_cpu = time.process_time() - c
    return {"setup_seconds": setup, "setup_cpu_seconds": setup_cpu, "solve_seconds": res.seconds,
            "solve_cpu_seconds": solve_cpu,
            "iterations": res.iterations,
            "final_residual": float(np.linalg.norm(b - A @ res.x) / np.linalg.norm(b)),
            "operator_complexity": float(ml.operator_complexity())}


def run_gamg(A, b, nullspace, tol) -> dict:
    from solvers.petsc_amg import petsc_amg_solve

    x, r = petsc_amg_solve(A, b, "gamg", tol=tol, nullspace=nullspace)
    return {"setup_seconds": r["setup_seconds"], "solve_seconds": r["solve_seconds"],
            "setup_cpu_seconds": r["setup_cpu_seconds"], "solve_cpu_seconds": r["solve_cpu_seconds"],
            "iterations": r["iterations"],
            "final_residual": float(np.linalg.norm(b - A @ x) / np.linalg.norm(b))}


def spmv_seconds(A, repeats: int = 30, clock=time.perf_counter) -> float:
    """Best of 3 mean times of ``repeats`` SpMV with ``A`` (``clock``: wall, or ``time.process_time``)."""
    x = np.ones(A.shape[0])
    best = np.inf
    for _ in range(3):
        t = clock()
        for _ in range(repeats):
            A @ x
        best = min(best, (clock() - t) / repeats)
    return best


def run_one(c: dict, prob: str, sname: str, tol: float) -> dict:
    """One solver on one case and problem (``sname``: a baseline, ``problem_multigrid[_VARIANT]`` or
    ``nestmg[_VARIANT]``)."""
    A, b, Ps, ns = c[prob]
    if sname == "pyamg_sa":
        return run_sa(A, b, ns, tol)
    if sname == "petsc_gamg":
        return run_gamg(A, b, ns, tol)
    if sname.startswith("problem_multigrid"):
        v = sname[len("problem_multigrid_"):]
        return run_nestmg(A, b, Ps, ns, tol, VARIANTS[v] if v else {}, problem=c["problem:" + prob])
    v = sname[len("nestmg_"):] if sname != "nestmg" else "default"
    opts = dict(VARIANTS[v])
    if v == "boundary_layer":
        opts["local_nodes"] = c["boundary_layer"]
    return run_nestmg(A, b, Ps, ns, tol, opts)


def _median_of_ratios(raw: dict, case: str, prob: str, num: str, den: str, key: str) -> float:
    pairs = zip(raw[(case, prob, num)], raw[(case, prob, den)])
    return float(np.median([rn[key] / rd[key] for rn, rd in pairs]))


def summarize(c: dict, prob: str, solvers: list, raw: dict) -> dict:
    """Medians per solver, fine-SpMV counts and within-run ratios against the first solver.

    The speed-ups and ratios are medians of per-repeat ratios of CPU seconds (``time.process_time``: the
    machine is shared, wall seconds are inflated by other jobs); ``*_wall_*`` keys hold the same for wall
    seconds. ``solve_spmv`` is the solve's CPU time over one fine SpMV's (CPU, the caller's order).
    """
    A = c[prob][0]
    t_spmv = spmv_seconds(A)
    t_spmv_cpu = spmv_seconds(A, clock=time.process_time)
    pd: dict = {"unknowns": A.shape[0], "nnz": A.nnz, "spmv_seconds": t_spmv, "spmv_cpu_seconds": t_spmv_cpu,
                "solvers": {}, "index_spread": index_spread(A)}
    for sname in solvers:
        runs = raw.get((c["name"], prob, sname))
        if not runs:
            continue
        med = {k: float(np.median([r[k] for r in runs])) for k in
               ("setup_seconds", "setup_cpu_seconds", "solve_seconds", "solve_cpu_seconds", "total_seconds",
                "total_cpu_seconds") if k in runs[0]}
        med.update(iterations=int(np.median([r["iterations"] for r in runs])),
                   max_final_residual=max(r["final_residual"] for r in runs),
                   solve_spmv=med["solve_cpu_seconds"] / t_spmv_cpu,
                   solve_spmv_wall=med["solve_seconds"] / t_spmv, runs=runs)
        if "spmv_internal_seconds" in runs[0]:
            med["spmv_internal_seconds"] = float(np.median([r["spmv_internal_seconds"] for r in runs]))
            med["spmv_speedup_internal_order"] = t_spmv / med["spmv_internal_seconds"]
            med["spmv_internal_cpu_seconds"] = float(np.median([r["spmv_internal_cpu_seconds"] for r in runs]))
            med["spmv_cpu_speedup_internal_order"] = t_spmv_cpu / med["spmv_internal_cpu_seconds"]
        for key in ("solve", "setup") if sname != solvers[0] else ():
            med[f"{key}_ratio_vs_first"] = _median_of_ratios(raw, c["name"], prob, sname, solvers[0],
                                                             f"{key}_cpu_seconds")
            med[f"{key}_wall_ratio_vs_first"] = _median_of_ratios(raw, c["name"], prob, sname, solvers[0],
                                                                  f"{key}_seconds")
        pd["solvers"][sname] = med
    for base in ("pyamg_sa", "petsc_gamg"):
        if base in pd["solvers"]:
            pd[f"speedup_vs_{base}"] = _median_of_ratios(raw, c["name"], prob, base, solvers[0],
                                                         "total_cpu_seconds")
            pd[f"speedup_wall_vs_{base}"] = _median_of_ratios(raw, c["name"], prob, base, solvers[0],
                                                              "total_seconds")
            pd[f"setup_ratio_vs_{base}"] = _median_of_ratios(raw, c["name"], prob, solvers[0], base,
                                                             "setup_seconds")
            pd[f"setup_cpu_ratio_vs_{base}"] = _median_of_ratios(raw, c["name"], prob, solvers[0], base,
                                                                 "setup_cpu_seconds")
    return pd


def kernels_info() -> dict:
    """Which set-up path ran: numba's compiled kernels (``pip install "nestmg[fast]"``) or numpy/scipy alone
    (``--kernels numpy`` or ``NESTMG_NUMBA=0``; the plain install has no numba). Call after the runs:
    ``loaded`` says whether a kernel was compiled or loaded in this process."""
    from solvers import _kernels

    version = None
    if _kernels.AVAILABLE:
        from importlib.metadata import version as _version

        version = _version("numba")
    return {"numba": version, "enabled": bool(_kernels.ENABLED), "loaded": bool(_kernels._state["loaded"])}


def _set_kernels(choice: str) -> None:
    """``--kernels numpy``: the set-up's numpy/scipy path even when numba is installed."""
    if choice == "numpy":
        from solvers import _kernels

        _kernels.ENABLED = False


def run(args) -> dict:
    """Interleaved repeats over cases x problems x solvers; medians and within-run ratios."""
    _set_kernels(args.kernels)
    solvers = [f"nestmg_{v}" if v != "default" else "nestmg" for v in args.variants]
    solvers += ["problem_multigrid"] * args.problem_multigrid
    solvers += [f"problem_multigrid_{v}" for v in args.problem_variants if args.problem_multigrid]
    solvers += list(args.baselines)
    cases = [load_case(Path(w), args.problems if args.problem_multigrid else ()) for w in args.cases]
    raw: dict = {}
    for rep in range(args.repeats):
        for c in cases:
            for prob in args.problems:
                for sname in solvers:
                    if sname == "nestmg_boundary_layer" and prob == "dirichlet":  # Neumann boundaries only
                        continue
                    r = run_one(c, prob, sname, args.tol)
                    r["total_seconds"] = r["setup_seconds"] + r["solve_seconds"]
                    r["total_cpu_seconds"] = r["setup_cpu_seconds"] + r["solve_cpu_seconds"]
                    raw.setdefault((c["name"], prob, sname), []).append(r)
                    print(f"[{rep}] {c['name']:>14s} {prob:9s} {sname:28s} "
                          f"setup {r['setup_seconds']:.3f} solve {r['solve_seconds']:.3f} (CPU "
                          f"{r['setup_cpu_seconds']:.3f} + {r['solve_cpu_seconds']:.3f}) it {r['iterations']}",
                          flush=True)
    out = {"code": args.label, "tol": args.tol, "repeats": args.repeats,
           "omp_num_threads": os.environ.get("OMP_NUM_THREADS"), "kernels": kernels_info(),
           "solvers": solvers, "cases": []}
    for c in cases:
        cd = {k: c[k] for k in ("name", "label", "tets", "nodes", "level_tets", "n_outside", "build")}
        cd["problems"] = {prob: summarize(c, prob, solvers, raw) for prob in args.problems}
        for prob, pd in cd["problems"].items():
            ref = pd["solvers"][solvers[0]]
            print(f"{c['name']} {prob}: {solvers[0]} CPU {ref['setup_cpu_seconds']:.3f}+{ref['solve_cpu_seconds']:.3f} s "
                  f"({ref['iterations']} it, {ref['solve_spmv']:.0f} SpMV); "
                  + "; ".join(f"x{pd[k]:.2f} {k[11:]}" for k in pd if k.startswith("speedup")), flush=True)
        out["cases"].append(cd)
    return out


#: ``profile``'s set-up parts: label -> (file, function) whose cumulative CPU time under cProfile is the
#: part's
SETUP_PARTS = {
    "input checks": ("multilevel.py", "_checked_inputs"),
    "unreached coarse nodes dropped": ("transfer.py", "_drop_unreached_columns"),
    "reordering (all)": ("multilevel.py", "_reorder"),
    "  locality order": ("ordering.py", "locality_order"),
    "  fine matrix permuted + its transpose (symmetry test)": ("ordering.py", "permute_symmetric"),
    "  fine matrix permuted, symmetry probed": ("ordering.py", "permute_symmetric_transpose"),
    "  prolongations permuted": ("ordering.py", "permute_prolongation"),
    "Galerkin products (all)": ("transfer.py", "_galerkin_chain"),
    "  lower halves L + D/2": ("transfer.py", "_lower_half"),
    "  sparse products": ("transfer.py", "_one_pass_product"),
    "  compiled level (products, transposes, merge)": ("transfer.py", "_symmetric_product_compiled"),
    "operator checks": ("multilevel.py", "_check_operators"),
    "smoother set-up": ("multilevel.py", "_make_levels"),
    "coarsest factor (incl. validation solves)": ("coarse.py", "_setup"),
    "deflation probe": ("multilevel.py", "_deflate"),
    "strong-coupling solve (all)": ("multilevel.py", "_strong_block_solve"),
    "  strongly coupled unknowns found": ("subdomain.py", "strongly_coupled"),
}


def _setup_parts(stats: dict) -> dict:
    """CPU seconds of each of :data:`SETUP_PARTS` in a ``pstats.Stats.stats`` dict (cumulative, all calls)."""
    out = {}
    for label, (file, func) in SETUP_PARTS.items():
        out[label] = sum(v[3] for k, v in stats.items() if Path(k[0]).name == file and k[2] == func)
    return out


def profile(args) -> dict:
    """cProfile of ``MultigridSolver(A, P)`` set-up (the code on ``PYTHONPATH``: run it once on the base
    commit's tree and once on this one for the before/after), plus pyamg SA's set-up time in the same run;
    ``parts``: the medians over three profiled set-ups of :data:`SETUP_PARTS`."""
    import cProfile
    import pstats

    import importlib.util

    import pyamg

    from solvers import MultigridSolver

    _set_kernels(args.kernels)
    c = load_case(Path(args.case))
    out: dict = {"case": c["name"], "tets": c["tets"], "code": args.label, "profile_clock": "process_time",
                 "has_locality_ordering": importlib.util.find_spec("solvers.ordering") is not None,
                 "problems": {}}
    for prob in args.problems:
        A, b, Ps, ns = c[prob]
        t_mg, t_sa, c_mg, c_sa = [], [], [], []
        for _ in range(args.repeats):  # interleaved
            t, c0 = time.perf_counter(), time.process_time()
            MultigridSolver(A, Ps, nullspace=ns)
            t_mg.append(time.perf_counter() - t)
            c_mg.append(time.process_time() - c0)
            t, c0 = time.perf_counter(), time.process_time()
            pyamg.smoothed_aggregation_solver(A)
            t_sa.append(time.perf_counter() - t)
            c_sa.append(time.process_time() - c0)
        parts = []
        for _ in range(3):
            pr = cProfile.Profile(time.process_time)  # CPU seconds: the machine is shared
            pr.enable()
            MultigridSolver(A, Ps, nullspace=ns)
            pr.disable()
            st = pstats.Stats(pr)
            parts.append(_setup_parts(st.stats) | {"total under cProfile": st.total_tt})
        rows = sorted(((v[2], v[3], f"{Path(k[0]).name}:{k[1]}({k[2]})") for k, v in st.stats.items()),
                      reverse=True)
        out["problems"][prob] = {
            "setup_seconds_median": float(np.median(t_mg)),
            "pyamg_sa_setup_seconds_median": float(np.median(t_sa)),
            "setup_ratio_vs_sa_median": float(np.median(np.array(t_mg) / np.array(t_sa))),
            "setup_cpu_seconds_median": float(np.median(c_mg)),
            "pyamg_sa_setup_cpu_seconds_median": float(np.median(c_sa)),
            "setup_cpu_ratio_vs_sa_median": float(np.median(np.array(c_mg) / np.array(c_sa))),
            "profile_seconds": float(st.total_tt),
            "parts": {k: float(np.median([p[k] for p in parts])) for k in parts[0]},
            "top_tottime": [{"function": f, "tottime": tt, "cumtime": ct} for tt, ct, f in rows[:12]],
        }
        print("; ".join(f"{k.strip()} {v:.3f}" for k, v in out["problems"][prob]["parts"].items()))
        print(f"{prob}: setup {np.median(t_mg):.3f} s vs SA {np.median(t_sa):.3f} s (CPU ratio "
              f"{np.median(np.array(c_mg) / np.array(c_sa)):.2f}); top: "
              + ", ".join(f"{f} {tt:.3f}" for tt, _, f in rows[:5]), flush=True)
    out["kernels"] = kernels_info()
    return out


def _median_cpu(f, repeats: int) -> float:
    return float(np.median(cpu_times(f, repeats)))


def _level_parts(L, repeats: int) -> dict:
    """CPU seconds of the pieces of a forward sweep's residual shortcut on one level (medians): the split
    of the level's matrix, a product with ``A``, with ``U`` and with ``(D + L)ᵀ`` (the kept lower triangle's
    transpose, the default path), a sweep from zero on ``A`` and the substitution with ``D + L``."""
    from pyamg.relaxation import relaxation

    from solvers.smoothing import triangular_split

    A = L.A
    DL, U = triangular_split(A)
    d = A.diagonal()
    x = np.random.default_rng(0).standard_normal(A.shape[0])

    def sweep(M):
        return lambda: relaxation.gauss_seidel(M, np.zeros(A.shape[0]), x, iterations=1, sweep="forward")

    return {"rows": A.shape[0], "nnz": A.nnz,
            "split": _median_cpu(lambda: triangular_split(A), 3),
            "product_A": _median_cpu(lambda: A @ x, repeats), "product_U": _median_cpu(lambda: U @ x, repeats),
            "product_lower_transposed": _median_cpu(lambda: DL.T @ x - d * x, repeats),
            "sweep_from_zero": _median_cpu(sweep(A), repeats), "substitution": _median_cpu(sweep(DL), repeats)}


def cycle_cost(args) -> dict:
    """CPU time of one preconditioner application (a V-cycle from zero) with the pre-smoother's cheap
    residual (the default) and without it (the plain residual ``b - A x``), interleaved (median of
    ``--repeats``), and of the first application of each (what it builds on first use is in it); the pieces
    of the shortcut per smoothed level (:func:`_level_parts`, among them what splitting the level's matrix
    would cost: :func:`solvers.smoothing.triangular_split`, the path without the Galerkin products' lower
    triangles)."""
    from solvers import MultigridSolver

    out: dict = {"repeats": args.repeats, "code": args.label, "cases": []}
    for work in args.cases:
        c = load_case(Path(work))
        cd = {"name": c["name"], "label": c["label"], "tets": c["tets"], "problems": {}}
        for prob in args.problems:
            A, b, Ps, ns = c[prob]
            fast, plain = MultigridSolver(A, Ps, nullspace=ns), MultigridSolver(A, Ps, nullspace=ns)
            for L in plain.levels[:-1]:
                L.presmoother.smooth_residual = None
            Mf, Mp = fast.aspreconditioner(), plain.aspreconditioner()
            t = time.process_time()
            zf = Mf.matvec(b)
            first_fast = time.process_time() - t
            t = time.process_time()
            zp = Mp.matvec(b)
            first_plain = time.process_time() - t
            tf, tp = [], []
            for _ in range(args.repeats):
                t = time.process_time()
                Mf.matvec(b)
                tf.append(time.process_time() - t)
                t = time.process_time()
                Mp.matvec(b)
                tp.append(time.process_time() - t)
            parts = [_level_parts(L, args.repeats) for L in fast.levels[:-1]]
            cd["problems"][prob] = {
                "cycle_cpu_seconds": float(np.median(tf)), "plain_cycle_cpu_seconds": float(np.median(tp)),
                "cycle_ratio": float(np.median(np.array(tf) / np.array(tp))),
                "first_cycle_cpu_seconds": first_fast, "first_plain_cycle_cpu_seconds": first_plain,
                "split_cpu_seconds": sum(p["split"] for p in parts), "levels": parts,
                "relative_difference": float(np.linalg.norm(zf - zp) / np.linalg.norm(zp))}
            print(c["name"], prob, {k: v for k, v in cd["problems"][prob].items() if k != "levels"}, flush=True)
        out["cases"].append(cd)
    return out


def _slow_error(ml, cycles: int) -> tuple[np.ndarray, float]:
    """The error left by ``cycles`` V-cycles on ``A x = 0`` from a seeded random start (the caller's order)
    and the last cycle's reduction of its energy norm: the stationary cycle's slowest components."""
    L = ml.levels[0]
    zero = np.zeros(L.A.shape[0])
    x = np.random.default_rng(0).standard_normal(L.A.shape[0])
    factor = np.nan
    for _ in range(cycles):
        x -= x.mean() if ml.nullspace else 0.0
        before = np.sqrt(x @ (L.A @ x))
        ml._cycle(0, x, zero, "V")
        x -= x.mean() if ml.nullspace else 0.0
        factor = float(np.sqrt(x @ (L.A @ x)) / before)
    return ml._to_caller(x), factor


def _split_boundary_columns(Ps: list, rows: np.ndarray) -> list:
    """``Ps`` with every first-level coarse node that reaches a fine node of ``rows`` split in two (its
    entries in ``rows``, its entries elsewhere; the copy interpolated from the next level as the original):
    a coarse space that can move the fine boundary layer apart from the interior. Rows still sum to 1."""
    import scipy.sparse as sp

    P0 = sp.csr_matrix(Ps[0])
    mask = np.zeros(P0.shape[0], bool)
    mask[rows] = True
    inside, layer = sp.diags((~mask).astype(float)) @ P0, sp.diags(mask.astype(float)) @ P0
    cols = np.unique(sp.csr_matrix(layer).indices)
    out = [sp.csr_matrix(sp.hstack([inside, layer[:, cols]]))]
    if len(Ps) > 1:
        P1 = sp.csr_matrix(Ps[1])
        out.append(sp.csr_matrix(sp.vstack([P1, P1[cols]])))
    return out + list(Ps[2:])


def _tet_quality(V: np.ndarray, T: np.ndarray, boundary: np.ndarray) -> dict:
    """Share of tets with all four nodes on the boundary (flat caps / slivers on the surface), the share of
    those and of all tets with a dihedral angle above 150 degrees."""
    P = V[T]
    big = np.zeros(len(T), bool)
    for p, q in ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)):
        r, s = (k for k in range(4) if k not in (p, q))
        e = P[:, q] - P[:, p]
        e /= np.linalg.norm(e, axis=1)[:, None]
        u = P[:, r] - P[:, p]
        u -= (u * e).sum(1)[:, None] * e
        v = P[:, s] - P[:, p]
        v -= (v * e).sum(1)[:, None] * e
        cos = (u * v).sum(1) / (np.linalg.norm(u, axis=1) * np.linalg.norm(v, axis=1))
        big |= cos < np.cos(np.radians(150.0))
    on = np.zeros(len(V), bool)
    on[boundary] = True
    flat = on[T].all(axis=1)
    return {"all_boundary_tets": float(flat.mean()), "all_boundary_tets_over_150": float(big[flat].mean()),
            "tets_over_150": float(big.mean())}


def _node_quality(V: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Per node, the worst quality ``6 sqrt(2) V / l_max^3`` (1: regular tet, 0: flat) of its tets."""
    P = V[T]
    vol = np.abs(np.einsum("ij,ij->i", np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]), P[:, 3] - P[:, 0])) / 6
    lmax = np.max([np.linalg.norm(P[:, a] - P[:, b], axis=1)
                   for a, b in ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))], axis=0)
    q = 6 * np.sqrt(2) * vol / lmax ** 3
    worst = np.full(len(V), np.inf)
    for k in range(4):
        np.minimum.at(worst, T[:, k], q)
    return worst


def couplings_case(work: Path, problems, cycles: int) -> dict:
    """Where the default cycle without the strong-coupling solve leaves its slow error, against the
    strongly coupled unknowns (:func:`solvers.subdomain.strongly_coupled`) and the tets' shapes."""
    from nestmg import load_tet_mesh
    from solvers import MultigridSolver
    from solvers.fem import boundary_nodes
    from solvers.subdomain import STRONG_COUPLING, strongly_coupled

    c = load_case(work)
    V, T = load_tet_mesh(work / "user_mesh.vtu")
    worst = _node_quality(V, T)
    on = np.zeros(len(V), bool)
    on[boundary_nodes(T)] = True
    out = {"name": c["name"], "label": c["label"], "tets": c["tets"], "theta": STRONG_COUPLING, "problems": {}}
    for prob in problems:
        A, _b, Ps, ns = c[prob]
        ml = MultigridSolver(A, Ps, nullspace=ns, strong_blocks=None)
        e, factor = _slow_error(ml, cycles)  # the caller's order
        Au = sp_csr(A)
        energy = np.abs(e * (Au @ e))
        energy /= energy.sum()
        d = Au.diagonal()
        C = Au.tocoo()
        off = C.row != C.col
        smax = np.zeros(Au.shape[0])
        np.maximum.at(smax, C.row[off], np.abs(C.data[off]) / np.sqrt(d[C.row[off]] * d[C.col[off]]))
        region = strongly_coupled(Au)
        region = np.empty(0, int) if region is None else region
        nodes = np.arange(len(V))  # the mesh node of each unknown: all, or the interior ones (Dirichlet)
        if prob == "dirichlet":
            nodes = np.flatnonzero(~on)
        top = np.argsort(-energy)[:200]
        out["problems"][prob] = {
            "unknowns": int(Au.shape[0]), "cycles": cycles, "factor": factor,
            "max_coupling_quantiles": {q: float(np.quantile(smax, float(q))) for q in ("0.5", "0.9", "0.99")},
            "region": int(region.size), "region_energy": float(energy[region].sum()),
            "top200_energy": float(energy[top].sum()),
            "top200_boundary": float(on[nodes[top]].mean()),
            "top200_worst_quality_median": float(np.median(worst[nodes[top]])),
            "all_worst_quality_median": float(np.median(worst[nodes])),
            "top200_max_coupling_median": float(np.median(smax[top])),
        }
        print(c["name"], prob, out["problems"][prob], flush=True)
    return out


def couplings(args) -> dict:
    return {"code": args.label, "cases": [couplings_case(w, args.problems, args.cycles) for w in args.cases]}


def diagnose_case(work: Path, tol: float, cycles: int) -> dict:
    """Where the default cycle is slow on one case, and which change of the hierarchy or the cycle helps:
    see :func:`diagnose`."""
    import scipy.sparse as sp

    from nestmg import load_tet_mesh
    from solvers import MultigridSolver
    from solvers.fem import boundary_layer_nodes, boundary_nodes, stiffness_matrix

    c = load_case(work)
    V, T = load_tet_mesh(work / "user_mesh.vtu")
    bnd = boundary_nodes(T)
    ring = boundary_layer_nodes(T, 1, boundary=bnd)
    interior = np.setdiff1d(np.arange(len(V)), bnd)
    out = {"name": c["name"], "label": c["label"], "tets": c["tets"],
           "boundary_node_share": bnd.size / len(V), "quality": _tet_quality(V, T, bnd), "problems": {}}
    for prob in ("dirichlet", "neumann", "diffusion"):
        A, b, Ps, ns = c[prob]
        if prob == "dirichlet":  # unknowns: the interior nodes; the layer: the ring next to the boundary
            layer, first = np.flatnonzero(np.isin(interior, ring)), np.zeros(0, np.int64)
        else:
            layer, first = ring, bnd
        x, factor = _slow_error(MultigridSolver(A, Ps, nullspace=ns), cycles)
        w = x * x
        pd = {"unknowns": A.shape[0], "layer_share": layer.size / A.shape[0], "stationary_factor": factor,
              "slow_error_on_boundary": float(w[first].sum() / w.sum()),
              "slow_error_on_layer": float(w[layer].sum() / w.sum()), "cg": {}}
        d = A.diagonal()
        off = sp.csr_matrix(A - sp.diags(d))
        pos = np.asarray(off.maximum(0).sum(axis=1)).ravel() / d
        other = np.setdiff1d(np.arange(A.shape[0]), layer)
        pd["positive_offdiagonal_over_diagonal_median"] = {"layer": float(np.median(pos[layer])),
                                                           "other": float(np.median(pos[other]))}
        variants = {"default": (A, Ps, {}),
                    "two_grid_exact": (A, Ps[:1], {"coarse_solver": "regularized"}),
                    "six_sweeps": (A, Ps, {"presmoother": ("gauss_seidel",
                                                           {"sweep": "forward", "iterations": 6})}),
                    "layer_two_symmetric": (A, Ps, {"local_nodes": layer, "local_sweeps": 2,
                                                    "local_levels": 1}),
                    "split_layer_columns": (A, _split_boundary_columns(Ps, layer), {})}
        if prob != "dirichlet":  # the boundary nodes alone
            variants["boundary_two_symmetric"] = (A, Ps, {"local_nodes": bnd, "local_sweeps": 2,
                                                          "local_levels": 1})
        if prob == "neumann":
            on = np.zeros(len(V), bool)
            on[bnd] = True
            flat = on[T].all(axis=1)
            used = np.bincount(T[~flat].ravel(), minlength=len(V))
            flat &= ~(used[T] == 0).any(axis=1)  # keep a flat tet whose node no other tet uses
            variants["without_flat_boundary_tets"] = (sp.csr_matrix(stiffness_matrix(V, T[~flat])), Ps, {})
        for name, (Av, Pv, opts) in variants.items():
            t = time.process_time()
            ml = MultigridSolver(Av, Pv, nullspace=ns, **opts)
            setup = time.process_time() - t
            t = time.process_time()
            _, r = ml.solve(b, tol=tol, accel="cg", return_info=True)
            pd["cg"][name] = {"iterations": r["iterations"], "setup_cpu_seconds": setup,
                              "solve_cpu_seconds": time.process_time() - t,
                              "level_unknowns": [L.A.shape[0] for L in ml.levels]}
        print(c["name"], prob, json.dumps({k: v for k, v in pd.items() if k != "cg"}),
              {k: v["iterations"] for k, v in pd["cg"].items()}, flush=True)
        out["problems"][prob] = pd
    return out


def diagnose(args) -> dict:
    """Why the Neumann problems of the TetGen cases take more CG iterations than their Dirichlet problems.

    Per case and problem: the default V-cycle's stationary factor on ``A x = 0`` after ``--cycles`` cycles,
    where the error it leaves lives (the boundary nodes, the boundary layer: the nodes within one tet ring
    of the boundary; for Dirichlet the interior nodes next to it), the median positive off-diagonal sum
    over the diagonal of the layer's rows and of the others, the boundary tets' shapes, and MG-PCG
    iterations of the default against: a two-grid cycle with an exact first coarse level (is it the coarse
    levels?), six sweeps on every level (the smoother?), two extra symmetric sweeps on the layer (the
    smoother at the boundary?) and on the boundary nodes alone, the first coarse nodes that reach the layer
    split in two (the coarse space at the boundary?), and, Neumann only, the matrix without the tets whose
    four nodes are on the boundary (the flat surface tets?). One run each (iterations, not times, are the
    point)."""
    return {"tol": args.tol, "cycles": args.cycles,
            "cases": [diagnose_case(Path(w), args.tol, args.cycles) for w in args.cases]}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    b = sub.add_parser("build", help="make one case: user mesh file + saved hierarchy")
    b.add_argument("surface", type=Path)
    b.add_argument("--mesher", choices=("tetgen", "tetwild"), default="tetgen", help="the user's mesher")
    b.add_argument("--coarse-mesher", choices=("tetgen", "tetwild"), default="tetgen")
    b.add_argument("--fine-tets", type=int, default=1_000_000)
    b.add_argument("--levels", type=int, default=4)
    b.add_argument("--refine", type=int, default=0,
                   help="red-refine the mesher's output this many times (mesher target: fine-tets / 8^n)")
    b.add_argument("--work", type=Path, required=True)
    r = sub.add_parser("run", help="compare the solvers on built cases")
    r.add_argument("cases", nargs="+", type=Path)
    r.add_argument("--problems", nargs="+", default=["dirichlet", "neumann"],
                   choices=("dirichlet", "neumann", "diffusion"))
    r.add_argument("--variants", nargs="+", default=["default"], choices=sorted(VARIANTS),
                   help="nestmg cycles; the first one is the reference of the ratios")
    r.add_argument("--baselines", nargs="*", default=["pyamg_sa", "petsc_gamg"],
                   choices=("pyamg_sa", "petsc_gamg"))
    r.add_argument("--problem-multigrid", action="store_true",
                   help="also nestmg.setup_problem(...).multigrid() (the pipeline's default cycle) on the "
                        "same matrix and right-hand side")
    r.add_argument("--problem-variants", nargs="*", default=[], choices=sorted(VARIANTS),
                   help="with --problem-multigrid: also Problem.multigrid(**VARIANTS[v]) for these variants")
    r.add_argument("--repeats", type=int, default=3)
    r.add_argument("--tol", type=float, default=1e-8)
    r.add_argument("--label", default="this tree", help="what code is on PYTHONPATH (recorded in the JSON)")
    r.add_argument("--kernels", choices=("auto", "numpy"), default="auto",
                   help="set-up path: numba's kernels when installed (auto) or numpy/scipy alone")
    r.add_argument("--json", type=Path, default=None)
    pr = sub.add_parser("profile", help="cProfile of the MultigridSolver set-up on one case")
    pr.add_argument("case", type=Path)
    pr.add_argument("--problems", nargs="+", default=["dirichlet", "neumann"],
                    choices=("dirichlet", "neumann", "diffusion"))
    pr.add_argument("--repeats", type=int, default=3)
    pr.add_argument("--label", default="this tree", help="what code is on PYTHONPATH (recorded in the JSON)")
    pr.add_argument("--kernels", choices=("auto", "numpy"), default="auto",
                    help="set-up path: numba's kernels when installed (auto) or numpy/scipy alone")
    pr.add_argument("--json", type=Path, default=None)
    cc = sub.add_parser("cycle",
                        help="one V-cycle's CPU time with and without the cheap pre-smoother residual")
    cc.add_argument("cases", nargs="+", type=Path)
    cc.add_argument("--problems", nargs="+", default=["dirichlet", "neumann"],
                    choices=("dirichlet", "neumann", "diffusion"))
    cc.add_argument("--repeats", type=int, default=15)
    cc.add_argument("--label", default=None, help="code label stored in the JSON (e.g. the commit)")
    cc.add_argument("--json", type=Path, default=None)
    dg = sub.add_parser("diagnose", help="where the default cycle is slow and what helps (one run each)")
    dg.add_argument("cases", nargs="+", type=Path)
    dg.add_argument("--cycles", type=int, default=25)
    dg.add_argument("--tol", type=float, default=1e-8)
    dg.add_argument("--json", type=Path, default=None)
    cp = sub.add_parser("couplings", help="the default cycle's slow error against the strongly coupled "
                        "unknowns and the tets' shapes (one run each)")
    cp.add_argument("cases", nargs="+", type=Path)
    cp.add_argument("--problems", nargs="+", default=["dirichlet", "neumann"],
                    choices=("dirichlet", "neumann", "diffusion"))
    cp.add_argument("--cycles", type=int, default=3)
    cp.add_argument("--label", default=None, help="code label stored in the JSON (e.g. the commit)")
    cp.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    if args.cmd == "build":
        return build(args)
    out = {"profile": profile, "cycle": cycle_cost, "run": run, "diagnose": diagnose,
           "couplings": couplings}[args.cmd](args)
    if args.json:
        from nestmg.io import json_default

        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=1, default=json_default))
    if args.cmd == "run" and "petsc_gamg" in args.baselines:
        os._exit(0)  # Debian's PETSc 3.18 may segfault at interpreter exit after correct solves
    return out


if __name__ == "__main__":
    main()
