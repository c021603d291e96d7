"""Barycentric prolongation between consecutive tet layers.

For every node of the finer tet mesh we locate the coarse tet that contains it (libigl AABB +
``in_element``) and use its barycentric coordinates as interpolation weights: row ``i`` of ``P``
holds the four weights of fine node ``i``. ``P`` reproduces every linear function exactly at nodes
inside the coarse mesh and its rows sum to one, so constants are reproduced everywhere (hence the
Galerkin operator ``P^T A P`` keeps the constant null space of a Neumann problem). Restriction is
``P^T``.

Fine nodes outside every coarse tet (naive decimation, or TetWild's epsilon envelope on touching
cages) must be *extrapolated*. Four rules are offered (the Nested Cages paper, Sec. 7, tried the
last three for naive decimation):

``"clamped"`` (default)
    barycentric coordinates in the nearest coarse tet, clamped to >= 0 and renormalised;
``"linear"``
    unclamped barycentric coordinates in the nearest coarse tet (linear extrapolation);
``"closest_point"``
    barycentric coordinates of the closest point on the coarse boundary (a face: 3 weights);
``"nearest_vertex"``
    weight 1 on the nearest coarse node.

The nearest tet is the one owning the closest boundary face. Every rule keeps rows summing to 1.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import igl
import numpy as np
import scipy.sparse as sp

from solvers.fem import boundary_faces

from .errors import NestmgInputError

__all__ = ["EXTRAPOLATIONS", "ProlongationReport", "prolongation"]

EXTRAPOLATIONS = ("clamped", "linear", "closest_point", "nearest_vertex")


@dataclass
class ProlongationReport:
    """Figures of one prolongation ``P`` (fine level k from coarse level k+1).

    Attributes
    ----------
    n_fine, n_coarse : int
        Rows and columns of ``P``.
    n_outside : int
        Fine nodes outside every coarse tet (extrapolated), farther than ``on_boundary_tol`` x diagonal.
    n_on_boundary : int
        Nodes that point location missed but that lie on the coarse boundary up to round-off; they are
        interpolated at their closest boundary point (exact), not extrapolated.
    max_distance : float
        Largest distance of an outside node to the coarse mesh (0 when none).
    max_distance_rel : float
        ``max_distance`` divided by the fine mesh's bounding-box diagonal.
    extrapolation : str
        Rule used for the outside nodes.
    seconds : float
        Wall time of the construction.
    """

    n_fine: int
    n_coarse: int
    n_outside: int
    n_on_boundary: int
    max_distance: float
    max_distance_rel: float
    extrapolation: str
    seconds: float

    def to_dict(self) -> dict:
        """JSON-serialisable dictionary of the figures."""
        return asdict(self)


def _tet_barycentric(Q: np.ndarray, Vc: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (n,4) of points ``Q`` (n,3) in tets ``tets`` (n,4) of ``Vc``."""
    if len(Q) == 0:
        return np.zeros((0, 4))
    return igl.barycentric_coordinates(
        np.ascontiguousarray(Q, dtype=np.float64),
        np.ascontiguousarray(Vc[tets[:, 0]]),
        np.ascontiguousarray(Vc[tets[:, 1]]),
        np.ascontiguousarray(Vc[tets[:, 2]]),
        np.ascontiguousarray(Vc[tets[:, 3]]),
    )


def prolongation(
    Vf: np.ndarray,
    Vc: np.ndarray,
    Tc: np.ndarray,
    *,
    extrapolation: str = "clamped",
    on_boundary_tol: float = 1e-12,
) -> tuple[sp.csr_matrix, ProlongationReport]:
    """Barycentric prolongation from a coarse tet mesh to the nodes of a finer one.

    Parameters
    ----------
    Vf : (n_fine,3) float array
        Nodes of the finer tet mesh (level k).
    Vc : (n_coarse,3) float array
        Nodes of the coarser tet mesh (level k+1).
    Tc : (t,4) int array
        Tets of the coarser mesh.
    extrapolation : {"clamped", "linear", "closest_point", "nearest_vertex"}
        Rule for fine nodes outside every coarse tet (see the module docstring).
    on_boundary_tol : float
        Nodes within this distance (relative to the fine bounding-box diagonal) of the coarse mesh count
        as on its boundary, not outside.

    Returns
    -------
    P : (n_fine, n_coarse) scipy.sparse.csr_matrix
        Prolongation; rows sum to 1; restriction is ``P.T``.
    report : ProlongationReport
        ``n_outside`` and the largest distance of an outside node, among others.

    Examples
    --------
    >>> import numpy as np
    >>> Vc = np.array([[0., 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]); Tc = np.array([[0, 1, 2, 3]])
    >>> P, rep = prolongation(np.array([[0.25, 0.25, 0.25]]), Vc, Tc)
    >>> np.round(P.toarray(), 3).tolist(), rep.n_outside
    ([[0.25, 0.25, 0.25, 0.25]], 0)
    """
    import time

    t0 = time.perf_counter()
    if extrapolation not in EXTRAPOLATIONS:
        raise NestmgInputError(f"unknown extrapolation {extrapolation!r}; choose from {EXTRAPOLATIONS}")
    Vf = np.ascontiguousarray(Vf, dtype=np.float64)
    Vc = np.ascontiguousarray(Vc, dtype=np.float64)
    Tc = np.ascontiguousarray(Tc, dtype=np.int64)
    if Vf.ndim != 2 or Vf.shape[1] != 3 or Vc.ndim != 2 or Vc.shape[1] != 3:
        raise NestmgInputError("Vf and Vc must be (n,3) arrays")
    if Tc.ndim != 2 or Tc.shape[1] != 4 or len(Tc) == 0:
        raise NestmgInputError("Tc must be a non-empty (t,4) array of tets")
    if not (np.isfinite(Vf).all() and np.isfinite(Vc).all()):
        raise NestmgInputError("node coordinates contain NaN or inf")
    if Tc.min() < 0 or Tc.max() >= len(Vc):
        raise NestmgInputError("Tc indexes nodes outside Vc")
    nf, nc = len(Vf), len(Vc)

    tree = igl.AABB()
    tree.init(Vc, Tc)
    tet = igl.in_element(Vc, Tc, Vf, tree)
    inside = tet >= 0
    out = np.flatnonzero(~inside)

    rows = np.repeat(np.arange(nf), 4).reshape(nf, 4)
    cols = np.zeros((nf, 4), dtype=np.int64)
    W = np.zeros((nf, 4))
    ins = np.flatnonzero(inside)
    cols[ins] = Tc[tet[ins]]
    W[ins] = _tet_barycentric(Vf[ins], Vc, Tc[tet[ins]])

    max_d = 0.0
    n_on = 0
    diag = float(np.linalg.norm(Vf.max(axis=0) - Vf.min(axis=0))) if nf else 1.0
    if len(out):
        Fb, J = boundary_faces(Tc)
        d2, fi, C = igl.point_mesh_squared_distance(Vf[out], Vc, np.ascontiguousarray(Fb))
        # nodes on the coarse boundary up to round-off (a fine boundary node on a coarse boundary facet
        # that point location missed by ~1e-17) are located at their closest point, not extrapolated
        on = d2 <= (on_boundary_tol * diag) ** 2
        if on.any():
            on_idx = out[on]
            cols[on_idx] = Tc[J[fi[on]]]
            W[on_idx] = _tet_barycentric(C[on], Vc, Tc[J[fi[on]]])
            n_on = int(on.sum())
            out, d2, fi, C = out[~on], d2[~on], fi[~on], C[~on]
    if len(out):
        max_d = float(np.sqrt(d2.max()))
        near_tet = Tc[J[fi]]
        if extrapolation == "nearest_vertex":
            from scipy.spatial import cKDTree

            _, vi = cKDTree(Vc).query(Vf[out])
            cols[out] = vi[:, None]
            W[out] = np.array([1.0, 0.0, 0.0, 0.0])
        elif extrapolation == "closest_point":
            cols[out] = near_tet
            W[out] = _tet_barycentric(C, Vc, near_tet)
        else:
            cols[out] = near_tet
            w = _tet_barycentric(Vf[out], Vc, near_tet)
            if extrapolation == "clamped":
                w = np.maximum(w, 0.0)
                w /= w.sum(axis=1, keepdims=True)
            W[out] = w

    # Nodes on a coarse face/edge get round-off weights (~1e-17) on the opposite corners; left in, they
    # make coarse columns that are reached only by round-off, i.e. near-zero rows in P^T A P (a
    # near-singular coarse operator). Drop them and renormalise so rows still sum to 1.
    W[np.abs(W) < 1e-10] = 0.0
    W /= W.sum(axis=1, keepdims=True)
    P = sp.csr_matrix((W.ravel(), (rows.ravel(), cols.ravel())), shape=(nf, nc))
    P.eliminate_zeros()
    rep = ProlongationReport(
        n_fine=nf,
        n_coarse=nc,
        n_outside=len(out),
        n_on_boundary=n_on,
        max_distance=max_d,
        max_distance_rel=max_d / diag if diag > 0 else 0.0,
        extrapolation=extrapolation,
        seconds=time.perf_counter() - t0,
    )
    return P, rep
