"""The pipeline's scalar problems with coarse_solver="auto" against "regularized" on the default hierarchies
of zoo meshes whose coarsest Galerkin level is singular (coarse nodes whose restricted prolongation columns
are linearly dependent). Before the guard (coarse.GUARD_MIN) "auto" ended there at the dense pivoted
Cholesky (PIVOTED_MAX); the regularised SuperLU is exact on the range up to 1e-9 diag / lambda
(benchmarks/results/setup_cost/coarse_guard_before.json, coarse_guard_after.json).

    OMP_NUM_THREADS=1 python benchmarks/archive/coarse_regularized_first.py ZOO_DIR/homer.obj ZOO_DIR/bunny.off \
        --out FILE.json

Per mesh, problem and solver (alternating, twice): set-up CPU seconds, MG-PCG CPU seconds and iterations to
1e-8, stationary cycles to 1e-8, the coarse solver used.
"""

from __future__ import annotations

import argparse
import json
import time
import warnings
from pathlib import Path

from nestmg import build_hierarchy, load_mesh, setup_problem


def measure(mesh: Path) -> list[dict]:
    V, F = load_mesh(mesh)[:2]
    H = build_hierarchy(V, F, levels=3, progress=False)
    rows = []
    for name in ("poisson-dirichlet", "poisson-neumann"):
        pr = setup_problem(H.tets, H.P, name)
        for cs in ("auto", "regularized", "auto", "regularized"):
            t = time.process_time()
            ml = pr.multigrid(coarse_solver=cs)
            setup = time.process_time() - t
            t = time.process_time()
            _, info = ml.solve(pr.b, tol=1e-8, accel="cg", return_info=True)
            pcg = time.process_time() - t
            res: list = []
            ml.solve(pr.b, tol=1e-8, residuals=res)
            rows.append({"mesh": mesh.name, "problem": name, "coarse_solver": cs, "used": ml._coarse_solver.method,
                         "coarse_n": int(ml.levels[-1].A.shape[0]), "coarse_nullity": int(ml.coarse_nullity),
                         "setup": setup, "pcg": pcg, "pcg_iterations": info["iterations"],
                         "stationary_cycles": len(res) - 1})
    return rows


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("meshes", nargs="+", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    rows = [r for m in args.meshes for r in measure(m)]
    args.out.write_text(json.dumps({"command": "benchmarks/archive/coarse_regularized_first.py", "clock": "process_time",
                                    "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
