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
The source of the variation (GEL's ``multiscale_local_separators``): ``std::thread::hardware_concurrency()``
threads share ``rand()`` (the separator sampling) and the ``touched`` counts, so the sampled separators
depend on the threads' interleaving; the thread count is the number of online CPUs (not the affinity
mask: ``taskset`` does not change it) and no option or environment variable sets it. The front-separator
skeleton (``graph_front_skeleton``, deterministic, 0.4-5 s) was tried with coordinate fields along the
principal and coordinate axes: it lost limbs on the zoo (homer's legs one path, cheburashka's arms
missing), so it is not used either. Reproducibility therefore comes from a cache: the raw MSLS graph
of the first usable extraction is stored under the SHA-256 of the input (``cache=``), and the cleaning
below is deterministic, so the same input gives the same skeleton. Non-finite node positions (once in
an MSLS result on spot) are dropped before cleaning; an extraction whose cleaned skeleton is unusable
is repeated (``attempts``).
"""

from __future__ import annotations

import hashlib
import io
import os
import tempfile
import time
from pathlib import Path

import igl
import numpy as np

from ..errors import BackendUnavailableError, CageError, MeshInputError
from .graph import Skeleton

__all__ = ["extract_skeleton", "skeleton_cache_dir"]


def _pygel_version() -> str:
    try:
        from importlib.metadata import version

        return version("pygel3d")
    except Exception:  # noqa: BLE001 -- only part of a cache key
        return "unknown"


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
    # Graph.positions() is a view of the C++ graph's memory ("by reference"): copy it while ``s`` is alive.
    # Returning the view (as before) let the positions change once ``s`` was freed: NaN nodes, skeletons
    # that collapsed to one node, and a different cleaned skeleton from the same call's result.
    pos = np.array(s.positions(), dtype=float, copy=True)
    idx = {n: i for i, n in enumerate(nodes)}
    E = {tuple(sorted((idx[n], idx[nb]))) for n in nodes for nb in s.neighbors(n)}
    P = pos[np.asarray(nodes, dtype=np.int64)]
    del s, g, m
    return P, np.array(sorted(E), dtype=np.int64).reshape(-1, 2)


def skeleton_cache_dir() -> Path:
    """Folder of cached raw skeletons: ``$NESTMG_CACHE/skeleton`` (default ``~/.cache/nestmg/skeleton``)."""
    return Path(os.environ.get("NESTMG_CACHE", Path.home() / ".cache" / "nestmg")) / "skeleton"


def _cache_key(V: np.ndarray, F: np.ndarray, grow_thresh: int) -> str:
    """SHA-256 (32 hex digits) of the surface's bytes, the extraction option and pygel3d's version."""
    h = hashlib.sha256(b"nestmg-skeleton-raw-v1")
    for a in (np.ascontiguousarray(V, np.float64), np.ascontiguousarray(F, np.int64)):
        h.update(str(a.shape).encode())
        h.update(a.tobytes())
    h.update(f"grow_thresh={int(grow_thresh)};pygel3d={_pygel_version()}".encode())
    return h.hexdigest()[:32]


def _cache_load(path: Path):
    """(P, E) stored at ``path`` when readable and consistent with its recorded digest, else None."""
    if not path.exists():
        return None
    try:
        with np.load(path) as z:
            P, E, digest = np.asarray(z["P"], float), np.asarray(z["E"], np.int64), str(z["digest"])
    except Exception:  # noqa: BLE001 -- an unreadable entry is a miss (re-extracted and rewritten)
        return None
    if digest != _raw_digest(P, E):
        return None
    return P, E


def _raw_digest(P: np.ndarray, E: np.ndarray) -> str:
    h = hashlib.sha256(np.ascontiguousarray(P, np.float64).tobytes())
    h.update(np.ascontiguousarray(E, np.int64).tobytes())
    return h.hexdigest()


def _cache_save(path: Path, P: np.ndarray, E: np.ndarray) -> None:
    """Write (P, E) atomically (temporary file in the same folder, then a rename)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    buf = io.BytesIO()
    np.savez_compressed(buf, P=P, E=E, digest=np.array(_raw_digest(P, E)))
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(buf.getvalue())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _finite_only(P: np.ndarray, E: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Drop nodes with non-finite coordinates (seen once in an MSLS result on spot) and their edges."""
    ok = np.all(np.isfinite(P), axis=1)
    if ok.all():
        return P, E, 0
    P2, E2 = _compact(P, E, ok)
    return P2, E2, int((~ok).sum())


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


def _clean(P: np.ndarray, E: np.ndarray, V: np.ndarray, F: np.ndarray, prune: float,
           merge: float) -> tuple[Skeleton, dict]:
    """The raw graph (P, E) cleaned into a tree inside (V, F) (module docstring); CageError when impossible."""
    P, E, n_nonfinite = _finite_only(np.asarray(P, float), np.asarray(E, np.int64).reshape(-1, 2))
    info = {"raw_nodes": len(P), "raw_edges": len(E), "raw_nonfinite_nodes": n_nonfinite}
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
                 "junctions_merged": junctions_merged, "n_leaves": len(S.leaves), "n_branching": len(S.branching)})
    return S, info


def extract_skeleton(V: np.ndarray, F: np.ndarray, grow_thresh: int = 64, prune: float = 2.0,
                     merge: float = 2.0, cache=None, attempts: int = 3) -> tuple[Skeleton, dict]:
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
    cache : None, False or path
        Folder of raw skeletons keyed by the SHA-256 of ``(V, F)``, ``grow_thresh`` and pygel3d's
        version (None: :func:`skeleton_cache_dir`, ``$NESTMG_CACHE/skeleton``; False: no cache).
        PyGEL3D's extraction is not deterministic (module docstring); with the cache, the same input
        always gets the same raw skeleton, hence the same cleaned skeleton (the cleaning is
        deterministic). The raw graph is stored, not the cleaned tree, so changes to the cleaning
        apply to cached entries; an entry whose cleaning fails is extracted again.
    attempts : int
        Extractions tried when the cleaned skeleton is unusable (a ``CageError`` of the cleaning: one
        node left, nodes outside M, empty); only a usable raw skeleton is cached.

    Returns
    -------
    skeleton : Skeleton
        A tree inside the surface (no bending nodes).
    info : dict
        ``seconds``, raw and final node/edge counts, spurs pruned, leaves dropped outside M, ``cache``
        ("hit", "miss" or "off"), ``cache_key``, ``attempts``, ``raw_digest`` / ``skeleton_digest``
        (SHA-256 of the raw graph / of the cleaned nodes and edges: equal digests, equal skeletons).

    Raises
    ------
    BackendUnavailableError
        pygel3d is not installed.
    CageError
        Every attempt's skeleton was empty, left the surface away from its leaves, or collapsed to one
        node (the message is the last attempt's).
    """
    t0 = time.perf_counter()
    V = np.asarray(V, np.float64)
    F = np.asarray(F, np.int64)
    key = _cache_key(V, F, grow_thresh)
    path = None if cache is False else (Path(cache) if cache is not None else skeleton_cache_dir()) / f"{key}.npz"
    status = "off" if path is None else "miss"
    failures: list = []
    cached = _cache_load(path) if path is not None else None
    for k in range(max(int(attempts), 1) + (cached is not None)):
        if cached is not None and k == 0:
            P, E = cached
        else:
            P, E = _pygel_graph(V, F, grow_thresh)
        try:
            S, info = _clean(P, E, V, F, prune, merge)
        except (CageError, MeshInputError) as exc:
            failures.append(str(exc))
            if k == 0 and cached is not None:
                status = "stale"  # the cleaning of the cached raw skeleton fails: extract again
            continue
        if cached is not None and k == 0:
            status = "hit"
        elif path is not None:
            try:
                _cache_save(path, np.asarray(P, float), np.asarray(E, np.int64).reshape(-1, 2))
            except OSError as exc:  # a read-only cache must not fail the extraction
                status = f"not written ({exc.__class__.__name__})"
        h = hashlib.sha256(np.ascontiguousarray(S.nodes, np.float64).tobytes())
        h.update(np.ascontiguousarray(S.edges, np.int64).tobytes())
        info.update({"cache": status, "cache_key": key, "attempts": len(failures) + 1,
                     "failed_attempts": failures,
                     "raw_digest": _raw_digest(np.asarray(P, float), np.asarray(E, np.int64).reshape(-1, 2)),
                     "skeleton_digest": h.hexdigest(), "seconds": time.perf_counter() - t0,
                     "method": "pygel3d.graph.MSLS_skeleton"})
        return S, info
    raise CageError(failures[-1] + f" ({len(failures)} extraction attempt(s))", layer=1)


