"""Model problems on a hierarchy: the FEM systems and the level data handed to the multigrid solver.

Problems (P1 FEM on the fine tet mesh, ``K`` stiffness, ``M`` lumped mass, Nested Cages paper Sec. 7):

``poisson-dirichlet``
    ``-Δu = f`` in the solid, ``u = 0`` on its boundary: ``K_ff u_f = (M f)_f``.
``poisson-neumann``
    ``-Δu = f`` with ``∂u/∂n = 0``: ``K u = M f`` with ``f`` of zero mean (compatibility), constant
    null space on every level, solution normalised to zero mean.
``diffusion-neumann``
    one implicit diffusion step ``(λK + M) u = M f`` (natural boundary), λ = ``lam``.

Coarse levels. With ``coarse="galerkin"`` the solver forms ``P^T A P``; the prolongations are only
restricted to the free fine nodes (Dirichlet) and to the coarse nodes they actually reach (zero
columns would make the coarse operator singular). With ``coarse="rediscretized"`` every coarse tet
mesh gets its own FEM operator of the same problem, Dirichlet conditions on the *coarse* boundary for
``poisson-dirichlet`` (coarse functions vanish on the cage, which lies outside the fine domain when
the hierarchy is nested).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from solvers.fem import boundary_nodes, mass_matrix, stiffness_matrix

__all__ = ["PROBLEMS", "Problem", "default_rhs", "setup_problem"]

PROBLEMS = ("poisson-dirichlet", "poisson-neumann", "diffusion-neumann")


@dataclass
class Problem:
    """A linear system on level 0 plus the per-level data of its multigrid hierarchy.

    Attributes
    ----------
    name : str
    A : (n_free, n_free) csr_matrix
        Fine operator on the free nodes.
    b : (n_free,) float array
        Right-hand side (compatible for Neumann problems).
    P : list of csr_matrix
        Prolongations restricted to the free nodes of consecutive levels.
    coarse_ops : list of csr_matrix or None
        Re-discretised coarse operators (None: Galerkin).
    free : list of int arrays
        Free node indices on every level.
    n_fine : int
        Number of fine nodes (for :meth:`expand`).
    nullspace : str or None
        ``"constant"`` for pure Neumann problems.
    params : dict
    """

    name: str
    A: sp.csr_matrix
    b: np.ndarray
    P: list
    coarse_ops: list | None
    free: list
    n_fine: int
    nullspace: str | None
    params: dict = field(default_factory=dict)

    def expand(self, x_free: np.ndarray) -> np.ndarray:
        """Full fine-level vector: ``x_free`` on free nodes, 0 on Dirichlet nodes."""
        x = np.zeros(self.n_fine)
        x[self.free[0]] = x_free
        return x


def default_rhs(V: np.ndarray) -> np.ndarray:
    """A smooth, non-symmetric source ``f(x) = 1 + sin(3x) cos(2y) + z`` on the nodes ``V`` (n,3)."""
    return 1.0 + np.sin(3 * V[:, 0]) * np.cos(2 * V[:, 1]) + V[:, 2]


def _level_operator(name: str, V: np.ndarray, T: np.ndarray, lam: float) -> sp.csr_matrix:
    K = stiffness_matrix(V, T)
    if name == "diffusion-neumann":
        return (lam * K + mass_matrix(V, T)).tocsr()
    return K


def _prune(rows: sp.csr_matrix, reach: np.ndarray, tau: float) -> np.ndarray:
    """Coarse columns kept for a Galerkin level: those reached with total weight >= ``tau``.

    A cage node that only one or two fine nodes reach (weights ~1e-3) adds nothing to the coarse space
    but makes ``P`` rank-deficient, i.e. ``P^T A P`` singular beyond its true null space. A weak
    column is kept anyway when some fine row has all its weight on weak columns.
    """
    if tau <= 0:
        return reach
    cs = np.asarray(rows.sum(axis=0)).ravel()
    weak = np.zeros(rows.shape[1], dtype=bool)
    weak[reach] = cs[reach] < tau
    strong_sum = np.asarray(rows[:, ~weak].sum(axis=1)).ravel()
    orphan_rows = np.flatnonzero(strong_sum <= 0)
    if orphan_rows.size:
        weak[np.unique(rows[orphan_rows].indices)] = False
    return reach[~weak[reach]]


def setup_problem(
    tets: list[tuple[np.ndarray, np.ndarray]],
    P: list[sp.csr_matrix],
    name: str = "poisson-dirichlet",
    *,
    coarse: str = "galerkin",
    lam: float = 1e-2,
    f: np.ndarray | None = None,
    prune: float = 0.2,
) -> Problem:
    """Assemble a model problem on ``tets[0]`` and the level data for multigrid.

    Parameters
    ----------
    tets : list of (V, T)
        Tet meshes, finest first (``Hierarchy.tets``).
    P : list of (n_k, n_{k+1}) csr_matrix
        Prolongations (``Hierarchy.P``).
    name : {"poisson-dirichlet", "poisson-neumann", "diffusion-neumann"}
    coarse : {"galerkin", "rediscretized"}
    lam : float
        Diffusion coefficient λ of ``diffusion-neumann`` (time step x conductivity).
    f : (n_fine,) float array, optional
        Source at the fine nodes (default :func:`default_rhs`). For ``poisson-neumann`` its
        mass-weighted mean is removed so that the system is compatible.
    prune : float
        Galerkin only: drop coarse nodes whose prolongation column sums to less than this (nodes of a
        cage that barely reach the fine mesh; they make ``P`` rank-deficient) and rescale the affected
        rows to sum to 1. 0 keeps every reached node.

    Returns
    -------
    Problem
    """
    if name not in PROBLEMS:
        raise ValueError(f"unknown problem {name!r}; choose from {PROBLEMS}")
    if coarse not in ("galerkin", "rediscretized"):
        raise ValueError(f"coarse must be 'galerkin' or 'rediscretized', got {coarse!r}")
    if len(P) != len(tets) - 1:
        raise ValueError(f"need len(P) == len(tets) - 1, got {len(P)} and {len(tets)}")
    V0, T0 = tets[0]
    n0 = len(V0)
    M0 = mass_matrix(V0, T0)
    f = default_rhs(V0) if f is None else np.asarray(f, dtype=np.float64)
    if f.shape != (n0,):
        raise ValueError(f"f must have shape ({n0},), got {f.shape}")
    m = M0.diagonal()
    if name == "poisson-neumann":
        f = f - (m @ f) / m.sum()  # zero mass-weighted mean -> sum(M f) = 0
    A_full = _level_operator(name, V0, T0, lam)
    b_full = M0 @ f
    dirichlet = name == "poisson-dirichlet"

    free = [np.setdiff1d(np.arange(n0), boundary_nodes(T0)) if dirichlet else np.arange(n0)]
    Pr: list[sp.csr_matrix] = []
    ops: list[sp.csr_matrix] = []
    for k, Pk in enumerate(P):
        Vc, Tc = tets[k + 1]
        rows = Pk.tocsr()[free[k]]
        reach = np.flatnonzero(np.asarray(abs(rows).sum(axis=0)).ravel() > 0)
        if coarse == "rediscretized":
            Ac = _level_operator(name, Vc, Tc, lam)
            cols = np.setdiff1d(np.arange(len(Vc)), boundary_nodes(Tc)) if dirichlet else np.arange(len(Vc))
            if dirichlet:
                cols = np.intersect1d(cols, reach)
            ops.append(Ac[cols][:, cols].tocsr())
        else:
            cols = _prune(rows, reach, prune)
        free.append(cols)
        Pk_r = rows[:, cols].tocsr()
        if coarse == "galerkin" and prune > 0:
            # rows that lost weight to pruned columns are rescaled to sum to 1 again (constants stay exact)
            rs = np.asarray(Pk_r.sum(axis=1)).ravel()
            Pk_r = sp.csr_matrix(sp.diags(1.0 / rs) @ Pk_r)
        Pr.append(Pk_r)
    A = A_full[free[0]][:, free[0]].tocsr()
    return Problem(
        name=name,
        A=A,
        b=np.asarray(b_full[free[0]]),
        P=Pr,
        coarse_ops=ops if coarse == "rediscretized" else None,
        free=free,
        n_fine=n0,
        nullspace="constant" if name == "poisson-neumann" else None,
        params={"lam": lam if name == "diffusion-neumann" else None, "coarse": coarse, "prune": prune},
    )
