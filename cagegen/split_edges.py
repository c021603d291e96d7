"""Conforming edge splitting: the same surface with no edge longer than a given length.

CAD exports (STL) describe a flat face by a few long, thin triangles whose size follows the CAD
topology rather than the geometry. The nested-cages flow samples the fine surface at its triangles'
quadrature points (paper Sec. 3.1, Eq. 5), so a triangle far longer than the target cage's edges is
sampled too sparsely: its quadrature points end inside the cage while its edges still cross it, and
the flow stalls. Splitting long edges at their midpoints gives the flow a surface that is
*geometrically the same set* (every new triangle lies in the plane of its parent) with enough
samples; the cage built around it is certified against the original surface.
"""

from __future__ import annotations

import numpy as np

from .errors import CageOptionError

__all__ = ["split_long_edges"]


def _unique_edges(F: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Unique undirected edges ``(e,2)`` and, per face, the edge index of (ab, bc, ca) ``(m,3)``."""
    half = np.stack([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]], axis=1).reshape(-1, 2)
    key = np.sort(half, axis=1)
    key = key[:, 0] * np.int64(n) + key[:, 1]
    ukey, inv = np.unique(key, return_inverse=True)
    E = np.stack([ukey // n, ukey % n], axis=1)
    return E, inv.reshape(-1, 3)


def _split_round(V: np.ndarray, F: np.ndarray, max_length: float) -> tuple[np.ndarray, np.ndarray, int]:
    """One round of red-green refinement of every edge longer than ``max_length``."""
    E, FE = _unique_edges(F, len(V))
    long_ = np.linalg.norm(V[E[:, 0]] - V[E[:, 1]], axis=1) > max_length
    n_split = int(long_.sum())
    if n_split == 0:
        return V, F, 0
    mid = np.full(len(E), -1, dtype=np.int64)
    mid[long_] = len(V) + np.arange(n_split)
    V = np.vstack([V, 0.5 * (V[E[long_, 0]] + V[E[long_, 1]])])
    marks = long_[FE]  # (m,3): ab, bc, ca
    count = marks.sum(1)
    out = [F[count == 0]]
    # rotate each face so that its pattern is canonical: one mark on ab, or two marks on ab and bc
    for shift in range(3):
        rolled = np.roll(marks, -shift, axis=1)
        c = np.roll(F, -shift, axis=1)
        m = np.roll(FE, -shift, axis=1)
        one = (count == 1) & rolled[:, 0]
        two = (count == 2) & ~rolled[:, 2]
        if one.any():
            a, b, cc, ab = c[one, 0], c[one, 1], c[one, 2], mid[m[one, 0]]
            out += [np.stack([a, ab, cc], 1), np.stack([ab, b, cc], 1)]
        if two.any():
            a, b, cc = c[two, 0], c[two, 1], c[two, 2]
            ab, bc = mid[m[two, 0]], mid[m[two, 1]]
            out.append(np.stack([ab, b, bc], 1))
            # the quad (a, ab, bc, c) is cut along its shorter diagonal
            d1 = np.linalg.norm(V[a] - V[bc], axis=1)
            d2 = np.linalg.norm(V[ab] - V[cc], axis=1)
            s = d1 <= d2
            out += [np.stack([a[s], ab[s], bc[s]], 1), np.stack([a[s], bc[s], cc[s]], 1),
                    np.stack([a[~s], ab[~s], cc[~s]], 1), np.stack([ab[~s], bc[~s], cc[~s]], 1)]
    three = count == 3
    if three.any():
        a, b, cc = F[three, 0], F[three, 1], F[three, 2]
        ab, bc, ca = mid[FE[three, 0]], mid[FE[three, 1]], mid[FE[three, 2]]
        out += [np.stack([a, ab, ca], 1), np.stack([ab, b, bc], 1), np.stack([ca, bc, cc], 1),
                np.stack([ab, bc, ca], 1)]
    return V, np.concatenate(out).astype(np.int64), n_split


def split_long_edges(V: np.ndarray, F: np.ndarray, max_length: float, *,
                     max_faces: int | None = None, max_rounds: int = 30) -> tuple[np.ndarray, np.ndarray, dict]:
    """Split every edge longer than ``max_length`` at its midpoint until none is left.

    Each round marks the long edges and refines every face by the red-green templates (one, two or
    three marked edges give two, three or four faces, orientation kept), so the result is conforming
    (closed and manifold when the input is) and covers exactly the input's surface: the first
    ``len(V)`` vertices are the input's, every new vertex is an edge midpoint and every new face lies
    in its parent's plane.

    Parameters
    ----------
    V : (n,3) float array
    F : (m,3) int array
        Triangle mesh (not modified).
    max_length : float
        Longest edge wanted, in the units of ``V``.
    max_faces : int, optional
        Stop (before exceeding it) once a round would give more faces than this.
    max_rounds : int
        Cap on refinement rounds.

    Returns
    -------
    V2 : (n2,3) float array
    F2 : (m2,3) int64 array
    info : dict
        ``rounds``, ``n_split`` (edges split), ``faces_in``, ``faces_out``, ``complete`` (no edge left
        longer than ``max_length``).

    Examples
    --------
    >>> import numpy as np
    >>> V = np.array([[0., 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    >>> F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    >>> V2, F2, info = split_long_edges(V, F, 0.6)
    >>> info["complete"], info["rounds"], len(F2)
    (True, 2, 40)
    """
    if not max_length > 0:
        raise CageOptionError(f"max_length must be positive, got {max_length!r}")
    V2 = np.array(V, dtype=np.float64)
    F2 = np.array(F, dtype=np.int64)
    info = {"faces_in": len(F2), "rounds": 0, "n_split": 0, "complete": True}
    for _ in range(int(max_rounds)):
        Vn, Fn, n = _split_round(V2, F2, max_length)
        if n == 0:
            break
        if max_faces is not None and len(Fn) > max_faces:
            info["complete"] = False
            break
        V2, F2 = Vn, Fn
        info["rounds"] += 1
        info["n_split"] += n
    else:
        E, _ = _unique_edges(F2, len(V2))
        info["complete"] = bool(np.linalg.norm(V2[E[:, 0]] - V2[E[:, 1]], axis=1).max() <= max_length)
    info["faces_out"] = len(F2)
    return V2, F2, info
