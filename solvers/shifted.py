"""Galerkin hierarchies of a family ``a M + b K``: two triple products once, then a sparse sum per member.

Implicit time stepping ``(M + Δt_k K) u_k = M u_{k-1}`` with a changing step, or a heat method with
several time steps, changes the operator but not the prolongations. Since the Galerkin product is
linear in the operator,

    ``P_kᵀ (a M_k + b K_k) P_k = a P_kᵀ M_k P_k + b P_kᵀ K_k P_k``,

the coarse operators of every member follow from ``M_{k+1} = P_kᵀ M_k P_k`` and
``K_{k+1} = P_kᵀ K_k P_k`` (computed once, :func:`solvers.galerkin_operators`) by one vector
operation on aligned data arrays: every level's ``M`` and ``K`` are stored on the union of their
sparsity patterns, so ``a M + b K`` costs ``O(nnz)`` flops and no sparse symbolic work. The result
equals the Galerkin hierarchy of ``a M_0 + b K_0`` up to round-off.

Example (a diffusion step, ``M`` lumped mass, ``K`` stiffness, ``Ps`` prolongations)::

    fam = ShiftedGalerkin(M, K, Ps)
    A, *coarse = fam.operators(1.0, dt)            # [A_0, A_1, ..., A_L]
    ml = MultigridSolver(A, Ps, coarse=coarse)     # only smoothers and coarsest factorisation are set up
"""

from __future__ import annotations

import time

import numpy as np
import scipy.sparse as sp

from .errors import SolverInputError
from .transfer import _as_csr, galerkin_operators

__all__ = ["ShiftedGalerkin"]


def _aligned(U: sp.csr_matrix, A: sp.csr_matrix) -> np.ndarray:
    """Values of ``A`` on the (sorted, canonical) pattern of ``U`` (which contains ``A``'s pattern)."""
    n = U.shape[1]
    ku = np.repeat(np.arange(U.shape[0], dtype=np.int64), np.diff(U.indptr)) * n + U.indices
    ka = np.repeat(np.arange(A.shape[0], dtype=np.int64), np.diff(A.indptr)) * n + A.indices
    pos = np.searchsorted(ku, ka)  # ku is sorted: row-major order of a canonical csr matrix
    out = np.zeros(U.nnz)
    out[pos] = A.data
    return out


class ShiftedGalerkin:
    """Galerkin hierarchies of ``a M + b K`` for any ``(a, b)``, from two triple products.

    Parameters
    ----------
    M, K : (n_0, n_0) sparse matrices
        The two fine operators (e.g. mass and stiffness on the free nodes).
    Ps : list of sparse
        ``Ps[k]`` of shape ``(n_k, n_{k+1})`` (as for :class:`solvers.MultigridSolver`; restrict them to
        the free nodes first).

    Attributes
    ----------
    M_levels, K_levels : list of csr_matrix
        ``[M_0, P_0ᵀ M_0 P_0, ...]`` and the same for ``K``.
    setup_seconds : float
        Time of the two Galerkin hierarchies and the pattern alignment.

    Examples
    --------
    >>> from solvers.gallery import kuhn_cube_hierarchy
    >>> from solvers import stiffness_matrix, mass_matrix, galerkin_operators
    >>> meshes, Ps = kuhn_cube_hierarchy(4, 2)
    >>> V, T = meshes[0]
    >>> K, M = stiffness_matrix(V, T), mass_matrix(V, T)
    >>> fam = ShiftedGalerkin(M, K, Ps)
    >>> ops = fam.operators(1.0, 0.3)
    >>> ref = galerkin_operators(M + 0.3 * K, Ps)
    >>> bool(abs(ops[1] - ref[1]).max() < 1e-12 * abs(ref[1]).max())
    True
    """

    def __init__(self, M, K, Ps):
        t0 = time.perf_counter()
        M = _as_csr(M, "M")
        K = _as_csr(K, "K")
        if M.shape != K.shape or M.shape[0] != M.shape[1]:
            raise SolverInputError(f"M and K must be square of the same shape, got {M.shape} and {K.shape}")
        self.Ps = [sp.csr_matrix(P, dtype=np.float64) for P in Ps]
        self.M_levels = galerkin_operators(M, self.Ps)
        self.K_levels = galerkin_operators(K, self.Ps)
        self._patterns = []
        self._mdata = []
        self._kdata = []
        for Mk, Kk in zip(self.M_levels, self.K_levels):
            # union pattern; absolute values so that no entry cancels out of the pattern
            U = sp.csr_matrix(abs(Mk) + abs(Kk))
            U.sum_duplicates()
            U.sort_indices()
            self._patterns.append((U.indptr, U.indices, U.shape))
            self._mdata.append(_aligned(U, Mk))
            self._kdata.append(_aligned(U, Kk))
        self.setup_seconds = time.perf_counter() - t0

    @property
    def n_levels(self) -> int:
        """Number of levels (fine level included)."""
        return len(self._patterns)

    def operators(self, a: float, b: float) -> list[sp.csr_matrix]:
        """The Galerkin hierarchy ``[a M_k + b K_k for every level k]``, finest first.

        Parameters
        ----------
        a, b : float
            Coefficients of ``M`` and ``K`` (a diffusion step: ``a = 1``, ``b = Δt``).

        Returns
        -------
        list of csr_matrix
            Canonical (sorted, no duplicates) matrices with their own index arrays.
        """
        a, b = float(a), float(b)
        if not (np.isfinite(a) and np.isfinite(b)):
            raise SolverInputError(f"coefficients must be finite, got a={a}, b={b}")
        out = []
        for (indptr, indices, shape), md, kd in zip(self._patterns, self._mdata, self._kdata):
            A = sp.csr_matrix((a * md + b * kd, indices.copy(), indptr.copy()), shape=shape)
            A.has_sorted_indices = True
            out.append(A)
        return out
