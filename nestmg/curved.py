"""Curved quadratic tets fitted to the input surface, with validity certified by Bernstein bounds.

A straight tet mesh ``(V, T)`` gets one node per edge (the P2 / ``tetra10`` nodes); the nodes of the
boundary edges are projected onto the true surface (a triangle mesh through libigl, or an analytic
projector), so every boundary facet becomes a quadratic patch and P2 finite elements on the mesh are
isoparametric (:mod:`solvers.fem_p2`). Where the projection would invert an element, the mid-nodes
around it are moved by the energy of *Mapping Polynomial Volumes* (Hencky distortion, eq. 2–3, plus the
point-to-plane boundary fit, eq. 9; :mod:`nestmg.curved_fit`).

**Certified validity.** ``det J`` of a quadratic tet is a cubic polynomial on the reference tet. Its 20
Bernstein–Bézier coefficients follow exactly from its values on the degree-3 lattice (a fixed 20x20
change of basis); all coefficients positive ⇒ ``det J > 0`` everywhere (convex hull property). Where
the bound is inconclusive the tet is split (red refinement of the reference tet) and the coefficients
of the pieces are checked, up to ``depth`` times; a negative ``det J`` at any lattice point proves the
tet invalid. The paper only checks quadrature points (its §4.1 names this as open).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from functools import lru_cache
from math import factorial
from typing import Callable

import numpy as np
import scipy.sparse as sp

from solvers.fem_p2 import P2_EDGES, p2_basis, p2_boundary_facets

from .errors import NestmgInputError

__all__ = [
    "CurvedMesh",
    "Projector",
    "certify_tets",
    "curve_mesh",
    "jacobian_bernstein",
    "linear_scaled_jacobians",
    "p2_nodes",
    "p2_prolongation",
    "scaled_jacobians",
    "sphere_projector",
    "surface_projector",
    "torus_projector",
]

#: A projector maps points (m,3) to their closest surface points (m,3) and unit normals there (m,3).
Projector = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]

VALID, UNCERTAIN, INVALID = 1, 0, -1


# ----------------------------------------------------------------------------- P2 nodes


def p2_nodes(V: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Straight P2 nodes of a tet mesh: the vertices, then the edge midpoints.

    Edges are numbered as in :func:`nestmg.refine.refine_tets` (sorted ``(a, b)`` pairs in increasing
    ``a * n + b``), so the P2 nodes are exactly the nodes of the red refinement of ``(V, T)``.

    Parameters
    ----------
    V : (n,3) float array
    T : (t,4) int array

    Returns
    -------
    X : (n + e, 3) float array
    T10 : (t, 10) int64 array
        ``tetra10`` connectivity (meshio / VTK order).
    E : (e, 2) int64 array
        Vertex pairs of the edge nodes ``n .. n + e - 1``.

    Examples
    --------
    >>> X, T10, E = p2_nodes(np.eye(4, 3), np.array([[0, 1, 2, 3]]))
    >>> X.shape, T10.tolist(), E.tolist()[:2]
    ((10, 3), [[0, 1, 2, 3, 4, 7, 5, 6, 8, 9]], [[0, 1], [0, 2]])
    """
    V = np.asarray(V, dtype=np.float64)
    T = np.asarray(T, dtype=np.int64)
    n = len(V)
    pairs = np.stack([np.sort(T[:, [a, b]], axis=1) for a, b in P2_EDGES], axis=1).reshape(-1, 2)
    uniq, inv = np.unique(pairs[:, 0] * n + pairs[:, 1], return_inverse=True)
    E = np.c_[uniq // n, uniq % n]
    X = np.vstack([V, 0.5 * (V[E[:, 0]] + V[E[:, 1]])])
    T10 = np.c_[T, n + inv.reshape(len(T), 6)]
    return X, T10, E


def p2_prolongation(n_vertices: int, E: np.ndarray) -> sp.csr_matrix:
    """Exact P1 → P2 interpolation on the same (curved) tets, ``(n + e, n)`` csr.

    Curved P1 functions lie in the isoparametric P2 space, so the p-multigrid level is exact on curved
    tets too: vertex values copied, an edge node gets the mean of its two vertices.
    """
    from .usermesh import p1_to_p2_prolongation

    return p1_to_p2_prolongation(n_vertices, E)


# ----------------------------------------------------------------------------- projectors


def sphere_projector(center=(0.0, 0.0, 0.0), radius: float = 1.0) -> Projector:
    """Closest points and outer normals on a sphere."""
    c = np.asarray(center, dtype=np.float64)

    def project(P):
        d = np.asarray(P, dtype=np.float64) - c
        n = d / np.linalg.norm(d, axis=1, keepdims=True)
        return c + radius * n, n

    return project


def torus_projector(R: float = 1.0, r: float = 0.35) -> Projector:
    """Closest points and outer normals on the torus of axis z, core radius ``R`` and tube radius ``r``."""

    def project(P):
        P = np.asarray(P, dtype=np.float64)
        rho = np.linalg.norm(P[:, :2], axis=1, keepdims=True)
        core = np.c_[R * P[:, :2] / rho, np.zeros(len(P))]
        n = (P - core) / np.linalg.norm(P - core, axis=1, keepdims=True)
        return core + r * n, n

    return project


def surface_projector(V: np.ndarray, F: np.ndarray, normals: str = "face",
                      crease: float = 60.0) -> Projector:
    """Closest points on a triangle mesh (libigl ``point_mesh_squared_distance``) and normals there.

    Parameters
    ----------
    V : (n,3) float array
    F : (f,3) int array
        A consistently oriented triangle mesh.
    normals : {"smooth", "face"}
        ``"face"``: the closest triangle's normal (piecewise constant: it jumps across every input edge).
        ``"smooth"``: the corner normals of the closest triangle (libigl ``per_corner_normals``: incident
        face normals averaged over the faces within ``crease`` degrees of the corner's face, so sharp
        features keep their jump) interpolated with the closest point's barycentric coordinates; where
        the result is more than ``crease`` degrees from the face normal (or vanishes), the face normal.
    crease : float
        Dihedral angle in degrees above which an input edge is a sharp feature.

    Examples
    --------
    >>> V = np.array([[0., 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    >>> F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    >>> C, n = surface_projector(V, F)(np.array([[0.2, 0.2, -1.0]]))
    >>> C.round(3).tolist(), n.round(3).tolist()   # the face z = 0: a 90° crease all around
    ([[0.2, 0.2, 0.0]], [[0.0, 0.0, -1.0]])
    """
    import igl

    if normals not in ("smooth", "face"):
        raise NestmgInputError(f"normals must be 'smooth' or 'face', got {normals!r}")
    V = np.ascontiguousarray(V, dtype=np.float64)
    F = np.ascontiguousarray(F, dtype=np.int64)
    N = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    N /= np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-300)
    CN = None
    if normals == "smooth":
        CN = np.asarray(igl.per_corner_normals(V, F, float(crease))).reshape(-1, 3, 3)
    cos_max = np.cos(np.radians(crease))

    def project(P):
        _, idx, C = igl.point_mesh_squared_distance(np.ascontiguousarray(P, dtype=np.float64), V, F)
        idx, C = np.asarray(idx).ravel(), np.asarray(C)
        if CN is None:
            return C, N[idx]
        a, b, c = (np.ascontiguousarray(V[F[idx, k]]) for k in range(3))
        bc = np.asarray(igl.barycentric_coordinates(C, a, b, c))
        n = np.einsum("ik,ikd->id", bc, CN[idx])
        length = np.linalg.norm(n, axis=1)
        ok = length > 1e-12
        n[ok] /= length[ok, None]
        off = ~ok | (np.einsum("ij,ij->i", n, N[idx]) < cos_max)  # orientation / crease guard
        n[off] = N[idx[off]]
        return C, n

    return project


# ----------------------------------------------------------------------------- Jacobian bounds


def _lattice(order: int) -> np.ndarray:
    """Barycentric multi-indices ``α`` with ``|α| = order`` (m, 4)."""
    return np.array([(order - i - j - k, i, j, k) for i in range(order + 1) for j in range(order + 1 - i)
                     for k in range(order + 1 - i - j)], dtype=np.int64)


@lru_cache(maxsize=None)
def _bernstein_change() -> tuple[np.ndarray, np.ndarray]:
    """Degree-3 lattice (20,4) and the matrix taking det J's lattice values to its Bernstein coefficients."""
    A = _lattice(3)
    lam = A / 3.0
    mult = np.array([factorial(3) / np.prod([factorial(a) for a in al]) for al in A])
    B = mult[None, :] * np.prod(lam[:, None, :] ** A[None, :, :], axis=2)  # B[p, α] = B_α(λ_p)
    return A, np.linalg.inv(B)


def _det_at(X: np.ndarray, T10: np.ndarray, tet: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """det J of tets ``tet`` (m,) at reference points ``xi``: shared (p,3) or per tet (m,p,3) -> (m,p)."""
    from solvers.fem_p2 import det3

    if xi.ndim == 2:  # the same points in every tet: one basis evaluation
        _, dN = p2_basis(xi)
        return det3(np.einsum("mad,pak->mpdk", X[T10[tet]], dN, optimize=True))
    m, p, _ = xi.shape
    _, dN = p2_basis(xi.reshape(-1, 3))
    return det3(np.einsum("mad,mpak->mpdk", X[T10[tet]], dN.reshape(m, p, 10, 3), optimize=True))


def _red_children() -> np.ndarray:
    """The 8 children of the reference tet (8, 4, 3) in ξ coordinates."""
    v = np.eye(4, 3, k=-1)  # (0,0,0), e1, e2, e3
    m = {(i, j): 0.5 * (v[i] + v[j]) for i in range(4) for j in range(i + 1, 4)}
    corners = [[v[0], m[0, 1], m[0, 2], m[0, 3]], [m[0, 1], v[1], m[1, 2], m[1, 3]],
               [m[0, 2], m[1, 2], v[2], m[2, 3]], [m[0, 3], m[1, 3], m[2, 3], v[3]]]
    ring = [m[0, 2], m[0, 3], m[1, 3], m[1, 2]]  # around the diagonal m01 - m23
    inner = [[m[0, 1], m[2, 3], ring[i], ring[(i + 1) % 4]] for i in range(4)]
    return np.array(corners + inner)


def jacobian_bernstein(X: np.ndarray, T10: np.ndarray, tets: np.ndarray | None = None,
                       corners: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Bernstein coefficients of the cubic ``det J`` of P2 tets (on sub-tets ``corners`` if given).

    Parameters
    ----------
    X : (N,3) float array
    T10 : (t,10) int array
    tets : (m,) int array, optional
        Which tets (default all).
    corners : (m,4,3) float array, optional
        A sub-tet of the reference tet per entry (default the reference tet itself).

    Returns
    -------
    coef : (m, 20) float array
        ``det J = Σ_α coef_α B_α(λ)`` on the (sub-)tet; ``min coef <= min det J``.
    values : (m, 20) float array
        ``det J`` at the degree-3 lattice points.
    """
    A, Binv = _bernstein_change()
    tets = np.arange(len(T10)) if tets is None else np.asarray(tets, dtype=np.int64)
    if corners is None:
        xi = (A / 3.0)[:, 1:]  # the reference tet's lattice, shared
    else:
        xi = np.einsum("pj,mjd->mpd", A / 3.0, corners)
    vals = _det_at(X, T10, tets, xi)
    return vals @ Binv.T, vals


def certify_tets(X: np.ndarray, T10: np.ndarray, tets: np.ndarray | None = None, *,
                 depth: int = 2) -> np.ndarray:
    """Certify ``det J > 0`` on whole P2 tets: 1 valid (proved), -1 invalid (proved), 0 undecided.

    All Bernstein coefficients positive proves validity; a lattice value ``<= 0`` proves invalidity;
    otherwise the tet's undecided pieces are split in 8 and checked again, ``depth`` times.

    Examples
    --------
    >>> X, T10, _ = p2_nodes(np.eye(4, 3, k=-1), np.array([[0, 1, 2, 3]]))
    >>> certify_tets(X, T10).tolist()
    [1]
    >>> X[T10[0, 4]] = [0.5, 0.6, 0.6]   # node of edge v0-v1 pushed through the face v1 v2 v3
    >>> certify_tets(X, T10).tolist()
    [-1]
    """
    tets = np.arange(len(T10)) if tets is None else np.asarray(tets, dtype=np.int64)
    status = np.full(len(tets), VALID, dtype=np.int8)
    owner = np.arange(len(tets))
    corners = None  # the whole reference tet
    for level in range(depth + 1):
        if owner.size == 0:
            break
        coef, vals = jacobian_bernstein(X, T10, tets[owner], corners)
        bad = (vals <= 0).any(axis=1)
        status[owner[bad]] = INVALID
        open_ = ~bad & ~(coef > 0).all(axis=1) & (status[owner] != INVALID)
        status[owner[open_]] = UNCERTAIN  # until every piece is proved
        if level == depth or not open_.any():
            break
        # split the undecided pieces; a tet is valid again only if all its pieces are proved
        o = owner[open_]
        c = np.broadcast_to(np.eye(4, 3, k=-1), (len(o), 4, 3)) if corners is None else corners[open_]
        status[o] = VALID
        owner = np.repeat(o, 8)
        corners = np.einsum("kij,mjd->mkid", _child_barycentric(), c).reshape(-1, 4, 3)
    return status


@lru_cache(maxsize=None)
def _child_barycentric() -> np.ndarray:
    """Barycentric coordinates (8, 4, 4) of the 8 children's corners w.r.t. their parent's corners."""
    kids = _red_children()
    return np.concatenate([1.0 - kids.sum(axis=2, keepdims=True), kids], axis=2)


def scaled_jacobians(X: np.ndarray, T10: np.ndarray, order: int = 6, *, bound: bool = False) -> np.ndarray:
    """Scaled Jacobian of P2 tets: ``min det J / max det J`` over each tet (1 for a straight tet).

    The usual distortion measure of curved elements (<= 0 for an invalid tet). It is invariant to the
    straight tet's shape: it measures what curving costs, not how well shaped the straight tet is
    (:func:`linear_scaled_jacobians`).

    Parameters
    ----------
    X : (N,3) float array
    T10 : (t,10) int array
    order : int
        ``det J`` is sampled on the degree-``order`` lattice of each tet (an upper estimate of the
        true ratio).
    bound : bool
        Return instead the certified lower bound ``max(min c, 0) / max c`` of the Bernstein
        coefficients ``c`` of ``det J`` (:func:`jacobian_bernstein`; they bound ``det J`` on both sides).

    Returns
    -------
    (t,) float array
    """
    lam = _lattice(order) / float(order)
    xi = lam[:, 1:]
    out = np.empty(len(T10))
    for s in range(0, len(T10), 20000):
        idx = np.arange(s, min(len(T10), s + 20000))
        if bound:
            c = jacobian_bernstein(X, T10, idx)[0]
            out[idx] = np.maximum(c.min(axis=1), 0.0) / c.max(axis=1)
            continue
        d = _det_at(X, T10, idx, xi)
        out[idx] = d.min(axis=1) / d.max(axis=1)
    return out


def linear_scaled_jacobians(V: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Scaled Jacobian of straight tets (Knupp): the smallest over the 4 corners of ``det(e1, e2, e3) /
    (|e1| |e2| |e3|)``, ``e`` the corner's edges, times √2 (1 for the regular tet, 0 for a flat one).

    Examples
    --------
    >>> V = np.array([[1., 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]])   # regular
    >>> linear_scaled_jacobians(V, np.array([[0, 1, 2, 3]])).round(6).tolist()
    [1.0]
    """
    P = np.asarray(V, dtype=np.float64)[np.asarray(T)]
    from solvers.fem_p2 import det3

    q = np.empty((len(P), 4))
    for c, (a, b, d) in enumerate(((1, 2, 3), (0, 3, 2), (0, 1, 3), (0, 2, 1))):  # same orientation
        e = P[:, [a, b, d]] - P[:, [c]]
        q[:, c] = det3(np.swapaxes(e, 1, 2)) / np.prod(np.linalg.norm(e, axis=2), axis=1)
    q *= np.sign(q.sum(axis=1, keepdims=True))  # either orientation of T
    return np.sqrt(2.0) * q.min(axis=1)


def surface_distance(X: np.ndarray, F6: np.ndarray, project: Projector, order: int = 4) -> np.ndarray:
    """Largest distance to the surface of each curved 6-node facet (sampled: degree-``order`` lattice)."""
    from solvers.fem_p2 import _p2_tri_basis

    st = np.array([(i / order, j / order) for i in range(order + 1) for j in range(order + 1 - i)])
    N, _ = _p2_tri_basis(st)
    P = np.einsum("qa,fad->fqd", N, np.asarray(X)[np.asarray(F6)]).reshape(-1, 3)
    d = np.linalg.norm(project(P)[0] - P, axis=1)
    return d.reshape(len(F6), len(st)).max(axis=1)


# ----------------------------------------------------------------------------- curving


@dataclass
class CurvedMesh:
    """A tet mesh of quadratic (``tetra10``) elements, straight inside, fitted to the surface at the boundary.

    Attributes
    ----------
    X : (n + e, 3) float array
        Nodes: the ``n`` vertices first (boundary ones projected onto the surface when asked), then one
        per edge (:func:`p2_nodes` numbering: the nodes of the red refinement of ``T``).
    T : (t, 4) int64 array
        The straight tets (positively oriented).
    T10 : (t, 10) int64 array
        ``tetra10`` connectivity (meshio / VTK order).
    E : (e, 2) int64 array
        Vertex pairs of the edge nodes.
    report : dict
        Counts (curved, invalid after projection, fitted, straightened), certification, scaled
        Jacobians, fit distances, seconds per stage.
    """

    X: np.ndarray
    T: np.ndarray
    T10: np.ndarray
    E: np.ndarray
    report: dict = field(default_factory=dict)

    @property
    def n_vertices(self) -> int:
        """Number of tet vertices (the P1 nodes)."""
        return len(self.X) - len(self.E)

    @property
    def V(self) -> np.ndarray:
        """Vertex positions (n,3) of the straight P1 mesh under the curved one."""
        return self.X[: self.n_vertices]

    def straight(self) -> CurvedMesh:
        """The same mesh with every edge node at its edge's midpoint (straight P2)."""
        X = np.vstack([self.V, 0.5 * (self.X[self.E[:, 0]] + self.X[self.E[:, 1]])])
        return CurvedMesh(X, self.T, self.T10, self.E, {"straight": True})

    def boundary_facets(self) -> np.ndarray:
        """Outward 6-node boundary facets (f,6) (:func:`solvers.fem_p2.p2_boundary_facets`)."""
        return p2_boundary_facets(self.T10)[0]

    def prolongation(self) -> sp.csr_matrix:
        """The exact P1 → P2 interpolation on this mesh (:func:`p2_prolongation`)."""
        return p2_prolongation(self.n_vertices, self.E)


def _project_vertices(V, T, bv, project, max_rounds: int = 20):
    """Boundary vertices onto the surface, except those whose move would invert a straight tet."""
    from .tetmesh import tet_volumes

    Vp = V.copy()
    Vp[bv] = project(V[bv])[0]
    kept = np.zeros(len(V), dtype=bool)
    for _ in range(max_rounds):
        neg = tet_volumes(Vp, T) <= 0
        if not neg.any():
            break
        undo = np.intersect1d(T[neg].ravel(), bv)
        Vp[undo] = V[undo]
        kept[undo] = True
    return Vp, int(kept.sum())


def _tets_with_nodes(T10: np.ndarray, nodes: np.ndarray, N: int) -> np.ndarray:
    mark = np.zeros(N, dtype=bool)
    mark[nodes] = True
    return np.flatnonzero(mark[T10].any(axis=1))


def _fit_patch(X, Xs, T, T10, bad, project, *, lam, reference, rounds, depth) -> tuple[np.ndarray, dict]:
    """Move the edge nodes around the ``bad`` tets by the paper's energy, from a valid (straight) start."""
    from .curved_fit import fit_mid_nodes, reference_inverse

    N = len(X)
    vmark = np.zeros(N, dtype=bool)
    vmark[T[bad].ravel()] = True
    patch = np.flatnonzero(vmark[T].any(axis=1))  # the bad tets and their vertex neighbours
    for _ in range(10):  # straighten the patch's edge nodes; grow it until every touched tet is certified
        free = np.unique(T10[patch, 4:])
        X1 = X.copy()
        X1[free] = Xs[free]
        etets = _tets_with_nodes(T10, free, N)
        ok = certify_tets(X1, T10, etets, depth=depth) == VALID
        if ok.all():
            break
        patch = np.union1d(patch, etets[~ok])
    Ainv = reference_inverse(X1, T[etets], reference)
    bmark = np.zeros(N, dtype=bool)
    bmark[p2_boundary_facets(T10)[0][:, 3:].ravel()] = True
    h = _edge_length_of_nodes(Xs, T10, free)
    Xf, info = fit_mid_nodes(X1, T10[etets], Ainv, free, bmark[free], h, project, lam=lam, rounds=rounds)
    info.update(patch_tets=int(len(patch)), free_nodes=int(len(free)), energy_tets=int(len(etets)))
    return Xf, info


def _edge_length_of_nodes(Xs: np.ndarray, T10: np.ndarray, nodes: np.ndarray) -> np.ndarray:
    """Length of the edge of each edge node in ``nodes`` (from the straight tets' corners)."""
    from solvers.fem_p2 import P2_EDGES

    length = np.zeros(len(Xs))
    for k, (a, b) in enumerate(P2_EDGES):
        length[T10[:, 4 + k]] = np.linalg.norm(Xs[T10[:, a]] - Xs[T10[:, b]], axis=1)
    return length[nodes]


def _straighten(X, Xs, T10, bad, depth) -> tuple[np.ndarray, int]:
    """Put the edge nodes of uncertified tets back on their edges until every tet is certified."""
    N = len(X)
    straight = np.zeros(len(T10), dtype=bool)
    todo = np.asarray(bad, dtype=np.int64)
    while todo.size:
        straight[todo] = True
        nodes = np.unique(T10[todo, 4:])
        X[nodes] = Xs[nodes]
        touched = _tets_with_nodes(T10, nodes, N)
        touched = touched[~straight[touched]]
        todo = touched[certify_tets(X, T10, touched, depth=depth) != VALID]
    return X, int(straight.sum())


def _moved_tets(X: np.ndarray, Xs: np.ndarray, T10: np.ndarray) -> np.ndarray:
    """Tets with an edge node off its straight position (the curved tets)."""
    return _tets_with_nodes(T10, np.flatnonzero(np.any(X != Xs, axis=1)), len(X))


def _sj_summary(X: np.ndarray, T10: np.ndarray, tets: np.ndarray, threshold: float) -> dict:
    """Min / mean scaled Jacobian of ``tets`` (sampled; certified lower bound), count below ``threshold``."""
    sj = scaled_jacobians(X, T10[tets]) if len(tets) else np.ones(1)  # no curved tet: all straight, 1
    lb = scaled_jacobians(X, T10[tets], bound=True) if len(tets) else np.ones(1)
    return {"tets": int(len(tets)), "min": float(sj.min()), "mean": float(sj.mean()),
            "below_threshold": int((sj < threshold).sum()), "bound_min": float(lb.min()),
            "bound_mean": float(lb.mean())}


def _quality_pass(X, Xs, T, T10, bmark, project, *, threshold: float, lam: float, rounds: int,
                  passes: int, depth: int) -> tuple[np.ndarray, dict]:
    """Raise the scaled Jacobian of the tets below ``threshold`` by the paper's energy (quality pass).

    A pass frees the edge nodes of the curved tets whose scaled Jacobian is below ``threshold`` (from
    the second pass on, those of their vertex neighbours too: more room for the few tets left) and
    minimises the paper's ``E_S + λ E_Ω`` over them (:func:`nestmg.curved_fit.fit_mid_nodes`: boundary
    nodes held near their tangent planes, every iterate certified; here ``E_Ω`` weights every tet
    alike, so small bad tets count as much as large ones). A pass is kept only if all its tets are
    certified, its worst scaled Jacobian did not go down and its mean went up.
    """
    from .curved_fit import fit_mid_nodes, reference_inverse

    t0 = time.perf_counter()
    info: dict = {"threshold": threshold, "lam": lam, "passes": [], "iterations": 0}
    for k in range(passes):
        n_low, low = _low_tets(X, Xs, T, T10, threshold, neighbours=k > 0)
        if low.size == 0:
            break
        free = np.unique(T10[low, 4:])
        etets = _tets_with_nodes(T10, free, len(X))
        Ainv = reference_inverse(Xs, T[etets], "straight")
        h = _edge_length_of_nodes(Xs, T10, free)
        X1, fit = fit_mid_nodes(X, T10[etets], Ainv, free, bmark[free], h, project, lam=lam, rounds=rounds,
                                weighting="element")
        old, new = scaled_jacobians(X, T10[etets]), scaled_jacobians(X1, T10[etets])
        kept = bool(new.min() >= old.min() and new.mean() > old.mean()
                    and (certify_tets(X1, T10, etets, depth=depth) == VALID).all())
        info["passes"].append({"below": n_low, "free_nodes": int(len(free)),
                               "energy_tets": int(len(etets)), "iterations": fit["iterations"],
                               "min_before": float(old.min()),
                               "min_after": float(new.min()), "mean_before": float(old.mean()),
                               "mean_after": float(new.mean()), "kept": kept})
        info["iterations"] += fit["iterations"]
        if not kept:
            break
        X = X1
    info["seconds"] = time.perf_counter() - t0
    return X, info


def _relax_pass(X, Xs, T, T10, bmark, *, threshold: float, beta: float, passes: int = 2,
                depth: int) -> tuple[np.ndarray, dict]:
    """Even out ``det J`` of the curved tets below ``threshold`` by moving interior edge nodes only.

    Pass 0 frees the interior edge nodes of the curved tets whose scaled Jacobian is below
    ``threshold``; pass 1 those of the tets still below and of their vertex neighbours (more room,
    fewer tets). Each minimises :func:`nestmg.curved_fit.jacobian_spread_energy` over the tets around
    the free nodes (:func:`nestmg.curved_fit.relax_interior`). Boundary nodes never move: the facets
    stay where the projection put them. A pass is kept if its tets are certified and its worst scaled
    Jacobian did not go down.
    """
    from .curved_fit import reference_inverse, relax_interior

    t0 = time.perf_counter()
    info: dict = {"threshold": threshold, "beta": beta, "passes": [], "iterations": 0}
    for k in range(passes):
        n_low, low = _low_tets(X, Xs, T, T10, threshold, neighbours=k > 0)
        if low.size == 0:
            break
        free = np.unique(T10[low, 4:])
        free = free[~bmark[free]]
        if free.size == 0:
            break
        etets = _tets_with_nodes(T10, free, len(X))
        X1, fit = relax_interior(X, T10[etets], reference_inverse(Xs, T[etets], "straight"), free,
                                 _edge_length_of_nodes(Xs, T10, free), beta=beta)
        old, new = scaled_jacobians(X, T10[etets]), scaled_jacobians(X1, T10[etets])
        kept = bool(new.min() >= old.min() and (certify_tets(X1, T10, etets, depth=depth) == VALID).all())
        info["passes"].append({"below": n_low, "free_nodes": int(len(free)),
                               "energy_tets": int(len(etets)), "iterations": fit["iterations"],
                               "min_before": float(old.min()), "min_after": float(new.min()),
                               "mean_before": float(old.mean()), "mean_after": float(new.mean()),
                               "kept": kept})
        info["iterations"] += fit["iterations"]
        if kept:
            X = X1
    info["seconds"] = time.perf_counter() - t0
    return X, info


def _low_tets(X, Xs, T, T10, threshold: float, *, neighbours: bool) -> tuple[int, np.ndarray]:
    """How many curved tets have a scaled Jacobian below ``threshold``, and those tets (with
    ``neighbours``, every tet sharing a vertex with one of them)."""
    curved = _moved_tets(X, Xs, T10)
    low = curved[scaled_jacobians(X, T10[curved]) < threshold]
    if neighbours and low.size:
        return int(low.size), _tets_with_nodes(T10, np.unique(T[low]), len(X))
    return int(low.size), low


def _sj_floor(X, Xs, T10, floor: float, bmark: np.ndarray, *, factor: float = 0.75,
              steps: int = 8) -> tuple[np.ndarray, dict]:
    """Partial curving: back off edge nodes until every tet's certified scaled Jacobian is >= ``floor``.

    Each edge node sits at ``Xs + t (X - Xs)``, ``t = 1`` at first. While a tet's certified lower bound
    (:func:`scaled_jacobians` with ``bound=True``) is below ``floor``, the ``t`` of its curved edge nodes
    is multiplied by ``factor`` (``steps`` times, then 0: straight) and the tets around those nodes are
    re-checked. A straight tet has a scaled Jacobian of 1, so the loop ends; ``floor > 0`` also certifies
    every tet (all Bernstein coefficients of ``det J`` positive). Interior edge nodes moved by the
    relaxation are scaled alike (``bmark``: the boundary nodes, counted apart). ``factor`` 0.75 left the
    facets about half as far from the surface as 0.5 at floor 0.8 on the procedural ball and torus (a
    trial run).
    """
    t0 = time.perf_counter()
    X = X.copy()
    D = X - Xs
    t = np.where(np.any(D != 0, axis=1), 1.0, 0.0)
    check, rounds = _moved_tets(X, Xs, T10), 0
    before = scaled_jacobians(X, T10[check], bound=True) if check.size else np.ones(0)
    while check.size:
        low = check[scaled_jacobians(X, T10[check], bound=True) < floor]
        nodes = np.unique(T10[low, 4:])
        nodes = nodes[t[nodes] > 0]
        if nodes.size == 0:  # only straight tets left below: rounding of a bound ~1 (floor < 1)
            break
        t[nodes] = np.where(t[nodes] > factor ** (steps - 1), factor * t[nodes], 0.0)
        X[nodes] = Xs[nodes] + t[nodes, None] * D[nodes]
        check, rounds = _tets_with_nodes(T10, nodes, len(X)), rounds + 1
    curved = np.flatnonzero(np.any(D != 0, axis=1))
    info = {"floor": floor, "rounds": rounds, "tets_below_before": int((before < floor).sum()),
            "curved_edge_nodes": int(len(curved)), "backed_off": int((t[curved] < 1).sum()),
            "straightened": int((t[curved] == 0).sum()), "boundary_edge_nodes": int(bmark[curved].sum()),
            "boundary_backed_off": int((t[curved][bmark[curved]] < 1).sum()),
            "seconds": time.perf_counter() - t0}
    return X, info


def curve_mesh(V: np.ndarray, T: np.ndarray, project: Projector, *, vertices: bool = True, fit: bool = True,
               lam: float = 0.05, reference: str = "straight", rounds: int = 4, depth: int = 2,
               relax: float | None = None, relax_beta: float = 0.1, quality: float | None = None,
               quality_lam: float = 1.0, quality_passes: int = 2,
               sj_floor: float | None = None) -> CurvedMesh:
    """Curve a tet mesh's boundary onto a surface at order 2, with every element certified valid.

    1. P2 nodes (:func:`p2_nodes`); the boundary vertices (``vertices=True``; a vertex whose move would
       invert a straight tet stays) and the boundary edge nodes are projected onto the surface.
    2. Every tet is certified (:func:`certify_tets`). Where the projection leaves tets not certified and
       ``fit`` is on, the edge nodes of those tets and of their vertex neighbours are restarted straight
       and moved by the paper's energy ``E_S + λ E_Ω`` (:func:`nestmg.curved_fit.fit_mid_nodes`).
    3. Tets still not certified get their edge nodes straightened (counted in ``report["straightened"]``).
    4. Interior relaxation (``relax`` not None): the interior edge nodes of the curved tets whose
       scaled Jacobian is below ``relax`` (then also of their vertex neighbours) minimise the spread of
       ``det J`` over each tet plus ``relax_beta`` times the deviatoric Hencky distortion
       (:func:`nestmg.curved_fit.jacobian_spread_energy`); boundary nodes stay on the surface
       (``report["relax"]``).
    5. Quality pass (``quality`` not None): the edge nodes of the curved tets whose scaled Jacobian
       (:func:`scaled_jacobians`) is below ``quality`` are moved by ``E_S + quality_lam E_Ω`` (the fit
       and the Hencky energy, every tet weighted alike), every iterate certified, up to
       ``quality_passes`` times (``report["quality"]``).
    6. Scaled-Jacobian floor (``sj_floor`` not None): partial curving; the curving displacement of the
       edge nodes of every tet whose certified scaled Jacobian is below ``sj_floor`` is scaled by 0.75, up
       to 8 times, then removed, until every tet meets the floor (``report["sj_floor"]``).

    Parameters
    ----------
    V : (n,3) float array
    T : (t,4) int array
    project : callable
        ``points (m,3) -> (closest points (m,3), unit normals (m,3))``: :func:`surface_projector` for a
        triangle mesh, :func:`sphere_projector` / :func:`torus_projector` for analytic shapes.
    vertices : bool
        Also project the boundary vertices (TetWild's lie only within its envelope of the surface).
    fit : bool
        Run the energy where the projection is not certified (else straighten at once).
    lam : float
        λ of the volume energy in step 2 (paper eq. 1; 0.05 is its close-fitting value).
    reference : {"straight", "regular"}
        The ideal element of the Hencky energy in step 2 (:func:`nestmg.curved_fit.reference_inverse`).
    rounds : int
        L-BFGS rounds (point-to-plane targets refreshed between them).
    depth : int
        Subdivision depth of the Bernstein certification.
    relax : float or None
        Scaled-Jacobian threshold of the interior relaxation (None: none).
    relax_beta : float
        Weight of the deviatoric (shape) Hencky distortion in the relaxation.
    quality : float or None
        Scaled-Jacobian threshold of the quality pass (None: no pass).
    quality_lam : float
        λ of the quality pass: larger trades surface fit for element quality (10 un-curves a coarse
        ball; 1 keeps the facet distance within ~1.5x).
    quality_passes : int
        Quality passes at most (each on the tets still below the threshold).
    sj_floor : float or None
        Lowest certified scaled Jacobian (``max(min c, 0) / max c`` of the Bernstein coefficients of
        ``det J``) allowed on any tet, in (0, 1); None: no floor.

    Returns
    -------
    CurvedMesh
        ``report``: counts, ``scaled_jacobian`` (final, over the curved tets; ``before_quality``: after
        step 3), ``relax`` (step 4: per pass the tets below, free nodes, iterations, min / mean before
        and after, kept), ``sj_floor`` (step 6: rounds, tets below the floor before, curved edge nodes,
        how many were backed off and straightened, and of the boundary ones), ``linear_scaled_jacobian``
        (the straight tets', :func:`linear_scaled_jacobians`), ``surface_distance``, ``seconds``.
    """
    from .tetmesh import tet_volumes

    V = np.asarray(V, dtype=np.float64)
    T = np.asarray(T, dtype=np.int64)
    if V.ndim != 2 or V.shape[1] != 3 or T.ndim != 2 or T.shape[1] != 4 or len(T) == 0:
        raise NestmgInputError(f"curve_mesh needs V (n,3) and T (t,4) with t > 0, got {V.shape} and "
                               f"{T.shape}")
    if np.any(np.abs(tet_volumes(V, T)) <= 0):
        raise NestmgInputError("curve_mesh needs a tet mesh without degenerate (zero-volume) tets")
    for key, val in (("relax", relax), ("quality", quality), ("sj_floor", sj_floor)):
        if val is not None and not 0.0 < val < 1.0:
            raise NestmgInputError(f"{key} must be a scaled Jacobian in (0, 1) or None, got {val}")
    X, Xs, T, T10, E, rep = _project_and_repair(V, T, project, vertices=vertices, fit=fit, lam=lam,
                                                reference=reference, rounds=rounds, depth=depth)
    bmark = np.zeros(len(X), dtype=bool)
    bmark[p2_boundary_facets(T10)[0][:, 3:].ravel()] = True
    thr = 0.9 if quality is None else quality
    rep["scaled_jacobian"] = {"before_quality": _sj_summary(X, T10, _moved_tets(X, Xs, T10), thr)}
    if relax is not None:
        X, rep["relax"] = _relax_pass(X, Xs, T, T10, bmark, threshold=relax, beta=relax_beta, depth=depth)
        rep["seconds"]["relax"] = rep["relax"]["seconds"]
    if quality is not None:
        X, rep["quality"] = _quality_pass(X, Xs, T, T10, bmark, project, threshold=quality, lam=quality_lam,
                                          rounds=rounds, passes=quality_passes, depth=depth)
        rep["seconds"]["quality"] = rep["quality"]["seconds"]
    if sj_floor is not None:
        X, rep["sj_floor"] = _sj_floor(X, Xs, T10, sj_floor, bmark)
        rep["seconds"]["sj_floor"] = rep["sj_floor"]["seconds"]
    _measure(X, Xs, T, T10, project, thr, rep, depth)
    return CurvedMesh(X, T, T10, E, rep)


def _project_and_repair(V, T, project, *, vertices, fit, lam, reference, rounds, depth):
    """Steps 1–3 of :func:`curve_mesh`: project, certify, fit uncertified patches, straighten the rest."""
    from .tetmesh import orient_tets

    sec: dict[str, float] = {}
    t0 = time.perf_counter()
    T = orient_tets(V, T)
    _, T10, E = p2_nodes(V, T)
    F6 = p2_boundary_facets(T10)[0]
    bv, bm = np.unique(F6[:, :3]), np.unique(F6[:, 3:])
    Vp, n_kept = _project_vertices(V, T, bv, project) if vertices else (V, 0)
    Xs, _, _ = p2_nodes(Vp, T)  # straight nodes of the (projected) vertices
    X = Xs.copy()
    X[bm] = project(Xs[bm])[0]
    sec["project"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    curved = _tets_with_nodes(T10, bm, len(X))
    status = certify_tets(X, T10, curved, depth=depth)
    bad = curved[status != VALID]
    sec["certify"] = time.perf_counter() - t0
    rep: dict = {"tets": int(len(T)), "boundary_edge_nodes": int(len(bm)), "curved_tets": int(len(curved)),
                 "vertices_not_projected": n_kept, "invalid_after_projection": int((status == INVALID).sum()),
                 "undecided_after_projection": int((status == UNCERTAIN).sum()), "fit": None}
    t0 = time.perf_counter()
    if bad.size and fit:
        X, rep["fit"] = _fit_patch(X, Xs, T, T10, bad, project, lam=lam, reference=reference, rounds=rounds,
                                   depth=depth)
        recheck = _tets_with_nodes(T10, np.unique(T10[bad, 4:]), len(X))
        recheck = _tets_with_nodes(T10, np.unique(T10[recheck, 4:]), len(X))
        bad = recheck[certify_tets(X, T10, recheck, depth=depth) != VALID]
    sec["fit"] = time.perf_counter() - t0
    X, rep["straightened"] = _straighten(X, Xs, T10, bad, depth)
    rep["seconds"] = sec
    return X, Xs, T, T10, E, rep


def _measure(X, Xs, T, T10, project, threshold, rep, depth) -> None:
    """Certification, scaled Jacobians (curved and straight) and surface distances into ``rep``."""
    t0 = time.perf_counter()
    curved = _moved_tets(X, Xs, T10)
    rep["curved_tets"] = int(len(curved))
    rep["certified"] = bool((certify_tets(X, T10, curved, depth=depth) == VALID).all())
    sj = rep["scaled_jacobian"]
    sj.update(_sj_summary(X, T10, curved, threshold), threshold=threshold)
    sj["mean_curved"] = sj["mean"]  # straight tets have a scaled Jacobian of exactly 1
    sj["mean_all"] = (sj["mean"] * len(curved) + len(T) - len(curved)) / len(T)
    lin = linear_scaled_jacobians(X, T)
    rep["linear_scaled_jacobian"] = {"min": float(lin.min()), "mean": float(lin.mean()),
                                     "min_curved": float(lin[curved].min()) if len(curved) else None,
                                     "mean_curved": float(lin[curved].mean()) if len(curved) else None}
    F6 = p2_boundary_facets(T10)[0]
    dc, ds = surface_distance(X, F6, project), surface_distance(Xs, F6, project)
    rep["surface_distance"] = {"curved_max": float(dc.max()), "straight_max": float(ds.max()),
                               "curved_mean": float(dc.mean()), "straight_mean": float(ds.mean())}
    rep["seconds"]["measure"] = time.perf_counter() - t0
