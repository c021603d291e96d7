"""The guiding harmonic field of Casti et al. (2019), Sec. 3.1, and its integral lines.

A TetWild mesh (pytetwild, MPL-2.0; TetGen is AGPL and not used here) fills the surface M. The
paper embeds the skeleton S as chains of internal edges; TetWild cannot, so the condition f = 0 is
imposed on the tet nodes nearest to dense samples of S (the distance of those nodes to S is
recorded in :attr:`GuidingField.skeleton_offset` as the measure of that approximation). With f = 1
on the boundary nodes, f solves the cotangent-Laplace problem ``Δf = 0`` (libigl ``cotmatrix``).

f is linear in each tet, so ∇f is constant per tet and an integral line is a polyline that crosses
each tet in a straight segment: :meth:`GuidingField.trace` walks tet to tet (all lines at once, in
numpy) until a boundary face is reached, then snaps the end onto M (TetWild's boundary is within
its ``epsilon`` of M).
"""

from __future__ import annotations

import contextlib
import os
import tempfile
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


@contextlib.contextmanager
def _in_temp_dir():
    """fTetWild writes a tracking file into the working directory: keep it out of the user's."""
    old = os.getcwd()
    with tempfile.TemporaryDirectory(prefix="cagegen-tetwild-") as d:
        os.chdir(d)
        try:
            yield
        finally:
            os.chdir(old)


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

    def __init__(self, V: np.ndarray, F: np.ndarray, skel_points: np.ndarray, edge_length: float,
                 epsilon: float = 1e-3):
        self.V, self.F = V, F
        self.seconds = {}
        t0 = time.perf_counter()
        try:
            import pytetwild

            with _in_temp_dir():
                TV, TT = pytetwild.tetrahedralize(V, F.astype(np.int32), edge_length_abs=float(edge_length),
                                                  epsilon=float(epsilon), quiet=True)
        except Exception as exc:  # pytetwild raises RuntimeError on bad input
            raise CageError(f"skeleton cage, guiding field: TetWild failed: {exc}", layer=1) from exc
        TV = np.asarray(TV, dtype=np.float64)
        TT = np.asarray(TT, dtype=np.int64)
        used = np.unique(TT)
        remap = np.full(len(TV), -1)
        remap[used] = np.arange(len(used))
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
        self.skeleton_offset = {"max": float(dist.max()), "mean": float(dist.mean()), "n_nodes": int(len(zero))}
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
        ng = np.zeros((len(TV), 3))
        for j in range(4):
            np.add.at(ng, TT[:, j], self.grad)
        self._node_grad = ng
        self.centroids = P.mean(axis=1)
        self._ctree = cKDTree(self.centroids)
        self.seconds["solve"] = time.perf_counter() - t0
        self.n_tets = int(len(TT))
        self.n_nodes = int(len(TV))

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
    def trace(self, P: np.ndarray, max_steps: int = 5000, return_paths: bool = False):
        """Follow the integral lines of ∇f from ``P`` to the surface (paper Sec. 3.1 / 3.3).

        Parameters
        ----------
        P : (n,3) float array
            Seeds inside the tet mesh (seeds outside it are returned unchanged with ``ok`` False).
        max_steps : int
            Tet crossings allowed per line.
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
        tet = self.locate(P)
        pos = P.copy()
        active = tet >= 0
        done = np.zeros(n, bool)
        paths = [[p.copy()] for p in P] if return_paths else None
        for _ in range(max_steps):
            ids = np.flatnonzero(active)
            if len(ids) == 0:
                break
            t = tet[ids]
            g = self.grad[t]
            gn = np.linalg.norm(g, axis=1)
            flat = gn < 1e-12
            if flat.any():  # flat tet (all nodes fixed to one value): averaged nodal gradient
                g[flat] = self._node_grad[self.TT[t[flat]]].sum(axis=1)
                gn[flat] = np.linalg.norm(g[flat], axis=1)
            g = g / np.maximum(gn, 1e-300)[:, None]
            lam = np.clip(self._bary(pos[ids], t), 0.0, None)
            dl = np.einsum("nij,nj->ni", self.Dinv[t], g)
            dlam = np.column_stack([-dl.sum(axis=1), dl])
            with np.errstate(divide="ignore", invalid="ignore"):
                tex = np.where(dlam < -1e-14, lam / -dlam, np.inf)
            j = np.argmin(tex, axis=1)
            s = tex[np.arange(len(ids)), j]
            s = np.where(np.isfinite(s), s, 0.0)
            newpos = pos[ids] + s[:, None] * g
            # nudge past the face so the next tet's barycentrics are non-negative
            nxt = self.adj[t, j]
            pos[ids] = newpos
            if paths is not None:
                for i in ids:
                    paths[i].append(pos[i].copy())
            at_boundary = nxt < 0
            fin = ids[at_boundary]
            done[fin] = True
            active[fin] = False
            cont = ids[~at_boundary]
            tet[cont] = nxt[~at_boundary]
        end = pos
        ok = done.copy()
        if ok.any():  # snap onto M
            _, _, C = igl.point_mesh_squared_distance(end[ok], self.V, self.F)
            end = end.copy()
            end[ok] = C
        if return_paths:
            return end, ok, [np.array(p) for p in paths]
        return end, ok


def guiding_field(V: np.ndarray, F: np.ndarray, skel_points: np.ndarray, edge_length: float,
                  epsilon: float = 1e-3) -> GuidingField:
    """Build the :class:`GuidingField` of the surface ``(V, F)`` and skeleton samples ``skel_points``."""
    return GuidingField(V, F, skel_points, edge_length, epsilon)
