"""Triangle quadrature for the integrated signed distance of the flow (paper Sec. 3.1).

The flow energy is Φ(F̄) = ∫_F̄ s(p) d(p) dA ≈ Σ_i Σ_j A_i w_j sd(p_ij), with quadrature points
p_ij = λ_a f_a + λ_b f_b + λ_c f_c inside each fine triangle i (paper Eq. 1 and the sum after it).
Everything here is a fixed sparse linear map from vertex positions to quadrature points, so the
chain rule of Eq. 5 (gradient at vertex f = Σ over incident triangles of w_j λ_f g_ij) is a single
transposed sparse product.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..errors import CageOptionError

__all__ = ["quadrature_matrix", "quadrature_points", "triangle_rule"]

# Symmetric rules on the reference triangle, barycentric coordinates (q,3) and weights summing to 1
# (Strang & Fix / Dunavant). Keys: polynomial degree integrated exactly.
_A6, _B6 = 0.445948490915965, 0.091576213509771
_W6a, _W6b = 0.223381589678011, 0.109951743655322
_A7, _B7 = 0.059715871789770, 0.470142064105115
_C7, _D7 = 0.797426985353087, 0.101286507323456


def _perm3(a: float, b: float) -> list[tuple[float, float, float]]:
    """The three distinct permutations of (a, b, b)."""
    return [(a, b, b), (b, a, b), (b, b, a)]


_RULES: dict[int, tuple[np.ndarray, np.ndarray]] = {
    1: (np.array([[1 / 3, 1 / 3, 1 / 3]]), np.array([1.0])),
    2: (np.array(_perm3(2 / 3, 1 / 6)), np.full(3, 1 / 3)),
    4: (
        np.array(_perm3(1 - 2 * _A6, _A6) + _perm3(1 - 2 * _B6, _B6)),
        np.array([_W6a] * 3 + [_W6b] * 3),
    ),
    5: (
        np.array([(1 / 3, 1 / 3, 1 / 3)] + _perm3(_A7, _B7) + _perm3(_C7, _D7)),
        np.array([0.225] + [0.132394152788506] * 3 + [0.125939180544827] * 3),
    ),
}


def triangle_rule(order: int) -> tuple[np.ndarray, np.ndarray]:
    """Barycentric points and weights of a symmetric triangle rule exact to degree ``order``.

    Parameters
    ----------
    order : int
        Polynomial degree integrated exactly, 1 to 5 (3 uses the degree-4 rule).

    Returns
    -------
    bary : (q,3) float array
        Barycentric coordinates of the q quadrature points (rows sum to 1).
    weights : (q,) float array
        Weights, summing to 1 (multiply by the triangle area to integrate).

    Examples
    --------
    >>> b, w = triangle_rule(2)
    >>> b.shape, float(w.sum())
    ((3, 3), 1.0)
    """
    order = int(order)
    if order < 1 or order > 5:
        raise CageOptionError(f"quadrature order must be in 1..5, got {order}")
    key = {1: 1, 2: 2, 3: 4, 4: 4, 5: 5}[order]
    bary, w = _RULES[key]
    return bary.copy(), w.copy()


def quadrature_matrix(F: np.ndarray, n_vertices: int, order: int = 2) -> tuple[sp.csr_matrix, np.ndarray]:
    """Sparse map from vertex positions to quadrature points of every triangle.

    Parameters
    ----------
    F : (m,3) int array
        Triangles.
    n_vertices : int
        Number of vertices n.
    order : int
        Quadrature degree (see :func:`triangle_rule`).

    Returns
    -------
    B : (m*q, n) csr_matrix
        ``B @ V`` are the quadrature points, triangle-major (row ``i*q + j`` is point j of triangle i);
        entries are the barycentric coordinates λ of Eq. 5.
    weights : (q,) float array
        Rule weights (per triangle, to be multiplied by the triangle areas).
    """
    F = np.asarray(F, dtype=np.int64)
    bary, w = triangle_rule(order)
    m, q = len(F), len(w)
    rows = np.repeat(np.arange(m * q), 3)
    cols = np.repeat(F, q, axis=0).ravel()
    vals = np.tile(bary, (m, 1)).ravel()
    B = sp.csr_matrix((vals, (rows, cols)), shape=(m * q, n_vertices))
    return B, w


def quadrature_points(V: np.ndarray, F: np.ndarray, order: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Quadrature points and their area weights on a triangle mesh.

    Parameters
    ----------
    V : (n,3) float array
    F : (m,3) int array
    order : int

    Returns
    -------
    P : (m*q,3) float array
        Quadrature points, triangle-major.
    W : (m*q,) float array
        Area × rule weight of each point (sums to the surface area).
    """
    B, w = quadrature_matrix(F, len(V), order)
    A = triangle_areas(V, F)
    return B @ np.asarray(V, dtype=float), np.outer(A, w).ravel()


def triangle_areas(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Areas (m,) of the triangles ``F`` of vertex positions ``V``."""
    V = np.asarray(V, dtype=float)
    e1 = V[F[:, 1]] - V[F[:, 0]]
    e2 = V[F[:, 2]] - V[F[:, 0]]
    return 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1)
