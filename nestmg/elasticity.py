"""Linear elasticity model problems on a hierarchy (issue 32): the FEM system and the multigrid data.

Problems (P1 vector elements on the fine tet mesh, isotropic material ``E``, ``ν``; unknowns interleaved
per node, ``[x_0, y_0, z_0, x_1, ...]``, :mod:`solvers.elasticity`):

``elasticity-clamped``
    The boundary nodes within ``band`` (fraction of the extent) of the lowest ``x`` are fixed,
    ``u = 0``; gravity ``ρ g = (0, 0, -1)`` acts on the solid: ``b_a = m_a g`` with the lumped mass
    ``m_a = ∫ φ_a`` (exact for a constant body force). Symmetric positive definite.
``elasticity-free``
    Pure traction (no node fixed) under a smooth body force ``f`` balanced against the rigid motions:
    ``f <- f - Z c`` with ``c = (Zᵀ M Z)⁻¹ Zᵀ M f`` (the load seen in the body's accelerating frame), so
    ``Zᵀ b = 0`` for the six rigid-body modes ``Z``; the operator is singular with kernel ``span Z``
    on every level (:class:`solvers.elasticity.NullspaceMultigridSolver`), the solution is returned
    orthogonal to it.

Levels: the hierarchy's nodal prolongations restricted to the free nodes become ``P ⊗ I₃``
(:func:`solvers.elasticity.block_prolongation`), the coarse operators are Galerkin products. The free
problem keeps every reached coarse node (``prune=0``): pruning rescales rows, which breaks the exact
reproduction of linear fields that keeps the rigid modes in every coarse kernel.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp

from solvers.elasticity import (
    NullspaceMultigridSolver,
    block_dofs,
    block_prolongation,
    elasticity_matrix,
    galerkin_nullspaces,
    rigid_body_modes,
)
from solvers.fem import boundary_nodes, check_tet_mesh, mass_matrix
from solvers.multilevel import restrict_prolongations

from .errors import NestmgInputError

if TYPE_CHECKING:
    from .options import SolverOptions
from .options import ELASTICITY_COARSE_NU, ELASTICITY_NU, ELASTICITY_SMOOTHER
from .problems import Problem, cycle_smoothers
from .problems import FAST_SMOOTHERS as _FAST_SMOOTHERS

__all__ = ["CLAMPED_PRUNE", "ELASTICITY_PROBLEMS", "ELASTICITY_SMOOTHERS", "ElasticityProblem",
           "NEARLY_INCOMPRESSIBLE_SMOOTHERS", "clamped_nodes",
           "default_body_force", "setup_elasticity"]

ELASTICITY_PROBLEMS = ("elasticity-clamped", "elasticity-free")

#: ``elasticity-clamped`` drops coarse nodes whose restricted prolongation column sums to less than this
#: (:func:`solvers.restrict_prolongations`). Such cage nodes reach a few fine nodes with small weights and
#: make the Galerkin coarse operators singular: at 0.2 the coarsest levels of fandisk (173k fine tets) and
#: spot (349k) needed the dense pivoted Cholesky; at 0.35 SuperLU factorises them, and the clamped set-up
#: takes 0.4x the CPU seconds (0.22 against 0.55 s on fandisk) for the same MG-PCG iterations
#: (``default_cycle_f_*.json``, docs/elasticity.md).
CLAMPED_PRUNE = 0.35

#: Smoothers of the ``"robust"`` preset not set, ν < 0.4 (point-wise spelling; ``multigrid(block=True)``
#: turns them into nodal block sweeps), run in the F-cycle: two forward Gauss–Seidel sweeps on the fine
#: level and four on the coarser ones before the coarse correction, the backward ones after it (the
#: solver's adjoint post-smoother); from ν = 0.4 three on the fine level
#: (:data:`NEARLY_INCOMPRESSIBLE_SMOOTHERS`). :meth:`nestmg.SolverOptions.resolved` holds the rule.
ELASTICITY_SMOOTHERS = cycle_smoothers(ELASTICITY_SMOOTHER, ELASTICITY_NU, ELASTICITY_COARSE_NU)
NEARLY_INCOMPRESSIBLE_SMOOTHERS = cycle_smoothers(ELASTICITY_SMOOTHER, ELASTICITY_NU + 1,
                                                  ELASTICITY_COARSE_NU)

#: The ``"fast"`` preset: one forward sweep before the coarse correction and the backward one after it.
FAST_SMOOTHERS = _FAST_SMOOTHERS


def default_body_force(V: np.ndarray) -> np.ndarray:
    """A smooth, non-symmetric vector field ``f(x)`` (n, 3) at the nodes ``V`` (the free problem's load)."""
    x, y, z = np.asarray(V, dtype=np.float64).T
    return np.column_stack([np.sin(3 * y) + z, np.cos(2 * z) - x, x * y + 0.5 * np.sin(2 * x)])


def clamped_nodes(V: np.ndarray, T: np.ndarray, band: float = 0.05, axis: int = 0) -> np.ndarray:
    """Boundary nodes within ``band`` of the lowest coordinate along ``axis`` (the clamped end).

    Parameters
    ----------
    V : (n, 3) float, T : (t, 4) int
    band : float
        Width of the clamped slab as a fraction of the extent along ``axis``, in (0, 1].
    axis : int

    Returns
    -------
    (m,) int64, sorted
        At least three nodes spanning a plane (so no rigid motion survives); raises ``ValueError``
        otherwise.
    """
    if not 0.0 < band <= 1.0:
        raise NestmgInputError(f"band must be in (0, 1], got {band}")
    bnd = boundary_nodes(T, n=len(V))
    c = V[bnd, axis]
    lo, hi = float(V[:, axis].min()), float(V[:, axis].max())
    fixed = np.sort(bnd[c <= lo + band * (hi - lo)])
    if len(fixed) < 3 or np.linalg.matrix_rank(V[fixed] - V[fixed].mean(axis=0), tol=1e-9 * (hi - lo)) < 2:
        raise NestmgInputError(f"the clamped band (band={band}) holds {len(fixed)} boundary nodes, not a plane's "
                         "worth: rigid motions would survive; widen it")
    return fixed


def _balanced_load(V: np.ndarray, m: np.ndarray, f: np.ndarray) -> np.ndarray:
    """``M (f - Z c)``, ``c = (Zᵀ M Z)⁻¹ Zᵀ M f``: the lumped load with its rigid-body part removed."""
    Z = rigid_body_modes(V)
    mf = (m[:, None] * f).ravel()  # M f, interleaved (M = diag(m) ⊗ I₃)
    MZ = np.repeat(m, 3)[:, None] * Z
    c = np.linalg.solve(Z.T @ MZ, Z.T @ mf)
    return mf - MZ @ c


@dataclass
class ElasticityProblem(Problem):
    """An elasticity :class:`nestmg.problems.Problem`: interleaved unknowns, block prolongations.

    Attributes (beyond :class:`~nestmg.problems.Problem`'s)
    ----------
    modes : list of (3 m_k, r_k) arrays or None
        Kernel bases of every level's operator (``elasticity-free``; None when clamped): the six rigid-body
        modes of the level's kept nodes on nested levels, the part of them the prolongations carry into
        the finer kernel on others (:func:`solvers.galerkin_nullspaces`: ``r_k = 3``, the translations,
        below a level whose outside nodes are extrapolated by clamped weights).
    fixed : (c,) int array
        Clamped fine nodes (empty for ``elasticity-free``).

    ``free`` holds the kept *node* indices of every level, ``A`` and ``P`` act on their 3 components;
    ``nullspace`` is ``"rigid"`` for ``elasticity-free`` (handled by :meth:`multigrid`, not a
    :class:`solvers.MultigridSolver` option).
    """

    modes: list | None = None
    fixed: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    def multigrid(self, options: SolverOptions | None = None, *, block: bool = False, **kwargs):
        """The multigrid solver: Galerkin operators, Gauss–Seidel (point or block), the rigid-body kernel.

        Parameters
        ----------
        options : SolverOptions, optional
            Its smoothing fields: ``smoothing="robust"`` (default) is ``nu`` sweeps of ``smoother`` on the
            fine level and ``coarse_nu`` (default ``2 nu``) on the coarser ones, ``"fast"`` is
            :data:`FAST_SMOOTHERS`; ``coarse_scaling`` ``"auto"`` is None (Galerkin operators); ``local``
            is unused (no boundary-layer sweeps for elasticity); ``cycle`` becomes the solver's
            :attr:`~solvers.MultigridSolver.cycle` (run by ``solve`` and ``aspreconditioner`` given none).
            Not set (the default), the F-cycle with :data:`ELASTICITY_SMOOTHERS` (two forward / backward
            Gauss–Seidel sweeps on the fine level, four below), from ν = 0.4
            :data:`NEARLY_INCOMPRESSIBLE_SMOOTHERS` (three on the fine level;
            :meth:`nestmg.SolverOptions.resolved`): fewer MG-PCG iterations and CPU seconds than the V-cycle
            with one symmetric sweep, the default before (docs/elasticity.md).
        block : bool
            ``True``: Gauss–Seidel specs (the presets, or ``"gauss_seidel"`` / ``"symmetric_gauss_seidel"``
            in ``presmoother``, e.g. from the command line) act on nodal 3x3 blocks
            (``"block_gauss_seidel"``, same sweeps). Default ``False`` (point-wise): measured at 63k–392k
            tets, ν = 0.3 and 0.45 (``benchmarks/elasticity.py``), the block sweeps took the same number of
            MG-PCG iterations (±1) at about twice the cost per sweep and a longer set-up
            (docs/elasticity.md).
        **kwargs
            Passed to :class:`solvers.MultigridSolver` (or
            :class:`solvers.elasticity.NullspaceMultigridSolver` for ``elasticity-free``). ``deflate``
            defaults to 0 for both problems: the elasticity cycle is slow on the bulk of its spectrum, not on
            a few modes, and on 390k / 350k-tet bunny and spot the deflation probe cost more setup than it
            saved (``benchmarks/elasticity.py``, docs/elasticity.md#deflation).

        Returns
        -------
        solvers.MultigridSolver
        """
        from solvers import MultigridSolver

        from .options import SolverOptions, typed

        # not set: F-cycle, gauss_seidel, 2 / 4 sweeps (3 / 4 from ν = 0.4: the problem's ν, not options')
        o = typed(options, SolverOptions, "options").resolved(self.name, self.params.get("nu"))
        coarse_scaling = None if o.coarse_scaling == "auto" else o.coarse_scaling
        robust = cycle_smoothers(o.smoother, o.nu, o.coarse_nu)
        pre = kwargs.pop("presmoother", FAST_SMOOTHERS if o.smoothing == "fast" else robust)
        kwargs["presmoother"] = _as_block_specs(pre) if block else pre
        kwargs.setdefault("deflate", 0)  # measured: the probe does not pay for elasticity (docs/elasticity.md)
        # symmetric by construction (elasticity_matrix mirrors its off-diagonal blocks; the clamped operator
        # is a principal submatrix): skips the O(nnz) test; free problem, 182k unknowns: set-up 0.60 s CPU
        # instead of 1.08 (median of 4)
        kwargs.setdefault("symmetric", True)
        kwargs.setdefault("cycle", o.cycle)  # the cycle of solve() and aspreconditioner() given none
        if self.modes is None:
            return MultigridSolver(self.A, self.P, coarse_scaling=coarse_scaling, **kwargs)
        return NullspaceMultigridSolver(self.A, self.P, self.modes, coarse_scaling=coarse_scaling, **kwargs)

    def expand(self, x_free: np.ndarray) -> np.ndarray:
        """Displacement (n_fine, 3) at every fine node: ``x_free`` on the free nodes, 0 on clamped ones."""
        u = np.zeros((self.n_fine, 3))
        u[self.free[0]] = np.asarray(x_free).reshape(-1, 3)
        return u


def _as_block_specs(spec):
    """Point Gauss–Seidel smoother specs turned into nodal block ones (same sweeps); others unchanged."""
    if isinstance(spec, list):
        return [_as_block_specs(s) for s in spec]
    name, opts = (spec, {}) if isinstance(spec, str) else (spec if isinstance(spec, tuple) else (None, None))
    if name == "symmetric_gauss_seidel":
        return ("block_gauss_seidel", dict(opts or {}, sweep="symmetric"))
    if name == "gauss_seidel":
        return ("block_gauss_seidel", dict(opts or {}))
    return spec


def setup_elasticity(
    tets: list[tuple[np.ndarray, np.ndarray]],
    P: list[sp.csr_matrix],
    name: str = "elasticity-clamped",
    *,
    E=1.0,
    nu: float = 0.3,
    coarse: str = "galerkin",
    f: np.ndarray | None = None,
    band: float = 0.05,
    gravity=(0.0, 0.0, -1.0),
    prune: float | None = None,
) -> ElasticityProblem:
    """Assemble an elasticity model problem on ``tets[0]`` and its block multigrid data.

    Parameters
    ----------
    tets : list of (V, T)
        Tet meshes, finest first (``Hierarchy.tets``; ``Hierarchy.tets_in("normalized")`` for the
        command line's scale).
    P : list of (n_k, n_{k+1}) csr_matrix
        Nodal prolongations (``Hierarchy.P``).
    name : {"elasticity-clamped", "elasticity-free"}
    E : float or (t,) float
        Young's modulus, constant or per fine tet.
    nu : float
        Poisson's ratio in (-1, 0.5).
    coarse : {"galerkin"}
        Only Galerkin coarse operators (the re-discretised variants are scalar).
    f : (n_fine, 3) float, optional
        Body force at the nodes: default ``gravity`` everywhere (clamped) or :func:`default_body_force`
        (free, balanced against the rigid motions).
    band : float
        Clamped slab, fraction of the x extent (:func:`clamped_nodes`).
    gravity : (3,) float
        Constant body force of ``elasticity-clamped`` when ``f`` is None.
    prune : float, optional
        ``min_column_sum`` of :func:`solvers.restrict_prolongations`: default :data:`CLAMPED_PRUNE`
        (clamped) and 0 (free, see the module docstring).

    Returns
    -------
    ElasticityProblem
    """
    if name not in ELASTICITY_PROBLEMS:
        raise NestmgInputError(f"unknown elasticity problem {name!r}; choose from {ELASTICITY_PROBLEMS}")
    if coarse != "galerkin":
        raise NestmgInputError(f"elasticity problems take coarse='galerkin' only, got {coarse!r}")
    if len(P) != len(tets) - 1:
        raise NestmgInputError(f"need len(P) == len(tets) - 1, got {len(P)} and {len(tets)}")
    free_problem = name == "elasticity-free"
    prune = (0.0 if free_problem else CLAMPED_PRUNE) if prune is None else float(prune)
    V0, T0, vol0 = check_tet_mesh(*tets[0], return_volumes=True)
    n0 = len(V0)
    m = mass_matrix(V0, T0, check=False, volumes=vol0).diagonal()
    K = elasticity_matrix(V0, T0, E, nu, check=False)
    if f is None:
        f = default_body_force(V0) if free_problem else np.broadcast_to(np.asarray(gravity, float), (n0, 3))
    f = np.asarray(f, dtype=np.float64)
    if f.shape != (n0, 3) or not np.all(np.isfinite(f)):
        raise NestmgInputError(f"f must be a finite ({n0}, 3) array, got shape {f.shape}")
    if free_problem:
        fixed = np.zeros(0, dtype=np.int64)
        b = _balanced_load(V0, m, f)
    else:
        fixed = clamped_nodes(V0, T0, band)
        b = (m[:, None] * f).ravel()
    free0 = np.setdiff1d(np.arange(n0), fixed, assume_unique=True)
    d0 = block_dofs(free0)
    A = K if free_problem else K[d0][:, d0].tocsr()
    if P:
        Pr, free = restrict_prolongations(P, free0, min_column_sum=prune)
    else:
        Pr, free = [], [free0]
    modes = None
    Pb = [block_prolongation(Pk) for Pk in Pr]
    if free_problem:
        c = V0.mean(axis=0)  # one centre for every level: P_k ⊗ I₃ maps coarse modes onto fine ones
        # the part of each level's rigid modes that P carries into the finer kernel: all six on nested
        # levels, the translations where clamped extrapolation (decimate) does not reproduce rotations
        modes = galerkin_nullspaces(Pb, [rigid_body_modes(np.asarray(Vk, dtype=np.float64)[fk], center=c)
                                         for (Vk, _), fk in zip(tets, free)])
    return ElasticityProblem(
        name=name, A=A, b=b[d0], P=Pb, coarse="galerkin", free=free, n_fine=n0,
        nullspace="rigid" if free_problem else None, params={"lam": None, "coarse": coarse, "prune": prune, "E": E if np.ndim(E) == 0 else "per-tet",
                                "nu": nu, "band": None if free_problem else band},
        local_nodes=None, modes=modes, fixed=fixed,
    )
