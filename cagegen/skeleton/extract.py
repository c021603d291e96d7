"""Automatic curve-skeleton extraction with PyGEL3D (MIT), then cleaning into a :class:`Skeleton` tree.

Candidates considered (licences read from the packages' metadata): ``skeletor`` (GPL-3.0, mesh
contraction) and ``kimimaro`` (GPL-3.0, voxel TEASAR) cannot be imported by MIT nestmg; ``pygel3d``
(GEL's Python bindings, MIT) can: its multi-scale local-separator skeleton (Bærentzen & Rotenberg
2021, ``graph.MSLS_skeleton``) works on the mesh's own vertex graph and returns a graph skeleton in
seconds. It is an optional extra (``pip install nestmg[skeleton]``).

Cleaning: cycles are cut by a minimum spanning tree; leaf branches shorter than ``prune`` x the
inscribed radius at their branching node are removed (spurs), repeatedly; leaf nodes outside the
surface are dropped; interior nodes outside it (thin parts) are moved halfway to their neighbours'
mean until inside (50 steps at most), then merged into a neighbour inside M; degree-2 nodes are kept (they carry the curve);
chains between two branching nodes shorter than ``merge`` (2) inscribed radii are collapsed into one
junction node (close junctions made the sections of their limbs overlap), then spurs are pruned again.

PyGEL3D's ``MSLS_skeleton`` is not deterministic (its separator search is multi-threaded): two runs on
the same mesh can give different node counts. ``LS_skeleton(g, sampling=False)`` was deterministic in
our runs but took 150-220 s on the 6,000-vertex zoo characters (MSLS: 3-11 s), so it is not used.
"""

from __future__ import annotations

import time

import igl
import numpy as np

from ..errors import BackendUnavailableError, CageError
from .graph import Skeleton

__all__ = ["extract_skeleton"]


def _pygel_graph(V: np.ndarray, F: np.ndarray, grow_thresh: int):
    try:
        from pygel3d import graph, hmesh
    except ImportError as exc:
        raise BackendUnavailableError(
            "automatic skeleton extraction needs the optional 'pygel3d' package (MIT; pip install pygel3d), "
            "or pass skeleton= (a .skel file or (nodes, edges))") from exc
    m = hmesh.Manifold.from_triangles(np.ascontiguousarray(V, float), np.ascontiguousarray(F, np.int32))
    g = graph.from_mesh(m)
    s = graph.MSLS_skeleton(g, grow_thresh=int(grow_thresh))
    nodes = list(s.nodes())
    pos = np.asarray(s.positions(), dtype=float)
    idx = {n: i for i, n in enumerate(nodes)}
    E = {tuple(sorted((idx[n], idx[nb]))) for n in nodes for nb in s.neighbors(n)}
    return pos[nodes] if len(pos) > len(nodes) else pos, np.array(sorted(E), dtype=np.int64).reshape(-1, 2)


def _spanning_tree(P: np.ndarray, E: np.ndarray) -> np.ndarray:
    import scipy.sparse as sp
    from scipy.sparse.csgraph import minimum_spanning_tree

    w = np.linalg.norm(P[E[:, 0]] - P[E[:, 1]], axis=1) + 1e-12
    A = sp.coo_matrix((w, (E[:, 0], E[:, 1])), shape=(len(P), len(P)))
    T = minimum_spanning_tree(A).tocoo()
    return np.column_stack([T.row, T.col]).astype(np.int64)


def _largest_component(P, E):
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    A = sp.coo_matrix((np.ones(len(E)), (E[:, 0], E[:, 1])), shape=(len(P), len(P)))
    _, lab = connected_components(A, directed=False)
    keep = lab == np.bincount(lab).argmax()
    return _compact(P, E, keep)


def _compact(P, E, keep):
    new = np.full(len(P), -1)
    new[keep] = np.arange(keep.sum())
    E = E[keep[E[:, 0]] & keep[E[:, 1]]]
    return P[keep], new[E]


def _contract_short(P: np.ndarray, E: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Merge the end points of edges shorter than ``tol`` (coincident skeleton nodes)."""
    parent = np.arange(len(P))

    def root(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for a, b in E[np.linalg.norm(P[E[:, 0]] - P[E[:, 1]], axis=1) < tol]:
        ra, rb = root(a), root(b)
        if ra != rb:
            parent[rb] = ra
    r = np.array([root(i) for i in range(len(P))])
    E2 = r[E]
    E2 = E2[E2[:, 0] != E2[:, 1]]
    E2 = np.unique(np.sort(E2, axis=1), axis=0)
    keep = r == np.arange(len(P))
    new = np.cumsum(keep) - 1
    return P[keep], new[E2]


def _prune(P: np.ndarray, E: np.ndarray, r: np.ndarray, prune: float) -> tuple[np.ndarray, np.ndarray, int]:
    """Remove leaf chains shorter than ``prune * r[branching node]`` until none is left."""
    removed = 0
    while True:
        S = Skeleton.__new__(Skeleton)  # no validation: may still have cycles/degenerate parts
        S.nodes, S.edges, S.bending = P, E, []
        deg = np.bincount(E.ravel(), minlength=len(P))
        if (deg >= 3).sum() == 0:
            return P, E, removed
        drop = np.zeros(len(P), bool)
        for ch in Skeleton.chains(S):
            a, b = ch.start, ch.end
            if deg[a] == 1 and deg[b] >= 3:
                br = b
            elif deg[b] == 1 and deg[a] >= 3:
                br = a
            else:
                continue
            X = P[np.asarray(ch.nodes)]
            L = float(np.linalg.norm(np.diff(X, axis=0), axis=1).sum())
            if L < prune * r[br]:
                drop[[n for n in ch.nodes if n != br]] = True
                break  # one spur at a time: degrees change
        if not drop.any():
            return P, E, removed
        removed += 1
        P, E = _compact(P, E, ~drop)


def _merge_close_branching(P: np.ndarray, E: np.ndarray, V: np.ndarray, F: np.ndarray,
                           merge: float) -> tuple[np.ndarray, np.ndarray, list]:
    """Collapse chains between two branching nodes shorter than ``merge`` x the larger inscribed radius
    of their ends into one junction node (at the chain's arc-length middle if it is inside M, else at
    the end with the larger radius). One chain at a time, shortest first, until none is left.

    Returns (P, E, list of merged chains as {"length", "radius", "n_nodes"}).
    """
    merged: list = []
    while True:
        deg = np.bincount(E.ravel(), minlength=len(P))
        if (deg >= 3).sum() < 2:
            return P, E, merged
        S = Skeleton.__new__(Skeleton)  # no validation
        S.nodes, S.edges, S.bending = P, E, []
        r = np.sqrt(igl.point_mesh_squared_distance(P, V, F)[0])
        best = None
        for ch in Skeleton.chains(S):
            a, b = ch.start, ch.end
            if deg[a] < 3 or deg[b] < 3 or a == b:
                continue
            X = P[np.asarray(ch.nodes)]
            s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(X, axis=0), axis=1))]
            if s[-1] < merge * max(r[a], r[b]) and (best is None or s[-1] < best[1]):
                best = (ch, float(s[-1]), X, s)
        if best is None:
            return P, E, merged
        ch, L, X, s = best
        mid = np.array([np.interp(L / 2, s, X[:, k]) for k in range(3)])
        a, b = ch.start, ch.end
        if igl.winding_number(V, F, mid[None])[0] < 0.5:
            mid = P[a] if r[a] >= r[b] else P[b]
        merged.append({"length": L, "radius": float(max(r[a], r[b])), "n_nodes": len(ch.nodes)})
        parent = np.arange(len(P))
        parent[np.asarray(ch.nodes)] = a
        P = P.copy()
        P[a] = mid
        E2 = parent[E]
        E2 = np.unique(np.sort(E2[E2[:, 0] != E2[:, 1]], axis=1), axis=0)
        keep = parent == np.arange(len(P))
        new = np.cumsum(keep) - 1
        P, E = P[keep], new[E2]


def extract_skeleton(V: np.ndarray, F: np.ndarray, grow_thresh: int = 64, prune: float = 2.0,
                     merge: float = 2.0) -> tuple[Skeleton, dict]:
    """Curve skeleton of a closed surface (PyGEL3D multi-scale local separators), cleaned to a tree.

    Parameters
    ----------
    V : (n,3) float array
    F : (m,3) int array
    grow_thresh : int
        PyGEL3D's separator growth limit (larger: coarser, faster).
    prune : float
        Leaf branches shorter than this many inscribed radii at their branching node are removed.
    merge : float
        Chains between two branching nodes shorter than this many inscribed radii (the larger of their
        ends) are collapsed into one junction node, so that the sections of the limbs leaving two close
        junctions do not overlap (0: no merging). Spurs are pruned again after merging.

    Returns
    -------
    skeleton : Skeleton
        A tree inside the surface (no bending nodes).
    info : dict
        ``seconds``, raw and final node/edge counts, spurs pruned, leaves dropped outside M.

    Raises
    ------
    BackendUnavailableError
        pygel3d is not installed.
    CageError
        The extracted skeleton is empty or leaves the surface away from its leaves.
    """
    t0 = time.perf_counter()
    P, E = _pygel_graph(V, F, grow_thresh)
    info = {"raw_nodes": len(P), "raw_edges": len(E)}
    if len(E) == 0:
        raise CageError("skeleton extraction (pygel3d): empty skeleton", layer=1)
    P, E = _largest_component(P, E)
    E = _spanning_tree(P, E)
    # drop nodes outside the surface from the leaves inwards
    dropped = 0
    while True:
        w = igl.winding_number(V, F, P)
        deg = np.bincount(E.ravel(), minlength=len(P))
        out = (w < 0.5) & (deg <= 1)
        if not out.any():
            break
        dropped += int(out.sum())
        P, E = _compact(P, E, ~out)
    # interior nodes outside M (thin parts): move them towards their neighbours' mean until inside
    moved = 0
    for _ in range(50):
        out = np.flatnonzero(igl.winding_number(V, F, P) < 0.5)
        if len(out) == 0:
            break
        nb_sum = np.zeros_like(P)
        cnt = np.zeros(len(P))
        np.add.at(nb_sum, E[:, 0], P[E[:, 1]])
        np.add.at(nb_sum, E[:, 1], P[E[:, 0]])
        np.add.at(cnt, E.ravel(), 1.0)
        P = P.copy()
        P[out] = 0.5 * P[out] + 0.5 * nb_sum[out] / np.maximum(cnt[out], 1.0)[:, None]
        moved += len(out)
    # still outside: merge each such node into a neighbour inside M (edge contraction)
    merged = 0
    for _ in range(10):
        w = igl.winding_number(V, F, P)
        out = np.flatnonzero(w < 0.5)
        if len(out) == 0:
            break
        nb = [[] for _ in range(len(P))]
        for a, b in E:
            nb[a].append(b)
            nb[b].append(a)
        pairs = [(o, max(nb[o], key=lambda j: w[j])) for o in out if nb[o]]
        parent = np.arange(len(P))
        for o, j in pairs:
            if w[j] >= 0.5 and parent[j] == j:
                parent[o] = j
        if np.all(parent == np.arange(len(P))):
            break
        E2 = parent[E]
        E2 = np.unique(np.sort(E2[E2[:, 0] != E2[:, 1]], axis=1), axis=0)
        keep = parent == np.arange(len(P))
        new = np.cumsum(keep) - 1
        P, E = P[keep], new[E2]
        merged += int((~keep).sum())
    n_out = int(np.sum(igl.winding_number(V, F, P) < 0.5))
    if n_out:
        raise CageError(f"skeleton extraction (pygel3d): {n_out} interior skeleton nodes lie outside the surface "
                        "(after 50 smoothing steps)", layer=1)
    P, E = _contract_short(P, E, 1e-6 * float(np.linalg.norm(np.ptp(V, axis=0))))
    d2, _, _ = igl.point_mesh_squared_distance(P, V, F)
    P, E, n_pruned = _prune(P, E, np.sqrt(d2), prune)
    junctions_merged: list = []
    if merge > 0:
        P, E, junctions_merged = _merge_close_branching(P, E, V, F, merge)
        if junctions_merged:
            d2, _, _ = igl.point_mesh_squared_distance(P, V, F)
            P, E, n2 = _prune(P, E, np.sqrt(d2), prune)
            n_pruned += n2
    if len(P) < 2 or len(E) == 0:
        # pruning and junction merging can reduce a blob-like shape's skeleton to one node: that is a
        # failed extraction (no tube to build), not a bad user skeleton
        raise CageError(f"skeleton extraction (pygel3d): the cleaned skeleton has {len(P)} node(s) and no edge "
                        f"({n_pruned} spurs pruned, {len(junctions_merged)} junctions merged); the shape has no "
                        "limbs for a skeleton cage: give a skeleton or use another method", layer=1)
    S = Skeleton(P, E)
    info.update({"n_nodes": len(P), "n_edges": len(E), "spurs_pruned": n_pruned,
                 "leaves_outside_dropped": dropped, "outside_node_moves": moved, "outside_nodes_merged": merged,
                 "junctions_merged": junctions_merged, "n_leaves": len(S.leaves), "n_branching": len(S.branching),
                 "seconds": time.perf_counter() - t0, "method": "pygel3d.graph.MSLS_skeleton"})
    return S, info
