"""PETSc backend benchmark: PCMG with nestmg's nested prolongations vs GAMG vs hypre vs the in-process solver.

Dirichlet P1 Poisson on the unit cube, Kuhn tets with ``n`` cells per side (n=56: 1,053,696 tets,
166,375 interior unknowns), exactly nested hierarchy halving ``n`` per level, random right-hand side,
CG to a relative residual of 1e-8. The script runs the in-process :class:`solvers.MultigridSolver`
(and pyamg SA) itself, then launches itself under ``mpirun -n R`` for every ``R`` in ``--ranks`` (each
rank builds the same global problem and copies its rows into PETSc). Prints one JSON object and saves
a PNG bar chart of setup and solve times. Run from the repository root:

    PYTHONPATH=. python benchmarks/petsc.py [--n 56] [--levels 4] [--ranks 1 2] [--repeat 3] \\
        [--out benchmarks/petsc.png]
    # or a hierarchy from the nestmg pipeline (cages -> tets -> prolongations) of a surface mesh:
    PYTHONPATH=. python benchmarks/petsc.py --mesh ZOO_DIR/gargo.off --levels 3 \\
        [--method nested] [--mesher tetgen] [--edge-fac 0.006] [--save STEM]
    # later runs can reuse it: --load STEM

The parent process builds the hierarchy once and writes it with :func:`solvers.petsc.save_operators`;
every MPI rank reads it with ``load_operators`` (the pattern docs/petsc.md recommends on a cluster).

Timings are wall-clock: setup = copying the scipy matrices into PETSc + KSPSetUp (Galerkin products,
AMG coarsening, coarse factorisation); solve = best of ``--repeat`` KSPSolve calls (max over ranks).
On a 2-core machine ``-n 2`` uses both cores; other jobs on the machine inflate the numbers
(``loadavg`` is recorded).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

import numpy as np
import scipy.sparse as sp

from solvers.fem import boundary_nodes, stiffness_matrix
from solvers.gallery import kuhn_cube_hierarchy
from solvers.multilevel import restrict_prolongations
from nestmg import MeshingOptions, SizingOptions


def kuhn_dirichlet(n: int, levels: int, seed: int = 0) -> dict:
    """Interior-node Poisson system on the Kuhn cube, Galerkin-ready and re-discretised hierarchies."""
    meshes, Ps = kuhn_cube_hierarchy(n, levels)
    V, T = meshes[0]
    free = np.setdiff1d(np.arange(len(V)), boundary_nodes(T))
    A = sp.csr_matrix(stiffness_matrix(V, T)[free][:, free])
    Pg, _ = restrict_prolongations(Ps, free)
    interiors = [np.setdiff1d(np.arange(len(Vk)), boundary_nodes(Tk)) for Vk, Tk in meshes[1:]]
    Pi, frees = restrict_prolongations(Ps, free, coarse_free=interiors)
    coarse = [sp.csr_matrix(stiffness_matrix(Vk, Tk)[f][:, f]) for (Vk, Tk), f in zip(meshes[1:], frees[1:])]
    b = np.random.default_rng(seed).standard_normal(A.shape[0])
    return {"A": A, "Ps": Pg, "Ps_int": Pi, "coarse": coarse, "b": b, "tets": int(T.shape[0]),
            "label": f"Kuhn cube n={n}"}


def pipeline_dirichlet(path: str, levels: int, method: str, mesher: str, edge_fac: float | None) -> dict:
    """Dirichlet Poisson on a nestmg hierarchy (cages, tet layers, prolongations) of a surface mesh."""
    from nestmg.hierarchy import build_hierarchy
    from nestmg.io import load_mesh
    from nestmg.problems import setup_problem

    V, F = load_mesh(path)
    h = build_hierarchy(V, F, levels, method, sizing=SizingOptions(edge_length=edge_fac),
                        meshing=MeshingOptions(mesher=mesher), progress=False)
    gal = setup_problem(h.tets, h.P, "poisson-dirichlet", coarse="galerkin")
    red = setup_problem(h.tets, h.P, "poisson-dirichlet", coarse="rediscretized")
    return {"A": gal.A, "Ps": gal.P, "Ps_int": red.P, "coarse": red.coarse, "b": gal.b,
            "tets": int(h.tets[0][1].shape[0]), "label": f"{os.path.basename(path)} ({method} cages, {mesher})",
            "n_outside": [int(r.n_outside) for r in h.prolongation_reports]}


def _keep(info: dict) -> dict:
    keys = ("iterations", "converged", "final_residual", "factor", "setup_seconds", "solve_seconds",
            "rows_per_rank", "ghosts_per_rank")
    return {k: info[k] for k in keys if k in info}


def worker(args) -> None:
    """One mpirun job: every solver on the same matrices; rank 0 prints the JSON line."""
    import petsc4py

    petsc4py.init([sys.argv[0]])
    from petsc4py import PETSc

    from solvers.petsc import PetscMultigrid, load_operators, petsc_amg_solve

    comm = PETSc.COMM_WORLD
    t0 = time.perf_counter()
    gal, red = load_operators(args.worker + "_galerkin.npz"), load_operators(args.worker + "_rediscretized.npz")
    prob = {"A": gal["A"], "b": gal["b"], "Ps": gal["Ps"], "Ps_int": red["Ps"], "coarse": red["coarse"]}
    load = time.perf_counter() - t0
    A, b = prob["A"], prob["b"]
    res: dict = {"ranks": comm.getSize(), "load_seconds": load, "solvers": {}}

    def pcmg(name, Ps, reps, **kw):
        with PetscMultigrid(A, Ps, **kw) as mg:
            best = None
            for _ in range(reps):
                _, info = mg.solve(b, tol=1e-8, maxiter=200)
                if best is None or info["solve_seconds"] < best["solve_seconds"]:
                    best = info
            best["nnz"] = [L["nnz"] for L in mg.levels]
            res["solvers"][name] = _keep(best) | {"nnz": best["nnz"], "partition": mg.partition}

    pcmg("pcmg_galerkin", prob["Ps"], args.repeat)
    pcmg("pcmg_rediscretized", prob["Ps_int"], args.repeat, coarse=prob["coarse"])
    pcmg("pcmg_stationary", prob["Ps"], 1, krylov="richardson")
    if comm.getSize() > 1:  # the default partition is PT-Scotch on several ranks; compare with rows in order
        pcmg("pcmg_natural_partition", prob["Ps"], args.repeat, partition="natural")
    for kind in ("gamg", "hypre"):
        best = None
        for _ in range(args.repeat):
            _, info = petsc_amg_solve(A, b, kind, tol=1e-8, maxiter=500)
            if best is None or info["setup_seconds"] + info["solve_seconds"] < (
                    best["setup_seconds"] + best["solve_seconds"]):
                best = info
        res["solvers"][kind] = _keep(best)
    if comm.getRank() == 0:
        print(json.dumps(res), flush=True)


def inprocess(prob: dict, repeat: int) -> dict:
    """nestmg's own MultigridSolver (Galerkin, V(1,1) symmetric GS, CG) and pyamg SA, one core."""
    from solvers.baselines import pyamg_sa
    from solvers.multilevel import MultigridSolver

    out = {}
    for name, kw, Ps in (("inprocess_galerkin", {}, prob["Ps"]),
                         ("inprocess_rediscretized", {"coarse": prob["coarse"]}, prob["Ps_int"])):
        t0 = time.perf_counter()
        ml = MultigridSolver(prob["A"], Ps, **kw)
        setup = time.perf_counter() - t0
        best = None
        for _ in range(repeat):
            x, info = ml.solve(prob["b"], tol=1e-8, maxiter=200, accel="cg", return_info=True)
            if best is None or info["seconds"] < best["seconds"]:
                best = info
        r = np.linalg.norm(prob["b"] - prob["A"] @ x) / np.linalg.norm(prob["b"])
        out[name] = {"iterations": best["iterations"], "converged": best["converged"], "final_residual": float(r),
                     "setup_seconds": setup, "solve_seconds": best["seconds"]}
    ml = MultigridSolver(prob["A"], prob["Ps"])
    _, st = ml.solve(prob["b"], tol=1e-8, maxiter=200, return_info=True)
    out["inprocess_stationary"] = {"iterations": st["iterations"], "factor": st["factor"],
                                   "solve_seconds": st["seconds"], "converged": st["converged"]}
    r = pyamg_sa(prob["A"], prob["b"], tol=1e-8)
    out["pyamg_sa"] = {"iterations": r.iterations, "converged": r.converged, "setup_seconds": r.setup_seconds,
                       "solve_seconds": r.solve_seconds}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=56)
    ap.add_argument("--levels", type=int, default=4)
    ap.add_argument("--ranks", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", default="benchmarks/petsc.png")
    ap.add_argument("--mesh", help="surface mesh: build the hierarchy with nestmg.build_hierarchy instead")
    ap.add_argument("--method", default="nested", help="cage backend for --mesh")
    ap.add_argument("--mesher", default="tetgen", help="tet mesher for --mesh (tetgen or tetwild)")
    ap.add_argument("--edge-fac", type=float, default=None, help="fine edge length / bbox diagonal for --mesh")
    ap.add_argument("--save", metavar="STEM", help="keep the hierarchy in STEM_galerkin.npz / STEM_rediscretized.npz")
    ap.add_argument("--load", metavar="STEM", help="reuse a hierarchy kept with --save (skips building it)")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        worker(args)
        return

    import tempfile

    from solvers.petsc import load_operators, save_operators

    load0 = os.getloadavg()
    t0 = time.perf_counter()
    if args.load:
        gal, red = load_operators(args.load + "_galerkin.npz"), load_operators(args.load + "_rediscretized.npz")
        prob = {"A": gal["A"], "Ps": gal["Ps"], "b": gal["b"], "Ps_int": red["Ps"], "coarse": red["coarse"],
                "tets": int(gal["tets"]), "label": str(gal["label"])}
        prob["n_outside"] = gal["n_outside"].tolist() if "n_outside" in gal else None
    elif args.mesh:
        prob = pipeline_dirichlet(args.mesh, args.levels, args.method, args.mesher, args.edge_fac)
    else:
        prob = kuhn_dirichlet(args.n, args.levels)
    args.levels = len(prob["Ps"]) + 1
    out = {"problem": {"label": prob["label"], "levels": args.levels, "tets": prob["tets"],
                       "unknowns": int(prob["A"].shape[0]), "nnz": int(prob["A"].nnz),
                       "coarse_unknowns": [int(P.shape[1]) for P in prob["Ps"]],
                       "n_outside": prob.get("n_outside"), "build_seconds": time.perf_counter() - t0},
           "inprocess": inprocess(prob, args.repeat), "petsc": {}}
    tmp = tempfile.TemporaryDirectory()
    stem = args.save or os.path.join(tmp.name, "h")
    extra = {"tets": np.array(prob["tets"]), "label": np.array(prob["label"])}
    if prob.get("n_outside") is not None:
        extra["n_outside"] = np.array(prob["n_outside"])
    save_operators(stem + "_galerkin.npz", prob["A"], prob["Ps"], b=prob["b"], **extra)
    save_operators(stem + "_rediscretized.npz", prob["A"], prob["Ps_int"], coarse=prob["coarse"], b=prob["b"])
    env = dict(os.environ, OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1", OMP_NUM_THREADS="1",
               OPENBLAS_NUM_THREADS="1")
    env["PYTHONPATH"] = os.pathsep.join([os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                                         env.get("PYTHONPATH", "")])
    for r in args.ranks:
        cmd = ["mpirun", "-n", str(r), sys.executable, os.path.abspath(__file__), "--worker", stem,
               "--repeat", str(args.repeat)]
        proc = subprocess.run(cmd, check=False, capture_output=True, text=True, env=env)
        lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("{")]
        if proc.returncode != 0 or not lines:
            raise SystemExit(f"mpirun -n {r} failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
        out["petsc"][str(r)] = json.loads(lines[-1])
    out["loadavg"] = {"before": load0, "after": os.getloadavg()}

    # ratios against the in-process geometric multigrid (setup + solve)
    ref = out["inprocess"]["inprocess_galerkin"]
    ref_total = ref["setup_seconds"] + ref["solve_seconds"]
    ratios = {}
    for r, res in out["petsc"].items():
        for name, s in res["solvers"].items():
            if "setup_seconds" in s:
                ratios[f"{name}@{r}"] = {
                    "solve_vs_inprocess": s["solve_seconds"] / ref["solve_seconds"],
                    "total_vs_inprocess": (s["setup_seconds"] + s["solve_seconds"]) / ref_total,
                }
    out["ratios"] = ratios
    plot(out, args.out)
    print(json.dumps(out, indent=2, default=float))


def plot(out: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels, setup, solve, its = [], [], [], []
    for name in ("inprocess_galerkin", "pyamg_sa"):
        s = out["inprocess"][name]
        labels.append(f"{name}\n(1 core)")
        setup.append(s["setup_seconds"])
        solve.append(s["solve_seconds"])
        its.append(s["iterations"])
    for r, res in out["petsc"].items():
        for name in ("pcmg_galerkin", "pcmg_rediscretized", "pcmg_natural_partition", "gamg", "hypre"):
            if name in res["solvers"]:
                s = res["solvers"][name]
                labels.append(f"{name}\n({r} rank{'s' if r != '1' else ''})")
                setup.append(s["setup_seconds"])
                solve.append(s["solve_seconds"])
                its.append(s["iterations"])
    x = np.arange(len(labels))
    fig, ax = plt.subplots(figsize=(max(8, 0.9 * len(labels)), 4.5))
    ax.bar(x, setup, label="setup", color="#9ecae1")
    ax.bar(x, solve, bottom=setup, label="solve (CG to 1e-8)", color="#3182bd")
    for xi, s0, s1, it in zip(x, setup, solve, its):
        ax.text(xi, s0 + s1, f"{it} it", ha="center", va="bottom", fontsize=8)
    ax.set_xticks(x, labels, rotation=60, ha="right", fontsize=7)
    ax.set_ylabel("seconds (wall)")
    p = out["problem"]
    ax.set_title(f"{p['label']}: Dirichlet Poisson, {p['tets']:,} tets, {p['unknowns']:,} unknowns, "
                 f"{p['levels']} levels", fontsize=10)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)


if __name__ == "__main__":
    main()
