"""Triangle-triangle intersection tests without copyleft code (numpy + scipy only).

The nesting verifier and the input audit need two answers: which face pairs of two meshes
intersect or touch, and which face pairs of one mesh do. libigl's CGAL module answers both exactly
but is GPL; this module is the default engine of :mod:`cagegen` (CGAL stays available as
``engine="cgal"`` in :func:`cagegen._geometry.cross_intersection_pairs` and
:func:`cagegen._geometry.self_intersection_pairs`).

Decision rule
-------------
Two closed triangles intersect iff an edge of one meets the other (if they do, the ends of their
common segment lie on edges). A segment ``pq`` meets triangle ``abc`` iff ``p`` and ``q`` are not
strictly on the same side of the plane ``abc`` *and* the line ``pq`` does not pass strictly beside
one of the triangle's edges (the three orientations ``orient(p, q, a, b)``, ``(p, q, b, c)``,
``(p, q, c, a)`` do not take both strict signs).

Every orientation is a 3x3 determinant evaluated in floating point together with a forward error
bound (a multiple of Shewchuk's static bound for ``orient3d``, times a safety factor 16). A sign is
trusted only when ``|det|`` exceeds the bound; an uncertain sign counts as zero, i.e. as touching.
So "no intersection" is always exact, and the only possible error is a conservative one: a pair
whose configuration is degenerate to within ~1e-14 relative (touching, or coplanar with overlapping
bounding boxes) is reported. Touching counts as failing in the verifier anyway.

:func:`self_pairs` (the self-intersection test of the audit and the verifier) re-evaluates the
uncertain signs of predicates on input coordinates exactly (integer arithmetic on the floats), so there a zero
means exactly degenerate: neighbouring faces of one mesh are often coplanar to ~1e-16 (rotated
meshes, flat regions), and the conservative rule reported them as self-intersecting, i.e. refused
clean inputs (7 of 40 randomly rotated, scaled and shifted trimesh tori). Only the angle test of
faces sharing a vertex, which takes signs of *computed* vectors, stays conservative.

Pairs of one mesh that share a vertex or an edge are tested for overlap *beyond* the shared part:
for a shared edge, the two faces must not fold onto each other (coplanar, third vertices on the same
side); for a shared vertex, the opposite edges are tested as above and a face edge lying in the
other face's plane is tested for entering the other face's angle at the shared vertex.

Broad phase: face pairs whose bounding boxes (inflated by 1e-9 of the coordinates' magnitude for
rounding) overlap, found on a uniform grid; everything is vectorised, no Python loop over faces.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

__all__ = ["FaceGrid", "cross_pairs", "face_grid", "orient3d", "self_pairs"]

_EPS = np.finfo(np.float64).eps / 2  # unit roundoff 2^-53
#: Shewchuk's orient3d static bound (7 + 56 eps) eps, times a safety factor
_O3D_BOUND = 16.0 * (7.0 + 56.0 * _EPS) * _EPS


def _as_ints(*points) -> list[list[int]]:
    """Float coordinates as exact integers over one common power-of-two denominator."""
    ratios = [[float(x).as_integer_ratio() for x in p] for p in points]
    den = max(dd for r in ratios for _, dd in r)
    return [[n * (den // dd) for n, dd in r] for r in ratios]


def _exact_det3(a, b, c, d) -> int:
    """Exact sign of ``det[a - d, b - d, c - d]`` for one row (integer arithmetic on the exact floats)."""
    a, b, c, d = _as_ints(a, b, c, d)
    ad = [a[i] - d[i] for i in range(3)]
    bd = [b[i] - d[i] for i in range(3)]
    cd = [c[i] - d[i] for i in range(3)]
    det = (ad[0] * (bd[1] * cd[2] - bd[2] * cd[1]) + bd[0] * (cd[1] * ad[2] - cd[2] * ad[1])
           + cd[0] * (ad[1] * bd[2] - ad[2] * bd[1]))
    return (det > 0) - (det < 0)


def _exact_det3_rows(a: np.ndarray, b: np.ndarray, c: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Exact signs of ``det[a - d, b - d, c - d]`` for (k,3) rows of finite floats, vectorised.

    Every float is ``M 2^E`` with an integer mantissa ``|M| < 2^53`` (``np.frexp``); each row's values are
    put over its smallest exponent, ``M 2^(E - E_min)``, as Python integers in numpy object arrays, and the
    determinant is evaluated exactly in them. Same result as :func:`_exact_det3` row by row (checked in
    the tests), ~10x faster on the millions of rows an input with exactly coplanar faces produces.
    """
    P = np.stack([a, b, c, d], axis=1).reshape(len(a), 12)
    m, e = np.frexp(P)
    M = np.ldexp(m, 53).astype(np.int64)  # exact: |m| in [0.5, 1) has 53 significant bits
    E = e.astype(np.int64) - 53
    E = np.where(M == 0, np.iinfo(np.int64).max, E)
    emin = E.min(axis=1, keepdims=True)
    emin = np.where(emin == np.iinfo(np.int64).max, 0, emin)
    sh = np.where(M == 0, 0, E - emin)
    X = M.astype(object) * np.left_shift(np.ones_like(sh, dtype=object), sh.astype(object))
    X = X.reshape(len(a), 4, 3)
    ad, bd, cd = X[:, 0] - X[:, 3], X[:, 1] - X[:, 3], X[:, 2] - X[:, 3]
    det = (ad[:, 0] * (bd[:, 1] * cd[:, 2] - bd[:, 2] * cd[:, 1])
           + bd[:, 0] * (cd[:, 1] * ad[:, 2] - cd[:, 2] * ad[:, 1])
           + cd[:, 0] * (ad[:, 1] * bd[:, 2] - ad[:, 2] * bd[:, 1]))
    return np.array([(x > 0) - (x < 0) for x in det], dtype=np.int8)


def orient3d(a: np.ndarray, b: np.ndarray, c: np.ndarray, d: np.ndarray, exact: bool = False) -> np.ndarray:
    """Sign of ``det[a - d, b - d, c - d]`` row by row.

    Parameters
    ----------
    a, b, c, d : (k,3) float arrays
    exact : bool
        Re-evaluate the rows whose floating-point sign is not certain in exact integer arithmetic
        (0 then means exactly zero). False (default): 0 where the sign is not certain.

    Returns
    -------
    (k,) int8 array in {-1, 0, 1}.
    """
    ad, bd, cd = a - d, b - d, c - d
    t1 = bd[:, 1] * cd[:, 2]
    t2 = bd[:, 2] * cd[:, 1]
    t3 = cd[:, 1] * ad[:, 2]
    t4 = cd[:, 2] * ad[:, 1]
    t5 = ad[:, 1] * bd[:, 2]
    t6 = ad[:, 2] * bd[:, 1]
    det = ad[:, 0] * (t1 - t2) + bd[:, 0] * (t3 - t4) + cd[:, 0] * (t5 - t6)
    perm = (np.abs(ad[:, 0]) * (np.abs(t1) + np.abs(t2)) + np.abs(bd[:, 0]) * (np.abs(t3) + np.abs(t4))
            + np.abs(cd[:, 0]) * (np.abs(t5) + np.abs(t6)))
    s = np.sign(det).astype(np.int8)
    unsure = np.flatnonzero(np.abs(det) <= _O3D_BOUND * perm)
    s[unsure] = 0
    if exact and len(unsure) and np.all(np.isfinite(perm[unsure])):
        unsure = unsure[~_zero_column_or_row(ad[unsure], bd[unsure], cd[unsure])]  # exactly 0 already
        if len(unsure):
            s[unsure] = _exact_det3_rows(a[unsure], b[unsure], c[unsure], d[unsure])
    return s


def _zero_column_or_row(*rows: np.ndarray) -> np.ndarray:
    """(k,) bool: the square matrix whose rows are ``rows`` (difference vectors, (k,d) arrays, d of them) has a
    zero column or row, so its determinant is exactly 0.

    ``x - y`` is 0 in floating point iff ``x == y`` (gradual underflow), so a zero difference is exact:
    four points sharing one coordinate bit for bit (a zero column: an axis-aligned plane, as on CAD parts
    and on marching-cubes envelopes of them) or two equal points (a zero row). Those were >99% of the
    uncertain rows of a boxy assembly's sdf cage (400-750k rows per self-intersection test, 1-3 s each in
    :func:`_exact_det3_rows`'s integer arithmetic).
    """
    zero = np.stack([r == 0.0 for r in rows])  # (d, k, d)
    return zero.all(axis=0).any(axis=1) | zero.all(axis=2).any(axis=0)


_O2D_BOUND = 16.0 * (3.0 + 16.0 * _EPS) * _EPS


def _orient2d(a: np.ndarray, b: np.ndarray, c: np.ndarray, exact: bool = False) -> np.ndarray:
    """Sign of ``det[a - c, b - c]`` for (k,2) rows, 0 where not certain (``exact``: re-evaluated exactly)."""
    l = (a[:, 0] - c[:, 0]) * (b[:, 1] - c[:, 1])
    r = (a[:, 1] - c[:, 1]) * (b[:, 0] - c[:, 0])
    det = l - r
    s = np.sign(det).astype(np.int8)
    unsure = np.flatnonzero(np.abs(det) <= _O2D_BOUND * (np.abs(l) + np.abs(r)))
    s[unsure] = 0
    if exact and len(unsure):  # a zero column or row of [a - c, b - c] is exactly 0
        unsure = unsure[~_zero_column_or_row(a[unsure] - c[unsure], b[unsure] - c[unsure])]
    for i in unsure if exact else ():  # exact re-evaluation (the inputs are projected input coordinates)
        if np.all(np.isfinite(a[i])) and np.all(np.isfinite(b[i])) and np.all(np.isfinite(c[i])):
            A, B, C = _as_ints(a[i], b[i], c[i])
            e = (A[0] - C[0]) * (B[1] - C[1]) - (A[1] - C[1]) * (B[0] - C[0])
            s[i] = (e > 0) - (e < 0)
    return s


def _segments_meet_2d(p, q, a, b, exact: bool = False) -> np.ndarray:
    """(k,) bool: closed 2D segments ``pq`` and ``ab`` meet (or uncertain)."""
    o1, o2 = _orient2d(p, q, a, exact), _orient2d(p, q, b, exact)
    o3, o4 = _orient2d(a, b, p, exact), _orient2d(a, b, q, exact)
    meet = (o1 * o2 <= 0) & (o3 * o4 <= 0)
    # collinear (or uncertain): they meet only if their boxes overlap
    col = (o1 == 0) & (o2 == 0)
    if col.any():
        lo1, hi1 = np.minimum(p, q), np.maximum(p, q)
        lo2, hi2 = np.minimum(a, b), np.maximum(a, b)
        box = ((lo1 <= hi2) & (lo2 <= hi1)).all(axis=1)
        meet &= ~col | box
    return meet


def _segment_hits_triangle_2d(p, q, a, b, c, exact: bool = False) -> np.ndarray:
    """Segment and triangle (nearly) in one plane: test their projections along the dominant normal axis.

    Disjoint projections imply disjoint 3D sets, so the answer is never a false "no".
    """
    n = np.abs(np.cross(b - a, c - a))
    drop = n.argmax(axis=1)
    keep = np.array([[1, 2], [0, 2], [0, 1]])[drop]  # (k,2) coordinates kept
    r = np.arange(len(p))[:, None]
    P, Q, A, B, C = (x[r, keep] for x in (p, q, a, b, c))
    s = [_orient2d(A, B, X, exact) for X in (P, Q)] + [_orient2d(B, C, X, exact) for X in (P, Q)] + \
        [_orient2d(C, A, X, exact) for X in (P, Q)]
    in_p = ~(np.stack(s[0::2], 1).max(1) > 0) | ~(np.stack(s[0::2], 1).min(1) < 0)
    in_q = ~(np.stack(s[1::2], 1).max(1) > 0) | ~(np.stack(s[1::2], 1).min(1) < 0)
    return (in_p | in_q | _segments_meet_2d(P, Q, A, B, exact) | _segments_meet_2d(P, Q, B, C, exact)
            | _segments_meet_2d(P, Q, C, A, exact))


def _segment_hits_triangle(p, q, a, b, c, exact: bool = False) -> np.ndarray:
    """(k,) bool: closed segment ``pq`` meets closed triangle ``abc`` (or the decision is uncertain;
    ``exact``: uncertain signs are re-evaluated exactly, so only exact contact counts)."""
    sp = orient3d(a, b, c, p, exact)
    sq = orient3d(a, b, c, q, exact)
    straddle = sp * sq <= 0  # not strictly on one side of the plane
    hit = np.zeros(len(p), dtype=bool)
    flat = straddle & (sp == 0) & (sq == 0)  # segment in the plane: the line test says nothing
    idx = np.flatnonzero(straddle & ~flat)
    if idx.size:
        P, Q, A, B, C = p[idx], q[idx], a[idx], b[idx], c[idx]
        s1 = orient3d(P, Q, A, B, exact)
        s2 = orient3d(P, Q, B, C, exact)
        s3 = orient3d(P, Q, C, A, exact)
        S = np.stack([s1, s2, s3], axis=1)
        hit[idx] = ~((S > 0).any(axis=1) & (S < 0).any(axis=1))  # no two strict opposite signs
    idx = np.flatnonzero(flat)
    if idx.size:
        hit[idx] = _segment_hits_triangle_2d(p[idx], q[idx], a[idx], b[idx], c[idx], exact)
    return hit


def _cells(lo, hi, origin, cell, dims, clip: bool = False):
    """Grid cells overlapped by each box: (entries,) face ids, (entries,) int64 cell keys and the (m,3) int64
    cell of each box's lower corner (``clip``: box parts outside the grid go to its border cells)."""
    i0 = np.floor((lo - origin) / cell).astype(np.int64)
    i1 = np.floor((hi - origin) / cell).astype(np.int64)
    if clip:
        i0, i1 = np.clip(i0, 0, dims - 1), np.clip(i1, 0, dims - 1)
    n = i1 - i0 + 1  # (m,3) cells per axis
    tot = n.prod(axis=1)
    ids = np.repeat(np.arange(len(lo)), tot)
    k = np.arange(int(tot.sum())) - np.repeat(np.cumsum(tot) - tot, tot)
    nx, ny = n[ids, 0], n[ids, 1]
    cx = i0[ids, 0] + k % nx
    cy = i0[ids, 1] + (k // nx) % ny
    cz = i0[ids, 2] + k // (nx * ny)
    return ids, (cx * dims[1] + cy) * dims[2] + cz, i0


def _candidates(VA, FA, VB, FB, slop, upper: bool = False):
    """Candidate (face of A, face of B) pairs whose bounding boxes overlap, (k,2) int64 sorted by rows.

    Uniform-grid broad phase, fully vectorised: every box is entered into the cells it overlaps (cell
    size ~ the median face extent), entries of A and B with the same cell key are paired through
    sorted searches, each pair is kept in one cell only (:func:`_overlapping`) and the boxes are compared.
    ``upper``: only pairs ``a < b`` (A and B the same mesh).
    """
    TA, TB = VA[FA], VB[FB]
    loA, hiA = TA.min(axis=1) - slop, TA.max(axis=1) + slop
    loB, hiB = TB.min(axis=1) - slop, TB.max(axis=1) + slop
    origin = np.minimum(loA.min(axis=0), loB.min(axis=0))
    top = np.maximum(hiA.max(axis=0), hiB.max(axis=0))
    ext = np.concatenate([(hiA - loA).max(axis=1), (hiB - loB).max(axis=1)])
    cell = max(float(np.median(ext)), float((top - origin).max()) / 2.0**18, 1e-300)
    dims = np.floor((top - origin) / cell).astype(np.int64) + 2
    idA, keyA, cornerA = _cells(loA, hiA, origin, cell, dims)
    order = np.argsort(keyA, kind="stable")
    if upper:
        ia, ib, key = _same_cell_upper(keyA[order], idA[order])
        return _overlapping(ia, ib, key, len(FB), (loA, hiA, cornerA), (loA, hiA, cornerA), dims)
    idB, keyB, cornerB = _cells(loB, hiB, origin, cell, dims)
    ib, ia, key = _same_cell(idB, keyB, keyA[order], idA[order])
    return _overlapping(ia, ib, key, len(FB), (loA, hiA, cornerA), (loB, hiB, cornerB), dims)


def _same_cell(id_q, key_q, keys, ids) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every (query entry's face, indexed entry's face, their cell key) sharing a cell (``keys`` sorted,
    ``ids`` alike)."""
    left = np.searchsorted(keys, key_q, side="left")
    cnt = np.searchsorted(keys, key_q, side="right") - left
    total = int(cnt.sum())
    pos = np.repeat(left, cnt) + (np.arange(total) - np.repeat(np.cumsum(cnt) - cnt, cnt))
    return np.repeat(id_q, cnt), ids[pos], np.repeat(key_q, cnt)


def _same_cell_upper(keys, ids) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every (face, later face in the cell, their cell key) of one mesh's entries (``keys`` sorted, ``ids``
    alike and ascending within a cell: a stable sort of :func:`_cells`' entries): each unordered pair of a
    cell once, ``a < b``, and no face with itself (half the pairs of :func:`_same_cell` against itself)."""
    n = len(keys)
    start = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]]) if n else np.zeros(0, dtype=np.int64)
    ends = np.r_[start[1:], n]
    cnt = np.repeat(ends, np.diff(np.r_[start, n])) - np.arange(n) - 1  # later entries of the same cell
    total = int(cnt.sum())
    first = np.repeat(np.arange(n), cnt)
    later = first + 1 + (np.arange(total) - np.repeat(np.cumsum(cnt) - cnt, cnt))
    return ids[first], ids[later], keys[first]


def _overlapping(ia, ib, key, mB: int, boxA, boxB, dims) -> np.ndarray:
    """The distinct pairs ``(ia, ib)`` whose boxes overlap, (k,2) sorted by ``(ia, ib)``; ``key``: the cell
    in which each pair was found, ``boxA`` / ``boxB``: ``(lo, hi, corner cell)`` of the faces.

    Two overlapping boxes share exactly one cell holding the lower corner of their intersection, the cell
    ``max(corner_a, corner_b)`` per axis (integers: no rounding); a pair is kept in that cell only, which
    removes the duplicates of pairs sharing several cells without hashing or sorting them all (``np.unique``
    was 45% of a 342k-face input's audit)."""
    (loA, hiA, cA), (loB, hiB, cB) = boxA, boxB
    c = np.maximum(cA[ia], cB[ib])
    m = (c[:, 0] * dims[1] + c[:, 1]) * dims[2] + c[:, 2] == key
    ia, ib = ia[m], ib[m]
    m = ((loA[ia] <= hiB[ib]) & (loB[ib] <= hiA[ia])).all(axis=1)
    pair = np.sort(ia[m] * mB + ib[m])
    return np.stack([pair // mB, pair % mB], axis=1)


class FaceGrid(NamedTuple):
    """:func:`face_grid`: the uniform-grid broad phase of one mesh, for repeated :func:`cross_pairs` queries."""

    V: np.ndarray
    F: np.ndarray
    lo: np.ndarray  # (m,3) face boxes
    hi: np.ndarray
    inflate: float  # the cells hold the boxes grown by this much
    origin: np.ndarray
    cell: float
    dims: np.ndarray
    keys: np.ndarray  # sorted cell keys of the entries
    ids: np.ndarray  # their faces
    corner: np.ndarray  # (m,3) cell of each entered box's lower corner


#: :func:`face_grid` enters boxes grown by this many times the mesh's own slop (:func:`_slop`): a query's
#: slop (of both meshes) up to it finds the same candidates as :func:`_candidates`
GRID_SLOP_FACTOR = 4.0


def face_grid(V: np.ndarray, F: np.ndarray) -> FaceGrid:
    """Index the faces of a mesh that :func:`cross_pairs` will test many times (a fixed input against a
    changing cage): its cells are built once instead of at every query. Cell size: the median face box."""
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    T = V[F]
    lo, hi = T.min(axis=1), T.max(axis=1)
    inflate = GRID_SLOP_FACTOR * _slop(V)
    origin, top = lo.min(axis=0) - inflate, hi.max(axis=0) + inflate
    cell = max(float(np.median((hi - lo).max(axis=1))), float((top - origin).max()) / 2.0**18, 1e-300)
    dims = np.floor((top - origin) / cell).astype(np.int64) + 2
    ids, keys, corner = _cells(lo - inflate, hi + inflate, origin, cell, dims)
    order = np.argsort(keys, kind="stable")
    return FaceGrid(V, F, lo, hi, inflate, origin, cell, dims, keys[order], ids[order], corner)


def _grid_candidates(VA, FA, grid: FaceGrid, slop: float) -> np.ndarray:
    """:func:`_candidates` of ``(VA, FA)`` against the indexed mesh (the same pairs for ``slop`` up to the
    grid's ``inflate``: every pair of boxes that overlap shares a cell of the grid)."""
    TA = VA[FA]
    loA, hiA = TA.min(axis=1) - slop, TA.max(axis=1) + slop
    idA, keyA, cornerA = _cells(loA, hiA, grid.origin, grid.cell, grid.dims, clip=True)
    ia, ib, key = _same_cell(idA, keyA, grid.keys, grid.ids)
    return _overlapping(ia, ib, key, len(grid.F), (loA, hiA, cornerA), (grid.lo - slop, grid.hi + slop, grid.corner),
                        grid.dims)


def _tri_tri(TA: np.ndarray, TB: np.ndarray, exact: bool = False) -> np.ndarray:
    """(k,) bool: closed triangles ``TA[i]`` and ``TB[i]`` ((k,3,3) arrays) meet (or uncertain)."""
    hit = np.zeros(len(TA), dtype=bool)
    for X, Y in ((TA, TB), (TB, TA)):
        for i, j in ((0, 1), (1, 2), (2, 0)):
            todo = ~hit
            if not todo.any():
                break
            hit[todo] |= _segment_hits_triangle(X[todo, i], X[todo, j], Y[todo, 0], Y[todo, 1], Y[todo, 2], exact)
    return hit


def _slop(*Vs) -> float:
    ext = max(float(np.abs(V).max()) for V in Vs)
    return 1e-9 * max(ext, 1e-300)


def cross_pairs(VA: np.ndarray, FA: np.ndarray, VB: np.ndarray, FB: np.ndarray,
                grid: FaceGrid | None = None) -> np.ndarray:
    """Face pairs ``(a, b)`` of two meshes that intersect or touch.

    Parameters
    ----------
    VA : (nA,3) float array
    FA : (mA,3) int array
    VB : (nB,3) float array
    FB : (mB,3) int array
    grid : FaceGrid, optional
        :func:`face_grid` of ``(VB, FB)`` (the same arrays): its cells are reused (the same pairs).

    Returns
    -------
    (k,2) int64 array: column 0 indexes ``FA``, column 1 ``FB``, sorted lexicographically.

    Examples
    --------
    >>> import numpy as np
    >>> V = np.array([[0., 0, 0], [1, 0, 0], [0, 1, 0]]); F = np.array([[0, 1, 2]])
    >>> cross_pairs(V, F, V + [0.2, 0.2, -0.5] + [[0, 0, 0], [0, 0, 1], [0, 0, 1]], F).tolist()
    [[0, 0]]
    >>> cross_pairs(V, F, V + [0, 0, 0.1], F).tolist()
    []
    """
    VA = np.asarray(VA, dtype=np.float64)
    VB = np.asarray(VB, dtype=np.float64)
    FA = np.asarray(FA, dtype=np.int64)
    FB = np.asarray(FB, dtype=np.int64)
    slop = _slop(VA, VB)
    if grid is not None and slop <= grid.inflate:
        C = _grid_candidates(VA, FA, grid, slop)
    else:
        C = _candidates(VA, FA, VB, FB, slop)
    if not len(C):
        return C
    hit = _tri_tri(VA[FA[C[:, 0]]], VB[FB[C[:, 1]]])
    out = C[hit]
    return out[np.lexsort((out[:, 1], out[:, 0]))]


def _separated(R: np.ndarray, P: list, Q: list, directions: list, apex: bool = False) -> np.ndarray:
    """(k,) bool: some direction ``w`` of ``directions`` ((k,3) arrays) certainly separates the points ``P``
    from the points ``Q`` (lists of (k,3) arrays) in floating point: their projections ``(X - R) . w`` lie in
    disjoint intervals farther apart than the rounding error. Projections are linear, so the convex hulls
    (the triangles) are then disjoint. ``apex``: ``R`` is a point both triangles share and only the rest must
    be separated: ``P`` strictly above 0, ``Q`` strictly below, or the reverse (the hulls meet at ``R`` only).

    ``fl(x - r) = (x - r)(1 + d)``, ``|d| <= u`` (u = 2^-53), and a 3-term dot product adds ``3u`` of
    ``sum |d_i w_i|``: each computed projection is within ``5u sum |d_i| |w_i|`` of the exact one for the
    float ``w``; the margin is 32u times ``max |d| |w|``, a bound of the largest such sum. Any ``w`` gives a
    sound certificate; a row no direction certifies is left to the exact tests (False here)."""
    D = [X - R for X in (*P, *Q)]
    # sum |d_i| |w_i| <= |d| |w| (Cauchy-Schwarz): one norm per point instead of one sum per point and direction
    dmax = np.sqrt(np.maximum.reduce([np.einsum("ij,ij->i", d, d) for d in D]))
    out = np.zeros(len(R), dtype=bool)
    for w in directions:
        err = 32.0 * _EPS * dmax * np.sqrt(np.einsum("ij,ij->i", w, w))
        proj = [np.einsum("ij,ij->i", d, w) for d in D]
        pmin, pmax = np.minimum.reduce(proj[: len(P)]), np.maximum.reduce(proj[: len(P)])
        qmin, qmax = np.minimum.reduce(proj[len(P):]), np.maximum.reduce(proj[len(P):])
        if apex:
            out |= ((pmin > err) & (qmax < -err)) | ((pmax < -err) & (qmin > err))
        else:
            out |= (pmax + 2.0 * err < qmin) | (qmax + 2.0 * err < pmin)
    return out


def _unit(x: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(x, axis=1, keepdims=True)
    return np.divide(x, n, out=np.zeros_like(x), where=n > 0)


def _disjoint_hits(TA: np.ndarray, TB: np.ndarray) -> np.ndarray:
    """(k,) bool: triangles sharing no vertex meet. A floating-point separation certificate first (the two
    planes' normals and the in-plane normals of the six edges, the separating axes of coplanar triangles);
    the exact test only for the rest (on a finely tessellated CAD part, neighbours are nearly coplanar and
    the exact arithmetic was most of the audit)."""
    A, B = [TA[:, i] for i in range(3)], [TB[:, i] for i in range(3)]
    nA, nB = np.cross(A[1] - A[0], A[2] - A[0]), np.cross(B[1] - B[0], B[2] - B[0])
    n = _unit(nA) + _unit(nB)
    edges = [A[1] - A[0], A[2] - A[1], A[0] - A[2], B[1] - B[0], B[2] - B[1], B[0] - B[2]]
    sep = _separated(A[0], A, B, [nA, nB] + [np.cross(n, e) for e in edges])
    hit = np.zeros(len(TA), dtype=bool)
    todo = np.flatnonzero(~sep)
    if todo.size:
        hit[todo] = _tri_tri(TA[todo], TB[todo], exact=True)
    return hit


def _shared_edge_hits(V: np.ndarray, FA: np.ndarray, FB: np.ndarray, eq: np.ndarray) -> np.ndarray:
    """(k,) bool: triangles sharing an edge meet beyond it: a fold onto each other (the third vertices on the
    same side of the edge, then coplanar exactly; the side test first, so a flat region's neighbours, on
    opposite sides, need no exact test)."""
    inA = eq.any(axis=2)  # (k,3) which vertices of A are shared
    inB = eq.any(axis=1)
    sa = np.sort(np.where(inA, FA, -1), axis=1)[:, 1:]  # the two shared vertex ids
    ua, ub = FA[~inA], FB[~inB]
    s, t = V[sa[:, 0]], V[sa[:, 1]]
    n1 = np.cross(t - s, V[ua] - s)
    n2 = np.cross(t - s, V[ub] - s)
    dot = np.einsum("ij,ij->i", n1, n2)
    same_side = dot > -1e-12 * np.linalg.norm(n1, axis=1) * np.linalg.norm(n2, axis=1)
    hit = np.zeros(len(FA), dtype=bool)
    k = np.flatnonzero(same_side)
    if k.size:
        hit[k] = orient3d(s[k], t[k], V[ua[k]], V[ub[k]], exact=True) == 0
    return hit


def _shared_vertex_hits(V: np.ndarray, FA: np.ndarray, FB: np.ndarray, eq: np.ndarray) -> np.ndarray:
    """(k,) bool: triangles sharing one vertex S meet beyond it. A floating-point certificate first: a plane
    through S with the rest of A strictly on one side and the rest of B on the other (candidates: bisectors
    of one edge of each at S, in the mean plane; the difference of the two corners' bisectors). The rest:
    opposite edges against the other face, in-plane edges against the other's angle at S (exact)."""
    ia = eq.any(axis=2).argmax(axis=1)  # position of the shared vertex in A
    ib = eq.any(axis=1).argmax(axis=1)  # ... in B
    r = np.arange(len(FA))
    S = V[FA[r, ia]]
    A1, A2 = V[FA[r, (ia + 1) % 3]], V[FA[r, (ia + 2) % 3]]
    B1, B2 = V[FB[r, (ib + 1) % 3]], V[FB[r, (ib + 2) % 3]]
    ua, va, ub, vb = (_unit(X - S) for X in (A1, A2, B1, B2))
    n = _unit(np.cross(ua, va)) + _unit(np.cross(ub, vb))
    cands = [np.cross(n, x + y) for x in (ua, va) for y in (ub, vb)] + [ua + va - ub - vb]
    todo = np.flatnonzero(~_separated(S, [A1, A2], [B1, B2], cands, apex=True))
    hit = np.zeros(len(FA), dtype=bool)
    if todo.size:
        hit[todo] = _shared_vertex_exact(S[todo], A1[todo], A2[todo], B1[todo], B2[todo])
    return hit


def _shared_vertex_exact(S, A1, A2, B1, B2) -> np.ndarray:
    """The exact test of :func:`_shared_vertex_hits` on triangles ``S A1 A2`` and ``S B1 B2``."""
    nA = np.cross(A1 - S, A2 - S)
    nB = np.cross(B1 - S, B2 - S)
    h = np.zeros(len(S), dtype=bool)
    # edge S-X lies in the other face's plane (uncertain = yes) and enters its angle at S
    combos = ((B1, nA, A1, A2), (B2, nA, A1, A2), (A1, nB, B1, B2), (A2, nB, B1, B2))
    inplane = [orient3d(Y1, Y2, X, S, exact=True) == 0 for X, _, Y1, Y2 in combos]
    for (X, nX, Y1, Y2), ip in zip(combos, inplane):
        k = np.flatnonzero(ip)
        if k.size:
            h[k] |= _ray_in_angle(X[k] - S[k], Y1[k] - S[k], Y2[k] - S[k], nX[k])
    # not coplanar: the common part beyond S ends on an opposite edge
    coplanar = (inplane[0] & inplane[1]) | (inplane[2] & inplane[3])
    k = np.flatnonzero(~coplanar & ~h)
    if k.size:
        h[k] = (_segment_hits_triangle(A1[k], A2[k], S[k], B1[k], B2[k], exact=True)
                | _segment_hits_triangle(B1[k], B2[k], S[k], A1[k], A2[k], exact=True))
    return h


def _ray_in_angle(r, u, v, n) -> np.ndarray:
    """(k,) bool: direction ``r`` lies in the closed planar angle spanned by ``u``, ``v`` (normal ``n``),
    or the decision is uncertain. All vectors are relative to the apex; ``n = u x v``."""
    z = np.zeros_like(r)
    s1 = orient3d(u, r, n, z)  # sign of det[u, r, n] = (u x r) . n (computed vectors: conservative)
    s2 = orient3d(r, v, n, z)
    return (s1 >= 0) & (s2 >= 0)


def self_pairs(V: np.ndarray, F: np.ndarray, only=None) -> np.ndarray:
    """Face pairs of one mesh that intersect beyond what they share (a vertex or an edge).

    Parameters
    ----------
    V : (n,3) float array
    F : (m,3) int array
    only : int array, optional
        Report only pairs with at least one face in ``only`` (indices into ``F``); the pairs between
        two other faces are not tested (a local edit of a mesh known to be clean: the new faces).

    Returns
    -------
    (k,2) int64 array of face indices, ``k[:,0] < k[:,1]``, sorted lexicographically.

    Examples
    --------
    >>> import trimesh
    >>> s = trimesh.creation.icosphere(subdivisions=2)
    >>> len(self_pairs(s.vertices, s.faces))
    0
    """
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    if only is None:
        C = _candidates(V, F, V, F, _slop(V), upper=True)
    else:
        rows = np.unique(np.asarray(only, dtype=np.int64))
        C = _candidates(V, F[rows], V, F, _slop(V)) if len(rows) else np.zeros((0, 2), dtype=np.int64)
        C[:, 0] = rows[C[:, 0]]
        C = np.sort(C[C[:, 0] != C[:, 1]], axis=1)
        key = np.unique(C[:, 0] * len(F) + C[:, 1])  # the sorted unique rows (faster than unique(axis=0))
        C = np.stack([key // len(F), key % len(F)], axis=1)
    if not len(C):
        return C
    FA, FB = F[C[:, 0]], F[C[:, 1]]
    eq = FA[:, :, None] == FB[:, None, :]  # (k,3,3): vertex i of A is vertex j of B
    n_shared = eq.sum(axis=(1, 2))
    hit = np.zeros(len(C), dtype=bool)
    m0 = np.flatnonzero(n_shared == 0)
    if m0.size:
        hit[m0] = _disjoint_hits(V[FA[m0]], V[FB[m0]])
    m2 = np.flatnonzero(n_shared == 2)
    if m2.size:
        hit[m2] = _shared_edge_hits(V, FA[m2], FB[m2], eq[m2])
    m1 = np.flatnonzero(n_shared == 1)
    if m1.size:
        hit[m1] = _shared_vertex_hits(V, FA[m1], FB[m1], eq[m1])
    # three shared vertices: a duplicated face
    hit[n_shared == 3] = True
    out = C[hit]
    return out[np.lexsort((out[:, 1], out[:, 0]))]
