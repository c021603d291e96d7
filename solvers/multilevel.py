"""Geometric multigrid from a fine operator and a list of prolongations (pyamg-like API).

Notation: level 0 is the finest. ``Ps[k]`` has shape ``(n_k, n_{k+1})`` and interpolates level
``k+1`` values to level ``k`` nodes; restriction is ``R_k = P_kᵀ``. Coarse operators are either
Galerkin products ``A_{k+1} = P_kᵀ A_k P_k`` (default) or supplied by the caller (re-discretisation
on the coarse meshes).

Null space (pure Neumann problems, ``nullspace="constant"``): if every ``P_k`` has rows summing to 1,
then ``P_k 1 = 1`` and ``A_{k+1} 1 = P_kᵀ A_k P_k 1 = P_kᵀ A_k 1 = 0``: Galerkin products keep the
constants in the null space on every level (checked at setup, also for user-supplied operators).
Restricted residuals stay in the range, ``1ᵀ P_kᵀ r = (P_k 1)ᵀ r = 1ᵀ r = 0``; round-off is removed by
projecting every level's right-hand side to zero sum. The coarsest singular operator is factorised
with one node pinned (its row and column removed); for a compatible right-hand side the dropped
equation then holds automatically because the rows sum to zero. Solutions are normalised to zero
*plain nodal* mean ``1ᵀ x = 0`` (use :func:`solvers.fem.remove_mean` with a mass matrix for the
continuous mean).
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .errors import DivergenceError, IncompatibleRHSError, SolverError, SolverInputError
from .fem import node_indices
from .memory import check_memory, galerkin_bytes
from .smoothing import Smoother, make_smoother

__all__ = [
    "Level",
    "MultigridSolver",
    "convergence_factor",
    "galerkin_operators",
    "prune_prolongations",
    "restrict_prolongations",
]

DEFAULT_SMOOTHER = ("gauss_seidel", {"sweep": "symmetric", "iterations": 1})


class ConvergenceWarning(UserWarning):
    """``solve`` stopped at ``maxiter`` before reaching ``tol``."""


def _as_csr(A, name: str) -> sp.csr_matrix:
    if not sp.issparse(A):
        raise SolverInputError(f"{name} must be a scipy sparse matrix, got {type(A).__name__}")
    if np.iscomplexobj(A.data if hasattr(A, "data") else A):
        raise SolverInputError(f"{name} must be real")
    A = sp.csr_matrix(A, dtype=np.float64, copy=True)
    A.sum_duplicates()
    A.sort_indices()
    if not np.all(np.isfinite(A.data)):
        raise SolverInputError(f"{name} contains {np.count_nonzero(~np.isfinite(A.data))} NaN/inf entries")
    return A


def _is_symmetric(A: sp.csr_matrix, rtol: float = 1e-10) -> bool:
    d = abs(A - A.T)
    return (d.max() if d.nnz else 0.0) <= rtol * (abs(A).max() if A.nnz else 1.0)


def galerkin_operators(A: sp.spmatrix, Ps) -> list[sp.csr_matrix]:
    """Galerkin hierarchy ``[A, P_0ᵀ A P_0, P_1ᵀ (P_0ᵀ A P_0) P_1, ...]``.

    The products are symmetrised, ``(Ac + Acᵀ)/2``, to remove the round-off asymmetry of the sparse
    triple product (so the hierarchy is exactly symmetric for CG).

    Parameters
    ----------
    A : (n_0, n_0) sparse
    Ps : list of sparse, ``Ps[k]`` of shape (n_k, n_{k+1})

    Returns
    -------
    list of csr_matrix, length ``len(Ps) + 1``, finest first.

    Raises
    ------
    InsufficientMemoryError
        Before a product whose estimated size (:func:`solvers.memory.galerkin_bytes`) exceeds the
        memory available (``$NESTMG_MEMORY_LIMIT`` or the system's).
    """
    ops = [_as_csr(A, "A")]
    for k, P in enumerate(Ps):
        P = sp.csr_matrix(P, dtype=np.float64)
        if P.shape[0] != ops[-1].shape[0]:
            raise SolverInputError(f"Ps[{k}] has {P.shape[0]} rows but level {k} has {ops[-1].shape[0]} nodes")
        # refuse before allocating a product that would not fit (MemoryError subclass naming the level)
        check_memory(galerkin_bytes(ops[-1], P), f"the Galerkin operator of level {k + 1} (P_{k}ᵀ A_{k} P_{k})")
        Ac = sp.csr_matrix(P.T @ ops[-1] @ P)
        Ac = sp.csr_matrix(0.5 * (Ac + Ac.T))
        Ac.sum_duplicates()
        Ac.sort_indices()
        ops.append(Ac)
    return ops


def _weak_columns(rows: sp.csr_matrix, cols: np.ndarray, min_column_sum: float, level: int) -> np.ndarray:
    """Columns of ``rows[:, cols]`` kept by pruning: column sum >= ``min_column_sum``.

    A weak column is kept anyway when some row has all its weight on weak columns (that finer node
    would otherwise lose its whole interpolation).
    """
    sub = sp.csr_matrix(rows[:, cols])
    cs = np.asarray(sub.sum(axis=0)).ravel()
    weak = cs < min_column_sum
    if not weak.any():
        return cols
    if weak.all():
        raise SolverInputError(f"every coarse node of level {level} has column sum < {min_column_sum}")
    strong_sum = np.asarray(sub[:, ~weak].sum(axis=1)).ravel()
    orphan = np.flatnonzero((np.diff(sub.indptr) > 0) & (strong_sum <= 0))
    if orphan.size:
        weak[np.unique(sub[orphan].indices)] = False
    return cols[~weak]


def restrict_prolongations(Ps, free, coarse_free="support", *, min_column_sum: float = 0.0,
                           renormalize: bool = True, support_only: bool = False):
    """Restrict prolongations to the free (non-Dirichlet) nodes of every level.

    Row ``i`` of ``P_k`` is kept iff node ``i`` is free on level ``k``; column ``j`` iff node ``j`` is
    free on level ``k+1``. On the finest level the free nodes are the caller's; on coarse levels:

    * ``coarse_free="support"`` (default, for Galerkin operators): a coarse node is free iff its column
      still has a non-zero after the row restriction, i.e. its hat function touches a free finer node.
      All other coarse nodes would give an all-zero row and column in ``Pᵀ A P`` (a singular coarse
      operator). This keeps every useful coarse node, including cage nodes outside the fine domain and
      coarse boundary nodes, and is always correct for Galerkin operators. (Keeping *all* coarse nodes
      is not: on the Kuhn cube the nodes on 6 of the 12 cube edges, including 6 of the 8 corners, touch
      no interior fine node, because the Kuhn tets along those edges have no interior fine vertex.)
    * a list of per-level index arrays or boolean masks (length ``len(Ps)``, level 1 first): e.g. the
      coarse interior nodes, which is what re-discretised coarse operators with Dirichlet boundary
      on a same-domain hierarchy need (restrict those operators with the returned indices too).

    This is the one restriction and pruning path of the project (``nestmg.problems.setup_problem``
    and :func:`prune_prolongations` call it).

    Parameters
    ----------
    Ps : list of sparse, ``Ps[k]`` of shape (n_k, n_{k+1})
    free : (m_0,) int array_like or (n_0,) bool mask
        Free nodes of the finest level.
    coarse_free : "support" or list of array_like
    min_column_sum : float
        ``coarse_free="support"`` only: also drop coarse nodes whose (row-restricted) column sums to
        less than this. Cage nodes that one or two fine nodes reach with weights ~1e-3 add nothing to
        the coarse space but make ``P`` rank-deficient (``Pᵀ A P`` singular beyond its null space) and
        denser. A weak column is kept when some row has all its weight on weak columns. 0 (default)
        keeps every reached node.
    renormalize : bool
        After pruning, rescale the rows that lost weight to their previous sum (1 for interpolation:
        constants stay reproduced, as ``nullspace="constant"`` needs).
    support_only : bool
        With a list ``coarse_free``: keep only the listed nodes that the restricted rows reach.

    Returns
    -------
    Ps_free : list of csr_matrix, ``Ps_free[k]`` of shape (len(frees[k]), len(frees[k+1]))
    frees : list of (m_k,) int64 arrays, sorted free node indices of every level (finest first)

    Examples
    --------
    >>> from solvers.gallery import kuhn_cube_hierarchy
    >>> from solvers.fem import boundary_nodes
    >>> meshes, Ps = kuhn_cube_hierarchy(4, 2)
    >>> V, T = meshes[0]
    >>> interior = np.setdiff1d(np.arange(len(V)), boundary_nodes(T))
    >>> Pf, frees = restrict_prolongations(Ps, interior)
    >>> Pf[0].shape    # 27 fine interior nodes; the 12 coarse nodes on 6 cube edges touch none
    (27, 15)
    """
    Ps = [sp.csr_matrix(P, dtype=np.float64) for P in Ps]

    def _idx(f, n, what):
        f = np.unique(node_indices(f, n, what))
        if f.size == 0:
            raise SolverInputError(f"{what}: no free node")
        return f

    if not Ps:
        raise SolverInputError("restrict_prolongations needs at least one prolongation")
    if isinstance(coarse_free, str) and coarse_free != "support":
        raise SolverInputError(f"coarse_free must be 'support' or a list of index arrays, got {coarse_free!r}")
    if not isinstance(coarse_free, str) and len(coarse_free) != len(Ps):
        raise SolverInputError(f"coarse_free needs {len(Ps)} entries (levels 1..), got {len(coarse_free)}")
    frees = [_idx(free, Ps[0].shape[0], "free")]
    out = []
    for k, P in enumerate(Ps):
        if P.shape[0] != (Ps[k - 1].shape[1] if k else P.shape[0]):
            raise SolverInputError(f"Ps[{k}] has {P.shape[0]} rows, level {k} has {Ps[k - 1].shape[1]} nodes")
        Pr = P[frees[k]]
        Pr.eliminate_zeros()
        support = np.flatnonzero(np.diff(Pr.tocsc().indptr) > 0)
        pruning = isinstance(coarse_free, str) and min_column_sum > 0
        if isinstance(coarse_free, str):
            cf = support
            if pruning and cf.size:
                cf = _weak_columns(Pr, cf, min_column_sum, k + 1)
        else:
            cf = _idx(coarse_free[k], P.shape[1], f"coarse_free[{k}]")
            if support_only:
                cf = np.intersect1d(cf, support)
        if cf.size == 0:
            raise SolverInputError(f"level {k + 1}: no coarse node touches a free node of level {k}")
        before = np.asarray(Pr.sum(axis=1)).ravel() if pruning and renormalize else None
        Pr = sp.csr_matrix(Pr[:, cf])
        if before is not None:
            after = np.asarray(Pr.sum(axis=1)).ravel()
            scale = np.divide(before, after, out=np.ones_like(after), where=after != 0)
            Pr = sp.csr_matrix(sp.diags(scale) @ Pr)
        Pr.sort_indices()
        out.append(Pr)
        frees.append(cf)
    return out, frees


def prune_prolongations(Ps, min_column_sum: float = 0.2, renormalize: bool = True):
    """Drop coarse nodes that carry almost no interpolation weight.

    A coarse node whose column of ``P_k`` sums to less than ``min_column_sum`` (e.g. a cage node that
    touches one or two fine nodes with barycentric weights ~1e-3) adds almost nothing to the coarse
    space but makes ``Pᵀ A P`` ill-conditioned or singular (rank-deficient ``P``) and denser. Dropping
    the column removes the node from level ``k+1``, so the rows of ``P_{k+1}`` for that node go too.
    Measured on a 4-level nested torus hierarchy (TetGen, 7.9k fine nodes): ``min_column_sum=0.2``
    removed every extra null vector of the Galerkin operators and cut the operator complexity from
    3.07 to 2.33 (Dirichlet) and 2.56 to 2.37 (Neumann) with unchanged convergence factors.

    Parameters
    ----------
    Ps : list of sparse, ``Ps[k]`` of shape (n_k, n_{k+1})
    min_column_sum : float
        Keep coarse node ``j`` iff ``sum_i P_k[i, j] >= min_column_sum`` (a fully interior node of a
        2:1 refinement in 3D sums to about 8; nodes near a boundary or the cage to much less).
    renormalize : bool
        Rescale the rows that lost weight to sum to what they summed to before (1 for interpolation), so
        constants stay reproduced (needed for ``nullspace="constant"``). A weak column is kept when a
        row would otherwise lose all its weight (see :func:`restrict_prolongations`, which this calls
        with every fine node free).

    Returns
    -------
    Ps_pruned : list of csr_matrix
    kept : list of (m_k,) int64 arrays
        Kept node indices of levels 1..L (into the columns of the input ``Ps[k]``).
    """
    if not Ps:
        raise SolverInputError("prune_prolongations needs at least one prolongation")
    n0 = sp.csr_matrix(Ps[0]).shape[0]
    out, frees = restrict_prolongations(Ps, np.arange(n0), min_column_sum=min_column_sum, renormalize=renormalize)
    return out, frees[1:]


def convergence_factor(residuals, last: int = 5) -> float:
    """Asymptotic convergence factor from a residual history.

    The geometric mean of the ratios ``r[i+1]/r[i]`` over the last ``last`` cycles,
    ``(r[-1] / r[-1-last]) ** (1/last)``, ignoring trailing entries that already sit at round-off
    level (``r < 1e-14 · r[0]``), where ratios are noise. Uses the whole history if it is shorter.

    Parameters
    ----------
    residuals : sequence of float
        Residual norms (absolute or relative), initial residual first.
    last : int

    Returns
    -------
    float (``nan`` if fewer than two usable entries)
    """
    r = np.asarray(residuals, dtype=np.float64).ravel()
    if r.size and r[0] > 0:
        r = r[: max(np.count_nonzero(r >= 1e-14 * r[0]), 1)] if np.all(np.isfinite(r)) else r
    if r.size < 2 or r[0] == 0:
        return float("nan")
    m = min(int(last), r.size - 1)
    if r[-1 - m] == 0:
        return float("nan")
    return float((r[-1] / r[-1 - m]) ** (1.0 / m))


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
    ``method="regularized"``: SuperLU of ``A + 1e-9 diag(A)`` (cheap and sparse; exact on the range for
    consistent right-hand sides). ``method="auto"``: SuperLU, then the regularised LU, then the
    pseudo-inverse when the level has at most ``pinv_max`` unknowns.
    """

    def __init__(self, A: sp.csr_matrix, nullspace: str | None, level: int, method: str = "auto",
                 pinv_max: int = 3000, rtol: float = 1e-10):
        self.n = A.shape[0]
        self.nullspace = nullspace
        self.pin = None
        self.lu = None
        self.Q = None
        t0 = time.perf_counter()
        if method not in ("auto", "pinv", "splu", "regularized"):
            raise SolverInputError(
                f"coarse_solver must be 'auto', 'pinv', 'splu' or 'regularized', got {method!r}")
        self.fallback = False
        if method == "auto":
            try:
                self._setup(A, nullspace, level, "splu", rtol)
            except SolverError:
                self.fallback = True
                self.pin, self.lu = None, None
                try:
                    self._setup(A, nullspace, level, "regularized", rtol)
                except SolverError:
                    if self.n > pinv_max:
                        raise
                    self.pin, self.lu = None, None
                    self._setup(A, nullspace, level, "pinv", rtol)
        else:
            self._setup(A, nullspace, level, method, rtol)
        self.seconds = time.perf_counter() - t0

    def _setup(self, A, nullspace, level, method, rtol):
        self.method = method
        expected = 1 if nullspace == "constant" else 0
        if method == "regularized":
            # sparse LU of A + eps diag(A): for a consistent right-hand side (b orthogonal to ker A, as
            # the restricted residual P^T r is) the range component is exact to O(eps cond) and null
            # components are irrelevant -- they are invisible after prolongation (ker of a Galerkin
            # operator = ker P, plus the constants, which are projected out). Validated by the residual.
            eps = 1e-9
            Ar = sp.csc_matrix(A + eps * sp.diags(np.maximum(A.diagonal(), np.finfo(float).tiny)))
            try:
                self.lu = spla.splu(Ar, permc_spec="MMD_AT_PLUS_A")
            except RuntimeError as e:
                raise SolverError(f"coarsest operator (level {level}, n={self.n}): regularised LU failed: {e}") from None
            self.nnz = int(self.lu.L.nnz + self.lu.U.nnz)
            self.nullity = -1  # not computed (at least the expected one)
            v = np.random.default_rng(0).standard_normal(self.n)
            b = A @ v
            with np.errstate(all="ignore"):
                err = np.linalg.norm(A @ self(b) - b) / np.linalg.norm(b)
            if not err < 1e-6:
                raise SolverError(f"coarsest operator (level {level}, n={self.n}): regularised LU residual {err:.1e}")
            return
        if method == "pinv":
            Ad = A.toarray()
            if _is_symmetric(A):
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
            if self.n > 1 or nullspace != "constant":
                try:
                    self.lu = spla.splu(sp.csc_matrix(Af), permc_spec="MMD_AT_PLUS_A")
                except RuntimeError as e:
                    raise SolverError(
                        f"coarsest operator (level {level}, n={self.n}) is singular: {e}; use coarse_solver='pinv'"
                    ) from None
            self.nnz = 0 if self.lu is None else int(self.lu.L.nnz + self.lu.U.nnz)
            self.nullity = expected
            # validate: an operator singular beyond the expected null space gives an LU whose solutions
            # satisfy A x = b but carry huge null-space components, without any error. The solution of
            # A x = A v must be v itself (up to a constant for Neumann).
            v = np.random.default_rng(0).standard_normal(self.n)
            if nullspace == "constant":
                v -= v.mean()
            with np.errstate(all="ignore"):
                err = np.linalg.norm(self(A @ v) - v) / np.linalg.norm(v)
            if not err < 1e-6:
                raise SolverError(
                    f"coarsest operator (level {level}, n={self.n}) is numerically singular beyond the "
                    f"expected null space (LU solve error {err:.1e} on a consistent right-hand side). With "
                    "Galerkin operators this means a rank-deficient prolongation (coarse nodes whose hat "
                    "functions are linearly dependent on the finer nodes); use coarse_solver='pinv' "
                    "(or more levels so the coarsest is small enough for it), or drop those coarse nodes "
                    "(prune_prolongations)"
                )

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


@dataclass
class Level:
    """One level of the hierarchy (a bare struct, as pyamg's).

    Attributes
    ----------
    A : (n_k, n_k) csr_matrix
    P : (n_k, n_{k+1}) csr_matrix or None on the coarsest level
    R : (n_{k+1}, n_k) csr_matrix (``Pᵀ``) or None
    presmoother, postsmoother : Smoother or None on the coarsest level
    """

    A: sp.csr_matrix
    P: sp.csr_matrix | None = None
    R: sp.csr_matrix | None = None
    presmoother: Smoother | None = None
    postsmoother: Smoother | None = None
    info: dict = field(default_factory=dict)


class MultigridSolver:
    """Multigrid hierarchy with ``solve`` and ``aspreconditioner`` (modelled on pyamg's MultilevelSolver).

    Parameters
    ----------
    A : (n_0, n_0) sparse matrix
        Fine operator (symmetric positive (semi-)definite for the theory and for CG).
    Ps : list of sparse matrices
        ``Ps[k]`` of shape ``(n_k, n_{k+1})`` maps level ``k+1`` to level ``k`` (rows sum to 1 for
        interpolation; restricted rows near Dirichlet nodes may sum to less). May be empty (one level,
        direct solve).
    coarse : "galerkin" or list of sparse
        ``"galerkin"`` (default): ``A_{k+1} = P_kᵀ A_k P_k``. A list ``[A_1, ..., A_L]`` (shapes
        ``(n_k, n_k)``): the caller's coarse operators, e.g. re-discretised or volume-fraction weighted
        ones (``nestmg.problems.setup_problem(coarse=...)`` makes them). ``coarse_operators=`` is the
        deprecated spelling of the list form.
    coarse_scaling : None or "energy"
        ``"energy"``: scale every coarse-grid correction ``e = P x_c`` by the energy-optimal
        ``α = (rᵀ e) / (eᵀ A e)`` (minimises the energy norm of the error along ``e``; one extra
        SpMV per level and cycle). It corrects coarse operators that are uniformly too soft or too
        stiff (re-discretisation on a cage: a larger domain); with Galerkin operators ``α = 1``
        exactly in exact arithmetic for a single correction. Makes the cycle a (mildly) non-linear
        preconditioner; ``solve(accel="cg")`` then uses the flexible (Polak–Ribière) CG update.
    presmoother, postsmoother : str or (str, dict)
        See :func:`solvers.smoothing.make_smoother`. Default symmetric Gauss–Seidel, one sweep each:
        V(1,1). ``postsmoother=None`` (default) means the adjoint of the presmoother: the same smoother,
        with a forward Gauss–Seidel sweep turned into a backward one, so the cycle is symmetric and can
        precondition CG. An explicit non-adjoint pair (e.g. forward GS on both sides) is allowed for
        stationary cycling; ``solve(accel="cg")`` then warns.
    nullspace : None or "constant"
        ``"constant"`` for pure Neumann operators (see module docstring): checks ``A_k 1 = 0`` on every
        level, projects right-hand sides and returns zero-mean solutions.
    coarse_solver : {"auto", "pinv", "splu", "regularized"}
        Coarsest-level direct solver, set up once. ``"splu"``: SuperLU (one node pinned for Neumann),
        validated at setup on a random consistent right-hand side; raises :class:`SolverError` if the
        operator is singular beyond the expected null space. ``"regularized"``: SuperLU of
        ``A + 1e-9 diag(A)``, right for consistent right-hand sides also with extra null vectors
        (validated by the residual). ``"pinv"``: dense pseudo-inverse (robust to extra null vectors
        from rank-deficient prolongations; O(n³) setup). ``"auto"`` (default): SuperLU, then the
        regularised LU when validation fails, then the pseudo-inverse if the coarsest level has at most
        ``pinv_max`` unknowns (the fallback is reported by ``repr``). Measured on a 550k-tet bunny
        Galerkin hierarchy (2k-node coarsest level, 3 extra null vectors): regularised 3 s setup,
        pseudo-inverse 31-54 s, identical residual histories.
    pinv_max : int
        Size limit of the ``"auto"`` fallback (dense eigh of 2000 unknowns: ~1–4 s on this machine).

    Attributes
    ----------
    levels : list of Level
    setup_seconds : float

    Examples
    --------
    >>> from solvers.gallery import kuhn_cube_hierarchy
    >>> from solvers.fem import stiffness_matrix, boundary_nodes
    >>> meshes, Ps = kuhn_cube_hierarchy(8, 3)
    >>> V, T = meshes[0]
    >>> K = stiffness_matrix(V, T)
    >>> free = np.setdiff1d(np.arange(len(V)), boundary_nodes(T))
    >>> Pf, _ = restrict_prolongations(Ps, free)
    >>> ml = MultigridSolver(K[free][:, free], Pf)
    >>> res = []
    >>> x = ml.solve(np.ones(len(free)), tol=1e-8, residuals=res)
    >>> len(res) < 15, res[-1] < 1e-8
    (True, True)
    """

    def __init__(
        self,
        A,
        Ps,
        *,
        coarse="galerkin",
        coarse_scaling: str | None = None,
        coarse_operators=None,
        presmoother=DEFAULT_SMOOTHER,
        postsmoother=None,
        nullspace: str | None = None,
        coarse_solver: str = "auto",
        pinv_max: int = 3000,
    ):
        t0 = time.perf_counter()
        if nullspace not in (None, "constant"):
            raise SolverInputError(f"nullspace must be None or 'constant', got {nullspace!r}")
        self.nullspace = nullspace
        A = _as_csr(A, "A")
        if A.shape[0] != A.shape[1]:
            raise SolverInputError(f"A must be square, got {A.shape}")
        Ps = [_as_csr(P, f"Ps[{k}]") for k, P in enumerate(Ps)]
        n = A.shape[0]
        for k, P in enumerate(Ps):
            if P.shape[0] != n:
                raise SolverInputError(f"Ps[{k}] has shape {P.shape}; expected {n} rows (level {k} size)")
            if P.shape[1] == 0 or P.shape[1] >= P.shape[0]:
                raise SolverInputError(f"Ps[{k}] has shape {P.shape}: the coarse level must be smaller and non-empty")
            if nullspace == "constant":
                rs = np.asarray(P.sum(axis=1)).ravel()
                if np.abs(rs - 1).max() > 1e-8:
                    raise SolverInputError(
                        f"nullspace='constant' needs prolongations reproducing constants, but rows of Ps[{k}] "
                        f"sum to values in [{rs.min():.3g}, {rs.max():.3g}]"
                    )
            n = P.shape[1]
        if coarse_operators is not None:
            warnings.warn("MultigridSolver(coarse_operators=...) is deprecated; use coarse=[A_1, ...]",
                          DeprecationWarning, stacklevel=2)
            if not (isinstance(coarse, str) and coarse == "galerkin"):
                raise SolverInputError("give the coarse operators once: coarse=[...] (coarse_operators is deprecated)")
            coarse = coarse_operators
        if coarse_scaling not in (None, "energy"):
            raise SolverInputError(f"coarse_scaling must be None or 'energy', got {coarse_scaling!r}")
        self.coarse_scaling = coarse_scaling
        if isinstance(coarse, str):
            if coarse != "galerkin":
                raise SolverInputError(
                    f"coarse must be 'galerkin' or a list of coarse operators, got {coarse!r} (named coarse "
                    "operators such as 'weighted' are built by nestmg.problems.setup_problem)")
            if any((np.diff(P.tocsc().indptr) == 0).any() for P in Ps):
                # coarse nodes that reach no finer node (e.g. cage nodes of a hierarchy's raw P) would give
                # empty rows of P^T A P; as Galerkin levels they add nothing, so they are dropped
                Ps, _ = restrict_prolongations(Ps, np.arange(A.shape[0]))
            ops = galerkin_operators(A, Ps)
            self.coarse = "galerkin"
        else:
            coarse_operators = list(coarse)
            if len(coarse_operators) != len(Ps):
                raise SolverInputError(f"coarse_operators needs {len(Ps)} matrices, got {len(coarse_operators)}")
            ops = [A] + [_as_csr(Ac, f"coarse_operators[{k}]") for k, Ac in enumerate(coarse_operators)]
            for k, (P, Ac) in enumerate(zip(Ps, ops[1:])):
                if Ac.shape != (P.shape[1], P.shape[1]):
                    raise SolverInputError(
                        f"coarse_operators[{k}] has shape {Ac.shape}, expected {(P.shape[1], P.shape[1])}"
                    )
            self.coarse = "given"
        for k, Ak in enumerate(ops):
            d = Ak.diagonal()
            if np.any(d <= 0):
                bad = np.flatnonzero(d <= 0)
                raise SolverError(
                    f"level {k} operator has {bad.size} rows with diagonal <= 0 (first: node {bad[0]}); "
                    "a coarse node that touches no free fine node gives an empty row: restrict the "
                    "prolongations with restrict_prolongations(Ps, free)"
                )
            if nullspace == "constant":
                r = np.abs(Ak @ np.ones(Ak.shape[0])).max()
                if r > 1e-9 * np.abs(Ak).sum(axis=1).max():  # relative to ||A_k||_inf
                    raise SolverError(
                        f"nullspace='constant' but the level {k} operator does not annihilate constants "
                        f"(max |A_{k} 1| = {r:.3e})"
                    )
        pre_spec = presmoother
        post_spec = _adjoint_spec(presmoother) if postsmoother is None else postsmoother
        self.levels: list[Level] = []
        for k, Ak in enumerate(ops):
            if k < len(Ps):
                P = Ps[k]
                pre = make_smoother(Ak, pre_spec)
                # a self-adjoint smoother is shared (one spectral radius estimate per level)
                post = pre if post_spec is pre_spec else make_smoother(Ak, post_spec)
                lvl = Level(Ak, P, sp.csr_matrix(P.T), pre, post)
            else:
                lvl = Level(Ak)
            self.levels.append(lvl)
        self._coarse_solver = _CoarseSolver(ops[-1], nullspace, len(ops) - 1, coarse_solver, pinv_max)
        #: null vectors of the coarsest operator (1 expected for Neumann, 0 for Dirichlet; more means a
        #: rank-deficient prolongation, handled by the pseudo-inverse)
        self.coarse_nullity = self._coarse_solver.nullity
        self.symmetric = all(_is_symmetric(L.A) for L in self.levels)
        # a cycle is a symmetric operator iff A_k are symmetric and post = adjoint(pre) on every level
        self.symmetric_cycle = self.symmetric and (
            len(self.levels) == 1 or _smoothers_adjoint(self.levels[0].presmoother, self.levels[0].postsmoother)
        )
        self.setup_seconds = time.perf_counter() - t0

    # ------------------------------------------------------------------ description
    def __repr__(self) -> str:
        cs = self._coarse_solver
        fallback = " (fallback: SuperLU failed validation)" if cs.fallback else ""
        rows = [
            ("Number of levels", f"{len(self.levels)}"),
            ("Coarse operators", self.coarse),
            ("Smoothers (pre/post)", self._smoother_desc()),
            ("Null space", f"{self.nullspace}"),
            ("Coarsest solver", (f"{cs.method}{fallback} (null vectors: "
                                 f"{self.coarse_nullity if self.coarse_nullity >= 0 else 'not computed'})")),
            ("Operator complexity", f"{self.operator_complexity():.3f}"),
            ("Grid complexity", f"{self.grid_complexity():.3f}"),
            ("Cycle complexity (V)", f"{self.cycle_complexity('V'):.3f} fine SpMVs"),
        ]
        lines = ["MultigridSolver"] + [f"{k + ':':22s}{v}" for k, v in rows]
        lines.append("  level   unknowns     nonzeros   nnz/row     nnz(P)")
        for k, L in enumerate(self.levels):
            n = L.A.shape[0]
            nnzp = "" if L.P is None else f"{L.P.nnz:10d}"
            lines.append(f"{k:7d} {n:10d} {L.A.nnz:12d} {L.A.nnz / n:9.1f} {nnzp:>10}")
        return "\n".join(lines)

    def _smoother_desc(self) -> str:
        if len(self.levels) < 2:
            return "none (direct solve)"
        L = self.levels[0]
        return f"{L.presmoother.name}{L.presmoother.params} / {L.postsmoother.name}{L.postsmoother.params}"

    def operator_complexity(self) -> float:
        """``sum_k nnz(A_k) / nnz(A_0)``."""
        return sum(L.A.nnz for L in self.levels) / self.levels[0].A.nnz

    def grid_complexity(self) -> float:
        """``sum_k n_k / n_0``."""
        return sum(L.A.shape[0] for L in self.levels) / self.levels[0].A.shape[0]

    def _visits(self, cycle: str) -> np.ndarray:
        """How many times each level is smoothed (or, coarsest, solved) in one cycle."""
        counts = np.zeros(len(self.levels))

        def walk(k, c):
            counts[k] += 1
            if k == len(self.levels) - 1:
                return
            if k + 1 == len(self.levels) - 1:
                counts[k + 1] += 1
                return
            if c == "V":
                walk(k + 1, "V")
            elif c == "W":
                walk(k + 1, "W")
                walk(k + 1, "W")
            else:
                walk(k + 1, "F")
                walk(k + 1, "V")

        walk(0, cycle)
        return counts

    def cycle_complexity(self, cycle: str = "V") -> float:
        """Work of one cycle in units of one SpMV with the fine operator (``nnz(A_0)`` flops pairs).

        Per visit of level ``k``: pre- and post-smoothing (``Smoother.work`` SpMVs each), one residual
        SpMV, restriction and interpolation (``2 nnz(P_k)``); the coarsest level costs the two
        triangular solves (``nnz(L) + nnz(U)``). Vector updates are not counted. Measured wall-clock
        cost is higher in Python (see the report in the docs / benchmarks).
        """
        cycle = self._check_cycle(cycle)
        visits = self._visits(cycle)
        work = 0.0
        for k, L in enumerate(self.levels):
            if L.P is None:
                w = self._coarse_solver.nnz
            else:
                w = (L.presmoother.work + L.postsmoother.work + 1.0) * L.A.nnz + 2.0 * L.P.nnz
            work += visits[k] * w
        return float(work / self.levels[0].A.nnz)

    # ------------------------------------------------------------------ cycling
    @staticmethod
    def _check_cycle(cycle: str) -> str:
        if cycle not in ("V", "W", "F"):
            raise SolverInputError(f"cycle must be 'V', 'W' or 'F', got {cycle!r}")
        return cycle

    def _cycle(self, k: int, x: np.ndarray, b: np.ndarray, cycle: str, check: bool = False) -> None:
        """One cycle on level ``k``: x is updated in place."""
        L = self.levels[k]
        A = L.A
        L.presmoother(A, x, b)
        if check:
            self._check_finite(x, k, "pre-smoothing")
        r = b - A @ x
        bc = L.R @ r
        if self.nullspace == "constant":
            bc -= bc.mean()
        if check:
            self._check_finite(bc, k + 1, "restriction")
        if k + 1 == len(self.levels) - 1:
            xc = self._coarse_solver(bc)
            if check:
                self._check_finite(xc, k + 1, "coarsest direct solve")
        else:
            xc = np.zeros_like(bc)
            if cycle == "V":
                self._cycle(k + 1, xc, bc, "V", check)
            elif cycle == "W":
                self._cycle(k + 1, xc, bc, "W", check)
                self._cycle(k + 1, xc, bc, "W", check)
            else:  # F: an F-cycle then a V-cycle on the coarser level
                self._cycle(k + 1, xc, bc, "F", check)
                self._cycle(k + 1, xc, bc, "V", check)
        e = L.P @ xc
        if self.coarse_scaling == "energy":
            den = float(e @ (A @ e))
            if den > 0:
                e *= float(r @ e) / den
        x += e
        if check:
            self._check_finite(x, k, "coarse-grid correction")
        L.postsmoother(A, x, b)
        if check:
            self._check_finite(x, k, "post-smoothing")

    @staticmethod
    def _check_finite(v, level, stage):
        if not np.all(np.isfinite(v)):
            raise _NonFinite(level, stage)

    def _locate_nan(self, x_prev, b, cycle) -> tuple[int | None, str]:
        """Re-run one cycle with checks on every level to name where NaN/inf first appears."""
        try:
            if len(self.levels) == 1:
                self._check_finite(self._coarse_solver(b), 0, "direct solve")
            else:
                self._cycle(0, x_prev.copy(), b, cycle, check=True)
        except _NonFinite as e:
            return e.level, e.stage
        return None, "unknown (not reproducible)"

    def _one(self, x, b, cycle):
        if len(self.levels) == 1:
            x[:] = self._coarse_solver(b)
        else:
            self._cycle(0, x, b, cycle)

    def _prepare_rhs(self, b, project: bool) -> np.ndarray:
        n = self.levels[0].A.shape[0]
        b = np.asarray(b)
        if b.ndim == 2 and b.shape[1] == 1:
            b = b[:, 0]
        if b.shape != (n,):
            raise SolverInputError(f"b must have shape ({n},), got {b.shape}")
        b = np.array(b, dtype=np.float64)  # a copy: never touch the caller's array
        if not np.all(np.isfinite(b)):
            raise SolverInputError(f"b contains {np.count_nonzero(~np.isfinite(b))} NaN/inf entries")
        if self.nullspace == "constant":
            if project:
                b -= b.mean()
            else:
                from .fem import check_compatible

                check_compatible(b)
        return b

    def solve(
        self,
        b,
        x0=None,
        tol: float = 1e-8,
        maxiter: int = 100,
        cycle: str = "V",
        accel: str | None = None,
        residuals: list | None = None,
        *,
        project: bool = False,
        divtol: float = 1e5,
        return_info: bool = False,
    ):
        """Solve ``A x = b`` by multigrid cycles (or CG preconditioned by one cycle).

        Parameters
        ----------
        b : (n_0,) array_like
        x0 : (n_0,) array_like, optional (default zeros)
        tol : float
            Stop when ``||b - A x|| <= tol ||b||`` (2-norms).
        maxiter : int
            Maximum number of cycles (or CG iterations).
        cycle : {"V", "W", "F"}
        accel : None or "cg"
            ``"cg"``: conjugate gradients (pyamg.krylov.cg) preconditioned by one cycle from zero.
        residuals : list, optional
            Cleared and filled with the relative residuals ``||b - A x_i|| / ||b||``, ``i = 0..iters``
            (``residuals[0]`` is that of ``x0``).
        project : bool
            With ``nullspace="constant"``: remove the mean of an incompatible ``b`` instead of raising
            :class:`IncompatibleRHSError`.
        divtol : float
            Raise :class:`DivergenceError` when the residual exceeds ``divtol`` times the initial one.
        return_info : bool
            Also return a dict ``{iterations, converged, residuals, factor, seconds}``.

        Returns
        -------
        x : (n_0,) float64 (zero plain mean when ``nullspace="constant"``)
        info : dict, only with ``return_info=True``

        Raises
        ------
        DivergenceError
            NaN/inf (naming the cycle and the level where it first appeared) or residual growth.
        IncompatibleRHSError
            Neumann problem with ``sum(b) != 0`` and ``project=False``.
        """
        cycle = self._check_cycle(cycle)
        if accel not in (None, "cg"):
            raise SolverInputError(f"accel must be None or 'cg', got {accel!r}")
        maxiter = int(maxiter)
        if maxiter < 0:
            raise SolverInputError(f"maxiter must be >= 0, got {maxiter}")
        b = self._prepare_rhs(b, project)
        n = b.size
        A = self.levels[0].A
        if x0 is None:
            x = np.zeros(n)
        else:
            x = np.array(np.asarray(x0).reshape(-1), dtype=np.float64)
            if x.shape != (n,) or not np.all(np.isfinite(x)):
                raise SolverInputError(f"x0 must be a finite array of shape ({n},)")
        t0 = time.perf_counter()
        normb = float(np.linalg.norm(b))
        hist: list[float] = []
        if normb == 0.0:
            x[:] = 0.0
            hist = [0.0]
        elif accel == "cg":
            from .krylov import pcg

            if not self.symmetric_cycle:
                warnings.warn(
                    "accel='cg' with a non-symmetric cycle (non-symmetric operators or non-adjoint pre/post "
                    "smoothers): CG may stall; use adjoint smoothers (postsmoother=None)",
                    stacklevel=2,
                )

            res = pcg(A, b, M=self.aspreconditioner(cycle), x0=x, tol=tol, maxiter=maxiter,
                      nullspace=self.nullspace, divtol=divtol, flexible=self.coarse_scaling is not None)
            x, hist = res.x, res.residuals
            if res.nonfinite:
                level, stage = self._locate_nan(np.zeros(n), b, cycle)
                raise DivergenceError(
                    f"MG-preconditioned CG produced NaN/inf in preconditioner {cycle}-cycle {res.iterations}; first "
                    f"non-finite value on level {level} during {stage}",
                    cycle=res.iterations, level=level, residuals=hist,
                )
        else:
            rel = float(np.linalg.norm(b - A @ x)) / normb
            hist = [rel]
            it = 0
            while rel > tol and it < maxiter:
                x_prev = x.copy()
                self._one(x, b, cycle)
                it += 1
                rel = float(np.linalg.norm(b - A @ x)) / normb
                hist.append(rel)
                if not np.isfinite(rel) and np.all(np.isfinite(x)):  # finite iterate, overflowing norm
                    raise DivergenceError(
                        f"{cycle}-cycle {it} diverges: the residual norm overflowed (max |x| = "
                        f"{np.abs(x).max():.3g}; relative residual before this cycle {hist[-2]:.3g})",
                        cycle=it, level=None, residuals=hist,
                    )
                if not np.isfinite(rel):
                    level, stage = self._locate_nan(x_prev, b, cycle)
                    raise DivergenceError(
                        f"{cycle}-cycle {it} produced NaN/inf; first non-finite value on level {level} "
                        f"during {stage}",
                        cycle=it, level=level, residuals=hist,
                    )
                if rel > divtol * hist[0]:
                    raise DivergenceError(
                        f"{cycle}-cycle {it} diverges: residual grew by {rel / hist[0]:.3g} (> divtol={divtol:g}); "
                        f"recent factor per cycle {convergence_factor(hist, 3):.3g}. Inconsistent coarse "
                        "operators or prolongations (e.g. extrapolation outside the coarse mesh)?",
                        cycle=it, level=None, residuals=hist,
                    )
        if self.nullspace == "constant":
            x -= x.mean()
        seconds = time.perf_counter() - t0
        converged = hist[-1] <= tol
        if not converged:
            warnings.warn(
                f"multigrid stopped after {len(hist) - 1} iterations at relative residual {hist[-1]:.3e} > tol={tol:g}",
                ConvergenceWarning,
                stacklevel=2,
            )
        if residuals is not None:
            residuals[:] = hist
        if return_info:
            return x, {
                "iterations": len(hist) - 1,
                "converged": bool(converged),
                "residuals": list(hist),
                "factor": convergence_factor(hist),
                "seconds": seconds,
            }
        return x

    def aspreconditioner(self, cycle: str = "V") -> spla.LinearOperator:
        """One cycle from a zero initial guess, as a ``scipy.sparse.linalg.LinearOperator``.

        Usable as ``M=`` in ``scipy.sparse.linalg.cg``. Symmetric positive definite when the operators
        are SPD and the pre/post smoothers are adjoint. With ``nullspace="constant"`` input and output are
        projected to zero mean.
        """
        cycle = self._check_cycle(cycle)
        n = self.levels[0].A.shape[0]

        def matvec(b):
            b = np.asarray(b, dtype=np.float64).reshape(-1)
            if self.nullspace == "constant":
                b = b - b.mean()
            x = np.zeros(n)
            self._one(x, b, cycle)
            if self.nullspace == "constant":
                x -= x.mean()
            return x

        return spla.LinearOperator((n, n), matvec=matvec, rmatvec=matvec, dtype=np.float64)


def _spec_parts(spec):
    if isinstance(spec, str):
        return spec, {}
    if isinstance(spec, (tuple, list)) and len(spec) == 2 and isinstance(spec[0], str):
        return spec[0], dict(spec[1] or {})
    return None, None


def _adjoint_spec(spec):
    """Spec of the adjoint smoother: forward <-> backward Gauss-Seidel, everything else unchanged."""
    name, opts = _spec_parts(spec)
    if name == "gauss_seidel":
        sweep = opts.get("sweep", "forward")
        opts["sweep"] = {"forward": "backward", "backward": "forward"}.get(sweep, sweep)
        return (name, opts)
    return spec


def _smoothers_adjoint(pre: Smoother, post: Smoother) -> bool:
    if pre.name != post.name:
        return False
    if pre.name in ("gauss_seidel", "symmetric_gauss_seidel"):
        flip = {"forward": "backward", "backward": "forward", "symmetric": "symmetric"}
        a, b = pre.params, post.params
        return flip[a["sweep"]] == b["sweep"] and a["iterations"] == b["iterations"] and a["omega"] == b["omega"]
    return pre.params == post.params


class _NonFinite(Exception):
    def __init__(self, level, stage):
        super().__init__(f"non-finite value on level {level} during {stage}")
        self.level, self.stage = level, stage


# re-exported for convenience
__all__ += ["ConvergenceWarning", "IncompatibleRHSError"]
