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

import numpy as np
import scipy.sparse as sp

from solvers.locate import clean_weights, locate_in_tets, tet_barycentric

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

    Raises
    ------
    NestmgInputError
        For an unknown ``extrapolation``.
    solvers.SolverInputError
        For arrays of the wrong shape, NaN/inf coordinates or tets indexing missing nodes (checked by
        :func:`solvers.locate.locate_in_tets`; both errors are ``NestmgError`` and ``ValueError``).

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
    # the shapes, finiteness and indices of Vf, Vc, Tc are checked by locate_in_tets (SolverInputError);
    # the tolerance's diagonal is Vf's, its default
    loc = locate_in_tets(Vf, Vc, Tc, on_boundary_tol=on_boundary_tol)
    nf, nc = len(Vf), len(Vc)
    diag = float(np.linalg.norm(Vf.max(axis=0) - Vf.min(axis=0))) if nf else 1.0
    rows = np.repeat(np.arange(nf), 4).reshape(nf, 4)
    cols, W, out = loc.cols, loc.weights, loc.outside
    n_on = loc.n_on_boundary
    max_d = float(np.sqrt(loc.distance2.max())) if len(out) else 0.0
    if len(out):
        # loc gives the nearest tet (owning the closest boundary face) and unclamped coordinates there
        if extrapolation == "nearest_vertex":
            from scipy.spatial import cKDTree

            _, vi = cKDTree(Vc).query(Vf[out])
            cols[out] = vi[:, None]
            W[out] = np.array([1.0, 0.0, 0.0, 0.0])
        elif extrapolation == "closest_point":
            W[out] = tet_barycentric(loc.closest, Vc, cols[out])
        elif extrapolation == "clamped":
            w = np.maximum(W[out], 0.0)
            W[out] = w / w.sum(axis=1, keepdims=True)
    clean_weights(W)
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
