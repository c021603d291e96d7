"""Barycentric point location in a tet mesh: the rows of a prolongation, for any subset of fine nodes.

:func:`locate_in_tets` is the one location path of the project: :func:`nestmg.prolongation.prolongation`
builds a whole ``P`` from it, and :meth:`solvers.petsc.PetscMultigrid.from_distributed` builds each MPI
rank's own rows of ``P₀`` from it (the rank's nodes only). Plain arrays in and out; libigl (a base
dependency) does the work: an AABB tree over the coarse tets, ``in_element``, ``barycentric_coordinates``,
and ``point_mesh_squared_distance`` for the nodes that location misses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import SolverInputError
from .fem import boundary_faces

__all__ = ["Location", "clean_weights", "locate_in_tets", "tet_barycentric"]


@dataclass
class Location:
    """Where points ``Q`` lie in a tet mesh ``(Vc, Tc)`` (result of :func:`locate_in_tets`).

    Attributes
    ----------
    cols : (n,4) int64
        Coarse nodes of the tet containing each point (of the nearest tet for outside points).
    weights : (n,4) float64
        Barycentric coordinates in that tet (unclamped for outside points; rows sum to 1).
    outside : (n,) int64
        Indices of the points outside every tet, farther than the on-boundary tolerance.
    n_on_boundary : int
        Points that location missed but that lie on the coarse boundary up to the tolerance; they are
        located at their closest boundary point (exact).
    distance2 : (len(outside),) float64
        Squared distances of the outside points to the coarse boundary.
    closest : (len(outside),3) float64
        Their closest points on the coarse boundary.
    """

    cols: np.ndarray
    weights: np.ndarray
    outside: np.ndarray
    n_on_boundary: int
    distance2: np.ndarray
    closest: np.ndarray


def tet_barycentric(Q: np.ndarray, Vc: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (n,4) of points ``Q`` (n,3) in tets ``tets`` (n,4) of ``Vc`` (m,3)."""
    import igl

    if len(Q) == 0:
        return np.zeros((0, 4))
    return igl.barycentric_coordinates(
        np.ascontiguousarray(Q, dtype=np.float64),
        np.ascontiguousarray(Vc[tets[:, 0]]),
        np.ascontiguousarray(Vc[tets[:, 1]]),
        np.ascontiguousarray(Vc[tets[:, 2]]),
        np.ascontiguousarray(Vc[tets[:, 3]]),
    )


def locate_in_tets(Q, Vc, Tc, *, on_boundary_tol: float = 1e-12, diag: float | None = None) -> Location:
    """Locate points in a tet mesh and return their barycentric coordinates.

    Parameters
    ----------
    Q : (n,3) float array
        Points (fine nodes); any subset of a fine level, e.g. one MPI rank's nodes.
    Vc : (m,3) float array
        Nodes of the coarse tet mesh.
    Tc : (t,4) int array
        Its tets.
    on_boundary_tol : float
        Points within ``on_boundary_tol * diag`` of the coarse boundary count as on it, not outside.
    diag : float, optional
        Length scale of the tolerance: the bounding-box diagonal of the *whole* fine level (pass it
        when ``Q`` is a subset, so every subset uses the same tolerance); default that of ``Q``.

    Returns
    -------
    Location
        ``cols``, ``weights`` (rows sum to 1), ``outside`` and the closest boundary points of those.

    Examples
    --------
    >>> Vc = np.array([[0., 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]); Tc = np.array([[0, 1, 2, 3]])
    >>> loc = locate_in_tets(np.array([[0.25, 0.25, 0.25], [1.0, 1.0, 1.0]]), Vc, Tc)
    >>> np.round(loc.weights[0], 3).tolist(), loc.outside.tolist()
    ([0.25, 0.25, 0.25, 0.25], [1])
    """
    import igl

    Q = np.ascontiguousarray(Q, dtype=np.float64).reshape(-1, 3) if np.size(Q) == 0 else \
        np.ascontiguousarray(Q, dtype=np.float64)
    Vc = np.ascontiguousarray(Vc, dtype=np.float64)
    Tc = np.ascontiguousarray(Tc, dtype=np.int64)
    if Q.ndim != 2 or Q.shape[1] != 3 or Vc.ndim != 2 or Vc.shape[1] != 3:
        raise SolverInputError(f"the points (fine nodes) and the coarse nodes must be (n,3) arrays, got "
                               f"shapes {Q.shape} and {Vc.shape}")
    if Tc.ndim != 2 or Tc.shape[1] != 4 or len(Tc) == 0:
        raise SolverInputError(f"the coarse tets must be a non-empty (t,4) array, got shape {Tc.shape}")
    if not (np.isfinite(Q).all() and np.isfinite(Vc).all()):
        raise SolverInputError("node coordinates contain NaN or inf")
    if Tc.min() < 0 or Tc.max() >= len(Vc):
        raise SolverInputError(f"the coarse tets index nodes outside the {len(Vc)} coarse nodes "
                               f"(indices {Tc.min()} to {Tc.max()})")
    n = len(Q)
    cols = np.zeros((n, 4), dtype=np.int64)
    W = np.zeros((n, 4))
    empty = Location(cols, W, np.zeros(0, dtype=np.int64), 0, np.zeros(0), np.zeros((0, 3)))
    if n == 0:
        return empty
    tree = igl.AABB()
    tree.init(Vc, Tc)
    tet = np.asarray(igl.in_element(Vc, Tc, Q, tree)).ravel()
    ins = np.flatnonzero(tet >= 0)
    out = np.flatnonzero(tet < 0)
    cols[ins] = Tc[tet[ins]]
    W[ins] = tet_barycentric(Q[ins], Vc, Tc[tet[ins]])
    if diag is None:
        diag = float(np.linalg.norm(Q.max(axis=0) - Q.min(axis=0)))
    d2, C, n_on = np.zeros(0), np.zeros((0, 3)), 0
    if len(out):
        Fb, J = boundary_faces(Tc)
        d2, fi, C = igl.point_mesh_squared_distance(Q[out], Vc, np.ascontiguousarray(Fb))
        # nodes on the coarse boundary up to round-off (a fine boundary node on a coarse boundary facet
        # that point location missed by ~1e-17) are located at their closest point, not extrapolated
        on = d2 <= (on_boundary_tol * diag) ** 2
        if on.any():
            on_idx = out[on]
            cols[on_idx] = Tc[J[fi[on]]]
            W[on_idx] = tet_barycentric(C[on], Vc, Tc[J[fi[on]]])
            n_on = int(on.sum())
        out, d2, fi, C = out[~on], d2[~on], fi[~on], C[~on]
        cols[out] = Tc[J[fi]]
        W[out] = tet_barycentric(Q[out], Vc, Tc[J[fi]])
    return Location(cols, W, out, n_on, np.asarray(d2), np.asarray(C))


def clean_weights(W: np.ndarray) -> np.ndarray:
    """Drop round-off weights (``|w| < 1e-10``) in place and renormalise rows to sum 1.

    Nodes on a coarse face/edge get round-off weights (~1e-17) on the opposite corners; left in, they
    make coarse columns reached only by round-off, i.e. near-zero rows in ``Pᵀ A P`` (a near-singular
    coarse operator).
    """
    W[np.abs(W) < 1e-10] = 0.0
    W /= W.sum(axis=1, keepdims=True)
    return W
