"""Implicit diffusion time stepping on a fixed hierarchy, with a time step that may change every step.

Backward Euler for ``∂u/∂t = Δu`` with a natural (Neumann) boundary on the fine tet mesh:

    ``(M + Δt_k K) u_k = M u_{k-1}``,   ``K`` P1 stiffness, ``M`` lumped mass.

The hierarchy (cages, tet layers, prolongations) is geometry and is reused. The Galerkin coarse operators
``P_kᵀ M_k P_k`` and ``P_kᵀ K_k P_k`` are formed once (:class:`solvers.shifted.ShiftedGalerkin`);
every step's coarse operators are then the sparse sum ``M_c + Δt_k K_c`` (exactly the Galerkin
operators of the step's matrix, up to round-off), so a new step only sets up the smoothers and the
coarsest factorisation, and MG-PCG is warm-started from ``u_{k-1}``.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from solvers.fem import boundary_layer_nodes, check_tet_mesh, mass_matrix, stiffness_matrix
from solvers.multilevel import DEFAULT_MAXITER, restrict_prolongations
from solvers.shifted import ShiftedGalerkin

from .errors import NestmgInputError
from .options import SolverOptions
from .problems import Problem

__all__ = ["DiffusionStepper", "diffusion_stepper", "implicit_diffusion"]


@dataclass
class DiffusionStepper:
    """Reusable multigrid data of backward-Euler diffusion on one hierarchy.

    Attributes
    ----------
    problem : Problem
        Template problem (``diffusion-neumann``): restricted prolongations and free nodes (all fine nodes).
    M, K : (n, n) csr_matrix
        Fine lumped mass and stiffness.
    family : ShiftedGalerkin
        Galerkin ``M`` and ``K`` on every level.
    setup_seconds : dict
        Wall seconds of ``assembly`` (``K``, ``M``; 0 when given), ``problem`` (pruned prolongations,
        boundary layer), ``galerkin`` (the two hierarchies of triple products); ``cpu``: the same in
        process CPU time.
    smoothing : str
        Cycle preset of every step (:meth:`nestmg.problems.Problem.multigrid`).
    """

    problem: Problem
    M: sp.csr_matrix
    K: sp.csr_matrix
    family: ShiftedGalerkin
    setup_seconds: dict
    smoothing: str = "fast"

    def step(self, u_prev: np.ndarray, dt: float, *, tol: float = 1e-8, maxiter: int = DEFAULT_MAXITER,
             **multigrid_kwargs) -> tuple[np.ndarray, dict]:
        """One backward-Euler step ``(M + dt K) u = M u_prev`` by MG-PCG warm-started from ``u_prev``.

        Parameters
        ----------
        u_prev : (n,) float array
            Previous state at the fine nodes.
        dt : float
            Time step (> 0).
        tol, maxiter
            Relative residual ``||b - A u|| <= tol ||b||`` and iteration cap of CG.
        **multigrid_kwargs
            Passed to :meth:`Problem.multigrid` (:class:`solvers.MultigridSolver` keywords; the smoothing
            preset is the stepper's ``smoothing``).

        Returns
        -------
        u : (n,) float array
        info : dict
            ``iterations``, ``converged``, ``residuals``, ``final_residual`` (true relative residual),
            ``seconds``: wall time of ``operators`` (the sparse sums), ``setup`` (smoothers, coarsest
            factorisation) and ``solve``; ``cpu_seconds``: the same in process CPU time.
        """
        dt = float(dt)
        if not np.isfinite(dt) or dt <= 0:
            raise NestmgInputError(f"time step must be positive and finite, got {dt}")
        u_prev = np.asarray(u_prev, dtype=np.float64)
        if u_prev.shape != (self.M.shape[0],):
            raise NestmgInputError(f"u_prev must have shape ({self.M.shape[0]},), got {u_prev.shape}")
        t0, c0 = time.perf_counter(), time.process_time()
        A, *coarse = self.family.operators(1.0, dt)
        b = self.M @ u_prev
        t1, c1 = time.perf_counter(), time.process_time()
        prob = dataclasses.replace(self.problem, A=A, b=b, coarse=coarse,
                                   params=dict(self.problem.params, lam=dt, coarse="galerkin (sparse sum)"))
        # the sparse sums are Galerkin operators: no energy scaling; symmetric by construction (M, K
        # symmetric, products symmetrised), so the solver need not test it at every step
        multigrid_kwargs.setdefault("symmetric", True)
        # the caller's node order: a locality permutation (MultigridSolver(ordering="auto")) would re-permute
        # the fine matrix and every coarse sum at each step; the reuse figures (docs/reuse.md) are without it
        multigrid_kwargs.setdefault("ordering", None)
        # no deflation probe: it would cost about one solve at every step, and a step's operator M + dt K is
        # better conditioned than the Neumann Laplacian the probe is for
        multigrid_kwargs.setdefault("deflate", 0)
        ml = prob.multigrid(SolverOptions(smoothing=self.smoothing, coarse_scaling=None), **multigrid_kwargs)
        t2, c2 = time.perf_counter(), time.process_time()
        u, info = ml.solve(b, x0=u_prev, tol=tol, maxiter=maxiter, accel="cg", return_info=True)
        t3, c3 = time.perf_counter(), time.process_time()
        nb = float(np.linalg.norm(b))
        final = float(np.linalg.norm(b - A @ u) / nb) if nb else 0.0
        return u, {"iterations": info["iterations"], "converged": info["converged"], "residuals": info["residuals"],
                   "final_residual": final, "seconds": {"operators": t1 - t0, "setup": t2 - t1, "solve": t3 - t2},
                   "cpu_seconds": {"operators": c1 - c0, "setup": c2 - c1, "solve": c3 - c2}}


def diffusion_stepper(tets: list[tuple[np.ndarray, np.ndarray]], P: list[sp.csr_matrix], *,
                      K: sp.spmatrix | None = None, M: sp.spmatrix | None = None, prune: float = 0.2,
                      smoothing: str = "fast") -> DiffusionStepper:
    """Set up backward-Euler diffusion on a hierarchy (once; every step reuses it).

    Parameters
    ----------
    tets : list of (V, T)
        Tet meshes, finest first (``Hierarchy.tets``).
    P : list of (n_k, n_{k+1}) csr_matrix
        Prolongations (``Hierarchy.P``).
    K, M : (n_0, n_0) sparse matrices, optional
        The fine stiffness and mass matrices, e.g. a simulation code's own (any symmetric pair on the
        fine nodes: a consistent mass matrix or a conductivity-weighted stiffness work too). Default:
        P1 stiffness and lumped mass assembled on ``tets[0]``.
    prune : float
        As :func:`setup_problem` (weak coarse nodes dropped from the prolongations).
    smoothing : {"fast", "robust"}
        Cycle preset of :meth:`Problem.multigrid` used by :meth:`DiffusionStepper.step` (default
        ``"fast"``, the textbook V(1,1): with the mass term the steps are easy and under CG the cheaper
        cycle wins in wall time, docs/reuse.md).

    Returns
    -------
    DiffusionStepper
    """
    from .problems import SMOOTHING

    if smoothing not in SMOOTHING:
        raise NestmgInputError(f"smoothing must be one of {SMOOTHING}, got {smoothing!r}")
    if len(P) != len(tets) - 1:
        raise NestmgInputError(f"need len(P) == len(tets) - 1, got {len(P)} and {len(tets)}")
    t0, c0 = time.perf_counter(), time.process_time()
    V0, T0 = tets[0]
    n0 = len(V0)
    if K is None or M is None:
        V0, T0, vol0 = check_tet_mesh(V0, T0, return_volumes=True)
        K = stiffness_matrix(V0, T0, check=False) if K is None else K
        M = mass_matrix(V0, T0, check=False, volumes=vol0) if M is None else M
    K, M = sp.csr_matrix(K, dtype=np.float64), sp.csr_matrix(M, dtype=np.float64)
    for name, X in (("K", K), ("M", M)):
        if X.shape != (n0, n0):
            raise NestmgInputError(f"{name} must have shape ({n0}, {n0}) (the fine nodes), got {X.shape}")
        if not np.all(np.isfinite(X.data)):
            raise NestmgInputError(f"{name} contains NaN/inf entries")
    t1, c1 = time.perf_counter(), time.process_time()
    # natural boundary: every fine node is free; the prolongations are pruned as in setup_problem
    Pr, free = restrict_prolongations(P, np.arange(n0), min_column_sum=prune)
    local = boundary_layer_nodes(T0, rings=1, n=n0) if smoothing == "robust" else None
    prob = Problem(name="diffusion-neumann", A=M + K, b=np.zeros(n0), P=Pr, coarse="galerkin", free=free,
                   n_fine=n0, nullspace=None, params={"lam": 1.0, "coarse": "galerkin", "prune": prune,
                                                      "smoothing": smoothing}, local_nodes=local)
    t2, c2 = time.perf_counter(), time.process_time()
    fam = ShiftedGalerkin(M, K, prob.P)
    t3, c3 = time.perf_counter(), time.process_time()
    return DiffusionStepper(prob, M, K, fam,
                            {"assembly": t1 - t0, "problem": t2 - t1, "galerkin": t3 - t2,
                             "cpu": {"assembly": c1 - c0, "problem": c2 - c1, "galerkin": c3 - c2}},
                            smoothing)


def implicit_diffusion(tets: list[tuple[np.ndarray, np.ndarray]], P: list[sp.csr_matrix], u0: np.ndarray, dts,
                       *, tol: float = 1e-8, maxiter: int = DEFAULT_MAXITER) -> tuple[np.ndarray, list[dict]]:
    """Backward-Euler diffusion ``(M + Δt_k K) u_k = M u_{k-1}`` for the time steps ``dts``.

    Parameters
    ----------
    tets, P
        The hierarchy (see :func:`diffusion_stepper`).
    u0 : (n_0,) float array
        Initial state at the fine nodes.
    dts : sequence of float
        Time steps (may change every step).
    tol, maxiter
        Per-step MG-PCG tolerance (relative residual) and iteration cap.

    Returns
    -------
    u : (n_0,) float array
        The state after the last step.
    infos : list of dict
        One :meth:`DiffusionStepper.step` info per step.

    Examples
    --------
    >>> from solvers.gallery import kuhn_cube_hierarchy
    >>> meshes, Ps = kuhn_cube_hierarchy(8, 3)
    >>> u0 = meshes[0][0][:, 0].copy()          # u = x on the unit cube
    >>> u, infos = implicit_diffusion(meshes, Ps, u0, [1e-3, 1e-2, 1e-1])
    >>> bool(u.max() - u.min() < 1.0), all(i["converged"] for i in infos)
    (True, True)
    """
    stepper = diffusion_stepper(tets, P)
    u = np.asarray(u0, dtype=np.float64)
    infos = []
    for dt in dts:
        u, info = stepper.step(u, dt, tol=tol, maxiter=maxiter)
        infos.append(info)
    return u, infos
