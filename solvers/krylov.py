"""Preconditioned conjugate gradients with a residual history.

MG-PCG is ``MultigridSolver.solve(b, accel="cg")``, which calls :func:`pcg` with one cycle as ``M``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .errors import DivergenceError, SolverInputError

__all__ = ["STALL_ITERATIONS", "KrylovResult", "pcg"]


class _NonFiniteStop(Exception):
    pass


class _Stagnated(Exception):
    pass


#: :func:`pcg` stops when this many iterations in a row bring no new minimum of the residual: CG has reached
#: the system's attainable accuracy (round-off, about ``eps ||A|| ||x|| / ||b||``) or its preconditioner is
#: inexact. Past that point the residual only drifts: on clamped elasticity on spot at ν = 0.45 (193k
#: unknowns; SuperLU plus one refinement step reaches 1.4e-8) W-preconditioned CG asked for 1e-8 ended at
#: residual 1.9 after 500 iterations (benchmarks/results/elasticity/spot_clamped_045_*.json). A converging
#: MG-PCG run makes a new minimum every one or two iterations.
STALL_ITERATIONS = 10


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
    stagnated : bool
        True if CG stopped after :data:`STALL_ITERATIONS` iterations without a new minimum residual; ``x``
        is then the iterate of the smallest residual, and the last of ``residuals`` its true residual.
    attainable : float or None
        With ``stagnated``: ``eps ||A||_1 ||x|| / ||b||``, the relative residual round-off alone allows
        (None when ``A`` is not a sparse matrix).
    breakdown : str or None
        Why CG stopped early, when ``A`` or ``M`` showed a non-positive curvature (``pᵀAp <= 0`` or
        ``rᵀMr <= 0``): not symmetric positive definite on the iterates' subspace.
    """

    x: np.ndarray
    iterations: int
    residuals: list = field(default_factory=list)
    converged: bool = False
    seconds: float = 0.0
    nonfinite: bool = False
    stagnated: bool = False
    attainable: float | None = None
    breakdown: str | None = None


class _Best:
    """The iterate of the smallest residual so far; raises :class:`_Stagnated` after ``stall`` iterations
    without a new one (the ``callback`` of :func:`_cg`, called after each residual is appended)."""

    def __init__(self, res: list, stall: int):
        self.res, self.stall, self.x, self.at = res, stall, None, 0

    def __call__(self, x: np.ndarray) -> None:
        k = len(self.res) - 1
        if self.res[-1] < self.res[self.at] or self.x is None:
            self.x, self.at = x.copy(), k
        elif k - self.at >= self.stall:
            raise _Stagnated


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
    stall: int = STALL_ITERATIONS,
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
    stall : int
        Stop after this many iterations without a new minimum residual and return the iterate of the
        smallest one (``stagnated=True``): default :data:`STALL_ITERATIONS`.

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
    best = _Best(res, max(int(stall), 1))
    stagnated = False
    rtrue = None  # ||b - A x|| of the returned x, when the iteration formed it
    breakdown = None
    try:
        with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
            if flexible:
                x = _flexible_cg(A, b, x, Mop, tol, maxiter, res, nullspace == "constant", best)
            else:
                x, rtrue, breakdown = _cg(A, b, x, Mop, tol, maxiter, res, best)
    except _Stagnated:
        stagnated, x = True, best.x
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
        rtrue = None  # A times a constant is round-off, not zero: form it again
    # report the true final residual (CG's recursive one can drift from it)
    rtrue = float(np.linalg.norm(b - A @ x) if rtrue is None else rtrue) / normb
    rel[-1] = rtrue if stagnated else max(rel[-1], rtrue) if len(rel) > 1 else rtrue  # stagnated: best x's
    attainable = None
    if stagnated and sp.issparse(A):  # ||A||_1: the largest column sum of |A|
        attainable = float(np.finfo(float).eps * abs(A).sum(axis=0).max() * np.linalg.norm(x) / normb)
    return KrylovResult(x, len(rel) - 1, rel, rel[-1] <= tol * 1.0000001 or rtrue <= tol, seconds,
                        stagnated=stagnated, attainable=attainable, breakdown=breakdown)


def _cg(A, b, x, M, tol, maxiter, res, callback):
    """PCG (Hestenes–Stiefel; Saad 2003, Alg. 9.1); fills ``res`` with the recursive residual norms.

    Per iteration one product with ``A`` and one application of ``M``, none wasted: the residual is not
    formed from a zero ``x0`` (it is ``b``), the convergence test comes before ``M`` is applied to the
    new residual, and ``r`` is recomputed as ``b - A x`` only when the recursive one meets the tolerance
    (then the true one must too, else CG goes on from it). pyamg's ``cg``, used before, spent one more
    cycle and two or three more products on a 10-iteration MG-PCG solve. Returns ``x``, ``||b - A x||``
    when the last step formed it (else None) and the reason of a breakdown (else None).
    """
    normb = float(np.linalg.norm(b))
    r = b - A @ x if x.any() else b.copy()
    res.append(float(np.linalg.norm(r)))
    if res[-1] <= tol * normb:
        return x, res[-1], None
    z = M.matvec(r) if M is not None else r.copy()
    p = z.copy()
    rz = float(r @ z)
    for _ in range(maxiter):
        if not rz > 0.0:  # (or a NaN): stop, not converged, before a product with A
            return x, None, f"the preconditioner is not positive definite (rᵀMr = {rz:.3g})"
        q = A @ p
        pq = float(p @ q)
        if not pq > 0.0:
            return x, None, f"A is not positive definite (pᵀAp = {pq:.3g} along a search direction)"
        alpha = rz / pq
        x += alpha * p
        r -= alpha * q
        res.append(float(np.linalg.norm(r)))
        callback(x)
        if res[-1] <= tol * normb:
            r = b - A @ x  # drift of the recursive residual: trust only the true one
            true = float(np.linalg.norm(r))
            if true <= tol * normb:
                return x, true, None
        z = M.matvec(r) if M is not None else r.copy()
        rz_new = float(r @ z)
        p *= rz_new / rz
        p += z
        rz = rz_new
    return x, None, None


def _flexible_cg(A, b, x, M, tol, maxiter, res, zero_mean, callback):
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
        callback(x)
    return x
