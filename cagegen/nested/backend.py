"""The ``"nested"`` cage backend: Sacht et al.'s Nested Cages (2015), layer by layer.

For every consecutive pair (fine layer F, target face count m):

1. **Decimate** F (or, with ``decimate_from="input"``, the input) to Ĉ with m faces
   (:func:`cagegen.decimate.decimate_surface`: watertight, self-intersection free, same genus).
2. **Flow** F inside Ĉ along Ĉ's signed distance (:func:`cagegen.nested.flow.flow_inside`).
3. **Re-inflate** F back to its rest pose along the reversed flow, pushing Ĉ out of the way with
   ipctk's CCD and barrier (:func:`cagegen.nested.reinflate.reinflate`), then minimise the final
   energy of the cage with F at rest.
4. **Certify** the pair with :func:`cagegen.verify_nesting`; a failing layer is never returned.

When the flow or the re-inflation fails (the paper's known failure: Ĉ too far from F, e.g. bunny
→ [1000, 250] in the reference implementation), the pair is retried with the other decimator, then
with an intermediate layer inserted (F → √(|F|·m) faces → m), recursively; every action is
recorded in ``info["layers"][k]["recovery"]``.

The work is done on a copy scaled to a unit bounding-box diagonal (the paper's step sizes are
relative to it); the cages are mapped back to the input's coordinates and certified there.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import NamedTuple

import igl
import numpy as np
from threadpoolctl import threadpool_limits

from .._geometry import normalize
from ..collision import PairMesh, close_edge_pairs, ipctk_threads, min_distance, self_collision_free_step
from ..decimate import decimate_surface
from ..envelope import build_envelope
from ..errors import CageError, CageOptionError
from ..failures import PairFailure
from ..fallbacks import FALLBACKS
from ..options import check_time_budget
from ..split_edges import split_long_edges
from ..verify import verify_nesting
from .energies import COPYLEFT_ENERGIES, ENERGIES, check_energy_available, signed_volume
from .flow import flow_inside
from .reinflate import reinflate

__all__ = ["budget_check", "complete_clearance", "estimate_seconds", "nest_pair", "nested_backend", "offset_surface",
           "push_out"]

#: ``kappa`` (the barrier's stiffness while re-inflating) is 1e4, was 1e3: a stiffer barrier keeps the cage
#: further ahead of the fine surface, with fewer contacts inside ``dhat`` (homer.obj 557k -> 494k over a run)
#: and cheaper Newton steps. CPU geomean x0.953-0.955 over 21 zoo meshes in two runs, lucy.ply's full surface
#: 152 -> 107 s, three meshes 1.12-1.19x slower (``benchmarks/results/cages/ab_kappa1e4_0e7e562*.json``); the
#: corpus solve column with it certified 22 of 22 meshes within every goal (``corpus/zoo_kappa1e4.json``).
_DEFAULTS = {
    "energy": "volume",
    "quad_order": 2,
    "flow_step": 1e-3,
    "flow_max_iter": 1000,
    "dhat": 5e-3,
    "kappa": 1e4,
    "dhat_final": 1e-3,
    "kappa_final": 1e3,
    "max_move": 5e-3,
    "final_iters": 60,
}


class _Reporter:
    """Progress output: rich bars (``progress=True``), a message callable, or nothing."""

    def __init__(self, progress):
        self.say: Callable[[str], None] = lambda msg: None
        self.bar = None
        if callable(progress):
            self.say = progress
        elif progress:
            from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

            self.bar = Progress(TextColumn("{task.description}"), BarColumn(),
                                TextColumn("{task.completed}/{task.total}"), TimeElapsedColumn(),
                                transient=False)
        self.layer_task = None
        self.phase_task = None

    def __enter__(self):
        if self.bar is not None:
            self.bar.__enter__()
        return self

    def __exit__(self, *exc):
        if self.bar is not None:
            self.bar.__exit__(*exc)

    def layers(self, n: int) -> None:
        if self.bar is not None:
            self.layer_task = self.bar.add_task("nested cages: layers", total=n)

    def layer_done(self) -> None:
        if self.bar is not None:
            self.bar.advance(self.layer_task)

    def phase(self, name: str, total: int | None) -> Callable:
        """Start a phase; returns ``update(done, total=None)``."""
        self.say(name)
        if self.bar is None:
            return lambda done, total=None: None
        if self.phase_task is not None:
            self.bar.remove_task(self.phase_task)
        self.phase_task = self.bar.add_task(f"  {name}", total=total)
        task = self.phase_task

        def update(done: int, total: int | None = None) -> None:
            self.bar.update(task, completed=done, total=total if total is not None else None)

        return update


def offset_surface(V: np.ndarray, F: np.ndarray, gap: float, fold_factor: float | None = None) -> np.ndarray:
    """Vertices moved outward so every face plane of ``(V, F)`` is at least ``gap`` behind them.

    Each vertex moves along its angle-weighted normal n by ``gap / min_f (n · n_f)`` (incident faces
    f, the factor clamped to 3), so a cage outside the offset surface keeps about ``gap`` from the
    original one. The offset surface may self-intersect in thin parts; nothing here needs it not to
    (the flow and re-inflation ignore fine-fine contacts) and the gap is measured on the original.

    Parameters
    ----------
    V : (n,3) float array
    F : (m,3) int array
    gap : float or (n,) float array
        Absolute offset distance (per vertex if an array).
    fold_factor : float, optional
        The factor of the vertices past the clamp (some ``n · n_f < 1/3``: a fold or a needle, where no
        direction clears every incident plane), instead of 3.

    Returns
    -------
    (n,3) float array
    """
    if np.all(np.asarray(gap) <= 0):
        return np.array(V, dtype=float)
    N = igl.per_vertex_normals(V, F, igl.PER_VERTEX_NORMALS_WEIGHTING_TYPE_ANGLE)
    FN = igl.per_face_normals(V, F, np.array([0.0, 0.0, 1.0]))
    cos = np.full(len(V), 1.0)
    for k in range(3):  # vectorised over faces, loop over the 3 corners
        np.minimum.at(cos, F[:, k], np.einsum("ij,ij->i", N[F[:, k]], FN))
    scale = 1.0 / np.clip(cos, 1.0 / 3.0, 1.0)
    if fold_factor is not None:
        scale[cos < 1.0 / 3.0] = fold_factor
    return V + (gap * scale)[:, None] * N


def push_out(C: np.ndarray, Fc: np.ndarray, Vf: np.ndarray, Ff: np.ndarray, gap: float,
             max_iter: int = 8, accept: float | None = None, distance: float | None = None
             ) -> tuple[np.ndarray | None, dict]:
    """Move a cage that contains ``(Vf, Ff)`` outward until it keeps ``gap`` from it.

    Each pass offsets the cage by the missing clearance (:func:`offset_surface` of the cage itself:
    every face plane moves out by at least that much) along a straight path cut by ipctk's CCD, so the
    cage never meets itself nor the fine surface on the way.

    Parameters
    ----------
    C : (nc,3) float array
    Fc : (mc,3) int array
        The cage (containing the fine surface, free of self-intersections).
    Vf : (nf,3) float array
    Ff : (mf,3) int array
        The fine surface (fixed).
    gap : float
        Absolute clearance wanted.
    max_iter : int
        Passes before giving up.
    accept : float, optional
        When the motion is blocked or the passes run out, the cage reached so far is still returned if it
        keeps at least this distance (default: ``gap``).
    distance : float, optional
        :func:`cagegen.collision.min_distance` of ``C`` to F when the caller has it (not measured again).

    Returns
    -------
    C2 : (nc,3) float array or None
        The pushed cage, or None when the motion was blocked before ``accept`` (``info["reason"]``).
    info : dict
        ``passes``, ``distance`` (achieved, of the returned cage when there is one), ``reason``.
    """
    C = np.array(C, dtype=float)
    accept = gap if accept is None else float(accept)
    pair = PairMesh(C, Fc, Vf, Ff)
    d = min_distance(C, Fc, Vf, Ff) if distance is None else float(distance)
    info: dict = {"passes": 0, "distance_before": d}
    adj = igl.adjacency_matrix(np.asarray(Fc, dtype=np.int64)).tocsr()
    for it in range(max_iter):
        if d >= gap:
            info.update(distance=d, reason="ok")
            return C, info
        near = _near_parts(C, Fc, Vf, Ff, 1.05 * gap)
        target = _push_target(C, Fc, gap, adj, near, 1.05 * gap)
        alpha = pair.stepsize(pair.stack(C, Vf), pair.stack(target, Vf))
        if alpha < 1.0:  # blocked (two cage sheets pushed into each other in a slot, ...): only the parts
            # closer than ``accept`` then move, if that goes farther (box_parts.stl's union: 4 vertices
            # instead of 569, free, where the full push stopped at 0.06 of its way five passes running)
            t2 = _push_target(C, Fc, gap, adj, near, accept, soften=False)
            a2 = pair.stepsize(pair.stack(C, Vf), pair.stack(t2, Vf))
            if a2 > alpha:
                target, alpha = t2, a2
        info["passes"] = it + 1
        if alpha <= 1e-3:
            info.update(distance=d, reason=f"blocked by a collision at pass {it + 1} (step {alpha:.2g})")
            return (C if d >= accept else None), info
        C = C + min(1.0, alpha) * (target - C)
        d = min_distance(C, Fc, Vf, Ff)
    info.update(distance=d, reason="ok" if d >= gap else f"gap {d:.3g} < {gap:.3g} after {max_iter} passes")
    return (C, info) if d >= accept else (None, info)


def _near_parts(C: np.ndarray, Fc: np.ndarray, Vf: np.ndarray, Ff: np.ndarray, radius: float) -> tuple:
    """The distances :func:`_push_target` reads, for every threshold up to ``radius``: fine vertices to
    their nearest cage faces ``(df, I)``, cage vertices to F ``dc``, and the cage edges closer than
    ``radius`` to an edge of F (:func:`cagegen.collision.close_edge_pairs`)."""
    d2, I, _ = igl.point_mesh_squared_distance(Vf, C, Fc)
    dc = np.sqrt(igl.point_mesh_squared_distance(C, Vf, Ff)[0])
    return np.sqrt(d2), I, dc, close_edge_pairs(C, Fc, Vf, Ff, radius)


def _push_target(C: np.ndarray, Fc: np.ndarray, gap: float, adj, near: tuple, below: float,
                 soften: bool = True) -> np.ndarray:
    """:func:`push_out`'s target for one pass: the cage parts closer than ``below`` to F (``near``, from
    :func:`_near_parts` at a radius >= ``below``) moved out to ``1.05 gap`` (point distances: along the cage's
    normals; a cage edge passing over an edge of F, a sharp crease where no vertex is close: along that pair's
    direction, as the vertex normals may run along it). Parts already far stay, so the cage's own creases do
    not close up; ``soften`` moves the neighbours of a moved vertex half as far."""
    df, I, dc, (E, de, dirs) = near
    need = np.zeros(len(C))
    short = df < below
    for k in range(3):
        np.maximum.at(need, Fc[I[short], k], 1.05 * gap - df[short])
    need = np.maximum(need, np.where(dc < below, 1.05 * gap - dc, 0.0))
    if soften:
        need = np.maximum(need, 0.5 * adj.multiply(need[None, :]).max(axis=1).toarray().ravel())
    need = np.where(need > 0, need + 0.02 * gap, 0.0)  # a little beyond: the offset is on face planes
    target = offset_surface(C, Fc, need)
    close = de < below
    for k in range(2):
        target[E[close, k]] += (1.07 * gap - de[close])[:, None] * dirs[close]
    return target


#: The flow expands Ĉ where points stay outside for this many iterations (:func:`flow_inside`'s
#: ``expand_after``; its own default is 50): decimated-knight.off's layer 1 came inside in 133 iterations
#: instead of 497 (8.8 s against 25.5 s), angle_block.stl's in 88 instead of 156. The flow's other stall
#: and expansion settings are its defaults (the switches ``flow_stall_iter`` / ``flow_max_expansions``
#: were tried on the skeleton cages and deleted, docs/history/skeleton.md).
FLOW_EXPAND_AFTER = 5


def nest_pair(
    Vf: np.ndarray,
    Ff: np.ndarray,
    Vc: np.ndarray,
    Fc: np.ndarray,
    *,
    energy: str = "volume",
    quad_order: int = 2,
    flow_step: float = 1e-3,
    flow_max_iter: int = 1000,
    flow_active_depth: float | None = None,
    flow_stall_window: int | None = 100,
    flow_plateau_window: int | None = None,
    dhat: float = 5e-3,
    kappa: float = 1e4,
    dhat_final: float = 1e-3,
    kappa_final: float = 1e3,
    max_move: float = 5e-3,
    final_iters: int = 60,
    gap: float = 0.0,
    reporter: _Reporter | None = None,
) -> tuple[np.ndarray, dict]:
    """Deform the target Ĉ = ``(Vc, Fc)`` into a cage that nests the fine surface ``(Vf, Ff)``.

    Works in the caller's units; the relative parameters refer to the bounding-box diagonal of the
    fine surface (the backend passes unit-diagonal inputs, so they are the paper's values).

    Parameters
    ----------
    Vf : (nf,3) float array
    Ff : (mf,3) int array
        Fine surface (rest pose).
    Vc : (nc,3) float array
    Fc : (mc,3) int array
        Target cage Ĉ (closed, free of self-intersections).
    energy : str
        Final cage energy (:data:`cagegen.nested.energies.ENERGIES`).
    quad_order, flow_step, flow_max_iter, flow_active_depth
        Flow options (:func:`cagegen.nested.flow.flow_inside`: ``step``, ``max_iter``,
        ``active_depth``; ``flow_active_depth`` flows only the parts of the fine surface outside Ĉ or
        shallower than that depth, e.g. for a cage that already contains most of it).
    flow_stall_window : int, optional
        :func:`cagegen.nested.flow.flow_inside`'s ``stall_window`` (fail fast when the flow cannot
        finish within ``flow_max_iter`` at its current rate; None: run to the cap).
    flow_plateau_window : int, optional
        :func:`cagegen.nested.flow.flow_inside`'s ``plateau_window`` (stop a flow that makes no progress
        at all; :func:`_build_layer` sets it when another target follows).
    dhat, kappa, dhat_final, kappa_final, max_move, final_iters
        Re-inflation options (:func:`cagegen.nested.reinflate.reinflate`).
    gap : float
        Absolute clearance to keep between the cage and the fine surface (0: any positive gap).
        The clearance is built into the re-inflation: the fine surface itself is flowed and
        re-inflated, and one last reverse step moves it from its rest pose to its offset surface
        (:func:`offset_surface`), pushing the cage out by the gap. (Two other ways were measured and
        deleted, docs/history/scale.md: the tight cage pushed out along its normals, blocked in concave
        creases on the gargoyle; the offset surface flowed instead, 15x the no-clearance time on an
        86k-face scan.)
    reporter : optional
        Progress reporter (internal).

    Returns
    -------
    C : (nc,3) float array
        Cage vertices (same triangles ``Fc``).
    info : dict
        ``flow``, ``reinflate`` figures and ``seconds`` per phase.
    looser : list of (nc,3) float arrays
        Looser cages of the final phase (:attr:`cagegen.nested.reinflate.ReinflateResult.looser`), for
        :func:`complete_clearance`.

    Raises
    ------
    PairFailure
        The flow or the re-inflation failed (internal; the backend recovers or raises CageError).
    """
    rep = reporter or _Reporter(False)
    info: dict = {"seconds": {}}
    Vf, Ff, info["split"] = _split_for_flow(Vf, Ff, Vc, Fc)
    Vc, info["dilation"] = _dilate_target(Vc, Fc, 2.0 * gap if gap > 0 else flow_step)
    # a fold of F (a repaired CAD union's sliver junction: incident normals 120 degrees apart) moves out by
    # the gap alone: its clamped 3x offset pointed where the cage could not follow and the clearance step
    # stalled (box_parts.stl); push_out completes what that leaves (:func:`complete_clearance`)
    target = offset_surface(Vf, Ff, gap, fold_factor=FOLD_FACTOR) if gap > 0 else np.array(Vf, dtype=float)
    flowed = np.array(Vf, dtype=float)

    t = time.perf_counter()
    upd = rep.phase("flow", flow_max_iter)
    fl = flow_inside(flowed, Ff, Vc, Fc, quad_order=quad_order, step=flow_step,
                     max_iter=flow_max_iter, active_depth=flow_active_depth, stall_window=flow_stall_window,
                     plateau_window=flow_plateau_window,
                     expand_after=FLOW_EXPAND_AFTER, callback=lambda it: upd(it))
    info["seconds"]["flow"] = time.perf_counter() - t
    info["flow"] = fl.to_dict()
    if not fl.success:
        raise PairFailure("flow", fl.reason, info)

    t = time.perf_counter()
    upd = rep.phase("re-inflation", None)
    if fl.expansions:
        Vc = fl.target  # the flow expanded Ĉ where it got stuck
    history = fl.history
    if gap > 0:
        # the offset surface becomes the rest pose: the last reverse steps carry the fine surface from
        # its own rest pose out to the offset, and the barrier pushes the cage ahead of it
        history = [target, *history]
    rr = reinflate(history, Ff, Vc, Fc, energy=energy, dhat=dhat, kappa=kappa,
                   dhat_final=dhat_final, kappa_final=kappa_final, max_move=max_move,
                   final_iters=final_iters, callback=lambda k, n: upd(k, n))
    info["seconds"]["reinflate"] = rr.stats.get("t_reinflate", time.perf_counter() - t)
    info["seconds"]["final_energy"] = rr.stats.get("t_final", 0.0)
    info["reinflate"] = {k: (float(v) if isinstance(v, (float, np.floating)) else v) for k, v in rr.stats.items()}
    if not rr.success:
        raise PairFailure("reinflate", rr.reason, info)
    # the re-inflation ends with the fine surface exactly at its rest pose
    info["reinflate"]["fine_at_rest"] = bool(np.array_equal(rr.fine, target))
    return rr.cage, info, rr.looser


#: the offset factor of F's folds in the re-inflation's target (:func:`offset_surface`'s ``fold_factor``)
FOLD_FACTOR = 1.0

#: the re-inflation aims at this many times the requested clearance (:func:`offset_surface` keeps it
#: on face planes, not at the tips of spikes, where its factor is clamped)
GAP_AIM = 1.1

#: the flow's copy of F has no edge longer than this many times Ĉ's median edge (:func:`_split_for_flow`)
SPLIT_FACTOR = 2.0


def _split_for_flow(Vf, Ff, Vc, Fc):
    """The fine surface with no edge longer than :data:`SPLIT_FACTOR` x Ĉ's median edge (same surface).

    The flow samples F at its triangles' quadrature points (paper Eq. 5); a triangle longer than
    Ĉ's edges (CAD exports: long slivers across flat faces) is sampled too sparsely, its points end
    inside Ĉ while its edges still cross Ĉ, and the flow stalls (angle_block.stl, 704 -> 176 faces:
    failed after 1000 iterations unsplit; certified in 6.8 s split at this factor). The flow and
    re-inflation run on the split copy; the cage is certified against the caller's surface.
    """
    E = igl.edges(np.asarray(Fc, dtype=np.int64))
    L = SPLIT_FACTOR * float(np.median(np.linalg.norm(Vc[E[:, 0]] - Vc[E[:, 1]], axis=1)))
    Vs, Fs, sinfo = split_long_edges(Vf, Ff, L, max_faces=max(8 * len(Ff), 20 * len(Fc)))
    sinfo["max_length"] = L
    return Vs, Fs, sinfo


#: Rounds of :func:`_dilate_target`'s local cut: each halves the motion of the vertices around a face
#: that turns too far or meets another face at the dilated position.
DILATE_ROUNDS = 8
#: A face of Ĉ may turn by at most this many degrees when Ĉ is dilated.
DILATE_MAX_TURN_DEGREES = 30.0


def _dilate_target(Vc, Fc, delta):
    """Ĉ moved out by ``delta`` along its normals (:func:`offset_surface`), cut locally, then by CCD.

    A decimation keeps the input's flat faces in place (QEM's error is zero there), so on CAD parts
    Ĉ and F coincide over whole faces: signed distances are 0, the intersection tests degenerate
    (ipctk's CCD warns of gaps of 1e-17). The cage has to keep ``gap`` from F anyway, so starting Ĉ
    about 2 ``gap`` out costs no tightness the clearance had not already taken, and the re-inflation's
    clearance step (F from its rest pose to its offset) then meets Ĉ only where the decimation cut
    into F.

    The motion is cut where it would fold Ĉ: the vertices of a face that turns by more than
    :data:`DILATE_MAX_TURN_DEGREES` (sharp, coarse corners moved along averaged normals: the CCD does
    not see a triangle turning over between its neighbours, and the signed distance to a folded Ĉ keeps
    points "outside" forever, decimated-knight) or that meets another face at the dilated position
    (concave creases, thin parts), and their neighbours, move half as far, round after round
    (:data:`DILATE_ROUNDS`; still folded after them: those vertices stay). The CCD (stopping short of a
    contact) then guards the cut motion. One global fraction, as before 2026-12-04, let a single crease
    stop the whole dilation: 0.02 of it on homer.obj's first target (now 0.82, its first pair 19.5 -> 13
    CPU s: 3 reverse steps instead of 5), 0.0004 on lucy.ply's (now 0.21 of a 0.32 mean: near contacts in
    its drapery still cut the CCD step; its re-inflation 234 -> 213 s).
    """
    from ..intersect import self_pairs

    faces = np.asarray(Fc, dtype=np.int64)
    D = offset_surface(Vc, faces, delta) - Vc
    scale = np.ones(len(Vc))
    N0 = igl.per_face_normals(Vc, faces, np.array([0.0, 0.0, 1.0]))
    adj = igl.adjacency_matrix(faces).tocsr()
    cos_max = np.cos(np.radians(DILATE_MAX_TURN_DEGREES))
    rounds = 0
    moved = None  # faces whose position changed since the last round (None: all)
    for rounds in range(DILATE_ROUNDS + 1):
        W = Vc + scale[:, None] * D
        N1 = igl.per_face_normals(W, faces, np.array([0.0, 0.0, 1.0]))
        bad = np.flatnonzero(np.einsum("ij,ij->i", N0, N1) < cos_max)
        # two faces that kept their position cannot meet: the last round tested them and moved every
        # face of a meeting pair, unless all its vertices were already held at Ĉ (free of intersections)
        bad = np.union1d(bad, self_pairs(W, faces, only=moved).ravel())
        if not len(bad):
            break
        verts = np.zeros(len(Vc), dtype=bool)
        verts[faces[bad].ravel()] = True
        verts |= adj @ verts > 0  # and their neighbours: the cut motion stays smooth
        old = scale.copy()
        scale[verts] = 0.0 if rounds == DILATE_ROUNDS - 1 else 0.5 * scale[verts]
        moved = np.flatnonzero((scale != old)[faces].any(axis=1))
    target = Vc + scale[:, None] * D
    alpha = self_collision_free_step(Vc, Fc, target)
    alpha = min(1.0, 0.9 * alpha) if alpha < 1.0 else 1.0  # stop short of a contact the CCD found
    for _ in range(6):  # a face still turning too far after the rounds: shorten the whole step
        N1 = igl.per_face_normals(Vc + alpha * (target - Vc), faces, np.array([0.0, 0.0, 1.0]))
        if np.einsum("ij,ij->i", N0, N1).min() >= cos_max:
            break
        alpha *= 0.5
    else:
        alpha = 0.0
    return Vc + alpha * (target - Vc), {"delta": float(delta), "fraction": alpha, "rounds": rounds,
                                        "mean_scale": float(scale.mean()),
                                        "held": int(np.count_nonzero(scale == 0.0))}


def _decimate(V, F, n_faces, decimator, inspect=None):
    U, G, dinfo = decimate_surface(V, F, int(n_faces), decimator=decimator, inspect=inspect)
    return U, G, {"decimator": dinfo["decimator"], "block_intersections": dinfo["block_intersections"],
                  "n_faces": int(G.shape[0]), "seconds": dinfo["seconds"]}


#: Ĉ is decimated from the fine layer's envelope at this many times the clearance, and at least
#: :data:`MIN_TARGET_OFFSET` of the diagonal (:func:`_envelope_target`; ``target_offset=None``). The
#: envelope's marching cubes run on a grid of that spacing (the sdf paper's c = h = 0.01): at half the
#: offset and twice the spacing the grid lost featuretype.stl's sharp edges (0.017 of the diagonal
#: outside after decimation, flow stalled); at half both, 4x the faces and time for no better flow.
TARGET_OFFSET_GAPS = 4.0
MIN_TARGET_OFFSET = 0.01

#: When that envelope fails too, one at this fraction of the edge of an equilateral ``n_faces``-face mesh
#: of the layer's area (:func:`_target_edge`, :func:`_target_sources`): a target that coarse cannot follow
#: a hole or a gap narrower than half its edge, so its envelope closes them. featuretype.stl (genus 9):
#: layer 2 (218 faces, edge 0.13 of the diagonal) from the 0.01 envelope, the layer itself and two
#: intermediate layers failed for ~300 s before a 614-face detour certified; the 0.033 envelope is
#: genus 0 and certifies in 0 flow iterations (0.3 CPU s), 6% less cage volume.
TARGET_OFFSET_EDGE_FRACTION = 0.25
COARSE_ENVELOPE_FACTOR = 1.5

#: Work cap (fine faces x iterations) of the flow into every target Ĉ but the last one tried
#: (:func:`_build_layer`), at least :data:`QUICK_FLOW_MIN_ITER` iterations. Each iteration costs about
#: one signed-distance query per quadrature point, so the cap bounds the seconds a target can waste
#: before the next is tried. Measured (``nestmg cages``, 2026-12-03): every flow of eight zoo meshes at
#: three levels (homer, bunny, vase, fandisk, elephant, gargo, pepper; 15 flows) was inside Ĉ after
#: 0-12 iterations; decimated-knight.off and angle_block.stl (~1,000 faces) need 133 and 88 iterations
#: with expansions (cap: 1,000 iterations); on lucy.ply's predecimated 16k faces the flow into the
#: decimated layer plateaus 0.0002-0.0006 of the diagonal outside, with or without expansions, and
#: stopped after 225 iterations (61 s) before the envelope target certified in 6 iterations. Halved from
#: 1,000,000 (2026-12-03, second round): lucy's plateaued flow still used its whole cap of 62 iterations
#: (~0.57 CPU s each), featuretype.stl's first target its 287 before failing; 500,000 keeps every cap
#: measured above the iterations a successful first flow needed (knight: cap 500 for 133).
QUICK_FLOW_WORK = 500_000
QUICK_FLOW_MIN_ITER = 30
#: Every flow, the last target's too, stops once it makes no progress at all over twice this many
#: iterations (:func:`cagegen.nested.flow._plateaued`): featuretype.stl's shortest-edge first target went
#: on for its whole cap of 143 iterations (17-27 s) with its largest signed distance rising; on
#: 42400-IDGH.stl (repaired, layer 1) the last target, deferred for its slots, flowed 200 iterations
#: (170 s) without its largest signed distance falling at all before the recovery certified.
FLOW_PLATEAU = 20

#: Once a layer certified only with the envelope target, the run's later layers try the envelope
#: first (their inputs are that layer's cage, smoother but of the same shape): on lucy.ply's
#: predecimated 16k faces the flow into layer 2's decimated layer failed after its 122-iteration cap
#: (37 of the cages' 124 s, 2026-12-04) before the envelope target certified in 0 iterations, as on
#: layer 1. A layer whose first target certifies changes nothing. The same holds within a recovery,
#: from the intermediate layer to the layer around it: on 42400-IDGH.stl (repaired) the intermediate
#: certified with the envelope, then the layer target around it failed its re-inflation (23 s) before
#: the envelope certified in 5 s.
FOLLOW_PREVIOUS_SOURCE = True


def _target_edge(V: np.ndarray, F: np.ndarray, n_faces: int) -> float:
    """Edge of an equilateral mesh of ``n_faces`` triangles with the area of ``(V, F)``."""
    area = 0.5 * float(igl.doublearea(V, F).sum())
    return float(np.sqrt(4.0 * area / (np.sqrt(3.0) * max(int(n_faces), 1))))


#: The envelope target's grid spacing starts at its offset (marching cubes' error below the offset) and
#: is halved, down to a quarter of it, while the envelope, without the amplification, would have fewer
#: than this many times the target's faces. lucy.ply's first layer (25k faces from 100k) had an envelope
#: of 21k faces at spacing 0.01: refused as too coarse after its amplification had cost ~140 CPU s. The
#: amplification changed the face count by less than 2% on featuretype, cheburashka, homer and pepper.
ENVELOPE_FACE_MARGIN = 1.1


#: The envelope target finds the active points (its amplification, sdf paper Sec. 3.1) of a layer with
#: more faces on a decimated copy of this many faces (:func:`cagegen.envelope.coarse_active_points`): on
#: lucy.ply's 100k faces the search alone took ~140 CPU s. No zoo layer up to 20k faces changes.
ACTIVE_POINTS_MAX_FACES = 20_000


def _envelope_spacing(Vf, Ff, n_faces: int, offset: float) -> float:
    """Grid spacing of the envelope target: ``offset``, halved (twice at most) while the envelope without
    amplification (cheap: no active points) has at most :data:`ENVELOPE_FACE_MARGIN` ``n_faces`` faces.

    No probe when the envelope is surely fine enough: marching cubes gave 2.1-3.3 faces per ``h²`` of F's
    area (featuretype, cheburashka, homer, pepper, lucy at ``h = 0.01``), so ``2 area / h²`` is a bound.
    """
    h = offset
    area = 0.5 * float(igl.doublearea(Vf, Ff).sum())
    while h > offset / 4 * 1.01 and 2.0 * area / h ** 2 <= 2.0 * ENVELOPE_FACE_MARGIN * n_faces:
        probe = build_envelope(Vf, Ff, c=offset, h=h, band=4.0 * offset, amplify=False)
        if len(probe.F) > ENVELOPE_FACE_MARGIN * n_faces:
            break
        h /= 2
    return h


def _envelope_target(Vf, Ff, n_faces, offset):
    """Ĉ decimated from the envelope ``{d = offset}`` of the fine layer, not from the layer itself.

    QEM keeps a CAD part's flat faces in place and cuts into its sharp edges and holes, so the
    decimated layer leaves much of F outside (featuretype.stl, 1,722 vertices, decimated to 868
    faces: 678 outside) and the flow has to pull F in through Ĉ's narrowed tunnels, where it
    stalls whatever Ĉ's expansion does. Decimated from the offset envelope
    (:func:`cagegen.envelope.build_envelope`: marching cubes of the distance field at ``offset`` on a
    grid of that spacing, which may cut a sharp edge of F), Ĉ contains F except where the grid or
    QEM's error exceeds ``offset`` (featuretype.stl: 33 vertices, at most 0.0016 of the diagonal
    outside): a short flow. Only QEM, with
    intersection blocking when needed: shortest-edge collapses cut ~5% of the diagonal into such
    envelopes.
    """
    t = time.perf_counter()
    h = _envelope_spacing(Vf, Ff, n_faces, float(offset))
    env = build_envelope(Vf, Ff, c=float(offset), h=h, band=4.0 * float(offset),
                         active_max_faces=ACTIVE_POINTS_MAX_FACES)
    if len(env.F) <= n_faces:
        raise CageError(f"envelope at {offset:.3g} has {len(env.F)} faces, not more than the target")
    U, G, dinfo = decimate_surface(env.V, env.F, int(n_faces), decimator="qslim", other_decimator=False)
    return U, G, {"decimator": dinfo["decimator"], "block_intersections": dinfo["block_intersections"],
                  "n_faces": int(G.shape[0]), "offset": float(offset), "envelope_faces": len(env.F),
                  "seconds": time.perf_counter() - t}


def complete_clearance(C: np.ndarray, G: np.ndarray, Vf: np.ndarray, Ff: np.ndarray,
                       gap: float, looser: list = ()) -> tuple[np.ndarray, float, dict | None]:
    """The re-inflated cage, pushed out (:func:`push_out`) where it is closer than ``gap / GAP_AIM``,
    or else a tight one of its ``looser`` iterates that keeps that clearance.

    The re-inflation keeps the cage outside the fine surface's offset (:func:`offset_surface`), which
    is ``gap`` from it on face planes but not at spikes, where the offset factor is clamped, nor in
    sharp creases, where the offset crosses the surface: decimated-knight.off (0.00184 for 0.0025)
    and 42400-IDGH.stl (0.00096) fell short there. Used by nested's recovery and skeleton's clearance.

    Parameters
    ----------
    C : (n,3) float array
        Cage vertices (outside the fine surface).
    G : (m,3) int array
        Cage faces.
    Vf : (k,3) float array
    Ff : (l,3) int array
        The fine surface the cage must clear.
    gap : float
        Wanted clearance, in the units of ``C``.
    looser : list of (n,3) float arrays
        Earlier, looser cages on the way to ``C`` (the final phase's iterates, loosest first). When
        ``push_out`` is blocked, one at ``gap / GAP_AIM`` or more is taken, found by bisection: the
        last such one when the distance shrinks along the list (the final phase pulls the cage in),
        a measured one in any case.

    Returns
    -------
    C : (n,3) float array
        The cage, pushed out where needed (unchanged when already clear or when ``push_out`` is
        blocked and no looser iterate keeps the clearance).
    distance : float
        Its smallest distance to the fine surface.
    record : dict or None
        ``push_out``'s record (None: nothing to do).
    """
    d = min_distance(C, G, Vf, Ff)
    if d >= gap / GAP_AIM:
        return C, d, None
    C2, oinfo = push_out(C, G, Vf, Ff, gap, accept=gap / GAP_AIM, distance=d)
    if C2 is None:
        return _looser_clear(C, d, G, Vf, Ff, gap / GAP_AIM, looser, oinfo)
    return C2, oinfo["distance"], oinfo


def _looser_clear(C, d, G, Vf, Ff, accept, looser, oinfo) -> tuple[np.ndarray, float, dict]:
    """A ``looser`` cage keeping ``accept``, found by bisection (the last one when the distance shrinks along
    them), with its distance; ``(C, d)`` when the loosest does not keep it either."""
    if not looser:
        return C, d, oinfo
    d0 = min_distance(looser[0], G, Vf, Ff)
    if d0 < accept:
        return C, d, dict(oinfo, looser_tried=1)
    lo, hi, d_lo, tried = 0, len(looser), d0, 1  # looser[lo] keeps it; C (index len) does not
    while hi - lo > 1:
        mid = (lo + hi) // 2
        dm = min_distance(looser[mid], G, Vf, Ff)
        tried += 1
        if dm >= accept:
            lo, d_lo = mid, dm
        else:
            hi = mid
    return looser[lo], d_lo, dict(oinfo, looser_iterate=lo, looser_of=len(looser), looser_tried=tried)


#: Facing walls: the wall a ray along F's outward normal hits next faces back within this angle.
SLOT_FACING_DEGREES = 30.0


def narrow_slot_vertices(U: np.ndarray, Vf: np.ndarray, Ff: np.ndarray, width: float) -> np.ndarray:
    """Vertices of ``U`` outside F and between two facing walls of F closer than ``width``.

    A cage that keeps ``gap`` from F cannot have a point in an exterior slot of F narrower than
    ``2 gap`` (it would be closer than ``gap`` to one wall), and the re-inflation only pushes the cage
    along the walls' normals, never out through the slot's mouth. For each vertex p of ``U`` outside F
    (signed distance ``s > 0``), a ray from its closest point q along that face's outward normal hits F
    again at ``t < width`` on a wall facing back (normals within :data:`SLOT_FACING_DEGREES` of
    opposite: a concave crease, whose walls meet at an angle, is not a slot) and beyond p (``s < t``).
    Measured on the decimated first layers of 21 zoo meshes (quarter faces, ``width`` twice the
    clearance): cheburashka.obj 4 vertices between its legs (slot 0.0041-0.0055 of the diagonal, where
    the re-inflation stalled after 50 s), lucy.ply 20, every other mesh 0; 0.01-0.7 CPU s.

    Returns
    -------
    (k,) int array
        Indices into ``U``.
    """
    # the pseudonormal sign (exact on a closed manifold surface, F here; as the flow's) instead of the
    # winding number's: 0.04 against 0.25 CPU s for bumpy-cube.obj's first decimated layer
    S, I, Q = igl.signed_distance(np.asarray(U, dtype=float), Vf, Ff,
                                  sign_type=igl.SIGNED_DISTANCE_TYPE_PSEUDONORMAL)[:3]
    N = igl.per_face_normals(Vf, Ff, np.array([0.0, 0.0, 1.0]))
    cand = np.flatnonzero((S > 0) & (S < width))
    if not len(cand):
        return cand
    u = N[I[cand]]
    tree = igl.AABB()
    tree.init(Vf, Ff)
    hit_face, t, _ = tree.intersect_ray_first(Vf, Ff, Q[cand] + 1e-9 * u, u, float(width))
    hit = (hit_face >= 0) & (t < width)
    facing = np.zeros(len(cand), dtype=bool)
    facing[hit] = np.einsum("ij,ij->i", N[hit_face[hit]], u[hit]) < -np.cos(np.radians(SLOT_FACING_DEGREES))
    return cand[facing & (S[cand] < t)]


def _target_sources(Vf, Ff, n_faces: int, opts: dict, first: str) -> list:
    """``(source, decimator, envelope offset)`` of the targets Ĉ :func:`_build_layer` tries in turn.

    The envelope at ``target_offset``, then (default ``target_offset=None`` only) the envelope at
    :data:`TARGET_OFFSET_EDGE_FRACTION` of the target's edge when that is more than
    :data:`COARSE_ENVELOPE_FACTOR` times larger: it closes the holes a coarse target cannot follow. It comes
    second, not instead: on a plate with four 0.07-radius holes the 0.027 envelope of a 100-face layer left
    F 0.0007 outside where the 0.01 one certified (``tests/test_cad_part.py``).
    """
    first_alg = opts.get("decimator", "qslim")
    other_alg = "shortest_edge" if first_alg == "qslim" else "qslim"
    layer, env = [("layer", first_alg, None)], []
    if opts.get("target_offset"):
        env = [("envelope", first_alg, opts["target_offset"])]
        coarse = opts.get("target_offset_edge_fraction", 0.0) * _target_edge(Vf, Ff, n_faces)
        if coarse > COARSE_ENVELOPE_FACTOR * opts["target_offset"]:
            env.append(("envelope", first_alg, coarse))
    return (env + layer if first == "envelope" else layer + env) + [("layer", other_alg, None)]


class _Slotted(Exception):
    """A decimated layer target with vertices in slots of F narrower than twice the clearance."""

    def __init__(self, n_vertices: int):
        super().__init__(f"{n_vertices} vertex(es) in slots of F narrower than twice the clearance")
        self.n_vertices = n_vertices


def _slot_probe(Vf, Ff, gap: float, sources: list, i: int, deferred: set
                ) -> Callable[[np.ndarray, np.ndarray], None] | None:
    """The test :func:`_decimate` runs on every attempt at ``sources[i]``, a layer target: vertices in
    slots of F narrower than ``2 gap`` (:func:`narrow_slot_vertices`) raise :class:`_Slotted`, and the
    target goes behind the envelope targets (None: nothing to defer it behind, or deferred already).

    Its clearance step cannot pass there: cheburashka.obj's first layer flowed inside, then its
    re-inflation stalled in the last reverse step (50 s) before the envelope certified in 6 s. Moved
    once, when an envelope target follows; it is still tried, last. The test runs on each decimation
    attempt, not on the accepted one only: lucy.ply's first attempt (QEM) had 20 slot vertices and
    self-intersections; the third, accepted one (blocking QEM, after a self-intersecting shortest-edge
    attempt) had the same 20, after 8 s in all against 2.5 s to the first (ad hoc).
    """
    src = sources[i]
    if src[0] != "layer" or gap <= 0 or src in deferred or all(s[0] != "envelope" for s in sources[i + 1:]):
        return None

    def probe(U: np.ndarray, G: np.ndarray) -> None:
        n_slot = len(narrow_slot_vertices(U, Vf, Ff, 2.0 * gap))
        if n_slot:
            raise _Slotted(n_slot)

    return probe


def _build_layer(Vf, Ff, n_faces, opts, gap, rep, depth, max_depth, log, layer_no, first="layer"):
    """Cage with ~n_faces faces nesting (Vf, Ff), with recovery. Returns (C, G, info).

    Targets Ĉ tried in turn: the layer decimated by the first decimator (the paper's Ĉ: the tightest
    cages), the decimated offset envelope (:func:`_envelope_target`, unless ``target_offset`` is 0;
    it certified the CAD parts and scans on which the paper's flow stalls, but first on every input
    it gave looser cages and slower Neumann cycles: decimated-knight 0.49 against 0.24, homer 0.40
    against 0.33, corpus at c9049ce), then the layer by the other decimator. ``first="envelope"`` tries
    the envelope before the layer: the backend asks for it when the previous layer of the run certified
    only with the envelope (:data:`FOLLOW_PREVIOUS_SOURCE`).
    """
    sources = _target_sources(Vf, Ff, n_faces, opts, first)
    failures = []
    tried, deferred = set(), set()
    for i, (src, alg, offset) in enumerate(sources):  # may grow: a deferred target goes last
        t = time.perf_counter()
        what = src if offset is None else f"{src} at {offset:.3g}"
        try:
            if src == "envelope":
                U, G, dinfo = _envelope_target(Vf, Ff, n_faces, offset)
            else:
                U, G, dinfo = _decimate(Vf, Ff, n_faces, alg, _slot_probe(Vf, Ff, gap, sources, i, deferred))
        except _Slotted as exc:
            deferred.add(sources[i])
            sources.append(sources[i])
            failures.append({"action": f"decimate the {what} with {alg}", "stage": "slot",
                             "reason": f"{exc}: tried after the envelopes"})
            log.append({"layer": layer_no, **failures[-1]})
            continue
        except CageError as exc:
            failures.append({"action": f"decimate the {what} with {alg}", "stage": "decimate", "reason": str(exc)})
            log.append({"layer": layer_no, **failures[-1]})
            rep.say(f"layer {layer_no}: {failures[-1]['action']}: {exc}")
            continue
        key = (src, dinfo["decimator"], dinfo["block_intersections"], offset)
        if key in tried:  # the decimator fell back to a result already tried: same flow, skip it
            continue
        tried.add(key)
        t_dec = time.perf_counter() - t
        flow_opts = {k: opts[k] for k in _DEFAULTS}
        flow_opts["flow_plateau_window"] = FLOW_PLATEAU  # a flow going nowhere stops, last target too
        # another target follows: a flow that does not arrive soon stops
        if (src, alg, offset) != sources[-1]:
            quick = max(QUICK_FLOW_MIN_ITER, QUICK_FLOW_WORK // max(len(Ff), 1))
            flow_opts["flow_max_iter"] = min(flow_opts["flow_max_iter"], quick)
        try:
            C, pinfo, looser = nest_pair(Vf, Ff, U, G, gap=gap, reporter=rep, **flow_opts)
        except PairFailure as exc:
            failures.append({"action": f"decimate the {what} with {dinfo['decimator']} to {dinfo['n_faces']} faces",
                             "stage": exc.stage, "reason": exc.reason,
                             "seconds": time.perf_counter() - t,
                             "flow_iterations": exc.info.get("flow", {}).get("iterations")})
            log.append({"layer": layer_no, **failures[-1]})
            rep.say(f"layer {layer_no}: {failures[-1]['action']}: {exc.stage} failed")
            continue
        C, d, pinfo["clearance_completion"] = complete_clearance(C, G, Vf, Ff, gap, looser)
        if d < gap / GAP_AIM:
            failures.append({"action": f"decimate the {what} with {dinfo['decimator']} to {dinfo['n_faces']} faces",
                             "stage": "clearance", "reason": f"gap {d:.3g} < {gap / GAP_AIM:.3g}"})
            log.append({"layer": layer_no, **failures[-1]})
            rep.say(f"layer {layer_no}: {failures[-1]['action']}: clearance {d:.3g} too small")
            continue
        pinfo["decimation"] = dict(dinfo, source=src)
        pinfo["clearance_distance"] = d  # to (Vf, Ff), unit frame (:func:`_finish_layer`)
        pinfo["seconds"]["decimate"] = t_dec
        pinfo["failed_attempts"] = failures
        return C, G, pinfo
    if depth >= max_depth:
        raise CageError(
            f"layer {layer_no}: no nested cage with {n_faces} faces around a {len(Ff)}-face surface "
            f"after {len(failures)} attempts: " + "; ".join(f"{f['action']}: {f['stage']} {f['reason']}" for f in failures),
            layer=layer_no, reason=failures[-1]["reason"] if failures else "decimation failed")
    # recovery: insert an intermediate layer (geometric mean of the face counts), then retry
    mid = int(2 * round(np.sqrt(len(Ff) * n_faces) / 2))
    if mid <= n_faces or mid >= len(Ff):
        raise CageError(f"layer {layer_no}: no room for an intermediate layer between {len(Ff)} and {n_faces} faces",
                        layer=layer_no, reason="flow failed")
    log.append({"layer": layer_no, "action": f"insert intermediate layer of {mid} faces", "stage": "recovery",
                "reason": failures[-1]["reason"] if failures else ""})
    rep.say(f"layer {layer_no}: recovering with an intermediate layer of {mid} faces")
    Ci, Gi, iinfo = _build_layer(Vf, Ff, mid, opts, gap, rep, depth + 1, max_depth, log, layer_no, first)
    if FOLLOW_PREVIOUS_SOURCE and iinfo.get("decimation", {}).get("source") == "envelope":
        first = "envelope"  # as between layers: the intermediate cage is the next target's input
    C, G, pinfo = _build_layer(Ci, Gi, n_faces, opts, gap, rep, depth + 1, max_depth, log, layer_no, first)
    pinfo["intermediate"] = {"n_faces": len(Gi), "info": iinfo}
    pinfo["failed_attempts"] = failures + pinfo.get("failed_attempts", [])
    return C, G, pinfo


#: Default ``cage_time_budget`` of :func:`nested_backend`: estimated seconds above which it refuses, before
#: any work (as the sdf backend's ``cagegen.sdf.backend.DEFAULT_TIME_BUDGET``).
DEFAULT_TIME_BUDGET = 900.0

#: :func:`estimate_seconds`' model of one layer built around an ``n``-face surface:
#: ``LAYER_SECONDS + SECONDS_PER_FACE n (1 + (n / GROWTH_FACES)^2)``.
LAYER_SECONDS = 5.0
SECONDS_PER_FACE = 1.2e-3
GROWTH_FACES = 100_000


def estimate_seconds(n_faces: int, face_counts) -> float:
    """Seconds :func:`nested_backend` may take on one core of the 2-core dev machine for an ``n_faces``-face
    input and the cages' ``face_counts`` (each layer is built around the previous one).

    Per layer around an ``n``-face surface, ``5 + 1.2 ms n (1 + (n / 100k)^2)``: the re-inflation's contacts
    and Newton systems grow with the fine surface, and so does the count of Newton steps; a stalled target
    (20 Newton steps before the next one) costs most on the largest. An upper envelope of
    ``nestmg cages --levels 3`` on scans and subdivided zoo meshes (``benchmarks/results/corpus/
    nested_scale.json``, docs/cagegen.md): stanford-bunny 69k faces 52 s (estimated 156), lucy 100k 81 s
    (282), bunny.off subdivided to 111k 89 s (346), homer.obj subdivided to 192k 979 s (1161, a stalled first
    target), gargo.off subdivided to 342k 1395 s (5399); with the reverse steps' ``dhat`` rule (2c7e533,
    ``nested_scale_*_2c7e533.json``) 747 s and 527 s. CAD parts cost more per face at a few thousand faces (featuretype, 3.5k faces: 30 s,
    estimated 15), which it does not follow: it is a guard against starting an hour of work, not a
    prediction.
    """
    sizes = [int(n_faces)] + [int(m) for m in face_counts][:-1]
    return float(sum(LAYER_SECONDS + SECONDS_PER_FACE * n * (1.0 + (n / GROWTH_FACES) ** 2) for n in sizes))


def budget_check(n_faces: int, face_counts, *, cage_time_budget: float | None = DEFAULT_TIME_BUDGET,
                 **opts) -> float:
    """:func:`estimate_seconds` of a run, checked against ``cage_time_budget`` (None: no limit): raises
    :class:`CageError` (``reason="time budget"``) above it. The registry's ``budget`` check of ``"nested"``
    (:func:`cagegen.build_cages` calls it before the input audit); ``opts``: the backend's other options."""
    est = estimate_seconds(n_faces, face_counts)
    check_time_budget(est, cage_time_budget, f"nested cages {[int(c) for c in face_counts]} of a "
                                             f"{int(n_faces):,}-face input: estimated {est:.0f} s")
    return est


def nested_backend(
    V: np.ndarray,
    F: np.ndarray,
    face_counts,
    *,
    energy: str = "volume",
    quad_order: int = 2,
    min_gap: float = 0.0,
    min_gap_abs: float | None = None,
    decimate_from: str = "previous",
    decimator: str = "qslim",
    max_recovery_depth: int = 2,
    progress=False,
    certify: bool = True,
    fallback: str | None = "sdf",
    target_offset: float | None = None,
    cage_time_budget: float | None = DEFAULT_TIME_BUDGET,
    cage_threads: int | None = None,
    **opts,
) -> tuple[list[tuple[np.ndarray, np.ndarray]], dict]:
    """Cage backend ``"nested"``: strictly nested cages by flow and re-inflation (Sacht et al. 2015).

    Parameters
    ----------
    V : (n,3) float array
    F : (m,3) int array
        The closed input surface (layer 0; already audited by :func:`cagegen.build_cages`). Not
        modified.
    face_counts : sequence of int
        Target faces per cage, finest first.
    energy : str
        Cage energy minimised once the fine surface is back at rest: ``"volume"`` (tight, default),
        ``"step"`` (the pushed-out decimation), ``"surface_arap"`` (shape preserving),
        ``"volumetric_arap"`` (ARAP on a TetGen tessellation of Ĉ; between the two; loads TetGen,
        AGPL-3.0: a copyleft opt-in, recorded in ``info["copyleft"]``; needs the ``tetgen`` extra).
    quad_order : int
        Quadrature degree of the flow (paper: 2).
    min_gap : float
        Clearance to keep between consecutive layers, relative to the input's bounding-box diagonal
        (0: touching is avoided but any positive gap is accepted). For TetWild, whose boundary is
        only within ``epsilon`` (default 1e-3) of its input, use ``min_gap > epsilon``.
    min_gap_abs : float, optional
        The same clearance in absolute units (overrides ``min_gap``).
    decimate_from : {"previous", "input"}
        Decimate the previous layer (default) or the input for each target.
    decimator : {"qslim", "shortest_edge"}
        Decimator tried first (the other one is the first recovery).
    max_recovery_depth : int
        How many intermediate layers may be nested into each other when recovering.
    progress : bool or callable
        ``True``: rich progress bars per layer and phase; a callable gets one-line messages;
        ``False``: silent.
    certify : bool
        Verify every pair with :func:`cagegen.verify_nesting` (the layer is recomputed through the
        recovery path, or :class:`CageError` is raised, when it fails).
    fallback : str or None
        Last resort, by name (:data:`cagegen.fallbacks.FALLBACKS`), when the flow fails and intermediate
        layers do not
        help either; the layer it builds is certified like every other, recorded in ``info["recovery"]``
        and in the layer's ``fallback`` entry (``Hierarchy.fallbacks`` reports it). ``"sdf"`` (default):
        :func:`cagegen.sdf.sdf_cage_layer` around the previous layer (tight, exact face count, MIT;
        certified on every closed dev-zoo mesh, docs/sdf.md; 6-48 CPU s on coarse spiky inputs, ~10 s
        at 7k faces). ``"lazy"``: :func:`cagegen.copyleft.lazy.lazy_cage_layer` (loose but fast; loads
        GPL code, opt-in by name only, needs the ``lazy`` extra). None: raise :class:`CageError`.
        Nothing copyleft is loaded unless ``"lazy"`` is named.
    target_offset : float, optional
        Offset, relative to the input's bounding-box diagonal, of the envelope the second target Ĉ
        is decimated from (:func:`_envelope_target`), tried when the flow into the paper's Ĉ (the
        decimated layer) fails. None (default): :data:`TARGET_OFFSET_GAPS` times ``min_gap``, at least
        :data:`MIN_TARGET_OFFSET`, then, if that fails, :data:`TARGET_OFFSET_EDGE_FRACTION` of the target's
        edge length (a coarse layer closes the holes it cannot follow). 0: only the paper's Ĉ.
    cage_time_budget : float or None
        Refuse at once (:class:`CageError`, ``reason="time budget"``) when :func:`estimate_seconds` exceeds
        this many seconds (default :data:`DEFAULT_TIME_BUDGET`; None: no limit).
    cage_threads : int, optional
        ipctk's threads while the cages are built (:func:`cagegen.collision.ipctk_threads`): 1 gives the
        same cages, byte for byte, every run; None (default) leaves ipctk's (all cores), whose parallel
        sums make a run's cages differ from another's beyond round-off on some inputs.
    **opts
        Advanced: ``flow_step``, ``flow_max_iter``, ``dhat``, ``kappa``, ``dhat_final``,
        ``kappa_final``, ``max_move``, ``final_iters`` (see :func:`nest_pair`).

    Returns
    -------
    layers : list of (V_k, F_k)
        The cages only, finest first; ``V_k`` (n_k,3) float64, ``F_k`` (m_k,3) int64.
    info : dict
        JSON-serialisable: ``options``, per layer ``target``, ``n_faces``, ``decimation``, ``flow``,
        ``reinflate``, ``seconds`` per phase, ``min_gap`` achieved (relative and absolute),
        ``volume_ratio``, ``verification``, ``recovery`` (list of actions); ``seconds`` in total.

    Raises
    ------
    CageError
        A layer could not be built or certified (``.layer`` is its index, 1 = first cage).
    ValueError
        Unknown option or energy.
    """
    t_all = time.perf_counter()
    _check_options(energy, decimate_from, opts, fallback)
    budget_check(len(F), face_counts, cage_time_budget=cage_time_budget)
    V = np.array(V, dtype=np.float64)  # private copies
    F = np.array(F, dtype=np.int64)
    face_counts = [int(c) for c in face_counts]
    params = {**_DEFAULTS, **opts, "energy": energy, "quad_order": int(quad_order), "decimator": decimator}

    # work at unit bounding-box diagonal (the paper's relative step sizes)
    lo, hi = V.min(0), V.max(0)
    diag = float(np.linalg.norm(hi - lo))  # this backend's own measure (its cages depend on its bits)
    Vn, center, _ = normalize(V, diag)
    gap_abs = float(min_gap_abs) if min_gap_abs is not None else float(min_gap) * diag
    gap_n = gap_abs / diag
    # aim a little beyond the requested clearance (the offset is measured on face planes)
    gap_target = GAP_AIM * gap_n if gap_n > 0 else 0.0
    params["target_offset_edge_fraction"] = TARGET_OFFSET_EDGE_FRACTION if target_offset is None else 0.0
    if target_offset is None:
        target_offset = max(TARGET_OFFSET_GAPS * gap_n, MIN_TARGET_OFFSET)
    if not target_offset >= 0:
        raise CageOptionError(f"target_offset must be >= 0, got {target_offset!r}")
    params["target_offset"] = float(target_offset)
    info: dict = {
        "method": "nested",
        "options": {k: (v if isinstance(v, (int, float, str)) else str(v)) for k, v in params.items()},
        "min_gap_requested": {"relative": gap_n, "absolute": gap_abs},
        "decimate_from": decimate_from,
        "fallback": fallback,
        "copyleft": [COPYLEFT_ENERGIES[energy][1]] if energy in COPYLEFT_ENERGIES else [],
        "layers": [],
        "recovery": [],
    }
    run = _Run(V, F, Vn, diag, center, params, gap_target, gap_abs, decimate_from, int(max_recovery_depth),
               fallback, certify, {"first": "layer"})
    layers = []
    prev_n, prev_F = Vn, F
    prev_orig = (V, F)
    # one BLAS thread: the backend's BLAS work is dot products of Newton-CG vectors (~20k entries), too
    # short to share, and OpenBLAS's spinning threads beside ipctk's TBB pool cost homer.obj's cages
    # 1.1x wall on an idle machine and up to 30x per CG solve on a loaded one (2 cores; ad hoc)
    with _Reporter(progress) as rep, threadpool_limits(limits=1, user_api="blas"), ipctk_threads(cage_threads):
        rep.layers(len(face_counts))
        for k, m in enumerate(face_counts, start=1):
            t_layer = time.perf_counter()
            rep.say(f"layer {k}: target {m} faces")
            log: list = []
            C, G, linfo = _cage_layer(run, k, m, prev_n, prev_F, rep, log)
            Vk, Gk = _finish_layer(run, k, m, C, G, linfo, log, prev_orig)
            linfo["seconds"]["total"] = time.perf_counter() - t_layer
            info["layers"].append(_jsonable(linfo))
            info["recovery"].extend(log)
            layers.append((Vk, Gk))
            if FOLLOW_PREVIOUS_SOURCE and linfo.get("decimation", {}).get("source") == "envelope":
                run.state["first"] = "envelope"
            prev_n, prev_F = C, Gk
            prev_orig = (Vk, Gk)
            rep.layer_done()
    info["seconds"] = time.perf_counter() - t_all
    return layers, info


def _check_options(energy: str, decimate_from: str, opts: dict, fallback: str | None) -> None:
    """One-line :class:`CageOptionError` for an unknown energy, source, option or fallback."""
    if energy not in ENERGIES:
        raise CageOptionError(f"unknown energy {energy!r}; choose one of {sorted(ENERGIES)}")
    if decimate_from not in ("previous", "input"):
        raise CageOptionError(f"decimate_from must be 'previous' or 'input', got {decimate_from!r}")
    unknown = set(opts) - set(_DEFAULTS)
    if unknown:
        raise CageOptionError(f"unknown option(s) for the nested backend: {sorted(unknown)}")
    if fallback is not None and fallback not in FALLBACKS:
        raise CageOptionError(f"unknown fallback {fallback!r}; choose one of {sorted(FALLBACKS)} or None")
    check_energy_available(energy)  # a copyleft energy's package, before the flow runs


class _Run(NamedTuple):
    """What every layer of one :func:`nested_backend` run shares (``Vn``: the input at unit diagonal)."""

    V: np.ndarray
    F: np.ndarray
    Vn: np.ndarray
    diag: float
    center: np.ndarray
    params: dict
    gap_target: float
    gap_abs: float
    decimate_from: str
    max_depth: int
    fallback: str | None
    certify: bool
    state: dict  # "first": the target source the next layer tries first (:data:`FOLLOW_PREVIOUS_SOURCE`)


def _cage_layer(run: _Run, k: int, m: int, prev_n, prev_F, rep, log: list) -> tuple:
    """Layer ``k`` (``m`` faces) around the previous one, at unit diagonal: recovery, then the fallback."""
    src_V, src_F = (prev_n, prev_F) if run.decimate_from == "previous" else (run.Vn, run.F)
    try:
        if run.decimate_from == "input" and k > 1:
            # the target is a decimation of the input, but it must nest the previous layer
            return _layer_from_target(prev_n, prev_F, run.Vn, run.F, m, run.params, run.gap_target, rep, log,
                                      k)
        return _build_layer(src_V, src_F, m, run.params, run.gap_target, rep, 0, run.max_depth, log, k,
                            run.state["first"])
    except CageError as exc:
        return _fallback(prev_n, prev_F, m, exc, run.fallback, rep, log, k, run.gap_target)


def _finish_layer(run: _Run, k: int, m: int, C, G, linfo: dict, log: list, prev_orig) -> tuple:
    """Layer ``k`` in the caller's coordinates, certified against the previous one; figures in ``linfo``."""
    Vk = C * run.diag + run.center
    Gk = np.ascontiguousarray(G, dtype=np.int64)
    t = time.perf_counter()
    if run.certify:
        report = verify_nesting([prev_orig, (Vk, Gk)], min_gap=run.gap_abs / _diag(prev_orig[0]))
        linfo["verification"] = report.to_dict()
        if not report.ok:
            raise CageError(f"layer {k} failed certification: {report.pairs[0].reason}",
                            layer=k, reason=str(report.pairs[0].reason))
    linfo.setdefault("seconds", {})["verify"] = time.perf_counter() - t
    gap_k = _layer_gap(run, Vk, Gk, linfo, prev_orig)
    linfo.update({
        "layer": k,
        "target": m,
        "n_faces": len(Gk),
        "n_vertices": len(Vk),
        "min_gap_absolute": gap_k,
        "min_gap_relative": gap_k / run.diag,
        "volume_ratio": signed_volume(Vk, Gk) / signed_volume(*prev_orig),
        "volume_ratio_to_input": signed_volume(Vk, Gk) / signed_volume(run.V, run.F),
        "hausdorff_relative": float(igl.hausdorff(Vk, Gk, run.V, run.F)) / run.diag,
        "recovery": log,
    })
    return Vk, Gk


def _layer_gap(run: _Run, Vk, Gk, linfo: dict, prev_orig) -> float:
    """Distance of layer ``k`` to the previous layer in the caller's units: the one
    :func:`complete_clearance` measured at unit diagonal, scaled, when it was measured against the previous
    layer itself (no intermediate layer, not a fallback), else :func:`min_distance` again (0.2-0.3 CPU s
    on a 10k-face layer)."""
    d = linfo.pop("clearance_distance", None)
    if d is not None and "intermediate" not in linfo and run.decimate_from == "previous":
        return float(d) * run.diag
    return min_distance(Vk, Gk, *prev_orig)


def _layer_from_target(Vf, Ff, Vsrc, Fsrc, m, params, gap, rep, log, k):
    """``decimate_from="input"``: decimate the input, nest it around the previous layer."""
    U, G, dinfo = _decimate(Vsrc, Fsrc, m, params.get("decimator", "qslim"))
    try:
        C, pinfo, _ = nest_pair(Vf, Ff, U, G, gap=gap, reporter=rep, **{kk: params[kk] for kk in _DEFAULTS})
    except PairFailure as exc:
        log.append({"layer": k, "action": "decimation of the input failed; decimating the previous layer",
                    "stage": exc.stage, "reason": exc.reason})
        return _build_layer(Vf, Ff, m, params, gap, rep, 0, 2, log, k)
    pinfo["decimation"] = dinfo
    return C, G, pinfo


def _fallback(Vf, Ff, m, exc, fallback, rep, log, k, gap):
    """Last resort for layer ``k`` once the flow and the intermediate layers failed (None: raise).

    The fallback keeps the layer's clearance ``gap`` (absolute, unit-diagonal frame) like the flow
    does: a cage closer than that would only be refused by the certification after it.
    """
    if fallback is None:
        raise exc
    return FALLBACKS[fallback](Vf, Ff, m, exc, rep, log, k, gap)


def _diag(V: np.ndarray) -> float:
    return float(np.linalg.norm(V.max(0) - V.min(0)))


def _jsonable(obj):
    """Recursively convert numpy scalars/arrays to plain Python for JSON."""
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.floating,)):
        return float(obj)
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (np.bool_,)):
        return bool(obj)
    return obj
