"""PETSc's algebraic multigrid (GAMG, hypre BoomerAMG) as a baseline. Split from :mod:`solvers.petsc`."""

from __future__ import annotations

import time

import numpy as np

from .errors import SolverError, SolverInputError
from .multilevel import convergence_factor
from .petsc_common import (
    AMG_KINDS,
    PetscUnavailableError,
    _barrier_time,
    _check_hierarchy,
    _check_nullspace,
    _check_reason,
    _gather,
    _ksp_solve,
    _Layout,
    _options,
    _petsc,
    _petsc_message,
    _prepare_rhs,
    _to_petsc,
)


# ----------------------------------------------------------------------------------- PETSc AMG
def petsc_amg_solve(
    A,
    b,
    kind: str = "gamg",
    *,
    tol: float = 1e-8,
    maxiter: int = 200,
    comm=None,
    nullspace: str | None = None,
    project: bool = False,
    options_prefix: str | None = None,
    options: dict | None = None,
) -> tuple[np.ndarray, dict]:
    """Solve ``A x = b`` by CG preconditioned with PETSc's algebraic multigrid, for comparison.

    Parameters
    ----------
    A : (n, n) sparse matrix
        Global SPD (or, with ``nullspace="constant"``, semi-definite) matrix, identical on every rank.
    b : (n,) array_like
        Global right-hand side.
    kind : {"gamg", "hypre"}
        ``"gamg"``: PETSc's smoothed-aggregation PCGAMG (defaults of PETSc 3.18: Chebyshev/Jacobi
        smoothing). ``"hypre"``: hypre's BoomerAMG through PCHYPRE (classical AMG).
    tol, maxiter : float, int
        Relative unpreconditioned residual tolerance and iteration cap of CG.
    comm : petsc4py ``PETSc.Comm``, optional
    nullspace : None or "constant"
    project : bool
        With ``nullspace="constant"``: project an incompatible ``b`` instead of raising.
    options_prefix : str, optional
        Default ``"nestmg_gamg_"`` / ``"nestmg_hypre_"``.
    options : dict, optional
        Extra PETSc options without the prefix (e.g. ``{"pc_gamg_threshold": 0.02}``).

    Returns
    -------
    x : (n,) float64, on every rank
    info : dict
        As :meth:`PetscMultigrid.solve`, plus ``kind``; ``setup_seconds`` covers matrix copy and AMG setup;
        ``setup_cpu_seconds`` / ``solve_cpu_seconds`` are this process's CPU time over the same spans.

    Raises
    ------
    PetscUnavailableError
        No petsc4py, or ``kind="hypre"`` and this PETSc has no hypre.
    """
    PETSc = _petsc()
    if kind not in AMG_KINDS:
        raise SolverInputError(f"kind must be one of {AMG_KINDS}, got {kind!r}")
    nullspace = _check_nullspace(nullspace)
    A, _, _ = _check_hierarchy(A, [], None)
    n = A.shape[0]
    b = _prepare_rhs(b, n, nullspace, project)
    maxiter = int(maxiter)
    if maxiter < 0 or not tol > 0:
        raise SolverInputError(f"need tol > 0 and maxiter >= 0, got {tol}, {maxiter}")
    comm = PETSc.COMM_WORLD if comm is None else comm
    prefix = options_prefix or f"nestmg_{kind}_"
    t0 = _barrier_time(comm)
    c0 = time.process_time()
    lay = _Layout(None, n, comm.getSize())
    Ap = _to_petsc(PETSc, A, lay, lay, comm)
    ns = None
    if nullspace == "constant":
        ns = PETSc.NullSpace().create(constant=True, comm=comm)
        Ap.setNullSpace(ns)
        Ap.setNearNullSpace(ns)
    ksp = PETSc.KSP().create(comm=comm)
    ksp.setOptionsPrefix(prefix)
    ksp.setOperators(Ap)
    ksp.setType("cg")
    ksp.setNormType(PETSc.KSP.NormType.UNPRECONDITIONED)
    pc = ksp.getPC()
    try:
        if kind == "gamg":
            pc.setType("gamg")
            pc.setGAMGType(PETSc.PC.GAMGType.AGG)
        else:
            pc.setType("hypre")
            pc.setHYPREType("boomeramg")
    except PETSc.Error as e:
        ksp.destroy()
        Ap.destroy()
        raise PetscUnavailableError(f"this PETSc cannot provide {kind!r} ({e})") from None
    ksp.setTolerances(rtol=tol, atol=1e-300, max_it=maxiter)
    with _options(PETSc, prefix, dict(options or {})):
        ksp.setFromOptions()
        try:
            ksp.setUp()
        except PETSc.Error as e:
            raise SolverError(f"PETSc {kind} setup failed: {_petsc_message(e)}") from None
    setup_seconds = _barrier_time(comm) - t0
    setup_cpu = time.process_time() - c0
    rows = lay.local_rows(comm.getRank())
    xv, bv = Ap.createVecs()
    bv.setArray(b[rows])
    xv.set(0.0)
    normb = float(np.linalg.norm(b))
    ksp.setConvergenceHistory(length=maxiter + 1, reset=True)
    c1 = time.process_time()
    out = _ksp_solve(PETSc, ksp, Ap, bv, xv, normb, comm, f" (CG+{kind})")
    solve_cpu = time.process_time() - c1
    hist, its, reason = out["history"], out["iterations"], out["reason"]
    solve_seconds, final = out["solve_seconds"], out["final"]
    x = _gather(PETSc, xv)
    if nullspace == "constant":
        x -= x.mean()
    for obj in (xv, bv, ksp, Ap) + ((ns,) if ns is not None else ()):
        obj.destroy()
    _check_reason(reason, its, hist, f"PETSc CG+{kind}", tol)
    return x, {
        "kind": kind,
        "iterations": int(its),
        "converged": reason.startswith("CONVERGED"),
        "reason": reason,
        "residuals": hist,
        "factor": convergence_factor(hist),
        "final_residual": final,
        "setup_seconds": setup_seconds,
        "solve_seconds": solve_seconds,
        "setup_cpu_seconds": setup_cpu,
        "solve_cpu_seconds": solve_cpu,
        "ranks": comm.getSize(),
    }
