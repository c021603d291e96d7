"""Many right-hand sides with one multigrid set-up: column-blocked MG-PCG.

``solve_many(ml, B)`` solves ``A X = B`` for a block ``B`` of ``k`` columns with the levels of one
:class:`solvers.MultigridSolver`: every column runs its own conjugate-gradient recurrence (its own step
lengths), but all columns advance together, so each iteration is one sparse-times-dense product
``A @ X`` and one V-cycle on the whole block instead of ``k`` SpMVs and ``k`` cycles. Columns that reach
the tolerance leave the block.

The cycle must accept blocks: the multicolour Gauss–Seidel smoother with ``blocksize=1``
(:data:`MULTI_RHS_SMOOTHER`; a colour's rows update at once, one sparse product per colour, so it takes
``(n, k)`` arrays as they are) and the coarsest SuperLU solve (``splu.solve`` takes columns). pyamg's
compiled point Gauss–Seidel, the default, works on one vector only: build the solver with
``presmoother=MULTI_RHS_SMOOTHER``.
"""

from __future__ import annotations

import time

import numpy as np

from .errors import SolverInputError
from .multilevel import DEFAULT_MAXITER, MultigridSolver

__all__ = ["MULTI_RHS_SMOOTHER", "solve_many"]

#: Smoother spec of a :class:`MultigridSolver` whose cycle takes blocks of right-hand sides: multicolour
#: point Gauss–Seidel, a forward sweep before the coarse correction and (the default post-smoother, its
#: adjoint) a backward one after it, so the cycle is a symmetric preconditioner for CG.
MULTI_RHS_SMOOTHER = ("block_gauss_seidel", {"blocksize": 1, "sweep": "forward"})


def _check_block_cycle(ml: MultigridSolver) -> None:
    """Raise unless every smoother of ``ml`` is the multicolour one and the coarse solve is SuperLU."""
    for k, L in enumerate(ml.levels[:-1]):
        for sm in (L.presmoother, L.postsmoother):
            if sm.name != "block_gauss_seidel" or sm.params.get("ordering") != "multicolor":
                raise SolverInputError(
                    f"solve_many needs smoothers that take blocks of columns; level {k} has {sm.name!r}: "
                    "build the "
                    "MultigridSolver with presmoother=solvers.multirhs.MULTI_RHS_SMOOTHER")
    if ml.nullspace is not None or ml._coarse_solver.lu is None or ml._coarse_solver.pin is not None:
        raise SolverInputError("solve_many handles non-singular operators with a SuperLU coarsest solve only")
    if not ml.symmetric_cycle:
        raise SolverInputError("solve_many runs CG: the cycle must be symmetric (adjoint smoothers)")


def _cycle_block(ml: MultigridSolver, R: np.ndarray) -> np.ndarray:
    """One V-cycle from zero on every column of ``R`` (n, k)."""
    Z = np.zeros_like(R)
    if len(ml.levels) == 1:
        return ml._coarse_solver(R)
    ml._cycle(0, Z, R, "V")
    return Z


def solve_many(ml: MultigridSolver, B, *, tol: float = 1e-8, maxiter: int = DEFAULT_MAXITER,
               chunk: int = 64, return_info: bool = False):
    """Solve ``A X = B`` column by column with MG-preconditioned CG, the columns advanced as a block.

    Parameters
    ----------
    ml : MultigridSolver
        Built with ``presmoother=MULTI_RHS_SMOOTHER``, no null space.
    B : (n, k) array_like
        Right-hand sides.
    tol : float
        Stop a column when ``||b_j - A x_j|| <= tol ||b_j||`` (CG's recursive residual).
    maxiter : int
        Iterations per block of columns.
    chunk : int
        Columns per block (memory: about 6 ``(n, chunk)`` float arrays at once).
    return_info : bool
        Also return ``{"iterations": (k,) int, "converged": bool, "seconds": float}``.

    Returns
    -------
    X : (n, k) float64
    info : dict, only with ``return_info=True``
    """
    _check_block_cycle(ml)
    A = ml.levels[0].A
    B = np.asarray(B, dtype=np.float64)
    if B.ndim == 1:
        B = B[:, None]
    if B.ndim != 2 or B.shape[0] != A.shape[0]:
        raise SolverInputError(f"B must have shape ({A.shape[0]}, k), got {B.shape}")
    if not np.all(np.isfinite(B)):
        raise SolverInputError("B contains NaN/inf entries")
    if int(chunk) < 1 or int(maxiter) < 1 or not tol > 0:
        raise SolverInputError(f"need chunk >= 1, maxiter >= 1 and tol > 0, got {chunk}, {maxiter}, {tol}")
    t0 = time.perf_counter()
    X = np.zeros_like(B)
    its = np.zeros(B.shape[1], dtype=np.int64)
    for s in range(0, B.shape[1], int(chunk)):
        cols = np.arange(s, min(s + int(chunk), B.shape[1]))
        X[:, cols], its[cols] = _block_pcg(ml, A, B[:, cols], tol, int(maxiter))
    converged = bool(np.all(its <= maxiter))
    its = np.minimum(its, maxiter)
    if return_info:
        return X, {"iterations": its, "converged": converged, "seconds": time.perf_counter() - t0}
    return X


def _block_pcg(ml, A, B, tol, maxiter):
    """CG on every column of ``B`` (n, k) at once; returns ``X`` and the iterations per column
    (``maxiter + 1`` for a column that did not converge)."""
    k = B.shape[1]
    X = np.zeros_like(B)
    its = np.full(k, maxiter + 1, dtype=np.int64)
    normb = np.linalg.norm(B, axis=0)
    its[normb == 0] = 0
    act = np.flatnonzero(normb > 0)  # columns still iterating
    R = B[:, act].copy()
    Z = _cycle_block(ml, R)
    D = Z.copy()
    rz = np.einsum("ij,ij->j", R, Z)
    Xa = np.zeros_like(R)
    for it in range(1, maxiter + 1):
        if not len(act):
            break
        AD = A @ D
        alpha = rz / np.einsum("ij,ij->j", D, AD)
        Xa += alpha * D
        R -= alpha * AD
        done = np.linalg.norm(R, axis=0) <= tol * normb[act]
        if done.any():  # converged columns leave the block
            X[:, act[done]] = Xa[:, done]
            its[act[done]] = it
            keep = ~done
            act, Xa, R, D, rz = act[keep], Xa[:, keep], R[:, keep], D[:, keep], rz[keep]
            if not len(act):
                break
        Z = _cycle_block(ml, R)
        rz_new = np.einsum("ij,ij->j", R, Z)
        D = Z + (rz_new / rz) * D
        rz = rz_new
    X[:, act] = Xa
    return X, its
