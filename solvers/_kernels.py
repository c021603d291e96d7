"""Optional compiled loops (numba) for the set-up's O(nnz) passes; pure numpy/scipy fallbacks elsewhere.

Each kernel fuses a chain of numpy/scipy passes over a matrix's entries into one loop and returns the very
arrays the code it replaces returns (its sums in its order; tested bit for bit,
``tests/test_solvers_kernels.py``), so a set-up gives the same operators either way: the symmetric Galerkin
level (both products, the two transposes, the merge, the next level's ``L + D/2`` split), the fine matrix's
relabelling, transpose and symmetry-probe products, the ``L + D/2`` split, the strong-coupling scan, the
diagonal-first swaps and the locality order's row minima. On the 1M-tet user meshes of docs/usermesh.md the
set-up took ~0.75x the CPU time of the numpy path (``benchmarks/user_mesh_solvers.py``).

Used when numba is installed (``pip install nestmg[fast]``), ``NESTMG_NUMBA`` is not "0", and the matrix has
at least :data:`MIN_NNZ` entries or numba is already loaded. numba is imported on first use, not with
``solvers``: loading it and the cached kernels costs ~0.5-1 s of CPU once per process (~7 s the very first
time, when the kernels are compiled and cached on disk, ``cache=True``), against ~25 ns per matrix entry saved
on each set-up: a process pays it back after a few dozen set-ups of a 1M-tet matrix, not on one.
"""

from __future__ import annotations

import functools
import importlib.util
import os

import numpy as np

#: numba can be imported (not imported yet: see :func:`wanted`)
AVAILABLE = importlib.util.find_spec("numba") is not None
#: whether the compiled kernels may be used (numba available and ``NESTMG_NUMBA`` not "0"); tests switch it
ENABLED = AVAILABLE and os.environ.get("NESTMG_NUMBA", "1") != "0"
#: the compiled kernels start with a matrix of at least this many entries (then serve every later call)
MIN_NNZ = 1_000_000
_state = {"loaded": False}


def wanted(nnz: int) -> bool:
    """Whether to run a compiled kernel on a matrix of ``nnz`` entries: :data:`ENABLED` and either numba is
    loaded already or the matrix is large enough to be worth loading it (:data:`MIN_NNZ`)."""
    return ENABLED and (_state["loaded"] or nnz >= MIN_NNZ)


def _jit(f):
    """``f`` compiled by ``numba.njit(cache=True, nogil=True)`` on its first call (numba imported then)."""
    compiled = []

    @functools.wraps(f)
    def call(*args):
        if not compiled:
            import numba

            compiled.append(numba.njit(cache=True, nogil=True)(f))
            _state["loaded"] = True
        return compiled[0](*args)

    return call


# Every index below is cast to uint64 (``_U``): numba wraps a negative signed index around, a test and a
# branch on each array access that cost these loops 1.5x (a CSR product with the casts ran as fast as
# scipy's, 3.3 ms against 5.3 without on a 2.5M-entry matrix). Mixed signed/unsigned arithmetic would be
# typed float64 by numba, hence the unsigned constants.
_U = np.uint64


@_jit
def relabelled_transpose(indptr, indices, data, inv, x, probe, tind, tdat):  # pragma: no cover - compiled
    """``Bᵀ`` in canonical CSR form for ``B`` = the rows of ``(indptr, indices, data)`` with their columns
    relabelled by ``inv`` (a permutation), and, when ``probe``, ``(B x, Bᵀ x, max |b_ij|)`` from the same
    pass: the relabelling ``take``, scipy's counting transpose and the two probe products in one (the same
    arrays as ``_transposed`` of the relabelled matrix). ``tind``, ``tdat``: the output's indices and values,
    of ``nnz`` entries, allocated by the caller (see :func:`lower_half`).

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
def lower_half(indptr, indices, data, sorted_rows, hind, hdat):  # pragma: no cover - compiled
    """The ``L + D/2`` split of :func:`solvers.transfer._lower_half` in one pass: the entries with column <=
    row in ``A``'s order, the diagonal ones halved, into ``hind``, ``hdat`` (allocated by numpy at ``nnz(A)``
    entries: numba's own allocations get no transparent huge pages, and their page faults cost more CPU
    than the loop saved, 10k faults against 7k per 1M-tet set-up). With ``sorted_rows`` a row's scan stops
    after its diagonal.

    Returns ``(indptr, diag, positions, half_positions)``: ``diag`` zero where a row stores no diagonal
    entry, the diagonal entries' positions in ``A`` and in the half (-1 where missing)."""
    one = _U(1)
    n = _U(indptr.size - 1)
    hptr = np.empty(n + one, indptr.dtype)
    hptr[0] = 0
    pos = np.full(n, -1, np.int64)
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
                    pos[r] = q
                    hpos[r] = w
                    v *= 0.5
                hdat[w] = v
                w += one
            elif sorted_rows:
                break
        hptr[r + one] = w
    return hptr, diag, pos, hpos


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


@_jit
def csr_matmat(aptr, aind, adat, bptr, bind, bdat, k, ncol, oind, odat,
               counts):  # pragma: no cover - compiled
    """``C = A B`` into ``oind``, ``odat`` (allocated by the caller at a bound of ``nnz(C)``): scipy's
    ``csr_matmat`` (the same sums in the same order, exact zeros dropped), each row's entries in the order
    they were first reached instead of scipy's linked-list order. ``k > 0``: every row of ``B`` holds ``k``
    entries (``bptr`` unused: a non-nested prolongation's four weights). ``counts``: ``ncol + 1`` zeros that
    receive the column counts of ``C`` at ``[c + 1]`` (the next transpose skips its counting pass), or empty.

    Returns ``C``'s row pointers (``nnz(C)`` their last)."""
    one = _U(1)
    kk = _U(k)
    n = _U(aptr.size - 1)
    count = counts.size > 0
    optr = np.empty(n + one, aptr.dtype)
    acc = np.zeros(ncol, odat.dtype)
    mark = np.zeros(ncol, np.uint64)  # 1 + the last row that reached the column
    w = _U(0)
    optr[0] = 0
    for i in range(n):
        stamp = i + one
        start = w
        for m in range(_U(aptr[i]), _U(aptr[i + one])):
            j = _U(aind[m])
            v = adat[m]
            s, e = (kk * j, kk * j + kk) if kk > 0 else (_U(bptr[j]), _U(bptr[j + one]))
            for q in range(s, e):
                b = _U(bind[q])
                if mark[b] != stamp:
                    mark[b] = stamp
                    acc[b] = v * bdat[q]
                    oind[w] = bind[q]
                    w += one
                else:
                    acc[b] += v * bdat[q]
        keep = start
        for q in range(start, w):
            b = _U(oind[q])
            if acc[b] != 0.0:
                oind[keep] = oind[q]
                odat[keep] = acc[b]
                keep += one
                if count:
                    counts[b + one] += 1
        w = keep
        optr[i + one] = w
    return optr


@_jit
def csr_transpose(ptr, ind, dat, ncol, counts, tind, tdat):  # pragma: no cover - compiled
    """``Bᵀ`` (canonical CSR: each row's entries in increasing column, the counting sort's order) into
    ``tind``, ``tdat``; ``counts``: :func:`csr_matmat`'s column counts of ``B``, or empty (counted here).
    Returns the row pointers."""
    one = _U(1)
    n = _U(ptr.size - 1)
    nxt = np.zeros(_U(ncol) + one, ptr.dtype)
    if counts.size > 0:
        nxt[:] = counts
    else:
        for q in range(_U(ptr[n])):
            nxt[_U(ind[q]) + one] += 1
    for c in range(_U(ncol)):
        nxt[c + one] += nxt[c]
    tptr = nxt.copy()
    for r in range(n):
        for q in range(_U(ptr[r]), _U(ptr[r + one])):
            c = _U(ind[q])
            w = _U(nxt[c])
            tind[w] = r
            tdat[w] = dat[q]
            nxt[c] += 1
    return tptr


@_jit
def symmetric_sum(ptr, ind, dat, tptr, tind, tdat, split, oind, odat, hind, hdat):  # pragma: no cover
    """``S = B + Bᵀ`` from ``B`` and ``Bᵀ`` in canonical form: one merge of each row pair, exact zeros
    dropped (scipy's ``csr_plus_csr`` on canonical operands: the same arrays), into ``oind``, ``odat``
    (allocated at ``nnz(B) + nnz(Bᵀ)``). With ``split`` also :func:`lower_half`'s split of ``S`` into
    ``hind``, ``hdat`` (same bound): the merge's sorted rows end their lower part with the diagonal.

    Returns ``(indptr, half_indptr, diag, positions, half_positions)``, the split's arrays empty without
    ``split`` (see :func:`lower_half`)."""
    one = _U(1)
    n = _U(ptr.size - 1)
    optr = np.empty(n + one, ptr.dtype)
    optr[0] = 0
    ns = n if split else _U(0)
    hptr = np.zeros(ns + one, ptr.dtype)
    diag = np.zeros(ns, odat.dtype)
    pos = np.full(ns, -1, np.int64)
    hpos = np.full(ns, -1, np.int64)
    w = _U(0)
    h = _U(0)
    for a in range(n):
        p, pe = _U(ptr[a]), _U(ptr[a + one])
        q, qe = _U(tptr[a]), _U(tptr[a + one])
        while p < pe or q < qe:
            if q >= qe or (p < pe and ind[p] < tind[q]):
                c, v = ind[p], dat[p]
                p += one
            elif p >= pe or tind[q] < ind[p]:
                c, v = tind[q], tdat[q]
                q += one
            else:
                c, v = ind[p], dat[p] + tdat[q]
                p += one
                q += one
            if v != 0.0:
                oind[w] = c
                odat[w] = v
                if split and _U(c) <= a:
                    hind[h] = c
                    if _U(c) == a:
                        diag[a] = v
                        pos[a] = w
                        hpos[a] = h
                        v *= 0.5
                    hdat[h] = v
                    h += one
                w += one
        optr[a + one] = w
        if split:
            hptr[a + one] = h
    return optr, hptr, diag, pos, hpos
