"""Vectorised mesh primitives shared by the audit, the verifier and the decimation backend.

Everything here takes plain arrays and returns plain arrays or numbers; nothing modifies its input.
Edge statistics come from one ``np.unique`` over integer edge keys (no per-element Python loops);
exact intersection tests come from :mod:`cagegen.intersect` (filtered floating-point predicates, no
copyleft code) or, as an option, libigl's CGAL bindings (``igl.copyleft.cgal``, GPL).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import CageOptionError, MeshInputError


def as_mesh_arrays(V, F, name: str = "input") -> tuple[np.ndarray, np.ndarray]:
    """Validate shapes and dtypes and return C-contiguous float64 / int64 *copies*.

    Only structural problems are checked here (what makes every other check impossible):
    array-ness, shapes, dtypes, emptiness and index range.

    Parameters
    ----------
    V : (n,3) array_like of real numbers
    F : (m,3) array_like of integers
    name : str
        Name used in error messages.

    Returns
    -------
    V : (n,3) float64 array (a copy)
    F : (m,3) int64 array (a copy)

    Raises
    ------
    MeshInputError
        Wrong shape or dtype, empty arrays, or face indices out of ``range(n)``.
    """
    try:
        Va = np.asarray(V)
        Fa = np.asarray(F)
    except Exception as exc:  # ragged lists and the like
        raise MeshInputError(f"{name}: V and F must be array-like ({exc})") from exc
    if Va.dtype == object or Fa.dtype == object:
        raise MeshInputError(f"{name}: V and F must be numeric arrays, got dtype object (ragged input?)")
    if Va.ndim != 2 or Va.shape[1] != 3:
        raise MeshInputError(f"{name}: V must have shape (n, 3), got {Va.shape}")
    if Fa.ndim != 2 or Fa.shape[1] != 3:
        raise MeshInputError(f"{name}: F must have shape (m, 3) (triangles), got {Fa.shape}")
    if Va.shape[0] == 0:
        raise MeshInputError(f"{name}: empty mesh (no vertices)")
    if Fa.shape[0] == 0:
        raise MeshInputError(f"{name}: empty mesh (no faces)")
    if Va.dtype == bool or not (np.issubdtype(Va.dtype, np.floating) or np.issubdtype(Va.dtype, np.integer)):
        raise MeshInputError(f"{name}: V must hold real numbers, got dtype {Va.dtype}")
    if Fa.dtype == bool or not np.issubdtype(Fa.dtype, np.integer):
        raise MeshInputError(f"{name}: F must be an integer array, got dtype {Fa.dtype}")
    Vc = np.array(Va, dtype=np.float64, order="C", copy=True)
    Fc = np.array(Fa, dtype=np.int64, order="C", copy=True)
    lo, hi = int(Fc.min()), int(Fc.max())
    if lo < 0 or hi >= Vc.shape[0]:
        bad = int(np.count_nonzero((Fc < 0) | (Fc >= Vc.shape[0])))
        raise MeshInputError(
            f"{name}: {bad} face indices out of range [0, {Vc.shape[0]}) (min {lo}, max {hi})"
        )
    return Vc, Fc


def bbox_diagonal(V: np.ndarray) -> float:
    """Length of the axis-aligned bounding-box diagonal of ``V`` (n,3).

    Computed as ``s * |ext / s|`` with ``s`` the largest extent, so that it neither underflows to 0
    (extents ~1e-200) nor overflows to inf (extents ~1e200) when squaring.

    Parameters
    ----------
    V : (n,3) float array

    Returns
    -------
    float
        The diagonal (0 when all points coincide; inf or nan passed through for non-finite input).

    Examples
    --------
    >>> import numpy as np
    >>> bbox_diagonal(np.array([[0.0, 0, 0], [3, 4, 12]]))
    13.0
    """
    ext = np.abs(V.max(axis=0) - V.min(axis=0))
    s = float(ext.max())
    if s == 0.0 or not np.isfinite(s):
        return s
    return s * float(np.linalg.norm(ext / s))


def normalize(V: np.ndarray, unit: float | None = None) -> tuple[np.ndarray, np.ndarray, float]:
    """The one bounding-box normalisation of the project: ``Vn = (V - center) / unit``.

    ``center`` is the bounding box's centre; ``unit`` defaults to :func:`bbox_diagonal` (a unit-diagonal
    copy centred at the origin, the frame of every relative length). Undo with ``Vn * unit + center``.

    Parameters
    ----------
    V : (n,3) float array
    unit : float, optional
        Scale to divide by (a backend may keep its own measure of the diagonal, or the input's when
        normalising a later layer in the input's frame).

    Returns
    -------
    Vn : (n,3) float array
    center : (3,) float array
    unit : float

    Examples
    --------
    >>> import numpy as np
    >>> Vn, c, s = normalize(np.array([[0.0, 0, 0], [3, 4, 12]]))
    >>> c.tolist(), s, Vn[1].round(4).tolist()
    ([1.5, 2.0, 6.0], 13.0, [0.1154, 0.1538, 0.4615])
    """
    lo, hi = V.min(axis=0), V.max(axis=0)
    center = 0.5 * (lo + hi)
    unit = bbox_diagonal(V) if unit is None else float(unit)
    return (V - center) / unit, center, unit


def signed_volume(V: np.ndarray, F: np.ndarray) -> float:
    """Signed enclosed volume of a closed triangle mesh (divergence theorem).

    Sum over faces of ``det(a-c, b-c, d-c) / 6`` with ``c`` the centroid of ``V`` (subtracting it
    keeps the sum accurate for meshes far from the origin). Positive for outward-oriented faces.
    """
    c = V.mean(axis=0)
    a, b, d = V[F[:, 0]] - c, V[F[:, 1]] - c, V[F[:, 2]] - c
    return float(np.einsum("ij,ij->", a, np.cross(b, d)) / 6.0)


def double_areas(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Twice the area of each face, (m,) float64."""
    return np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)


@dataclass
class EdgeStats:
    """Edge-face incidence summary of a triangle mesh.

    Attributes
    ----------
    n_edges : int
        Number of distinct undirected edges.
    n_boundary_edges : int
        Edges with exactly one incident face (an open surface).
    n_nonmanifold_edges : int
        Edges with three or more incident faces.
    n_inconsistent_edges : int
        Two-face edges traversed twice in the same direction (inconsistent orientation).
    edges : (e,2) int64 array
        The distinct undirected edges, ``edges[:, 0] < edges[:, 1]``.
    counts : (e,) int64 array
        Number of incident faces per edge.
    """

    n_edges: int
    n_boundary_edges: int
    n_nonmanifold_edges: int
    n_inconsistent_edges: int
    edges: np.ndarray
    counts: np.ndarray

    @property
    def closed_manifold(self) -> bool:
        """True when every edge has exactly two incident faces, traversed in opposite directions."""
        return self.n_boundary_edges == 0 and self.n_nonmanifold_edges == 0 and self.n_inconsistent_edges == 0


def edge_stats(F: np.ndarray, n_vertices: int | None = None) -> EdgeStats:
    """Count boundary, non-manifold and inconsistently oriented edges of ``F`` (m,3).

    Half-edges ``(F[:,k], F[:,k+1])`` are encoded as integer keys ``i*n + j``; one ``np.unique`` on
    the undirected keys gives face counts per edge, one on the directed keys finds edges that two
    faces traverse in the same direction.
    """
    n = int(F.max()) + 1 if n_vertices is None else int(n_vertices)
    he = np.stack([F, np.roll(F, -1, axis=1)], axis=2).reshape(-1, 2)  # (3m,2) directed half-edges
    lo = he.min(axis=1)
    hi = he.max(axis=1)
    und_key = lo * n + hi
    ukeys, uinv, counts = np.unique(und_key, return_inverse=True, return_counts=True)
    edges = np.stack([ukeys // n, ukeys % n], axis=1)
    # directed duplicates on edges with exactly two faces: both faces use i->j (orientation flip)
    dir_key = he[:, 0] * n + he[:, 1]
    two = counts[uinv] == 2
    dk = np.sort(dir_key[two])
    n_incons = int(np.count_nonzero(dk[1:] == dk[:-1])) if dk.size > 1 else 0
    return EdgeStats(
        n_edges=int(ukeys.size),
        n_boundary_edges=int(np.count_nonzero(counts == 1)),
        n_nonmanifold_edges=int(np.count_nonzero(counts > 2)),
        n_inconsistent_edges=n_incons,
        edges=edges,
        counts=counts,
    )


def vertex_components(F: np.ndarray, n_vertices: int) -> np.ndarray:
    """Label of each vertex's edge-connected component of the faces ``F`` (an unreferenced vertex is a
    component of its own)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    i = F.ravel()
    j = np.roll(F, -1, axis=1).ravel()
    A = sp.coo_matrix((np.ones(i.size, dtype=np.int8), (i, j)), shape=(n_vertices, n_vertices)).tocsr()
    return connected_components(A, directed=False)[1]


def n_components(F: np.ndarray, n_vertices: int) -> int:
    """Number of edge-connected components of the faces ``F`` (unreferenced vertices ignored)."""
    return int(np.unique(vertex_components(F, n_vertices)[np.unique(F)]).size)


#: Engine of the exact intersection tests: ``"filtered"`` (default; :mod:`cagegen.intersect`, numpy
#: and scipy only) or ``"cgal"`` (libigl's ``igl.copyleft.cgal``, GPL; an option, never required).
INTERSECTION_ENGINES = ("filtered", "cgal")
DEFAULT_INTERSECTION_ENGINE = "filtered"


def _engine(engine: str | None) -> str:
    engine = DEFAULT_INTERSECTION_ENGINE if engine is None else engine
    if engine not in INTERSECTION_ENGINES:
        raise CageOptionError(f"intersection engine must be one of {INTERSECTION_ENGINES}, got {engine!r}")
    return engine


def self_intersection_pairs(V: np.ndarray, F: np.ndarray, engine: str | None = None) -> np.ndarray:
    """Pairs of faces of one mesh that intersect (exact decision, see :mod:`cagegen.intersect`).

    Faces sharing a vertex or an edge are only reported if they overlap beyond that shared part.
    ``engine``: ``"filtered"`` (default, no copyleft code) or ``"cgal"`` (``igl.copyleft.cgal``, GPL).

    Returns
    -------
    (k,2) int64 array of face indices into ``F``.
    """
    if _engine(engine) == "filtered":
        from .intersect import self_pairs

        return self_pairs(V, F)
    from igl.copyleft import cgal

    out = cgal.remesh_self_intersections(V, F, detect_only=True)
    return np.asarray(out[2], dtype=np.int64).reshape(-1, 2)


def cross_intersection_pairs(
    VA: np.ndarray, FA: np.ndarray, VB: np.ndarray, FB: np.ndarray, engine: str | None = None
) -> np.ndarray:
    """Pairs ``(a, b)`` of faces of mesh A and mesh B that intersect or touch (exact decision).

    Touching (a vertex of one surface exactly on the other) counts as an intersection. ``engine``:
    ``"filtered"`` (default, :mod:`cagegen.intersect`; also reports pairs that touch to within
    rounding, ~1e-16 of the coordinates) or ``"cgal"`` (``igl.copyleft.cgal``, GPL).

    Returns
    -------
    (k,2) int64 array: column 0 indexes ``FA``, column 1 indexes ``FB``.
    """
    if _engine(engine) == "filtered":
        from .intersect import cross_pairs

        return cross_pairs(VA, FA, VB, FB)
    from igl.copyleft import cgal

    out = cgal.intersect_other(VA, FA, VB, FB, detect_only=True)
    return np.asarray(out[0], dtype=np.int64).reshape(-1, 2)


def segment_segment_sqdist(P0: np.ndarray, P1: np.ndarray, Q0: np.ndarray, Q1: np.ndarray) -> np.ndarray:
    """Squared distances between segments ``P0P1`` and ``Q0Q1``, row by row (all (k,3)).

    Minimises ``|P0 + s d1 - Q0 - t d2|^2`` over ``s, t`` in [0, 1]: the unconstrained ``s`` is
    clamped, ``t`` follows from it and, when ``t`` leaves [0, 1], is clamped and ``s`` recomputed
    (the standard clamped closest-point construction). Parallel segments take ``s = 0``.
    """
    d1 = P1 - P0
    d2 = Q1 - Q0
    r = P0 - Q0
    a = np.einsum("ij,ij->i", d1, d1)
    e = np.einsum("ij,ij->i", d2, d2)
    b = np.einsum("ij,ij->i", d1, d2)
    c = np.einsum("ij,ij->i", d1, r)
    f = np.einsum("ij,ij->i", d2, r)
    tiny = np.finfo(float).tiny
    a_s = np.maximum(a, tiny)
    e_s = np.maximum(e, tiny)
    denom = a * e - b * b
    parallel = denom <= 1e-14 * a * e
    s = np.where(parallel, 0.0, np.clip((b * f - c * e) / np.where(parallel, 1.0, denom), 0.0, 1.0))
    t = (b * s + f) / e_s
    lo, hi = t < 0.0, t > 1.0
    s = np.where(lo, np.clip(-c / a_s, 0.0, 1.0), np.where(hi, np.clip((b - c) / a_s, 0.0, 1.0), s))
    t = np.clip(t, 0.0, 1.0)
    D = r + s[:, None] * d1 - t[:, None] * d2
    return np.einsum("ij,ij->i", D, D)


def min_edge_edge_distance(
    VA: np.ndarray, FA: np.ndarray, VB: np.ndarray, FB: np.ndarray, bound: float, chunk: int = 2_000_000
) -> float:
    """Smallest distance between an edge of mesh A and an edge of mesh B, if below ``bound``.

    Candidate pairs come from k-d trees on edge midpoints: two segments with midpoints ``m_a, m_b``
    and half-lengths ``h_a, h_b`` are at least ``|m_a - m_b| - h_a - h_b`` apart, so only pairs with
    ``|m_a - m_b| < bound + h_a + h_b`` can beat ``bound``. The edges of each mesh are grouped by
    half-length (factors of :data:`EDGE_LENGTH_CLASS_RATIO`), one tree per group, and every pair of groups is
    searched with its own radius (the groups' longest half-lengths), so that a few long edges do not widen
    every query ball (lucy.ply against its first cage: 12 s in one tree, the longest edge 13x the median);
    the pairs of two trees come out as arrays (``cKDTree.sparse_distance_matrix``), not as per-edge lists:
    1.70-1.75x faster than per-edge ball queries on homer.obj's and pepper.ply's first cage pairs, 1.30-1.48x
    on their second (CPU medians of 5, ``benchmarks/results/audit/edge_edge_search.json``). Distances are
    evaluated vectorised in chunks of at most ``chunk`` pairs.

    Returns
    -------
    float
        ``min(bound, smallest edge-edge distance)``.
    """
    from scipy.spatial import cKDTree

    def edge_groups(V, F):
        E = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
        E = np.unique(E, axis=0)
        P0, P1 = V[E[:, 0]], V[E[:, 1]]
        h = 0.5 * np.linalg.norm(P1 - P0, axis=1)
        # length classes: [0, 2 median], then doubling
        edges = 2.0 * max(float(np.median(h)), 1e-300) * EDGE_LENGTH_CLASS_RATIO ** np.arange(64)
        cls = np.searchsorted(edges, h)
        groups = []
        for c in np.unique(cls):
            sel = np.flatnonzero(cls == c)
            groups.append((P0[sel], P1[sel], h[sel], cKDTree(0.5 * (P0[sel] + P1[sel]))))
        return groups

    best = float(bound) ** 2
    groups_b = edge_groups(VB, FB)
    for A in edge_groups(VA, FA):
        for B in groups_b:
            best = _min_ee_groups(A, B, best, chunk)
    return float(np.sqrt(best))


#: Edges of :func:`min_edge_edge_distance` are grouped by half-length within this factor.
EDGE_LENGTH_CLASS_RATIO = 2.0


def _min_ee_groups(A: tuple, B: tuple, best: float, chunk: int) -> float:
    """Smallest squared edge-edge distance between two groups of edges (each ``(P0, P1, half_length,
    midpoint tree)``), if below ``best`` (squared; returned otherwise)."""
    A0, A1, hA, tA = A
    B0, B1, hB, tB = B
    radius = np.sqrt(best) + float(hA.max()) + float(hB.max())
    pairs = tA.sparse_distance_matrix(tB, radius, output_type="ndarray")
    if not len(pairs):
        return best
    ia, ib, dm = pairs["i"], pairs["j"], pairs["v"]
    near = dm < np.sqrt(best) + hA[ia] + hB[ib]  # the lower bound per pair: most pairs go here
    ia, ib = ia[near], ib[near]
    for s in range(0, len(ia), chunk):
        a, b = ia[s:s + chunk], ib[s:s + chunk]
        best = min(best, float(segment_segment_sqdist(A0[a], A1[a], B0[b], B1[b]).min()))
    return best


def point_triangle_sqdist(P, A, B, C):
    """Squared distances of points ``P`` to triangles ``ABC``, row by row (Ericson's closest-point
    regions, vectorised)."""
    ab, ac, ap = B - A, C - A, P - A
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    bp = P - B
    d3, d4 = np.einsum("ij,ij->i", ab, bp), np.einsum("ij,ij->i", ac, bp)
    cp = P - C
    d5, d6 = np.einsum("ij,ij->i", ab, cp), np.einsum("ij,ij->i", ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    denom = va + vb + vc
    tiny = 1e-300
    v = vb / np.where(np.abs(denom) > tiny, denom, tiny)
    w = vc / np.where(np.abs(denom) > tiny, denom, tiny)
    Q = A + v[:, None] * ab + w[:, None] * ac  # interior projection
    # edge regions
    def seg(X, Y):
        t = np.clip(np.einsum("ij,ij->i", P - X, Y - X) / np.maximum(np.einsum("ij,ij->i", Y - X, Y - X), tiny), 0, 1)
        return X + t[:, None] * (Y - X)
    inside = (va >= 0) & (vb >= 0) & (vc >= 0) & (denom > tiny)
    cands = [seg(A, B), seg(B, C), seg(C, A)]
    dist = [np.einsum("ij,ij->i", P - q, P - q) for q in cands]
    best = np.minimum(np.minimum(dist[0], dist[1]), dist[2])
    dq = np.einsum("ij,ij->i", P - Q, P - Q)
    return np.where(inside, np.minimum(dq, best), best)
