"""Which cycle the pipeline's problems should run under MG-PCG (issue 31 item 2): ``Problem.multigrid()``
(the robust smoothing: symmetric Gauss–Seidel, ``2 nu`` sweeps below the finest, boundary-layer sweeps on
Neumann problems, coarse-level deflation probes) against the bare constructor's default cycle
(``MultigridSolver(A, P)`` on the same operators: two forward / backward Gauss–Seidel sweeps, one on dense
coarse levels, no probe) and ``smoothing="fast"``.

For each mesh: the default hierarchy (``build_hierarchy(V, F, levels=3)``, cached), then for the three model
problems each variant set up and run by MG-PCG to 1e-8 (CPU seconds, iterations; alternating, twice each)
and as a stationary cycle (its factor, ``solvers.convergence_factor``, 40 cycles at most).

    OMP_NUM_THREADS=1 python benchmarks/archive/cg_default_cycle.py ZOO_DIR/homer.obj --out FILE.json
"""

from __future__ import annotations

import sys
from pathlib import Path

from nestmg import SolverOptions
from solvers import MultigridSolver

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from exp_common import mesh_study_main, model_problems, timed_pcg  # noqa: E402


def variants(pr) -> dict:
    """Solver factories of the compared cycles for one problem."""
    return {
        "problem_multigrid": lambda: pr.multigrid(),
        "constructor": lambda: MultigridSolver(pr.A, pr.P, coarse=pr.coarse, nullspace=pr.nullspace),
        "fast": lambda: pr.multigrid(SolverOptions(smoothing="fast")),
        # the constructor's cycle plus the boundary layer's one-way sweeps on the fine level (natural
        # boundaries only: Problem.local_nodes is None on Dirichlet problems)
        "constructor_layer": lambda: MultigridSolver(pr.A, pr.P, coarse=pr.coarse, nullspace=pr.nullspace,
                                                     local_nodes=pr.local_nodes, local_sweep="one-way",
                                                     local_levels=1),
        "constructor_layer_sym": lambda: MultigridSolver(pr.A, pr.P, coarse=pr.coarse, nullspace=pr.nullspace,
                                                         local_nodes=pr.local_nodes, local_levels=1),
    }


def measure(mesh: Path) -> dict:
    """CG set-up / solve CPU seconds, iterations and the stationary factor of every variant on one mesh."""
    out, problems = model_problems(mesh)
    for name, pr in problems:
        make = variants(pr)
        for rep in range(2):
            for v, f in make.items():
                ml, setup, solve, info = timed_pcg(f, pr.b)
                row = {"problem": name, "variant": v, "setup": setup, "solve": solve, "it": info["iterations"],
                       "cycle_complexity": ml.cycle_complexity()}
                if rep == 0:
                    st = ml.solve(pr.b, tol=1e-8, maxiter=40, accel=None, return_info=True)[1]
                    row["stationary_factor"] = st["factor"]
                    row["stationary_cycles"] = st["iterations"]
                out["rows"].append(row)
    return out


def main(argv=None) -> None:
    mesh_study_main("benchmarks/archive/cg_default_cycle.py", __doc__.splitlines()[0], measure, argv)


if __name__ == "__main__":
    main()
