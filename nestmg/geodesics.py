"""Smooth geodesic distance inside a solid by the heat method (Crane, Weischedel & Wardetzky 2013).

On a P1 tet mesh with stiffness ``K``, lumped mass ``M`` and time step ``t`` (default: the squared
mean edge length, the paper's choice ``t = h^2``) the distance from a set of source nodes is found
with two sparse solves:

1. **heat step** ``(M + t K) u = δ`` (natural boundary), ``δ`` = unit impulse at every source node;
2. the normalised, reversed heat gradient ``X = -∇u / |∇u|`` (one vector per tet);
3. **Poisson step** ``K φ = b`` with ``b_i = Σ_T |T| ∇λ_i · X_T`` (pure Neumann; ``Σ b_i = 0``
   exactly, because the barycentric gradients of a tet sum to zero), i.e. ``φ`` is the least-squares
   fit ``min ∫ |∇φ - X|²``;
4. ``φ`` is shifted so that its smallest value over the sources is 0.

Both systems are the ones multigrid is tested on elsewhere (``diffusion-neumann`` with ``λ = t`` and
``poisson-neumann``), so any solver fits: :func:`heat_geodesic` takes a ``solve(A, b, kind)`` callable
(default: a sparse direct solve); :func:`multigrid_solve` makes one from a multigrid hierarchy.

Inside a convex solid the geodesic distance is the straight-line distance, which the tests use as
the reference.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from solvers.fem import check_tet_mesh, mass_matrix, stiffness_matrix
from solvers.multilevel import DEFAULT_DEFLATE, DEFAULT_MAXITER

from .errors import NestmgInputError

__all__ = [
    "GeodesicInputError",
    "HeatGeodesicResult",
    "HeatPrecompute",
    "direct_solve",
    "divergence_rhs",
    "gradient_operator",
    "heat_geodesic",
    "heat_precompute",
    "multigrid_solve",
]

#: ``solve(A, b, kind) -> (x, info)`` with ``kind`` in {"heat", "poisson"}; ``info`` is a dict.
SolveFn = Callable[[sp.csr_matrix, np.ndarray, str], tuple[np.ndarray, dict]]


class GeodesicInputError(NestmgInputError):
    """Bad input to the heat method (mesh, sources or time step)."""


def gradient_operator(V: np.ndarray, T: np.ndarray) -> tuple[sp.csr_matrix, np.ndarray]:
    """Per-tet gradient of P1 functions.

    Parameters
    ----------
    V : (n,3) float array
    T : (t,4) int array

    Returns
    -------
    G : (3t, n) csr_matrix
        ``(G @ u).reshape(t, 3)[j]`` is the (constant) gradient of the P1 interpolant of ``u`` (n,) in
        tet ``j``.
    vol : (t,) float array
        Unsigned tet volumes.
    """
    V, T = check_tet_mesh(V, T)
    P = V[T]  # (t,4,3)
    J = (P[:, 1:] - P[:, :1]).transpose(0, 2, 1)  # columns p_k - p_0, (t,3,3)
    det = np.linalg.det(J)
    Jinv = np.linalg.inv(J)  # rows: gradients of λ_1..λ_3
    grads = np.concatenate([-Jinv.sum(axis=1, keepdims=True), Jinv], axis=1)  # (t,4,3): ∇λ_i
    t = len(T)
    rows = (3 * np.arange(t)[:, None, None] + np.arange(3)[None, None, :]).repeat(4, axis=1)  # (t,4,3)
    cols = np.broadcast_to(T[:, :, None], (t, 4, 3))
    G = sp.csr_matrix((grads.ravel(), (rows.ravel(), cols.ravel())), shape=(3 * t, len(V)))
    return G, np.abs(det) / 6.0


@dataclass
class HeatPrecompute:
    """Matrices of the heat method on one tet mesh (reused for every source set).

    Attributes
    ----------
    K : (n,n) csr_matrix
        P1 stiffness.
    M : (n,n) csr_matrix
        Lumped (barycentric) mass.
    G : (3t,n) csr_matrix
        Per-tet gradient (:func:`gradient_operator`).
    vol : (t,) float array
        Tet volumes.
    t : float
        Time step.
    A_heat : (n,n) csr_matrix
        ``M + t K``.
    """

    K: sp.csr_matrix
    M: sp.csr_matrix
    G: sp.csr_matrix
    vol: np.ndarray
    t: float
    A_heat: sp.csr_matrix = field(repr=False)


def heat_precompute(V: np.ndarray, T: np.ndarray, t: float | None = None, t_factor: float = 1.0) -> HeatPrecompute:
    """Assemble the heat-method matrices of the tet mesh ``(V, T)``.

    Parameters
    ----------
    V : (n,3) float array
    T : (t,4) int array
    t : float, optional
        Time step; default ``t_factor * h^2`` with ``h`` the mean tet edge length.
    t_factor : float
        Multiplier of the default time step (larger = smoother distance).

    Returns
    -------
    HeatPrecompute

    Raises
    ------
    GeodesicInputError
        Non-positive or non-finite time step.
    solvers.SolverInputError
        Malformed tet mesh.
    """
    V, T = check_tet_mesh(V, T)
    if t is None:
        E = np.concatenate([T[:, [i, j]] for i, j in ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))])
        E = np.unique(np.sort(E, axis=1), axis=0)
        h = float(np.linalg.norm(V[E[:, 0]] - V[E[:, 1]], axis=1).mean())
        t = t_factor * h * h
    t = float(t)
    if not np.isfinite(t) or t <= 0:
        raise GeodesicInputError(f"time step t must be positive and finite, got {t}")
    K = stiffness_matrix(V, T)
    M = mass_matrix(V, T)
    G, vol = gradient_operator(V, T)
    return HeatPrecompute(K=K, M=M, G=G, vol=vol, t=t, A_heat=(M + t * K).tocsr())


def divergence_rhs(pre: HeatPrecompute, u: np.ndarray) -> np.ndarray:
    """Right-hand side ``b`` (n,) of the Poisson step from the heat solution ``u`` (n,).

    ``b_i = Σ_T |T| ∇λ_i · X_T`` with ``X = -∇u/|∇u|`` (tets where ``∇u = 0`` get ``X = 0``).
    ``sum(b) = 0`` up to round-off.
    """
    g = (pre.G @ u).reshape(-1, 3)
    norm = np.linalg.norm(g, axis=1)
    X = np.zeros_like(g)
    nz = norm > 0
    X[nz] = -g[nz] / norm[nz, None]
    b = pre.G.T @ (X * pre.vol[:, None]).ravel()
    return b - b.mean()  # remove the round-off incompatibility


def _check_sources(sources, n: int) -> np.ndarray:
    s = np.asarray(sources)
    if s.ndim == 0:
        s = s.reshape(1)
    if s.ndim != 1 or s.size == 0:
        raise GeodesicInputError(f"sources must be a non-empty 1-D array of node indices, got shape {s.shape}")
    if not np.issubdtype(s.dtype, np.integer):
        raise GeodesicInputError(f"sources must be integer node indices, got dtype {s.dtype}")
    if s.min() < 0 or s.max() >= n:
        raise GeodesicInputError(f"source indices must be in [0, {n}), got range [{s.min()}, {s.max()}]")
    return np.unique(s.astype(np.int64))


def direct_solve(A: sp.csr_matrix, b: np.ndarray, kind: str) -> tuple[np.ndarray, dict]:
    """Sparse direct solve of the heat (``kind="heat"``) or singular Poisson (``"poisson"``) step.

    The Poisson matrix has the constants as null space: one node is pinned to 0 (the result is shifted
    afterwards anyway).
    """
    from solvers.coarse import sparse_lu

    if kind == "poisson":
        keep = np.arange(1, A.shape[0])
        x = np.zeros(A.shape[0])
        x[keep] = sparse_lu(A[keep][:, keep]).solve(b[keep])
    else:
        x = sparse_lu(A).solve(b)
    return x, {"solver": "splu"}


def multigrid_solve(
    tets: list[tuple[np.ndarray, np.ndarray]],
    P: list[sp.csr_matrix],
    *,
    t: float,
    coarse: str = "galerkin",
    nu: int = 1,
    cycle: str = "V",
    accel: str | None = "cg",
    tol: float = 1e-10,
    maxiter: int = DEFAULT_MAXITER,
) -> SolveFn:
    """A ``solve(A, b, kind)`` for :func:`heat_geodesic` by geometric multigrid on a hierarchy.

    Parameters
    ----------
    tets : list of (V, T)
        Tet layers, finest first (``Hierarchy.tets``); ``tets[0]`` must be the mesh of the problem.
    P : list of (n_k, n_{k+1}) csr_matrix
        Prolongations (``Hierarchy.P``).
    t : float
        The heat step's time step (``HeatPrecompute.t``): re-discretised coarse heat operators are
        ``M_k + t K_k``.
    coarse : {"galerkin", "rediscretized"}
    nu : int
        Symmetric Gauss–Seidel sweeps before and after the coarse correction on the fine level:
        V(nu, nu); ``2 nu`` on coarser levels and one extra local sweep on the boundary layer (the
        pipeline's cycle before ``MultigridSolver``'s default became its default: kept here, where the
        geodesics' accuracy was measured with it).
    cycle, accel, tol, maxiter
        See :meth:`solvers.MultigridSolver.solve`.

    Returns
    -------
    callable
        ``solve(A, b, kind) -> (x, info)``; ``info`` has ``iterations``, ``converged``, ``residuals``
        and ``factor``. A diverging cycle raises :class:`solvers.DivergenceError`.
    """
    from solvers import MultigridSolver

    from .problems import cycle_smoothers, setup_problem

    if coarse not in ("galerkin", "rediscretized"):
        raise GeodesicInputError(f"coarse must be 'galerkin' or 'rediscretized', got {coarse!r}")
    n0 = len(tets[0][0])

    solvers_by_kind: dict = {}  # kind -> (A, MultigridSolver): set up once per operator, reused per source

    def solve(A: sp.csr_matrix, b: np.ndarray, kind: str) -> tuple[np.ndarray, dict]:
        hit = solvers_by_kind.get(kind)
        if hit is not None and hit[0] is A:
            x, info = hit[1].solve(b, tol=tol, maxiter=maxiter, cycle=cycle, accel=accel, return_info=True)
            return x, {k: info[k] for k in ("iterations", "converged", "residuals", "factor")}
        name = "diffusion-neumann" if kind == "heat" else "poisson-neumann"
        prob = setup_problem(tets, P, name, coarse=coarse, lam=t, prune=0.0 if kind == "heat" else 0.5)
        if prob.A.shape != A.shape or prob.free[0].size != n0:
            raise GeodesicInputError("the hierarchy's finest tet mesh is not the mesh of the problem")
        ml = MultigridSolver(A, prob.P, coarse=prob.coarse,
                             presmoother=cycle_smoothers("symmetric_gauss_seidel", nu),
                             local_nodes=prob.local_nodes, deflate=DEFAULT_DEFLATE,
                             nullspace="constant" if kind == "poisson" else None)
        solvers_by_kind[kind] = (A, ml)
        x, info = ml.solve(b, tol=tol, maxiter=maxiter, cycle=cycle, accel=accel, return_info=True)
        return x, {k: info[k] for k in ("iterations", "converged", "residuals", "factor")}

    return solve


@dataclass
class HeatGeodesicResult:
    """Output of :func:`heat_geodesic`.

    Attributes
    ----------
    distance : (n,) float array
        Approximate geodesic distance (0 at the closest source, >= 0 up to discretisation error).
    heat : (n,) float array
        Heat-step solution ``u``.
    t : float
        Time step used.
    info : dict
        ``{"heat": ..., "poisson": ...}``: the solver's info dict for each step.
    """

    distance: np.ndarray
    heat: np.ndarray
    t: float
    info: dict


def heat_geodesic(
    V: np.ndarray,
    T: np.ndarray,
    sources,
    *,
    t: float | None = None,
    t_factor: float = 1.0,
    solve: SolveFn | None = None,
    pre: HeatPrecompute | None = None,
) -> HeatGeodesicResult:
    """Geodesic distance inside the solid ``(V, T)`` from ``sources`` by the heat method.

    Parameters
    ----------
    V : (n,3) float array
    T : (t,4) int array
    sources : int or (s,) int array
        Source node indices.
    t, t_factor
        Time step (see :func:`heat_precompute`); ignored when ``pre`` is given.
    solve : callable, optional
        ``solve(A, b, kind) -> (x, info)`` for ``kind`` in {"heat", "poisson"} (default
        :func:`direct_solve`; :func:`multigrid_solve` builds a multigrid one).
    pre : HeatPrecompute, optional
        Reuse the matrices of an earlier call on the same mesh.

    Returns
    -------
    HeatGeodesicResult

    Raises
    ------
    GeodesicInputError
        Empty, non-integer or out-of-range sources; bad time step.
    solvers.SolverInputError
        Malformed tet mesh.

    Examples
    --------
    >>> from solvers.gallery import kuhn_cube_mesh
    >>> V, T = kuhn_cube_mesh(6)
    >>> d = heat_geodesic(V, T, 0).distance   # node 0 is a corner of the unit cube
    >>> bool(abs(d.max() - 3 ** 0.5) < 0.2)
    True
    """
    if pre is None:
        pre = heat_precompute(V, T, t=t, t_factor=t_factor)
    n = pre.K.shape[0]
    src = _check_sources(sources, n)
    solve = direct_solve if solve is None else solve
    delta = np.zeros(n)
    delta[src] = 1.0
    u, info_h = solve(pre.A_heat, delta, "heat")
    b = divergence_rhs(pre, u)
    phi, info_p = solve(pre.K, b, "poisson")
    phi = phi - phi[src].min()
    return HeatGeodesicResult(distance=phi, heat=u, t=pre.t, info={"heat": info_h, "poisson": info_p})
