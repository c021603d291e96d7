"""Optional compiled loops (numba) for the set-up's O(nnz) passes; pure numpy/scipy fallbacks elsewhere.

Each kernel here fuses a chain of numpy passes over a matrix's entries (index arrays built by ``np.repeat``,
``take`` gathers, masks, ``flatnonzero``) into one loop, and returns the very arrays the numpy code it
replaces returns (tested bit for bit, ``tests/test_solvers_kernels.py``): the numpy code stays as the
fallback when numba is not installed (``pip install nestmg[fast]``) or ``NESTMG_NUMBA=0``. Measured on a
1M-tet user hierarchy (docs/usermesh.md): the set-up's split into ``L + D/2``, its permuted fine-matrix
gather and its strong-coupling scan cost several times one pass over the entries in numpy.

The kernels are compiled on first use and cached on disk (``cache=True``): the first set-up in a fresh
environment pays the compilation once (about a second per kernel), later processes load the cache.
"""

from __future__ import annotations

import os

import numpy as np

try:  # pragma: no cover - depends on the environment
    import numba
except ImportError:  # pragma: no cover
    numba = None

#: whether the compiled kernels are used (numba importable and ``NESTMG_NUMBA`` not "0"); tests switch it
ENABLED = numba is not None and os.environ.get("NESTMG_NUMBA", "1") != "0"


def _jit(f):
    """``numba.njit(cache=True, nogil=True)(f)``, or ``f`` itself (never called) without numba."""
    return f if numba is None else numba.njit(cache=True, nogil=True)(f)


# Every index below is cast to uint64 (``_U``): numba wraps a negative signed index around, a test and a
# branch on each array access that cost these loops 1.5x (a CSR product with the casts ran as fast as
# scipy's, 3.3 ms against 5.3 without on a 2.5M-entry matrix). Mixed signed/unsigned arithmetic would be
# typed float64 by numba, hence the unsigned constants.
_U = np.uint64


@_jit
def probe_products(indptr, indices, data, x):  # pragma: no cover - compiled
    """``(B x, Bᵀ x, max |b_ij|)`` of a CSR matrix ``B`` in one pass over its entries (two SpMV and two
    reductions in scipy/numpy)."""
    n = _U(indptr.size - 1)
    y = np.zeros(n)
    yt = np.zeros(x.size)
    amax = 0.0
    for r in range(n):
        acc = 0.0
        xr = x[r]
        for q in range(_U(indptr[r]), _U(indptr[r + _U(1)])):
            c = _U(indices[q])
            v = data[q]
            acc += v * x[c]
            yt[c] += v * xr
            amax = max(amax, abs(v))
        y[r] = acc
    return y, yt, amax


@_jit
def relabelled_transpose(indptr, indices, data, inv, x, probe, tind, tdat):  # pragma: no cover - compiled
    """``Bᵀ`` in canonical CSR form for ``B`` = the rows of ``(indptr, indices, data)`` with their columns
    relabelled by ``inv`` (a permutation), and, when ``probe``, ``(B x, Bᵀ x, max |b_ij|)`` from the same
    pass: the relabelling ``take``, scipy's counting transpose and :func:`probe_products` in one (the same
    arrays as ``_transposed`` of the relabelled matrix). ``tind``, ``tdat``: the output's indices and values,
    of ``nnz`` entries, allocated by the caller (see :func:`lower_counts`).

    Returns ``(indptr, Bx, Btx, amax)`` (the vectors empty without ``probe``)."""
    one = _U(1)
    n = _U(indptr.size - 1)
    ncol = _U(inv.size)
    nxt = np.zeros(ncol + one, indptr.dtype)
    for q in range(_U(indptr[n])):
        nxt[_U(inv[_U(indices[q])]) + one] += 1
    for c in range(ncol):
        nxt[c + one] += nxt[c]
    tptr = nxt.copy()
    m = n if probe else _U(0)
    y = np.zeros(m)
    yt = np.zeros(ncol if probe else _U(0))
    amax = 0.0
    for r in range(n):
        acc = 0.0
        xr = x[r] if probe else 0.0
        for q in range(_U(indptr[r]), _U(indptr[r + one])):
            c = _U(inv[_U(indices[q])])
            v = data[q]
            w = _U(nxt[c])
            tind[w] = r
            tdat[w] = v
            nxt[c] += 1
            if probe:
                acc += v * x[c]
                yt[c] += v * xr
                amax = max(amax, abs(v))
        if probe:
            y[r] = acc
    return tptr, y, yt, amax


@_jit
def lower_counts(indptr, indices, sorted_rows):  # pragma: no cover - compiled
    """The row pointers of the ``L + D/2`` split of :func:`solvers.transfer._lower_half` (the entries with
    column <= row) and the diagonal entries' positions (-1 where a row stores none); with ``sorted_rows`` a
    row's scan stops after its diagonal. Then :func:`lower_fill` writes the split into arrays of
    ``indptr[-1]`` entries allocated by numpy: numba's own allocations get no transparent huge pages, and
    their page faults cost more CPU than the loop saved (10k faults against 7k per 1M-tet set-up)."""
    one = _U(1)
    n = _U(indptr.size - 1)
    hptr = np.empty(n + one, indptr.dtype)
    hptr[0] = 0
    pos = np.full(n, -1, np.int64)
    w = _U(0)
    for r in range(n):
        for q in range(_U(indptr[r]), _U(indptr[r + one])):
            c = _U(indices[q])
            if c <= r:
                w += one
                if c == r:
                    pos[r] = q
            elif sorted_rows:
                break
        hptr[r + one] = w
    return hptr, pos


@_jit
def lower_fill(indptr, indices, data, sorted_rows, hind, hdat):  # pragma: no cover - compiled
    """Fill :func:`lower_counts`'s split: ``hind``, ``hdat`` receive the entries with column <= row in ``A``'s
    order, the diagonal ones halved. Returns ``(diag, half_positions)``: ``diag`` zero where a row stores no
    diagonal entry, the diagonal entries' positions in the half (-1 where missing)."""
    one = _U(1)
    n = _U(indptr.size - 1)
    hpos = np.full(n, -1, np.int64)
    diag = np.zeros(n, data.dtype)
    w = _U(0)
    for r in range(n):
        for q in range(_U(indptr[r]), _U(indptr[r + one])):
            c = _U(indices[q])
            if c <= r:
                hind[w] = indices[q]
                v = data[q]
                if c == r:
                    diag[r] = v
                    hpos[r] = w
                    v *= 0.5
                hdat[w] = v
                w += one
            elif sorted_rows:
                break
    return diag, hpos


@_jit
def strong_mask(indptr, indices, data, dp, theta2):  # pragma: no cover - compiled
    """Both ends of every off-diagonal entry with ``a_ij**2 >= (dp_i dp_j) theta2`` (the numpy expression of
    :func:`solvers.subdomain.strongly_coupled`, evaluated in the same order), as a boolean mask."""
    n = _U(indptr.size - 1)
    mask = np.zeros(n, np.bool_)
    for r in range(n):
        dr = dp[r]
        for q in range(_U(indptr[r]), _U(indptr[r + _U(1)])):
            c = _U(indices[q])
            if c != r:
                v = data[q]
                if v * v >= dr * dp[c] * theta2:
                    mask[r] = True
                    mask[c] = True
    return mask


@_jit
def swap_diagonal_first(indptr, indices, data, positions):  # pragma: no cover - compiled
    """In place: each row's entry at ``positions[i]`` trades places with the row's first entry
    (:func:`solvers.ordering.diagonal_first`)."""
    for r in range(_U(indptr.size - 1)):
        s = _U(indptr[r])
        q = _U(positions[r])
        c = indices[s]
        indices[s] = indices[q]
        indices[q] = c
        v = data[s]
        data[s] = data[q]
        data[q] = v


@_jit
def sort_rows(indptr, indices, data):  # pragma: no cover - compiled
    """In place: every row's entries sorted by column (insertion sort: for short rows, such as a
    prolongation's four barycentric weights; a row without duplicate columns has one sorted order)."""
    one = _U(1)
    for r in range(_U(indptr.size - 1)):
        s = _U(indptr[r])
        for q in range(s + one, _U(indptr[r + one])):
            c = indices[q]
            v = data[q]
            m = q
            while m > s and indices[m - one] > c:
                indices[m] = indices[m - one]
                data[m] = data[m - one]
                m -= one
            indices[m] = c
            data[m] = v


@_jit
def row_min(indptr, indices, rank):  # pragma: no cover - compiled
    """``min(rank[indices[q]] for q in row i)`` for every (non-empty) row: ``np.minimum.reduceat`` of the
    gathered ranks without the gathered array (7 ms against ~1 on a 1M-tet hierarchy's first prolongation)."""
    one = _U(1)
    n = _U(indptr.size - 1)
    out = np.empty(n, rank.dtype)
    for r in range(n):
        s = _U(indptr[r])
        m = rank[_U(indices[s])]
        for q in range(s + one, _U(indptr[r + one])):
            m = min(m, rank[_U(indices[q])])
        out[r] = m
    return out
