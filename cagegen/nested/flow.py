"""Signed-distance flow of the fine surface inside the coarse target (paper Sec. 3.1, Alg. 2).

The fine vertices descend Φ(F̄) = ∫_F̄ sd_Ĉ(p) dA (Eq. 1), the integrated signed distance to the
decimated target Ĉ, approximated by triangle quadrature. Closest points and signs are frozen during
a step (the ICP-like linearisation of Eqs. 3-4), so the gradient at a quadrature point is the unit
vector g = s (p - q*) / |p - q*|, or the pseudonormal at q* when p is within ``eps`` of Ĉ (Eq. 6);
a vertex gathers the gradients of the quadrature points of its incident triangles, weighted by
area × rule weight × barycentric coordinate (Eq. 5). We normalise by the total weight, so a step of
length ``h`` moves every vertex by at most ``h``: ``h`` is the paper's ∆t ≈ 1e-3 of the mesh's
bounding-box diagonal, adapted by a backtracking line search on Φ.

The flow stops when every quadrature point is inside Ĉ and F̄ and Ĉ do not intersect (ipctk's exact
triangle-edge tests; the fine surface may intersect itself).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import igl
import numpy as np

from .._geometry import cross_intersection_pairs
from ..collision import PairMesh, self_collision_free_step
from .quadrature import quadrature_matrix, triangle_areas

__all__ = ["FlowResult", "flow_inside"]

#: Quadrature points deeper inside Ĉ than this (fraction of the bounding-box diagonal) are not queried
#: again until they may have come closer (:meth:`_Flow.evaluate`). The query of a deep point costs
#: more (the AABB search opens more boxes): on 42400-IDGH.stl's first layer 86% of the 85k points sank
#: deeper than 0.01 while a few stayed outside, and a query went from 0.24 to 0.8 s (75% of the run).
DEEP_POINT_DEPTH = 0.005
#: ... when the flow has at least this many quadrature points. Below, every query is exact and cheap
#: (10k points: under 0.1 s at any depth); the flow's outcome depends on its path, and on
#: angle_block.stl (~3k points) the approximate path failed where the exact one certified a tighter cage.
DEEP_POINT_MIN_POINTS = 10_000


@dataclass
class FlowResult:
    """Outcome of :func:`flow_inside`.

    Attributes
    ----------
    history : list of (nf,3) float arrays
        Fine vertex positions along the flow, ``history[0]`` is the input (exactly), the last is the
        flowed surface F̄. Intermediate iterates are kept every ``keep_every`` of motion.
    success : bool
        True if F̄ is strictly inside Ĉ (all quadrature points inside, no intersection).
    iterations : int
        Flow steps taken.
    reason : str
        Why the flow stopped.
    max_signed_distance : float
        Largest signed distance of a quadrature point of F̄ to Ĉ (negative = all inside).
    target : (nc,3) float array
        The target Ĉ the flow ended inside: the input Ĉ, or Ĉ expanded where the flow got stuck.
    expansions : int
        Number of expansion steps applied to Ĉ.
    """

    history: list
    success: bool
    iterations: int
    reason: str
    max_signed_distance: float
    intersection_checks: int = 0
    step_sizes: list = field(default_factory=list)
    target: np.ndarray | None = None
    expansions: int = 0

    def to_dict(self) -> dict:
        """JSON-serialisable summary (without the history arrays)."""
        return {
            "success": bool(self.success),
            "iterations": int(self.iterations),
            "reason": self.reason,
            "max_signed_distance": float(self.max_signed_distance),
            "snapshots": len(self.history),
            "intersection_checks": int(self.intersection_checks),
            "expansions": int(self.expansions),
        }


def _signed_distance(P: np.ndarray, Vc: np.ndarray, Fc: np.ndarray):
    """Signed distance, closest faces, closest points and pseudonormals of ``P`` w.r.t. Ĉ."""
    S, I, Q, N = igl.signed_distance(P, Vc, Fc, sign_type=igl.SIGNED_DISTANCE_TYPE_PSEUDONORMAL)
    return S, I, Q, N


def _expand_target(Vc: np.ndarray, Fc: np.ndarray, faces: np.ndarray, amount: np.ndarray):
    """Push the target Ĉ outward around some of its faces (paper Sec. 3.1, "expand the coarse mesh").

    Every vertex of ``faces[i]`` moves along its angle-weighted normal by the largest ``amount[i]``
    of its listed faces. The motion is cut by CCD so Ĉ never intersects itself. Returns the new
    vertices and the step fraction taken.
    """
    a = np.zeros(len(Vc))
    for k in range(3):  # the three corners; vectorised over faces
        np.maximum.at(a, Fc[faces, k], amount)
    Nv = igl.per_vertex_normals(Vc, Fc, igl.PER_VERTEX_NORMALS_WEIGHTING_TYPE_ANGLE)
    D = a[:, None] * Nv
    alpha = self_collision_free_step(Vc, Fc, Vc + D)
    return Vc + min(1.0, alpha) * D, alpha


def flow_inside(
    Vf: np.ndarray,
    Ff: np.ndarray,
    Vc: np.ndarray,
    Fc: np.ndarray,
    *,
    quad_order: int = 2,
    step: float = 1e-3,
    max_step: float = 1e-2,
    max_iter: int = 1000,
    eps: float = 1e-5,
    margin: float = 0.0,
    keep_every: float = 5e-3,
    stall_iter: int = 150,
    active_depth: float | None = None,
    expand_after: int | None = 50,
    max_expansions: int = 20,
    stall_window: int | None = None,
    plateau_window: int | None = None,
    callback: Callable[[int], None] | None = None,
) -> FlowResult:
    """Flow the fine surface along the signed distance to Ĉ until it is strictly inside Ĉ.

    Parameters
    ----------
    Vf : (nf,3) float array
        Fine vertices (not modified).
    Ff : (mf,3) int array
        Fine triangles.
    Vc : (nc,3) float array
        Target (decimated) vertices Ĉ; must be closed and free of self-intersections.
    Fc : (mc,3) int array
        Target triangles.
    quad_order : int
        Triangle quadrature degree (paper: 2nd order by default).
    step : float
        Initial step ∆t as a fraction of the bounding-box diagonal of F (paper: 1e-3).
    max_step : float
        Largest step the line search may grow to (fraction of the diagonal).
    max_iter : int
        Iteration cap (the reference implementation gives up after 1000).
    eps : float
        Distance (fraction of the diagonal) under which the pseudonormal replaces p - q* (Eq. 6).
    margin : float
        Extra depth (fraction of the diagonal) every quadrature point must reach inside Ĉ.
    keep_every : float
        A snapshot is stored in the history after this much motion (fraction of the diagonal) of the
        fastest vertex, plus the first and the last positions.
    stall_iter : int
        Give up if this many iterations pass with all quadrature points inside but intersections left.
    active_depth : float, optional
        If given (fraction of the diagonal), only quadrature points outside Ĉ or less than this deep
        inside it are flowed ("local" flow): the integrand becomes sd(p) restricted to
        sd(p) > -active_depth, so the parts of F already well inside stay at rest and the history
        (hence the re-inflation) is much shorter. ``None`` is the paper's flow (every point moves).
    expand_after : int or None
        When some quadrature points stay outside Ĉ and the largest signed distance has not improved
        for this many iterations, expand Ĉ locally (the paper's remedy for hard cases: "reverse the
        picture and expand the coarse mesh"), CCD-limited so Ĉ stays free of self-intersections.
        Likewise every ``expand_after`` iterations during which all points are inside but Ĉ still
        crosses F̄: Ĉ is expanded around the crossing faces.
        ``None`` disables it (then ``FlowResult.target`` is Ĉ itself).
    max_expansions : int
        Cap on expansion steps.
    stall_window : int, optional
        Fail fast (None: never): every ``min(25, stall_window)`` iterations after ``2 * stall_window``,
        while quadrature points are still outside Ĉ (or within the margin), the decrease of the largest
        signed distance over the last ``stall_window`` iterations is extrapolated linearly; if reaching
        the margin at that rate needs more iterations than ``max_iter`` leaves, the flow stops with a
        "stalled ... outside" reason (it cannot succeed within the cap unless it speeds up).
    plateau_window : int, optional
        Fail faster (None: never), for a flow that another target can replace: every 5 iterations after
        ``2 * plateau_window``, while points are outside, stop when the smallest largest signed distance
        of the last ``plateau_window`` iterations is no lower than that of the ``plateau_window`` before
        (no progress at all: expansions and flow together going nowhere, see :func:`_plateaued`).
        Likewise once every point is inside but Ĉ still crosses F̄: stop when the fewest crossing pairs
        counted (every ``expand_after`` such iterations) in the last ``plateau_window`` of them are no
        fewer than in the ``plateau_window`` before (:func:`_crossings_plateaued`).
    callback : callable, optional
        Called with the iteration number after each step (progress bars).

    Returns
    -------
    FlowResult
    """
    fl = _Flow(Vf, Ff, Vc, Fc, quad_order, active_depth)
    diag = fl.diag
    h, h_max, h_min = step * diag, max_step * diag, step * diag / 64
    eps_abs, margin_abs, keep_abs = eps * diag, margin * diag, keep_every * diag
    history = [fl.Vf0.copy()]
    last_kept = fl.V.copy()
    reason = f"no convergence after {max_iter} iterations"
    success = False
    steps = []
    best, since_best = float(fl.S.max()), 0
    smax_log = [float(fl.S.max())]  # largest signed distance after each iteration (stall_window)
    while True:
        if fl.S.max() < best - 0.02 * max(abs(best), 1e-4 * diag):
            best, since_best = float(fl.S.max()), 0
        else:
            since_best += 1
        if (expand_after is not None and fl.S.max() > -margin_abs and since_best >= expand_after
                and fl.n_expand < max_expansions):
            # points stuck outside (or within the margin): push their closest faces out by sd + margin
            m_e = max(margin_abs, 1e-3 * diag)
            stuck = fl.S > -m_e
            fl.expand(fl.I[stuck], fl.S[stuck] + m_e)
            since_best, best = 0, np.inf
            continue
        if fl.S.max() < -margin_abs:
            action = _when_inside(fl, stall_iter, expand_after, max_expansions, plateau_window)
            if action == "inside":
                success, reason = True, "inside"
                break
            if action == "again":
                continue
            if action == "stalled":
                reason = (f"stalled: quadrature points inside but intersections remain after {fl.it} "
                          f"iterations")
                break
            if action == "plateaued":
                reason = (f"plateaued: quadrature points inside but intersections remain after {fl.it} "
                          f"iterations (crossing pairs no fewer in the last {plateau_window} inside "
                          f"iterations than in the {plateau_window} before: {fl.crossings[-1]})")
                break
        if fl.it >= max_iter:
            break
        h = _descent_step(fl, h, h_min, eps_abs)
        steps.append(h / diag)
        h = min(h * 1.25, h_max)
        fl.it += 1
        if stall_window or plateau_window:
            smax_log.append(float(fl.S.max()))
            stalled = ""
            if stall_window:
                stalled = _stalled_outside(smax_log, fl.it, stall_window, margin_abs, max_iter, diag)
            stalled = stalled or _plateaued(smax_log, fl.it, plateau_window, margin_abs, diag)
            if stalled:
                reason = stalled
                break
        if np.abs(fl.V - last_kept).max() >= keep_abs:
            history.append(fl.V.copy())
            last_kept = fl.V.copy()
        if callback is not None:
            callback(fl.it)
    if history[-1] is not fl.V and not np.array_equal(history[-1], fl.V):
        history.append(fl.V.copy())
    return FlowResult(history, success, fl.it, reason, float(fl.S.max()), fl.n_checks, steps, fl.Vc,
                      fl.n_expand)


class _Flow:
    """State of one :func:`flow_inside` run: the iterate F̄, its quadrature, the target Ĉ, counters."""

    def __init__(self, Vf, Ff, Vc, Fc, quad_order: int, active_depth: float | None):
        self.Vf0 = np.array(Vf, dtype=float)  # private copy: the caller's array is never touched
        self.Ff = np.asarray(Ff, dtype=np.int64)
        self.Vc = np.array(Vc, dtype=float)  # private copy (may be expanded)
        self.Fc = np.asarray(Fc, dtype=np.int64)
        self.diag = float(np.linalg.norm(self.Vf0.max(0) - self.Vf0.min(0)))
        self.active_depth = active_depth
        self.B, self.w = quadrature_matrix(self.Ff, len(self.Vf0), quad_order)
        self.pair = PairMesh(self.Vc, self.Fc, self.Vf0, self.Ff)
        self.it = self.n_checks = self.inside_iters = self.n_expand = 0
        self.crossings: list = []  # crossing pairs of Ĉ and F̄ counted by :func:`_when_inside`
        self._exact = None  # per point: position, signed distance, face, closest point, normal when exact
        self.V = self.Vf0.copy()
        self.evaluate_here()

    def evaluate(self, V: np.ndarray) -> tuple:
        """Quadrature points ``P`` of ``V``, their signed distances, closest points and pseudonormals on Ĉ
        and weights (area × rule weight); ``self.I``: their closest faces of Ĉ.

        Deep points are not queried again (:data:`DEEP_POINT_DEPTH`): a point whose exact distance,
        measured at ``P0``, was ``-s0 > depth`` and that has moved less than ``-s0 - depth`` since, is
        still deeper than ``depth`` (the distance is 1-Lipschitz); it keeps its closest point ``q0``
        and gets ``-|p - q0|`` (a bound on the true value, exact while the closest point stays). Every
        point within ``depth`` of Ĉ, hence every point that decides "inside", is exact.
        """
        P = self.B @ V
        W = np.outer(triangle_areas(V, self.Ff), self.w).ravel()  # area × rule weight per point
        ex = self._exact  # reset by evaluate_here whenever Ĉ or the quadrature changes
        if ex is None or len(P) < DEEP_POINT_MIN_POINTS:
            S, I, Q, N = _signed_distance(P, self.Vc, self.Fc)
            if len(P) >= DEEP_POINT_MIN_POINTS:  # copies: the cache is updated in place, the arrays
                # returned become the flow's state
                self._exact = {"P": P.copy(), "S": S.copy(), "I": I.copy(), "Q": Q.copy(), "N": N.copy()}
            self.I = I
            return P, S, Q, N, W
        depth = DEEP_POINT_DEPTH * self.diag
        moved = np.linalg.norm(P - ex["P"], axis=1)
        redo = np.flatnonzero(~(ex["S"] < -depth) | (moved >= -ex["S"] - depth))
        if len(redo):
            S, I, Q, N = _signed_distance(np.ascontiguousarray(P[redo]), self.Vc, self.Fc)
            for k, v in (("P", P[redo]), ("S", S), ("I", I), ("Q", Q), ("N", N)):
                ex[k][redo] = v
        Q, N, self.I = ex["Q"].copy(), ex["N"].copy(), ex["I"].copy()
        S = -np.linalg.norm(P - Q, axis=1)
        S[redo] = ex["S"][redo]
        return P, S, Q, N, W

    def evaluate_here(self) -> None:
        self._exact = None  # Ĉ or the quadrature changed: query every point
        self.P, self.S, self.Q, self.N, self.W = self.evaluate(self.V)

    def phi(self, S: np.ndarray, W: np.ndarray) -> float:
        """Φ (Eq. 1) by quadrature; the local flow ignores points deeper than ``active_depth``."""
        if self.active_depth is not None:
            S = np.maximum(S, -self.active_depth * self.diag)
        return float(W @ S)

    def refine_quadrature(self, order: int) -> None:
        self.B, self.w = quadrature_matrix(self.Ff, len(self.Vf0), order)
        self.evaluate_here()

    def expand(self, faces: np.ndarray, amount: np.ndarray) -> None:
        """Expand Ĉ around ``faces`` (:func:`_expand_target`) and evaluate again."""
        self.Vc, _ = _expand_target(self.Vc, self.Fc, faces, amount)
        self.n_expand += 1
        self.pair = PairMesh(self.Vc, self.Fc, self.Vf0, self.Ff)
        self.evaluate_here()


def _when_inside(fl: _Flow, stall_iter: int, expand_after: int | None, max_expansions: int,
                 plateau_window: int | None = None) -> str:
    """Every quadrature point is inside Ĉ: ``"inside"`` (no intersection left), ``"again"`` (denser
    quadrature or Ĉ expanded: evaluate again), ``"stalled"``, ``"plateaued"``
    (:func:`_crossings_plateaued`), or ``""`` (keep flowing)."""
    fl.n_checks += 1
    if not fl.pair.intersects(fl.pair.stack(fl.Vc, fl.V)):
        return "inside"
    fl.inside_iters += 1
    if fl.inside_iters == stall_iter // 4 and len(fl.w) < 7:
        # every quadrature point is inside but triangles still cut Ĉ (they stretch around
        # Ĉ's corners, the paper's "invalid F̄"): sample each triangle more densely
        fl.refine_quadrature(5)
        return "again"
    if expand_after is not None and fl.inside_iters % expand_after == 0:
        # still cut by Ĉ: expand Ĉ around the faces that cross the fine surface. The flow alone rarely
        # clears these crossings (Ĉ's edges dipping into F between quadrature points): on the envelope
        # target of featuretype.stl's first layer it went on for 100 iterations until the 4th expansion.
        # The crossings are counted also once the expansions are used up (the plateau rule).
        pairs = cross_intersection_pairs(fl.Vc, fl.Fc, fl.V, fl.Ff)
        fl.crossings.append(len(pairs))
        if _crossings_plateaued(fl.crossings, plateau_window, expand_after):
            return "plateaued"
        if len(pairs) and fl.n_expand < max_expansions:
            fl.expand(pairs[:, 0], np.full(len(pairs), 2e-3 * fl.diag))
            return "again"
    return "stalled" if fl.inside_iters >= stall_iter else ""


def _crossings_plateaued(counts: list, window: int | None, every: int) -> bool:
    """True when the fewest crossing pairs among the counts of the last ``window`` inside iterations (one
    count every ``every`` of them) is no lower than among the ``window`` before: expansions and flow
    together clear no crossing.

    Measured (``nestmg cages``, 2026-12-05, one run): featuretype.stl's second layer, envelope target
    at 0.01 (218 faces): 8, 24, 24, 22 crossing pairs at the first counts, then 24 at every count after
    the expansions were used up, until ``stall_iter`` stopped it after 139 iterations (2.4 CPU s); the
    coarser envelope then certified in 0 iterations. This rule stops that flow at its 8th count (39
    iterations); the envelope flow of the first layer that certified (counts ... 102, 60, 35, 10, then
    no crossing) does not meet it.
    """
    if not window:
        return False
    m = max(1, window // max(every, 1))
    if len(counts) < 2 * m:
        return False
    return min(counts[-m:]) >= min(counts[-2 * m:-m])


def _descent_step(fl: _Flow, h: float, h_min: float, eps_abs: float) -> float:
    """One step of the flow (Eqs. 5-6) with a backtracking line search on Φ; returns the step taken."""
    S, W = fl.S, fl.W
    # Eq. 6: unit direction of increasing signed distance, pseudonormal when too close
    D = fl.P - fl.Q
    dist = np.abs(S)
    G = np.where((dist > eps_abs)[:, None], np.sign(S)[:, None] * D / np.maximum(dist, 1e-300)[:, None], fl.N)
    if fl.active_depth is not None:
        G[S < -fl.active_depth * fl.diag] = 0.0
    # Eq. 5: gather at vertices (weights: area × rule weight × barycentric coordinate)
    grad = fl.B.T @ (W[:, None] * G)
    mass = fl.B.T @ W
    vel = -grad / np.maximum(mass, 1e-300)[:, None]
    phi0 = fl.phi(S, W)
    # backtracking line search on Φ (closest points are recomputed at the trial positions)
    while True:
        Vt = fl.V + h * vel
        Pt, St, Qt, Nt, Wt = fl.evaluate(Vt)
        if fl.phi(St, Wt) < phi0 or h <= h_min:
            break
        h *= 0.5
    fl.V, fl.P, fl.S, fl.Q, fl.N, fl.W = Vt, Pt, St, Qt, Nt, Wt
    return h


def _plateaued(smax_log: list, it: int, window: int | None, margin_abs: float, diag: float) -> str:
    """The ``plateau_window`` reason (``""``: not plateaued, or not time to check).

    Measured on the flows of layer targets (quarter faces, pipeline clearance): featuretype.stl's
    shortest-edge layer rose from 0.002 to 0.013 of the diagonal over 143 iterations and 20 expansions
    (stopped by this rule after 40 with a window of 20); the successful flows of decimated-knight.off (80
    iterations, 17 expansions), angle_block.stl (42, 9), featuretype's envelope (26, 7), round.stl and
    plate_holes.stl never met the rule.
    """
    if not (window and it >= 2 * window and it % 5 == 0 and smax_log[-1] > -margin_abs):
        return ""
    recent, before = min(smax_log[-window:]), min(smax_log[-2 * window:-window])
    if recent < before:
        return ""
    return (f"plateaued: points outside after {it} iterations (largest signed distance no lower in the "
            f"last {window} than in the {window} before: {recent / diag:.3g} of the diagonal)")


def _stalled_outside(smax_log: list, it: int, stall_window: int, margin_abs: float, max_iter: int,
                     diag: float) -> str:
    """The ``stall_window`` reason when the largest signed distance, falling at its recent rate, cannot
    reach the margin within ``max_iter`` (``""`` otherwise or when it is not time to check)."""
    if not (it >= 2 * stall_window and it % min(25, stall_window) == 0 and smax_log[-1] > -margin_abs):
        return ""
    drop = smax_log[-1 - stall_window] - smax_log[-1]
    need = np.inf if drop <= 0 else (smax_log[-1] + margin_abs) / drop * stall_window
    if need <= max_iter - it:
        return ""
    return (f"stalled: points outside after {it} iterations (largest signed distance "
            f"{smax_log[-1] / diag:.3g} of the diagonal, down {max(drop, 0.0) / diag:.2g} in the "
            f"last {stall_window}; about {need:.0f} more iterations needed at that rate, "
            f"{max_iter - it} left)")
