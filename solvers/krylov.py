"""Preconditioned conjugate gradients with a residual history (wrapping ``pyamg.krylov.cg``).

MG-PCG is ``MultigridSolver.solve(b, accel="cg")``, which calls :func:`pcg` with one cycle as ``M``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse.linalg as spla
from pyamg.krylov import cg as _pyamg_cg

from .errors import DivergenceError, SolverInputError

__all__ = ["KrylovResult", "pcg"]


class _NonFiniteStop(Exception):
    pass


@dataclass
class KrylovResult:
    """Outcome of :func:`pcg`.

    Attributes
    ----------
    x : (n,) float64
    iterations : int
    residuals : list of float
        Relative residuals ``||r_i|| / ||b||``, initial one first (CG's recursively updated residual).
    converged : bool
    seconds : float
    nonfinite : bool
        True if the iteration produced NaN/inf (only returned with ``raise_on_nonfinite=False``).
    """

    x: np.ndarray
    iterations: int
    residuals: list = field(default_factory=list)
    converged: bool = False
    seconds: float = 0.0
    nonfinite: bool = False


def pcg(
    A,
    b,
    M=None,
    *,
    x0=None,
    tol: float = 1e-8,
    maxiter: int | None = None,
    nullspace: str | None = None,
    divtol: float = 1e5,
    flexible: bool = False,
) -> KrylovResult:
    """Preconditioned CG for a symmetric positive (semi-)definite system.

    Parameters
    ----------
    A : (n, n) sparse matrix or LinearOperator
    b : (n,) array_like
    M : (n, n) LinearOperator, optional
        Preconditioner (approximate inverse), e.g. ``MultigridSolver.aspreconditioner()``.
    x0 : (n,) array_like, optional
    tol : float
        Stop when ``||r|| <= tol ||b||``.
    maxiter : int, optional (default ``n``)
    nullspace : None or "constant"
        Keep iterates and ``b`` in the zero-mean subspace (pure Neumann operators).
    divtol : float
        Flag divergence when the residual grows past ``divtol`` times the initial one.
    flexible : bool
        Flexible CG (Polak–Ribière ``β = zᵀ(r - r_old) / (z_oldᵀ r_old)``, Notay 2000) for a
        preconditioner that varies slightly between iterations (e.g. a cycle with energy-scaled
        coarse corrections). Same cost per iteration as plain CG plus one dot product.

    Returns
    -------
    KrylovResult
        ``nonfinite=True`` instead of an exception when NaN/inf appears, so callers can locate it
        (``MultigridSolver.solve`` does); otherwise divergence raises :class:`DivergenceError`.
    """
    n = A.shape[0]
    b = np.array(np.asarray(b).reshape(-1), dtype=np.float64)
    if b.shape != (n,) or not np.all(np.isfinite(b)):
        raise SolverInputError(f"b must be a finite array of shape ({n},)")
    x = np.zeros(n) if x0 is None else np.array(np.asarray(x0).reshape(-1), dtype=np.float64)
    if x.shape != (n,):
        raise SolverInputError(f"x0 must have shape ({n},)")
    if nullspace == "constant":
        b -= b.mean()
        x -= x.mean()
    maxiter = n if maxiter is None else int(maxiter)
    t0 = time.perf_counter()
    normb = float(np.linalg.norm(b))
    if normb == 0.0:
        return KrylovResult(np.zeros(n), 0, [0.0], True, 0.0)
    res: list[float] = []
    calls = [0]
    Mop = None
    if M is not None:
        M = spla.aslinearoperator(M)

        def _checked(r):
            # stop at the first non-finite preconditioned residual instead of iterating on NaN
            calls[0] += 1
            z = M.matvec(r)
            if not np.all(np.isfinite(z)):
                raise _NonFiniteStop
            return z

        Mop = spla.LinearOperator((n, n), matvec=_checked, dtype=np.float64)
    try:
        with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
            if flexible:
                x = _flexible_cg(A, b, x, Mop, tol, maxiter, res, nullspace == "constant")
            else:
                x, _ = _pyamg_cg(A, b, x0=x, tol=tol, criteria="rr", maxiter=maxiter, M=Mop, residuals=res)
    except _NonFiniteStop:
        rel = [float(r) / normb for r in res] + [float("nan")]
        return KrylovResult(x, calls[0], rel, False, time.perf_counter() - t0, nonfinite=True)
    rel = [float(r) / normb for r in res]
    seconds = time.perf_counter() - t0
    if not np.all(np.isfinite(x)) or not np.all(np.isfinite(rel)):
        return KrylovResult(x, len(rel) - 1, rel, False, seconds, nonfinite=True)
    if max(rel) > divtol * rel[0]:
        raise DivergenceError(
            f"CG diverged: residual grew by {max(rel) / rel[0]:.3g} (> divtol={divtol:g}); "
            "is the preconditioner symmetric positive definite?",
            cycle=int(np.argmax(rel)), residuals=rel,
        )
    if nullspace == "constant":
        x = x - x.mean()
    # report the true final residual (CG's recursive one can drift from it)
    rtrue = float(np.linalg.norm(b - A @ x)) / normb
    rel[-1] = max(rel[-1], rtrue) if len(rel) > 1 else rtrue
    return KrylovResult(x, len(rel) - 1, rel, rel[-1] <= tol * 1.0000001 or rtrue <= tol, seconds)


def _flexible_cg(A, b, x, M, tol, maxiter, res, zero_mean):
    """Flexible PCG (Polak–Ribière β); fills ``res`` with residual norms like pyamg's ``cg``."""
    r = b - A @ x
    normb = float(np.linalg.norm(b))
    res.append(float(np.linalg.norm(r)))
    z_old = r_old = p = None
    for _ in range(maxiter):
        if res[-1] <= tol * normb:
            break
        z = M.matvec(r) if M is not None else r.copy()
        if zero_mean:
            z -= z.mean()
        rz = float(r @ z)
        if p is None:
            p = z.copy()
        else:
            beta = float(z @ (r - r_old)) / float(z_old @ r_old)
            p = z + beta * p
        q = A @ p
        pq = float(p @ q)
        if not pq > 0:
            break
        a = rz / pq
        x = x + a * p
        z_old, r_old = z, r
        r = r - a * q
        res.append(float(np.linalg.norm(r)))
        if not np.isfinite(res[-1]):
            break
    return x
