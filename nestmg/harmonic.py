"""Harmonic coordinates of a cage (Joshi et al. 2007), one multigrid set-up for every cage vertex.

The harmonic coordinate ``w_j`` of cage vertex ``j`` solves Laplace's equation inside the cage with
Dirichlet data the piecewise-linear hat of vertex ``j`` on the cage surface (1 at ``j``, 0 at the other
vertices, linear on each triangle). A point ``x`` inside then moves with the cage as
``x' = Σ_j w_j(x) v'_j``; the weights sum to one (partition of unity) and reproduce ``x`` for the rest
cage (linear precision: ``Σ_j w_j(x) v_j = x``), because the Dirichlet data do and linear functions are
harmonic.

Discretisation (:func:`harmonic_coordinates`): a tet mesh of the cage's interior (the hierarchy's
coarsest level, TetWild's, whose boundary lies within ``epsilon`` of the cage) has its boundary nodes
moved to their closest points on the cage, where the hats are evaluated (barycentric coordinates in the
closest triangle). The mesh is then red-refined ``refine`` times (:func:`nestmg.refine.refine_tets`):
exactly nested levels with exact linear prolongations, which carry the boundary data to the new boundary
nodes (linear along boundary edges, so the data still reproduce the coordinates exactly) and serve as the
multigrid hierarchy. All ``n_cage`` Dirichlet problems share one operator: one
:class:`solvers.MultigridSolver` set-up, then :func:`solvers.multirhs.solve_many` runs MG-PCG on blocks of
right-hand sides (``solver="multigrid"``), or one sparse factorisation is reused (``solver="direct"``:
CHOLMOD when scikit-sparse is installed, SuperLU otherwise). Only the weights at the query points are
kept: the points are located in the finest tets (barycentric interpolation).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from .errors import NestmgInputError
from .prolongation import prolongation
from .refine import refine_tets
from .tetmesh import orient_tets, tet_volumes

__all__ = ["HarmonicCoordinates", "harmonic_coordinates", "hierarchy_harmonic_coordinates", "snap_boundary"]

SOLVERS = ("multigrid", "direct")


@dataclass
class HarmonicCoordinates:
    """Harmonic coordinates of a cage at a set of points.

    Attributes
    ----------
    W : (n_points, n_cage) float
        ``W[i, j]`` = coordinate of cage vertex ``j`` at point ``i``.
    cage_V : (n_cage, 3) float, cage_F : (m, 3) int
        The rest cage.
    points : (n_points, 3) float
        Where the coordinates were evaluated.
    info : dict
        Mesh sizes, seconds per stage, iterations, ``max_snap`` (largest boundary-node move).
    """

    W: np.ndarray
    cage_V: np.ndarray
    cage_F: np.ndarray
    points: np.ndarray
    info: dict = field(default_factory=dict)

    def deform(self, cage_V_new: np.ndarray) -> np.ndarray:
        """The points moved with the cage: ``W @ cage_V_new`` (n_points, 3)."""
        Vn = np.asarray(cage_V_new, dtype=np.float64)
        if Vn.shape != self.cage_V.shape:
            raise NestmgInputError(f"cage_V_new must have shape {self.cage_V.shape}, got {Vn.shape}")
        return self.W @ Vn

    def partition_of_unity_error(self) -> float:
        """``max_i |Σ_j W[i, j] - 1|``."""
        return float(np.abs(self.W.sum(axis=1) - 1.0).max())

    def linear_precision_error(self) -> float:
        """``max_i |Σ_j W[i, j] v_j - x_i|`` relative to the cage's bounding-box diagonal."""
        diag = float(np.linalg.norm(self.cage_V.max(axis=0) - self.cage_V.min(axis=0)))
        return float(np.linalg.norm(self.W @ self.cage_V - self.points, axis=1).max() / diag)


def _triangle_barycentric(X: np.ndarray, A: np.ndarray, B: np.ndarray, C: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (n, 3) of points ``X`` lying on triangles ``ABC`` (rows), clipped to >= 0."""
    e0, e1, d = B - A, C - A, X - A
    d00, d01, d11 = (e0 * e0).sum(1), (e0 * e1).sum(1), (e1 * e1).sum(1)
    d20, d21 = (d * e0).sum(1), (d * e1).sum(1)
    den = d00 * d11 - d01 * d01
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    L = np.maximum(np.column_stack([1.0 - v - w, v, w]), 0.0)  # closest points are on the triangle
    return L / L.sum(axis=1, keepdims=True)


def snap_boundary(V: np.ndarray, T: np.ndarray, cage_V: np.ndarray, cage_F: np.ndarray):
    """Move a tet mesh's boundary nodes to their closest points on the cage; hats there.

    Parameters
    ----------
    V : (n, 3) float, T : (t, 4) int
        Tet mesh of the cage's interior (boundary within a small envelope of the cage).
    cage_V : (c, 3) float, cage_F : (m, 3) int

    Returns
    -------
    V_snapped : (n, 3) float
    T : (t, 4) int
        ``T`` positively oriented.
    bnd : (b,) int
        Boundary nodes.
    G : (b, c) csr_matrix
        Hat values of every cage vertex at the snapped boundary nodes (rows sum to 1).
    max_move : float
        Largest distance a node moved.

    Raises
    ------
    NestmgInputError
        When moving the nodes inverts or flattens a tet (mesh the cage with a smaller envelope).
    """
    import igl

    from solvers.fem import boundary_nodes

    V = np.asarray(V, dtype=np.float64)
    cage_V = np.ascontiguousarray(cage_V, dtype=np.float64)
    cage_F = np.ascontiguousarray(cage_F, dtype=np.int64)
    T = orient_tets(V, np.asarray(T, dtype=np.int64))
    bnd = boundary_nodes(T, n=len(V))
    d2, fi, C = igl.point_mesh_squared_distance(V[bnd], cage_V, cage_F)
    tri = cage_F[fi]
    L = _triangle_barycentric(C, *(cage_V[tri[:, k]] for k in range(3)))
    Vs = V.copy()
    Vs[bnd] = L[:, 0:1] * cage_V[tri[:, 0]] + L[:, 1:2] * cage_V[tri[:, 1]] + L[:, 2:3] * cage_V[tri[:, 2]]
    vol0, vol1 = tet_volumes(V, T), tet_volumes(Vs, T)
    bad = np.count_nonzero(vol1 <= 1e-3 * vol0)
    if bad:
        raise NestmgInputError(f"moving the boundary nodes onto the cage flattens or inverts {bad} tets; "
                               "mesh the "
                               "cage's interior with a smaller envelope (epsilon)")
    rows = np.repeat(np.arange(len(bnd)), 3)
    G = sp.csr_matrix((L.ravel(), (rows, tri.ravel())), shape=(len(bnd), len(cage_V)))
    return Vs, T, bnd, G, float(np.sqrt(d2.max())) if len(d2) else 0.0


def _refined_levels(V, T, refine: int):
    """``refine`` red refinements: meshes and exact prolongations, finest first."""
    meshes, Ps = [(V, T)], []
    for _ in range(refine):
        V, T, P = refine_tets(V, T)
        meshes.insert(0, (V, T))
        Ps.insert(0, P)
    return meshes, Ps


def _dirichlet_system(meshes, Ps, G_c, bnd_c):
    """Interior operator, boundary data at the finest boundary nodes, and the index sets."""
    from solvers.fem import boundary_nodes, stiffness_matrix

    Vf, Tf = meshes[0]
    n = len(Vf)
    Ptot = sp.identity(n, format="csr")
    for P in Ps:
        Ptot = Ptot @ P
    bnd = boundary_nodes(Tf, n=n)
    interior = np.setdiff1d(np.arange(n), bnd, assume_unique=True)
    Pb = sp.csr_matrix(Ptot[bnd][:, bnd_c])
    if np.abs(np.asarray(Pb.sum(axis=1)).ravel() - 1.0).max() > 1e-12:  # boundary nodes from boundary ones
        raise NestmgInputError("refined boundary nodes are not interpolated from coarse boundary nodes")
    G = sp.csr_matrix(Pb @ G_c)  # hats at the finest boundary nodes (linear along boundary edges)
    K = stiffness_matrix(Vf, Tf).tocsr()
    A = K[interior][:, interior].tocsr()
    K_ib = K[interior][:, bnd].tocsr()
    return A, K_ib, G, interior, bnd


def _block_solver(A, Ps, interior, solver: str, tol: float, maxiter: int, chunk: int):
    """``solve(R) -> X`` for blocks of right-hand sides, set up once, and its set-up seconds."""
    t0 = time.perf_counter()
    if solver == "multigrid":
        from solvers import MultigridSolver, SolverError, restrict_prolongations
        from solvers.multilevel import DEFAULT_DEFLATE
        from solvers.multirhs import MULTI_RHS_SMOOTHER, solve_many

        Pf, _ = restrict_prolongations(Ps, interior)
        ml = MultigridSolver(A, Pf, presmoother=MULTI_RHS_SMOOTHER, deflate=DEFAULT_DEFLATE)
        its: list = []

        def solve(R):
            X, info = solve_many(ml, R, tol=tol, maxiter=maxiter, chunk=chunk, return_info=True)
            if not info["converged"]:
                raise SolverError(f"harmonic coordinates: MG-PCG did not reach tol={tol:g} in {maxiter} "
                                  "iterations")
            its.extend(info["iterations"].tolist())
            return X

        return solve, time.perf_counter() - t0, {"iterations": its, "backend": "nestmg MG-PCG"}
    from solvers.baselines import cholmod_available

    if cholmod_available():
        from sksparse.cholmod import cholesky

        fac = cholesky(sp.csc_matrix(A))
        return fac, time.perf_counter() - t0, {"backend": "CHOLMOD", "factor_nnz": int(fac.L().nnz)}
    from solvers.coarse import sparse_lu

    lu = sparse_lu(A, symmetric=True)
    return lu.solve, time.perf_counter() - t0, {"backend": "SuperLU", "factor_nnz": int(lu.L.nnz + lu.U.nnz)}


def harmonic_coordinates(
    cage_V: np.ndarray,
    cage_F: np.ndarray,
    points: np.ndarray,
    tets: tuple[np.ndarray, np.ndarray],
    *,
    refine: int = 2,
    solver: str = "multigrid",
    tol: float = 1e-10,
    maxiter: int = 100,
    chunk: int = 64,
) -> HarmonicCoordinates:
    """Harmonic coordinates of the cage ``(cage_V, cage_F)`` at ``points`` (see the module docstring).

    Parameters
    ----------
    cage_V : (c, 3) float, cage_F : (m, 3) int
        Closed, outward-oriented cage.
    points : (p, 3) float
        Points inside the cage (e.g. the input's vertices); points outside the meshed interior get the
        coordinates of the nearest tet's clamped barycentric extrapolation (``info["n_outside"]``).
    tets : ((n, 3) float, (t, 4) int)
        Tet mesh of the cage's interior, boundary within a small envelope of the cage (the hierarchy's
        coarsest level: ``Hierarchy.tets[-1]``).
    refine : int
        Red refinements of ``tets`` (each 8x the tets); ``refine + 1`` multigrid levels.
    solver : {"multigrid", "direct"}
        Block MG-PCG with one set-up, or one factorisation (CHOLMOD if installed, else SuperLU).
    tol : float
        Relative residual per right-hand side (multigrid).
    maxiter : int
    chunk : int
        Right-hand sides per block (memory: a few ``(n, chunk)`` arrays).

    Returns
    -------
    HarmonicCoordinates
    """
    if solver not in SOLVERS:
        raise NestmgInputError(f"solver must be one of {SOLVERS}, got {solver!r}")
    if int(refine) < 0 or (solver == "multigrid" and int(refine) < 1):
        raise NestmgInputError(f"refine must be >= 1 for the multigrid solver (>= 0 otherwise), got {refine}")
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or not np.isfinite(points).all():
        raise NestmgInputError(f"points must be a finite (p, 3) array, got shape {points.shape}")
    cage_V = np.asarray(cage_V, dtype=np.float64)
    t0 = time.perf_counter()
    Vs, Ts, bnd_c, G_c, max_move = snap_boundary(*tets, cage_V, cage_F)
    meshes, Ps = _refined_levels(Vs, Ts, int(refine))
    A, K_ib, G, interior, bnd = _dirichlet_system(meshes, Ps, G_c, bnd_c)
    S, rep = prolongation(points, *meshes[0])
    S_i, S_b = S[:, interior].tocsr(), S[:, bnd].tocsr()
    t1 = time.perf_counter()
    solve, setup_s, extra = _block_solver(A, Ps, interior, solver, tol, maxiter, chunk)
    t2 = time.perf_counter()
    W = np.asarray((S_b @ G).todense())  # boundary part of the interpolation
    for s in range(0, len(cage_V), int(chunk)):
        cols = slice(s, min(s + int(chunk), len(cage_V)))
        R = -np.asarray((K_ib @ G[:, cols]).todense())  # A X = -K_ib g: the Dirichlet data moved right
        W[:, cols] += S_i @ solve(R)
    t3 = time.perf_counter()
    info = {"nodes": len(meshes[0][0]), "tets": len(meshes[0][1]), "unknowns": int(A.shape[0]),
            "coarse_nodes": len(Vs), "coarse_tets": len(Ts), "levels": int(refine) + 1, "solver": solver,
            "max_snap": max_move, "n_outside": rep.n_outside, "seconds_mesh": t1 - t0,
            "seconds_setup": setup_s, "seconds_solve": t3 - t2, **extra}
    return HarmonicCoordinates(W, cage_V, np.asarray(cage_F, dtype=np.int64), points, info)


def hierarchy_harmonic_coordinates(h, points: np.ndarray | None = None, **kwargs) -> HarmonicCoordinates:
    """Harmonic coordinates of a hierarchy's coarsest cage at the input's vertices (or ``points``).

    Parameters
    ----------
    h : nestmg.Hierarchy
        Its coarsest surface is the cage, its coarsest tet level the cage's interior.
    points : (p, 3) float, optional
        In the input's frame; default the input surface's vertices ``h.surfaces[0][0]``.
    **kwargs
        Passed to :func:`harmonic_coordinates`.

    Returns
    -------
    HarmonicCoordinates
        In the input's frame (the coordinates themselves are invariant under the normalisation: they are
        affine invariant), so ``deform`` takes cage positions in the input's frame.
    """
    Vc, Fc = h.surfaces_in("normalized")[-1]
    tets = h.tets_in("normalized")[-1]
    pts = h.surfaces[0][0] if points is None else points
    hc = harmonic_coordinates(Vc, Fc, h.to_normalized(pts), tets, **kwargs)
    return HarmonicCoordinates(hc.W, h.surfaces[-1][0].astype(np.float64), hc.cage_F,
                               np.asarray(pts, dtype=np.float64), hc.info)
