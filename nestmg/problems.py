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

import logging
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from solvers.fem import boundary_layer_nodes, boundary_nodes, check_tet_mesh, mass_matrix, stiffness_matrix
from solvers.multilevel import restrict_prolongations, sparsified_galerkin_operators

from .errors import NestmgInputError

_log = logging.getLogger(__name__)

if TYPE_CHECKING:
    from .options import SolverOptions

__all__ = ["COARSE", "FACTOR_GOALS", "FAST_NEUMANN_SMOOTHERS", "FAST_SMOOTHERS", "PROBE_MARGIN", "PROBLEMS",
           "SMOOTHING", "Problem", "default_rhs", "setup_problem", "volume_fractions"]

PROBLEMS = ("poisson-dirichlet", "poisson-neumann", "diffusion-neumann")

#: The V-cycle factor the defaults aim at, per problem (issue 27, item 3): :meth:`Problem.multigrid`
#: deflates the slow modes of a level whose probe is above it (``MultigridSolver(deflate_goal=)``; other
#: problems: :data:`solvers.deflation.DEFLATION_GOAL`). On idler_riser.stl some TetWild meshes left one
#: Dirichlet mode at 0.21-0.26 under the former single goal 0.3 (1 in 10: 0.223 -> 0.161 deflated,
#: benchmarks/results/corpus/idler_deflation_goal_8c7c925.json).
FACTOR_GOALS = {"poisson-dirichlet": 0.2, "poisson-neumann": 0.3, "diffusion-neumann": 0.3}

#: The probe's goal is this fraction of the problem's :data:`FACTOR_GOALS` (``deflate_goal``). A probe
#: estimate just under the goal left the measured factor at the goal: homer.obj's and cheburashka.obj's
#: Neumann probes read 0.298 / 0.293, their factors 0.296 / 0.299 (corpus zoo_cb3e803_merged.json); on three
#: lucy.ply hierarchies the margin took Neumann 0.268-0.283 to 0.232-0.259 (lucy_probe_margin_43baf99.json).
PROBE_MARGIN = 0.9

#: ``poisson-dirichlet`` with Galerkin coarse operators: when at least this fraction of the first coarse
#: level's nodes coincide with fine Dirichlet nodes (a prolongation row ``e_j`` on a boundary node: the
#: same-domain level below a red refinement), those coarse nodes are dropped, i.e. the coarse space is the
#: conforming ``V_H ∩ V_h,0`` of textbook geometric multigrid instead of every coarse node the free fine
#: nodes reach. On thin-walled parts most of that level sits on the boundary: a cup with walls 1% of its
#: height (93% there) had operator complexity 1.80, without them 1.01, V-cycle factor 0.025 -> 0.065, MG-PCG
#: 4 -> 5 iterations, set-up + solve CPU 0.267 -> 0.073 s; a sphere shell with a window (83%) 1.55 -> 1.07.
#: On solid shapes (26-57%) they pay for themselves: dropping them raised the factors to 0.157-0.201 and
#: cost 1-2 more MG-PCG iterations (``benchmarks/results/dirichlet/dirichlet_coarse_388b75f.json``).
CONFORMING_MIN_FRACTION = 0.75


def cycle_smoothers(smoother: str = "gauss_seidel", nu: int = 2, coarse_nu: int | None = None) -> list:
    """Per-level smoother specs of a variable V-cycle, finest level first (the default: the pipeline's cycle,
    ``MultigridSolver``'s default, on a hierarchy whose coarse levels are as sparse as its finest).

    ``nu`` sweeps of ``smoother`` on the fine level and ``coarse_nu`` (default ``2 * nu``) on every
    coarser one (``MultigridSolver(presmoother=...)``).
    """
    cnu = 2 * nu if coarse_nu is None else coarse_nu
    return [(smoother, {"iterations": nu}), (smoother, {"iterations": cnu})]


#: The pipeline's smoothers written out, finest level first: two forward Gauss–Seidel sweeps before the
#: coarse correction (and two backward after it) on the fine level, four on the coarser ones (a variable
#: V-cycle; the coarse levels are ~8x smaller, so the extra sweeps cost ~0.5 fine SpMV per cycle): the
#: default cycle of ``MultigridSolver`` (:data:`solvers.multilevel.DEFAULT_SMOOTHER`), which the pipeline
#: uses, on a hierarchy without dense coarse levels (:data:`solvers.multilevel.DENSE_LEVEL_ROWS`).
DEFAULT_SMOOTHERS = cycle_smoothers()

#: The textbook V(1,1) cycle: one forward Gauss–Seidel sweep before the coarse-grid correction and one
#: backward sweep after it (the adjoint, so the cycle is symmetric and preconditions CG) on every level,
#: no local sweeps. A weaker cycle than :data:`DEFAULT_SMOOTHERS` but about half its cost; under CG it
#: is the faster choice in wall time at 1M tets (docs/reuse.md, "Which cycle under CG").
FAST_SMOOTHERS = [("gauss_seidel", {"sweep": "forward", "iterations": 1})]

#: The ``"fast"`` preset on pure Neumann problems (:attr:`Problem.nullspace` ``"constant"``): the
#: textbook V(1,1) on the fine level, two forward / backward sweeps on the coarser levels (~0.35 fine
#: SpMV more per cycle: they hold ~15 % of the nonzeros), plus one forward sweep over the fine
#: boundary layer before the coarse correction and one backward sweep after it
#: (``local_sweep="one-way"``): under natural boundary conditions Gauss–Seidel is weakest there.
#: Measured at 1M tets: 9–10 MG-PCG iterations instead of 13–14, 5–18 % less wall time (docs/reuse.md).
FAST_NEUMANN_SMOOTHERS = [("gauss_seidel", {"sweep": "forward", "iterations": 1}),
                          ("gauss_seidel", {"sweep": "forward", "iterations": 2})]

#: Names of :meth:`Problem.multigrid`'s smoothing presets.
SMOOTHING = ("robust", "fast")


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
    coarse : "galerkin" or list of csr_matrix
        The coarse operators as :class:`solvers.MultigridSolver` takes them: ``"galerkin"`` (the solver
        forms ``Pᵀ A P``) or the built ones ``[A_1, ..., A_L]`` (re-discretised, weighted, sparsified);
        the name asked of :func:`setup_problem` is ``params["coarse"]``.
    free : list of int arrays
        Free node indices on every level.
    n_fine : int
        Number of fine nodes (for :meth:`expand`).
    nullspace : str or None
        ``"constant"`` for pure Neumann problems.
    params : dict
    local_nodes : int array or None
        Free-node indices (level-0 numbering of ``A``) that get extra local Gauss–Seidel sweeps: the
        boundary layer (boundary nodes and one tet ring) of Neumann and diffusion problems, where
        natural boundary conditions make the global smoother weakest (docs/scale.md).
    fixed_values : (n_fine,) float array or None
        Dirichlet values on the fine nodes (P2 problems with ``boundary_values``); :meth:`expand`
        puts them back (None: zero).
    mesh : nestmg.curved.CurvedMesh or None
        The quadratic mesh of ``element="P2"`` problems (nodes ``mesh.X``, ``tetra10`` cells ``mesh.T10``).
    """

    name: str
    A: sp.csr_matrix
    b: np.ndarray
    P: list
    coarse: str | list
    free: list
    n_fine: int
    nullspace: str | None
    params: dict = field(default_factory=dict)
    local_nodes: np.ndarray | None = None
    fixed_values: np.ndarray | None = None
    mesh: object | None = None

    def multigrid(self, options: SolverOptions | None = None, **kwargs):
        """The :class:`solvers.MultigridSolver` of this problem (its coarse operators and null space).

        Parameters
        ----------
        options : SolverOptions, optional
            Its smoothing fields are used (``coarse``, ``lam``, ``poisson_ratio`` were the problem's,
            :func:`setup_problem`; the solve's are :meth:`solvers.MultigridSolver.solve`'s):

            * ``smoothing="robust"`` (default): ``MultigridSolver``'s default cycle
              (:data:`solvers.multilevel.DEFAULT_SMOOTHER`; written out on nestmg's hierarchies:
              :data:`DEFAULT_SMOOTHERS`), or with ``smoother``, ``nu`` or ``coarse_nu`` given ``nu`` sweeps
              of ``smoother`` on the fine level and ``coarse_nu`` (default ``2 nu``) on the coarser ones
              (:func:`cycle_smoothers`); plus with ``local`` sweeps over :attr:`local_nodes` (the
              problem's boundary layer, natural-boundary problems only): with the default sweeps one forward
              sweep before the coarse correction and one backward after it on the fine level
              (``local_sweep="one-way"``, ``local_levels=1``), with chosen ones one extra symmetric sweep
              per smoothing step on every level (the cycle before issue 31's one default). The one default
              of the bare constructor, ``Problem.multigrid()`` and ``aspreconditioner()``: what the problem
              adds is its null space, boundary layer, factor goal and the finest level's probe for
              stationary cycling;
            * ``smoothing="fast"``: the textbook V(1,1) of :data:`FAST_SMOOTHERS` without local sweeps
              (about half the cost per cycle, a few more CG iterations; the faster MG-PCG in wall time),
              except on pure Neumann problems (``nullspace="constant"``), where it is
              :data:`FAST_NEUMANN_SMOOTHERS` with one-way sweeps over the fine boundary layer
              (``local=False`` drops them);
            * ``coarse_scaling``: ``"auto"`` is ``"energy"`` with re-discretised or weighted coarse
              operators (they are not energy projections; docs/coarse.md), None with Galerkin ones.
            * every level, the finest included (``probe_finest=True``), is probed for a few slow modes,
              which are then deflated (:mod:`solvers.deflation`; ``deflate=0`` turns it off) when the
              probe is above :data:`PROBE_MARGIN` times the problem's goal (:data:`FACTOR_GOALS`), as
              ``MultigridSolver``'s ``deflate="auto"`` decides (within its operator complexity bound); the
              finest level's probe runs at the first stationary solve (``probe_at="stationary"``):
              ``solve(accel="cg")`` and ``aspreconditioner()`` skip it;
            * ``cycle`` (default V) becomes the solver's :attr:`~solvers.MultigridSolver.cycle`, the one its
              ``solve`` and ``aspreconditioner`` run when given none.

            ``nu`` and ``cycle`` not set are filled in by :meth:`nestmg.SolverOptions.resolved`.
        **kwargs
            Passed on to :class:`solvers.MultigridSolver` (``presmoother``, ``local_nodes``,
            ``coarse_solver``, ``block``, ...), overriding what ``options`` chose.

        Returns
        -------
        solvers.MultigridSolver
        """
        from solvers import MultigridSolver
        from solvers.multilevel import DEFAULT_SMOOTHER as SOLVER_DEFAULT

        from .options import DEFAULT_NU, DEFAULT_SMOOTHER, SolverOptions, typed

        o = typed(options, SolverOptions, "options").resolved(self.name)  # V, nu = 2 unless given
        coarse_scaling = o.coarse_scaling
        if coarse_scaling == "auto":
            coarse_scaling = None if isinstance(self.coarse, str) else "energy"
        fast = o.smoothing == "fast"
        fast_layer = fast and o.local and self.nullspace == "constant" and self.local_nodes is not None
        # the solver's own default (its rule for dense coarse levels) unless the sweeps were chosen
        default = (o.smoother, o.nu, o.coarse_nu) == (DEFAULT_SMOOTHER, DEFAULT_NU, None)
        robust = SOLVER_DEFAULT if default else cycle_smoothers(o.smoother, o.nu, o.coarse_nu)
        kwargs.setdefault("presmoother", FAST_NEUMANN_SMOOTHERS if fast_layer else FAST_SMOOTHERS if fast else robust)
        kwargs.setdefault("local_nodes", self.local_nodes if o.local and (fast_layer or not fast) else None)
        if fast_layer or (default and not fast):  # one-way fine-level layer sweeps, as docs/usermesh.md advises
            kwargs.setdefault("local_sweep", "one-way")
            kwargs.setdefault("local_levels", 1)
        if self.name in FACTOR_GOALS:
            kwargs.setdefault("deflate_goal", PROBE_MARGIN * FACTOR_GOALS[self.name])
        kwargs.setdefault("probe_finest", True)  # the probe costs about one solve: small in a pipeline run
        # ... but it serves the stationary cycle only: MG-PCG and aspreconditioner() never run it
        kwargs.setdefault("probe_at", "stationary")
        kwargs.setdefault("cycle", o.cycle)  # the cycle of solve() and aspreconditioner() given none
        return MultigridSolver(self.A, self.P, coarse=self.coarse, nullspace=self.nullspace,
                               coarse_scaling=coarse_scaling, **kwargs)

    def expand(self, x_free: np.ndarray) -> np.ndarray:
        """Full fine-level vector: ``x_free`` on free nodes, the Dirichlet values (default 0) on the others."""
        x = np.zeros(self.n_fine) if self.fixed_values is None else np.array(self.fixed_values, dtype=np.float64)
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


def volume_fractions(tets: list[tuple[np.ndarray, np.ndarray]], samples: int = 64, seed: int = 0) -> list[np.ndarray]:
    """Fraction of every coarse tet's volume covered by the fine tets (the solid of ``tets[0]``).

    Point location in the fine tet mesh (libigl ``AABB`` + ``in_element``, as behind ``P``): a coarse
    tet whose four corners lie inside the fine mesh and that contains no fine boundary node counts as
    covered (1), one with its corners outside and no fine boundary node as empty (0); the others --
    the tets cut by the fine boundary -- get the share of ``samples`` random points (uniform in the
    tet, independent per tet, fixed seed) that fall inside a fine tet: standard error
    ``<= 0.5 / sqrt(samples)`` per tet.
    Sampling the coarse tets, not the fine ones, keeps the estimate right where the coarse tets near
    a cage are smaller than the fine tets.

    Parameters
    ----------
    tets : list of (V, T)
        Tet meshes, finest first (``Hierarchy.tets``).
    samples : int
        Points per cut coarse tet.
    seed : int
        Seed of the sample points (the result is deterministic).

    Returns
    -------
    list of (t_k,) float arrays
        ``w_0 = 1`` on the fine level, then one array per coarse level.
    """
    import igl

    if samples < 1:
        raise NestmgInputError(f"samples must be >= 1, got {samples}")
    V0 = np.ascontiguousarray(tets[0][0], dtype=np.float64)
    T0 = np.ascontiguousarray(tets[0][1], dtype=np.int64)
    tree = igl.AABB()
    tree.init(V0, T0)
    Xb = np.ascontiguousarray(V0[boundary_nodes(T0)])
    rng = np.random.default_rng(seed)

    def inside(X):
        return np.asarray(igl.in_element(V0, T0, np.ascontiguousarray(X, dtype=np.float64), tree)).ravel() >= 0

    out = [np.ones(len(T0))]
    for Vc, Tc in tets[1:]:
        Vc = np.ascontiguousarray(Vc, dtype=np.float64)
        Tc = np.ascontiguousarray(Tc, dtype=np.int64)
        vin = inside(Vc)[Tc]  # (t, 4) corner inside the fine mesh
        w = vin.all(axis=1).astype(np.float64)
        ctree = igl.AABB()
        ctree.init(Vc, Tc)
        hit = np.asarray(igl.in_element(Vc, Tc, Xb, ctree)).ravel()
        cut = vin.any(axis=1) & ~vin.all(axis=1)
        cut[hit[hit >= 0]] = True
        idx = np.flatnonzero(cut)
        if idx.size:
            bc = rng.dirichlet(np.ones(4), (idx.size, samples))  # uniform in each tet, independent
            X = np.einsum("tsj,tjk->tsk", bc, Vc[Tc[idx]]).reshape(-1, 3)
            w[idx] = inside(X).reshape(len(idx), samples).mean(axis=1)
        out.append(w)
    return out


def _boundary_penalty(K0: sp.csr_matrix, bnd: np.ndarray) -> np.ndarray:
    """Energy the fine Dirichlet condition adds to a constant, per fine boundary node.

    Zeroing the boundary values of the constant 1 leaves the energy ``1_Bᵀ K 1_B = Σ_b d_b`` with
    ``d_b = (K 1_B)_b = -Σ_{j∉B} K_bj``: the Galerkin coarse operator sees the Dirichlet condition as
    this boundary layer. ``Gᵀ diag(d) G`` (``G`` = the boundary rows of the composite prolongation)
    reproduces it on a coarse level with the coarse sparsity (a fine boundary node's row lies in one
    coarse tet).
    """
    ind = np.zeros(K0.shape[0])
    ind[bnd] = 1.0
    return np.maximum((K0 @ ind)[bnd], 0.0)


COARSE = ("galerkin", "rediscretized", "weighted", "sparsified")


def setup_problem(
    tets: list[tuple[np.ndarray, np.ndarray]],
    P: list[sp.csr_matrix],
    name: str = "poisson-dirichlet",
    *,
    coarse: str = "galerkin",
    lam: float = 1e-2,
    f: np.ndarray | None = None,
    prune: float = 0.2,
    fractions: list[np.ndarray] | None = None,
    poisson_ratio: float = 0.3,
    element: str = "P1",
    curved=None,
    boundary_values=None,
    flux=None,
) -> Problem:
    """Assemble a model problem on ``tets[0]`` and the level data for multigrid.

    Parameters
    ----------
    tets : list of (V, T)
        Tet meshes, finest first (``Hierarchy.tets``).
    P : list of (n_k, n_{k+1}) csr_matrix
        Prolongations (``Hierarchy.P``).
    name : {"poisson-dirichlet", "poisson-neumann", "diffusion-neumann", "elasticity-clamped",
            "elasticity-free"}
    coarse : {"galerkin", "rediscretized", "weighted", "sparsified"}
        ``"galerkin"``: the solver forms ``Pᵀ A P``. ``"rediscretized"``: the same FEM problem on every
        coarse tet mesh (Dirichlet on the coarse boundary). ``"weighted"``: re-discretised with every
        coarse tet's stiffness and mass scaled by the fraction of its volume covered by the fine domain
        (:func:`volume_fractions`), and, for ``poisson-dirichlet``, the fine Dirichlet condition as
        the boundary-layer term ``Gᵀ diag(d) G`` (:func:`_boundary_penalty`) instead of a Dirichlet
        condition on the cage: sparse (coarse-mesh sparsity) and consistent with ``Pᵀ A P`` on
        constants. ``"sparsified"``: the Galerkin product of each level moved onto the coarse tet
        mesh's own sparsity by :func:`solvers.reroute_to_pattern` (dropped couplings rerouted along
        two-edge paths; row sums kept; spectrally equivalent), level by level: Galerkin's
        consistency at the re-discretised operator complexity.
    lam : float
        Diffusion coefficient λ of ``diffusion-neumann`` (time step x conductivity).
    f : (n_fine,) float array, optional
        Source at the fine nodes (default :func:`default_rhs`). For ``poisson-neumann`` its
        mass-weighted mean is removed so that the system is compatible.
    prune : float
        Galerkin and weighted: drop coarse nodes whose prolongation column sums to less than this
        (nodes of a cage that barely reach the fine mesh; they make ``P`` rank-deficient) and rescale
        the affected rows to sum to 1 (:func:`solvers.restrict_prolongations`). 0 keeps every reached
        node.
    fractions : list of arrays, optional
        Precomputed :func:`volume_fractions` (``coarse="weighted"``; reuse across problems).
    poisson_ratio : float
        ν of the elasticity problems (``"elasticity-clamped"``, ``"elasticity-free"``: assembled by
        :func:`nestmg.elasticity.setup_elasticity` with ``E = 1``, its default loads and pruning; ``f`` is
        then an (n, 3) body force and ``lam``, ``prune``, ``fractions`` do not apply).
    element : {"P1", "P2"}
        ``"P2"``: quadratic elements on ``tets[0]`` (:func:`nestmg.p2problem.setup_p2_problem`), straight
        or ``curved`` (a :class:`nestmg.curved.CurvedMesh` of ``tets[0]``), with the exact P1 → P2
        interpolation as the first prolongation; ``f`` may then be a function of points, and
        ``boundary_values`` (Dirichlet) / ``flux`` (Neumann) give boundary data on the curved boundary.
        Galerkin coarse operators only.
    curved, boundary_values, flux
        ``element="P2"`` only (see above).

    Returns
    -------
    Problem
    """
    if element not in ("P1", "P2"):
        raise NestmgInputError(f"element must be 'P1' or 'P2', got {element!r}")
    if element == "P2":
        from .p2problem import setup_p2_problem

        return setup_p2_problem(tets, P, name, curved=curved, coarse=coarse, lam=lam, f=f,
                                boundary_values=boundary_values, flux=flux, prune=prune)
    if curved is not None or boundary_values is not None or flux is not None:
        raise NestmgInputError("curved, boundary_values and flux need element='P2'")
    if name in ("elasticity-clamped", "elasticity-free"):
        from .elasticity import setup_elasticity

        return setup_elasticity(tets, P, name, nu=poisson_ratio, coarse=coarse, f=f)
    if name not in PROBLEMS:
        raise NestmgInputError(f"unknown problem {name!r}; choose from {PROBLEMS} or elasticity-clamped, elasticity-free")
    if coarse not in COARSE:
        raise NestmgInputError(f"coarse must be one of {COARSE}, got {coarse!r}")
    if len(P) != len(tets) - 1:
        raise NestmgInputError(f"need len(P) == len(tets) - 1, got {len(P)} and {len(tets)}")
    V0, T0, vol0 = check_tet_mesh(*tets[0], return_volumes=True)  # validated once; assembly skips its check
    n0 = len(V0)
    M0 = mass_matrix(V0, T0, check=False, volumes=vol0)
    f = default_rhs(V0) if f is None else np.asarray(f, dtype=np.float64)
    if f.shape != (n0,):
        raise NestmgInputError(f"f must have shape ({n0},), got {f.shape}")
    m = M0.diagonal()
    K0 = stiffness_matrix(V0, T0, check=False)
    if name == "poisson-neumann":  # zero mass-weighted mean on every body -> M f sums to 0 on each
        body = connected_components(K0, directed=False)[1]  # K0's pattern: the mesh's node graph
        f = f - (np.bincount(body, m * f) / np.bincount(body, m))[body]
    A_full = (lam * K0 + M0).tocsr() if name == "diffusion-neumann" else K0
    b_full = M0 @ f
    dirichlet = name == "poisson-dirichlet"
    bnd = boundary_nodes(T0, stiffness=K0) if dirichlet else np.zeros(0, dtype=np.int64)
    free0 = np.setdiff1d(np.arange(n0), bnd, assume_unique=True) if dirichlet else np.arange(n0)

    # natural boundary: every node is free, no submatrix copy (two O(nnz) fancy-index passes at 1M tets)
    A = A_full[free0][:, free0].tocsr() if dirichlet else A_full.tocsr()
    ops: list[sp.csr_matrix] | None = None
    conforming = None
    if coarse == "rediscretized" and P:
        cand = [np.setdiff1d(np.arange(len(Vc)), boundary_nodes(Tc)) if dirichlet else np.arange(len(Vc))
                for Vc, Tc in tets[1:]]
        Pr, free = restrict_prolongations(P, free0, coarse_free=cand, support_only=dirichlet)
        ops = [_level_operator(name, Vc, Tc, lam)[c][:, c].tocsr() for (Vc, Tc), c in zip(tets[1:], free[1:])]
    elif not P:
        Pr, free = [], [free0]
    else:
        conforming = _conforming_first_level(P, bnd) if dirichlet and coarse == "galerkin" else None
        if conforming is not None and conforming[0][0][free0].nnz == 0:
            Pr, free = [], [free0]  # no coarse node off the boundary (a tiny part): one level, a direct solve
        else:
            Pr, free = restrict_prolongations(P if conforming is None else conforming[0], free0,
                                              min_column_sum=prune)
            Pr, free = _coarsening_levels(Pr, free)
        if coarse == "sparsified":
            # allowed couplings: the edges of each coarse tet mesh among its kept nodes
            pats = [stiffness_matrix(Vc, Tc)[c][:, c] for (Vc, Tc), c in zip(tets[1:], free[1:])]
            ops = sparsified_galerkin_operators(A, Pr, pats)[1:]
        if coarse == "weighted":
            w = volume_fractions(tets) if fractions is None else fractions
            if len(w) != len(tets):
                raise NestmgInputError(f"fractions needs {len(tets)} arrays (level 0 first), got {len(w)}")
            ops = _weighted_operators(name, tets, w, free, lam, K0, bnd)
    local = None
    if not dirichlet:  # natural boundary: the boundary layer gets extra local sweeps (free0 = all nodes)
        local = boundary_layer_nodes(T0, rings=1, boundary=boundary_nodes(T0, stiffness=K0), n=n0)
    return Problem(
        name=name,
        A=A,
        b=np.asarray(b_full[free0]),
        P=Pr,
        coarse="galerkin" if ops is None else ops,
        free=free,
        n_fine=n0,
        nullspace="constant" if name == "poisson-neumann" else None,
        params={"lam": lam if name == "diffusion-neumann" else None, "coarse": coarse, "prune": prune,
                "dirichlet_coarse_dropped": 0 if conforming is None else conforming[1]},
        local_nodes=local,
    )


def _conforming_first_level(P: list, bnd: np.ndarray) -> tuple[list, int] | None:
    """``P`` with the first prolongation's columns of coarse nodes at fine Dirichlet nodes zeroed, and their
    number, when they are at least :data:`CONFORMING_MIN_FRACTION` of its columns; else None.

    A coarse node sits at a fine node ``i`` when row ``i`` of ``P[0]`` is (to rounding) ``e_j``. Zeroing the
    column (no renormalisation: the coarse function vanishes on the boundary) leaves the node unreached, and
    :func:`solvers.restrict_prolongations` drops it."""
    P0 = sp.csr_matrix(P[0])
    on = _coarse_at_dirichlet(P0, bnd)
    if on.size == 0 or on.size < CONFORMING_MIN_FRACTION * P0.shape[1]:
        return None
    _log.info("poisson-dirichlet: %d of the first coarse level's %d nodes sit at fine Dirichlet nodes: dropped "
              "(the conforming coarse space)", on.size, P0.shape[1])
    keep = np.ones(P0.shape[1])
    keep[on] = 0.0
    Q = sp.csr_matrix(P0 @ sp.diags(keep))
    Q.eliminate_zeros()
    return [Q, *P[1:]], int(on.size)


def _coarse_at_dirichlet(P0: sp.csr_matrix, bnd: np.ndarray) -> np.ndarray:
    """The coarse nodes of ``P0`` (columns) that sit at a fine Dirichlet node of ``bnd`` (row ``e_j``)."""
    rows = P0[bnd]
    return np.unique(rows.indices[rows.data >= 1.0 - 1e-12])


def _coarsening_levels(Pr: list, free: list) -> tuple[list, list]:
    """``(Pr, free)`` without the first coarse level that is not smaller than the one above it and every
    coarser one (a multigrid level must coarsen; after :func:`_conforming_first_level` the cage level below
    the first coarse level can be the larger one)."""
    for k, P in enumerate(Pr):
        if P.shape[1] == 0 or P.shape[1] >= P.shape[0]:
            _log.info("level %d has %d unknowns for %d on the level above it: the problem uses %d of %d levels",
                      k + 1, P.shape[1], P.shape[0], k + 1, len(Pr) + 1)
            return Pr[:k], free[:k + 1]
    return Pr, free


_MIN_FRACTION = 1e-2


def _kept_extension(T: np.ndarray, n: int, kept: np.ndarray) -> tuple[sp.csr_matrix, np.ndarray]:
    """Extension ``Q`` (n, len(kept)) of kept-node values to every node of a coarse mesh.

    A node dropped by the restriction (not reached by ``P`` or pruned as too weak) takes the mean of
    the kept nodes it shares a tet with, so ``Q 1 = 1`` there and a weighted operator ``Qᵀ W Q`` keeps
    the constants in its kernel; tets touching a dropped node with no kept neighbour are returned in
    ``dead`` (their weight must be 0).
    """
    T = np.asarray(T, dtype=np.int64)
    is_kept = np.zeros(n, dtype=bool)
    is_kept[kept] = True
    col = -np.ones(n, dtype=np.int64)
    col[kept] = np.arange(len(kept))
    # node-node adjacency through tets, restricted to (dropped row, kept column) pairs
    r = np.repeat(T, 4, axis=1).ravel()
    q = np.tile(T, (1, 4)).ravel()
    sel = ~is_kept[r] & is_kept[q]
    E = sp.csr_matrix((np.ones(int(sel.sum())), (r[sel], col[q[sel]])), shape=(n, len(kept)))
    E.data[:] = 1.0  # duplicates summed: back to a 0/1 pattern
    deg = np.asarray(E.sum(axis=1)).ravel()
    E = sp.csr_matrix(sp.diags(np.divide(1.0, deg, out=np.zeros_like(deg), where=deg > 0)) @ E)
    I = sp.csr_matrix((np.ones(len(kept)), (kept, np.arange(len(kept)))), shape=(n, len(kept)))
    Q = sp.csr_matrix(I + E)
    orphan = ~is_kept & (deg == 0)
    dead = np.flatnonzero(orphan[T].any(axis=1))
    return Q, dead


def _weighted_operators(name, tets, w, free, lam, K0, bnd) -> list[sp.csr_matrix]:
    """Volume-fraction-weighted coarse operators on the kept coarse nodes ``free[1:]``."""
    from .prolongation import prolongation

    ops = []
    d = _boundary_penalty(K0, bnd) if name == "poisson-dirichlet" else None
    Vb = np.asarray(tets[0][0])[bnd]
    for k in range(1, len(tets)):
        Vc, Tc = tets[k]
        c = free[k]
        # a floor keeps the rows of reached nodes whose tets sampled no fine point non-empty
        wk = np.maximum(w[k], _MIN_FRACTION)
        if name == "poisson-dirichlet":
            # dropped coarse nodes are 0, as in P (no constants to keep); the fine Dirichlet condition
            # enters as G^T diag(d) G, G = the fine boundary nodes located in this level's tets
            # (4 weights per row: coarse sparsity), rows renormalised to 1 over the kept nodes
            Kw = stiffness_matrix(Vc, Tc, wk, check=False)[c][:, c]
            G = prolongation(Vb, np.asarray(Vc, dtype=np.float64), np.asarray(Tc, dtype=np.int64))[0][:, c]
            rs = np.asarray(G.sum(axis=1)).ravel()
            G = sp.csr_matrix(sp.diags(np.divide(1.0, rs, out=np.zeros_like(rs), where=rs > 0)) @ G)
            ops.append(_finish(Kw + G.T @ sp.diags(d) @ G))
            continue
        Q, dead = _kept_extension(Tc, len(Vc), c)
        wk[dead] = 0.0
        Kw = sp.csr_matrix(Q.T @ stiffness_matrix(Vc, Tc, wk, check=False) @ Q)
        if name == "diffusion-neumann":
            Ac = lam * Kw + Q.T @ mass_matrix(Vc, Tc, weights=wk, check=False) @ Q
        else:
            Ac = Kw
        ops.append(_finish(Ac))
    return ops


def _finish(A) -> sp.csr_matrix:
    A = sp.csr_matrix(A)
    A = sp.csr_matrix(0.5 * (A + A.T))
    A.sum_duplicates()
    A.sort_indices()
    return A
