"""Direct solve on the coarsest level (SuperLU, pivoted Cholesky, regularised SuperLU, dense pseudo-inverse).

Split from :mod:`solvers.multilevel`; also used by :mod:`solvers.petsc` for PETSc's coarsest level, so
both paths share the same safeguards for rank-deficient Galerkin coarse operators.
"""

from __future__ import annotations

import time

import numpy as np
import scipy.linalg as sla
from scipy.linalg import lapack
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.sparse.csgraph import reverse_cuthill_mckee

from .errors import SolverError, SolverInputError
from .transfer import _is_symmetric

__all__ = ["BAND_MAX_FRACTION", "DENSE_MAX", "PIVOTED_MAX", "sparse_lu"]

#: ``coarse_solver="auto"`` factorises a coarsest level of at most this many unknowns densely (LAPACK
#: Cholesky, ``scipy.linalg.cho_factor``) instead of with SuperLU. Galerkin products of non-nested
#: levels fill up (86-95 nonzeros per row on the coarsest level of 1M-tet user hierarchies): there the
#: dense factor (n³/3 flops, BLAS 3) took 0.07-0.08 s where SuperLU's validated factorisations took
#: 0.33-0.52 s (cProfile, docs/usermesh.md). Raised from 1,500 to 2,000 for the TetGen spot's 1,576-unknown
#: coarsest level: 0.06 s dense against 0.15-0.28 s for SuperLU's failed plain and regularised factors, the
#: same CG iterations.
DENSE_MAX = 2000

#: ``coarse_solver="auto"``: a symmetric coarsest level of at most this many unknowns whose SuperLU factor
#: fails validation gets the dense pivoted Cholesky (:class:`_PivotedCholesky`) before the regularised
#: SuperLU. LAPACK ``dpstrf`` took 0.12 / 0.83 / 2.7 CPU s at 2,000 / 4,000 / 6,000 unknowns (1.3-1.5x a
#: plain Cholesky, one thread); the regularised factor is cheaper but can stall CG (see the class).
PIVOTED_MAX = 6000

#: the guarded regularised factor of "auto": block inverse iteration (vectors, steps) estimating the smallest
#: range eigenvalue, quotients below GUARD_NULL taken as null vectors, and the factor refused when the
#: floor is below GUARD_MIN (then the regularised solve could be off by more than 1e-9 / GUARD_MIN = 1e-4)
GUARD_VECTORS = 16
GUARD_STEPS = 4
GUARD_NULL = 1e-10
GUARD_MIN = 1e-5

#: A symmetric coarsest level under ``DENSE_MAX`` is factorised as a band matrix (LAPACK's banded
#: Cholesky, ``scipy.linalg.cholesky_banded``) in the reverse Cuthill–McKee order of its own pattern when
#: that order's half-bandwidth ``b`` is at most this fraction of ``n``: about ``n b²`` flops against
#: ``n³/3`` for the full factor. Measured (one core, ``n`` = 1,500): 0.21x / 0.41x / 0.87x of the full
#: Cholesky's time at ``b/n`` = 0.2 / 0.4 / 0.5; on the coarsest levels of the 1M-tet TetGen and TetWild
#: spot hierarchies of docs/usermesh.md (``b/n`` = 0.33 / 0.28 in that order) 12 / 7 ms against 40 / 30 ms.
BAND_MAX_FRACTION = 0.4


def _band_storage(A: sp.csr_matrix, shift) -> tuple[np.ndarray, np.ndarray] | None:
    """``(perm, ab)``: the reverse Cuthill–McKee order ``perm`` of ``A``'s pattern and LAPACK's lower band
    storage of ``A[perm][:, perm]`` (``ab[i - j, j]``, ``0 <= i - j <= b``; the lower triangle is read,
    duplicates summed), ``shift`` added to the diagonal; None when the half-bandwidth ``b`` in that order
    exceeds :data:`BAND_MAX_FRACTION` of ``n``."""
    n = A.shape[0]
    perm = np.asarray(reverse_cuthill_mckee(A, symmetric_mode=True), dtype=np.int64)
    inv = np.empty(n, dtype=np.int64)
    inv[perm] = np.arange(n)
    i = np.repeat(inv, np.diff(A.indptr))
    j = inv.take(A.indices)
    low = np.flatnonzero(i >= j)
    j = j[low]
    off = i[low] - j
    b = int(off.max(initial=0))
    if b > BAND_MAX_FRACTION * n:
        return None
    ab = np.bincount(off * n + j, weights=A.data[low], minlength=(b + 1) * n).reshape(b + 1, n)
    if shift is not None:
        ab[0, inv] += shift
    return perm, ab


class _DenseFactor:
    """LAPACK factor (symmetric: Cholesky, in band storage when the bandwidth allows; else LU) with SuperLU's
    ``solve`` / ``L`` / ``U`` interface. ``shift``: added to the diagonal before factorising (regularisation),
    without forming ``A + diag(shift)``. A symmetric ``A`` is read from its lower triangle, as LAPACK does."""

    def __init__(self, A: sp.spmatrix, symmetric: bool, shift: np.ndarray | None = None):
        A = sp.csr_matrix(A)
        n = A.shape[0]
        self.symmetric = symmetric
        self.perm = None
        band = _band_storage(A, shift) if symmetric and n > 1 else None
        try:
            if band is not None:
                self.perm, ab = band
                b = ab.shape[0] - 1
                self.c = sla.cholesky_banded(ab, lower=True, overwrite_ab=True, check_finite=False)
                diagonal = self.c[0]
                self.nnz = 2 * (b + 1) * n - b * (b + 1)  # the two triangular solves
            else:
                Ad = A.toarray()
                if shift is not None:
                    Ad[np.diag_indices(n)] += shift
                if symmetric:
                    self.c = sla.cho_factor(Ad, lower=True, overwrite_a=True, check_finite=False)
                    diagonal = self.c[0].diagonal()
                else:
                    self.c = sla.lu_factor(Ad, overwrite_a=True, check_finite=False)
                    diagonal = np.ones(1)
                self.nnz = n * (n + 1)
            if not np.all(np.isfinite(diagonal)):
                raise sla.LinAlgError("non-finite Cholesky factor")
        except (sla.LinAlgError, ValueError) as e:
            raise SolverError(str(e)) from None  # a RuntimeError: caught by the callers below
        self.L = self.U = sp.csr_matrix((n, n))

    def solve(self, b: np.ndarray) -> np.ndarray:
        if self.perm is not None:
            x = np.empty_like(b, dtype=np.float64)
            x[self.perm] = sla.cho_solve_banded((self.c, True), b[self.perm], check_finite=False)
            return x
        if self.symmetric:
            return sla.cho_solve(self.c, b, check_finite=False)
        return sla.lu_solve(self.c, b, check_finite=False)


class _PivotedCholesky:
    """Rank-revealing Cholesky ``Πᵀ A Π = L Lᵀ`` of a symmetric positive semi-definite matrix (LAPACK
    ``dpstrf``: complete diagonal pivoting, stopped at the first pivot below ``rtol · max diag A``).

    ``solve`` returns the basic solution: the ``rank`` pivoted unknowns from ``L``, the others zero. With
    ``A = [[A11, A12], [A21, A22]]`` in pivoted order and a zero Schur complement, ``A22 = A21 A11⁻¹ A12``,
    any consistent ``b`` has ``b2 = A21 A11⁻¹ b1``, so ``x = (A11⁻¹ b1, 0)`` solves ``A x = b`` exactly,
    whatever the null space, and ``b ↦ x`` is symmetric positive semi-definite (a CG preconditioner stays
    one). The regularised factor of ``A + 1e-9 diag A`` is not exact on the range: on the clamped
    elasticity coarsest level of spot (4,017 unknowns, ν = 0.45, six null vectors from a rank-deficient
    prolongation, smallest nonzero eigenvalue 9.7e-8 λ_max) its coarse corrections were 2.7 % off (median;
    this factor's 1e-10), and MG-PCG with the W-cycle ended at residual 1.9 after 500 iterations; with this
    factor (and :func:`solvers.pcg`'s stall stop) it reaches the attainable 1.6e-8 in 23
    (``benchmarks/results/elasticity/``). Higham, *Accuracy and Stability of Numerical Algorithms*, §10.3.
    """

    def __init__(self, A: sp.spmatrix, rtol: float, sparse_solve: bool = False):
        A = sp.csr_matrix(A)
        n = A.shape[0]
        d = A.diagonal()
        if not (np.all(np.isfinite(A.data)) and d.size and d.max() > 0):
            raise SolverError("pivoted Cholesky: no positive diagonal entry (or non-finite entries)")
        # in Fortran order LAPACK factorises the array in place (a C-ordered one is copied first)
        c, piv, rank, info = lapack.dpstrf(A.toarray(order="F"), lower=1, tol=rtol * float(d.max()),
                                           overwrite_a=1)
        if info < 0:
            raise SolverError(f"pivoted Cholesky: LAPACK dpstrf argument {-info} is invalid")
        self.rank = rank = int(rank)
        p = (piv - 1).astype(np.int64)
        self.perm, dropped = p[:rank], p[rank:]
        self.L = self.U = sp.csr_matrix((n, n))
        self.lu = self.c = None
        if sparse_solve and rank:
            # the cycle solves many times: SuperLU of the kept block A11 (nonsingular) solves faster than
            # the dense triangles (spot elasticity-free, 4,017 unknowns, W-cycle MG-PCG: 3.4 s against 11.6)
            del c
            self.lu = sparse_lu(sp.csc_matrix(A[self.perm][:, self.perm]), symmetric=True)
            self.nnz = int(self.lu.L.nnz + self.lu.U.nnz)
        else:
            # L11 kept in place, the trailing rows of the lower triangle set to (0, I): the n x n triangular
            # solves of (b1, 0) give (A11⁻¹ b1, 0) without a copy of L11 (a strided block would be copied
            # to Fortran order at every solve)
            c[rank:, :] = 0.0
            c[np.arange(rank, n), np.arange(rank, n)] = 1.0
            self.c = (c, True)
            self.nnz = rank * (rank + 1)
        # orthonormal basis of the null space, Π (-A11⁻¹ A12; I): the basic solution minus its part there
        # is the minimum-norm solution, the pseudo-inverse's (the cycle's coarse correction then carries no
        # null components, which non-nested P only nearly annihilates)
        self.kernel = np.zeros((n, n - rank))
        if 0 < rank < n:
            self.kernel[self.perm] = -self._solve_kept(A[self.perm][:, dropped].toarray())
            self.kernel[dropped, np.arange(n - rank)] = 1.0
            self.kernel = np.linalg.qr(self.kernel)[0]

    def _solve_kept(self, b1: np.ndarray) -> np.ndarray:
        """``A11⁻¹ b1`` (rows in pivoted order)."""
        if self.lu is not None:
            return self.lu.solve(b1)
        y = np.zeros((self.c[0].shape[0],) + b1.shape[1:])
        y[: self.rank] = b1
        return sla.cho_solve(self.c, y, check_finite=False)[: self.rank]

    def solve(self, b: np.ndarray) -> np.ndarray:
        x = np.zeros(b.shape)
        if self.rank:
            x[self.perm] = self._solve_kept(b[self.perm])
        return x - self.kernel @ (self.kernel.T @ x)


def sparse_lu(A: sp.spmatrix, symmetric: bool | None = None):
    """SuperLU factorisation (``scipy.sparse.linalg.splu``) with the settings that suit ``A``.

    For a symmetric matrix (tested when ``symmetric`` is None) the ordering is a minimum-degree ordering
    of ``A`` itself and SuperLU runs in its symmetric mode with no partial pivoting
    (``diag_pivot_thresh=0``, ``SymmetricMode``): a Cholesky-like factorisation that keeps the ordering's
    fill. With SuperLU's default threshold pivoting the row swaps destroy the symmetric ordering; measured
    on a Galerkin level of a 0.97M-tet hierarchy (24,616 unknowns, 331k nonzeros) that took 70 s against
    0.50 s in symmetric mode (same fill, 8.07M), and 0.043 s against 0.024 s on its 2,708-unknown
    coarsest level (``benchmarks/coarse_factor.py``, docs/reuse.md). Without pivoting an indefinite or
    singular matrix can give a useless factor without an error: callers validate the factor (as
    :class:`_CoarseSolver` does).
    """
    A = sp.csc_matrix(A)
    if symmetric is None:
        symmetric = _is_symmetric(sp.csr_matrix(A))
    if symmetric:
        return spla.splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    return spla.splu(A, permc_spec="MMD_AT_PLUS_A")


class _CoarseSolver:
    """Direct solve on the coarsest level, set up once.

    ``method="pinv"``: dense symmetric pseudo-inverse ``Q_k Λ_k⁻¹ Q_kᵀ`` over the eigenvalues above
    ``rtol · λ_max`` (scipy.linalg.eigh). It returns the minimum-norm solution, which is right for any
    consistent right-hand side, also when the operator has more null vectors than expected: a Galerkin
    operator ``Pᵀ A P`` inherits the kernel of a rank-deficient ``P`` (coarse hat functions that are
    linearly dependent on the finer nodes, e.g. cage nodes touching one or two fine nodes), and the
    restricted residual ``Pᵀ r`` is orthogonal to that kernel. ``method="splu"``: sparse LU (SuperLU),
    with one node pinned for ``nullspace="constant"``; validated at setup on a random consistent
    right-hand side, so a rank-deficient operator raises instead of returning garbage.
    ``method="pivoted"``: dense rank-revealing Cholesky (:class:`_PivotedCholesky`; symmetric positive
    semi-definite operators, exact on the range, any null space). ``method="regularized"``: SuperLU of
    ``A + 1e-9 diag(A)`` (cheap and sparse; for consistent right-hand sides accurate to
    ``1e-9 diag / λ`` on an eigenvalue ``λ``: poor on ill-conditioned levels). ``method="auto"``:
    :meth:`_setup_auto`.
    """

    def __init__(self, A: sp.csr_matrix, nullspace: str | None, level: int, method: str = "auto",
                 pinv_max: int = 3000, rtol: float = 1e-10, symmetric: bool | None = None):
        self.n = A.shape[0]
        self.nullspace = nullspace
        self.symmetric = _is_symmetric(A) if symmetric is None else bool(symmetric)
        self.pin = None
        self.lu = None
        self.Q = None
        t0 = time.perf_counter()
        if method not in ("auto", "pinv", "splu", "pivoted", "regularized"):
            raise SolverInputError("coarse_solver must be 'auto', 'pinv', 'splu', 'pivoted' or "
                                   f"'regularized', got {method!r}")
        self.fallback = False
        # "auto" factorises small coarsest levels densely (same pinning, regularisation and validation)
        self.dense = method == "auto" and self.n <= DENSE_MAX
        if method != "auto":
            self._setup(A, nullspace, level, method, rtol)
        else:
            self._setup_auto(A, nullspace, level, pinv_max, rtol)
        self.seconds = time.perf_counter() - t0

    def _setup_auto(self, A, nullspace, level, pinv_max, rtol):
        """``coarse_solver="auto"``: the first of its steps whose factor passes validation.

        Large levels: SuperLU's symmetric mode, then (symmetric, at most :data:`PIVOTED_MAX` unknowns) the
        regularised SuperLU if :meth:`_range_floor` is at least :data:`GUARD_MIN` ("guarded": homer's
        singular Poisson levels, 0.4-0.7 s set-up against 1.4-2.5 s for the pivoted factor, the same
        iterations), the pivoted Cholesky, then SuperLU's pivoting LU (a symmetric indefinite level), then
        the regularised
        SuperLU, then (at most ``pinv_max``) the pseudo-inverse. The pivoting LU of a semi-definite level
        that failed the symmetric factor cost as much as the pivoted Cholesky (0.35 s at 2,730 unknowns)
        and fails as well. A small coarsest level of a hierarchy (``level > 0``, at most
        :data:`DENSE_MAX`) starts at the regularised dense (band) Cholesky, then the pivoted one: it is
        part of a preconditioner, and the plain Cholesky fails on the extra null vectors of non-nested
        Galerkin levels (0.1 s of 0.2 s at 1,263 unknowns); the pivoted factor first cost 20-50 ms more
        set-up and 2.5 ms instead of 0.3 per solve on the user-mesh levels, for the same iterations
        (docs/usermesh.md).
        """
        steps = [("splu", True)]
        if self.symmetric and self.n <= PIVOTED_MAX:
            steps = [("splu", False), ("guarded", True), ("pivoted", True), ("splu", True)]
        steps += [("regularized", True)] + ([("pinv", True)] if self.n <= pinv_max else [])
        if self.dense and level > 0:
            steps = [("regularized", True)] + [st for st in steps if st[0] not in ("splu", "regularized")]
        for i, (step, pivoting) in enumerate(steps):
            self.pin, self.lu, self.Q = None, None, None
            try:
                self._setup(A, nullspace, level, step, rtol, pivoting)
                return
            except SolverError:
                if i == len(steps) - 1:
                    raise
                self.fallback = True

    def _setup(self, A, nullspace, level, method, rtol, pivoting: bool = True):
        self.method = method
        if method == "pivoted":
            self.lu = _PivotedCholesky(A, rtol, sparse_solve=self.n > DENSE_MAX)
            self.nnz = self.lu.nnz
            self.nullity = self.n - self.lu.rank
            err = self._range_residual(A)  # the basic solution must reproduce a consistent b
            if not err < 1e-6:
                raise SolverError(f"coarsest operator (level {level}, n={self.n}): pivoted Cholesky residual "
                                  f"{err:.1e} (not positive semi-definite?)")
            return
        expected = 1 if nullspace == "constant" else 0
        if method == "guarded":  # the regularised factor, kept only where the range is well conditioned
            self._setup(A, nullspace, level, "regularized", rtol)
            floor = self._range_floor(A)
            if floor < GUARD_MIN:
                raise SolverError(f"coarsest operator (level {level}, n={self.n}): a range eigenvalue "
                                  f"{floor:.1e} x diag: the regularised factor is inexact there")
            self.method = "guarded"  # reported by MultigridSolver.coarsest_solver: the regularised factor, kept
            return
        if method == "regularized":
            # sparse LU of A + eps diag(A): for a consistent right-hand side (b orthogonal to ker A, as
            # the restricted residual P^T r is) the range component is exact to O(eps cond) and null
            # components are irrelevant -- they are invisible after prolongation (ker of a Galerkin
            # operator = ker P, plus the constants, which are projected out). Validated by the residual.
            shift = 1e-9 * np.maximum(A.diagonal(), np.finfo(float).tiny)
            try:
                self.lu = self._factor(A, self.symmetric, shift)
            except RuntimeError as e:
                if not (self.dense and self.symmetric):
                    raise SolverError(f"coarsest operator (level {level}, n={self.n}): regularised LU "
                                      f"failed: {e}") from None
                # dense path: a symmetric operator that is not semi-definite gets the pivoting LU instead
                try:
                    self.lu = _DenseFactor(A, False)
                except RuntimeError as e2:
                    raise SolverError(f"coarsest operator (level {level}, n={self.n}): dense LU failed: "
                                      f"{e2}") from None
            self.nnz = self._nnz()
            self.nullity = -1  # not computed (at least the expected one)
            err = self._range_residual(A)
            if not err < 1e-6:
                raise SolverError(f"coarsest operator (level {level}, n={self.n}): regularised LU residual "
                                  f"{err:.1e}")
            return
        if method == "pinv":
            Ad = A.toarray()
            if self.symmetric:
                w, Q = sla.eigh(Ad)
                keep = w > rtol * max(w.max(), 0.0)
                self.Q, self.winv, self.Qt = Q[:, keep], 1.0 / w[keep], None
            else:  # non-symmetric user operator: SVD pseudo-inverse
                U, sv, Vt = sla.svd(Ad)
                keep = sv > rtol * sv.max()
                self.Q, self.winv, self.Qt = Vt[keep].T, 1.0 / sv[keep], U[:, keep].T
            self.nullity = int(self.n - np.count_nonzero(keep))
            self.nnz = int(2 * self.Q.size)
        else:
            Af = A
            if nullspace == "constant" and self.n > 1:
                # pin the node with the largest diagonal (any node works for a connected graph)
                self.pin = int(np.argmax(A.diagonal()))
                self.keep = np.delete(np.arange(self.n), self.pin)
                Af = A[self.keep][:, self.keep]
            # validate: an operator singular beyond the expected null space gives an LU whose solutions
            # satisfy A x = b but carry huge null-space components, without any error. The solution of
            # A x = A v must be v itself (up to a constant for Neumann).
            v = np.random.default_rng(0).standard_normal(self.n)
            if nullspace == "constant":
                v -= v.mean()
            self.nullity = expected
            # symmetric mode first (no pivoting: right for the SPD operators of this project); a symmetric
            # indefinite operator whose unpivoted factor fails validation gets SuperLU's pivoting LU. The
            # dense path tries Cholesky only: a failure (mostly a semi-definite Galerkin operator with null
            # vectors from a rank-deficient P) goes to the regularised step, which tries the pivoting LU last
            err = np.inf
            # SuperLU's pivoting LU after its symmetric mode
            retry = self.symmetric and not self.dense and pivoting
            for sym in ((True, False) if retry else (self.symmetric,)):
                self.lu = None
                if self.n > 1 or nullspace != "constant":
                    try:
                        self.lu = self._factor(Af, sym)
                    except RuntimeError as e:
                        if sym:
                            continue
                        raise SolverError(f"coarsest operator (level {level}, n={self.n}) is singular: {e}; "
                                          "use coarse_solver='pinv'") from None
                self.nnz = self._nnz()
                with np.errstate(all="ignore"):
                    err = np.linalg.norm(self(A @ v) - v) / np.linalg.norm(v)
                if err < 1e-6:
                    break
            if not err < 1e-6:
                raise SolverError(
                    f"coarsest operator (level {level}, n={self.n}) is numerically singular beyond the "
                    f"expected null space (LU solve error {err:.1e} on a consistent right-hand side). With "
                    "Galerkin operators this means a rank-deficient prolongation (coarse nodes whose hat "
                    "functions are linearly dependent on the finer nodes); use coarse_solver='pinv' "
                    "(or more levels so the coarsest is small enough for it), or drop those coarse nodes "
                    "(prune_prolongations)"
                )

    def _range_floor(self, A: sp.spmatrix) -> float:
        """Smallest nonzero generalised Rayleigh quotient ``xᵀAx / xᵀDx`` (``D = diag A``) found by
        :data:`GUARD_STEPS` block inverse iterations of :data:`GUARD_VECTORS` vectors with this (regularised)
        factor; quotients below :data:`GUARD_NULL` are null vectors and skipped. The regularised solve is
        off by about ``1e-9 / floor`` along the slowest range direction."""
        d = np.maximum(A.diagonal(), np.finfo(float).tiny)
        X = np.random.default_rng(0).standard_normal((self.n, min(GUARD_VECTORS, self.n)))
        for _ in range(GUARD_STEPS):
            X = np.linalg.qr(self.lu.solve(d[:, None] * X))[0]
        with np.errstate(all="ignore"):
            theta = sla.eigh(X.T @ (A @ X), X.T @ (d[:, None] * X), eigvals_only=True)
        nonzero = theta[theta > GUARD_NULL]
        return float(nonzero.min()) if nonzero.size else np.inf

    def _range_residual(self, A: sp.spmatrix) -> float:
        """``||A x - b|| / ||b||`` for ``x`` this solve of the consistent ``b = A v``, ``v`` random
        (seeded)."""
        b = A @ np.random.default_rng(0).standard_normal(self.n)
        with np.errstate(all="ignore"):
            return float(np.linalg.norm(A @ self(b) - b) / np.linalg.norm(b))

    def _factor(self, A: sp.spmatrix, symmetric: bool, shift: np.ndarray | None = None):
        """SuperLU (:func:`sparse_lu`) or, for a small level under ``"auto"``, the LAPACK factor, of
        ``A + diag(shift)``."""
        if self.dense:
            return _DenseFactor(A, symmetric, shift)
        return sparse_lu(A if shift is None else A + sp.diags(shift), symmetric)

    def _nnz(self) -> int:
        if self.lu is None:
            return 0
        if isinstance(self.lu, _DenseFactor):
            return self.lu.nnz
        return int(self.lu.L.nnz + self.lu.U.nnz)

    def __call__(self, b: np.ndarray) -> np.ndarray:
        if self.nullspace == "constant":
            b = b - b.mean()
        if self.Q is not None:
            y = (self.Q.T @ b) if self.Qt is None else (self.Qt @ b)
            x = self.Q @ (self.winv * y)
        elif self.lu is None:
            x = np.zeros(self.n)
        elif self.pin is not None:
            x = np.zeros(self.n)
            x[self.keep] = self.lu.solve(b[self.keep])
        else:
            x = self.lu.solve(b)
        if self.nullspace == "constant":
            x = x - x.mean()
        return x
