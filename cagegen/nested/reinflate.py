"""Re-inflation: replay the flow backwards while the cage is pushed out of the way (paper Sec. 3.2).

The fine surface must return exactly to its rest pose along its flow history; the cage C has to
move so that C never intersects itself nor the fine surface *during* every step (continuous-time
constraints, Eqs. 9-10). Instead of a velocity filter we use ipctk's incremental-potential
machinery: for every reverse step F(t) → F(t+∆t) we minimise over both surfaces

    Φ(C, F) = E(C) + (k_F/2) ‖F − F(t+∆t)‖² + κ B(C, F)

with Newton's method (ipctk's barrier Hessian projected to PSD, or :mod:`cagegen.nested.contact_hessian`),
a CCD-bounded backtracking line search (``compute_collision_free_stepsize``: every accepted motion is
intersection-free) and the barrier B of Li et al. (IPC) with activation distance ``dhat``. The stiff
spring k_F plays the role of the fine mesh's "infinite mass": the barrier's reaction moves the cage,
the fine surface follows its prescribed path. When F is within ``snap_tol`` of its target, it is
snapped *exactly* onto it (after a CCD check, or none when F moves less than half the smallest pair
distance: :meth:`_Problem.snap_is_free`), so after the last step F equals its rest positions bit for
bit. As in the paper, E_step is minimised while re-inflating and the final energy (e.g. E_vol) only
once F is at rest, with F fixed.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import igl
import ipctk
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ..collision import PairMesh
from .contact_hessian import (
    ContactArrays,
    collision_lists,
    contact_arrays,
    contact_gradients,
    gauss_newton_hessian,
    subset,
)
from .energies import make_energy, signed_volume

_log = logging.getLogger(__name__)

__all__ = ["ReinflateResult", "reinflate", "resample_history"]


@dataclass
class ReinflateResult:
    """Outcome of :func:`reinflate`.

    Attributes
    ----------
    cage : (nc,3) float array
        New cage positions C (nests the fine surface at rest if ``success``).
    fine : (nf,3) float array
        Final fine positions (equal to ``history[0]`` if ``success``).
    success : bool
    reason : str
    stats : dict
        Counters and timings (JSON-serialisable).
    looser : list of (nc,3) float arrays
        The cage before the final phase and after each of its iterations but the last (loosest
        first): every one nests the fine surface at rest (each a CCD-certified step from the one
        before, with a lower objective but after a barrier stiffening).
    """

    cage: np.ndarray
    fine: np.ndarray
    success: bool
    reason: str
    stats: dict = field(default_factory=dict)
    looser: list = field(default_factory=list)


#: A reverse step ends when the fine surface is within this fraction of ``dhat`` of its target and the CCD lets
#: it jump there (the snap: one collision-free linear motion, so F still ends at its rest pose bit for bit).
SNAP_TOL = 0.01
#: The same for the last reverse step, after which only the final phase moves the cage. Its last Newton
#: iterations crept from 1e-4 to the 5e-5 of ``SNAP_TOL`` (homer.obj's first layer: 10 iterations of that
#: step, 5 of them below 1.3e-4). The last step only: 12 zoo meshes 0.99x the CPU seconds in all (homer
#: 0.92x, decimated-max 0.90x), lucy.ply 0.94x, the same volume ratios to 0.02. Every step from 0.1: 0.91x on
#: the 12 but lucy.ply 1.29x: F, snapped from farther, left the cage less pushed out and the next step took
#: 25 Newton iterations instead of 10 (``benchmarks/results/cages/ab_lastsnap_2137b50.json``,
#: ``ab_snaptol_*_2137b50.json``, ``ab_lucy_*_2137b50.json``).
LAST_SNAP_TOL = 0.1

#: A reverse step gives up when its smallest |F - target| has not halved in this many Newton iterations
#: (it needs ~7 halvings to reach ``snap_tol``). cheburashka.obj's first target: the last step (the
#: clearance) reached 0.0013 of the diagonal in 8 iterations, stayed there for 15 and then drifted away,
#: until ``max_newton`` ran out: 52 of 104 CPU s spent after the stall. Over 21 zoo meshes no reverse step
#: that went on to converge had gone more than 5 iterations without halving (242 steps,
#: ``benchmarks/results/cages/stall_plateaus_84c70b7.json``), so 10 would do there; it stays 20 because
#: lucy.ply's full surface, not among them, ran past 700 s with 10 and Gauss-Newton reverse steps
#: (``corpus/lucy_cages_e8342fb.json``); with 20 and Gauss-Newton it took 166 against 156 CPU s with
#: ipctk's Hessian (``cages/ab_32667e4.json``): the window of 10 (or that run's load) was the cause.
STALL_NEWTON = 20

#: Newton matrix of the barrier in the final phase (and of the reverse steps: :data:`REVERSE_HESSIAN`):
#: ``"gauss_newton"`` (:func:`cagegen.nested.contact_hessian.gauss_newton_hessian`, numpy) or ``"ipctk"``
#: (ipctk's full Hessian projected to PSD by clamping the eigenvalues of every contact's 12x12 block). Both
#: are SPD; the gradient and the line search are ipctk's either way.
#: Default ``"ipctk"``: with ``"gauss_newton"`` in both phases the cages were 1.0-1.7x cheaper in CPU
#: (``benchmarks/results/cages/ab_0eb1630.json``) but homer.obj's diffusion V-cycle factor came out 0.317 and
#: 0.260 over two fresh hierarchies against 0.197 with ipctk's Hessian in the same session (0.126-0.241 in
#: earlier corpus runs; ``corpus/zoo_866d3e5_part.json``): not the default until the solve column backs it.
BARRIER_HESSIAN = "ipctk"

#: Newton matrix of the reverse steps (same choices). ``"gauss_newton"`` there is cheaper: ipctk's clamped
#: Hessian costs 6.4-10.6 CPU us a contact on homer's and pepper's collision sets, the Gauss-Newton matrix
#: 1.6-2.2 with its contact arrays (``benchmarks/results/cages/contact_hessian_cost_0568980.json``); with it
#: and ``STALL_NEWTON = 10`` the cages were 1.3-1.4x cheaper in CPU on homer and pepper, 1.2x on
#: decimated-max (``cages/ab_ada0168_run*.json``), the median diffusion factors on fresh hierarchies
#: 0.216 -> 0.128, 0.106 -> 0.104, 0.124 -> 0.127 (``cages/factor_reverse_hessian_*.json``). Not the default:
#: the cages of lucy.ply's full 100k-face surface took 301 s with ipctk's Hessian and ran past 700 s with
#: Gauss-Newton reverse steps and a stall window of 10 (the two run side by side, ``corpus/lucy_cages_*``),
#: and round.stl's corpus hierarchy missed its tet-level certificate once (one fine node outside after the
#: retries, ``corpus/zoo_e8342fb.json``; certified on a re-run). A blocked or slow step switches a
#: Gauss-Newton re-inflation to ipctk's Hessian (:data:`GN_BLOCKED_ALPHA`).
REVERSE_HESSIAN = "ipctk"

#: With ``"ipctk"``, a collision set of at least this many contacts gets a hybrid Newton matrix: ipctk's
#: projected Hessian on the contacts closer than :data:`HYBRID_NEAR` ``dhat``, the Gauss-Newton matrix on
#: the others. After the clearance dilation the whole cage floats within ``dhat`` of F: on homer.obj's
#: first layer 35k contacts, the median at 0.87 ``dhat``, 0.6% closer than 0.5 ``dhat``; ipctk took 5.8
#: wall us a contact (two threads), the hybrid 3.8, half of it reading the contacts into arrays
#: (``benchmarks/results/cages/contact_hessian_cost_36a31a7.json``). Far from F ``h'(d) -> 0`` and the
#: dropped term ``h'(d) grad^2 d`` is what the PSD projection mostly removes; near it the distance curvature
#: keeps the direction from running into a contact (Gauss-Newton everywhere stalled,
#: :data:`GN_BLOCKED_ALPHA`). Small sets keep ipctk's Hessian: there it costs milliseconds.
#: ``cages_ab.py`` on 12 zoo meshes: CPU x0.91 in all (bumpy-cube 0.71, fandisk 0.83, pepper 0.85; homer
#: 1.12: its second layer tried one more target), lucy.ply x0.87; volume ratios within 0.015
#: (``cages/ab_hybrid_7754140.json``, ``ab_lucy_hybrid_7754140.json``); the near set picked from the objects
#: already read instead of a second broad phase: x0.95 more, lucy x0.93 (``ab_*hybrid_subset_d4d2e4c.json``).
HYBRID_MIN_CONTACTS = 5000
HYBRID_NEAR = 0.5

#: ``dhat`` and ``max_move`` of the reverse steps shrink (by the same factor) to at most this fraction of the
#: fine surface's mean edge length. The contacts a cage primitive has grow with the fine primitives inside
#: ``dhat`` of it, and a Newton step costs per contact: on dense inputs the barrier's range spanned edges
#: by the dozen (stanford-bunny.obj's first layer, mean edge 0.0059 of the diagonal: 119k contacts a collision
#: build, 2.6 s a Newton iteration; ad hoc). A fixed ``dhat`` of 3e-3 instead stalled homer.obj's second layer,
#: whose fine surface is a coarse cage (mean edge 0.024): the rule leaves such layers alone. Measured with
#: ``cages_ab.py``: ``benchmarks/results/cages/ab_dhat_edge_6a00d76.json`` (docs/cagegen.md).
DHAT_PER_EDGE = 0.5

#: The Gauss-Newton matrix gives way to ipctk's projected Hessian for the rest of a re-inflation when a
#: Newton step is cut below this fraction (CCD bound and backtracking) or a reverse step's |F - target|
#: has not halved in :data:`GN_PATIENCE` iterations; the switched step gets a fresh stall window.
#: Without the distance curvature the direction can keep running into a contact: on
#: decimated-knight.off a reverse step's steps shrank geometrically (0.3, 0.13, 0.046, ...) until the step
#: stalled and the layer fell back to other targets (36 CPU s against 3.2 with ipctk's Hessian), and a
#: homer.obj second layer stalled without short steps.
GN_BLOCKED_ALPHA = 0.1
GN_PATIENCE = 5


def _slow(best: list, n: int) -> bool:
    """True when ``best`` (smallest |F - target| after 0, 1, ... Newton iterations of one reverse step)
    has not halved over the last ``n`` iterations."""
    return len(best) > n and best[-1] > 0.5 * best[-1 - n]


def _stalled(best: list) -> bool:
    """True when ``best`` has not halved over the last :data:`STALL_NEWTON` iterations (:func:`_slow`)."""
    return _slow(best, STALL_NEWTON)


def resample_history(history: list, max_move: float) -> list:
    """Path of the fine surface through ``history`` in steps moving no vertex more than ``max_move``.

    Snapshots closer than ``max_move`` are merged, longer segments are split linearly (between
    snapshots the fine surface may follow any path: only its end, the rest pose, matters). The first
    and last entries are kept as the same objects, so ``path[0] is history[0]`` stays exact.
    """
    keep = [history[0]]
    for k in range(1, len(history)):
        if k < len(history) - 1 and np.abs(history[k + 1] - keep[-1]).max() <= max_move:
            continue
        a, b = keep[-1], history[k]
        n_sub = int(np.ceil(np.abs(b - a).max() / max_move)) if max_move > 0 else 1
        for s in range(1, n_sub):
            keep.append(a + (b - a) * (s / n_sub))
        keep.append(b)
    return keep


class _Problem:
    """Newton machinery on the stacked positions X = [C; F] (row-major DOFs)."""

    def __init__(self, pair: PairMesh, energy, dhat: float, kappa: float, k_fine: float):
        self.pair, self.energy = pair, energy
        self.nc, self.nf = pair.nc, pair.nf
        self.dhat, self.kappa, self.k_fine = dhat, kappa, k_fine
        self.barrier = ipctk.BarrierPotential(dhat, kappa)
        self.col = ipctk.NormalCollisions()
        self.n_ccd = 0
        self.n_build = 0
        self.n_snap_free = 0
        self.lam = np.zeros((pair.nf, 3))  # augmented-Lagrangian multipliers of F = target
        self._cache = None
        self.hessian_kind = REVERSE_HESSIAN
        self.rest = np.asarray(pair.mesh.rest_positions)

    def barrier_hessian(self, col: ipctk.NormalCollisions, X: np.ndarray, fine_moves: bool
                        ) -> tuple[sp.csr_matrix, np.ndarray]:
        """SPD Newton matrix of the barrier at ``X`` (see :data:`BARRIER_HESSIAN`) on the DOFs ``idx``
        it returns: the cage DOFs, then (``fine_moves``) the fine DOFs of the vertices in contact."""
        nc3 = 3 * self.nc
        if self.hessian_kind == "ipctk" and len(col) >= HYBRID_MIN_CONTACTS:
            return self._hybrid_hessian(col, X, fine_moves)
        if self.hessian_kind == "ipctk":
            HB = self.barrier.hessian(col, self.pair.mesh, X, ipctk.PSDProjectionMethod.CLAMP).tocsr()
            # the DOFs of some contact: the rows with entries (12x12 blocks: a symmetric pattern), found
            # from the row pointers instead of sorting every column index (2M on pepper.ply's layer 1)
            dofs = np.flatnonzero(np.diff(HB.indptr)) if fine_moves else np.zeros(0, dtype=np.int64)
            idx = np.r_[np.arange(nc3), dofs[dofs >= nc3]]
            return HB[idx][:, idx], idx
        ca = contact_arrays(col, self.pair.mesh)
        idx = self._contact_dofs(ca, fine_moves)
        return gauss_newton_hessian(X, ca, self.rest, self.dhat, self.kappa, dofs=idx), idx

    def _contact_dofs(self, ca: ContactArrays, fine_moves: bool) -> np.ndarray:
        """The cage DOFs, then (``fine_moves``) the DOFs of the fine vertices of some contact in ``ca``."""
        verts = np.zeros(0, dtype=np.int64)
        if fine_moves:  # the sorted distinct fine vertices of the contacts (a mask: no sort of every id)
            ids = ca.ids.ravel()
            seen = np.zeros(self.nc + self.nf, dtype=bool)
            seen[ids[ids >= self.nc]] = True
            verts = np.flatnonzero(seen)
        return np.r_[np.arange(3 * self.nc), (3 * verts[:, None] + np.arange(3)).ravel()]

    def _hybrid_hessian(self, col: ipctk.NormalCollisions, X: np.ndarray, fine_moves: bool
                        ) -> tuple[sp.csr_matrix, np.ndarray]:
        """ipctk's projected Hessian of the contacts closer than ``HYBRID_NEAR * dhat`` plus the
        Gauss-Newton matrix of the others (:data:`HYBRID_MIN_CONTACTS`), on the DOFs ``idx`` it returns."""
        lists = collision_lists(col)
        ca = contact_arrays(col, self.pair.mesh, lists)
        idx = self._contact_dofs(ca, fine_moves)
        grads = contact_gradients(X, ca, self.rest)
        far = grads[0] >= HYBRID_NEAR * self.dhat
        H = gauss_newton_hessian(X, ca, self.rest, self.dhat, self.kappa, dofs=idx, grads=grads, mask=far)
        if not far.all():  # the near contacts' own collision set, from the objects already read
            near = subset(lists, ~far)
            HB = self.barrier.hessian(near, self.pair.mesh, X, ipctk.PSDProjectionMethod.CLAMP).tocsr()
            H = H + HB[idx][:, idx]
        return H, idx

    def _collisions(self, X: np.ndarray) -> ipctk.NormalCollisions:
        # the accepted line-search point is the next Newton point: reuse its collision set
        if (self._cache is not None and self._cache[1] == self.dhat and self._cache[0].shape == X.shape
                and np.array_equal(self._cache[0], X)):
            return self._cache[2]
        col = self.pair.collisions(X, self.dhat)
        self.n_build += 1
        self._cache = (X.copy(), self.dhat, col)
        return col

    def snap_is_free(self, X: np.ndarray, Xs: np.ndarray) -> bool:
        """True when moving the fine surface alone, ``X -> Xs``, cannot make a contact (no CCD needed):
        every vertex moves less than half the smallest distance of a pair within ``dhat`` (the cached
        collision set at ``X``), and a pair's distance shrinks by at most that motion. Otherwise counts
        the CCD the caller runs."""
        col = self._collisions(X)
        d = self.dhat
        if len(col):
            d = min(d, float(np.sqrt(col.compute_minimum_distance(self.pair.mesh, X))))
        if float(np.sqrt(((Xs - X) ** 2).sum(axis=1).max())) < 0.5 * d:
            self.n_snap_free += 1
            return True
        self.n_ccd += 1
        return False

    def objective(self, X: np.ndarray, target: np.ndarray | None) -> float:
        C, F = X[: self.nc], X[self.nc :]
        val = self.energy.value(C) + float(self.barrier(self._collisions(X), self.pair.mesh, X))
        if target is not None:
            c = F - target
            val += 0.5 * self.k_fine * float(np.sum(c * c)) - float(np.sum(self.lam * c))
        return val

    def newton_step(self, X: np.ndarray, target: np.ndarray | None) -> tuple[np.ndarray, float, float]:
        """Newton direction, CCD-bounded and Armijo-backtracked. Returns (X_new, alpha, |dX|_inf).

        ``target`` is the fine surface's goal (spring); ``None`` keeps F fixed (final phase).
        """
        nc3 = 3 * self.nc
        C, F = X[: self.nc], X[self.nc :]
        col = self._collisions(X)
        gB = self.barrier.gradient(col, self.pair.mesh, X)
        HB, idx = self.barrier_hessian(col, X, target is not None)
        gC = self.energy.gradient(C).ravel() + gB[:nc3]
        HC = self.energy.metric(C)
        if target is None:  # fine surface fixed: reduced system on the cage DOFs
            g = gC
            d = np.zeros(X.size)
            d[:nc3] = -_solve_spd(HC + HB, g)
            f0 = self.energy.value(C) + float(self.barrier(col, self.pair.mesh, X))
        else:
            gF = (self.k_fine * (F - target) - self.lam).ravel() + gB[nc3:]
            g = np.r_[gC, gF]
            # fine DOFs untouched by any contact have the diagonal Hessian k_F: solve them in closed
            # form and the coupled system only on the cage + fine DOFs in contact (small); idx starts
            # with the nc3 cage DOFs
            d = -g / self.k_fine
            Hs = (HB + sp.diags(np.where(idx < nc3, 0.0, self.k_fine))
                  + sp.block_diag([HC, sp.csr_matrix((len(idx) - nc3, len(idx) - nc3))], format="csr"))
            d[idx] = -_solve_spd(Hs, g[idx])
            c = F - target
            f0 = (self.energy.value(C) + float(self.barrier(col, self.pair.mesh, X))
                  + 0.5 * self.k_fine * float(np.sum(c * c)) - float(np.sum(self.lam * c)))
        D = d.reshape(-1, 3)
        slope = float(g @ d[: g.size])
        self.n_ccd += 1
        alpha = self.pair.stepsize(X, X + D)
        if alpha <= 0.0:
            return X, 0.0, 0.0
        alpha = min(1.0, alpha)
        for _ in range(30):
            Xt = X + alpha * D
            if self.objective(Xt, target) <= f0 + 1e-4 * alpha * slope:
                return Xt, alpha, float(np.abs(alpha * D).max())
            alpha *= 0.5
        return X, 0.0, 0.0


#: Newton systems are solved by Jacobi-preconditioned CG to this relative residual (the direction then
#: agrees with a direct solve to ~1e-9), falling back to sparse LU after :data:`NEWTON_CG_MAXITER`
#: iterations. The spring ``k_fine`` and the cage metric dominate the diagonal: on homer.obj's first
#: layer (23k unknowns, 0.95M nonzeros) CG needs 30-55 iterations, 0.07-0.15 CPU s, against 0.35-0.46 s
#: for SuperLU (MMD ordering, symmetric mode), whose factorisation was a quarter of a Newton step.
#: Systems under :data:`NEWTON_CG_MIN_SIZE` unknowns keep SuperLU: there it costs milliseconds, and the
#: stiff small systems of decimated-knight.off's layers took CG 10x longer (1.8 against 0.19 CPU s).
NEWTON_CG_RTOL = 1e-10
NEWTON_CG_MAXITER = 400
NEWTON_CG_MIN_SIZE = 10_000
#: Systems with more unknowns never go to SuperLU: when CG stops at :data:`NEWTON_CG_MAXITER` its iterate is
#: the direction (truncated Newton: CG's iterates from 0 lower the quadratic model, so each one is a descent
#: direction, Nocedal & Wright, Sec. 7.1; the CCD and the line search bound the step as for an exact one).
#: SuperLU's fill grows faster than the system: lucy.ply's three unconverged systems (82-90k unknowns,
#: relative residuals 1e-6-1e-3 after 400 iterations) took it 1.3-2.1 s, but on a 342k-face scan (gargo.off
#: subdivided three times) one layer-1 system held the process in SuperLU with 8 GB resident until the
#: 15-minute limit.
NEWTON_LU_MAX_SIZE = 120_000


def _solve_spd(H: sp.spmatrix, g: np.ndarray) -> np.ndarray:
    """Solve the SPD Newton system H d = g: Jacobi-CG when large, sparse LU when small or when CG does
    not converge (up to :data:`NEWTON_LU_MAX_SIZE` unknowns; beyond, CG's last iterate)."""
    if H.shape[0] >= NEWTON_CG_MIN_SIZE:
        Hr = H.tocsr()
        diag = Hr.diagonal()
        if np.all(diag > 0):
            x, info = spla.cg(Hr, g, rtol=NEWTON_CG_RTOL, atol=0.0, maxiter=NEWTON_CG_MAXITER,
                              M=sp.diags(1.0 / diag))
            if info == 0 or (info > 0 and H.shape[0] > NEWTON_LU_MAX_SIZE and np.all(np.isfinite(x))):
                return x
    lu = spla.splu(H.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                   options={"SymmetricMode": True})
    return lu.solve(g)


def reinflate(
    history: list,
    Ff: np.ndarray,
    Vc: np.ndarray,
    Fc: np.ndarray,
    *,
    energy: str = "volume",
    dhat: float = 5e-3,
    kappa: float = 1e4,
    dhat_final: float = 1e-3,
    kappa_final: float = 1e3,
    k_fine: float = 1e3,
    max_move: float = 5e-3,
    snap_tol: float = SNAP_TOL,
    last_snap_tol: float = LAST_SNAP_TOL,
    max_newton: int = 60,
    final_iters: int = 60,
    final_tol: float = 1e-3,
    callback: Callable[[int, int], None] | None = None,
) -> ReinflateResult:
    """Re-inflate the flowed fine surface to its rest pose, pushing the cage outward (Alg. 3).

    Parameters
    ----------
    history : list of (nf,3) float arrays
        Fine positions along the flow, ``history[0]`` the rest pose, ``history[-1]`` strictly inside
        the cage (see :func:`cagegen.nested.flow.flow_inside`). Not modified.
    Ff : (mf,3) int array
        Fine triangles.
    Vc : (nc,3) float array
        Cage rest positions Ĉ (not modified); must be free of self-intersections.
    Fc : (mc,3) int array
        Cage triangles.
    energy : str
        Final energy minimised with the fine surface at rest: ``"step"`` (none: keep the pushed-out
        cage), ``"volume"`` (tight), ``"surface_arap"``, ``"volumetric_arap"``. E_step is used while
        re-inflating, as in the paper (the ARAP energies use surface ARAP while re-inflating).
    dhat : float
        Barrier activation distance while re-inflating, fraction of the fine bounding-box diagonal.
        Larger than the per-step motion ``max_move`` so the cage "sees" the fine surface coming. Both
        shrink by the same factor to at most :data:`DHAT_PER_EDGE` of the fine mean edge length.
    kappa : float
        Barrier stiffness while re-inflating (stiff: the cage keeps ahead of the fine surface, few
        contacts and Newton iterations; see :data:`cagegen.nested.backend._DEFAULTS`).
    dhat_final, kappa_final : float
        Barrier of the final phase (softer and shorter-ranged: the final energy pulls the cage
        close to the fine surface; the equilibrium gap shrinks with both).
    k_fine : float
        Spring stiffness pulling the fine surface to its next history position.
    max_move : float
        Largest vertex motion (fraction of the diagonal) of one reverse step; the history is
        resampled to respect it.
    snap_tol : float
        Distance (fraction of ``dhat``) from its target under which F is snapped onto it.
    last_snap_tol : float
        The same for the last reverse step (F onto its rest pose; :data:`LAST_SNAP_TOL`).
    max_newton : int
        Newton iterations allowed per reverse step.
    final_iters : int
        Iterations of the final energy minimisation.
    final_tol : float
        Stop the final phase when the objective decreases by less than this relative amount.
    callback : callable, optional
        ``callback(step, n_steps)`` after each reverse step.

    Returns
    -------
    ReinflateResult
    """
    t0 = time.perf_counter()
    Ff = np.asarray(Ff, dtype=np.int64)
    Fc = np.asarray(Fc, dtype=np.int64)
    rest = history[0]
    diag = float(np.linalg.norm(np.ptp(rest, axis=0)))
    shrink = min(1.0, DHAT_PER_EDGE * float(igl.avg_edge_length(rest, Ff)) / (dhat * diag))  # :data:`DHAT_PER_EDGE`
    dhat_abs = dhat * shrink * diag
    path = resample_history(history, max_move * shrink * diag)
    C = np.array(Vc, dtype=float)
    pair = PairMesh(C, Fc, path[-1], Ff)
    X = pair.stack(C, path[-1])
    stats: dict = {"reverse_steps": len(path) - 1, "newton_iterations": 0, "most_newton_in_a_step": 0,
                   "dhat": dhat * shrink, "max_move": max_move * shrink}
    if pair.intersects(X):
        return ReinflateResult(C, path[-1].copy(), False, "flowed surface intersects the cage", stats)

    reinflate_energy = make_energy("surface_arap" if energy.endswith("arap") else "step", C, Fc)
    prob = _Problem(pair, reinflate_energy, dhat_abs, kappa, k_fine)
    nc = len(C)
    targets = path[-2::-1]  # F(t+∆t) for the reverse steps, ending with the rest pose (same object)
    for k, Fb in enumerate(targets):
        reinflate_energy.begin_step(X[:nc])
        snapped = False
        best = [float(np.abs(X[nc:] - Fb).max())]  # smallest |F - target| after 0, 1, ... iterations
        for it in range(max_newton):
            X, alpha, move = prob.newton_step(X, Fb)
            stats["newton_iterations"] += 1
            stats["most_newton_in_a_step"] = max(stats["most_newton_in_a_step"], it + 1)
            gap = float(np.abs(X[nc:] - Fb).max())
            _log.debug("reverse step %d: alpha %.3g move %.3g |F - target| %.3g", k, alpha, move, gap)
            best.append(min(best[-1], gap))
            if prob.hessian_kind == "gauss_newton" and (alpha < GN_BLOCKED_ALPHA or _slow(best, GN_PATIENCE)):
                prob.hessian_kind = "ipctk"
                stats["hessian_switched_at"] = [k + 1, it + 1]
                best = best[-1:]
            if _stalled(best):
                stats["stalled"] = True
                break
            if gap < (last_snap_tol if k == len(targets) - 1 else snap_tol) * dhat_abs:
                Xs = X.copy()
                Xs[nc:] = Fb
                if prob.snap_is_free(X, Xs) or prob.pair.stepsize(X, Xs) >= 1.0:
                    X, snapped = Xs, True
                    break
            if alpha >= 0.5:
                # augmented Lagrangian update: the multiplier takes over the contact force, so the
                # fine surface converges onto its target without an infinitely stiff spring
                prob.lam -= prob.k_fine * (X[nc:] - Fb)
            if alpha == 0.0 or move < 1e-12 * diag:
                prob.k_fine *= 10.0  # stuck short of the target: stiffen the fine surface's spring
        if not snapped:
            stats.update(_counters(prob, t0))
            how = f"stalled ({STALL_NEWTON} Newton iterations without halving |F - target|)" \
                if stats.get("stalled") else "stuck"
            return ReinflateResult(X[:nc].copy(), X[nc:].copy(), False,
                                   f"re-inflation {how} at reverse step {k + 1}/{len(targets)}", stats)
        if callback is not None:
            callback(k + 1, len(targets))
    stats["t_reinflate"] = time.perf_counter() - t0

    # final phase: fine surface at rest (fixed), minimise the requested energy of the cage
    t1 = time.perf_counter()
    X[nc:] = rest  # already equal bit for bit; keeps the exact array values
    final_energy = make_energy(energy, np.asarray(Vc, dtype=float), Fc)
    final_energy.begin_step(X[:nc])
    stats["volume_before_final"] = signed_volume(X[:nc], Fc)
    n_final = 0
    looser = []
    if energy != "step":
        prob.hessian_kind = BARRIER_HESSIAN  # the final phase's blocked steps are the barrier's softness
        prob.energy = final_energy
        prob.dhat = dhat_final * diag
        prob.kappa = kappa_final
        prob.barrier = ipctk.BarrierPotential(prob.dhat, kappa_final)
        f_prev = prob.objective(X, None)
        kap = kappa_final
        for _ in range(final_iters):
            looser.append(X[:nc].copy())
            X, alpha, move = prob.newton_step(X, None)
            n_final += 1
            f = prob.objective(X, None)
            _log.debug("final: alpha %.3g move %.3g objective %.6g kappa %.3g", alpha, move, f, kap)
            if alpha < 0.5 and kap < 1e4:
                # a blocked (CCD-limited) step: the barrier is too soft to stop the cage before the
                # contact, stiffen it (adaptive stiffness, as in IPC)
                kap *= 2.0
                prob.kappa = kap
                prob.barrier = ipctk.BarrierPotential(prob.dhat, kap)
                f = prob.objective(X, None)
            elif abs(f_prev - f) <= final_tol * max(abs(f_prev), 1e-300):
                break
            f_prev = f
        stats["kappa_final_reached"] = kap
    stats["final_iterations"] = n_final
    stats["volume_after_final"] = signed_volume(X[:nc], Fc)
    stats["t_final"] = time.perf_counter() - t1
    stats.update(_counters(prob, t0))
    return ReinflateResult(X[:nc].copy(), X[nc:].copy(), True, "ok", stats, looser)


def _counters(prob: _Problem, t0: float) -> dict:
    return {"ccd_calls": prob.n_ccd, "collision_builds": prob.n_build, "snaps_without_ccd": prob.n_snap_free,
            "seconds": time.perf_counter() - t0}
