"""Baseline solvers to compare geometric multigrid against, each timed in one call.

Every function takes ``(A, b)`` plus options and returns a :class:`BaselineResult` with the solution,
the iteration count, setup and solve wall-clock times and the relative residual history, so a
benchmark can run all of them on the same system::

    results = run_baselines(A, b, tol=1e-8)
    for name, r in results.items():
        print(name, r.iterations, r.setup_seconds, r.solve_seconds)

Iterative baselines stop at ``||b - A x|| <= tol ||b||`` like :meth:`MultigridSolver.solve`.
With ``nullspace="constant"`` (pure Neumann) ``b`` must be compatible (``sum(b) = 0``), direct
solvers pin one node, and all solutions are returned with zero mean.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .errors import SolverError, SolverInputError
from .coarse import sparse_lu

__all__ = [
    "BASELINES",
    "BaselineResult",
    "BaselineUnavailableError",
    "cholmod",
    "cholmod_available",
    "pyamg_rs",
    "pyamg_sa",
    "run_baselines",
    "scipy_direct",
]


class BaselineUnavailableError(SolverError, ImportError):
    """The baseline needs an optional package that is not installed (e.g. scikit-sparse for CHOLMOD)."""


@dataclass
class BaselineResult:
    """Timings and outcome of one baseline run.

    Attributes
    ----------
    name : str
    x : (n,) float64
    iterations : int (0 for direct solvers)
    setup_seconds, solve_seconds : float
    residuals : list of float, relative residual history (final one only for direct solvers)
    converged : bool
    info : dict, solver-specific (levels, operator complexity, factor nnz, ...)
    """

    name: str
    x: np.ndarray
    iterations: int
    setup_seconds: float
    solve_seconds: float
    residuals: list = field(default_factory=list)
    converged: bool = True
    info: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        """JSON-serialisable summary (without ``x``)."""
        return {
            "name": self.name,
            "iterations": int(self.iterations),
            "setup_seconds": float(self.setup_seconds),
            "solve_seconds": float(self.solve_seconds),
            "final_residual": float(self.residuals[-1]) if self.residuals else None,
            "converged": bool(self.converged),
            "info": self.info,
        }


def _prep(A, b, nullspace):
    if not sp.issparse(A) or A.shape[0] != A.shape[1]:
        raise SolverInputError("A must be a square scipy sparse matrix")
    A = sp.csr_matrix(A, dtype=np.float64)
    b = np.array(np.asarray(b).reshape(-1), dtype=np.float64)
    if b.shape != (A.shape[0],) or not np.all(np.isfinite(b)):
        raise SolverInputError(f"b must be a finite array of shape ({A.shape[0]},)")
    if nullspace not in (None, "constant"):
        raise SolverInputError(f"nullspace must be None or 'constant', got {nullspace!r}")
    if nullspace == "constant":
        from .fem import check_compatible

        check_compatible(b)
        b -= b.mean()
    return A, b


def _rel(A, b, x):
    nb = np.linalg.norm(b)
    return float(np.linalg.norm(b - A @ x) / nb) if nb else 0.0


def _pyamg_run(name, builder, A, b, tol, maxiter, accel, nullspace, **kw):
    A, b = _prep(A, b, nullspace)
    t0 = time.perf_counter()
    ml = builder(A, **kw)
    t1 = time.perf_counter()
    res: list[float] = []
    x = ml.solve(b, tol=tol, maxiter=maxiter, accel=accel, residuals=res)
    if nullspace == "constant":
        x = x - x.mean()
    final = _rel(A, b, x)
    for _ in range(2):  # pyamg's CG stops on its own residual norm, which can sit below the true one:
        if final <= tol or len(res) > maxiter:  # restart from x until the true residual meets tol
            break
        more: list[float] = []
        x = ml.solve(b, x0=x, tol=tol, maxiter=maxiter, accel=accel, residuals=more)
        res += more[1:]
        if nullspace == "constant":
            x = x - x.mean()
        final = _rel(A, b, x)
    t2 = time.perf_counter()
    nb = np.linalg.norm(b)
    rel = [float(r) / nb for r in res] if nb else [0.0]
    return BaselineResult(
        name, x, len(rel) - 1, t1 - t0, t2 - t1, rel, final <= tol * 1.01,
        {"levels": len(ml.levels), "operator_complexity": float(ml.operator_complexity()),
         "final_true_residual": final, "accel": accel},
    )


def pyamg_sa(A, b, *, tol: float = 1e-8, maxiter: int = 500, accel: str | None = "cg", smooth="default",
             nullspace: str | None = None, **kwargs) -> BaselineResult:
    """pyamg smoothed aggregation (``smooth="default"`` Jacobi prolongation smoothing, or ``"energy"``).

    Extra ``kwargs`` go to ``pyamg.smoothed_aggregation_solver``.
    """
    import pyamg

    if smooth != "default":
        kwargs["smooth"] = smooth
    name = "pyamg_sa" if smooth == "default" else f"pyamg_sa_{smooth if isinstance(smooth, str) else 'custom'}"
    return _pyamg_run(name, pyamg.smoothed_aggregation_solver, A, b, tol, maxiter, accel, nullspace, **kwargs)


def pyamg_rs(A, b, *, tol: float = 1e-8, maxiter: int = 500, accel: str | None = "cg",
             nullspace: str | None = None, **kwargs) -> BaselineResult:
    """pyamg classical Ruge–Stüben AMG (``kwargs`` go to ``pyamg.ruge_stuben_solver``)."""
    import pyamg

    return _pyamg_run("pyamg_rs", pyamg.ruge_stuben_solver, A, b, tol, maxiter, accel, nullspace, **kwargs)


def _pinned(A, nullspace):
    """Matrix to factorise and the kept indices (all, or all but one pinned node for Neumann)."""
    n = A.shape[0]
    if nullspace == "constant":
        keep = np.delete(np.arange(n), int(np.argmax(A.diagonal())))
        return A[keep][:, keep], keep
    return A, None


def _unpinned(xk: np.ndarray, keep: np.ndarray | None, n: int) -> np.ndarray:
    """The solution of the whole singular system from that of the pinned one (:func:`_pinned`): the
    pinned node set to 0, then the constant removed (mean zero)."""
    if keep is None:
        return xk
    x = np.zeros(n)
    x[keep] = xk
    x -= x.mean()
    return x


def scipy_direct(A, b, *, method: str = "splu", nullspace: str | None = None) -> BaselineResult:
    """SuperLU (``method="splu"``: factorise then solve, timed separately) or ``spsolve`` (one call).

    ``"splu"`` uses :func:`solvers.coarse.sparse_lu`: SuperLU's symmetric mode (minimum-degree ordering of
    ``A``, no pivoting) for a symmetric matrix, its best setting for the SPD matrices of this project."""
    if method not in ("splu", "spsolve"):
        raise SolverInputError(f"method must be 'splu' or 'spsolve', got {method!r}")
    A, b = _prep(A, b, nullspace)
    Ak, keep = _pinned(A, nullspace)
    bk = b if keep is None else b[keep]
    Ak = sp.csc_matrix(Ak)
    t0 = time.perf_counter()
    info = {}
    try:
        if method == "splu":
            lu = sparse_lu(Ak)
            t1 = time.perf_counter()
            xk = lu.solve(bk)
            info["factor_nnz"] = int(lu.L.nnz + lu.U.nnz)
        else:
            t1 = t0
            xk = spla.spsolve(Ak, bk)
    except RuntimeError as e:
        raise SolverError(f"scipy {method} failed (singular matrix?): {e}") from None
    t2 = time.perf_counter()
    x = _unpinned(xk, keep, A.shape[0])
    final = _rel(A, b, x)
    info["final_true_residual"] = final
    return BaselineResult(f"scipy_{method}", x, 0, t1 - t0, t2 - t1, [final], bool(np.isfinite(final)), info)


def cholmod_available() -> bool:
    """True if scikit-sparse's CHOLMOD binding imports."""
    try:
        import sksparse.cholmod  # noqa: F401
    except (ImportError, OSError):
        return False
    return True


def cholmod(A, b, *, nullspace: str | None = None) -> BaselineResult:
    """Sparse Cholesky with CHOLMOD (scikit-sparse); raises :class:`BaselineUnavailableError` if absent."""
    try:
        from sksparse.cholmod import cholesky
    except (ImportError, OSError) as e:
        raise BaselineUnavailableError(
            "CHOLMOD baseline needs scikit-sparse (apt-get install libsuitesparse-dev; "
            f"pip install scikit-sparse==0.4.16): {e}"
        ) from None
    A, b = _prep(A, b, nullspace)
    Ak, keep = _pinned(A, nullspace)
    bk = b if keep is None else b[keep]
    t0 = time.perf_counter()
    factor = cholesky(sp.csc_matrix(Ak))
    t1 = time.perf_counter()
    xk = factor(bk)
    t2 = time.perf_counter()
    x = _unpinned(xk, keep, A.shape[0])
    final = _rel(A, b, x)
    return BaselineResult("cholmod", x, 0, t1 - t0, t2 - t1, [final], bool(np.isfinite(final)),
                          {"final_true_residual": final})


BASELINES = {
    "pyamg_sa": pyamg_sa,
    "pyamg_sa_energy": lambda A, b, **kw: pyamg_sa(A, b, smooth="energy", **kw),
    "pyamg_rs": pyamg_rs,
    "scipy_splu": lambda A, b, **kw: scipy_direct(A, b, method="splu", **kw),
    "cholmod": cholmod,
}


def run_baselines(A, b, names=None, *, tol: float = 1e-8, nullspace: str | None = None,
                  max_direct_size: int | None = 200_000) -> dict:
    """Run several baselines on ``A x = b``.

    Parameters
    ----------
    A : (n, n) sparse, b : (n,) array_like
    names : list of str, optional
        Keys of :data:`BASELINES` (default: all).
    tol : float, tolerance of the iterative ones.
    nullspace : None or "constant"
    max_direct_size : int or None
        Skip SuperLU above this many unknowns (it needs ~9 GB at 135k unknowns on a 3D mesh).

    Returns
    -------
    dict name -> BaselineResult, or name -> str (why it was skipped).
    """
    names = list(BASELINES) if names is None else list(names)
    out = {}
    for name in names:
        if name not in BASELINES:
            raise SolverInputError(f"unknown baseline {name!r}; choose from {sorted(BASELINES)}")
        if name == "cholmod" and not cholmod_available():
            out[name] = "skipped: scikit-sparse not installed"
            continue
        if name == "scipy_splu" and max_direct_size is not None and A.shape[0] > max_direct_size:
            out[name] = f"skipped: n={A.shape[0]} > max_direct_size={max_direct_size}"
            continue
        kw = {"nullspace": nullspace}
        if name.startswith("pyamg"):
            kw["tol"] = tol
        out[name] = BASELINES[name](A, b, **kw)
    return out
