"""``PetscMultigrid(A, P)`` against ``MultigridSolver(A, P)`` on a 1M-tet pipeline hierarchy (issue 15, item 4).

    OPENBLAS_NUM_THREADS=1 taskset -c 0 python benchmarks/petsc_scale.py ZOO_DIR/gargo.off \
        --edge-length 0.0065 --out benchmarks/results/petsc

The hierarchy is the reuse benchmarks' one (``exp_common.cached_hierarchy``: TetWild, refined fine level,
one nested cage; cached). For Dirichlet and Neumann Poisson (``setup_problem``, Galerkin), both solvers get
the same matrix and prolongations and the same cycle (one symmetric Gauss–Seidel sweep before and after on
every level = PCMG's default ``smoother="sor"``, local-symmetric SOR) under CG to 1e-8, one rank. PETSc is initialised once
before timing (its first solver in a process pays ~0.4 s of start-up). Each setup + solve is repeated
``--repeat`` times, interleaved; the JSON keeps every time and the best. Prints JSON, writes
``petsc_scale_<mesh>.json`` and ``.png``.
"""

from __future__ import annotations

import argparse
import json
import time
import warnings
from pathlib import Path

import numpy as np

from nestmg import SolverOptions

#: one symmetric Gauss–Seidel sweep per smoothing step: what PetscMultigrid(smoother="sor") runs
SGS = ("gauss_seidel", {"sweep": "symmetric", "iterations": 1})


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("mesh", type=Path)
    ap.add_argument("--edge-length", type=float, required=True, help="fine edge / diagonal (exp_common.cached_hierarchy)")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", type=Path, default=Path("bench_out/petsc"))
    args = ap.parse_args(argv)

    from exp_common import cached_hierarchy

    from nestmg.io import json_default
    from nestmg.problems import setup_problem
    from solvers.petsc import PetscMultigrid

    h, t_h = cached_hierarchy(args.mesh, edge_length=args.edge_length)
    doc: dict = {"benchmark": "petsc_scale", "mesh": args.mesh.name, "edge_length": args.edge_length,
                 "tets": [len(T) for _, T in h.tets], "hierarchy_load_seconds": t_h, "runs": []}
    for name in ("poisson-dirichlet", "poisson-neumann"):
        pr = setup_problem(h.tets, h.P, name)
        PetscMultigrid(pr.A, pr.P, nullspace=pr.nullspace).destroy()  # PETSc start-up, not timed
        rec: dict = {"problem": name, "unknowns": int(pr.A.shape[0]),
                     "inprocess": {"setup": [], "solve": [], "iterations": None},
                     "petsc": {"setup": [], "solve": [], "iterations": None}}
        for _ in range(args.repeat):
            t = time.perf_counter()
            ml = pr.multigrid(SolverOptions(local=False), presmoother=SGS)  # PCMG's SOR: symmetric sweeps
            rec["inprocess"]["setup"].append(time.perf_counter() - t)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                t = time.perf_counter()
                x1, i1 = ml.solve(pr.b, tol=1e-8, accel="cg", return_info=True)
                rec["inprocess"]["solve"].append(time.perf_counter() - t)
            t = time.perf_counter()
            pm = PetscMultigrid(pr.A, pr.P, nullspace=pr.nullspace)
            rec["petsc"]["setup"].append(time.perf_counter() - t)
            t = time.perf_counter()
            x2, i2 = pm.solve(pr.b, tol=1e-8)
            rec["petsc"]["solve"].append(time.perf_counter() - t)
            pm.destroy()
            rec["inprocess"]["iterations"], rec["petsc"]["iterations"] = i1["iterations"], i2["iterations"]
            rec["petsc"]["final_residual"] = i2["final_residual"]
            rec["solution_rel_diff"] = float(np.linalg.norm(x1 - x2) / np.linalg.norm(x1))
        for k in ("inprocess", "petsc"):
            rec[k]["best_setup"] = min(rec[k]["setup"])
            rec[k]["best_solve"] = min(rec[k]["solve"])
        rec["setup_ratio_best"] = rec["petsc"]["best_setup"] / rec["inprocess"]["best_setup"]
        rec["setup_ratio_all"] = [p / q for p, q in zip(rec["petsc"]["setup"], rec["inprocess"]["setup"])]
        doc["runs"].append(rec)
        print(f"{name}: setup in-process {rec['inprocess']['best_setup']:.3f} s, PETSc {rec['petsc']['best_setup']:.3f} s "
              f"({rec['setup_ratio_best']:.2f}x); solve {rec['inprocess']['best_solve']:.3f} / "
              f"{rec['petsc']['best_solve']:.3f} s; CG iterations {i1['iterations']} / {i2['iterations']}", flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    stem = args.out / f"petsc_scale_{args.mesh.stem}"
    stem.with_suffix(".json").write_text(json.dumps(doc, indent=1, default=json_default))
    _plot(doc, stem.with_suffix(".png"))
    print(json.dumps({"written": str(stem.with_suffix(".json"))}))
    return 0


def _plot(doc: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.2))
    labels, setup, solve = [], [], []
    for r in doc["runs"]:
        for k in ("inprocess", "petsc"):
            labels.append(f"{r['problem'].split('-')[1]}\n{k}")
            setup.append(r[k]["best_setup"])
            solve.append(r[k]["best_solve"])
    x = np.arange(len(labels))
    ax.bar(x, setup, label="setup")
    ax.bar(x, solve, bottom=setup, label="CG solve")
    ax.set_xticks(x, labels, fontsize=8)
    ax.set_ylabel("wall s (best of repeats)")
    ax.set_title(f"{doc['mesh']}: {doc['tets'][0]:,} fine tets, 1 rank")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
