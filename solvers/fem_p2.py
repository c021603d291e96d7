"""Quadratic (P2) finite elements on straight or curved (isoparametric) tets, vectorised numpy.

Conventions
-----------
* ``X : (N, 3) float64`` P2 node positions: the tet vertices first, then one node per edge (straight
  at the edge midpoint, or moved onto a curved boundary).
* ``T10 : (t, 10) int64`` element nodes in VTK / meshio ``tetra10`` order: vertices ``v0..v3``, then the
  edge nodes ``m01, m12, m02, m03, m13, m23``.
* The element map is isoparametric: ``x(ξ) = Σ_a X_a N_a(ξ)`` with the P2 Lagrange basis ``N_a`` on the
  reference tet ``{ξ >= 0, ξ1 + ξ2 + ξ3 <= 1}``; a curved element is valid where ``det J(ξ) > 0``.
* ``F6 : (f, 6) int64`` boundary facets as 6-node triangles ``v0, v1, v2, m01, m12, m02`` (outward).

Integrals use collapsed Gauss–Jacobi (Stroud conical product) rules computed here, positive weights,
exact to any requested polynomial degree on the reference simplex. Chunked over elements so that the
local matrices of a chunk stay below ~50 MB.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Callable

import numpy as np
import scipy.sparse as sp
from scipy.special import roots_jacobi

from .errors import SolverInputError

__all__ = [
    "P2_EDGES",
    "p2_basis",
    "p2_boundary_facets",
    "p2_jacobians",
    "p2_l2_error",
    "p2_load",
    "p2_mass_matrix",
    "p2_neumann_load",
    "p2_stiffness_matrix",
    "tet_quadrature",
    "triangle_quadrature",
]

#: Vertex pairs of the tetra10 edge nodes 4..9 (meshio / VTK order).
P2_EDGES = ((0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3))
_CHUNK = 20000


def _gauss_jacobi01(n: int, alpha: float) -> tuple[np.ndarray, np.ndarray]:
    """n-point Gauss rule on [0, 1] for the weight ``(1 - t)^alpha``."""
    x, w = roots_jacobi(n, alpha, 0.0)
    return 0.5 * (1.0 + x), w / 2.0 ** (alpha + 1.0)


@lru_cache(maxsize=None)
def tet_quadrature(degree: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Quadrature on the reference tet exact for polynomials of ``degree`` (collapsed Gauss–Jacobi).

    Returns
    -------
    points : (q, 3) float array
        Reference coordinates ``ξ``.
    weights : (q,) float array
        Positive, summing to the reference volume 1/6.

    Examples
    --------
    >>> p, w = tet_quadrature(2)
    >>> round(float(w.sum()), 15), round(float(w @ p[:, 0] ** 2), 15)  # ∫1, ∫x² on the tet
    (0.166666666666667, 0.016666666666667)
    """
    n = max(1, int(np.ceil((degree + 1) / 2)))
    a, wa = _gauss_jacobi01(n, 2.0)
    b, wb = _gauss_jacobi01(n, 1.0)
    c, wc = _gauss_jacobi01(n, 0.0)
    A, B, C = np.meshgrid(a, b, c, indexing="ij")
    W = (wa[:, None, None] * wb[None, :, None] * wc[None, None, :]).ravel()
    A, B, C = A.ravel(), B.ravel(), C.ravel()
    pts = np.c_[A, B * (1 - A), C * (1 - A) * (1 - B)]
    pts.setflags(write=False)
    W.setflags(write=False)
    return pts, W


@lru_cache(maxsize=None)
def triangle_quadrature(degree: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Quadrature on the reference triangle ``{s, t >= 0, s + t <= 1}``; weights sum to 1/2."""
    n = max(1, int(np.ceil((degree + 1) / 2)))
    a, wa = _gauss_jacobi01(n, 1.0)
    b, wb = _gauss_jacobi01(n, 0.0)
    A, B = np.meshgrid(a, b, indexing="ij")
    W = (wa[:, None] * wb[None, :]).ravel()
    pts = np.c_[A.ravel(), B.ravel() * (1 - A.ravel())]
    pts.setflags(write=False)
    W.setflags(write=False)
    return pts, W


def p2_basis(xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """P2 Lagrange basis of the reference tet (tetra10 order) at reference points.

    Parameters
    ----------
    xi : (q, 3) float array

    Returns
    -------
    N : (q, 10) float array
        Values.
    dN : (q, 10, 3) float array
        Gradients with respect to ``ξ``.
    """
    xi = np.atleast_2d(np.asarray(xi, dtype=np.float64))
    lam = np.c_[1.0 - xi.sum(axis=1), xi]  # barycentric (q, 4)
    dlam = np.array([[-1.0, -1.0, -1.0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])  # (4, 3)
    q = len(xi)
    N = np.empty((q, 10))
    dN = np.empty((q, 10, 3))
    for i in range(4):
        N[:, i] = lam[:, i] * (2 * lam[:, i] - 1)
        dN[:, i] = (4 * lam[:, i] - 1)[:, None] * dlam[i]
    for k, (i, j) in enumerate(P2_EDGES):
        N[:, 4 + k] = 4 * lam[:, i] * lam[:, j]
        dN[:, 4 + k] = 4 * (lam[:, i, None] * dlam[j] + lam[:, j, None] * dlam[i])
    return N, dN


def _p2_tri_basis(st: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """P2 basis of the reference triangle (nodes v0, v1, v2, m01, m12, m02): values (q,6), grads (q,6,2)."""
    lam = np.c_[1.0 - st.sum(axis=1), st]
    dlam = np.array([[-1.0, -1.0], [1, 0], [0, 1]])
    N = np.empty((len(st), 6))
    dN = np.empty((len(st), 6, 2))
    for i in range(3):
        N[:, i] = lam[:, i] * (2 * lam[:, i] - 1)
        dN[:, i] = (4 * lam[:, i] - 1)[:, None] * dlam[i]
    for k, (i, j) in enumerate(((0, 1), (1, 2), (0, 2))):
        N[:, 3 + k] = 4 * lam[:, i] * lam[:, j]
        dN[:, 3 + k] = 4 * (lam[:, i, None] * dlam[j] + lam[:, j, None] * dlam[i])
    return N, dN


def _check(X, T10) -> tuple[np.ndarray, np.ndarray]:
    X = np.ascontiguousarray(X, dtype=np.float64)
    T10 = np.ascontiguousarray(T10, dtype=np.int64)
    if X.ndim != 2 or X.shape[1] != 3 or T10.ndim != 2 or T10.shape[1] != 10:
        raise SolverInputError(f"P2 mesh needs X (N,3) and T10 (t,10), got {X.shape} and {T10.shape}")
    if T10.size and (T10.min() < 0 or T10.max() >= len(X)):
        raise SolverInputError(f"T10 refers to nodes outside 0..{len(X) - 1}")
    return X, T10


def p2_jacobians(X: np.ndarray, T10: np.ndarray, dN: np.ndarray) -> np.ndarray:
    """Jacobians ``J[t, q] = ∂x/∂ξ`` (columns = derivatives along ξ1, ξ2, ξ3) of the element maps.

    Parameters
    ----------
    X : (N, 3) float array
    T10 : (t, 10) int array
    dN : (q, 10, 3) float array
        Reference basis gradients (:func:`p2_basis`).

    Returns
    -------
    (t, q, 3, 3) float array
    """
    return np.einsum("tad,qak->tqdk", X[T10], dN, optimize=True)


def _chunks(t: int):
    for s in range(0, t, _CHUNK):
        yield slice(s, min(t, s + _CHUNK))


def _assemble(T10: np.ndarray, n: int, local_fn) -> sp.csr_matrix:
    """Sum the (c,10,10) local matrices returned by ``local_fn(slice)`` into an (n,n) csr matrix."""
    rows, cols, vals = [], [], []
    for sl in _chunks(len(T10)):
        Ke = local_fn(sl)
        idx = T10[sl]
        rows.append(np.repeat(idx, 10, axis=1).ravel())
        cols.append(np.tile(idx, (1, 10)).ravel())
        vals.append(Ke.ravel())
    A = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))
    A.sum_duplicates()
    return A


def det3(J: np.ndarray) -> np.ndarray:
    """Determinants of stacked 3x3 matrices ``(..., 3, 3)`` by cofactors (faster than LAPACK's batches)."""
    return (J[..., 0, 0] * (J[..., 1, 1] * J[..., 2, 2] - J[..., 1, 2] * J[..., 2, 1])
            - J[..., 0, 1] * (J[..., 1, 0] * J[..., 2, 2] - J[..., 1, 2] * J[..., 2, 0])
            + J[..., 0, 2] * (J[..., 1, 0] * J[..., 2, 1] - J[..., 1, 1] * J[..., 2, 0]))


def inv3(J: np.ndarray, det: np.ndarray) -> np.ndarray:
    """Inverses of stacked 3x3 matrices given their determinants (adjugate / det)."""
    C = np.empty_like(J)
    for i in range(3):
        for j in range(3):
            a, b = [k for k in range(3) if k != j], [k for k in range(3) if k != i]
            minor = J[..., a[0], b[0]] * J[..., a[1], b[1]] - J[..., a[0], b[1]] * J[..., a[1], b[0]]
            C[..., i, j] = minor * (-1) ** (i + j)
    return C / det[..., None, None]


def _geometry(X, T10, sl, dN):
    J = p2_jacobians(X, T10[sl], dN)  # (c, q, 3, 3)
    det = det3(J)
    if np.any(det <= 0):
        bad = int(np.count_nonzero((det <= 0).any(axis=1)))
        raise SolverInputError(f"{bad} P2 elements have det J <= 0 at a quadrature point (inverted or "
                               "degenerate curved tets; certify them with nestmg.curved.certify_tets)")
    return J, det


def _straight_elements(X: np.ndarray, T10: np.ndarray) -> np.ndarray:
    """Mask (t,) of elements whose edge nodes all sit at their edges' midpoints (affine maps)."""
    P = X[T10]
    mid = np.stack([0.5 * (P[:, a] + P[:, b]) for a, b in P2_EDGES], axis=1)
    dev = np.abs(P[:, 4:] - mid).max(axis=(1, 2))
    size = np.abs(P[:, 1:4] - P[:, :1]).max(axis=(1, 2))
    return dev <= 1e-12 * size


def p2_stiffness_matrix(X, T10, coefficient: np.ndarray | None = None, *, degree: int = 4) -> sp.csr_matrix:
    """Stiffness ``K_ab = ∫ κ ∇N_a · ∇N_b`` of straight or curved P2 tets (symmetric PSD, ``K1 = 0``).

    Straight elements (affine maps) use the exact degree-2 rule; curved ones the ``degree`` rule.

    Parameters
    ----------
    X : (N, 3) float array
    T10 : (t, 10) int array
    coefficient : (t,) float array, optional
        Per-element conductivity κ (default 1).
    degree : int
        Quadrature degree on curved elements (the integrand is rational there).

    Returns
    -------
    (N, N) csr_matrix
    """
    X, T10 = _check(X, T10)
    kappa = np.ones(len(T10)) if coefficient is None else np.asarray(coefficient, dtype=np.float64)
    straight = _straight_elements(X, T10)
    mats = []
    for mask, deg in ((straight, 2), (~straight, degree)):
        if not mask.any():
            continue
        pts, w = tet_quadrature(deg)
        _, dN = p2_basis(pts)
        Ts, ks = T10[mask], kappa[mask]

        def local(sl, Ts=Ts, ks=ks, dN=dN, w=w):
            J, det = _geometry(X, Ts, sl, dN)
            G = np.einsum("qak,tqkd->tqad", dN, inv3(J, det), optimize=True)  # physical gradients
            G *= np.sqrt(det * w * ks[sl, None])[:, :, None, None]
            G = G.transpose(0, 2, 1, 3).reshape(len(G), 10, -1)
            return G @ G.transpose(0, 2, 1)

        mats.append(_assemble(Ts, len(X), local))
    return sp.csr_matrix(sum(mats))


def p2_mass_matrix(X, T10, *, degree: int = 7) -> sp.csr_matrix:
    """Consistent mass ``M_ab = ∫ N_a N_b`` of straight or curved P2 tets, (N, N) csr (degree 7: exact)."""
    X, T10 = _check(X, T10)
    pts, w = tet_quadrature(degree)
    N, dN = p2_basis(pts)

    def local(sl):
        _, det = _geometry(X, T10, sl, dN)
        return np.einsum("tq,qa,qb->tab", det * w, N, N, optimize=True)

    return _assemble(T10, len(X), local)


def p2_load(X, T10, f: Callable[[np.ndarray], np.ndarray], *, degree: int = 5) -> np.ndarray:
    """Load vector ``b_a = ∫ f N_a`` for a source ``f`` given as a function of points (q,3) -> (q,)."""
    X, T10 = _check(X, T10)
    pts, w = tet_quadrature(degree)
    N, dN = p2_basis(pts)
    b = np.zeros(len(X))
    for sl in _chunks(len(T10)):
        _, det = _geometry(X, T10, sl, dN)
        xq = np.einsum("qa,tad->tqd", N, X[T10[sl]], optimize=True)
        fq = np.asarray(f(xq.reshape(-1, 3)), dtype=np.float64).reshape(det.shape)
        np.add.at(b, T10[sl], np.einsum("tq,qa->ta", det * w * fq, N, optimize=True))
    return b


def p2_boundary_facets(T10: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Boundary facets of a P2 tet mesh as 6-node triangles, outward for positively oriented tets.

    Returns
    -------
    F6 : (f, 6) int64
        ``v0, v1, v2, m01, m12, m02`` per facet.
    J : (f,) int64
        The tet of each facet.
    """
    from .fem import boundary_faces

    T10 = np.asarray(T10, dtype=np.int64)
    F, J = boundary_faces(T10[:, :4])
    key = {e: 4 + k for k, e in enumerate(P2_EDGES)}
    key.update({(j, i): v for (i, j), v in list(key.items())})
    # local vertex positions of each facet's corners in its tet, then the edge node between each pair
    loc = np.argmax(T10[J, :4][:, None, :] == F[:, :, None], axis=2)  # (f, 3)
    table = np.zeros((4, 4), dtype=np.int64)
    for (i, j), v in key.items():
        table[i, j] = v
    mids = [T10[J, table[loc[:, a], loc[:, b]]] for a, b in ((0, 1), (1, 2), (0, 2))]
    return np.c_[F, np.stack(mids, axis=1)], J


def p2_neumann_load(X, F6, flux: Callable[[np.ndarray, np.ndarray], np.ndarray], *,
                    degree: int = 6) -> np.ndarray:
    """Boundary load ``b_a = ∮ g N_a dS`` over curved 6-node facets.

    Parameters
    ----------
    X : (N, 3) float array
    F6 : (f, 6) int array
        Outward 6-node facets (:func:`p2_boundary_facets`).
    flux : callable ``g(x, n) -> (q,)``
        Normal flux ``∂u/∂n`` at points ``x`` (q,3), given the curved facet's unit outer normals ``n``
        (q,3).

    Returns
    -------
    (N,) float array
    """
    X = np.asarray(X, dtype=np.float64)
    F6 = np.asarray(F6, dtype=np.int64)
    pts, w = triangle_quadrature(degree)
    N, dN = _p2_tri_basis(pts)
    b = np.zeros(len(X))
    for sl in _chunks(len(F6)):
        P = X[F6[sl]]  # (c, 6, 3)
        xq = np.einsum("qa,cad->cqd", N, P, optimize=True)
        d = np.einsum("qak,cad->cqkd", dN, P, optimize=True)  # tangents (c, q, 2, 3)
        nrm = np.cross(d[:, :, 0], d[:, :, 1])
        area = np.linalg.norm(nrm, axis=2)
        gq = np.asarray(flux(xq.reshape(-1, 3), (nrm / area[..., None]).reshape(-1, 3)), float)
        np.add.at(b, F6[sl], np.einsum("cq,qa->ca", area * w * gq.reshape(area.shape), N, optimize=True))
    return b


def p2_l2_error(X, T10, uh: np.ndarray, u: Callable[[np.ndarray], np.ndarray], *, degree: int = 5,
                remove_mean: bool = False) -> float:
    """``‖u_h − u‖_{L2}`` over the (curved) elements, by quadrature.

    Parameters
    ----------
    uh : (N,) float array
        P2 nodal values.
    u : callable
        Exact solution of points (q,3) -> (q,).
    remove_mean : bool
        Compare ``u_h − u`` up to its mean (pure Neumann solutions are defined up to a constant).
    """
    X, T10 = _check(X, T10)
    pts, w = tet_quadrature(degree)
    N, dN = p2_basis(pts)
    dv, ev = [], []
    for sl in _chunks(len(T10)):
        _, det = _geometry(X, T10, sl, dN)
        xq = np.einsum("qa,tad->tqd", N, X[T10[sl]], optimize=True)
        e = (np.einsum("qa,ta->tq", N, np.asarray(uh)[T10[sl]])
             - np.asarray(u(xq.reshape(-1, 3))).reshape(det.shape))
        dv.append((det * w).ravel())
        ev.append(e.ravel())
    dv, ev = np.concatenate(dv), np.concatenate(ev)
    if remove_mean:
        ev = ev - (dv @ ev) / dv.sum()
    return float(np.sqrt(dv @ ev**2))
