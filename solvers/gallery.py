"""Small test problems with exactly nested tet hierarchies.

The Kuhn (Freudenthal) triangulation splits every cube cell of a regular grid into the 6 tets
``v0, v0+e_p0, v0+e_p0+e_p1, v0+(1,1,1)`` for the 6 permutations ``p`` of the axes. It is the
arrangement of the planes ``x_i = k`` and ``x_i - x_j = k`` (k integer), so the grid with spacing h/2
refines the one with spacing h: every fine tet lies inside one coarse tet, and the coarse P1 hat
functions are exactly piecewise linear on the fine mesh. Barycentric interpolation is then exact.
"""

from __future__ import annotations

import itertools

import numpy as np
import scipy.sparse as sp

from .errors import SolverInputError

__all__ = ["kuhn_cube_hierarchy", "kuhn_cube_mesh", "kuhn_interpolation", "kuhn_prolongation"]

# The 6 axis permutations; odd permutations give negatively oriented tets and are flipped below.
_PERMS = np.array(list(itertools.permutations(range(3))), dtype=np.int64)


def _grid_index(ijk: np.ndarray, n: int) -> np.ndarray:
    """Linear index of grid node ``ijk`` (.., 3) in an (n+1)^3 grid, x fastest."""
    m = n + 1
    return ijk[..., 0] + m * (ijk[..., 1] + m * ijk[..., 2])


def kuhn_cube_mesh(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Kuhn tet mesh of the unit cube with ``n`` cells per side.

    Parameters
    ----------
    n : int
        Number of cube cells per side (>= 1).

    Returns
    -------
    V : (( n+1)**3, 3) float64
        Node positions; node ``(i, j, k)`` has index ``i + (n+1)*(j + (n+1)*k)`` and position
        ``(i, j, k) / n``.
    T : (6*n**3, 4) int64
        Positively oriented tets (signed volume ``1/(6 n^3)`` each).

    Examples
    --------
    >>> V, T = kuhn_cube_mesh(2)
    >>> V.shape, T.shape
    ((27, 3), (48, 4))
    """
    n = int(n)
    if n < 1:
        raise SolverInputError(f"kuhn_cube_mesh: n must be >= 1, got {n}")
    g = np.arange(n + 1, dtype=np.float64) / n
    # x fastest: meshgrid with indexing="ij" over (z, y, x) then reverse columns.
    Z, Y, X = np.meshgrid(g, g, g, indexing="ij")
    V = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])

    c = np.arange(n, dtype=np.int64)
    cz, cy, cx = np.meshgrid(c, c, c, indexing="ij")
    corner = np.column_stack([cx.ravel(), cy.ravel(), cz.ravel()])  # (n^3, 3)
    eye = np.eye(3, dtype=np.int64)
    tets = []
    for p in _PERMS:
        v0 = corner
        v1 = v0 + eye[p[0]]
        v2 = v1 + eye[p[1]]
        v3 = v0 + 1
        tet = np.column_stack([_grid_index(v, n) for v in (v0, v1, v2, v3)])
        # parity of the permutation decides the orientation
        odd = _parity(p)
        if odd:
            tet = tet[:, [0, 2, 1, 3]]
        tets.append(tet)
    T = np.stack(tets, axis=1).reshape(-1, 4)  # the 6 tets of a cell are consecutive
    return V, T


def _parity(p: np.ndarray) -> bool:
    """True for an odd permutation of (0, 1, 2)."""
    inv = sum(1 for a in range(3) for b in range(a + 1, 3) if p[a] > p[b])
    return inv % 2 == 1


def kuhn_interpolation(Q, n: int, tol: float = 1e-12) -> sp.csr_matrix:
    """Barycentric interpolation matrix from the Kuhn mesh with ``n`` cells per side to points ``Q``.

    Parameters
    ----------
    Q : (m, 3) array_like of float
        Points in the closed unit cube (up to ``tol``).
    n : int
        Cells per side of the Kuhn mesh (nodes numbered as in :func:`kuhn_cube_mesh`).
    tol : float
        Points farther than ``tol`` outside the cube raise; points within it are clamped.

    Returns
    -------
    P : (m, (n+1)**3) csr_matrix
        Row ``i`` holds the barycentric coordinates of ``Q[i]`` in the Kuhn tet containing it
        (at most 4 non-zeros, non-negative, summing to 1).

    Examples
    --------
    >>> P = kuhn_interpolation([[0.5, 0.25, 0.0]], 2)
    >>> P.toarray().nonzero()[1].tolist(), P.data.tolist()
    ([1, 4], [0.5, 0.5])
    """
    n = int(n)
    if n < 1:
        raise SolverInputError(f"kuhn_interpolation: n must be >= 1, got {n}")
    Q = np.asarray(Q, dtype=np.float64)
    if Q.ndim != 2 or Q.shape[1] != 3:
        raise SolverInputError(f"Q must be an (m, 3) array of points, got shape {Q.shape}")
    if not np.all(np.isfinite(Q)):
        raise SolverInputError("Q contains NaN/inf")
    outside = np.any((Q < -tol) | (Q > 1 + tol), axis=1)
    if np.any(outside):
        raise SolverInputError(f"{np.count_nonzero(outside)} points lie outside the unit cube (first: {Q[outside][0]})")
    q = np.clip(Q, 0.0, 1.0) * n  # in grid units
    cell = np.minimum(np.floor(q).astype(np.int64), n - 1)
    t = q - cell  # local coordinates in [0, 1]^3
    # Freudenthal barycentric coordinates: sort t decreasingly, t_p0 >= t_p1 >= t_p2.
    order = np.argsort(-t, axis=1, kind="stable")
    ts = np.take_along_axis(t, order, axis=1)
    w = np.column_stack([1.0 - ts[:, 0], ts[:, 0] - ts[:, 1], ts[:, 1] - ts[:, 2], ts[:, 2]])
    eye = np.eye(3, dtype=np.int64)
    v0 = cell
    v1 = v0 + eye[order[:, 0]]
    v2 = v1 + eye[order[:, 1]]
    v3 = v0 + 1
    cols = np.column_stack([_grid_index(v, n) for v in (v0, v1, v2, v3)])
    rows = np.repeat(np.arange(Q.shape[0]), 4)
    P = sp.csr_matrix((w.ravel(), (rows, cols.ravel())), shape=(Q.shape[0], (n + 1) ** 3))
    P.sum_duplicates()
    P.data[np.abs(P.data) < 1e-14] = 0.0
    P.eliminate_zeros()
    return P


def kuhn_prolongation(n_coarse: int) -> sp.csr_matrix:
    """Exact P1 prolongation from the Kuhn mesh with ``n_coarse`` cells per side to ``2*n_coarse``.

    Parameters
    ----------
    n_coarse : int
        Cells per side of the coarse mesh.

    Returns
    -------
    P : ((2*n_coarse+1)**3, (n_coarse+1)**3) csr_matrix, float64
        ``P[i, j]`` = coarse hat function ``j`` evaluated at fine node ``i``. Rows sum to 1, entries are in
        {0, 1/2, 1}, and ``P @ (V_c @ a) == V_f @ a`` for every linear function ``a``.
    """
    nc = int(n_coarse)
    if nc < 1:
        raise SolverInputError(f"kuhn_prolongation: n_coarse must be >= 1, got {nc}")
    Vf, _ = kuhn_cube_mesh(2 * nc)
    return kuhn_interpolation(Vf, nc)


def kuhn_cube_hierarchy(n: int, levels: int) -> tuple[list[tuple[np.ndarray, np.ndarray]], list[sp.csr_matrix]]:
    """Exactly nested hierarchy of Kuhn meshes of the unit cube.

    Parameters
    ----------
    n : int
        Cells per side of the finest mesh; must be divisible by ``2**(levels-1)``.
    levels : int
        Number of levels (>= 1).

    Returns
    -------
    meshes : list of (V, T)
        ``levels`` meshes, finest first; level k has ``n / 2**k`` cells per side.
    Ps : list of csr_matrix
        ``levels - 1`` prolongations; ``Ps[k]`` has shape (n_nodes[k], n_nodes[k+1]) and maps level k+1
        to level k (rows sum to 1, exact for P1 functions).

    Examples
    --------
    >>> meshes, Ps = kuhn_cube_hierarchy(8, 3)
    >>> [V.shape[0] for V, T in meshes], [P.shape for P in Ps]
    ([729, 125, 27], [(729, 125), (125, 27)])
    """
    n, levels = int(n), int(levels)
    if levels < 1:
        raise SolverInputError(f"kuhn_cube_hierarchy: levels must be >= 1, got {levels}")
    if n < 1 or n % (2 ** (levels - 1)) != 0:
        raise SolverInputError(
            f"kuhn_cube_hierarchy: n={n} must be a positive multiple of 2**(levels-1)={2 ** (levels - 1)}"
        )
    meshes = [kuhn_cube_mesh(n // 2**k) for k in range(levels)]
    Ps = [kuhn_prolongation(n // 2 ** (k + 1)) for k in range(levels - 1)]
    return meshes, Ps
