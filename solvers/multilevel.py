"""Geometric multigrid from a fine operator and a list of prolongations (pyamg-like API).

Notation: level 0 is the finest. ``Ps[k]`` has shape ``(n_k, n_{k+1})`` and interpolates level
``k+1`` values to level ``k`` nodes; restriction is ``R_k = P_kᵀ``. Coarse operators are either
Galerkin products ``A_{k+1} = P_kᵀ A_k P_k`` (default) or supplied by the caller (re-discretisation
on the coarse meshes).

Null space (pure Neumann problems, ``nullspace="constant"``): if every ``P_k`` has rows summing to 1,
then ``P_k 1 = 1`` and ``A_{k+1} 1 = P_kᵀ A_k P_k 1 = P_kᵀ A_k 1 = 0``: Galerkin products keep the
constants in the null space on every level (checked at setup, also for user-supplied operators).
Restricted residuals stay in the range, ``1ᵀ P_kᵀ r = (P_k 1)ᵀ r = 1ᵀ r = 0``; round-off is removed by
projecting every level's right-hand side to zero sum. The coarsest singular operator is factorised
with one node pinned (its row and column removed); for a compatible right-hand side the dropped
equation then holds automatically because the rows sum to zero. Solutions are normalised to zero
*plain nodal* mean ``1ᵀ x = 0`` (use :func:`solvers.fem.remove_mean` with a mass matrix for the
continuous mean).
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ._threads import one_blas_thread, under_one_blas_thread
from .coarse import _CoarseSolver
from .deflation import DEFLATION_GOAL, _kernel_projector, slow_modes, with_deflation
from .errors import DivergenceError, IncompatibleRHSError, SolverError, SolverInputError
from .krylov import STALL_ITERATIONS
from .ordering import (
    ORDER_MIN_N,
    ORDER_MIN_SPREAD,
    SPREAD_STRIDE,
    index_spread,
    locality_order,
    permute_prolongation,
    permute_symmetric,
    permute_symmetric_transpose,
)
from .smoothing import Smoother, local_rows, make_smoother, with_local_sweeps
from .subdomain import (
    REGION_MAX_FRACTION,
    STRONG_COUPLING,
    concentrated_region,
    power_probe,
    slow_region,
    strongly_coupled,
    subdomain_factor,
    with_subdomain_solve,
)
from .transfer import (
    _as_csr,
    _drop_unreached_columns,
    _galerkin_chain,
    _is_symmetric,
    galerkin_operators,
    prune_prolongations,
    reroute_to_pattern,
    restrict_prolongations,
    sparsified_galerkin_operators,
)

__all__ = [
    "AUTO_PROBE_MAX_COMPLEXITY",
    "COARSE_SWEEPS",
    "DEFAULT_DEFLATE",
    "DEFAULT_MAXITER",
    "DEFAULT_SMOOTHER",
    "DENSE_LEVEL_ROWS",
    "Level",
    "MultigridSolver",
    "convergence_factor",
    "galerkin_operators",
    "prune_prolongations",
    "reroute_to_pattern",
    "restrict_prolongations",
    "sparsified_galerkin_operators",
]

#: The default cycle of ``MultigridSolver(A, Ps)``: two forward Gauss–Seidel sweeps before the coarse-grid
#: correction and, as the adjoint post-smoother, two backward sweeps after it (a symmetric V(2,2) that
#: preconditions CG) on the finest level; on the coarser levels :data:`COARSE_SWEEPS` of each where the level is
#: as sparse as the finest, one where it is dense (:data:`DENSE_LEVEL_ROWS`).
#: Chosen as the fastest MG-PCG among symmetric GS V(1,1), forward/backward GS V(1,1), V(2,2) and V(3,3),
#: V(2,2) with one or three coarse sweeps, and Chebyshev of degree 2 and 3 on 1M-tet user hierarchies
#: (TetGen bunny and spot, Dirichlet and Neumann; exploratory runs, the final figures in docs/usermesh.md):
#: 7 / 11-12 CG iterations (Dirichlet / Neumann) where symmetric GS V(1,1), at the same cost per cycle,
#: took 8-9 / 12-14.
DEFAULT_SMOOTHER = ("gauss_seidel", {"sweep": "forward", "iterations": 2})

#: Sweeps before (and after) the coarse correction of the default cycle on a coarse level as sparse as the
#: finest: twice the finest level's (a variable V-cycle; such a level has ~1/8 of the finest's unknowns, so
#: the two extra each way cost ~0.5 fine SpMV per cycle). nestmg's own hierarchies (a red refinement on top)
#: have one. With two sweeps there lucy.ply's pure Neumann problem took 14 MG-PCG iterations (stationary
#: factor 0.54), with four 10 (0.31); over 66 zoo problems at most 14 became at most 10, for x0.96 the CPU
#: time (median; ``benchmarks/results/setup_cost/cg_default_cycle_744b745.json``, docs/solvers.md).
COARSE_SWEEPS = 4

#: With the default smoother, a coarse level whose operator has more than this many times the nonzeros per
#: row of the finest one (Galerkin levels of a non-nested hierarchy: 40-90 against 15) gets one sweep
#: instead of two: on the 1M-tet user hierarchies that cut 10-20% of a cycle's time at equal CG iterations.
#: Levels as sparse as the finest get :data:`COARSE_SWEEPS`: on nested hierarchies (Kuhn cube) one coarse
#: sweep made the stationary factor grow with the number of levels (0.20 / 0.28 / 0.30 for 2 / 3 / 4 levels).
DENSE_LEVEL_ROWS = 2.0

#: Default cap on cycles (stationary) or CG iterations (``accel="cg"``) of every multigrid solve:
#: :meth:`MultigridSolver.solve`, :meth:`solvers.petsc.PetscMultigrid.solve`,
#: :func:`nestmg.solve_on_hierarchy`, the time stepper, the geodesics and ``nestmg solve --maxiter``.
DEFAULT_MAXITER = 100

#: Cap on the slow modes deflated per level that :meth:`nestmg.problems.Problem.multigrid` passes as
#: ``MultigridSolver(deflate=)``, and that the constructor's ``deflate="auto"`` uses on the coarse levels of
#: a hierarchy within :data:`AUTO_PROBE_MAX_COMPLEXITY`.
DEFAULT_DEFLATE = 8

#: ``MultigridSolver(deflate="auto")`` (the default) probes the coarse levels (:data:`DEFAULT_DEFLATE`
#: modes, not the finest level) when the operator complexity is at most this, and not at all above it. The
#: probe runs a few dozen cycles of each coarse level, so its cost in fine cycles grows with the coarse
#: levels' share of the nonzeros, ``1 - 1/complexity``. nestmg's own hierarchies are at 1.17-1.44: on the
#: zoo's 26 single-body meshes x 3 problems it brought MG-PCG to at most 10 iterations in 77 of 78 cases
#: (66 without it: Neumann or diffusion problems of lucy.ply, cow.obj, decimated-knight.off, cheburashka.obj
#: and three CAD parts took 11-15) for a set-up + solve CPU time x1.26 of the cycle without it (median;
#: x0.84-2.24), still x0.90 of ``Problem.multigrid()``'s (``benchmarks/results/corpus/zoo_e9b70b9_*.json``,
#: the docs' corpus; the run at f122700, ``zoo_f122700_*.json``, gave 77 / 69 of 78, x1.22, x0.89). The 1M-tet
#: user hierarchies are at 1.71-1.83 (``user_mesh/auto_probe.json``), where the probe found only bulk modes,
#: saved no CG iteration and cost 1.5-2.2x the set-up (``nestmg_deflate8`` in ``user_mesh/solvers.json``).
#: 1.5 is also the pipeline's own complexity goal.
AUTO_PROBE_MAX_COMPLEXITY = 1.5


class ConvergenceWarning(UserWarning):
    """``solve`` stopped at ``maxiter`` before reaching ``tol``."""


def convergence_factor(residuals, last: int = 5) -> float:
    """Asymptotic convergence factor from a residual history.

    The geometric mean of the ratios ``r[i+1]/r[i]`` over the last ``last`` cycles,
    ``(r[-1] / r[-1-last]) ** (1/last)``, ignoring trailing entries that already sit at round-off
    level (``r < 1e-14 · r[0]``), where ratios are noise. Uses the whole history if it is shorter.

    Parameters
    ----------
    residuals : sequence of float
        Residual norms (absolute or relative), initial residual first.
    last : int

    Returns
    -------
    float (``nan`` if fewer than two usable entries)
    """
    r = np.asarray(residuals, dtype=np.float64).ravel()
    if r.size and r[0] > 0:
        r = r[: max(np.count_nonzero(r >= 1e-14 * r[0]), 1)] if np.all(np.isfinite(r)) else r
    if r.size < 2 or r[0] == 0:
        return float("nan")
    m = min(int(last), r.size - 1)
    if r[-1 - m] == 0:
        return float("nan")
    return float((r[-1] / r[-1 - m]) ** (1.0 / m))


def _probe_helps(before: dict, after: dict) -> bool:
    """Whether a correction added to a level's smoothers helps, by two probes of the cycle (the same start
    and steps, :func:`solvers.deflation.slow_modes`): a correction inside a product of smoothers is not sure
    to; kept only if the slowest factor drops and the cycle still contracts both ways (smallest Ritz value
    above -0.95: a positive definite preconditioner)."""
    return after["probe_factor"] < before["probe_factor"] and after.get("probe_min", 0.0) > -0.95


@dataclass
class Level:
    """One level of the hierarchy (a bare struct, as pyamg's).

    Attributes
    ----------
    A : (n_k, n_k) csr_matrix
    P : (n_k, n_{k+1}) csr_matrix or None on the coarsest level
    R : (n_{k+1}, n_k) csr_matrix (``Pᵀ``) or None
    presmoother, postsmoother : Smoother or None on the coarsest level
    """

    A: sp.csr_matrix
    P: sp.csr_matrix | None = None
    R: sp.csr_matrix | None = None
    presmoother: Smoother | None = None
    postsmoother: Smoother | None = None
    info: dict = field(default_factory=dict)


def _checked_inputs(A, Ps, nullspace) -> tuple:
    """``A`` and ``Ps`` as CSR, their shapes chained (each coarse level smaller, non-empty) and, for
    ``nullspace="constant"``, every prolongation reproducing constants (one-line errors otherwise)."""
    A = _as_csr(A, "A", copy=False)  # copied by the reordering, or by _reorder when the order is kept
    if A.shape[0] != A.shape[1]:
        raise SolverInputError(f"A must be square, got {A.shape}")
    Ps = [_as_csr(P, f"Ps[{k}]", copy=False) for k, P in enumerate(Ps)]  # copied or permuted by _reorder
    n = A.shape[0]
    for k, P in enumerate(Ps):
        if P.shape[0] != n:
            raise SolverInputError(f"Ps[{k}] has shape {P.shape}; expected {n} rows (level {k} size)")
        if P.shape[1] == 0 or P.shape[1] >= P.shape[0]:
            raise SolverInputError(f"Ps[{k}] has shape {P.shape}: the coarse level must be smaller and non-empty")
        if nullspace == "constant":
            rs = P @ np.ones(P.shape[1])
            if np.abs(rs - 1).max() > 1e-8:
                raise SolverInputError(
                    f"nullspace='constant' needs prolongations reproducing constants, but rows of Ps[{k}] "
                    f"sum to values in [{rs.min():.3g}, {rs.max():.3g}]"
                )
        n = P.shape[1]
    return A, Ps


def _check_operators(ops, nullspace, diagonals=()) -> None:
    """Every level operator has a positive diagonal and, for ``nullspace="constant"``, annihilates
    constants (one-line :class:`SolverError` naming the level otherwise). ``diagonals``: those of the first
    levels, if the caller has them."""
    for k, Ak in enumerate(ops):
        d = diagonals[k] if k < len(diagonals) else Ak.diagonal()
        if np.any(d <= 0):
            bad = np.flatnonzero(d <= 0)
            raise SolverError(
                f"level {k} operator has {bad.size} rows with diagonal <= 0 (first: node {bad[0]}); "
                "a coarse node that touches no free fine node gives an empty row: restrict the "
                "prolongations with restrict_prolongations(Ps, free)"
            )
        if nullspace == "constant":
            r = np.abs(Ak @ np.ones(Ak.shape[0])).max()
            # relative to ||A_k||_inf (no empty rows: the diagonal is positive), which is >= max(d): the
            # row sums are formed only when that cheaper bound does not already pass
            if r > 1e-9 * d.max() and r > 1e-9 * np.add.reduceat(np.abs(Ak.data), Ak.indptr[:-1]).max():
                raise SolverError(
                    f"nullspace='constant' but the level {k} operator does not annihilate constants "
                    f"(max |A_{k} 1| = {r:.3e})"
                )


class MultigridSolver:
    """Multigrid hierarchy with ``solve`` and ``aspreconditioner`` (modelled on pyamg's MultilevelSolver).

    Parameters
    ----------
    A : (n_0, n_0) sparse matrix
        Fine operator (symmetric positive (semi-)definite for the theory and for CG).
    Ps : list of sparse matrices
        ``Ps[k]`` of shape ``(n_k, n_{k+1})`` maps level ``k+1`` to level ``k`` (rows sum to 1 for
        interpolation; restricted rows near Dirichlet nodes may sum to less). May be empty (one level,
        direct solve).
    coarse : "galerkin" or list of sparse
        ``"galerkin"`` (default): ``A_{k+1} = P_kᵀ A_k P_k``. A list ``[A_1, ..., A_L]`` (shapes
        ``(n_k, n_k)``): the caller's coarse operators, e.g. re-discretised or volume-fraction weighted
        ones (``nestmg.problems.setup_problem(coarse=...)`` makes them).
    coarse_scaling : None or "energy"
        ``"energy"``: scale every coarse-grid correction ``e = P x_c`` by the energy-optimal
        ``α = (rᵀ e) / (eᵀ A e)`` (minimises the energy norm of the error along ``e``; one extra
        SpMV per level and cycle). It corrects coarse operators that are uniformly too soft or too
        stiff (re-discretisation on a cage: a larger domain); with Galerkin operators ``α = 1``
        exactly in exact arithmetic for a single correction. Makes the cycle a (mildly) non-linear
        preconditioner; ``solve(accel="cg")`` then uses the flexible (Polak–Ribière) CG update.
    presmoother, postsmoother : str or (str, dict), or a list of them
        See :func:`solvers.smoothing.make_smoother`. A list gives one spec per level, finest first,
        the last one repeated on deeper levels (e.g. more sweeps on the cheap coarse levels: the
        variable V-cycle). Default :data:`DEFAULT_SMOOTHER`: two forward Gauss–Seidel sweeps, and two
        backward ones after the correction (V(2,2)) on the finest level; :data:`COARSE_SWEEPS` of each on
        the coarse levels as sparse as the finest, one on those denser than :data:`DENSE_LEVEL_ROWS` times
        the finest (only for the default itself: an equal spec passed explicitly gives two sweeps on every
        level). ``postsmoother=None`` (default) means the adjoint of
        the presmoother: the same smoother,
        with a forward Gauss–Seidel sweep turned into a backward one, so the cycle is symmetric and can
        precondition CG. An explicit non-adjoint pair (e.g. forward GS on both sides) is allowed for
        stationary cycling; ``solve(accel="cg")`` then warns.
    nullspace : None or "constant"
        ``"constant"`` for pure Neumann operators (see module docstring): checks ``A_k 1 = 0`` on every
        level, projects right-hand sides and returns zero-mean solutions.
    coarse_solver : {"auto", "pinv", "splu", "pivoted", "regularized"}
        Coarsest-level direct solver, set up once. ``"splu"``: SuperLU (one node pinned for Neumann),
        validated at setup on a random consistent right-hand side; raises :class:`SolverError` if the
        operator is singular beyond the expected null space. ``"pivoted"``: dense rank-revealing Cholesky
        (LAPACK ``dpstrf``), the minimum-norm solution on the range whatever the null space (symmetric
        positive semi-definite operators). ``"regularized"``: SuperLU of ``A + 1e-9 diag(A)``, for
        consistent right-hand sides also with extra null vectors, but off by ``1e-9 diag / λ`` on an
        eigenvalue ``λ`` (validated by the residual). ``"pinv"``: dense pseudo-inverse (O(n³) setup,
        about 10x the pivoted Cholesky's). ``"auto"`` (default): SuperLU, then for a symmetric level of at
        most :data:`solvers.coarse.PIVOTED_MAX` unknowns the regularised LU if a guard finds its range well
        conditioned (:data:`solvers.coarse.GUARD_MIN`), else the pivoted Cholesky, then the regularised LU,
        then the pseudo-inverse if the coarsest level has at most ``pinv_max`` unknowns (the fallback is
        reported by ``repr``); a coarsest level of at most :data:`solvers.coarse.DENSE_MAX` unknowns
        starts at the regularised dense (band) Cholesky, then the pivoted one. Measured on a 550k-tet
        bunny Galerkin hierarchy (2k-node coarsest level, 3 extra null vectors): regularised 3 s setup,
        pseudo-inverse 31-54 s, identical residual histories; on the clamped elasticity coarsest level of
        spot (4,017 unknowns, ν = 0.45) the regularised solve stalled MG-PCG with the W-cycle, the pivoted
        one did not (:class:`solvers.coarse._PivotedCholesky`).
    pinv_max : int
        Size limit of the ``"auto"`` fallback (dense eigh of 2000 unknowns: ~1–4 s on this machine).
    local_nodes : int array or bool mask, optional
        Level-0 unknowns where the smoother is weak (for FEM: the boundary layer of a Neumann
        problem, see :func:`solvers.fem.boundary_layer_nodes`). They get ``local_sweeps`` extra
        symmetric Gauss–Seidel sweeps after pre-smoothing and before post-smoothing
        (:func:`solvers.smoothing.with_local_sweeps`; the cycle stays symmetric). Coarser levels relax
        the coarse nodes that interpolate to the finer set, down to ``local_levels`` levels (default:
        every smoothed level).
    local_sweeps : int
        Extra symmetric sweeps per application (default 1).
    local_levels : int, optional
        Number of levels, from the finest, that get local sweeps.
    local_sweep : {"symmetric", "one-way"}
        ``"symmetric"`` (default): each local sweep is a forward and a backward pass. ``"one-way"``:
        forward after pre-smoothing, backward before post-smoothing (still an adjoint pair, half the
        cost).
    ordering : {"auto", "locality"} or None
        Internal order of the finest level's unknowns. ``"locality"``: :func:`solvers.ordering.locality_order`
        (from the prolongations; a few integer sorts), applied as ``A[p][:, p]`` before the Galerkin products;
        ``solve`` and ``aspreconditioner`` take and return vectors in the caller's order. On scattered
        1M-tet user meshes the Galerkin products ran ~2.5x and a fine SpMV up to 1.4x faster
        (docs/usermesh.md). ``"auto"`` (default): ``"locality"`` when the finest level has
        at least :data:`solvers.ordering.ORDER_MIN_N` unknowns and a scattered order
        (:func:`solvers.ordering.index_spread` above :data:`solvers.ordering.ORDER_MIN_SPREAD`); None:
        the caller's order. ``levels[0]`` then holds the permuted operator and ``perm`` the permutation
        (a symmetric ``A``'s as the transpose of the permuted matrix: the same for an exactly symmetric
        ``A``, within the symmetry tolerance for one symmetric up to round-off).
    symmetric : bool, optional
        The caller's statement that ``A`` and the given coarse operators are symmetric (e.g. the sparse
        sums of :class:`solvers.shifted.ShiftedGalerkin`, symmetric by construction), which skips the
        symmetry tests (~40 ms per level visit of a 2.5M-nonzero operator, a third of a time step's
        set-up in ``benchmarks/reuse_diffusion.py``). ``None`` (default): tested (relative 1e-10).
    deflate : int or "auto"
        At most this many slow modes deflated per level (0: off; ``nestmg``'s problems pass
        :data:`DEFAULT_DEFLATE`). ``"auto"`` (default): :data:`DEFAULT_DEFLATE` when the operator
        complexity is at most :data:`AUTO_PROBE_MAX_COMPLEXITY` (cheap coarse levels), else 0; the value used
        is :attr:`deflate`. Every level between the finest and the
        coarsest is probed at setup with :data:`solvers.deflation.PROBE_CYCLES` cycles of its own (about
        one fine cycle in all on a hierarchy coarsening 8x per level); where the error survives them
        (factor above ``deflate_goal``), the slowest modes are found by a few more
        Lanczos steps and corrected exactly inside the cycle (:mod:`solvers.deflation`). Only linear
        symmetric cycles are probed (not with ``coarse_scaling``).
    deflate_goal : float
        The per-cycle factor a probed level must meet before its slow modes are deflated (default
        :data:`solvers.deflation.DEFLATION_GOAL`, 0.3; ``nestmg``'s problems pass their own goal,
        :data:`nestmg.problems.FACTOR_GOALS`: 0.2 for Dirichlet).
    probe_finest : bool
        Probe (and deflate) the finest level too: its probe costs about as much as one solve, so it is
        off by default here and on in ``nestmg``'s problems (:meth:`nestmg.problems.Problem.multigrid`),
        whose setup is a small part of a run.
    local_solve : bool
        Where a probed level's slow modes live on a small region (a thin lip of flat elements: a family of
        slow modes too large to deflate, or a few that deflation removes one by one), add an exact solve on
        that region to its smoothers instead (:mod:`solvers.subdomain`), kept only if the probe re-run with
        it is faster; the modes still slow after it are deflated as before. Default True; acts only where
        ``deflate`` probes.
    local_probe : int
        Cycles of a cheap search for a finest-level slow region, without Lanczos steps (default 0: off):
        ``local_probe`` V-cycles on a random error (:func:`solvers.subdomain.power_probe`); if its energy
        then sits on a few unknowns (:func:`solvers.subdomain.concentrated_region`), an exact solve on them
        and their neighbours is added to the fine smoothers as with ``local_solve``, kept if one more cycle
        shows it reduces the error faster per unit of work (:attr:`local_probe`). With 2 on the 1M-tet
        TetGen user hierarchies (Neumann, diffusion) it took 5.6-6.4k unknowns and cut MG-PCG from 10-12 to
        9-10 iterations and the solve's CPU time by 8-14%, but the set-up took 0.05-0.07 s more (3 cycles,
        a factor), more than the solve saved; on TetWild fine levels and Dirichlet problems it took nothing,
        for 0.03-0.06 s (``local_probe2`` in ``benchmarks/user_mesh_solvers.py``; docs/solvers.md). Off by
        default: it pays where one set-up serves several solves.
    strong_blocks : float or None
        Threshold ``θ`` of an exact solve on the finest level's strongly coupled unknowns, those with
        ``|a_ij| >= θ sqrt(a_ii a_jj)`` for some ``j != i`` (:func:`solvers.subdomain.strongly_coupled`), added
        to the fine smoothers as with ``local_solve`` (default :data:`solvers.subdomain.STRONG_COUPLING`, 0.5;
        None: off). A point smoother updates such a pair as if it were one unknown; a mesher's flat tets
        make them (the slivers on a TetGen mesh's boundary). Found in one pass over ``A``, no cycle; skipped
        when none is strong, when more than :data:`solvers.subdomain.REGION_MAX_FRACTION` of the unknowns
        are, or when the region's factor would cost more than a sweep (:attr:`strong_blocks`).
    probe_at : {"setup", "stationary"}
        When the finest level's probe (``probe_finest``) runs: at set-up (default), or at the first
        stationary solve (``solve(accel=None)``) or :meth:`probe` call (``nestmg``'s problems). The coarser
        levels are probed at set-up either way (cheap). The finest probe costs about one solve and serves
        the stationary cycle's factor; under CG it saved at most one iteration on the corpus meshes
        measured, so ``solve(accel="cg")`` and :meth:`aspreconditioner` skip it.
    cycle : {"V", "W", "F"}
        The cycle :meth:`solve`, :meth:`aspreconditioner` and :meth:`cycle_complexity` use when given none
        (default ``"V"``; ``nestmg``'s elasticity problems at ν >= 0.4 pass ``"W"``,
        :meth:`nestmg.SolverOptions.resolved`).

    Attributes
    ----------
    levels : list of Level
        Level 0 in the internal order ``perm`` (``levels[0].A == A[perm][:, perm]``).
    perm : (n_0,) int64 array or None
        The finest level's internal order (None: the caller's).
    deflation : list of dict
        Per probed level: ``level``, ``probe_factor``, ``vectors`` deflated and their ``factors`` (without
        the finest level while its probe, deferred by ``probe_at="stationary"``, has not run);
        ``local_solve`` where a subdomain solve was tried: its ``nodes``, ``kept``, and the re-run
        ``probe_factor`` (or ``refused_fill``: its factor would cost more than a sweep of the level; or
        ``singular``: the region's block is).
    local_probe : dict or None
        The ``local_probe`` search's report: ``cycles``, ``nodes`` of the region (0: none found), and when one
        was: the keep test's ``ratio`` (last probe cycle) and ``ratio_after`` (with the subdomain solve),
        ``kept``; None when it did not run.
    strong_blocks : dict or None
        The strong-coupling solve's report: ``theta``, ``nodes`` strongly coupled (0: none), ``installed``,
        and why not when they are not: ``refused_size`` (more than
        :data:`solvers.subdomain.REGION_MAX_FRACTION` of the unknowns), ``refused_fill`` / ``singular`` (as in
        :attr:`deflation`); None when off.
    deflate : int
        The ``deflate`` used (``"auto"`` resolved).
    setup_seconds : float

    Examples
    --------
    >>> from solvers.gallery import kuhn_cube_hierarchy
    >>> from solvers.fem import stiffness_matrix, boundary_nodes
    >>> meshes, Ps = kuhn_cube_hierarchy(8, 3)
    >>> V, T = meshes[0]
    >>> K = stiffness_matrix(V, T)
    >>> free = np.setdiff1d(np.arange(len(V)), boundary_nodes(T))
    >>> Pf, _ = restrict_prolongations(Ps, free)
    >>> ml = MultigridSolver(K[free][:, free], Pf)
    >>> res = []
    >>> x = ml.solve(np.ones(len(free)), tol=1e-8, residuals=res)
    >>> len(res) < 15, res[-1] < 1e-8
    (True, True)
    """

    @under_one_blas_thread  # the set-up's dense work is small: BLAS threads only spin (solvers._threads)
    def __init__(
        self,
        A,
        Ps,
        *,
        coarse="galerkin",
        coarse_scaling: str | None = None,
        presmoother=DEFAULT_SMOOTHER,
        postsmoother=None,
        nullspace: str | None = None,
        coarse_solver: str = "auto",
        pinv_max: int = 3000,
        local_nodes=None,
        local_sweeps: int = 1,
        local_levels: int | None = None,
        local_sweep: str = "symmetric",
        ordering: str | None = "auto",
        symmetric: bool | None = None,
        deflate: int | str = "auto",
        probe_finest: bool = False,
        cycle: str = "V",
        deflate_goal: float = DEFLATION_GOAL,
        probe_at: str = "setup",
        local_solve: bool = True,
        local_probe: int = 0,
        strong_blocks: float | None = STRONG_COUPLING,
    ):
        t0 = time.perf_counter()
        #: the cycle of :meth:`solve`, :meth:`aspreconditioner` and :meth:`cycle_complexity` when they are
        #: given none
        self.cycle = self._check_cycle(cycle)
        if nullspace not in (None, "constant"):
            raise SolverInputError(f"nullspace must be None or 'constant', got {nullspace!r}")
        self.nullspace = nullspace
        A_in = A
        A, Ps = _checked_inputs(A, Ps, nullspace)
        shared = hasattr(A_in, "data") and np.may_share_memory(A.data, A_in.data)
        if local_sweep not in ("symmetric", "one-way"):
            raise SolverInputError(f"local_sweep must be 'symmetric' or 'one-way', got {local_sweep!r}")
        if coarse_scaling not in (None, "energy"):
            raise SolverInputError(f"coarse_scaling must be None or 'energy', got {coarse_scaling!r}")
        self.coarse_scaling = coarse_scaling
        A, Ps, Rs, ops, sym0, diagonals, lowers = self._coarse_operators(A, Ps, coarse, ordering, symmetric,
                                                                         shared)
        _check_operators(ops, nullspace, diagonals)
        self.levels = self._make_levels(ops, Ps, Rs, presmoother, postsmoother, local_nodes, local_levels,
                                        local_sweep, local_sweeps, [*zip(lowers, diagonals)])
        # Galerkin products of a symmetric A are symmetrised on construction: only A is tested
        if self.coarse == "galerkin":
            self.symmetric = sym0
        else:
            self.symmetric = (all(_is_symmetric(L.A) for L in self.levels) if symmetric is None
                              else bool(symmetric))
        self._coarse_solver = _CoarseSolver(ops[-1], nullspace, len(ops) - 1, coarse_solver, pinv_max,
                                            symmetric=self.symmetric or None)
        #: null vectors of the coarsest operator (1 expected for Neumann, 0 for Dirichlet; more means a
        #: rank-deficient prolongation, handled by the pseudo-inverse)
        self.coarse_nullity = self._coarse_solver.nullity
        # a cycle is a symmetric operator iff A_k are symmetric and post = adjoint(pre) on every level
        self.symmetric_cycle = self.symmetric and (
            len(self.levels) == 1
            or all(_smoothers_adjoint(L.presmoother, L.postsmoother) for L in self.levels[:-1])
        )
        if not 0.0 < deflate_goal < 1.0:
            raise SolverInputError(f"deflate_goal must be in (0, 1), got {deflate_goal!r}")
        self.deflate_goal = float(deflate_goal)
        self.local_solve = bool(local_solve)
        #: the report of the finest level's strong-coupling solve (``strong_blocks``; see Attributes)
        fine_lower = (lowers[0], diagonals[0]) if lowers and lowers[0] is not None and diagonals else None
        self.strong_blocks = self._strong_block_solve(strong_blocks, fine_lower)
        #: the ``deflate`` used (``"auto"`` resolved, :data:`AUTO_PROBE_MAX_COMPLEXITY`)
        self.deflate = self._auto_deflate(deflate)
        self._schedule_probe(self.deflate, probe_finest, probe_at)
        #: the report of the finest level's cheap slow-region search (``local_probe``; see Attributes)
        self.local_probe = self._cheap_local_solve(local_probe)
        self.setup_seconds = time.perf_counter() - t0

    def _coarse_operators(self, A, Ps, coarse, ordering, symmetric, shared=False) -> tuple:
        """The level operators: Galerkin products, or the caller's (checked); both reordered (``ordering``).

        ``shared``: ``A`` holds the caller's arrays (copied unless reordering makes a new matrix anyway).
        Returns ``(A, Ps, Rs, ops, sym0, diagonals, lowers)`` in the solver's order (``diagonals``, ``lowers``:
        the diagonals and lower triangles ``D + L`` of the first operators, by-products of the Galerkin
        products; both empty for given operators); sets ``self.coarse``.
        """
        sym0 = None
        diagonals: list = []
        lowers: list = []
        if isinstance(coarse, str):
            if coarse != "galerkin":
                raise SolverInputError(
                    f"coarse must be 'galerkin' or a list of coarse operators, got {coarse!r} (named coarse "
                    "operators such as 'weighted' are built by nestmg.problems.setup_problem)")
            # coarse nodes that reach no finer node (e.g. cage nodes of a hierarchy's raw P) would give
            # empty rows of P^T A P; as Galerkin levels they add nothing, so they are dropped
            Ps = _drop_unreached_columns(Ps)
            A, Ps, Rs, _, sym0 = self._reorder(A, Ps, ordering, [], symmetric, shared)
            # A validated above: no second copy and check; the smoothed levels stored diagonal first
            ops = _galerkin_chain(A, Ps, sym0, Rs, diagonals, diagonal_first=True, lowers=lowers)
            self.coarse = "galerkin"
        else:
            given = list(coarse)
            if len(given) != len(Ps):
                raise SolverInputError(f"coarse needs {len(Ps)} matrices [A_1, ..., A_L], got {len(given)}")
            ops = [A] + [_as_csr(Ac, f"coarse[{k}]") for k, Ac in enumerate(given)]
            for k, (P, Ac) in enumerate(zip(Ps, ops[1:])):
                if Ac.shape != (P.shape[1], P.shape[1]):
                    raise SolverInputError(
                        f"coarse[{k}] has shape {Ac.shape}, expected {(P.shape[1], P.shape[1])}"
                    )
            self.coarse = "given"
            A, Ps, Rs, given, _ = self._reorder(A, Ps, ordering, ops[1:], False, shared)
            ops = [A] + given
        return A, Ps, Rs, ops, sym0, diagonals, lowers

    def _make_levels(self, ops, Ps, Rs, presmoother, postsmoother, local_nodes, local_levels, local_sweep,
                     local_sweeps, lowers=()) -> list[Level]:
        """One :class:`Level` per operator: smoothers (post = adjoint of pre unless given), local sweeps.
        ``lowers``: ``(D + L, diagonal)`` of the first operators (Gauss–Seidel's lower triangles, see
        :func:`solvers.smoothing.make_smoother`), when the Galerkin products kept them."""
        pre_specs = _level_specs(presmoother, len(Ps))
        if presmoother is DEFAULT_SMOOTHER:
            pre_specs = _default_level_specs(ops, pre_specs)
        post_specs = ([_adjoint_spec(s) for s in pre_specs] if postsmoother is None
                      else _level_specs(postsmoother, len(Ps)))
        local = _local_sets(_permuted_nodes(local_nodes, self.perm), Ps, local_levels, ops[0].shape[0])
        levels: list[Level] = []
        for k, Ak in enumerate(ops):
            if k < len(Ps):
                P = Ps[k]
                pre_spec, post_spec = pre_specs[k], post_specs[k]
                lower = lowers[k] if k < len(lowers) and lowers[k][0] is not None else None
                pre = make_smoother(Ak, pre_spec, diagonal_checked=True, lower=lower)  # checked above
                # a self-adjoint smoother is shared (one spectral radius estimate per level)
                post = (pre if post_spec is pre_spec
                        else make_smoother(Ak, post_spec, diagonal_checked=True, lower=lower))
                if local[k] is not None:
                    one_way = local_sweep == "one-way"
                    rows = local_rows(Ak, local[k])  # one copy of the rows for both smoothers
                    pre, post = (with_local_sweeps(pre, Ak, local[k], local_sweeps,
                                                   sweep="forward" if one_way else "symmetric", rows=rows),
                                 with_local_sweeps(post, Ak, local[k], local_sweeps, first=True,
                                                   sweep="backward" if one_way else "symmetric", rows=rows))
                lvl = Level(Ak, P, Rs[k], pre, post)
            else:
                lvl = Level(Ak)
            levels.append(lvl)
        return levels

    def _auto_deflate(self, deflate) -> int:
        """``deflate`` with ``"auto"`` resolved: :data:`DEFAULT_DEFLATE` within
        :data:`AUTO_PROBE_MAX_COMPLEXITY`, else 0 (other values are checked by :meth:`_deflate`)."""
        if isinstance(deflate, str):
            if deflate != "auto":
                raise SolverInputError(f"deflate must be a non-negative integer or 'auto', got {deflate!r}")
            return DEFAULT_DEFLATE if self.operator_complexity() <= AUTO_PROBE_MAX_COMPLEXITY else 0
        return deflate

    def _schedule_probe(self, max_vectors: int, probe_finest: bool, probe_at: str) -> None:
        """Probe the coarser levels now, and the finest (``probe_finest``) now (``probe_at="setup"``) or at
        :meth:`probe`."""
        if probe_at not in ("setup", "stationary"):
            raise SolverInputError(f"probe_at must be 'setup' or 'stationary', got {probe_at!r}")
        defer = probe_at == "stationary" and probe_finest and max_vectors
        #: (max_vectors) of the finest level's probe deferred to :meth:`probe`, or None
        self._pending_probe = int(max_vectors) if defer else None
        self.deflation: list[dict] = self._deflate(max_vectors, probe_finest and not defer)

    @under_one_blas_thread
    def probe(self) -> list[dict]:
        """Run the finest level's probe deferred by ``probe_at="stationary"`` (once; later calls, and a
        probe run at set-up, do nothing) and return :attr:`deflation`. ``solve(accel=None)`` calls it."""
        if self._pending_probe is not None:
            max_vectors, self._pending_probe = self._pending_probe, None
            self.deflation = self._deflate(max_vectors, True, first=0) + self.deflation
        return self.deflation

    def _deflate(self, max_vectors: int, probe_finest: bool, first: int | None = None) -> list[dict]:
        """Probe levels ``first .. 1`` (default ``first = L-2``; and 0 with ``probe_finest``), coarse first so
        that each probe sees the corrections below it, and deflate their slow modes
        (:func:`solvers.deflation.slow_modes`). Returns the reports, finest level first."""
        if isinstance(max_vectors, bool) or int(max_vectors) != max_vectors or max_vectors < 0:
            raise SolverInputError(f"deflate must be a non-negative integer, got {max_vectors!r}")
        report = []
        last = 0 if probe_finest else 1
        # the coarsest level is solved directly (no smoothers, nothing to deflate): a one-level solver has
        # no level to probe
        first = len(self.levels) - 2 if first is None else min(first, len(self.levels) - 2)
        linear = self.symmetric_cycle and self.coarse_scaling is None  # Lanczos needs a linear symmetric cycle
        probed = range(first, last - 1, -1) if max_vectors and linear else ()
        for k in probed:
            L = self.levels[k]
            zero = np.zeros(L.A.shape[0])

            def cycle(x, k=k, zero=zero):
                self._cycle(k, x, zero, "V")

            neumann = self.nullspace == "constant"
            kernel = self._level_kernel(k)
            Z, info = slow_modes(cycle, L.A, constant_nullspace=neumann, nullspace_basis=kernel,
                                 max_vectors=int(max_vectors), goal=self.deflate_goal,
                                 keep_bulk=self.local_solve)
            info["level"] = k
            bulk = info.pop("bulk_modes", None)
            if self.local_solve and (Z.shape[1] or bulk is not None):
                Z = self._local_solve(k, Z if Z.shape[1] else bulk, info, cycle, neumann, kernel,
                                      max_vectors, Z)
            if Z.shape[1]:
                pre, post = L.presmoother, L.postsmoother
                L.presmoother = with_deflation(pre, L.A, Z)
                L.postsmoother = with_deflation(post, L.A, Z, first=True)
                # a projection inside a product of smoothers is not sure to help: keep it only if the
                # probe (same start, same steps) says it does, and the cycle still contracts both ways
                check = slow_modes(cycle, L.A, constant_nullspace=neumann, nullspace_basis=kernel,
                                   max_vectors=0)[1]
                info["probe_after"] = check["probe_factor"]
                if not _probe_helps(info, check):
                    L.presmoother, L.postsmoother = pre, post
                    info.update(vectors=0, factors=[], reverted=True)
            report.append(info)
        return report[::-1]

    def _strong_block_solve(self, theta: float | None, lower=None) -> dict | None:
        """An exact solve on the finest level's strongly coupled unknowns (``strong_blocks``), added to its
        smoothers; returns the report, None when off or not applicable (a single level or a non-symmetric
        operator). ``lower``: the finest level's ``(D + L, diagonal)`` if kept."""
        if theta is None:
            return None
        if isinstance(theta, bool) or not isinstance(theta, (int, float)) or not 0.0 < theta <= 1.0:
            raise SolverInputError(f"strong_blocks must be None or a threshold in (0, 1], got {theta!r}")
        if len(self.levels) < 2 or not self.symmetric_cycle:
            return None
        report = {"theta": float(theta), "nodes": 0, "installed": False}
        region = strongly_coupled(self.levels[0].A, float(theta), max_fraction=1.0, lower=lower)
        if region is None:
            return report
        report["nodes"] = int(region.size)
        if region.size > REGION_MAX_FRACTION * self.levels[0].A.shape[0]:  # not local: e.g. elasticity's
            report["refused_size"] = True  # coupled displacement components, an anisotropic operator
            return report
        report["installed"] = self._add_subdomain_solve(0, region, report) is not None
        return report

    def _cheap_local_solve(self, cycles: int) -> dict | None:
        """The ``local_probe``: ``cycles`` V-cycles of the finest level on a random error
        (:func:`solvers.subdomain.power_probe`); where their error's energy is concentrated
        (:func:`solvers.subdomain.concentrated_region`), an exact solve on that region is added to the fine
        smoothers, kept if one cycle from the previous error ``e_{k-1}`` then reduces its energy norm more
        per unit of work than the last probe cycle did (``ratio_after`` against ``ratio``, each to the power
        ``1 / cycle_complexity``). Returns the report, None when it did not run (off, a single level, a
        nonlinear or non-symmetric cycle, or a fine local solve already kept)."""
        if isinstance(cycles, bool) or int(cycles) != cycles or cycles < 0:
            raise SolverInputError(f"local_probe must be a non-negative integer, got {cycles!r}")
        done = any(d["level"] == 0 and d.get("local_solve", {}).get("kept") for d in self.deflation)
        if not cycles or len(self.levels) < 2 or not self.symmetric_cycle or self.coarse_scaling or done:
            return None
        A = self.levels[0].A
        zero = np.zeros(A.shape[0])

        def cycle(x):
            self._cycle(0, x, zero, "V")

        project = _kernel_projector(self.nullspace == "constant", self._level_kernel(0))
        with np.errstate(all="ignore"):
            prev, e = power_probe(cycle, A, cycles, project)
        report = {"cycles": int(cycles), "nodes": 0, "kept": False}
        Ae = A @ e
        region = concentrated_region(e, A, Ae=Ae) if np.all(np.isfinite(Ae)) else None
        if region is None:
            return report
        report["nodes"] = int(region.size)
        work = self.cycle_complexity("V")
        installed = self._add_subdomain_solve(0, region, report)
        if installed is None:
            return report
        norm = float(np.sqrt(prev @ (A @ prev)))
        report["ratio"] = float(np.sqrt(max(e @ Ae, 0.0))) / norm
        cycle(prev)
        project(prev)
        report["ratio_after"] = float(np.sqrt(max(prev @ (A @ prev), 0.0))) / norm
        # the solve costs (work per cycle) / log(1 / factor): kept if that drops
        with np.errstate(divide="ignore"):
            gain = np.log(report["ratio_after"]) / self.cycle_complexity("V") < np.log(report["ratio"]) / work
        report["kept"] = bool(gain)
        if not report["kept"]:
            self.levels[0].presmoother, self.levels[0].postsmoother = installed
        return report

    def _local_solve(self, k, modes, info, cycle, neumann, kernel, max_vectors, Z) -> np.ndarray:
        """Try an exact subdomain solve on the region of level ``k``'s slow ``modes``
        (:mod:`solvers.subdomain`); keep it if the re-run probe is faster, and return the modes still to
        deflate (``Z``, the first probe's, when there is no local region or no gain)."""
        L = self.levels[k]
        region = slow_region(modes, L.A)
        if region is None:
            return Z
        info["local_solve"] = {"nodes": int(region.size), "kept": False}
        installed = self._add_subdomain_solve(k, region, info["local_solve"])
        if installed is None:
            return Z
        pre, post = installed
        Z2, again = slow_modes(cycle, L.A, constant_nullspace=neumann, nullspace_basis=kernel,
                               max_vectors=int(max_vectors), goal=self.deflate_goal)
        kept = _probe_helps(info, again)
        info["local_solve"].update(probe_factor=again["probe_factor"], kept=kept)
        if not kept:
            L.presmoother, L.postsmoother = pre, post
            return Z
        info.update(vectors=int(Z2.shape[1]), factors=again["factors"])
        return Z2

    def _add_subdomain_solve(self, k: int, region: np.ndarray, report: dict) -> tuple | None:
        """Add an exact solve on ``region`` to level ``k``'s smoothers; return the previous ``(pre, post)``,
        or None (``report`` says why: ``singular`` block, or ``refused_fill``: its factor would cost more than
        a sweep of the level)."""
        L = self.levels[k]
        rows = L.A[region]
        lu = subdomain_factor(L.A, region, rows)
        if lu is None:  # e.g. the extra kernel of a rank-deficient coarse level: nothing to solve there
            report["singular"] = True
            return None
        if lu.L.nnz + lu.U.nnz > L.A.nnz:  # dearer than a sweep of the level: no longer a local fix
            report["refused_fill"] = int(lu.L.nnz + lu.U.nnz)
            return None
        pre, post = L.presmoother, L.postsmoother
        L.presmoother = with_subdomain_solve(pre, L.A, region, factor=lu, rows=rows)
        L.postsmoother = with_subdomain_solve(post, L.A, region, first=True, factor=lu, rows=rows)
        return pre, post

    def _level_kernel(self, k: int) -> np.ndarray | None:
        """Orthonormal basis of level ``k``'s kernel kept out of the deflation probe (beyond the constant of
        ``nullspace="constant"``): none here, the rigid-body modes in
        :class:`solvers.elasticity.NullspaceMultigridSolver`."""
        return None

    def _reorder(self, A, Ps, ordering, given, symmetric, shared=False):
        """Apply the internal orders of every level (see ``ordering``) to ``A``, ``Ps`` and the given coarse
        operators; set ``self.perm``. Returns them, the restrictions ``Rs`` (``Pᵀ`` in CSR, one transpose per
        level, reused by the cycle) and whether ``A`` is symmetric (``symmetric`` if not None, else tested:
        on the permuted copy's by-product transpose when reordering). ``shared``: ``A`` holds the caller's
        arrays, copied when the caller's order is kept (the permuted matrix is a new one)."""
        if ordering not in ("auto", "locality", None):
            raise SolverInputError(f"ordering must be 'auto', 'locality' or None, got {ordering!r}")
        self.perm = None
        keep = (not Ps or ordering is None or any((np.diff(P.indptr) == 0).any() for P in Ps)  # unreached row
                or (ordering == "auto" and (A.shape[0] < ORDER_MIN_N
                                            or index_spread(A, SPREAD_STRIDE) <= ORDER_MIN_SPREAD)))
        if keep:
            A = A.copy() if shared else A
            Ps = [P.copy() for P in Ps]  # the caller's arrays are never shared (the permuted ones are new)
            return (A, Ps, [sp.csr_matrix(P.T) for P in Ps], list(given),
                    _is_symmetric(A) if symmetric is None else bool(symmetric))
        orders = locality_order(Ps)
        self.perm = orders[0]
        if symmetric is False:
            Ap = permute_symmetric(A, orders[0])
        else:  # one transpose, and two probe products when untold (a second transpose if not symmetric)
            # the transpose sorts the rows: left in A's column order the fine sweeps and products cost ~12%
            # more solve time on 1M-tet user matrices (bunny.off, TetWild), more than the set-up saved
            Ap, symmetric = permute_symmetric_transpose(A, orders[0], probe=symmetric is None)
        PRs = [permute_prolongation(P, orders[k], orders[k + 1], with_transpose=True) for k, P in enumerate(Ps)]
        given = [permute_symmetric(G, orders[k + 1]) for k, G in enumerate(given)]
        return Ap, [P for P, _ in PRs], [R for _, R in PRs], given, bool(symmetric)

    def _to_internal(self, v: np.ndarray) -> np.ndarray:
        return v if self.perm is None else v[self.perm]

    def _to_caller(self, v: np.ndarray) -> np.ndarray:
        if self.perm is None:
            return v
        out = np.empty_like(v)
        out[self.perm] = v
        return out

    # ------------------------------------------------------------------ description
    def __repr__(self) -> str:
        cs = self._coarse_solver
        fallback = " (fallback: SuperLU failed validation)" if cs.fallback else ""
        rows = [
            ("Number of levels", f"{len(self.levels)}"),
            ("Coarse operators", self.coarse),
            ("Smoothers (pre/post)", self._smoother_desc()),
            ("Null space", f"{self.nullspace}"),
            ("Coarsest solver", (f"{cs.method}{' (dense)' if cs.dense else ''}{fallback} (null vectors: "
                                 f"{self.coarse_nullity if self.coarse_nullity >= 0 else 'not computed'})")),
            ("Operator complexity", f"{self.operator_complexity():.3f}"),
            ("Grid complexity", f"{self.grid_complexity():.3f}"),
            (f"Cycle complexity ({self.cycle})", f"{self.cycle_complexity():.3f} fine SpMVs"),
            ("Deflation", self._deflation_desc()),
            ("Strong couplings", self._strong_desc()),
        ]
        lines = ["MultigridSolver"] + [f"{k + ':':22s}{v}" for k, v in rows]
        lines.append("  level   unknowns     nonzeros   nnz/row     nnz(P)")
        for k, L in enumerate(self.levels):
            n = L.A.shape[0]
            nnzp = "" if L.P is None else f"{L.P.nnz:10d}"
            lines.append(f"{k:7d} {n:10d} {L.A.nnz:12d} {L.A.nnz / n:9.1f} {nnzp:>10}")
        return "\n".join(lines)

    def _deflation_desc(self) -> str:
        used = [f"level {d['level']}: " + ", ".join(
                    ([f"{d['vectors']} modes"] if d["vectors"] else [])
                    + ([f"local solve on {d['local_solve']['nodes']} unknowns"]
                       if d.get("local_solve", {}).get("kept") else []))
                + f" (probe {d['probe_factor']:.2f})"
                for d in self.deflation if d["vectors"] or d.get("local_solve", {}).get("kept")]
        lp = self.local_probe
        if lp and lp["kept"]:
            used.insert(0, f"level 0: local solve on {lp['nodes']} unknowns ({lp['cycles']}-cycle probe)")
        if used:
            return "; ".join(used)
        return "none" + (f" (probe factors <= {max(d['probe_factor'] for d in self.deflation):.2f})"
                         if self.deflation else "")

    def _strong_desc(self) -> str:
        sb = self.strong_blocks
        if sb is None:
            return "off"
        head = f"theta {sb['theta']:g}: "
        if sb["installed"]:
            return head + f"exact solve on {sb['nodes']} fine unknowns"
        if not sb["nodes"]:
            return head + "none"
        why = ("more than a tenth of the unknowns" if sb.get("refused_size")
               else "singular block" if sb.get("singular") else "factor dearer than a sweep")
        return head + f"{sb['nodes']} unknowns, not solved ({why})"

    def _smoother_desc(self) -> str:
        if len(self.levels) < 2:
            return "none (direct solve)"
        L = self.levels[0]
        return f"{L.presmoother.name}{L.presmoother.params} / {L.postsmoother.name}{L.postsmoother.params}"

    @property
    def coarsest_solver(self) -> dict:
        """How the coarsest level is solved: ``method`` (``"splu"``, ``"guarded"``, ``"pivoted"``,
        ``"regularized"`` or ``"pinv"``),
        ``dense``, ``fallback`` (SuperLU failed its validation), ``unknowns`` and ``nullity`` (-1: not
        computed)."""
        cs = self._coarse_solver
        return {"method": cs.method, "dense": bool(cs.dense), "fallback": bool(cs.fallback),
                "unknowns": int(self.levels[-1].A.shape[0]), "nullity": int(self.coarse_nullity)}

    def operator_complexity(self) -> float:
        """``sum_k nnz(A_k) / nnz(A_0)``."""
        return sum(L.A.nnz for L in self.levels) / self.levels[0].A.nnz

    def grid_complexity(self) -> float:
        """``sum_k n_k / n_0``."""
        return sum(L.A.shape[0] for L in self.levels) / self.levels[0].A.shape[0]

    def _visits(self, cycle: str) -> np.ndarray:
        """How many times each level is smoothed (or, coarsest, solved) in one cycle."""
        counts = np.zeros(len(self.levels))

        def walk(k, c):
            counts[k] += 1
            if k == len(self.levels) - 1:
                return
            if k + 1 == len(self.levels) - 1:
                counts[k + 1] += 1
                return
            if c == "V":
                walk(k + 1, "V")
            elif c == "W":
                walk(k + 1, "W")
                walk(k + 1, "W")
            else:
                walk(k + 1, "F")
                walk(k + 1, "V")

        walk(0, cycle)
        return counts

    def cycle_complexity(self, cycle: str | None = None) -> float:
        """Work of one cycle in units of one SpMV with the fine operator (``nnz(A_0)`` flops pairs).

        Per visit of level ``k``: pre- and post-smoothing (``Smoother.work`` SpMVs each), one residual
        SpMV, restriction and interpolation (``2 nnz(P_k)``); the coarsest level costs the two
        triangular solves (``nnz(L) + nnz(U)``). Vector updates are not counted. Measured wall-clock
        cost is higher in Python (see the report in the docs / benchmarks). ``cycle``: default
        :attr:`cycle`.
        """
        cycle = self._check_cycle(self.cycle if cycle is None else cycle)
        visits = self._visits(cycle)
        work = 0.0
        for k, L in enumerate(self.levels):
            if L.P is None:
                w = self._coarse_solver.nnz
            else:
                w = (L.presmoother.work + L.postsmoother.work + 1.0) * L.A.nnz + 2.0 * L.P.nnz
            work += visits[k] * w
        return float(work / self.levels[0].A.nnz)

    # ------------------------------------------------------------------ cycling
    @staticmethod
    def _check_cycle(cycle: str) -> str:
        if cycle not in ("V", "W", "F"):
            raise SolverInputError(f"cycle must be 'V', 'W' or 'F', got {cycle!r}")
        return cycle

    def _cycle(self, k: int, x: np.ndarray, b: np.ndarray, cycle: str, check: bool = False,
               zero: bool = False) -> None:
        """One cycle on level ``k``: x is updated in place (``zero``: ``x`` is zero on entry, which the
        pre-smoother may exploit: :meth:`solvers.smoothing.Smoother.residual`)."""
        L = self.levels[k]
        A = L.A
        r = L.presmoother.residual(A, x, b, zero)
        if check:
            self._check_finite(x, k, "pre-smoothing")
        bc = L.R @ r
        if self.nullspace == "constant":
            bc -= bc.mean()
        if check:
            self._check_finite(bc, k + 1, "restriction")
        if k + 1 == len(self.levels) - 1:
            xc = self._coarse_solver(bc)
            if check:
                self._check_finite(xc, k + 1, "coarsest direct solve")
        else:
            xc = np.zeros_like(bc)
            if cycle == "V":
                self._cycle(k + 1, xc, bc, "V", check, zero=True)
            elif cycle == "W":
                self._cycle(k + 1, xc, bc, "W", check, zero=True)
                self._cycle(k + 1, xc, bc, "W", check)
            else:  # F: an F-cycle then a V-cycle on the coarser level
                self._cycle(k + 1, xc, bc, "F", check, zero=True)
                self._cycle(k + 1, xc, bc, "V", check)
        e = L.P @ xc
        if self.coarse_scaling == "energy":
            den = float(e @ (A @ e))
            if den > 0:
                e *= float(r @ e) / den
        x += e
        if check:
            self._check_finite(x, k, "coarse-grid correction")
        L.postsmoother(A, x, b)
        if check:
            self._check_finite(x, k, "post-smoothing")

    @staticmethod
    def _check_finite(v, level, stage):
        if not np.all(np.isfinite(v)):
            raise _NonFinite(level, stage)

    def _locate_nan(self, x_prev, b, cycle) -> tuple[int | None, str]:
        """Re-run one cycle with checks on every level to name where NaN/inf first appears."""
        try:
            if len(self.levels) == 1:
                self._check_finite(self._coarse_solver(b), 0, "direct solve")
            else:
                self._cycle(0, x_prev.copy(), b, cycle, check=True)
        except _NonFinite as e:
            return e.level, e.stage
        return None, "unknown (not reproducible)"

    def _one(self, x, b, cycle, zero: bool = False):
        if len(self.levels) == 1:
            x[:] = self._coarse_solver(b)
        else:
            self._cycle(0, x, b, cycle, zero=zero)

    def _prepare_rhs(self, b, project: bool) -> np.ndarray:
        n = self.levels[0].A.shape[0]
        b = np.asarray(b)
        if b.ndim == 2 and b.shape[1] == 1:
            b = b[:, 0]
        if b.shape != (n,):
            raise SolverInputError(f"b must have shape ({n},), got {b.shape}")
        b = np.array(b, dtype=np.float64)  # a copy: never touch the caller's array
        if not np.all(np.isfinite(b)):
            raise SolverInputError(f"b contains {np.count_nonzero(~np.isfinite(b))} NaN/inf entries")
        if self.nullspace == "constant":
            if project:
                b -= b.mean()
            else:
                from .fem import check_compatible

                check_compatible(b)
        return b

    @under_one_blas_thread  # the cycles' BLAS calls are short: threads only spin (solvers._threads)
    def solve(
        self,
        b,
        x0=None,
        tol: float = 1e-8,
        maxiter: int = DEFAULT_MAXITER,
        cycle: str | None = None,
        accel: str | None = None,
        residuals: list | None = None,
        *,
        project: bool = False,
        divtol: float = 1e5,
        return_info: bool = False,
    ):
        """Solve ``A x = b`` by multigrid cycles (or CG preconditioned by one cycle).

        Parameters
        ----------
        b : (n_0,) array_like
        x0 : (n_0,) array_like, optional (default zeros)
        tol : float
            Stop when ``||b - A x|| <= tol ||b||`` (2-norms).
        maxiter : int
            Maximum number of cycles (or CG iterations); default :data:`DEFAULT_MAXITER`.
        cycle : {"V", "W", "F"}, optional
            Default :attr:`cycle` (the constructor's, ``"V"`` unless given).
        accel : None or "cg"
            ``"cg"``: conjugate gradients (:func:`solvers.krylov.pcg`) preconditioned by one cycle from zero: the one
            MG-PCG entry point of the package (``nestmg.solve_on_hierarchy`` and the CLI call it).
        residuals : list, optional
            Cleared and filled with the relative residuals ``||b - A x_i|| / ||b||``, ``i = 0..iters``
            (``residuals[0]`` is that of ``x0``).
        project : bool
            With ``nullspace="constant"``: remove the mean of an incompatible ``b`` instead of raising
            :class:`IncompatibleRHSError`.
        divtol : float
            Raise :class:`DivergenceError` when the residual exceeds ``divtol`` times the initial one.
        return_info : bool
            Also return a dict ``{iterations, converged, residuals, factor, seconds}``.

        Returns
        -------
        x : (n_0,) float64 (zero plain mean when ``nullspace="constant"``)
        info : dict, only with ``return_info=True``

        Raises
        ------
        DivergenceError
            NaN/inf (naming the cycle and the level where it first appeared) or residual growth.
        IncompatibleRHSError
            Neumann problem with ``sum(b) != 0`` and ``project=False``.
        """
        cycle = self._check_cycle(self.cycle if cycle is None else cycle)
        if accel not in (None, "cg"):
            raise SolverInputError(f"accel must be None or 'cg', got {accel!r}")
        maxiter = int(maxiter)
        if maxiter < 0:
            raise SolverInputError(f"maxiter must be >= 0, got {maxiter}")
        b = self._to_internal(self._prepare_rhs(b, project))
        if accel is None:
            self.probe()  # a probe deferred by probe_at="stationary" (its time is not in info["seconds"])
        n = b.size
        A = self.levels[0].A
        if x0 is None:
            x = np.zeros(n)
        else:
            x = np.array(np.asarray(x0).reshape(-1), dtype=np.float64)
            if x.shape != (n,) or not np.all(np.isfinite(x)):
                raise SolverInputError(f"x0 must be a finite array of shape ({n},)")
            x = self._to_internal(x)
        t0 = time.perf_counter()
        normb = float(np.linalg.norm(b))
        hist: list[float] = []
        res = None  # pcg's result (accel="cg")
        if normb == 0.0:
            x[:] = 0.0
            hist = [0.0]
        elif accel == "cg":
            from .krylov import pcg

            if not self.symmetric_cycle:
                warnings.warn(
                    "accel='cg' with a non-symmetric cycle (non-symmetric operators or non-adjoint pre/post "
                    "smoothers): CG may stall; use adjoint smoothers (postsmoother=None)",
                    stacklevel=3,
                )

            res = pcg(A, b, M=self._preconditioner(cycle), x0=x, tol=tol, maxiter=maxiter,
                      nullspace=self.nullspace, divtol=divtol, flexible=self.coarse_scaling is not None)
            x, hist = res.x, res.residuals
            if res.nonfinite:
                level, stage = self._locate_nan(np.zeros(n), b, cycle)
                raise DivergenceError(
                    f"MG-preconditioned CG produced NaN/inf in preconditioner {cycle}-cycle {res.iterations}; first "
                    f"non-finite value on level {level} during {stage}",
                    cycle=res.iterations, level=level, residuals=hist,
                )
        else:
            rel = float(np.linalg.norm(b - A @ x)) / normb
            hist = [rel]
            it = 0
            while rel > tol and it < maxiter:
                x_prev = x.copy()
                self._one(x, b, cycle)
                it += 1
                rel = float(np.linalg.norm(b - A @ x)) / normb
                hist.append(rel)
                if not np.isfinite(rel) and np.all(np.isfinite(x)):  # finite iterate, overflowing norm
                    raise DivergenceError(
                        f"{cycle}-cycle {it} diverges: the residual norm overflowed (max |x| = "
                        f"{np.abs(x).max():.3g}; relative residual before this cycle {hist[-2]:.3g})",
                        cycle=it, level=None, residuals=hist,
                    )
                if not np.isfinite(rel):
                    level, stage = self._locate_nan(x_prev, b, cycle)
                    raise DivergenceError(
                        f"{cycle}-cycle {it} produced NaN/inf; first non-finite value on level {level} "
                        f"during {stage}",
                        cycle=it, level=level, residuals=hist,
                    )
                if rel > divtol * hist[0]:
                    raise DivergenceError(
                        f"{cycle}-cycle {it} diverges: residual grew by {rel / hist[0]:.3g} (> divtol={divtol:g}); "
                        f"recent factor per cycle {convergence_factor(hist, 3):.3g}. Inconsistent coarse "
                        "operators or prolongations (e.g. extrapolation outside the coarse mesh)?",
                        cycle=it, level=None, residuals=hist,
                    )
        if self.nullspace == "constant":
            x -= x.mean()
        x = self._to_caller(x)
        seconds = time.perf_counter() - t0
        converged = hist[-1] <= tol
        if not converged and res is not None and res.stagnated:
            floor = "" if res.attainable is None else (
                f"; round-off alone allows about {res.attainable:.1e} here (eps ||A|| ||x|| / ||b||)")
            warnings.warn(
                f"MG-PCG stagnated: no smaller residual in the last {STALL_ITERATIONS} of {len(hist) - 1} "
                f"iterations; returned the best iterate, relative residual {hist[-1]:.3e} > tol={tol:g}"
                f"{floor}. "
                "Ask for a larger tol, or check the preconditioner",
                ConvergenceWarning,
                stacklevel=3,
            )
        elif not converged:
            why = "" if res is None or res.breakdown is None else f": CG broke down, {res.breakdown}"
            warnings.warn(
                f"multigrid stopped after {len(hist) - 1} iterations at relative residual {hist[-1]:.3e} > tol={tol:g}"
                f"{why}",
                ConvergenceWarning,
                stacklevel=3,
            )
        if residuals is not None:
            residuals[:] = hist
        if return_info:
            return x, {
                "iterations": len(hist) - 1,
                "converged": bool(converged),
                "residuals": list(hist),
                "factor": convergence_factor(hist),
                "seconds": seconds,
            }
        return x

    def aspreconditioner(self, cycle: str | None = None) -> spla.LinearOperator:
        """One cycle (default :attr:`cycle`) from zero as a ``scipy.sparse.linalg.LinearOperator``.

        Usable as ``M=`` in ``scipy.sparse.linalg.cg``. Symmetric positive definite when the operators
        are SPD and the pre/post smoothers are adjoint. With ``nullspace="constant"`` input and output are
        projected to zero mean.
        """
        M = self._preconditioner(self.cycle if cycle is None else cycle)
        if self.perm is None:
            return M

        def matvec(b):
            return self._to_caller(M.matvec(self._to_internal(np.asarray(b, dtype=np.float64).reshape(-1))))

        return spla.LinearOperator(M.shape, matvec=matvec, rmatvec=matvec, dtype=np.float64)

    def _preconditioner(self, cycle: str) -> spla.LinearOperator:
        """One cycle from zero in the internal order (what ``solve(accel="cg")`` uses)."""
        cycle = self._check_cycle(cycle)
        n = self.levels[0].A.shape[0]

        def matvec(b):
            b = np.asarray(b, dtype=np.float64).reshape(-1)
            if self.nullspace == "constant":
                b = b - b.mean()
            x = np.zeros(n)
            with one_blas_thread():
                self._one(x, b, cycle, zero=True)
            if self.nullspace == "constant":
                x -= x.mean()
            return x

        return spla.LinearOperator((n, n), matvec=matvec, rmatvec=matvec, dtype=np.float64)


def _permuted_nodes(nodes, perm):
    """The caller's level-0 node set (indices or mask) in the internal order ``perm``."""
    if nodes is None or perm is None:
        return nodes
    idx = np.asarray(nodes)
    if idx.dtype == bool:
        return idx[perm] if idx.shape == perm.shape else idx  # a wrong shape is reported by _local_sets
    idx = idx.astype(np.int64)
    if idx.size and (idx.min() < 0 or idx.max() >= perm.size):
        return idx
    inv = np.empty_like(perm)
    inv[perm] = np.arange(perm.size, dtype=perm.dtype)
    return inv[idx]


def _local_sets(nodes, Ps, levels, n0) -> list:
    """Per-level node sets of the local sweeps: ``nodes`` on level 0, then on level ``k+1`` the coarse
    nodes whose basis functions reach the set of level ``k`` (the columns of ``P_k`` in those rows)."""
    out: list = [None] * (len(Ps) + 1)
    if nodes is None:
        return out
    idx = np.asarray(nodes)
    if idx.dtype == bool:
        if idx.shape != (n0,):
            raise SolverInputError(f"local_nodes as a mask needs shape ({n0},), got {idx.shape}")
        idx = np.flatnonzero(idx)
    idx = np.unique(idx.astype(np.int64))
    if idx.size and (idx[0] < 0 or idx[-1] >= n0):
        raise SolverInputError(f"local_nodes must lie in [0, {n0}), got [{idx[0]}, {idx[-1]}]")
    last = len(Ps) if levels is None else min(int(levels), len(Ps))
    for k in range(last):
        out[k] = idx
        idx = np.unique(Ps[k][idx].indices).astype(np.int64)
    return out


def _default_level_specs(ops, specs) -> list:
    """The default cycle's specs: :data:`COARSE_SWEEPS` sweeps on the coarse levels as sparse as the finest,
    one on the dense ones (see :data:`DENSE_LEVEL_ROWS`)."""
    fine = ops[0].nnz / max(ops[0].shape[0], 1)

    def sweeps(n):
        return (DEFAULT_SMOOTHER[0], dict(DEFAULT_SMOOTHER[1], iterations=n))

    return [spec if k == 0 else sweeps(1 if ops[k].nnz / max(ops[k].shape[0], 1) > DENSE_LEVEL_ROWS * fine
                                       else COARSE_SWEEPS)
            for k, spec in enumerate(specs)]


def _level_specs(spec, n_smoothed: int) -> list:
    """One smoother spec per smoothed level: a single spec for all, or a list (one per level, the
    last one repeated on deeper levels), as pyamg's per-level smoother lists."""
    single = isinstance(spec, (str, Smoother)) or (
        isinstance(spec, (tuple, list)) and len(spec) == 2 and isinstance(spec[0], str)
        and (spec[1] is None or isinstance(spec[1], dict)))
    if single or n_smoothed == 0:
        return [spec] * n_smoothed
    specs = list(spec)
    if not specs:
        raise SolverInputError("a per-level smoother list needs at least one spec")
    return [specs[min(k, len(specs) - 1)] for k in range(n_smoothed)]


def _spec_parts(spec):
    if isinstance(spec, str):
        return spec, {}
    if isinstance(spec, (tuple, list)) and len(spec) == 2 and isinstance(spec[0], str):
        return spec[0], dict(spec[1] or {})
    return None, None


def _adjoint_spec(spec):
    """Spec of the adjoint smoother: forward <-> backward Gauss-Seidel, everything else unchanged."""
    name, opts = _spec_parts(spec)
    if name in ("gauss_seidel", "block_gauss_seidel"):
        sweep = opts.get("sweep", "forward")
        if name == "block_gauss_seidel" and sweep == "symmetric":
            return spec  # self-adjoint: shared with the pre-smoother (one colouring and block set-up)
        opts["sweep"] = {"forward": "backward", "backward": "forward"}.get(sweep, sweep)
        return (name, opts)
    return spec


def _smoothers_adjoint(pre: Smoother, post: Smoother) -> bool:
    if pre.name != post.name:
        return False
    if pre.name in ("gauss_seidel", "symmetric_gauss_seidel", "block_gauss_seidel"):
        flip = {"forward": "backward", "backward": "forward", "symmetric": "symmetric"}
        a, b = pre.params, post.params
        return (flip[a["sweep"]] == b["sweep"] and a["iterations"] == b["iterations"] and a["omega"] == b["omega"]
                and flip[a.get("local_sweep", "symmetric")] == b.get("local_sweep", "symmetric")
                and a.get("local_nodes") == b.get("local_nodes") and a.get("local_sweeps") == b.get("local_sweeps"))
    return pre.params == post.params


class _NonFinite(Exception):
    def __init__(self, level, stage):
        super().__init__(f"non-finite value on level {level} during {stage}")
        self.level, self.stage = level, stage


# re-exported for convenience
__all__ += ["ConvergenceWarning", "IncompatibleRHSError"]
