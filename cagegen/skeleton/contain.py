"""Containment of the tight skeleton cage by a sweep of the guiding field's level sets (issue 29).

The Nested Cages flow (:mod:`cagegen.nested.flow`) moves M along the signed distance of the cage until
it is inside; after a skeleton cage it stalls where the cage's faces are far from M (Casti et al.
2019, Sec. 3.5 and Fig. 18). The harmonic guiding field f (0 on the skeleton, 1 on M) already gives
a path that ends inside the cage: its integral lines, followed *down*, carry every point of M to the
skeleton, and the level sets ``{f = s}`` sweep from a thin tube around the skeleton (inside the tight
cage, which is built around the skeleton) out to M. We follow each vertex of a target surface T
down its integral line and record where it crosses ``f = 1, s_1, ..., s_k``; replayed from ``s_k``
up to 1 and then to T's own positions, this is the history that Nested Cages' re-inflation
(:func:`cagegen.nested.reinflate.reinflate`: IPC barrier + CCD, Newton on the incremental
potential) replays while pushing the cage out of the way. No flow is run, so nothing can stall
before the re-inflation.

The target T is M itself (or the inner layer of a hierarchy); M's offset envelope and a ``nested``
proxy cage were measured as targets and dropped (slower, not tighter: docs/skeleton.md). The clearance is
added afterwards (:func:`cagegen.nested.backend.push_out`).
"""

from __future__ import annotations

import time

import igl
import numpy as np

from .field import GuidingField

__all__ = ["collapse_inside", "descend", "sweep_history", "start_level"]


def _inside_points(field: GuidingField, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points ``P`` on (or just off) M moved a hair into the tet mesh, and their tets (-1: none found)."""
    P = np.array(P, dtype=float)
    tet = field.locate(P)
    for frac in (1e-4, 1e-2, 0.1):
        miss = np.flatnonzero(tet < 0)
        if len(miss) == 0:
            break
        _, c = field._ctree.query(P[miss])
        Q = P[miss] + frac * (field.centroids[c] - P[miss])
        t = field.locate(Q)
        ok = t >= 0
        P[miss[ok]], tet[miss[ok]] = Q[ok], t[ok]
    return P, tet


def descend(field: GuidingField, P: np.ndarray, levels, step: float | None = None,
            max_steps: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Follow the integral lines of f *down* from ``P`` and record where they cross ``levels``.

    Parameters
    ----------
    field : GuidingField
    P : (n,3) float array
        Start points on M or inside it (points just outside are moved a hair inside).
    levels : sequence of float
        Decreasing values of f in (0, 1).
    step : float, optional
        RK2 step length (default: half the tet edge length).
    max_steps : int, optional
        Steps per line (default: 4 diagonals of travel).

    Returns
    -------
    X : (k,n,3) float array
        ``X[j, i]``: where the line from ``P[i]`` crosses ``levels[j]`` (a line that stops early goes
        on straight to the nearest skeleton node, :func:`_finish_lines`).
    reached : (n,) bool
        The line reached the last level.
    """
    levels = np.asarray(levels, dtype=float)
    P, tet = _inside_points(field, P)
    n, k = len(P), len(levels)
    h = float(step) if step is not None else 0.5 * field.edge_length
    if max_steps is None:
        max_steps = int(4 * float(np.linalg.norm(np.ptp(field.TV, axis=0))) / h) + 10
    X = np.repeat(P[None], k, axis=0)
    nxt = np.zeros(n, dtype=np.int64)  # next level to record, per line
    pos = P.copy()
    fv = np.where(tet >= 0, field.value(P, np.maximum(tet, 0)), 1.0)
    active = tet >= 0
    for _ in range(max_steps):
        ids = np.flatnonzero(active)
        if len(ids) == 0:
            break
        p0, t0, f0 = pos[ids], tet[ids], fv[ids]
        pm = p0 - 0.5 * h * field.gradient_at(p0, t0)
        tm = field._walk(pm, t0)
        g = field.gradient_at(np.where(tm[:, None] >= 0, pm, p0), np.where(tm >= 0, tm, t0))
        p1 = p0 - h * g
        t1 = field._walk(p1, t0)
        stop = (t1 < 0)
        f1 = np.where(stop, f0, field.value(p1, np.maximum(t1, 0)))
        stop |= f1 >= f0  # no descent left (skeleton reached, or a flat spot)
        for j in range(k):  # record the crossings of this step (several levels per step possible)
            c = ~stop & (nxt[ids] == j) & (f1 <= levels[j])
            if not c.any():
                continue
            w = ((f0[c] - levels[j]) / np.maximum(f0[c] - f1[c], 1e-300))[:, None]
            X[j, ids[c]] = p0[c] + w * (p1[c] - p0[c])
            nxt[ids[c]] = j + 1
        mv = ~stop
        pos[ids[mv]], tet[ids[mv]], fv[ids[mv]] = p1[mv], t1[mv], f1[mv]
        active[ids[stop]] = False
        active &= nxt < k
    _finish_lines(field, X, nxt, pos, fv, levels)
    return X, nxt >= k


def _finish_lines(field: GuidingField, X, nxt, pos, fv, levels) -> None:
    """Lines that stopped before the last level (left the tet mesh on their first step at a concave
    spot of M, a flat spot, or overshot the skeleton): the remaining crossings go straight to the
    nearest skeleton node q, ``q + (s / f_last) (p_last - q)`` (f taken as linear along the segment)."""
    from scipy.spatial import cKDTree

    todo = np.flatnonzero(nxt < len(levels))
    if len(todo) == 0:
        return
    zero = field.TV[field.f <= 0.0]
    _, qi = cKDTree(zero).query(pos[todo])
    q = zero[qi]
    for j in range(len(levels)):
        m = nxt[todo] <= j
        r = np.minimum(levels[j] / np.maximum(fv[todo[m]], 1e-12), 1.0)[:, None]
        X[j, todo[m]] = q[m] + r * (pos[todo[m]] - q[m])


def sweep_history(field: GuidingField, VT: np.ndarray, Vm: np.ndarray, Fm: np.ndarray,
                  levels) -> tuple[list, dict]:
    """Reverse-time history of the target ``VT`` for :func:`cagegen.nested.reinflate.reinflate`.

    ``[VT, VT's closest points on M, the level crossings at levels[0], ..., levels[-1]]`` (entries equal
    to the previous one are skipped). Returns the history and figures (lines reaching the last level,
    ``levels``: f of each history entry, None for ``VT``; seconds).
    """
    t = time.perf_counter()
    VT = np.asarray(VT, dtype=float)
    _, _, on_m = igl.point_mesh_squared_distance(VT, Vm, Fm)
    X, reached = descend(field, on_m, levels)
    hist, f_of = [VT], [None]
    for Y, f in zip((on_m, *X), (1.0, *levels)):
        if np.abs(Y - hist[-1]).max() > 0:
            hist.append(np.ascontiguousarray(Y))
            f_of.append(float(f))
    return hist, {"lines_reaching_last_level": int(reached.sum()), "n_lines": len(VT), "levels": f_of,
                  "seconds": time.perf_counter() - t}


def start_level(history: list, FT: np.ndarray, Vc: np.ndarray, Fc: np.ndarray) -> int:
    """Index of the shallowest entry of ``history`` such that it and every deeper entry lie strictly
    inside the cage ``(Vc, Fc)`` (no cage-target intersection, every target vertex inside by winding
    number), checked from the deepest entry outwards; -1 when the deepest is not inside."""
    from ..collision import PairMesh

    best = -1
    for j in range(len(history) - 1, 0, -1):
        Y = history[j]
        w = igl.fast_winding_number(Vc, Fc, Y)
        if np.any(w < 0.5):
            break
        pm = PairMesh(Vc, Fc, Y, FT)
        if pm.intersects(pm.stack(Vc, Y)):
            break
        best = j
    return best


def collapse_inside(field: GuidingField, Y: np.ndarray, FT: np.ndarray, Vc: np.ndarray, Fc: np.ndarray,
                    shrink: float = 0.05, rounds: int = 60) -> np.ndarray | None:
    """A last history entry strictly inside the cage: each point of ``Y`` (the deepest level) taken
    to ``q + a (y - q)``, q a skeleton node inside ``(Vc, Fc)`` (field nodes with f = 0 and winding
    number > 0.5), ``a <= shrink`` small enough to stay within half q's distance to the cage.

    Skeleton ends beyond a leaf section, or chords of the tight cage that cut the skeleton, leave some
    skeleton nodes outside the cage; those parts of the target start from the nearest node inside.
    q starts as the nearest such node; where an edge of ``FT`` joins two nodes whose chord leaves the
    cage (16 samples, winding number), the endpoint takes its neighbour's node (up to ``rounds``
    times). None when no skeleton node is inside.
    """
    from scipy.spatial import cKDTree

    Z = field.TV[field.f <= 0.0]
    Z = Z[igl.fast_winding_number(Vc, Fc, Z) > 0.5]
    if len(Z) == 0:
        return None
    r = np.sqrt(igl.point_mesh_squared_distance(Z, Vc, Fc)[0])
    _, lab = cKDTree(Z).query(Y)
    E = np.unique(np.sort(np.vstack([FT[:, [0, 1]], FT[:, [1, 2]], FT[:, [2, 0]]]), axis=1), axis=0)
    t = np.linspace(0.0, 1.0, 16)[1:-1]
    ok_pair: dict = {}
    for _ in range(rounds):
        a, b = lab[E[:, 0]], lab[E[:, 1]]
        diff = np.flatnonzero(a != b)
        pairs = {(int(x), int(y)) for x, y in zip(a[diff], b[diff])} - set(ok_pair)
        if pairs:
            P = np.array(sorted(pairs))
            S = Z[P[:, 0]][:, None] + t[None, :, None] * (Z[P[:, 1]] - Z[P[:, 0]])[:, None]
            w = igl.fast_winding_number(Vc, Fc, S.reshape(-1, 3)).reshape(len(P), -1)
            ok_pair.update({(int(x), int(y)): bool(v) for (x, y), v in zip(P, (w > 0.5).all(axis=1))})
        bad = [e for e in diff if not ok_pair[(int(a[e]), int(b[e]))]]
        if not bad:
            break
        for e in bad:  # the endpoint whose node is farther from the cage's core gives way
            u, v = E[e]
            if r[lab[u]] < r[lab[v]]:
                lab[u] = lab[v]
            else:
                lab[v] = lab[u]
    return _exact_repair(Y, FT, Vc, Fc, Z, r, lab, shrink)


def _collapsed(Y, Z, r, lab, shrink):
    q = Z[lab]
    L = np.linalg.norm(Y - q, axis=1)
    a = np.minimum(shrink, 0.5 * r[lab] / np.maximum(L, 1e-300))
    return np.ascontiguousarray(q + a[:, None] * (Y - q))


def _exact_repair(Y, FT, Vc, Fc, Z, r, lab, shrink, rounds: int = 30):
    """The collapsed entry, with the vertices of target faces that still cross the cage (exact test)
    or lie outside it moved to the deepest node (largest clearance) of their one-ring, repeatedly."""
    from .._geometry import cross_intersection_pairs

    ring = igl.adjacency_list(np.asarray(FT, dtype=np.int64))
    for _ in range(rounds):
        X = _collapsed(Y, Z, r, lab, shrink)
        bad = set(np.flatnonzero(igl.fast_winding_number(Vc, Fc, X) < 0.5).tolist())
        pr = cross_intersection_pairs(Vc, Fc, X, FT)
        if len(pr):
            bad |= set(np.unique(FT[pr[:, 1]]).tolist())
        if not bad:
            return X
        new = lab.copy()
        for v in bad:
            cand = [v, *ring[v]]
            best = max(cand, key=lambda u: r[lab[u]])
            new[v] = lab[best] if lab[best] != lab[v] else int(np.argmax(r))
        lab = new
    return _collapsed(Y, Z, r, lab, shrink)
