"""Exact subdomain solves where a level's slow modes live (adaptive local solves).

A cycle's slow modes are sometimes not a few global vectors but a whole family confined to one small
region: a thin lip of a shape, one or two elements thick, whose elements are flat. There the point smoother
is weak across the lip and the coarse level (whose elements span the lip and its surroundings) does not see
it either; a few of the family are deflated (:mod:`solvers.deflation`) and the next ones, just below the
deflation goal, set the factor. An exact solve on the region removes the whole family at once: a
multiplicative Schwarz step ``x_S += A_SS⁻¹ (b - A x)_S`` (Brandt's local relaxation taken to its limit),
placed like the deflation after the pre-smoother and before the post-smoother so that the cycle stays
symmetric.

:func:`slow_region` finds the region from the probe's slow Ritz vectors ``Z`` (``Zᵀ A Z = I``): the nodes
that carry :data:`REGION_SHARE` of their summed energy ``Σ_k |z_k,i (A z_k)_i|``, plus their neighbours,
and only when that is a small part of the level (:data:`REGION_MAX_FRACTION`, :data:`REGION_MAX_NODES`);
global slow modes are left to the deflation.

:func:`power_probe` and :func:`concentrated_region` find such a region without the probe's Lanczos steps (a
few cycles, for the finest level, whose Lanczos probe costs about a solve): a random error after a few
cycles, ``e_k = E^k e_0``, is dominated by the slow modes; when :data:`POWER_SHARE` of its energy
``|e_i (A e)_i|`` sits on at most :data:`POWER_CORE_FRACTION` of the unknowns, those nodes and their
neighbours are the region.

:func:`strongly_coupled` finds, without any cycle, the unknowns a point smoother updates as if they were one:
those with a coupling ``|a_ij| >= θ sqrt(a_ii a_jj)`` (:data:`STRONG_COUPLING`). A mesher's flat tets
(slivers, often on the boundary of a TetGen mesh) give such pairs; on the 1M-tet TetGen user meshes of
docs/usermesh.md the Neumann cycle's slow error sat on boundary nodes of tets ~15x flatter than the median,
and the strongly coupled 2.6% of the unknowns carried two thirds of its energy.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import scipy.sparse as sp

from . import _kernels
from .coarse import sparse_lu
from .errors import SolverInputError
from .smoothing import Smoother, chained

__all__ = ["POWER_CORE_FRACTION", "POWER_SHARE", "REGION_MAX_FRACTION", "REGION_MAX_NODES", "REGION_SHARE",
           "STRONG_COUPLING", "concentrated_region", "power_probe", "slow_region", "strongly_coupled",
           "subdomain_factor", "with_subdomain_solve"]

#: Share of the slow modes' energy the region must carry.
REGION_SHARE = 0.9
#: Largest region, as a fraction of the level's unknowns (after the neighbours are added): beyond it the
#: modes are not local and a subdomain solve would be a second coarse solve.
REGION_MAX_FRACTION = 0.1
#: Largest region in unknowns: bounds the sparse factorisation's time and fill.
REGION_MAX_NODES = 20_000
#: Share of a cheap probe's error energy the core of its region carries (:func:`concentrated_region`).
POWER_SHARE = 0.7
#: Largest core of a cheap probe's region, as a fraction of the level's unknowns. After two default
#: V-cycles on the 1M-tet user hierarchies, 70% of the energy sat on ~0.5% of the nodes of the TetGen
#: fine levels (Neumann; the Lanczos probe's local family) and needed 4-20% on the TetWild ones and on
#: Dirichlet problems (no local family).
POWER_CORE_FRACTION = 0.01
#: A coupling is strong when ``|a_ij| >= STRONG_COUPLING sqrt(a_ii a_jj)``. A well-shaped P1 mesh's strongest
#: coupling per row is ~0.24 at the median and ~0.37 at the 90th percentile of its rows (TetGen, 1M tets);
#: at 0.5 the point smoother's slow local error is concentrated on the strongly coupled nodes
#: (:func:`strongly_coupled`).
STRONG_COUPLING = 0.5


def slow_region(Z: np.ndarray, A: sp.csr_matrix, share: float = REGION_SHARE, rings: int = 1,
                max_fraction: float = REGION_MAX_FRACTION, max_nodes: int = REGION_MAX_NODES
                ) -> np.ndarray | None:
    """The small set of unknowns on which the slow modes ``Z`` live, or None if they are not local.

    Parameters
    ----------
    Z : (n, m) float array
        Slow modes (:func:`solvers.deflation.slow_modes`).
    A : (n, n) csr_matrix
        The level operator.
    share : float
        Share of the modes' summed energy the core set carries (its nodes taken by decreasing energy).
    rings : int
        Graph neighbourhoods (in ``A``'s pattern) added around the core set.
    max_fraction, max_nodes : float, int
        Largest accepted region (fraction of ``n``, and unknowns).

    Returns
    -------
    int array or None
        Sorted unknowns of the region; None when ``Z`` is empty or the region is too large.
    """
    n = A.shape[0]
    if Z.shape[1] == 0:
        return None
    limit = min(max_fraction * n, max_nodes)
    core = _energy_core(np.abs(Z * (A @ Z)).sum(axis=1), share, int(limit))
    return None if core is None else _grown(core, A, rings, limit)


def _energy_core(energy: np.ndarray, share: float, limit: int) -> np.ndarray | None:
    """The fewest nodes (by decreasing ``energy``) that carry ``share`` of its sum, or None if that takes
    more than ``limit``: only the ``limit`` largest are sorted (a partition first)."""
    n = energy.size
    top = np.argpartition(-energy, limit)[: limit + 1] if limit + 1 < n else np.arange(n)
    top = top[np.argsort(-energy[top])]
    cut = int(np.searchsorted(np.cumsum(energy[top]), share * energy.sum()))
    return top[: cut + 1] if cut < min(limit, top.size) else None


def _grown(core: np.ndarray, A: sp.csr_matrix, rings: int, limit: float) -> np.ndarray | None:
    """``core`` plus ``rings`` graph neighbourhoods in ``A``'s pattern (sorted), or None beyond ``limit``
    unknowns or when that is every unknown."""
    mask = np.zeros(A.shape[0], dtype=bool)
    mask[core] = True
    for _ in range(rings):
        mask[A[np.flatnonzero(mask)].indices] = True
    region = np.flatnonzero(mask)
    return region if region.size <= limit and region.size < A.shape[0] else None


def power_probe(cycle: Callable[[np.ndarray], None], A: sp.csr_matrix, cycles: int,
                project: Callable[[np.ndarray], None], seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The last two errors ``e_{k-1}, e_k`` of ``k = cycles`` applications of a cycle to ``A x = 0`` from a
    seeded random start (its slowest components, for the region and the keep test of a cheap probe).

    Parameters
    ----------
    cycle : callable
        ``cycle(x)``: one cycle on ``A x = 0``, in place (``x`` becomes ``E x``).
    A : (n, n) csr_matrix
    cycles : int
        At least 1 (``e_0`` is the random start).
    project : callable
        Removes the known kernel from a vector in place (the mean, for a Neumann operator).
    seed : int

    Returns
    -------
    (e_{k-1}, e_k) : two (n,) float arrays
    """
    e = np.random.default_rng(seed).standard_normal(A.shape[0])
    project(e)
    prev = e
    for _ in range(int(cycles)):
        prev = e.copy()
        cycle(e)
        project(e)
    return prev, e


def concentrated_region(e: np.ndarray, A: sp.csr_matrix, share: float = POWER_SHARE,
                        core_fraction: float = POWER_CORE_FRACTION, rings: int = 1,
                        max_fraction: float = REGION_MAX_FRACTION, max_nodes: int = REGION_MAX_NODES,
                        Ae: np.ndarray | None = None) -> np.ndarray | None:
    """The region of an error ``e`` whose energy ``|e_i (A e)_i|`` is concentrated: the fewest nodes carrying
    ``share`` of it (at most ``core_fraction`` of the unknowns) plus ``rings`` neighbourhoods.

    Parameters
    ----------
    e : (n,) float array
        E.g. :func:`power_probe`'s last error.
    A : (n, n) csr_matrix
    share, core_fraction : float
    rings : int
    max_fraction, max_nodes : float, int
        Largest accepted region (as :func:`slow_region`).
    Ae : (n,) float array, optional
        ``A @ e`` if already computed.

    Returns
    -------
    int array or None
        Sorted unknowns of the region; None when the energy is spread (or zero) or the region too large.
    """
    energy = np.abs(e * (A @ e if Ae is None else Ae))
    if not energy.sum() > 0.0:
        return None
    core = _energy_core(energy, share, int(core_fraction * A.shape[0]))
    return None if core is None else _grown(core, A, rings, min(max_fraction * A.shape[0], max_nodes))


def strongly_coupled(A: sp.csr_matrix, theta: float = STRONG_COUPLING,
                     max_fraction: float = REGION_MAX_FRACTION, lower=None) -> np.ndarray | None:
    """The unknowns of a symmetric ``A`` with a strong off-diagonal coupling,
    ``a_ij**2 >= theta**2 a_ii a_jj`` (``i != j``, both diagonals positive), sorted.

    Parameters
    ----------
    A : (n, n) csr_matrix
        Symmetric (the relation is symmetric: both ends of every strong entry are taken).
    theta : float
        In (0, 1].
    max_fraction : float
        Largest accepted region, as a fraction of ``n``: beyond it the couplings are not local (an
        anisotropic operator) and a subdomain solve would be a second coarse solve.
    lower : (csr_matrix, ndarray), optional
        ``(D + L, diag(A))``: ``A``'s entries with column <= row (any order within a row) and its diagonal,
        scanned instead of ``A`` (half the entries; Gauss–Seidel's split, kept by the solver's set-up).

    Returns
    -------
    int array or None
        None when no coupling is strong or when more than ``max_fraction`` of the unknowns are.
    """
    if not 0.0 < theta <= 1.0:
        raise SolverInputError(f"the strong-coupling threshold must be in (0, 1], got {theta!r}")
    M, d = (A, A.diagonal()) if lower is None else lower
    n = A.shape[0]
    dp = np.where(d > 0.0, d, np.inf)  # a non-positive diagonal: no strong coupling there
    if _kernels.wanted(M.nnz):  # one compiled pass instead of ten numpy passes over the entries (same mask)
        region = np.flatnonzero(_kernels.strong_mask(M.indptr, M.indices, M.data, dp, theta * theta))
        return region if 0 < region.size <= max_fraction * n else None
    rows = np.repeat(np.arange(n, dtype=M.indices.dtype), np.diff(M.indptr))
    bound = dp.take(rows)
    bound *= dp.take(M.indices)
    bound *= theta * theta  # theta**2 a_ii a_jj, one per stored entry
    strong = M.data * M.data >= bound
    strong &= rows != M.indices
    mask = np.zeros(n, dtype=bool)
    mask[rows[strong]] = True
    mask[M.indices[strong]] = True
    region = np.flatnonzero(mask)
    return region if 0 < region.size <= max_fraction * n else None


def subdomain_factor(A: sp.csr_matrix, nodes: np.ndarray, rows: sp.csr_matrix | None = None):
    """:func:`solvers.coarse.sparse_lu` of ``A_SS`` (``rows``: ``A[nodes]`` if already built), or None when
    ``A_SS`` is numerically singular or not positive definite (a pivot of ``U`` not above 1e-12 of the
    largest): a rank-deficient coarse level's extra kernel vectors are local slow modes too, and their
    region's block is singular; without pivoting SuperLU would return a useless factor."""
    A_S = A[nodes] if rows is None else rows
    try:
        lu = sparse_lu(A_S[:, nodes], symmetric=True)
    except RuntimeError:  # SuperLU: "Factor is exactly singular"
        return None
    pivots = lu.U.diagonal()
    return lu if pivots.size and np.all(pivots > 1e-12 * pivots.max()) else None


def with_subdomain_solve(base: Smoother, A: sp.csr_matrix, nodes: np.ndarray, first: bool = False,
                         factor=None, rows: sp.csr_matrix | None = None) -> Smoother:
    """``base`` plus the exact subdomain correction ``x_S += A_SS⁻¹ (b - A x)_S`` on the unknowns ``nodes``
    (a multiplicative Schwarz step).

    With ``first=False`` the correction follows ``base`` (pre-smoother), with ``first=True`` it precedes it
    (post-smoother): the pair stays adjoint and the cycle symmetric.

    Parameters
    ----------
    base : Smoother
    A : (n, n) csr_matrix
        The level operator (symmetric; ``A_SS`` must be nonsingular: a proper subset of a connected
        Neumann operator's unknowns is).
    nodes : int array
        The subdomain ``S`` (sorted, unique, a proper subset).
    first : bool
    factor : SuperLU, optional
        :func:`subdomain_factor` of ``A_SS`` if already built (a pre/post pair shares one).
    rows : csr_matrix, optional
        ``A[nodes]`` (CSR) if already built.

    Returns
    -------
    Smoother
        Its ``work`` adds the rows' product and the factor's two triangular solves (in SpMV units).
    """
    idx = np.asarray(nodes, dtype=np.int64)
    if idx.size == 0 or idx[0] < 0 or idx[-1] >= A.shape[0] or np.any(np.diff(idx) <= 0):
        raise SolverInputError(f"subdomain nodes must be sorted, unique and in [0, {A.shape[0]})")
    A_S = A[idx] if rows is None else rows
    lu = subdomain_factor(A, idx, A_S) if factor is None else factor
    if lu is None:
        raise SolverInputError(f"the subdomain's block A_SS ({idx.size} unknowns) is singular")

    def correct(A_, x, b):
        x[idx] += lu.solve(b[idx] - A_S @ x)

    work = base.work + (A_S.nnz + lu.L.nnz + lu.U.nnz) / max(A.nnz, 1)
    params = dict(base.params, subdomain_nodes=int(idx.size))
    fast = None if first or base.smooth_residual is None else _corrected_residual(base, A, idx, A_S, lu)
    return Smoother(base.name, chained(base, correct, first), work, params, smooth_residual=fast)


def _corrected_residual(base: Smoother, A0: sp.csr_matrix, idx: np.ndarray, A_S: sp.csr_matrix, lu):
    """``smooth_residual`` of a pre-smoother followed by the subdomain correction: ``base``'s own (cheap)
    residual ``r``, then ``d = A_SS⁻¹ r_S``, ``x_S += d`` and ``r -= A_{:,S} d`` (``A_Sᵀ d``, ``A`` symmetric:
    only the region's rows and their neighbours change). Without it the cycle would fall back to the plain
    path, a full product with ``A`` per visit on top of the correction's ``A_S x``."""
    cols, local = np.unique(A_S.indices, return_inverse=True)  # the region and its neighbours
    A_T = sp.csr_matrix((A_S.data, local, A_S.indptr), shape=(idx.size, cols.size)).T.tocsr()

    def smooth_residual(A, x, b, zero):
        r = base.smooth_residual(A, x, b, zero) if A is A0 else None
        if r is None:
            return None
        d = lu.solve(r[idx])
        x[idx] += d
        r[cols] -= A_T @ d
        return r

    return smooth_residual
