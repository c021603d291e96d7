"""Tighten a certified cage: pull its vertices towards the surface it contains, by collision-free moves.

The skeleton backend's containment leaves the pre-inflation's spikes in the cage (docs/skeleton.md):
vertices far from M that the re-inflation's volume phase barely moves. This post-step moves every
cage vertex farther than ``keep`` x gap from M towards its closest point on M, stopping ``keep`` x
gap short of it. The moves are straight lines cut by continuous collision detection with a minimum
distance (ipctk's additive CCD, ``min_distance = gap``: Li et al. 2021), so the cage never meets
itself nor comes closer than ``gap`` to M on the way; it therefore still contains M. A vertex whose
move is blocked does not block the others: the moving set is split in halves until each part moves
freely or is one vertex, which then takes its own collision-free fraction (one broad phase per
round, :meth:`cagegen.collision.PairMesh.candidates`). The connectivity is unchanged (every quad
kept). The caller certifies the result (:func:`cagegen.verify_nesting`).

Measured on the zoo's skeleton cages (docs/skeleton.md, "A tightening post-step"): every result
certifies, but the max distance does not move (the farthest corners' fans of faces would sweep into M),
so :func:`cagegen.skeleton.skeleton_cage` does not call it.
"""

from __future__ import annotations

import time

import igl
import numpy as np

from ..collision import PairMesh, min_distance

__all__ = ["tighten_cage"]


def tighten_cage(C: np.ndarray, Fc: np.ndarray, V: np.ndarray, F: np.ndarray, gap: float,
                 keep: float = 2.0, rounds: int = 12, min_move: float = 0.05) -> tuple[np.ndarray, dict]:
    """Move the cage ``(C, Fc)`` towards the surface ``(V, F)`` it contains, keeping at least ``gap``.

    Parameters
    ----------
    C : (nc,3) float array
        Cage vertices; the cage contains ``(V, F)``, is free of self-intersections and at least ``gap``
        from it (not modified).
    Fc : (mc,3) int array
        Cage triangles.
    V : (n,3) float array
    F : (m,3) int array
        The contained surface M.
    gap : float
        Clearance kept during every move (absolute, in the units of ``V``), > 0.
    keep : float
        A vertex's target is its closest point on M moved back ``keep * gap`` towards the vertex.
    rounds : int
        Rounds of moves (each recomputes the closest points).
    min_move : float
        Stop when no vertex moved more than ``min_move`` x its remaining distance to M in a round.

    Returns
    -------
    C2 : (nc,3) float array
        The moved cage.
    info : dict
        ``rounds``, ``ccd_calls``, ``seconds``, ``distance`` (cage to M after), the mean / max vertex
        distance to M before and after.
    """
    t0 = time.perf_counter()
    C = np.array(C, dtype=float)
    Fc = np.asarray(Fc, dtype=np.int64)
    V = np.asarray(V, dtype=float)
    pair = PairMesh(C, Fc, V, np.asarray(F, dtype=np.int64))
    dist0 = np.sqrt(igl.point_mesh_squared_distance(C, V, F)[0])
    info: dict = {"ccd_calls": 0, "rounds": 0,
                  "vertex_distance_before": [float(dist0.mean()), float(dist0.max())]}
    for r in range(rounds):
        d2, _, P = igl.point_mesh_squared_distance(C, V, F)
        dist = np.sqrt(d2)
        excess = dist - keep * gap
        active = np.flatnonzero(excess > min_move * dist)
        if not len(active):
            break
        T = C.copy()
        T[active] += (excess[active] / dist[active])[:, None] * (P[active] - C[active])
        cand = pair.candidates(pair.stack(C, V), pair.stack(T, V), gap)
        before = C.copy()
        C = _move_free(pair, cand, C, T, active, V, gap, info)
        info["rounds"] = r + 1
        if np.max(np.linalg.norm(C - before, axis=1) / np.maximum(dist, 1e-300)) < min_move:
            break
    dist1 = np.sqrt(igl.point_mesh_squared_distance(C, V, F)[0])
    info.update(vertex_distance_after=[float(dist1.mean()), float(dist1.max())],
                distance=float(min_distance(C, Fc, V, np.asarray(F, dtype=np.int64))),
                seconds=time.perf_counter() - t0)
    return C, info


def _move_free(pair: PairMesh, cand, C: np.ndarray, T: np.ndarray, S: np.ndarray, V: np.ndarray, gap: float,
               info: dict) -> np.ndarray:
    """Move the vertices ``S`` of ``C`` to ``T`` where the motion is free (CCD with ``min_distance=gap``);
    a blocked set is split in halves; a single blocked vertex takes 90% of its free fraction."""
    X1 = C.copy()
    X1[S] = T[S]
    a = pair.stepsize(pair.stack(C, V), pair.stack(X1, V), min_distance=gap, candidates=cand)
    info["ccd_calls"] += 1
    if a >= 1.0:
        return X1
    if len(S) == 1:
        out = C.copy()
        out[S] += 0.9 * a * (T[S] - C[S])
        return out
    h = len(S) // 2
    C = _move_free(pair, cand, C, T, S[:h], V, gap, info)
    return _move_free(pair, cand, C, T, S[h:], V, gap, info)
