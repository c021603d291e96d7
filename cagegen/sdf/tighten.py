"""Tightening pass of the ``sdf`` backend (not in the paper): a cage vertex in each bridged concavity.

The envelope is an offset at distance ``c``: over a concavity narrower than ``~2c`` (a pit, a slit,
an undercut) it is a bridge whose crease sits ``c / sin(theta / 2)`` above the bottom of a wedge of
opening ``theta`` (2.9 ``c`` for 40 degrees), and the simplified cage inherits the bridge. The
optimisation's input-to-cage pull (:func:`cagegen.sdf.optimize.optimize_cage`, ``w_p``) moves the
closest cage *face* toward such a point, but a face spanning the concavity cannot enter it: the cage
lacks a vertex there.

One round of :func:`tighten_cage`:

1. the input vertices farther than ``trigger`` from the cage, greedily thinned so that picks are at
   least ``separation`` apart, each split its closest cage face at the closest point (a 1-to-3 split:
   the surface is unchanged, so the cage stays certified);
2. the optimisation with the pull and a small barrier (``dhat``) lowers those new vertices into the
   concavities (the barrier and the CCD line search still forbid any intersection);
3. the constrained simplification (:func:`cagegen.sdf.simplify.constrained_simplify`, every test of the
   backend) collapses the same number of faces elsewhere, the inserted vertices *frozen*, so the face
   count is exactly the requested one again; a second optimisation smooths the result;
4. the round is kept only if :func:`cagegen.verify_nesting` certifies it and the largest input-to-cage
   distance went down; the pass stops at ``target`` or after ``rounds``.
"""

from __future__ import annotations

import time
from typing import NamedTuple

import numpy as np

from ..verify import verify_nesting
from .optimize import _barycentric, _Energy, _flip_pass, _min_angles, optimize_cage
from .simplify import SimplifyStuck, constrained_simplify

__all__ = ["input_to_cage", "split_far_faces", "tighten_cage"]


def input_to_cage(Vin: np.ndarray, Fin: np.ndarray, C: np.ndarray, Fc: np.ndarray):
    """Distance of every input vertex to the cage, the closest cage face and the closest point."""
    import igl

    d2, fi, Q = igl.point_mesh_squared_distance(np.asarray(Vin, float), np.asarray(C, float),
                                                np.asarray(Fc, np.int64))
    return np.sqrt(np.maximum(d2, 0.0)), np.asarray(fi, np.int64), np.asarray(Q, float)


def split_far_faces(C: np.ndarray, Fc: np.ndarray, Vin: np.ndarray, Fin: np.ndarray, trigger: float,
                    separation: float, min_bary: float = 0.15,
                    max_insert: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Insert a cage vertex above each input vertex farther than ``trigger`` from the cage.

    Input vertices are taken farthest first, skipping those within ``separation`` of one already
    taken; each splits its closest cage face (1 -> 3, at most once per face) at the closest point,
    its barycentric coordinates clamped to ``>= min_bary`` (no sliver triangles), at most ``max_insert``
    of them (the farthest). The cage's surface is unchanged.

    Returns
    -------
    C2, F2 : arrays
        The refined cage (``2 k`` more faces, ``k`` more vertices, appended at the end).
    picked : (k,) int array
        The input vertices the new vertices were inserted for.
    """
    d, fi, Q = input_to_cage(Vin, Fin, C, Fc)
    order = np.argsort(-d, kind="stable")
    order = order[d[order] > trigger]
    taken: list[int] = []
    faces_used: set[int] = set()
    new_pts, new_faces, picked = [], [], []
    F2 = np.array(Fc, dtype=np.int64)
    nv = len(C)
    sep2 = float(separation) ** 2
    for i in order.tolist():
        if taken and np.min(np.sum((Vin[taken] - Vin[i]) ** 2, axis=1)) < sep2:
            continue
        taken.append(i)
        f = int(fi[i])
        if f in faces_used:
            continue
        faces_used.add(f)
        a, b, c = F2[f]
        L = _barycentric(Q[i:i + 1], C[[a]], C[[b]], C[[c]])[0]
        L = np.maximum(L, min_bary)
        L /= L.sum()
        new_pts.append(L @ C[[a, b, c]])
        F2[f] = [a, b, nv]
        new_faces += [[b, c, nv], [c, a, nv]]
        picked.append(i)
        nv += 1
        if max_insert is not None and len(picked) >= max_insert:
            break
    if not new_pts:
        return np.array(C, float), F2, np.zeros(0, np.int64)
    return (np.vstack([C, np.asarray(new_pts)]), np.vstack([F2, np.asarray(new_faces, np.int64)]),
            np.asarray(picked, np.int64))


def tighten_cage(
    C: np.ndarray,
    Fc: np.ndarray,
    Vin: np.ndarray,
    Fin: np.ndarray,
    sdf,
    *,
    c: float,
    target: float,
    trigger: float | None = None,
    separation: float | None = None,
    rounds: int = 3,
    dhat: float | None = None,
    pull: float = 50.0,
    spacing: float | None = None,
    margin: float | None = None,
    min_gap: float = 0.0,
    gap_rel: float = 0.0,
    iters: int = 15,
    time_limit: float = 30.0,
    radius: float | None = None,
    step: float | None = None,
    second_full: bool = True,
    max_insert: int | None = None,
    min_angle: float = 2.0,
    deadline: float | None = None,
) -> tuple[np.ndarray, np.ndarray, dict, object]:
    """Lower the cage into the concavities it bridges, at the same face count (see the module docstring).

    Parameters
    ----------
    C, Fc : arrays
        A certified cage of ``(Vin, Fin)`` (unit-diagonal coordinates of the backend).
    sdf : cagegen.envelope.SDFGrid
        Signed distance of the input (the envelope's grid: guides the simplification's placements).
    c : float
        The layer's offset ``c``.
    target : float
        Stop once every input vertex is within ``target`` of the cage.
    trigger : float, optional
        Input vertices farther than this get a new cage vertex (default ``0.8 target``).
    separation : float, optional
        Smallest distance between two inserted vertices' input vertices (default ``1.5 c``; ``2 c`` left
        input vertices next to a pick far, so gargo's first cage needed a second round: 1.48% in 7.9 s
        against one round, 1.48% in 4.5 s, ``zoo_sdf_7a84149.json`` / ``zoo_sdf_sep15_*.json``).
    rounds : int
        Rounds at most.
    dhat : float, optional
        Barrier activation distance of the optimisations (default ``0.05 c``: with the backend's
        ``0.25 c`` the barrier holds a vertex at the mouth of a pit narrower than ``0.5 c``).
    pull, spacing, margin : float
        Input-to-cage pull weight, spacing target (default ``0.5 c``) and the simplification's sampled
        clearance (default ``max(0.3 c, 2 min_gap)``), as in :func:`cagegen.sdf.backend.sdf_cage_layer`.
    min_gap, gap_rel : float
        Absolute clearance the cage keeps from the input, and the same relative to layer 0's diagonal
        (what :func:`cagegen.verify_nesting` is given).
    iters, time_limit : int, float
        Descent steps per optimisation round, CPU seconds per optimisation.
    radius : float, optional
        Only the cage vertices within ``radius`` of an inserted vertex (or of a vertex the collapses
        moved) are optimised (default ``6 c``); the cage and input within ``radius + 4 c`` are the
        obstacles of the CCD. The result is certified on the whole cage.
    max_insert : int, optional
        Inserted vertices per round at most, the farthest first (default ``n_faces // 32``: every
        inserted vertex is frozen during the collapses, and too many leave none feasible).
    min_angle : float
        A round is kept only if the cage's smallest angle (degrees) stays at least
        ``min(min_angle, its value before the round)`` (a vertex pulled deep into a narrow pit can
        make needles: gargo_1000 reached 0.0 degrees, MIPS max 1,694).
    deadline : float, optional
        ``time.perf_counter()`` value after which no round is started: a round starts only if the
        previous round's wall time still fits before it (``info["stopped"] = "time budget"`` otherwise).
    second_full : bool
        The optimisation after the collapses also flips and descends twice (as the first; measured to
        matter on a slit).
    step : float, optional
        Largest vertex move per descent step (default ``2 dhat``, the optimiser's; 0.25 ``c`` was
        measured worse on the two dev-zoo slits/pits it was tried on).

    Returns
    -------
    C, Fc : arrays
        The tightest certified cage found (the input cage if no round helped); same face count.
    info : dict
        ``rounds`` (per round: inserted vertices, max distance after, smallest angle, certified,
        kept, CPU seconds), ``max_before``, ``max_after``, ``min_angle_floor``.
    report : cagegen.verify.NestingReport or None
        The :func:`cagegen.verify_nesting` report of the returned cage when a round was kept (it
        certifies it; the caller need not verify again), None when the input cage is returned.
    """
    C = np.asarray(C, float)
    Fc = np.asarray(Fc, np.int64)
    n_faces = len(Fc)
    trigger = 0.8 * target if trigger is None else float(trigger)
    separation = 1.5 * c if separation is None else float(separation)
    dhat = 0.05 * c if dhat is None else float(dhat)
    dhat = max(dhat, 2.0 * min_gap)
    spacing = 0.5 * c if spacing is None else float(spacing)
    margin = max(0.3 * c, 2.0 * min_gap) if margin is None else float(margin)
    radius = 6.0 * c if radius is None else float(radius)
    # frozen vertices cannot be collapsed: many of them on a coarse cage leave no feasible collapse
    # (measured: 52 on a 124-face cage, 120 on 334 faces)
    max_insert = max(1, n_faces // 32) if max_insert is None else int(max_insert)
    step = 2.0 * dhat if step is None else float(step)
    ps = _PatchSettings(Vin, Fin, c, radius, 4.0 * c, spacing, dhat, step, pull, iters, time_limit, min_gap)
    best = float(input_to_cage(Vin, Fin, C, Fc)[0].max())
    angle_floor = min(float(min_angle), float(_min_angles(C, Fc).min()))
    info: dict = {"max_before": best, "rounds": [], "min_angle_floor": angle_floor}
    report = None
    frozen_pts = np.zeros((0, 3))
    last = 0.0
    for _ in range(int(rounds)):
        if best <= target:
            break
        if deadline is not None and time.perf_counter() + last > deadline:
            info["stopped"] = "time budget"
            break
        tw = time.perf_counter()
        t = time.process_time()
        rec: dict = {}
        C2, F2, picked = split_far_faces(C, Fc, Vin, Fin, trigger, separation, max_insert=max_insert)
        rec["inserted"] = len(picked)
        if len(picked) == 0:
            info["rounds"].append(rec)
            break
        d5, out = _tighten_round(C, C2, F2, frozen_pts, ps, sdf, n_faces, margin, gap_rel, second_full, rec)
        rec["kept"] = bool(rec.get("certified") and d5 < best and len(out[1]) == n_faces
                           and rec["min_angle"] >= angle_floor)
        rec["cpu_seconds"] = time.process_time() - t
        last = time.perf_counter() - tw
        info["rounds"].append(rec)
        if not rec["kept"]:
            break
        C5, F5, rep, idx4 = out
        C, Fc, best, report = C5, F5, d5, rep
        frozen_pts = C5[idx4]
    info["max_after"] = best
    return C, Fc, info, report


class _PatchSettings(NamedTuple):
    """The input and the resolved options of :func:`tighten_cage`'s local optimisations."""

    Vin: np.ndarray
    Fin: np.ndarray
    c: float
    radius: float
    reach: float  # obstacles within radius + reach of the centres
    spacing: float
    dhat: float
    step: float
    pull: float
    iters: int
    time_limit: float
    min_gap: float


def _tighten_round(C, C2, F2, frozen_pts, ps: _PatchSettings, sdf, n_faces, margin, gap_rel, second_full,
                   rec):
    """One round after the splits: lower the new vertices, collapse as many faces elsewhere, certify."""
    from scipy.spatial import cKDTree

    Vin, Fin, min_gap = ps.Vin, ps.Fin, ps.min_gap
    out = None
    try:
        C3, F3 = _optimize_patch(C2, F2, C2[len(C):], ps)
        # freeze this round's new vertices and the earlier rounds' (found by position: the
        # simplification compacts the vertex array; frozen vertices never move in it)
        pts = np.vstack([frozen_pts, C3[len(C):]])
        fr = np.zeros(len(C3), dtype=bool)
        fr[cKDTree(C3).query(pts)[1]] = True
        C4, F4, sinfo = constrained_simplify(C3, F3, Vin, Fin, n_faces, sdf, margin=margin,
                                             edge_clear=float(min_gap), frozen=fr)
        idx4 = cKDTree(C4).query(pts)[1]  # same vertex order in C5 (the optimiser keeps it)
        # second pass around the inserted vertices and where the collapses moved vertices
        moved = cKDTree(C3).query(C4)[0] > 1e-12
        C5, F5 = _optimize_patch(C4, F4, np.vstack([C4[idx4], C4[moved]]), ps, full=second_full)
        rep = verify_nesting([(Vin, Fin), (C5, F5)], min_gap=gap_rel)
        rec["certified"] = bool(rep.ok)
        d5 = float(input_to_cage(Vin, Fin, C5, F5)[0].max())
        rec["max_after"] = d5
        rec["collapses"] = int(sinfo["collapses"])
        out = (C5, F5, rep, idx4)
    except (SimplifyStuck, RuntimeError) as exc:  # stuck collapses, or a start cage the optimiser refuses
        rec["certified"] = False
        rec["error"] = str(exc)
        d5 = np.inf
    if rec.get("certified"):
        rec["min_angle"] = float(_min_angles(C5, F5).min())
    return d5, out


def _optimize_patch(X, T, centers, ps: _PatchSettings, full=True):
    """Descent on the patch, edge flips on the whole cage, descent on the patch again (``full``)."""
    # energy-lowering edge flips, exactly checked: the backend's 15 + flips + 15 steps; the 1-to-3
    # splits need the flips to get neighbours along the concavity
    X = _patch_descent(X, T, centers, ps)
    if not full:
        return X, T
    T, _ = _flip_pass(X, T, ps.Vin, ps.Fin, max_flips=len(T), clear=1.05 * float(ps.min_gap),
                      tri_energy=_Energy(T, ps.Vin, ps.Fin, ps.spacing, 1.0, 0.05,
                                         max(ps.spacing, ps.dhat)).triangles(X))
    return _patch_descent(X, T, centers, ps), T


def _patch_descent(X, T, centers, ps: _PatchSettings):
    """The descent on the cage within ``radius`` of ``centers`` (the rest held, an obstacle nearby)."""
    # the rest of the cage is held, and kept as an obstacle within radius + reach; no flips (they
    # would change the patch's border)
    from scipy.spatial import cKDTree

    Vin, Fin, radius, reach = ps.Vin, ps.Fin, ps.radius, ps.reach
    X = np.array(X, dtype=float)
    tree = cKDTree(X)
    near = np.zeros(len(X), dtype=bool)
    for lst in tree.query_ball_point(centers, radius + reach):
        near[lst] = True
    movable = np.zeros(len(X), dtype=bool)
    for lst in tree.query_ball_point(centers, radius):
        movable[lst] = True
    fsub = np.flatnonzero(near[T].any(axis=1))
    vsub = np.unique(T[fsub])
    loc = np.full(len(X), -1, dtype=np.int64)
    loc[vsub] = np.arange(len(vsub))
    # a patch vertex moves if it is within radius and none of its faces leaves the patch
    border = np.zeros(len(X), dtype=bool)
    border[T[~near[T].any(axis=1)].ravel()] = True  # vertices of faces outside the patch
    free = movable[vsub] & ~border[vsub]
    lo_, hi_ = X[vsub].min(0) - reach, X[vsub].max(0) + reach
    fin = np.flatnonzero(((Vin[Fin].min(axis=1) <= hi_) & (Vin[Fin].max(axis=1) >= lo_)).all(axis=1))
    vin_sub = np.unique(Fin[fin])
    lin = np.full(len(Vin), -1, dtype=np.int64)
    lin[vin_sub] = np.arange(len(vin_sub))
    pm = np.zeros(len(vin_sub), dtype=bool)  # pulling input vertices: within radius of a centre
    for lst in cKDTree(Vin[vin_sub]).query_ball_point(centers, radius):
        pm[lst] = True
    Xs, _, _ = optimize_cage(X[vsub], loc[T[fsub]], Vin[vin_sub], lin[Fin[fin]], h=ps.spacing, dhat=ps.dhat,
                             iters=ps.iters, flip_rounds=0, time_limit=ps.time_limit, w_p=ps.pull,
                             pull_target=ps.c, step=ps.step, min_distance=1.05 * float(ps.min_gap), free=free,
                             pull_mask=pm)
    X[vsub] = Xs
    return X
