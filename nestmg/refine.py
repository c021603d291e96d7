"""Uniform ("red") refinement of a tet mesh: the cheapest fine level, exactly nested in its parent.

Every tet is split into 8 by its edge midpoints (Bey 1995; Zhang 1995): four corner tets, and the
inner octahedron cut into four along its *shortest* diagonal, which keeps the children in at most
three similarity classes (no quality decay under repeated refinement). The refined mesh covers
exactly the same domain as its parent, so the prolongation is the exact linear interpolation
``P = [I; (e_i + e_j)/2]`` (no point location, no extrapolation) and the Galerkin operator
``Pᵀ A_fine P`` *equals* the parent's own FEM matrix (nested P1 spaces): the top of the hierarchy is
textbook geometric multigrid, and its coarse operator is as sparse as a re-discretised one.

Why the pipeline uses it (docs/scale.md): fTetWild's time grows with the number of tets it makes, so
meshing at ``2h`` and refining once is ~8x cheaper than meshing at ``h``; the fine boundary is then
TetWild's boundary at ``2h`` (within TetWild's envelope of the input), not a new one at ``h``.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

__all__ = ["refine_tets"]

# the 6 edges of a tet, in the order of the midpoint columns m01, m02, m03, m12, m13, m23
_EDGES = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))


def refine_tets(V: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray, sp.csr_matrix]:
    """Split every tet into 8 (red refinement, shortest interior diagonal).

    Parameters
    ----------
    V : (n,3) float array
    T : (t,4) int array
        Tets (either orientation).

    Returns
    -------
    V2 : (n + e, 3) float64 array
        The parent's nodes first (same order), then one node per edge at its midpoint.
    T2 : (8t, 4) int64 array
        Positively oriented children; tet ``i``'s children are rows ``8i .. 8i+7``.
    P : (n + e, n) csr_matrix
        Exact linear prolongation from the parent: identity on its nodes, 1/2-1/2 on the midpoints.

    Examples
    --------
    >>> V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    >>> V2, T2, P = refine_tets(V, np.array([[0, 1, 2, 3]]))
    >>> from nestmg.tetmesh import tet_volumes
    >>> len(V2), len(T2), round(float(tet_volumes(V2, T2).sum()), 12), P.shape
    (10, 8, 0.166666666667, (10, 4))
    """
    from .tetmesh import orient_tets

    V = np.asarray(V, dtype=np.float64)
    T = np.asarray(T, dtype=np.int64)
    n, t = len(V), len(T)
    E = np.stack([np.sort(T[:, [a, b]], axis=1) for a, b in _EDGES], axis=1).reshape(-1, 2)  # (6t, 2)
    key = E[:, 0] * n + E[:, 1]
    uniq, inv = np.unique(key, return_inverse=True)
    ea, eb = uniq // n, uniq % n
    V2 = np.vstack([V, 0.5 * (V[ea] + V[eb])])
    M = (n + inv).reshape(t, 6)  # midpoint node of each tet edge
    m01, m02, m03, m12, m13, m23 = (M[:, i] for i in range(6))
    v0, v1, v2, v3 = (T[:, i] for i in range(4))
    corners = [np.c_[v0, m01, m02, m03], np.c_[m01, v1, m12, m13], np.c_[m02, m12, v2, m23],
               np.c_[m03, m13, m23, v3]]
    # the octahedron m01..m23: the three diagonals join opposite midpoints; cut along the shortest,
    # the other four midpoints form the equator (in cyclic order)
    diag = np.stack([np.linalg.norm(V2[m01] - V2[m23], axis=1), np.linalg.norm(V2[m02] - V2[m13], axis=1),
                     np.linalg.norm(V2[m03] - V2[m12], axis=1)], axis=1)
    choice = np.argmin(diag, axis=1)
    options = [
        (m01, m23, (m02, m03, m13, m12)),
        (m02, m13, (m01, m03, m23, m12)),
        (m03, m12, (m01, m02, m23, m13)),
    ]
    inner = np.zeros((t, 4, 4), dtype=np.int64)
    for c, (a, b, ring) in enumerate(options):
        sel = choice == c
        if not sel.any():
            continue
        for i in range(4):
            inner[sel, i] = np.c_[a[sel], b[sel], ring[i][sel], ring[(i + 1) % 4][sel]]
    T2 = np.concatenate([np.stack(corners, axis=1), inner], axis=1).reshape(-1, 4)
    T2 = orient_tets(V2, T2)
    m = len(uniq)
    rows = np.r_[np.arange(n), n + np.arange(m), n + np.arange(m)]
    cols = np.r_[np.arange(n), ea, eb]
    vals = np.r_[np.ones(n), np.full(2 * m, 0.5)]
    P = sp.csr_matrix((vals, (rows, cols)), shape=(n + m, n))
    return V2, T2, P
