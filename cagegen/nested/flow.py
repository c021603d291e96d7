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
        ``None`` disables it (then ``FlowResult.target`` is Ĉ itself).
    max_expansions : int
        Cap on expansion steps.
    stall_window : int, optional
        Fail fast (None: never): every ``min(25, stall_window)`` iterations after ``2 * stall_window``,
        while quadrature points are still outside Ĉ (or within the margin), the decrease of the largest
        signed distance over the last ``stall_window`` iterations is extrapolated linearly; if reaching the margin at that rate
        needs more iterations than ``max_iter`` leaves, the flow stops with a "stalled ... outside"
        reason (it cannot succeed within the cap unless it speeds up).
    callback : callable, optional
        Called with the iteration number after each step (progress bars).

    Returns
    -------
    FlowResult
    """
    Vf0 = np.array(Vf, dtype=float)  # private copy: the caller's array is never touched
    Ff = np.asarray(Ff, dtype=np.int64)
    Vc = np.array(Vc, dtype=float)  # private copy (may be expanded)
    Fc = np.asarray(Fc, dtype=np.int64)
    diag = float(np.linalg.norm(Vf0.max(0) - Vf0.min(0)))
    h, h_max, h_min = step * diag, max_step * diag, step * diag / 64
    eps_abs, margin_abs, keep_abs = eps * diag, margin * diag, keep_every * diag

    B, w = quadrature_matrix(Ff, len(Vf0), quad_order)
    q = len(w)
    pair = PairMesh(Vc, Fc, Vf0, Ff)

    def evaluate(V):
        P = B @ V
        S, I, Q, N = _signed_distance(P, Vc, Fc)
        evaluate.I = I
        W = np.outer(triangle_areas(V, Ff), w).ravel()  # area × rule weight per point
        return P, S, Q, N, W

    def phi(S, W):
        if active_depth is not None:
            S = np.maximum(S, -active_depth * diag)
        return float(W @ S)

    V = Vf0.copy()
    P, S, Q, N, W = evaluate(V)
    history = [Vf0.copy()]
    last_kept = V.copy()
    n_checks, inside_iters, it = 0, 0, 0
    reason = f"no convergence after {max_iter} iterations"
    success = False
    steps = []
    best, since_best, n_expand = float(S.max()), 0, 0
    smax_log = [float(S.max())]  # largest signed distance after each iteration (stall_window)
    while True:
        if S.max() < best - 0.02 * max(abs(best), 1e-4 * diag):
            best, since_best = float(S.max()), 0
        else:
            since_best += 1
        if (expand_after is not None and S.max() > -margin_abs and since_best >= expand_after
                and n_expand < max_expansions):
            # points stuck outside (or within the margin): push their closest faces out by sd + margin
            m_e = max(margin_abs, 1e-3 * diag)
            stuck = S > -m_e
            Vc, _ = _expand_target(Vc, Fc, evaluate.I[stuck], S[stuck] + m_e)
            n_expand += 1
            since_best, best = 0, np.inf
            pair = PairMesh(Vc, Fc, Vf0, Ff)
            P, S, Q, N, W = evaluate(V)
            continue
        if S.max() < -margin_abs:
            n_checks += 1
            if not pair.intersects(pair.stack(Vc, V)):
                success, reason = True, "inside"
                break
            inside_iters += 1
            if inside_iters == stall_iter // 4 and q < 7:
                # every quadrature point is inside but triangles still cut Ĉ (they stretch around
                # Ĉ's corners, the paper's "invalid F̄"): sample each triangle more densely
                B, w = quadrature_matrix(Ff, len(Vf0), 5)
                q = len(w)
                P, S, Q, N, W = evaluate(V)
                continue
            if (expand_after is not None and inside_iters > stall_iter // 4 and inside_iters % 25 == 0
                    and n_expand < max_expansions):
                # still cut by Ĉ: expand Ĉ around the faces that cross the fine surface
                pairs = cross_intersection_pairs(Vc, Fc, V, Ff)
                if len(pairs):
                    Vc, _ = _expand_target(Vc, Fc, pairs[:, 0], np.full(len(pairs), 2e-3 * diag))
                    n_expand += 1
                    pair = PairMesh(Vc, Fc, Vf0, Ff)
                    P, S, Q, N, W = evaluate(V)
                    continue
            if inside_iters >= stall_iter:
                reason = f"stalled: quadrature points inside but intersections remain after {it} iterations"
                break
        if it >= max_iter:
            break
        # Eq. 6: unit direction of increasing signed distance, pseudonormal when too close
        D = P - Q
        dist = np.abs(S)
        G = np.where((dist > eps_abs)[:, None], np.sign(S)[:, None] * D / np.maximum(dist, 1e-300)[:, None], N)
        if active_depth is not None:
            G[S < -active_depth * diag] = 0.0
        # Eq. 5: gather at vertices (weights: area × rule weight × barycentric coordinate)
        grad = B.T @ (W[:, None] * G)
        mass = B.T @ W
        vel = -grad / np.maximum(mass, 1e-300)[:, None]
        phi0 = phi(S, W)
        # backtracking line search on Φ (closest points are recomputed at the trial positions)
        while True:
            Vt = V + h * vel
            Pt, St, Qt, Nt, Wt = evaluate(Vt)
            if phi(St, Wt) < phi0 or h <= h_min:
                break
            h *= 0.5
        V, P, S, Q, N, W = Vt, Pt, St, Qt, Nt, Wt
        steps.append(h / diag)
        h = min(h * 1.25, h_max)
        it += 1
        if stall_window:
            smax_log.append(float(S.max()))
            if it >= 2 * stall_window and it % min(25, stall_window) == 0 and smax_log[-1] > -margin_abs:
                drop = smax_log[-1 - stall_window] - smax_log[-1]
                need = np.inf if drop <= 0 else (smax_log[-1] + margin_abs) / drop * stall_window
                if need > max_iter - it:
                    reason = (f"stalled: points outside after {it} iterations (largest signed distance "
                              f"{smax_log[-1] / diag:.3g} of the diagonal, down {max(drop, 0.0) / diag:.2g} in the "
                              f"last {stall_window}; about {need:.0f} more iterations needed at that rate, "
                              f"{max_iter - it} left)")
                    break
        if np.abs(V - last_kept).max() >= keep_abs:
            history.append(V.copy())
            last_kept = V.copy()
        if callback is not None:
            callback(it)
    if history[-1] is not V and not np.array_equal(history[-1], V):
        history.append(V.copy())
    return FlowResult(history, success, it, reason, float(S.max()), n_checks, steps, Vc, n_expand)
