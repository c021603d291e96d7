"""Node orderings for memory locality: a fine-level permutation taken from the prolongations.

A user's matrix comes in the user's node order, which meshers often leave scattered (1M-tet TetGen and
TetWild meshes written and read back: the mean index distance ``|i - j|`` of their nonzeros is 25-28% of
``n``, close to a random order's 33%). Every sparse kernel of a multigrid set-up and cycle then misses the
cache on almost every access; after a symmetric permutation to a local order the Galerkin products of a
1M-tet user hierarchy took 0.64-0.67 s instead of 1.63-1.99 s and a fine SpMV ran up to 1.4x faster
(docs/usermesh.md, ``benchmarks/results/user_mesh/``). :class:`solvers.MultigridSolver` applies
:func:`locality_order` to every level (``ordering="auto"``) and maps vectors in and out of the finest.

The order comes from the hierarchy itself, at the cost of a few integer sorts: the coarsest level is
ordered by reverse Cuthill–McKee on the pattern of ``P_{L-1}ᵀ P_{L-1}``, and every finer level is sorted
(stably) by the rank of the lowest-ranked coarse node that interpolates to each of its nodes, so the
nodes under one coarse node sit together and neighbouring coarse nodes' groups sit near each other.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import reverse_cuthill_mckee

from . import _kernels
from .errors import SolverInputError

__all__ = ["ORDER_MIN_N", "ORDER_MIN_SPREAD", "SPREAD_STRIDE", "diagonal_first", "index_spread",
           "locality_order", "permute_prolongation", "permute_symmetric", "permute_symmetric_transpose"]

#: ``ordering="auto"`` reorders a finest level of at least this many unknowns ...
ORDER_MIN_N = 20_000
#: ... whose :func:`index_spread` exceeds this (a random order gives 1/3; a reverse Cuthill–McKee or
#: :func:`locality_order` of a 1M-tet mesh ~0.02).
ORDER_MIN_SPREAD = 0.05
#: ... estimated on every this many rows (``index_spread(A, stride)``: a full pass over a 2.6M-nonzero
#: matrix cost ~10 ms of a 0.4 s set-up; the estimate differs from it in the third digit on the user
#: meshes of docs/usermesh.md).
SPREAD_STRIDE = 16


def index_spread(A: sp.csr_matrix, stride: int = 1) -> float:
    """Mean ``|i - j|`` over the nonzeros ``(i, j)`` of ``A`` divided by ``n`` (0: diagonal, ~1/3: random).

    ``stride > 1`` averages over the rows ``0, stride, 2 stride, ...`` only (an estimate at ``1/stride`` of
    the cost, for a threshold test such as ``ordering="auto"``'s).
    """
    n = A.shape[0]
    if A.nnz == 0 or n == 0:
        return 0.0
    if stride > 1:
        A = A[::stride]
        if A.nnz == 0:
            return 0.0
    rows = np.repeat(np.arange(0, n, stride, dtype=A.indices.dtype), np.diff(A.indptr))
    return float(np.abs(rows - A.indices).mean() / n)


def _inverse(p: np.ndarray, dtype=None) -> np.ndarray:
    """The inverse permutation of ``p`` (as ``dtype``, default ``p``'s)."""
    inv = np.empty(p.size, dtype=p.dtype if dtype is None else dtype)
    inv[p] = np.arange(p.size, dtype=inv.dtype)
    return inv


def _stable_argsort(key: np.ndarray) -> np.ndarray:
    """``np.argsort(key, kind="stable")`` for non-negative integer keys below ``2**32``, as numpy's radix sort:
    one pass on 16-bit keys, else two (low half, then high half: an LSD radix sort). The same permutation
    (a stable sort is unique); ~7x faster than the merge sort numpy runs on wider integer keys."""
    if key.size == 0 or int(key.max()) >= 1 << 32:
        return np.argsort(key, kind="stable")
    if int(key.max()) < 1 << 16:
        return np.argsort(key.astype(np.uint16), kind="stable")
    order = np.argsort((key & 0xFFFF).astype(np.uint16), kind="stable")
    return order[np.argsort((key[order] >> 16).astype(np.uint16), kind="stable")]


def locality_order(Ps) -> list[np.ndarray]:
    """Permutations of every level's unknowns that keep neighbours close in memory.

    Parameters
    ----------
    Ps : list of csr_matrix, ``Ps[k]`` of shape ``(n_k, n_{k+1})``, at least one; every row non-empty

    Returns
    -------
    list of (n_k,) int64 arrays, finest first (``len(Ps) + 1``)
        New position ``i`` of level ``k`` holds old unknown ``p_k[i]`` (apply as ``A_k[p_k][:, p_k]``,
        ``x[p_k]``, ``P_k[p_k][:, p_{k+1}]``).
    """
    if not Ps:
        raise SolverInputError("locality_order needs at least one prolongation")
    Ps = [sp.csr_matrix(P) for P in Ps]
    last = Ps[-1]
    pattern = sp.csr_matrix((np.ones(last.nnz), last.indices, last.indptr), shape=last.shape)
    order = np.asarray(reverse_cuthill_mckee(sp.csr_matrix(pattern.T @ pattern), symmetric_mode=True),
                       dtype=np.int64)
    orders = [order]
    for P in reversed(Ps):
        if (np.diff(P.indptr) == 0).any():
            raise SolverInputError("locality_order needs prolongations without empty rows")
        rank = _inverse(orders[0])
        # lowest-ranked coarse parent per row
        key = (_kernels.row_min(P.indptr, P.indices, rank) if _kernels.wanted(P.nnz)
               else np.minimum.reduceat(rank.take(P.indices), P.indptr[:-1]))
        orders.insert(0, _stable_argsort(key).astype(np.int64))
    return orders


def permute_symmetric(A: sp.csr_matrix, p: np.ndarray) -> sp.csr_matrix:
    """``A[p][:, p]`` in canonical CSR form: a row gather, a relabelling of the columns and two O(nnz)
    transposes (which leave every row's indices sorted), exact for any square ``A``."""
    return _transposed(_transposed(_gathered(A, p, p)))


def permute_symmetric_transpose(A: sp.csr_matrix, p: np.ndarray, *, probe: bool = True, rtol: float = 1e-10,
                                seed: int = 0) -> tuple[sp.csr_matrix, bool]:
    """``(A[p][:, p])ᵀ`` in canonical CSR form and whether ``A`` is symmetric, for one transpose.

    A symmetric matrix is its own transpose, so one O(nnz) transpose of the gathered, relabelled rows gives
    the permuted matrix in canonical form; :func:`permute_symmetric` needs a second one. Symmetry is tested
    by two products instead of that transpose (a third of its cost): ``max |(B - Bᵀ) x| <= rtol max |a_ij|``
    for a random ``x`` in ``[-1, 1]ⁿ`` (``B = A[p][:, p]``, fixed seed). An asymmetric entry ``δ`` is found
    unless ``|x_j| < rtol max |a_ij| / |δ|`` (or the row's asymmetries cancel, a set of measure zero): always
    for the asymmetry of an advection or a one-sided boundary condition, with probability ``1 - 1/c`` for a
    ``δ`` of ``c`` times the tolerance, whose test is a matter of convention anyway.
    A non-symmetric ``A`` gets the second transpose: the returned matrix is then ``A[p][:, p]`` itself.
    ``probe=False``: the caller states that ``A`` is symmetric (no test).

    Returns
    -------
    (csr_matrix, bool)
        ``Ap`` (canonical; ``A[p][:, p]`` exactly when ``A`` is exactly symmetric, else within ``rtol`` of
        it when symmetric, and exactly when not) and the symmetry verdict.
    """
    x = np.random.default_rng(seed).uniform(-1.0, 1.0, A.shape[0]) if probe else None
    if _kernels.wanted(A.nnz):  # the relabelling, the transpose and the probe products in one pass
        B = A[p]
        inv = _inverse(np.asarray(p, dtype=np.int64), B.indices.dtype)
        Bt, Bx, Btx, amax = _relabelled_transpose(B, inv, x)
    else:
        B = _gathered(A, p, p)
        Bt = _transposed(B)
        if probe:
            Bx, Btx = B @ x, Bt @ x
            # max |a_ij| as max(max a, -min a): two reductions, no O(nnz) temporary
            amax = max(float(B.data.max()), -float(B.data.min())) if B.nnz else 0.0
    if not probe:
        return Bt, True
    scale = rtol * (amax if B.nnz else 1.0)
    symmetric = float(np.abs(Bx - Btx).max(initial=0.0)) <= scale
    return (Bt, True) if symmetric else (_transposed(Bt), False)


def _gathered(A: sp.csr_matrix, rows: np.ndarray, cols: np.ndarray) -> sp.csr_matrix:
    """``A[rows][:, cols]`` for permutations ``rows`` and ``cols``, as CSR with each row's entries in ``A``'s
    column order (not sorted by new label): one row gather and one relabelling gather."""
    B = A[rows]
    inv = _inverse(np.asarray(cols, dtype=np.int64), B.indices.dtype)  # one gather in the index type
    return sp.csr_matrix((B.data, inv.take(B.indices), B.indptr), shape=A.shape)


def _transposed(B: sp.csr_matrix) -> sp.csr_matrix:
    """``Bᵀ`` as canonical CSR (one O(nnz) counting transpose; ``B`` without duplicates)."""
    t = B.tocsc()
    out = sp.csr_matrix((t.data, t.indices, t.indptr), shape=(B.shape[1], B.shape[0]))
    out.has_canonical_format = True
    return out


def _relabelled_transpose(B: sp.csr_matrix, inv: np.ndarray, x: np.ndarray | None):
    """``(Bᵀ, Bx, Bᵀx, max |b_ij|)`` of ``B`` = ``B``'s rows relabelled by ``inv`` (the last three None
    without ``x``), by :func:`solvers._kernels.relabelled_transpose`: ``Bᵀ`` the same canonical matrix as
    ``_transposed``'s."""
    probe = x is not None
    indices, data = np.empty(B.nnz, B.indices.dtype), np.empty(B.nnz, B.data.dtype)  # numpy's huge pages
    indptr, Bx, Btx, amax = _kernels.relabelled_transpose(B.indptr, B.indices, B.data, inv,
                                                          x if probe else np.zeros(0), probe, indices, data)
    Bt = sp.csr_matrix((data, indices, indptr), shape=(B.shape[1], B.shape[0]))
    Bt.has_canonical_format = True
    return (Bt, Bx, Btx, amax) if probe else (Bt, None, None, None)


def diagonal_first(A: sp.csr_matrix, positions: np.ndarray, *, in_place: bool = False) -> sp.csr_matrix:
    """``A`` with each row's diagonal entry first: it trades places with the row's first entry.

    pyamg's Gauss–Seidel kernel tests every entry of a row for the diagonal; with the diagonal at a varying
    place in the row that branch is mispredicted about once per row, and a sweep on a canonical P1 matrix
    (14-15 entries per row) cost 1.6-2.1 SpMVs (either direction). With the diagonal first the same sweep
    took 0.95-1.4 (the fine levels of the 1M-tet user hierarchies,
    ``benchmarks/results/user_mesh/sweep_direction.json``); 1.1-1.3x less on their coarse levels. One swap
    per row, O(n): moving the diagonal to the front with the other entries in their order was a gather of
    every entry (15-18 ms of a 1M-tet user hierarchy's set-up). Sums over a row (products, sweeps) then add
    its entries in another order (round-off).

    Parameters
    ----------
    A : csr_matrix
        Every row stores its diagonal entry once.
    positions : (n,) int array
        The position of row ``i``'s diagonal entry in ``A.indices`` / ``A.data``.
    in_place : bool
        Swap in ``A``'s own arrays (``A`` then is the result, no longer sorted) instead of copies.

    Returns
    -------
    csr_matrix
        ``A`` as a matrix (``has_sorted_indices`` False) on ``A``'s row pointers.
    """
    start = A.indptr[:-1]
    data, indices = (A.data, A.indices) if in_place else (A.data.copy(), A.indices.copy())
    compiled = _kernels.wanted(A.nnz)
    if compiled:  # one loop over the rows instead of four gathers and scatters per array
        _kernels.swap_diagonal_first(A.indptr, indices, data, positions)
    for arr in () if compiled else (data, indices):
        first = arr.take(start)
        arr[start] = arr.take(positions)
        arr[positions] = first
    if in_place:
        A.has_sorted_indices = False
        return A
    out = sp.csr_matrix((data, indices, A.indptr), shape=A.shape)
    out.has_sorted_indices = False
    return out


def permute_prolongation(P: sp.csr_matrix, p_fine: np.ndarray, p_coarse: np.ndarray, *,
                         with_transpose: bool = False):
    """``P[p_fine][:, p_coarse]`` (canonical CSR); with ``with_transpose=True`` also its transpose (the
    restriction, canonical CSR), a by-product: two O(nnz) transposes sort the relabelled rows (the rows'
    order before them does not matter, so rows of equal length are gathered as one dense block,
    :func:`_gathered_equal_rows`)."""
    B = _gathered_equal_rows(P, p_fine, p_coarse)
    R = _transposed(B if B is not None else _gathered(P, p_fine, p_coarse))
    out = _transposed(R)
    return (out, R) if with_transpose else out


def _gathered_equal_rows(P: sp.csr_matrix, rows: np.ndarray, cols: np.ndarray) -> sp.csr_matrix | None:
    """:func:`_gathered` for a matrix whose rows all hold the same number ``k`` of entries (a non-nested
    prolongation's rows: the four barycentric weights of a coarse tet), else None.

    The arrays are then an ``(n, k)`` block each and the row gather is one ``take`` of whole block rows:
    scipy's row indexing copies row by row (two ``memmove`` calls per row), which cost 4-7 ms against 0.4 for
    the first prolongation of a 1M-tet user hierarchy (173k rows of 4).
    """
    n = P.shape[0]
    k = P.nnz // n if n else 0
    if k == 0 or P.nnz != n * k or np.any(np.diff(P.indptr) != k):
        return None
    inv = _inverse(np.asarray(cols, dtype=np.int64), P.indices.dtype)
    indices = inv.take(P.indices.reshape(n, k).take(rows, axis=0)).ravel()
    data = P.data.reshape(n, k).take(rows, axis=0).ravel()
    indptr = np.arange(0, n * k + 1, k, dtype=P.indptr.dtype)
    return sp.csr_matrix((data, indices, indptr), shape=P.shape)
