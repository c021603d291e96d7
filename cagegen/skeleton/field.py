"""The guiding harmonic field of Casti et al. (2019), Sec. 3.1, and its integral lines.

Tet mesh of the interior of M: scipy's Qhull Delaunay tetrahedralisation of the surface vertices, a
body-centred lattice of spacing h inside M and the skeleton samples; tets whose centroid has winding
number > 1/2 are kept. The skeleton samples are tet nodes, so f = 0 is imposed exactly on points of S
(the paper embeds S as chains of tet edges). Seconds; the boundary approximates M. (A conforming TetWild
mesh was tried and deleted: minutes on a loaded 2-core machine, docs/history/skeleton.md.)

With f = 1 on the boundary nodes, f solves the cotangent-Laplace problem ``Δf = 0`` (libigl
``cotmatrix``, scipy direct solve). f is linear per tet, so ∇f is piecewise constant and its exact
integral lines collapse onto edges; :meth:`GuidingField.trace` integrates the nodal average of ∇f
(continuous) with midpoint steps and a tet walk, and snaps each line's end onto M.
"""

from __future__ import annotations

import time

import igl
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.spatial import cKDTree

from ..errors import CageError

__all__ = ["GuidingField", "guiding_field"]

# face j of a tet is opposite its vertex j
_FACE_OF = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])


def _tet_adjacency(T: np.ndarray) -> np.ndarray:
    """(t,4) int: the tet across face j (opposite vertex j) of each tet, -1 on the boundary."""
    t = len(T)
    faces = np.sort(T[:, _FACE_OF].reshape(-1, 3), axis=1)  # (4t,3), row 4i+j = face j of tet i
    order = np.lexsort(faces.T[::-1])
    fs = faces[order]
    same = np.all(fs[1:] == fs[:-1], axis=1)
    adj = np.full(4 * t, -1, dtype=np.int64)
    i = np.flatnonzero(same)
    a, b = order[i], order[i + 1]
    adj[a] = b // 4
    adj[b] = a // 4
    return adj.reshape(t, 4)


class GuidingField:
    """Harmonic field f on a tet mesh of the surface: 0 on the skeleton, 1 on the surface.

    Attributes
    ----------
    TV : (n,3) float array
        Tet mesh nodes.
    TT : (t,4) int array
        Tets (positively oriented).
    f : (n,) float array
        Field values.
    grad : (t,3) float array
        Per-tet gradient of f.
    skeleton_offset : dict
        ``max`` / ``mean`` distance between the nodes where f = 0 is imposed and the skeleton.
    seconds : dict
        ``tetmesh`` and ``solve`` timings.
    """

    def __init__(self, V: np.ndarray, F: np.ndarray, skel_points: np.ndarray, edge_length: float):
        self.V, self.F = V, F
        self.edge_length = float(edge_length)
        self.seconds = {}
        t0 = time.perf_counter()
        TV, TT = _delaunay_tets(V, F, skel_points, float(edge_length))
        n_skel = len(skel_points)
        TV = np.asarray(TV, dtype=np.float64)
        TT = np.asarray(TT, dtype=np.int64)
        if len(TT) == 0:
            raise CageError("skeleton cage, guiding field: the Delaunay mesh has no tet inside", layer=1)
        used = np.unique(TT)
        remap = np.full(len(TV), -1)
        remap[used] = np.arange(len(used))
        skel_ids = remap[len(TV) - n_skel:] if n_skel else np.zeros(0, dtype=np.int64)
        TV, TT = TV[used], remap[TT]
        P = TV[TT]
        D = np.stack([P[:, 1] - P[:, 0], P[:, 2] - P[:, 0], P[:, 3] - P[:, 0]], axis=2)  # columns
        vol = np.linalg.det(D)
        flip = vol < 0
        TT[flip] = TT[flip][:, [1, 0, 2, 3]]
        P = TV[TT]
        D = np.stack([P[:, 1] - P[:, 0], P[:, 2] - P[:, 0], P[:, 3] - P[:, 0]], axis=2)
        self.TV, self.TT = TV, TT
        self.Dinv = np.linalg.inv(D)  # barycentric coordinates: (l1,l2,l3) = Dinv (p - x0)
        self.adj = _tet_adjacency(TT)
        self.seconds["tetmesh"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        bfaces = self.adj == -1
        boundary = np.unique(TT[:, _FACE_OF][bfaces].ravel())
        # f = 0 at the tet nodes nearest to dense skeleton samples (the paper embeds S as tet edges)
        is_b = np.zeros(len(TV), bool)
        is_b[boundary] = True
        interior = np.flatnonzero(~is_b)
        if len(interior) == 0:
            raise CageError("skeleton cage, guiding field: the tet mesh has no interior node (edge length "
                            "too large for this shape)", layer=1)
        dist, idx = cKDTree(TV[interior]).query(skel_points)
        zero = np.unique(interior[idx])
        if n_skel:  # the skeleton samples are tet nodes: f = 0 exactly on them (paper: S embedded)
            zero = np.unique(skel_ids[(skel_ids >= 0)])
            zero = zero[~is_b[zero]]
            dist = np.zeros(1)
        if len(zero) == 0:
            raise CageError("skeleton cage, guiding field: no tet node on the skeleton (skeleton outside the "
                            "tet mesh?)", layer=1)
        self.skeleton_offset = {"max": float(dist.max()), "mean": float(dist.mean()), "n_nodes": len(zero)}
        fixed = np.zeros(len(TV), bool)
        fixed[boundary] = True
        fixed[zero] = True
        f = np.zeros(len(TV))
        f[boundary] = 1.0
        L = -igl.cotmatrix(TV, TT.astype(np.int64))  # positive semi-definite stiffness matrix
        L = sp.csr_matrix(L)
        free = np.flatnonzero(~fixed)
        rhs = -(L[free][:, fixed] @ f[fixed])
        A = L[free][:, free].tocsc()
        f[free] = spla.spsolve(A, rhs) if len(free) else f[free]
        self.f = f
        g = np.stack([f[TT[:, 1]] - f[TT[:, 0]], f[TT[:, 2]] - f[TT[:, 0]], f[TT[:, 3]] - f[TT[:, 0]]], axis=1)
        self.grad = np.einsum("tji,tj->ti", self.Dinv, g)  # grad = Dinv^T (f_i - f_0)
        # per-node averaged gradient: direction where a tet is flat (all nodes fixed to the same value)
        vol6 = np.abs(np.linalg.det(np.linalg.inv(self.Dinv)))
        ng = np.zeros((len(TV), 3))
        wsum = np.zeros(len(TV))
        for j in range(4):
            np.add.at(ng, TT[:, j], self.grad * vol6[:, None])
            np.add.at(wsum, TT[:, j], vol6)
        ng /= np.maximum(wsum, 1e-300)[:, None]
        self._node_grad = ng
        self.centroids = P.mean(axis=1)
        self._ctree = cKDTree(self.centroids)
        self.seconds["solve"] = time.perf_counter() - t0
        self.n_tets = len(TT)
        self.n_nodes = len(TV)

    # ------------------------------------------------------------------ point location
    def locate(self, P: np.ndarray, k: int = 24) -> np.ndarray:
        """Index of a tet containing each point (-1 when none of the ``k`` nearest tets does)."""
        P = np.atleast_2d(P)
        _, cand = self._ctree.query(P, k=min(k, len(self.TT)))
        cand = np.atleast_2d(cand)
        out = np.full(len(P), -1, dtype=np.int64)
        for j in range(cand.shape[1]):
            todo = out < 0
            if not todo.any():
                break
            c = cand[todo, j]
            lam = self._bary(P[todo], c)
            ok = lam.min(axis=1) >= -1e-9
            idx = np.flatnonzero(todo)[ok]
            out[idx] = c[ok]
        if (out < 0).any() and k < 200 and len(self.TT) > k:  # large tets: widen the candidate set
            miss = out < 0
            out[miss] = self.locate(P[miss], k=min(8 * k, 200))
        return out

    def _bary(self, P: np.ndarray, t: np.ndarray) -> np.ndarray:
        l123 = np.einsum("nij,nj->ni", self.Dinv[t], P - self.TV[self.TT[t, 0]])
        return np.column_stack([1.0 - l123.sum(axis=1), l123])

    def value(self, P: np.ndarray, tets: np.ndarray | None = None) -> np.ndarray:
        """f at points (NaN outside the tet mesh)."""
        t = self.locate(P) if tets is None else tets
        out = np.full(len(P), np.nan)
        ok = t >= 0
        lam = self._bary(P[ok], t[ok])
        out[ok] = np.einsum("ni,ni->n", lam, self.f[self.TT[t[ok]]])
        return out

    # ------------------------------------------------------------------ integral lines
    def _walk(self, P: np.ndarray, tet: np.ndarray, max_hops: int = 50) -> np.ndarray:
        """Tet containing each point, walking from ``tet`` across the most violated face (-1: left M)."""
        tet = tet.copy()
        todo = np.flatnonzero(tet >= 0)
        for _ in range(max_hops):
            if len(todo) == 0:
                break
            lam = self._bary(P[todo], tet[todo])
            j = np.argmin(lam, axis=1)
            inside = lam[np.arange(len(todo)), j] >= -1e-10
            moving = todo[~inside]
            tet[moving] = self.adj[tet[moving], j[~inside]]
            todo = moving[tet[moving] >= 0]
        if len(todo):  # walk did not converge (cycling around an edge): locate from scratch
            tet[todo] = self.locate(P[todo])
        return tet

    def gradient_at(self, P: np.ndarray, tet: np.ndarray) -> np.ndarray:
        """Unit direction of the continuous (nodal, linearly interpolated) gradient of f."""
        lam = np.clip(self._bary(P, tet), 0.0, None)
        g = np.einsum("nj,njd->nd", lam, self._node_grad[self.TT[tet]])
        n = np.linalg.norm(g, axis=1)
        flat = n < 1e-300
        if flat.any():
            g[flat] = self.grad[tet[flat]]
            n[flat] = np.linalg.norm(g[flat], axis=1)
        return g / np.maximum(n, 1e-300)[:, None]

    def trace(self, P: np.ndarray, step: float | None = None, max_steps: int | None = None,
              return_paths: bool = False):
        """Follow the integral lines of ∇f from ``P`` to the surface (paper Sec. 3.1 / 3.3).

        The per-tet gradient of a linear f is piecewise constant, and its integral lines collapse onto
        edges and faces (the paper's remark on [45]); we integrate the continuous field obtained by
        averaging it at the nodes (volume weights) and interpolating linearly, with midpoint (RK2)
        steps of ``step`` and a tet walk for point location. A line ends where it leaves the tet
        mesh; that point is snapped onto M.

        Parameters
        ----------
        P : (n,3) float array
            Seeds inside the tet mesh (seeds outside it are returned unchanged with ``ok`` False).
        step : float, optional
            Step length (default: half the tet edge length).
        max_steps : int, optional
            Steps allowed per line (default: 4 bounding-box diagonals of travel).
        return_paths : bool
            Also return the polylines (list of (m_i,3) arrays).

        Returns
        -------
        end : (n,3) float array
            Where each line meets the surface M (snapped onto M).
        ok : (n,) bool
            False when the seed was outside the tet mesh or the line did not reach the boundary.
        paths : list, only with ``return_paths``
        """
        P = np.array(np.atleast_2d(P), dtype=float)
        n = len(P)
        h = float(step) if step is not None else 0.5 * self.edge_length
        diag = float(np.linalg.norm(np.ptp(self.TV, axis=0)))
        if max_steps is None:
            max_steps = int(4 * diag / h) + 10
        tet = self.locate(P)
        pos = P.copy()
        active = tet >= 0
        done = np.zeros(n, bool)
        paths = [[p.copy()] for p in P] if return_paths else None
        for _ in range(max_steps):
            ids = np.flatnonzero(active)
            if len(ids) == 0:
                break
            p0, t0 = pos[ids], tet[ids]
            g0 = self.gradient_at(p0, t0)
            pm = p0 + 0.5 * h * g0
            tm = self._walk(pm, t0)
            out = tm < 0
            g = g0.copy()
            if (~out).any():
                g[~out] = self.gradient_at(pm[~out], tm[~out])
            p1 = p0 + h * g
            t1 = np.where(out, -1, self._walk(p1, np.where(out, t0, tm)))
            left = t1 < 0
            pos[ids] = p1
            tet[ids] = t1
            if paths is not None:
                for i in ids:
                    paths[i].append(pos[i].copy())
            done[ids[left]] = True
            active[ids[left]] = False
        end = pos.copy()
        ok = done.copy()
        if ok.any():  # snap onto M
            _, _, C = igl.point_mesh_squared_distance(end[ok], self.V, self.F)
            end[ok] = C
        if return_paths:
            return end, ok, [np.array(p) for p in paths]
        return end, ok


def _delaunay_tets(V: np.ndarray, F: np.ndarray, skel_points: np.ndarray, h: float):
    """Tets of the surface's interior from a Delaunay tetrahedralisation (scipy / Qhull).

    Points: the surface vertices, a grid of spacing ``h`` inside M (kept ``h/2`` away from M) and the
    skeleton samples (last, so f = 0 is imposed exactly on S's samples). A Delaunay tet is kept when
    its centroid is inside M (winding number > 1/2); flat tets are dropped. The kept tets' boundary
    approximates M (integral lines are snapped onto M at the end).
    """
    from scipy.spatial import Delaunay

    lo, hi = V.min(0), V.max(0)
    axes = [np.arange(lo[i] + h / 2, hi[i], h) for i in range(3)]
    G = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    # a body-centred lattice (grid + cell centres) has no cospherical 8-point cells: fewer slivers
    G = np.vstack([G, G + 0.5 * h])
    w = igl.fast_winding_number(V, F, G)
    G = G[w > 0.5]
    if len(G):
        d2, _, _ = igl.point_mesh_squared_distance(G, V, F)
        G = G[d2 > (0.5 * h) ** 2]
    if len(skel_points):
        _, i = cKDTree(skel_points).query(G) if len(G) else (None, None)
        if len(G):
            dd = np.linalg.norm(G - skel_points[i], axis=1)
            G = G[dd > 0.35 * h]
    P = np.vstack([V, G, skel_points])
    T = Delaunay(P).simplices.astype(np.int64)
    C = P[T].mean(axis=1)
    keep = igl.fast_winding_number(V, F, C) > 0.5
    T = T[keep]
    X = P[T]
    vol = np.einsum("ij,ij->i", X[:, 1] - X[:, 0], np.cross(X[:, 2] - X[:, 0], X[:, 3] - X[:, 0])) / 6
    T = T[np.abs(vol) > 1e-9 * h**3]
    return P, T


def guiding_field(V: np.ndarray, F: np.ndarray, skel_points: np.ndarray, edge_length: float) -> GuidingField:
    """Build the :class:`GuidingField` of the surface ``(V, F)`` and skeleton samples ``skel_points``."""
    return GuidingField(V, F, skel_points, edge_length)
