"""Shared helpers of the PETSc backend: input checks, row partitions and layouts, scipy -> PETSc
conversion, options, KSP reasons. Split from :mod:`solvers.petsc` (which re-exports the public names).
"""

from __future__ import annotations

import contextlib
import time
import warnings
from typing import Any

import numpy as np
import scipy.sparse as sp

from .errors import IncompatibleRHSError, SolverError, SolverInputError
from .multilevel import ConvergenceWarning

SMOOTHER_NAMES = ("sor", "jacobi", "chebyshev")
AMG_KINDS = ("gamg", "hypre")


class PetscUnavailableError(SolverError, ImportError):
    """petsc4py (or a PETSc feature such as hypre) is not installed; see ``scripts/install-petsc.sh``."""


def _petsc():
    """Import petsc4py lazily (it initialises MPI) and return the ``PETSc`` module."""
    try:
        from petsc4py import PETSc
    except ImportError as e:  # pragma: no cover - exercised only without petsc4py
        raise PetscUnavailableError(
            f"the PETSc backend needs petsc4py ({e}); run scripts/install-petsc.sh "
            "(Debian petsc-dev + petsc4py 3.18.5 built against it)"
        ) from None
    return PETSc


def petsc_available() -> bool:
    """True when ``from petsc4py import PETSc`` works."""
    try:
        _petsc()
    except PetscUnavailableError:
        return False
    return True


# --------------------------------------------------------------------------------------------- input
def _as_csr(M, name: str, shape: tuple[int, int] | None = None) -> sp.csr_matrix:
    if not sp.issparse(M):
        raise SolverInputError(f"{name} must be a scipy sparse matrix, got {type(M).__name__}")
    if np.iscomplexobj(M.data):
        raise SolverInputError(f"{name} must be real")
    M = sp.csr_matrix(M, dtype=np.float64, copy=True)
    M.sum_duplicates()
    M.sort_indices()
    if shape is not None and M.shape != shape:
        raise SolverInputError(f"{name} has shape {M.shape}, expected {shape}")
    if not np.all(np.isfinite(M.data)):
        raise SolverInputError(f"{name} contains {np.count_nonzero(~np.isfinite(M.data))} NaN/inf entries")
    return M


def _check_hierarchy(A, Ps, coarse) -> tuple[sp.csr_matrix, list[sp.csr_matrix], list[sp.csr_matrix] | None]:
    """Validated ``A``, ``Ps`` and given coarse operators ``coarse`` (a list, or None for Galerkin)."""
    A = _as_csr(A, "A")
    if A.shape[0] != A.shape[1] or A.shape[0] == 0:
        raise SolverInputError(f"A must be square and non-empty, got {A.shape}")
    if isinstance(Ps, sp.spmatrix) or not hasattr(Ps, "__len__"):
        raise SolverInputError("Ps must be a list of sparse prolongation matrices")
    sizes = [A.shape[0]]
    out = []
    for k, P in enumerate(Ps):
        P = _as_csr(P, f"Ps[{k}]")
        if P.shape[0] != sizes[-1]:
            raise SolverInputError(f"Ps[{k}] has shape {P.shape}; expected {sizes[-1]} rows (level {k} size)")
        if not 0 < P.shape[1] < P.shape[0]:
            raise SolverInputError(f"Ps[{k}] has shape {P.shape}: a coarse level must have 1..n_{k}-1 nodes")
        empty = np.flatnonzero(np.diff(sp.csc_matrix(P).indptr) == 0)
        if empty.size:
            raise SolverInputError(
                f"Ps[{k}] has {empty.size} all-zero columns (first {empty[0]}): those coarse nodes would get a "
                "zero row in P^T A P; drop them (solvers.restrict_prolongations does)"
            )
        sizes.append(P.shape[1])
        out.append(P)
    ops = None
    if coarse is not None:
        if len(coarse) != len(out):
            raise SolverInputError(f"coarse needs {len(out)} matrices [A_1, ..., A_L], got {len(coarse)}")
        ops = [_as_csr(Ac, f"coarse[{k}]", (sizes[k + 1], sizes[k + 1])) for k, Ac in enumerate(coarse)]
    return A, out, ops


def _check_diagonal(M: sp.csr_matrix, name: str) -> None:
    """SOR/Jacobi/Chebyshev smoothing divides by the diagonal: refuse it here, not deep inside PETSc.

    (An error raised inside PETSc's KSPSolve leaves Debian's PETSc 3.18 in a state that crashes at exit.)
    """
    d = M.diagonal()
    bad = np.flatnonzero(~(d > 0))
    if bad.size:
        raise SolverInputError(
            f"{name} has {bad.size} non-positive diagonal entries (first at row {bad[0]}: {d[bad[0]]:g}); "
            "the smoothers need a positive diagonal (an SPD operator)"
        )


def _check_vector(b, n: int, name: str = "b") -> np.ndarray:
    b = np.asarray(b)
    if b.ndim == 2 and b.shape[1] == 1:
        b = b[:, 0]
    if b.shape != (n,):
        raise SolverInputError(f"{name} must have shape ({n},), got {b.shape}")
    if not np.issubdtype(b.dtype, np.number) or np.iscomplexobj(b):
        raise SolverInputError(f"{name} must be real, got dtype {b.dtype}")
    b = np.array(b, dtype=np.float64)  # a copy: never touch the caller's array
    if not np.all(np.isfinite(b)):
        raise SolverInputError(f"{name} contains {np.count_nonzero(~np.isfinite(b))} NaN/inf entries")
    return b


def _check_nullspace(nullspace) -> str | None:
    if nullspace not in (None, "constant"):
        raise SolverInputError(f"nullspace must be None or 'constant', got {nullspace!r}")
    return nullspace


def _prepare_rhs(b, n: int, nullspace: str | None, project: bool) -> np.ndarray:
    b = _check_vector(b, n)
    if nullspace == "constant":
        scale = float(np.abs(b).sum())
        if project:
            b -= b.mean()
        elif abs(b.sum()) > 1e-10 * max(scale, 1e-300):
            raise IncompatibleRHSError(
                f"sum(b) = {b.sum():.3e} is not zero (relative {abs(b.sum()) / scale:.2e}): the singular system "
                "has no solution; pass project=True to remove the mean of b"
            )
    return b


# ------------------------------------------------------------------------------------- partitioning
def row_partition(n: int, size: int) -> np.ndarray:
    """PETSc's natural contiguous row split (``PETSC_DECIDE``): the first ``n % size`` ranks get one more.

    Parameters
    ----------
    n : int
        Global number of rows.
    size : int
        Number of ranks.

    Returns
    -------
    offsets : (size + 1,) int64
        Rank ``r`` owns rows ``offsets[r]:offsets[r+1]``.
    """
    n, size = int(n), int(size)
    counts = np.full(size, n // size, dtype=np.int64)
    counts[: n % size] += 1
    return np.concatenate([[0], np.cumsum(counts)])


class _Layout:
    """Row distribution of one level: a permutation (new -> old global index) and per-rank offsets."""

    def __init__(self, owner: np.ndarray | None, n: int, size: int):
        self.n = n
        if owner is None:  # natural partition: identity permutation
            self.perm = None
            self.inv = None
            self.offsets = row_partition(n, size)
        else:
            owner = np.asarray(owner, dtype=np.int64)
            self.perm = np.argsort(owner, kind="stable")
            self.inv = np.empty(n, dtype=np.int64)
            self.inv[self.perm] = np.arange(n)
            self.offsets = np.concatenate([[0], np.cumsum(np.bincount(owner, minlength=size))])

    def local_rows(self, rank: int) -> np.ndarray:
        lo, hi = self.offsets[rank], self.offsets[rank + 1]
        return np.arange(lo, hi) if self.perm is None else self.perm[lo:hi]

    def nlocal(self, rank: int) -> int:
        return int(self.offsets[rank + 1] - self.offsets[rank])

    def to_new(self, cols: np.ndarray) -> np.ndarray:
        return cols if self.inv is None else self.inv[cols]

    def to_old(self, x_new: np.ndarray) -> np.ndarray:
        if self.perm is None:
            return x_new
        x = np.empty_like(x_new)
        x[self.perm] = x_new
        return x


def _coarse_owner(P: sp.csr_matrix, fine_owner: np.ndarray, size: int) -> np.ndarray:
    """Give each coarse node to the rank holding most of its interpolation weight ``sum_i |P_ij|``."""
    onehot = sp.csr_matrix(
        (np.ones(fine_owner.size), (np.arange(fine_owner.size), fine_owner)), shape=(fine_owner.size, size)
    )
    weight = np.asarray((abs(P).T @ onehot).todense())
    return np.argmax(weight, axis=1).astype(np.int64)


def _fine_owner(PETSc, A_global, A_nat, partition, n: int, size: int, comm) -> np.ndarray | None:
    """Owner rank of every fine row: None (natural), RCM slabs, a given array, or PETSc MatPartitioning.

    PETSc's MatPartitioning runs in parallel on the naturally distributed operator ``A_nat``; note that
    PT-Scotch is not deterministic (Debian's build): repeated runs cut in different places, so factors
    vary by ~0.01 between runs. "rcm" is deterministic.
    """
    if partition is None or (isinstance(partition, str) and partition == "natural"):
        return None
    if isinstance(partition, str) and partition == "rcm":
        # deterministic level-set slabs: contiguous blocks of the reverse Cuthill-McKee order
        from scipy.sparse.csgraph import reverse_cuthill_mckee

        order = reverse_cuthill_mckee(sp.csr_matrix(A_global), symmetric_mode=True)
        owner = np.empty(n, dtype=np.int64)
        offsets = row_partition(n, size)
        for r in range(size):
            owner[order[offsets[r] : offsets[r + 1]]] = r
        return owner
    if isinstance(partition, str):
        if size == 1:
            return None
        part = PETSc.MatPartitioning().create(comm=comm)
        try:
            part.setType(partition)
        except PETSc.Error as e:
            raise SolverInputError(f"PETSc has no partitioner {partition!r} ({e}); try 'ptscotch' or 'natural'") from None
        part.setAdjacency(A_nat)
        is_ = PETSc.IS()
        part.apply(is_)
        owner = is_.allGather().getIndices().astype(np.int64)
        is_.destroy()
        part.destroy()
        if np.bincount(owner, minlength=size).min() == 0:
            raise SolverError(f"partitioner {partition!r} left a rank without rows")
        return owner
    owner = np.asarray(partition)
    if owner.shape != (n,) or not np.issubdtype(owner.dtype, np.integer):
        raise SolverInputError(f"partition must be 'natural', a PETSc partitioner name or ({n},) int ranks")
    if owner.min() < 0 or owner.max() >= size:
        raise SolverInputError(f"partition ranks must lie in [0, {size})")
    return owner.astype(np.int64)


def _to_petsc(PETSc, M: sp.csr_matrix, rows: _Layout, cols: _Layout, comm):
    """Copy this rank's rows of the global ``M`` into a PETSc AIJ matrix (columns in the new numbering)."""
    rank = comm.getRank()
    local = M[rows.local_rows(rank)] if rows.perm is not None else M[rows.offsets[rank] : rows.offsets[rank + 1]]
    local = sp.csr_matrix(local)
    if cols.inv is not None:
        local = sp.csr_matrix((local.data, cols.to_new(local.indices), local.indptr), shape=local.shape)
    local.sort_indices()
    it = PETSc.IntType
    mat = PETSc.Mat().createAIJ(
        size=((rows.nlocal(rank), rows.n), (cols.nlocal(rank), cols.n)),
        csr=(local.indptr.astype(it), local.indices.astype(it), local.data),
        comm=comm,
    )
    mat.assemble()
    return mat


def _gather(PETSc, vec) -> np.ndarray:
    """All entries of a distributed vector on every rank."""
    scatter, full = PETSc.Scatter.toAll(vec)
    scatter.scatter(vec, full, addv=PETSc.InsertMode.INSERT_VALUES, mode=PETSc.ScatterMode.FORWARD)
    out = full.getArray().copy()
    scatter.destroy()
    full.destroy()
    return out


def _allgather(PETSc, comm, value: float) -> np.ndarray:
    """One float from every rank, on every rank (without mpi4py)."""
    size = comm.getSize()
    vec = PETSc.Vec().createMPI((1, size), comm=comm)
    vec.setValue(comm.getRank(), float(value))
    vec.assemble()
    out = _gather(PETSc, vec)
    vec.destroy()
    return out


def _ghost_count(M: sp.csr_matrix, lay: _Layout, rank: int) -> int:
    """Distinct off-rank columns coupled to this rank's rows (the halo a SpMV must receive)."""
    lo, hi = int(lay.offsets[rank]), int(lay.offsets[rank + 1])
    if hi - lo == M.shape[1]:  # one rank owns every column: no halo (skips an O(nnz) pass)
        return 0
    rows = lay.local_rows(rank)
    seen = np.zeros(M.shape[1], dtype=bool)  # a mask, not np.unique: no hash or sort of nnz entries
    seen[M[rows].indices] = True
    cols = lay.to_new(np.flatnonzero(seen))
    return int(np.count_nonzero((cols < lo) | (cols >= hi)))


@contextlib.contextmanager
def _options(PETSc, prefix: str, values: dict[str, Any]):
    """Put ``values`` into PETSc's options database under ``prefix`` unless the user set them already.

    The options this function inserted are removed on exit, so nothing leaks into later solvers.
    """
    db = PETSc.Options()
    added = []
    for key, val in values.items():
        name = f"{prefix}{key}"
        if db.hasName(name):
            continue
        db.setValue(name, "" if val is None else str(val))
        added.append(name)
    try:
        yield
    finally:
        for name in added:
            db.delValue(name)


def _barrier_time(comm) -> float:
    comm.barrier()
    return time.perf_counter()


def _history(ksp, normb: float) -> list[float]:
    h = np.asarray(ksp.getConvergenceHistory(), dtype=np.float64)
    return [float(v) / normb for v in h]


def _ksp_solve(PETSc, ksp, A, bv, xv, normb: float, comm, what: str = "") -> dict:
    """``ksp.solve(bv, xv)`` (nothing to do for ``b = 0``), timed across ranks, with the true residual.

    Returns ``history`` (relative residuals), ``iterations``, ``reason``, ``solve_seconds`` and
    ``final`` (``||b - A x|| / ||b||``); a PETSc error becomes :class:`SolverError`
    ("PETSc KSPSolve<what> failed"). After a failure inside the solve the KSP is never destroyed
    (see the comment below): the process then still exits cleanly.
    """
    t0 = _barrier_time(comm)
    if normb == 0.0:
        xv.set(0.0)
        hist, its, reason = [0.0], 0, "CONVERGED_ATOL"
    else:
        try:
            ksp.solve(bv, xv)
        except BaseException as e:
            # Debian's PETSc 3.18 segfaults in KSPDestroy (VecDestroy in KSPReset) of a KSP whose solve
            # failed inside (a PETSc error, or a Python exception in a python PC or monitor), even after
            # a later solve succeeded: one extra reference keeps this KSP from ever being destroyed (it
            # is leaked, on purpose, until the process ends; destroy() then only drops a reference).
            ksp.incRef()
            if isinstance(e, PETSc.Error):
                raise SolverError(f"PETSc KSPSolve{what} failed: {_petsc_message(e)}") from None
            raise
        hist = _history(ksp, normb)
        its = ksp.getIterationNumber()
        reason = _reason_name(PETSc, ksp.getConvergedReason())
    solve_seconds = _barrier_time(comm) - t0
    rv = bv.duplicate()
    A.mult(xv, rv)
    rv.aypx(-1.0, bv)
    final = float(rv.norm()) / normb if normb > 0 else 0.0
    rv.destroy()
    return {"history": hist, "iterations": its, "reason": reason, "solve_seconds": solve_seconds, "final": final}


def _coarse_choice(coarse) -> tuple[bool, list | None]:
    """``coarse=`` ("galerkin" or a list ``[A_1, ..., A_L]``) as ``(galerkin, given operators or None)``."""
    if isinstance(coarse, str):
        if coarse != "galerkin":
            raise SolverInputError(
                f"coarse must be 'galerkin' or a list of coarse operators, got {coarse!r} (named coarse "
                "operators such as 'weighted' are built by nestmg.problems.setup_problem)")
        return True, None
    return False, list(coarse)


def _check_reason(reason: str, its: int, hist: list[float], what: str, tol: float) -> None:
    """Raise on breakdown/divergence; warn (as the in-process solver does) when maxiter was reached."""
    if reason == "DIVERGED_ITS":
        warnings.warn(f"{what} stopped after {its} iterations at relative residual {hist[-1]:.3e} > tol={tol:g}",
                      ConvergenceWarning, stacklevel=3)
    elif reason.startswith("DIVERGED"):
        raise SolverError(f"{what} failed: {reason} after {its} iterations (relative residual {hist[-1]:.3e})")


def _petsc_message(err) -> str:
    """The last lines of PETSc's error traceback (the message proper) on one line."""
    lines = [ln.split("] ", 1)[-1] for ln in str(err).splitlines() if ln.strip()]
    return " / ".join(lines[-2:]) if lines else repr(err)


def _noop_monitor(ksp, its, rnorm) -> None:
    """Empty KSP monitor (see PetscMultigrid: keeps KSPRICHARDSON on its generic, history-logging path)."""


def _reason_name(PETSc, code: int) -> str:
    """KSPConvergedReason as PETSc prints it with -ksp_converged_reason (e.g. "DIVERGED_ITS")."""
    if code == PETSc.KSP.ConvergedReason.DIVERGED_MAX_IT:
        return "DIVERGED_ITS"
    for name, val in vars(PETSc.KSP.ConvergedReason).items():
        if not name.startswith("_") and val == code and name != "ITERATING":
            return name
    return f"REASON_{code}"
