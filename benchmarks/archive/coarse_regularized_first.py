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

import sys
from pathlib import Path

from nestmg import build_hierarchy, load_mesh, setup_problem

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from exp_common import mesh_study_main, timed_pcg  # noqa: E402


def measure(mesh: Path) -> dict:
    V, F = load_mesh(mesh)[:2]
    H = build_hierarchy(V, F, levels=3, progress=False)
    rows = []
    for name in ("poisson-dirichlet", "poisson-neumann"):
        pr = setup_problem(H.tets, H.P, name)
        for cs in ("auto", "regularized", "auto", "regularized"):
            ml, setup, pcg, info = timed_pcg(lambda cs=cs: pr.multigrid(coarse_solver=cs), pr.b)
            res: list = []
            ml.solve(pr.b, tol=1e-8, residuals=res)
            rows.append({"mesh": mesh.name, "problem": name, "coarse_solver": cs, "used": ml._coarse_solver.method,
                         "coarse_n": int(ml.levels[-1].A.shape[0]), "coarse_nullity": int(ml.coarse_nullity),
                         "setup": setup, "pcg": pcg, "pcg_iterations": info["iterations"],
                         "stationary_cycles": len(res) - 1})
    return {"mesh": mesh.name, "rows": rows}


def main(argv=None) -> None:
    mesh_study_main("benchmarks/archive/coarse_regularized_first.py", __doc__.splitlines()[0], measure, argv)


if __name__ == "__main__":
    main()
