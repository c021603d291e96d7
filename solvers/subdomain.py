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
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .coarse import sparse_lu
from .errors import SolverInputError
from .smoothing import Smoother, chained

__all__ = ["REGION_MAX_FRACTION", "REGION_MAX_NODES", "REGION_SHARE", "slow_region", "subdomain_factor",
           "with_subdomain_solve"]

#: Share of the slow modes' energy the region must carry.
REGION_SHARE = 0.9
#: Largest region, as a fraction of the level's unknowns (after the neighbours are added): beyond it the
#: modes are not local and a subdomain solve would be a second coarse solve.
REGION_MAX_FRACTION = 0.1
#: Largest region in unknowns: bounds the sparse factorisation's time and fill.
REGION_MAX_NODES = 20_000


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
    energy = np.abs(Z * (A @ Z)).sum(axis=1)
    order = np.argsort(-energy)
    core = order[: int(np.searchsorted(np.cumsum(energy[order]), share * energy.sum())) + 1]
    limit = min(max_fraction * n, max_nodes)
    if core.size > limit:
        return None
    mask = np.zeros(n, dtype=bool)
    mask[core] = True
    for _ in range(rings):
        mask[A[np.flatnonzero(mask)].indices] = True
    region = np.flatnonzero(mask)
    return region if region.size <= limit and region.size < n else None


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
    return Smoother(base.name, chained(base, correct, first), work, params)
