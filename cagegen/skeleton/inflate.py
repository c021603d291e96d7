"""Pre-inflation of the tight cage along the integral lines of the guiding field (Casti et al. Sec. 3.5).

Samples of every cage face that lie inside M are projected onto M along the integral lines of f; a
face's displacement is the longest sample-to-projection vector. A vertex moves along the normalised
mean of its incident face displacements, by the largest projection of those displacements on that
direction (paper Fig. 9). Where the moved cage intersects itself, the vertices of the offending faces
step back towards their previous positions by a fraction of their displacement until no intersection
is left. The final inflation (Nested Cages' flow + re-inflation, :func:`cagegen.nested.backend.nest_pair`)
then makes the cage strictly contain M.
"""

from __future__ import annotations

import igl
import numpy as np

from .._geometry import self_intersection_pairs
from .field import GuidingField

__all__ = ["crease_push", "polish", "pre_inflate", "unfold"]

# barycentric sample pattern per triangle (vertices excluded: they are on M already)
_B = np.array([[1, 1, 1], [4, 1, 1], [1, 4, 1], [1, 1, 4], [2, 2, 1], [2, 1, 2], [1, 2, 2],
               [6, 1, 1], [1, 6, 1], [1, 1, 6], [3, 3, 1], [3, 1, 3], [1, 3, 3]], dtype=float)
_B /= _B.sum(axis=1, keepdims=True)


def _face_displacements(field: GuidingField, V: np.ndarray, F: np.ndarray, Vm: np.ndarray, Fm: np.ndarray):
    P = np.einsum("sk,fkd->fsd", _B, V[F]).reshape(-1, 3)
    fid = np.repeat(np.arange(len(F)), len(_B))
    w = igl.fast_winding_number(Vm, Fm, P) if hasattr(igl, "fast_winding_number") else igl.winding_number(Vm, Fm, P)
    inside = np.asarray(w) > 0.5
    disp = np.zeros((len(F), 3))
    if not inside.any():
        return disp, 0
    end, ok = field.trace(P[inside])
    d = np.where(ok[:, None], end - P[inside], 0.0)
    L = np.linalg.norm(d, axis=1)
    f_in = fid[inside]
    best = np.full(len(F), -1.0)
    np.maximum.at(best, f_in, L)
    pick = (L == best[f_in]) & (L > 0)
    disp[f_in[pick]] = d[pick]
    return disp, int(inside.sum())


def _vertex_displacements(V: np.ndarray, F: np.ndarray, disp: np.ndarray) -> np.ndarray:
    n = len(V)
    acc = np.zeros((n, 3))
    for k in range(3):
        np.add.at(acc, F[:, k], disp)
    nrm = np.linalg.norm(acc, axis=1)
    dirn = np.where(nrm[:, None] > 0, acc / np.maximum(nrm, 1e-300)[:, None], 0.0)
    mag = np.zeros(n)
    for k in range(3):
        np.maximum.at(mag, F[:, k], np.einsum("ij,ij->i", disp, dirn[F[:, k]]))
    return dirn * mag[:, None]


def pre_inflate(field: GuidingField, V: np.ndarray, F: np.ndarray, Vm: np.ndarray, Fm: np.ndarray,
                rounds: int = 3, margin: float = 0.05, backoff: float = 0.1,
                max_backoff: int = 40, contain_rounds: int = 12,
                clearance: float = 2e-3, crease_rounds: int = 20, polish_rounds: int = 12,
                fin_cos: float = -0.9) -> tuple[np.ndarray, dict]:
    """Pull the tight cage ``(V, F)`` out to the surface ``(Vm, Fm)`` along the integral lines of f.

    Parameters
    ----------
    field : GuidingField
    V : (n,3) float array
    F : (m,3) int array
        Cage (outward triangles).
    Vm : (k,3) float array
    Fm : (l,3) int array
        The surface M.
    rounds : int
        Repetitions of the paper's single pre-inflation step (each re-samples the moved cage).
    margin : float
        Each vertex displacement is lengthened by this fraction (the paper's step reaches M exactly).
    backoff : float
        Fraction of its displacement by which a vertex of a self-intersecting face steps back.
    max_backoff : int
        Step-back iterations per round.
    contain_rounds : int
        Rounds of the containment push that follows (0: the paper's pre-inflation only).
    clearance : float
        Distance (units of V) by which the containment push passes the vertices of M.
    crease_rounds : int
        Rounds of the crease push (:func:`crease_push`) when vertices of M are still outside after the
        containment push (0: none).
    polish_rounds : int
        When vertices of M are still outside after the crease push: rounds of a second containment
        push that also steps back where it would fold a face onto a neighbour (normal cosine below
        ``fin_cos``), then up to 2 rounds moving the cage vertices inside M (or within ``clearance`` of
        it) to ``2 * clearance`` outside M, each followed by that push (0: none; issue 18: the crease
        push's best round left 495-1,257 vertices of M outside on the zoo; this polish leaves 68-428).
    fin_cos : float
        Normal cosine under which two faces count as a fin (polish and :func:`crease_push`).

    Returns
    -------
    V : (n,3) float array
        Pre-inflated cage (free of self-intersections if ``info["self_intersections"] == 0``).
    info : dict
        Per round: samples inside M, mean / max vertex displacement, step-back iterations.
    """
    V = np.array(V, dtype=float)
    info = {"rounds": []}
    for _ in range(rounds):
        disp, n_in = _face_displacements(field, V, F, Vm, Fm)
        if n_in == 0:
            info["rounds"].append({"samples_inside": 0})
            break
        dv = _vertex_displacements(V, F, disp) * (1.0 + margin)
        V, dv, n_back, reverted = _move_without_intersection(V, F, dv, backoff, max_backoff)
        L = np.linalg.norm(dv, axis=1)
        info["rounds"].append({"samples_inside": n_in, "mean_move": float(L.mean()), "max_move": float(L.max()),
                               "backoff_iterations": n_back, "reverted": reverted})
    V, cinfo = _contain(V, F, Vm, Fm, rounds=contain_rounds, clearance=clearance, backoff=backoff,
                        max_backoff=max_backoff)
    info["containment"] = cinfo
    if crease_rounds and cinfo["outside_per_round"] and cinfo["outside_per_round"][-1] > 0:
        V, info["crease_push"] = crease_push(V, F, Vm, rounds=crease_rounds, clearance=clearance,
                                             backoff=backoff, max_backoff=max_backoff, fin_cos=fin_cos)
        if polish_rounds and info["crease_push"]["outside"] > 0:
            V, info["polish"] = polish(V, F, Vm, Fm, rounds=polish_rounds, clearance=clearance,
                                       backoff=backoff, max_backoff=max_backoff, fin_cos=fin_cos)
    info["self_intersections"] = len(self_intersection_pairs(V, F))
    return V, info


def polish(V, F, Vm, Fm, rounds: int = 12, clearance: float = 2e-3, backoff: float = 0.1,
           max_backoff: int = 40, fin_cos: float = -0.9, vertex_rounds: int = 2):
    """Containment push that never creates a fin, then cage vertices out of M (our addition, issue 18).

    (1) :func:`_contain` whose moves step back where a face would fold onto a neighbour (normal cosine
    below ``fin_cos``) as where the cage would intersect itself. (2) Up to ``vertex_rounds`` times:
    every cage vertex inside M or less than ``clearance`` outside moves to its closest point on M plus
    ``2 * clearance`` along the outward direction (same step-back), then (1) again. A cage vertex inside
    M makes M wrap around it in the Nested Cages flow.

    Returns ``(V, info)``: ``outside_per_round`` of each containment pass, ``cage_vertices_inside`` (cage
    vertices inside M or within the clearance before each vertex round), ``outside`` and ``fins`` of
    the result.
    """
    V = np.array(V, dtype=float)
    V, c = _contain(V, F, Vm, Fm, rounds, clearance, backoff, max_backoff, fin_cos)
    passes, inside = [c["outside_per_round"]], []
    for _ in range(vertex_rounds):
        V, n_near = _vertices_out_of(V, F, Vm, Fm, clearance, backoff, max_backoff, fin_cos)
        inside.append(n_near)
        if n_near == 0:
            break
        V, c = _contain(V, F, Vm, Fm, rounds, clearance, backoff, max_backoff, fin_cos)
        passes.append(c["outside_per_round"])
    s, _, _, _ = igl.signed_distance(Vm, V, F, sign_type=igl.SIGNED_DISTANCE_TYPE_FAST_WINDING_NUMBER)
    fins = int(_fin_mask(V, F, fin_cos).sum())
    return V, {"outside_per_round": passes, "cage_vertices_inside": inside, "outside": int((s > 0).sum()),
               "max_signed_distance": float(s.max()), "fins": fins}


def _vertices_out_of(V, F, Vm, Fm, clearance, backoff, max_backoff, fin_cos):
    """Move every cage vertex inside M or less than ``clearance`` outside it to its closest point on M
    plus ``2 * clearance`` outward (:func:`_move_without_intersection`'s step-back and fin guard).
    Returns ``(V, number of such vertices)`` (``V`` unchanged when there are none)."""
    s, _, C, _ = igl.signed_distance(V, Vm, Fm, sign_type=igl.SIGNED_DISTANCE_TYPE_FAST_WINDING_NUMBER)
    near = np.flatnonzero(s < clearance)
    if len(near) == 0:
        return V, 0
    L = np.abs(s[near])
    u = (C[near] - V[near]) * np.where(s[near] < 0, 1.0, -1.0)[:, None] / np.maximum(L, 1e-300)[:, None]
    dv = np.zeros_like(V)
    dv[near] = C[near] + 2.0 * clearance * u - V[near]
    V, _, _, _ = _move_without_intersection(V, F, dv, backoff, max_backoff, fin_cos)
    return V, len(near)


def _contain(V, F, Vm, Fm, rounds, clearance, backoff, max_backoff, fin_cos=None):
    """Push the cage past the vertices of M still outside it (our addition to the paper's step).

    Each vertex p of M outside the cage pulls its closest cage face by (p - closest point) lengthened
    by ``clearance``; the face displacements are combined at the vertices as in the pre-inflation
    (direction = mean, magnitude = largest projection), with the same step-back on self-intersection.
    This shortens the Nested Cages flow that follows (it starts from a cage containing most of M).
    """
    out_log = []
    for _ in range(rounds):
        w = igl.fast_winding_number(V, F, Vm)
        out = np.flatnonzero(w < 0.5)
        out_log.append(len(out))
        if len(out) == 0:
            break
        _, I, C, _ = igl.signed_distance(Vm[out], V, F, sign_type=igl.SIGNED_DISTANCE_TYPE_FAST_WINDING_NUMBER)
        d = Vm[out] - C
        L = np.linalg.norm(d, axis=1)
        d = d * ((L + clearance) / np.maximum(L, 1e-300))[:, None]
        disp = np.zeros((len(F), 3))
        best = np.full(len(F), -1.0)
        np.maximum.at(best, I, L)
        pick = best[I] == L
        disp[I[pick]] = d[pick]
        V, dvu, _, _ = _move_without_intersection(V, F, _vertex_displacements(V, F, disp), backoff,
                                                  max_backoff, fin_cos)
        if not np.any(dvu):
            break
    return V, {"outside_per_round": out_log}


def _fin_mask(V, F, fin_cos: float) -> np.ndarray:
    """Faces folded onto a neighbour: some neighbour's normal cosine below ``fin_cos`` (a thin fin)."""
    return (_fold_cosines(V, F) < fin_cos).any(axis=1)


def _offending_faces(V1, F, fin_cos, fins0):
    """Faces of ``(V1, F)`` that intersect another face, plus (``fin_cos`` given) faces folded onto a
    neighbour (normal cosine below ``fin_cos``) that were not folded so in ``fins0``."""
    pairs = self_intersection_pairs(V1, F)
    bad = np.unique(np.asarray(pairs).ravel()) if len(pairs) else np.zeros(0, dtype=np.int64)
    if fin_cos is not None:
        new_fins = np.flatnonzero(_fin_mask(V1, F, fin_cos) & ~fins0)
        bad = np.union1d(bad, new_fins)
    return bad.astype(np.int64)


def _move_without_intersection(V, F, dv, backoff, max_backoff, fin_cos=None):
    """``V + dv``, stepping the vertices of self-intersecting faces back by ``backoff`` of their move
    (never past ``V``) up to ``max_backoff`` times; if the cage still self-intersects, the vertices of
    the faces still intersecting do not move (repeated until the cage is free of intersections, at
    worst ``V`` itself).

    ``fin_cos`` (optional): a face that the move would fold onto a neighbour (normal cosine below
    ``fin_cos``, e.g. -0.9: a thin fin) and that was not folded so before counts as intersecting.
    Fins trap the Nested Cages flow: a point of M just inside the cage next to a fin is pushed away
    from its closest point, i.e. through the fin (zoo, cheburashka).

    Returns ``(V_new, dv_used, n_backoff, partly_reverted)``.
    """
    dv = dv.copy()
    V1 = V + dv
    n_back = 0
    fins0 = _fin_mask(V, F, fin_cos) if fin_cos is not None else None
    bad_f = _offending_faces(V1, F, fin_cos, fins0)
    while len(bad_f) and n_back < max_backoff:
        bad = np.unique(F[bad_f].ravel())
        V1[bad] -= backoff * dv[bad]
        dv[bad] *= 1.0 - backoff
        n_back += 1
        bad_f = _offending_faces(V1, F, fin_cos, fins0)
    frozen = 0
    while len(bad_f):  # the vertices of faces still offending do not move at all (V is free of them)
        bad = np.unique(F[bad_f].ravel())
        bad = bad[np.any(dv[bad] != 0, axis=1)]
        if len(bad) == 0:
            return V, np.zeros_like(dv), n_back, True  # keep the last intersection-free cage
        dv[bad] = 0.0
        V1 = V + dv
        frozen += len(bad)
        bad_f = _offending_faces(V1, F, fin_cos, fins0)
    return V1, dv, n_back, frozen > 0


def _fold_cosines(V, F):
    """Cosine between the normals of the faces on either side of each edge, (m, 3) (-1: folded flat)."""
    N = igl.per_face_normals(V, F, np.array([0.0, 0.0, 1.0]))
    TT, _ = igl.triangle_triangle_adjacency(F)
    return np.einsum("ij,ikj->ik", N, N[np.maximum(TT, 0)])


def unfold(V, F, fold_cos: float = -0.3, step: float = 0.5, iters: int = 20, backoff: float = 0.1,
           max_backoff: int = 40):
    """Open the folds of the cage: the vertices of every face whose normal makes a cosine below
    ``fold_cos`` with a neighbour's move ``step`` of the way to their 1-ring centroid (stepping back
    where the cage would intersect itself), until no fold is left or ``iters`` rounds.

    Folds appear where the pre-inflation or the containment push drives a tube into a junction
    (a concave crease closing on itself): a folded fin that points into M cannot be removed by the
    Nested Cages flow, and it blocks every outward push there. Returns ``(V, rounds, folds_left)``.
    """
    V = np.array(V, dtype=float)
    ring = igl.adjacency_list(F)
    for it in range(iters):
        bad = np.flatnonzero((_fold_cosines(V, F) < fold_cos).any(axis=1))
        if len(bad) == 0:
            return V, it, 0
        dv = np.zeros_like(V)
        for v in np.unique(F[bad].ravel()):
            dv[v] = step * (V[ring[v]].mean(axis=0) - V[v])
        V, _, _, _ = _move_without_intersection(V, F, dv, backoff, max_backoff)
    return V, iters, int((_fold_cosines(V, F) < fold_cos).any(axis=1).sum())


def crease_push(V, F, Vm, rounds: int = 20, clearance: float = 2e-3, fold_cos: float = -0.3,
                backoff: float = 0.1, max_backoff: int = 40, fin_cos: float = -0.9):
    """Push the cage out past the vertices of M still outside it or within ``clearance`` inside,
    along the cage's angle-weighted vertex normals, alternated with :func:`unfold` (our addition).

    Each round: every vertex of M with signed distance s > -clearance to the cage gives the three
    vertices of its closest cage face an outward move of s + clearance along their vertex normals
    (largest over the points); the move steps back where the cage would intersect itself
    (:func:`_move_without_intersection`); then the folds are opened. Unlike the containment push
    (moves towards the points, which closes concave creases into folds), the normal direction opens a
    concave crease. Kept: the round with the fewest vertices of M outside, or the input if it has
    fewer and no fin (faces folded onto a neighbour, normal cosine below ``fin_cos``; issue 18: on
    homer the first ``unfold`` raised the count outside from 651 to 2,644 and no round got back below
    1,095, but the input had 26 fins, which trap the Nested Cages flow: cheburashka's input, 73
    outside and 16 fins, stalled with intersections left after 154 iterations).

    Returns ``(V, info)``: ``info["outside_per_round"]`` (before each round, after the first unfold),
    ``outside_input`` and ``fins_input`` (the input), ``best_round`` (-1: the input was kept),
    ``outside``, ``folds`` and ``fins`` of the kept cage.
    """
    V = np.array(V, dtype=float)

    s, _, _, _ = igl.signed_distance(Vm, V, F, sign_type=igl.SIGNED_DISTANCE_TYPE_FAST_WINDING_NUMBER)
    out_in, fins_in = int((s > 0).sum()), int(_fin_mask(V, F, fin_cos).sum())
    # the input competes only without a fin (or with M inside): a fin traps the flow
    best = (out_in, -1, V.copy()) if (out_in == 0 or fins_in == 0) else (np.inf, -1, None)
    V, _, _ = unfold(V, F, fold_cos, backoff=backoff, max_backoff=max_backoff)
    log = []
    for r in range(rounds + 1):
        s, I, _, _ = igl.signed_distance(Vm, V, F, sign_type=igl.SIGNED_DISTANCE_TYPE_FAST_WINDING_NUMBER)
        n_out = int((s > 0).sum())
        log.append(n_out)
        if n_out < best[0]:
            best = (n_out, r, V.copy())
        if n_out == 0 or r == rounds:
            break
        sel = s > -clearance
        a = np.zeros(len(V))
        for k in range(3):
            np.maximum.at(a, F[I[sel], k], s[sel] + clearance)
        Nv = igl.per_vertex_normals(V, F, igl.PER_VERTEX_NORMALS_WEIGHTING_TYPE_ANGLE)
        V, _, _, _ = _move_without_intersection(V, F, a[:, None] * Nv, backoff, max_backoff)
        V, _, _ = unfold(V, F, fold_cos, backoff=backoff, max_backoff=max_backoff)
    n_out, r, V = best
    folds = int((_fold_cosines(V, F) < fold_cos).any(axis=1).sum())
    return V, {"outside_per_round": log, "outside_input": out_in, "fins_input": fins_in, "best_round": r,
               "outside": n_out, "folds": folds, "fins": int(_fin_mask(V, F, fin_cos).sum())}
