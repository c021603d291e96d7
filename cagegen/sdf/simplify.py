"""Step 2 of the ``sdf`` backend: QEM simplification constrained to stay outside the input.

Qiu, Liao, Chen (2024), Sec. 3.2, problem (4): collapse edges in quadric-error order (Garland &
Heckbert 1997); the new vertex ``p`` starts at the quadric minimiser and is pushed along the gradient
of ``Psi(p) = -sum_i w_i xi(x_i)`` (eq. 6, samples ``x_i`` on the new triangles ``N(p)``) until the
samples clear the input; a collapse whose new triangles cross the input or the cage itself (exact
test, :mod:`cagegen.intersect`) is infeasible (infinite cost) until its neighbourhood changes.

Implementation choices (see ``docs/sdf.md``):

* Collapses are applied in *batches* of edges with disjoint closed neighbourhoods (lowest cost first),
  each batch tested at once with vectorised exact predicates; rejected collapses are withdrawn and the
  remaining ones re-tested until the batch is clean. Every intermediate mesh is therefore crossing-
  and self-intersection-free, as in the paper's one-at-a-time loop.
* Placements tried per edge, in order: projected quadric minimiser, the two end points, the midpoint.
* Each collapse removes exactly two faces, so the face count is met exactly (closed surfaces have
  an even number of faces).
"""

from __future__ import annotations

import time
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp

from .._geometry import edge_stats, point_triangle_sqdist, segment_segment_sqdist
from ..envelope import SDFGrid
from ..errors import CageError, CageOptionError, NestmgError
from ..intersect import cross_pairs, face_grid, self_pairs
from ..split_edges import split_long_edges

__all__ = ["SimplifyStuck", "constrained_simplify", "face_quadrics"]

# barycentric samples on a new triangle (p, q1, q2): (weight of p, split between q1 and q2)
_SAMPLES = np.array([[1.0, 0.0], [0.5, 0.0], [0.5, 1.0], [1 / 3, 0.5], [0.75, 0.5], [0.25, 0.5],
                     [0.75, 0.0], [0.75, 1.0]])


#: :func:`constrained_simplify` checks against the input with no edge longer than this many grid cells
SPLIT_INPUT_CELLS = 4.0


class SimplifyStuck(NestmgError, RuntimeError):
    """No feasible collapse is left before the target face count."""


def face_quadrics(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Area-weighted plane quadrics accumulated per vertex, (n,4,4)."""
    N = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    A2 = np.linalg.norm(N, axis=1)
    n = N / np.maximum(A2, 1e-300)[:, None]
    d = -np.einsum("ij,ij->i", n, V[F[:, 0]])
    p = np.c_[n, d]
    K = 0.5 * A2[:, None, None] * p[:, :, None] * p[:, None, :]
    Q = np.zeros((len(V), 4, 4))
    for k in range(3):
        np.add.at(Q, F[:, k], K)
    return Q


def _edges(F: np.ndarray) -> np.ndarray:
    E = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    return np.unique(E, axis=0)


def _qem_place(Q: np.ndarray, Va: np.ndarray, Vb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Quadric minimiser (midpoint/end point when singular) and its cost, per edge."""
    A = Q[:, :3, :3]
    bvec = -Q[:, :3, 3]
    det = np.linalg.det(A)
    scale = np.maximum(np.abs(A).max(axis=(1, 2)) ** 3, 1e-300)
    good = np.abs(det) > 1e-9 * scale
    P = 0.5 * (Va + Vb)
    if good.any():
        P[good] = np.linalg.solve(A[good], bvec[good][:, :, None])[:, :, 0]
        # a minimiser far from the edge is a near-singular artefact: fall back to the midpoint
        far = np.linalg.norm(P - 0.5 * (Va + Vb), axis=1) > 2.0 * np.linalg.norm(Va - Vb, axis=1)
        P[far] = 0.5 * (Va + Vb)[far]
    cands = [P, Va, Vb, 0.5 * (Va + Vb)]
    costs = []
    for X in cands:
        x = np.c_[X, np.ones(len(X))]
        costs.append(np.einsum("ij,ijk,ik->i", x, Q, x))
    C = np.stack(costs, 1)
    best = np.argmin(C, axis=1)
    # prefer the minimiser unless singular (then the cheapest of the others)
    best = np.where(good, 0, best)
    Pbest = np.stack(cands, 1)[np.arange(len(P)), best]
    return Pbest, np.maximum(C[np.arange(len(P)), best], 0.0)


def _project(P: np.ndarray, owner: np.ndarray, Q1: np.ndarray, Q2: np.ndarray, sdf: SDFGrid, margin: float,
             iters: int = 8) -> np.ndarray:
    """Push each new vertex ``P[k]`` along the gradient of Psi (eq. 5-6) until the samples on its new
    triangles (``owner`` maps triangles to vertices; ``Q1, Q2`` their other corners) clear ``margin``."""
    P = P.copy()
    lam = _SAMPLES[:, 0]
    mu = _SAMPLES[:, 1]
    for _ in range(iters):
        X = (lam[None, :, None] * P[owner][:, None, :]
             + ((1 - lam) * (1 - mu))[None, :, None] * Q1[:, None, :]
             + ((1 - lam) * mu)[None, :, None] * Q2[:, None, :])
        val, g = sdf(X.reshape(-1, 3), grad=True)
        val = val.reshape(len(owner), -1)
        g = g.reshape(len(owner), -1, 3)
        viol = val < margin
        if not viol.any():
            break
        # gradient of sum_i w_i xi(x_i) w.r.t. p over the violating samples (eq. 6)
        gp = np.einsum("ts,tsk->tk", viol * lam[None, :], g)
        G = np.zeros_like(P)
        np.add.at(G, owner, gp)
        deficit = np.full(len(P), 0.0)
        np.maximum.at(deficit, owner, np.where(viol, margin - val, 0.0).max(axis=1))
        nrm = np.linalg.norm(G, axis=1)
        move = (deficit > 0) & (nrm > 1e-12)
        if not move.any():
            break
        step = np.minimum(deficit[move], 4 * sdf.h)
        P[move] += (step / nrm[move])[:, None] * G[move]
    return P


_AABB_CACHE: dict = {}


def _aabb(V: np.ndarray, F: np.ndarray):
    """libigl AABB tree of ``(V, F)``, kept for the last surface (rebuilt when it changes)."""
    import igl

    key = (id(V), id(F), V.shape, F.shape)
    if _AABB_CACHE.get("key") != key:
        tree = igl.AABB()
        tree.init(V, F)
        _AABB_CACHE.clear()
        _AABB_CACHE.update(key=key, tree=tree, ref=(V, F))
    return _AABB_CACHE["tree"]


def too_close(T: np.ndarray, Vin: np.ndarray, Fin: np.ndarray, vin_tree, clear: float) -> np.ndarray:
    """Which triangles ``T`` (k,3,3) come closer than ``clear`` to the surface ``(Vin, Fin)``: exact
    distances of samples on each triangle to the surface and of the surface's vertices near each
    triangle (``vin_tree``: a k-d tree of ``Vin``) to it. (A sharp edge of the surface passing between
    the samples can still come closer; the exact crossing test is separate.)"""
    L = _SAMPLES
    X = (L[:, 0][None, :, None] * T[:, None, 0] + ((1 - L[:, 0]) * (1 - L[:, 1]))[None, :, None]
         * T[:, None, 1] + ((1 - L[:, 0]) * L[:, 1])[None, :, None] * T[:, None, 2])
    X = np.concatenate([X, T[:, 1:]], axis=1)  # all three corners
    vals = _aabb(Vin, Fin).squared_distance(Vin, Fin, X.reshape(-1, 3))[0].reshape(len(T), -1)
    low = vals.min(axis=1) < clear * clear
    cq = T.mean(axis=1)
    rq = np.linalg.norm(T - cq[:, None, :], axis=2).max(axis=1)
    # every point of a triangle is within rq of its centroid (sample 3), so the surface, hence each of its
    # vertices, is at least sqrt(vals[:, 3]) - rq from the triangle: only the others are searched
    tol = 1e-12 * max(float(np.abs(T).max()), 1e-300)  # X[:, 3] and cq round differently
    look = np.flatnonzero(~low & (np.sqrt(vals[:, 3]) - rq < clear + tol))
    if not len(look):
        return low
    near_v = vin_tree.query_ball_point(cq[look], rq[look] + clear)
    cnt = np.fromiter((len(x) for x in near_v), dtype=np.int64, count=len(near_v))
    if cnt.sum():
        iv = np.concatenate([np.asarray(x, dtype=np.int64) for x in near_v if len(x)])
        it = np.repeat(look, cnt)
        # a vertex's distance to the triangle's plane bounds its distance to the triangle: only those within
        # clear of the plane get the full test (the surface under a cage triangle lies beyond it)
        Tl = T[look]  # the normals of the searched triangles only
        nrm = np.cross(Tl[:, 1] - Tl[:, 0], Tl[:, 2] - Tl[:, 0])
        nrm /= np.maximum(np.linalg.norm(nrm, axis=1), 1e-300)[:, None]
        h = np.abs(np.einsum("ij,ij->i", Vin[iv] - T[it, 0], np.repeat(nrm, cnt, axis=0)))
        near = h < clear * (1.0 + 1e-9) + tol
        iv, it = iv[near], it[near]
        d2 = point_triangle_sqdist(Vin[iv], T[it, 0], T[it, 1], T[it, 2])
        low[it[d2 < clear * clear]] = True
    return low


#: :func:`segments_beyond` halves a segment at most this many times before leaving it to the exact test
SEGMENT_HALVINGS = 8


def segments_beyond(P0: np.ndarray, P1: np.ndarray, V: np.ndarray, F: np.ndarray, clear: float) -> np.ndarray:
    """Which segments ``P0[k] P1[k]`` are certainly at least ``clear`` from the surface ``(V, F)`` (hence from
    its edges): a conservative filter in front of exact segment-edge distances.

    The distance to the surface is 1-Lipschitz, so on a segment ``ab`` of length ``l`` with end-point
    distances ``d_a, d_b`` (exact, libigl's AABB tree) every point is at least ``(d_a + d_b - l) / 2`` away.
    Pieces where that bound is below ``clear`` are halved (one more exact distance each), at most
    :data:`SEGMENT_HALVINGS` times; a segment is certified when all its pieces are, and a piece with an end
    point closer than ``clear`` stops its segment's search (False: left to the exact test).

    Returns
    -------
    (k,) bool array
    """
    tree = _aabb(V, F)
    n = len(P0)
    d = np.sqrt(np.maximum(tree.squared_distance(V, F, np.concatenate([P0, P1]))[0], 0.0))
    A, B, dA, dB, seg = P0, P1, d[:n], d[n:], np.arange(n)
    unresolved = np.zeros(n, dtype=bool)  # some piece can be closer than clear
    tol = 1e-12 * max(float(np.abs(V).max()), 1e-300)  # rounding of the distances
    for halving in range(SEGMENT_HALVINGS + 1):
        open_ = 0.5 * (dA + dB - np.linalg.norm(B - A, axis=1)) < clear + tol
        unresolved[seg[open_ & (np.minimum(dA, dB) < clear + tol)]] = True
        open_ &= ~unresolved[seg]
        A, B, dA, dB, seg = A[open_], B[open_], dA[open_], dB[open_], seg[open_]
        if not len(seg) or halving == SEGMENT_HALVINGS:
            break
        M = 0.5 * (A + B)
        dM = np.sqrt(np.maximum(tree.squared_distance(V, F, M)[0], 0.0))
        A, B = np.concatenate([A, M]), np.concatenate([M, B])
        dA, dB, seg = np.concatenate([dA, dM]), np.concatenate([dM, dB]), np.concatenate([seg, seg])
    unresolved[seg] = True  # pieces still open after the last halving
    return ~unresolved


def _tri_normals(V, F):
    return np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])


def constrained_simplify(
    V: np.ndarray,
    F: np.ndarray,
    Vin: np.ndarray,
    Fin: np.ndarray,
    target: int,
    sdf: SDFGrid,
    *,
    margin: float,
    Q: np.ndarray | None = None,
    batch_fraction: float = 0.12,
    min_quality: float = 0.02,
    max_batches: int = 10000,
    edge_clear: float = 0.0,
    frozen: np.ndarray | None = None,
    deadline: float | None = None,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """Collapse edges of the cage ``(V, F)`` (outside ``(Vin, Fin)``) down to exactly ``target`` faces.

    Parameters
    ----------
    V, F : arrays
        A closed cage strictly containing ``(Vin, Fin)``, free of self-intersections.
    Vin, Fin : arrays
        The surface to envelope.
    target : int
        Even face count ``< len(F)``.
    sdf : SDFGrid
        Signed distance of ``(Vin, Fin)`` (guides the placement, eq. 5-6).
    margin : float
        Clearance the samples of new triangles must keep (on the grid's distance).
    Q : (n,4,4) array, optional
        Initial quadrics (default: :func:`face_quadrics` of ``(V, F)``).
    batch_fraction : float
        Upper bound of the collapses per batch, as a fraction of the live vertices.
    min_quality : float
        Smallest ``2 area / sum of squared edge lengths`` a new triangle may have (0.289 for an
        equilateral one; 0.02 is a smallest angle of about 2-4 degrees).
    edge_clear : float
        With ``edge_clear > 0``, the new edges must also stay ``edge_clear`` away from the input's
        edges (exact segment-segment distances). With the sampled test and the exact input-vertex
        test this makes the clearance exact (a caller's ``min_gap``): the samples alone let a new edge
        pass next to a sharp input edge (a coarse input: the previous cage layer, 4e-4 for a 2.5e-3
        ``min_gap``), and the layer then failed its certificate.
    frozen : (n,) bool array, optional
        Vertices that must survive where they are: no edge incident to one is collapsed (the
        tightening pass of :func:`cagegen.sdf.backend.sdf_cage_layer` freezes the vertices it inserted).
    deadline : float, optional
        A ``time.perf_counter()`` value: no batch starts after it (:class:`cagegen.CageError`).

    Returns
    -------
    V, F : arrays (compacted)
    info : dict
        ``batches``, ``collapses``, ``rejected`` (per test), ``faces``.

    Raises
    ------
    SimplifyStuck
        When every remaining collapse is infeasible before ``target`` is reached.
    CageError
        Past ``deadline``.
    """
    V = np.array(V, dtype=np.float64)
    F = np.array(F, dtype=np.int64)
    if (len(F) - target) % 2:
        raise CageOptionError(f"cannot reach {target} faces from {len(F)} by edge collapses (parity)")
    Q = face_quadrics(V, F) if Q is None else np.array(Q)
    n = len(V)
    frozen = np.zeros(n, dtype=bool) if frozen is None else np.asarray(frozen, dtype=bool)
    if frozen.shape != (n,):
        raise CageOptionError(f"frozen must be a boolean mask of the {n} vertices")
    # edge key -> (failed placements, batch of the last failure); reset when a neighbourhood changes
    attempts: dict[int, tuple[int, int]] = {}
    changed_at = np.zeros(n, dtype=np.int64)
    # the proximity queries reach as far as the input's longest edge and widest triangle: with the STL
    # slivers of a CAD part (edges of 0.1-0.5 of the diagonal) every query returned most of the input
    # and featuretype.stl's layer exhausted 24 GB. The same surface, with no edge longer than
    # SPLIT_INPUT_CELLS grid cells, answers the same questions (inputs without such edges: unchanged).
    Vin, Fin, _ = split_long_edges(Vin, Fin, SPLIT_INPUT_CELLS * sdf.h, max_faces=max(20 * len(Fin), 200_000))
    inp = _input_index(Vin, Fin, edge_clear)
    rejected = {"input": 0, "self": 0, "normal": 0, "margin": 0}
    if edge_clear > 0:
        rejected["edge_clear"] = 0
    n_coll = 0
    batch = 0
    while len(F) > target:
        if deadline is not None and time.perf_counter() > deadline:
            raise CageError(f"sdf cage: the simplification ran out of its time budget at {len(F)} faces "
                            f"(target {target}; cage_time_budget)", reason="time budget")
        batch += 1
        if batch > max_batches:
            raise SimplifyStuck(f"no progress after {max_batches} batches at {len(F)} faces")
        need = (len(F) - target) // 2
        a, b, A, key, att, P, cand = _candidates(V, F, Q, frozen, attempts, changed_at, target)
        quota = max(1, min(need, int(batch_fraction * len(np.unique(F)))))
        sel = _independent_edges(cand, a, b, A, quota)
        bt = _new_triangles(V, F, a, b, sel, P, sdf, margin)
        idx, clean, failed = _test_rounds(V, F, bt, inp, margin, min_quality, edge_clear, rejected)
        if not clean or len(idx) == 0:
            # nothing applied unless the last set of collapses passed every test together; the
            # untested survivors count as a failed attempt too (no endless retry of the same batch)
            failed = failed + list(idx)
        for k in failed:
            attempts[int(key[sel[k]])] = (int(att[sel[k]]) + 1, batch)
        if not clean or len(idx) == 0:
            continue
        F = _apply_collapses(V, F, Q, bt, idx, changed_at, batch)
        n_coll += len(idx)
    used = np.unique(F)
    remap = np.full(n, -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    es = edge_stats(remap[F], len(used))
    if not es.closed_manifold:  # the link condition should make this impossible
        raise SimplifyStuck("the collapses produced a mesh that is not a closed oriented manifold")
    info = {"batches": batch, "collapses": n_coll, "rejected": rejected, "n_faces": len(F)}
    return V[used], remap[F], info


class _InputIndex(NamedTuple):
    """Search structures of the input surface ``(Vin, Fin)`` for the collapse tests."""

    Vin: np.ndarray
    Fin: np.ndarray
    vin_tree: object  # k-d tree of the vertices
    grid: object  # cagegen.intersect.face_grid of the faces
    EI: np.ndarray | None  # (k,2) edges (with edge_clear > 0)
    e_tree: object  # k-d tree of the edge midpoints (with edge_clear > 0)
    e_half: float | None  # half the longest edge (with edge_clear > 0)


def _input_index(Vin, Fin, edge_clear: float) -> _InputIndex:
    """k-d trees of the input's vertices and (``edge_clear > 0``) edge midpoints, the grid of its faces."""
    from scipy.spatial import cKDTree

    vin_tree = cKDTree(Vin)
    EI = e_tree = e_half = None
    if edge_clear > 0:
        EI = np.unique(np.sort(np.concatenate([Fin[:, [0, 1]], Fin[:, [1, 2]], Fin[:, [2, 0]]]), axis=1),
                       axis=0)
        e_tree = cKDTree(0.5 * (Vin[EI[:, 0]] + Vin[EI[:, 1]]))
        e_half = 0.5 * float(np.linalg.norm(Vin[EI[:, 0]] - Vin[EI[:, 1]], axis=1).max())
    return _InputIndex(Vin, Fin, vin_tree, face_grid(Vin, Fin), EI, e_tree, e_half)


def _candidates(V, F, Q, frozen, attempts, changed_at, target):
    """Step 1: the collapsible edges (link condition, not frozen or blocked), placed, cheapest first."""
    n = len(V)
    E = _edges(F)
    a, b = E[:, 0], E[:, 1]
    A = sp.coo_matrix((np.ones(2 * len(E)), (np.r_[a, b], np.r_[b, a])), shape=(n, n)).tocsr()
    common = np.asarray((A @ A)[a, b]).ravel()
    ok = common == 2  # link condition: the collapse keeps a closed 2-manifold
    ok &= ~(frozen[a] | frozen[b])
    key = a * n + b
    att = np.zeros(len(E), dtype=np.int64)
    if attempts:
        for i, k in enumerate(key.tolist()):
            rec = attempts.get(k)
            if rec is not None and rec[1] >= max(changed_at[a[i]], changed_at[b[i]]):
                att[i] = rec[0]
    ok &= att < 4
    Qe = Q[a] + Q[b]
    P, cost = _qem_place(Qe, V[a], V[b])
    # alternative placements for edges whose earlier attempts failed
    alt = att > 0
    if alt.any():
        choice = np.stack([P, V[a], V[b], 0.5 * (V[a] + V[b])], 1)
        P[alt] = choice[np.flatnonzero(alt), np.minimum(att[alt], 3)]
        x = np.c_[P[alt], np.ones(int(alt.sum()))]
        cost[alt] = np.einsum("ij,ijk,ik->i", x, Qe[alt], x)
    cand = np.flatnonzero(ok)
    if len(cand) == 0:
        raise SimplifyStuck(f"no feasible collapse left at {len(F)} faces (target {target})")
    cand = cand[np.argsort(cost[cand], kind="stable")]
    return a, b, A, key, att, P, cand


def _independent_edges(cand, a, b, A, quota: int) -> np.ndarray:
    """Step 2: up to ``quota`` candidates, in order, whose closed neighbourhoods are disjoint."""
    # greedy choice of edges whose incident faces are disjoint: an edge is taken when neither end
    # point is in the closed neighbourhood of an edge taken before (then no face is shared and
    # the link conditions stay valid)
    locked = [False] * A.shape[0]
    ptr, ind = A.indptr.tolist(), A.indices.tolist()
    al, bl = a.tolist(), b.tolist()
    sel = []
    for e in cand.tolist():
        x, y = al[e], bl[e]
        if locked[x] or locked[y]:
            continue
        for v in ind[ptr[x]:ptr[x + 1]]:
            locked[v] = True
        for v in ind[ptr[y]:ptr[y + 1]]:
            locked[v] = True
        locked[x] = locked[y] = True
        sel.append(e)
        if len(sel) >= quota:
            break
    return np.asarray(sel, dtype=np.int64)


class _Batch(NamedTuple):
    """One batch's collapses (edge ``sel[k]``: ``b[sel[k]]`` onto ``a[sel[k]]``) and their new triangles."""

    a: np.ndarray
    b: np.ndarray
    sel: np.ndarray
    inc: sp.coo_matrix  # collapse x face: 1 on a new triangle's face, 2 on a removed face
    own: np.ndarray  # collapse of each new triangle
    fid: np.ndarray  # face of each new triangle
    dead_f: np.ndarray  # removed faces
    tri_r: np.ndarray  # (t,3) corners of each new triangle, the collapsing vertex first
    P: np.ndarray  # (s,3) the new vertices, projected


def _new_triangles(V, F, a, b, sel, P, sdf, margin) -> _Batch:
    """Step 3: the new triangles of each chosen collapse, and its new vertex pushed clear of the input."""
    n = len(V)
    # new triangles of each collapse: faces around a or b except the two on edge (a, b); b -> a
    VFm = sp.coo_matrix((np.ones(3 * len(F)), (F.ravel(), np.repeat(np.arange(len(F)), 3))),
                        shape=(n, len(F))).tocsr()
    S = sp.coo_matrix((np.ones(2 * len(sel)), (np.r_[np.arange(len(sel)), np.arange(len(sel))],
                                               np.r_[a[sel], b[sel]])), shape=(len(sel), n)).tocsr()
    inc = (S @ VFm).tocoo()
    kept = inc.data == 1
    own, fid = inc.row[kept], inc.col[kept]
    dead_f = inc.col[inc.data == 2]
    Pnew = P[sel]
    # triangle corners other than the collapsing vertex, in order (p first keeps orientation)
    tri = F[fid]
    is_ab = (tri == a[sel][own][:, None]) | (tri == b[sel][own][:, None])
    rot = np.argmax(is_ab, axis=1)
    tri_r = np.stack([tri[np.arange(len(tri)), (rot + k) % 3] for k in range(3)], 1)
    Pnew = _project(Pnew, own, V[tri_r[:, 1]], V[tri_r[:, 2]], sdf, margin)
    return _Batch(a, b, sel, inc, own, fid, dead_f, tri_r, Pnew)


def _test_rounds(V, F, bt: _Batch, inp: _InputIndex, margin, min_quality, edge_clear, rejected):
    """Step 4: test the collapses together, withdrawing the failing ones, until clean (6 rounds at most)."""
    alive = np.ones(len(bt.sel), dtype=bool)
    clean = False
    failed: list = []  # collapses that failed a test, in order
    for _round in range(6):
        idx = np.flatnonzero(alive)
        if len(idx) == 0:
            break
        bad = _failing_collapses(V, F, bt, idx, inp, margin, min_quality, edge_clear, rejected)
        if not bad[idx].any():
            clean = True
            break
        failed.extend(np.flatnonzero(bad & alive))
        alive &= ~bad
    return np.flatnonzero(alive), clean, failed


def _failing_collapses(V, F, bt: _Batch, idx, inp: _InputIndex, margin, min_quality, edge_clear, rejected):
    """Step 4, one round: which of the collapses ``idx``, applied together, fail a test (counted by test)."""
    n = len(V)
    a, b, sel = bt.a, bt.b, bt.sel
    Vc = V.copy()
    Vc[a[sel[idx]]] = bt.P[idx]
    Fc = F.copy()
    rmap = np.arange(n)
    rmap[b[sel[idx]]] = a[sel[idx]]
    Fc = rmap[Fc]
    dmask = np.zeros(len(F), dtype=bool)
    inc_alive = np.isin(bt.own, idx)
    dmask[bt.dead_f[np.isin(bt.inc.row[bt.inc.data == 2], idx)]] = True
    nf = bt.fid[inc_alive]
    nown = bt.own[inc_alive]
    bad = np.zeros(len(sel), dtype=bool)
    # 1. no fold-over: the new normal keeps the old one's side, no degenerate triangle
    fold = _folds(V, F, Vc, Fc, nf, nown, len(sel), min_quality)
    bad[nown[fold]] = True
    rejected["normal"] += int(np.unique(nown[fold]).size)
    # 2. clearance (exact distances): samples on the new triangles to the input, and input
    #    vertices near the new triangles to them, must stay beyond half the margin
    own_v = Vc[rmap[bt.tri_r[inc_alive]]]  # corners with p first
    _clearance_test(own_v, nown, bad, inp, margin, edge_clear, rejected)
    # 3. exact: new triangles must not cross or touch the input
    _input_crossing_test(Vc, Fc, nf, nown, bad, inp, rejected)
    # 4. exact: new triangles must not intersect other cage triangles (local submesh)
    _self_crossing_test(Vc, Fc, nf, nown, ~dmask, bad, rejected)
    return bad


def _folds(V, F, Vc, Fc, nf, nown, n_sel: int, min_quality: float) -> np.ndarray:
    """Test 1: new triangles that flip or degenerate, or fall below ``min_quality`` and the old worst."""
    n_old = _tri_normals(V, F[nf])
    n_new = _tri_normals(Vc, Fc[nf])
    dots = np.einsum("ij,ij->i", n_old, n_new)
    a_new = np.linalg.norm(n_new, axis=1)
    e2 = sum(np.einsum("ij,ij->i", d, d) for d in (
        Vc[Fc[nf, 1]] - Vc[Fc[nf, 0]], Vc[Fc[nf, 2]] - Vc[Fc[nf, 1]], Vc[Fc[nf, 0]] - Vc[Fc[nf, 2]]))
    # quality floor: a new triangle below min_quality must not be worse than the worst old
    # triangle around the same collapse (never degrade an already poor neighbourhood further)
    q_new = a_new / np.maximum(e2, 1e-300)
    Xo = V[F[nf]]
    q_old = np.linalg.norm(n_old, axis=1) / np.maximum(sum(np.einsum("ij,ij->i", d, d) for d in (
        Xo[:, 1] - Xo[:, 0], Xo[:, 2] - Xo[:, 1], Xo[:, 0] - Xo[:, 2])), 1e-300)
    qo_min = np.full(n_sel, np.inf)
    np.minimum.at(qo_min, nown, q_old)
    qn_min = np.full(n_sel, np.inf)
    np.minimum.at(qn_min, nown, q_new)
    poor = (qn_min < min_quality) & (qn_min < qo_min)
    return (dots <= 0.0) | (a_new <= 1e-6 * e2) | poor[nown]


def _clearance_test(own_v, nown, bad, inp: _InputIndex, margin, edge_clear, rejected) -> None:
    """Test 2: new triangles closer than ``margin / 2`` to the input, or new edges than ``edge_clear``."""
    clear = 0.5 * margin
    low = too_close(own_v, inp.Vin, inp.Fin, inp.vin_tree, clear) & ~bad[nown]
    newb = np.unique(nown[low])
    rejected["margin"] += int(newb.size)
    bad[newb] = True
    if edge_clear > 0:  # the two new edges (p, q1), (p, q2) of each new triangle vs the input's edges
        live = ~bad[nown]
        P0 = np.r_[own_v[live, 0], own_v[live, 0]]
        P1 = np.r_[own_v[live, 1], own_v[live, 2]]
        ow = np.r_[nown[live], nown[live]]
        if len(P0):
            far = segments_beyond(P0, P1, inp.Vin, inp.Fin, edge_clear)
            P0, P1, ow = P0[~far], P1[~far], ow[~far]
        if len(P0):
            lists = inp.e_tree.query_ball_point(
                0.5 * (P0 + P1), 0.5 * np.linalg.norm(P1 - P0, axis=1) + inp.e_half + edge_clear)
            cnt = np.fromiter((len(x) for x in lists), dtype=np.int64, count=len(lists))
            if cnt.sum():
                ie = np.concatenate([np.asarray(x, dtype=np.int64) for x in lists if len(x)])
                iseg = np.repeat(np.arange(len(P0)), cnt)
                Vin, EI = inp.Vin, inp.EI
                d2 = segment_segment_sqdist(P0[iseg], P1[iseg], Vin[EI[ie, 0]], Vin[EI[ie, 1]])
                hit = np.unique(ow[iseg[d2 < edge_clear * edge_clear]])
                rejected["edge_clear"] += int(hit.size)
                bad[hit] = True


def _input_crossing_test(Vc, Fc, nf, nown, bad, inp: _InputIndex, rejected) -> None:
    """Test 3 (exact): new triangles that cross or touch the input."""
    chk = ~bad[nown]
    if chk.any():
        # the grid broad phase of cross_pairs over the whole input, its cells built once: the same candidate
        # pairs that meet as a k-d ball search, as arrays (the balls' Python lists cost more than the exact
        # tests, flange.stl)
        pr = cross_pairs(Vc, Fc[nf[chk]], inp.Vin, inp.Fin, grid=inp.grid)
        if len(pr):
            hit = np.unique(nown[chk][pr[:, 0]])
            rejected["input"] += int(hit.size)
            bad[hit] = True


def _self_crossing_test(Vc, Fc, nf, nown, live_f, bad, rejected) -> None:
    """Test 4 (exact): new triangles that intersect other live cage triangles (local submesh)."""
    chk = ~bad[nown]
    if chk.any():
        newf = nf[chk]
        # the live cage (new faces are live) through self_pairs' grid broad phase, only pairs with a new face:
        # the rest of the cage is clean (checked when it was made). A k-d ball search around the new faces
        # reached as far as the cage's largest face and returned its results as Python lists
        sub = np.union1d(np.flatnonzero(live_f), newf)
        pr = self_pairs(Vc, Fc[sub], only=np.searchsorted(sub, newf))
        if len(pr):
            pos = -np.ones(len(Fc), dtype=np.int64)
            pos[nf] = nown  # owner of each new face
            fa, fb = sub[pr[:, 0]], sub[pr[:, 1]]
            hit = np.unique(np.r_[pos[fa], pos[fb]])
            hit = hit[hit >= 0]
            rejected["self"] += int(hit.size)
            bad[hit] = True


def _apply_collapses(V, F, Q, bt: _Batch, idx, changed_at, batch: int) -> np.ndarray:
    """Step 5: apply the accepted collapses ``idx`` (``V``, ``Q``, ``changed_at`` in place); the new faces."""
    n = len(V)
    ai, bi = bt.a[bt.sel[idx]], bt.b[bt.sel[idx]]
    V[ai] = bt.P[idx]
    Q[ai] += Q[bi]
    rmap = np.arange(n)
    rmap[bi] = ai
    dead = np.zeros(len(F), dtype=bool)
    dead[bt.dead_f[np.isin(bt.inc.row[bt.inc.data == 2], idx)]] = True
    F = rmap[F[~dead]]
    # neighbourhoods changed: their blocked edges may be retried
    touched = np.unique(F[np.isin(F, ai).any(axis=1)])
    changed_at[touched] = batch
    return F
