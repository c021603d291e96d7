"""Which cycle the pipeline's problems should run under MG-PCG (issue 31 item 2, one default).

Since the pipeline and the bare constructor share one default cycle, ``Problem.multigrid()`` is
``MultigridSolver(A, P)``'s default (two forward / backward Gauss–Seidel sweeps on the fine level, four on
coarse levels as sparse as the finest, one on dense ones) plus the problem's boundary-layer sweeps, factor goal
and finest-level probe for stationary cycling. Compared here with the two defaults it replaced, spelled out:
the pipeline's former cycle (symmetric Gauss–Seidel once on the fine level, twice below, the same layer
sweeps, every level probed) and the constructor's former one (two sweeps on sparse coarse levels).
(The run at 9043a15, ``cg_default_cycle_9043a15.json``, compared the former ``Problem.multigrid()`` with the
constructor, ``smoothing="fast"`` and the constructor with one-way or symmetric layer sweeps.)

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
from solvers.multilevel import DEFAULT_SMOOTHER

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from exp_common import mesh_study_main, model_problems, timed_pcg  # noqa: E402

#: the pipeline's cycle before the one default: symmetric Gauss-Seidel, once on the fine level, twice below
FORMER_PIPELINE = SolverOptions(smoother="symmetric_gauss_seidel", nu=1)


def variants(pr) -> dict:
    """Solver factories of the compared cycles for one problem."""
    return {
        "problem_multigrid": lambda: pr.multigrid(),
        "constructor": lambda: MultigridSolver(pr.A, pr.P, coarse=pr.coarse, nullspace=pr.nullspace),
        # every level probed with 8 modes, whatever the operator complexity (the former pipeline default)
        "former_problem_multigrid": lambda: pr.multigrid(FORMER_PIPELINE, deflate=8),
        # two sweeps on every smoothed level (these 3-level hierarchies have one coarse smoothed level, sparse)
        "former_constructor": lambda: MultigridSolver(pr.A, pr.P, coarse=pr.coarse, nullspace=pr.nullspace,
                                                      presmoother=[DEFAULT_SMOOTHER, DEFAULT_SMOOTHER]),
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
