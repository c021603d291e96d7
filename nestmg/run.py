"""One call from a hierarchy to a measured multigrid solve (used by the CLI and the benchmarks)."""

from __future__ import annotations

import time
import warnings
from typing import Any

import numpy as np

from solvers import DivergenceError, MultigridSolver, convergence_factor

from .options import SolverOptions, typed
from .problems import setup_problem

__all__ = ["measure_cycle_cost", "solve_on_hierarchy"]


def measure_cycle_cost(ml: MultigridSolver, cycle: str = "V", repeats: int = 5) -> dict[str, float]:
    """Wall-clock cost of one cycle in units of one fine SpMV, beside the counted (flop) complexity.

    Returns
    -------
    dict
        ``spmv_seconds``, ``cycle_seconds``, ``measured_spmv_units`` (cycle / SpMV time) and
        ``counted_spmv_units`` (:meth:`MultigridSolver.cycle_complexity`).
    """
    A = ml.levels[0].A
    x = np.random.default_rng(0).standard_normal(A.shape[0])
    M = ml.aspreconditioner(cycle)
    M.matvec(x)  # warm-up
    n_spmv = max(20, repeats * 20)
    t0 = time.perf_counter()
    for _ in range(n_spmv):
        A @ x
    t_spmv = (time.perf_counter() - t0) / n_spmv
    t0 = time.perf_counter()
    for _ in range(repeats):
        M.matvec(x)
    t_cyc = (time.perf_counter() - t0) / repeats
    return {
        "spmv_seconds": t_spmv,
        "cycle_seconds": t_cyc,
        "measured_spmv_units": t_cyc / t_spmv,
        "counted_spmv_units": ml.cycle_complexity(cycle),
    }


def solve_on_hierarchy(
    tets: list,
    P: list,
    problem: str = "poisson-dirichlet",
    options: SolverOptions | None = None,
    *,
    cost: bool = True,
    return_solution: bool = False,
    fractions: list | None = None,
    element: str = "P1",
    curved=None,
) -> dict[str, Any]:
    """Assemble ``problem`` on ``tets[0]``, build the multigrid solver from ``P`` and solve.

    Divergence is a *result* here (the naive hierarchy with re-discretised operators is expected to
    diverge): it is returned as ``diverged=True`` with the message and the residuals so far.

    Parameters
    ----------
    tets, P
        ``Hierarchy.tets`` and ``Hierarchy.P``.
    problem : str
        See :func:`nestmg.problems.setup_problem`.
    options : SolverOptions, optional
        Coarse operators, ``lam``, ``poisson_ratio`` (the problem); smoothing (``smoothing`` preset, or
        ``nu`` sweeps of ``smoother`` on the fine level and ``coarse_nu`` -- default ``2 * nu`` -- on the
        coarser ones, plus boundary-layer sweeps with ``local``; :meth:`nestmg.problems.Problem.multigrid`);
        ``coarse_scaling``; ``cycle``, ``accel``, ``tol``, ``maxiter``
        (:meth:`solvers.MultigridSolver.solve`). ``nu`` and ``cycle`` not set follow the problem
        (:meth:`nestmg.SolverOptions.resolved`: the V-cycle; ``nu = 2`` for a W-cycle on elasticity at
        ν >= 0.4);
        the report gives the values used.
    element, curved
        ``"P2"``: quadratic elements on ``tets[0]``, curved when ``curved`` is its
        :class:`nestmg.curved.CurvedMesh` (see :func:`nestmg.setup_problem`); the solution is then on
        the P2 nodes ``curved.X``.
    cost : bool
        Also measure the cost of one cycle in fine SpMVs.
    return_solution : bool
        Also return the solution on every fine node as ``solution`` ((n_0,) array, 0 on Dirichlet nodes;
        (n_0, 3) displacements for elasticity; not JSON: pop it before writing the dict).
    fractions : list of arrays, optional
        Precomputed :func:`nestmg.problems.volume_fractions` (``coarse="weighted"``).

    Returns
    -------
    dict
        ``residuals``, ``factor``, ``iterations``, ``converged``, ``diverged``, ``message``,
        ``seconds`` (assembly / setup / solve, wall) and ``cpu_seconds`` (the same in CPU seconds),
        ``levels`` (n, nnz per level), ``coarsest`` (:attr:`solvers.MultigridSolver.coarsest_solver`),
        ``cycle_cost``.
    """
    o = typed(options, SolverOptions, "options")
    t0, c0 = time.perf_counter(), time.process_time()
    extra = {"element": element, "curved": curved} if element != "P1" else {}
    prob = setup_problem(tets, P, problem, coarse=o.coarse, lam=o.lam, fractions=fractions,
                         poisson_ratio=o.poisson_ratio, **extra)
    o = o.resolved(problem, prob.params.get("nu"))  # smoother, nu, cycle not set: the problem's defaults
    t_asm, c_asm = time.perf_counter() - t0, time.process_time() - c0
    t0, c0 = time.perf_counter(), time.process_time()
    ml = prob.multigrid(o)
    if o.accel is None:
        ml.probe()  # the deflation probe serves stationary cycling only: part of its set-up
    t_setup, c_setup = time.perf_counter() - t0, time.process_time() - c0
    pre = ml.levels[0].presmoother if len(ml.levels) > 1 else None
    out: dict[str, Any] = {
        "problem": problem, "coarse": o.coarse, "nu": o.nu, "smoothing": o.smoothing,
        # the smoother built (elasticity turns Gauss-Seidel into nodal block Gauss-Seidel)
        "smoother": pre.name if pre is not None else o.smoother,
        "coarse_nu": 2 * o.nu if o.coarse_nu is None else o.coarse_nu,
        "local_nodes": 0 if not o.local or prob.local_nodes is None else int(prob.local_nodes.size),
        "cycle": o.cycle, "accel": o.accel, "lam": prob.params["lam"], "element": element,
        **({"poisson_ratio": prob.params["nu"]} if "nu" in prob.params else {}),
        "tol": o.tol, "coarse_scaling": ml.coarse_scaling,
        "levels": [{"n": int(L.A.shape[0]), "nnz": int(L.A.nnz)} for L in ml.levels],
        "operator_complexity": ml.operator_complexity(),
        "coarsest": ml.coarsest_solver,
        # slow modes deflated per level (solvers.deflation): level, probe factor, modes kept
        "deflation": [{"level": d["level"], "probe_factor": d["probe_factor"], "modes": d["vectors"]}
                      | ({"local_solve": d["local_solve"]} if "local_solve" in d else {})
                      for d in ml.deflation],
    }
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            x, info = ml.solve(prob.b, tol=o.tol, maxiter=o.maxiter, cycle=o.cycle, accel=o.accel,
                               return_info=True)
        out.update(residuals=info["residuals"], iterations=info["iterations"], converged=info["converged"],
                   diverged=False, message="")
        out["solution_norm"] = float(np.linalg.norm(x))
        if return_solution:
            out["solution"] = prob.expand(x)
    except DivergenceError as exc:
        out.update(residuals=exc.residuals, iterations=exc.cycle, converged=False, diverged=True, message=str(exc))
    t_solve, c_solve = time.perf_counter() - t0, time.process_time() - c0
    out["factor"] = convergence_factor(out["residuals"])
    out["seconds"] = {"assembly": t_asm, "setup": t_setup, "solve": t_solve}
    # this process's CPU seconds (its threads included): less inflated than wall seconds on a busy machine
    out["cpu_seconds"] = {"assembly": c_asm, "setup": c_setup, "solve": c_solve}
    if cost:
        out["cycle_cost"] = measure_cycle_cost(ml, o.cycle)
    return out
