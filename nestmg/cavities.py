"""Solids with cavities: a closed outer surface plus inward-facing closed surfaces inside it (a hollow part).

A hollow CAD part or a tank exported as one surface file holds, besides its outer surface, one closed
surface per internal void, oriented towards the void (negative enclosed volume). The solid is what lies
inside the outer surface and outside every void. Its coarse levels need not have the voids: a cage of the
outer surface alone contains the whole solid, so the nested cages of the outer surface serve as they are,
and only the levels meshed from the input itself (TetWild decides inside by the generalised winding
number, which is 0 in a void) carry the voids. Prolongation and certification are unchanged: every fine
node still lies in the coarse tet mesh.

:func:`solid_groups` finds that structure among the pieces of a surface: each outward piece with the
inward pieces inside it, no two pieces crossing, no void inside another void.
"""

from __future__ import annotations

import numpy as np

__all__ = ["audit_voids", "hollow_solid", "merge_surfaces", "orient_by_nesting", "solid_groups"]


def _inside(outer: tuple[np.ndarray, np.ndarray], point: np.ndarray) -> bool:
    import igl

    V, F = outer
    w = float(np.asarray(igl.fast_winding_number(V, F, point[None, :])).ravel()[0])
    return abs(w) > 0.5


def _any_crossing(pieces: list[tuple[np.ndarray, np.ndarray]]) -> bool:
    """Whether two of the pieces intersect (exact test, for pairs whose bounding boxes meet)."""
    from cagegen.components import crossing_pairs

    boxes = [(V[np.unique(F)].min(axis=0), V[np.unique(F)].max(axis=0)) for V, F in pieces]
    return any(np.all(boxes[a][1] >= boxes[b][0]) and np.all(boxes[b][1] >= boxes[a][0])
               and len(crossing_pairs(*pieces[a], *pieces[b]))
               for a in range(len(pieces)) for b in range(a + 1, len(pieces)))


def solid_groups(pieces: list[tuple[np.ndarray, np.ndarray]]) -> list[tuple[tuple, list]] | None:
    """Group the closed pieces of a surface into solids with voids, when that is what they describe.

    Parameters
    ----------
    pieces : list of (V_i, F_i)
        Closed pieces (:func:`cagegen.split_components`).

    Returns
    -------
    list of (outer, voids) or None
        One entry per outward piece (positive enclosed volume) with the inward pieces inside it; None
        when no piece faces inward, or when the pieces do not describe solids with voids (an inward piece
        outside every outward one or inside several, a void inside a void, two pieces that cross): the
        callers' other checks then name the problem.
    """
    from .memory import signed_volume

    vols = [signed_volume(V, F) for V, F in pieces]
    outer = [i for i, v in enumerate(vols) if v > 0]
    voids = [i for i, v in enumerate(vols) if v < 0]
    if not voids or not outer or len(outer) + len(voids) != len(pieces):
        return None
    lo = np.array([V.min(axis=0) for V, _ in pieces])
    hi = np.array([V.max(axis=0) for V, _ in pieces])

    def boxes_meet(a, b):
        return not (np.any(hi[a] < lo[b]) or np.any(hi[b] < lo[a]))

    owner = {}
    for c in voids:
        p = pieces[c][0][0]
        hosts = [o for o in outer if boxes_meet(o, c) and _inside(pieces[o], p)]
        if len(hosts) != 1 or any(_inside(pieces[d], p) for d in voids if d != c and boxes_meet(d, c)):
            return None
        owner[c] = hosts[0]
    if _any_crossing(pieces):  # a void must lie strictly inside its solid
        return None
    return [(pieces[o], [pieces[c] for c in voids if owner[c] == o]) for o in outer]


def merge_surfaces(surfaces: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """One ``(V, F)`` of several surfaces (vertices stacked, faces re-indexed)."""
    offsets = np.cumsum([0] + [len(V) for V, _ in surfaces])
    return (np.vstack([np.asarray(V, dtype=np.float64) for V, _ in surfaces]),
            np.vstack([np.asarray(F, dtype=np.int64) + o for (_, F), o in zip(surfaces, offsets)]))


def _hollow_group(V: np.ndarray, F: np.ndarray) -> tuple[tuple, list] | None:
    """``(outer, [void, ...])`` of one solid with voids, else None (see :func:`hollow_solid`)."""
    import cagegen

    F = np.asarray(F)
    if F.ndim != 2 or F.shape[1] != 3 or len(F) == 0:
        return None
    pieces = cagegen.split_components(V, F)
    if len(pieces) < 2:
        return None
    groups = solid_groups(pieces)
    return groups[0] if groups is not None and len(groups) == 1 else None


def hollow_solid(V: np.ndarray, F: np.ndarray) -> tuple[tuple, tuple, int] | None:
    """``(outer, voids, n_voids)`` of one solid with voids (each a ``(V, F)``; ``voids`` all void surfaces
    merged), else None (one piece, several solids, or pieces that do not describe a solid with voids)."""
    group = _hollow_group(V, F)
    return None if group is None else (group[0], merge_surfaces(group[1]), len(group[1]))


def audit_voids(V: np.ndarray, F: np.ndarray, name: str = "input", outer: bool = True) -> tuple | None:
    """:func:`cagegen.check_mesh` of a solid that may have voids: each void (turned outward for the audit)
    and, with ``outer``, the outer surface, one by one, when :func:`hollow_solid` finds voids; with
    ``outer`` and no voids, ``(V, F)`` as a whole. Returns :func:`hollow_solid`'s result (None without
    voids); raises :class:`cagegen.MeshInputError` naming the piece."""
    import cagegen

    group = _hollow_group(V, F)
    if group is None:
        if outer:
            cagegen.check_mesh(V, F, name=name)
        return None
    (Vo, Fo), voids = group
    if outer:
        cagegen.check_mesh(Vo, Fo, name=f"{name} (outer surface)")
    for k, (Vc, Fc) in enumerate(voids):
        cagegen.check_mesh(Vc, Fc[:, ::-1], name=f"{name} (void {k + 1} of {len(voids)}, turned outward)")
    return (Vo, Fo), merge_surfaces(voids), len(voids)


def orient_by_nesting(V: np.ndarray, F: np.ndarray) -> np.ndarray | None:
    """Faces of a surface of nested pieces oriented by the even-odd rule: a piece inside an odd number of
    others faces inward (a void), the others outward. For files whose orientation says nothing (an STL
    exporter's voids facing out). Returns new faces, or None when there is no such nesting, pieces cross,
    or the result is not one solid with voids (:func:`hollow_solid`)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    from .memory import signed_volume

    V, F = np.asarray(V, dtype=np.float64), np.asarray(F, dtype=np.int64)
    E = F[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    _, vertex_label = connected_components(sp.csr_matrix((np.ones(len(E)), (E[:, 0], E[:, 1])),
                                                          shape=(len(V), len(V))), directed=False)
    face_label = vertex_label[F[:, 0]]
    masks = [face_label == label for label in np.unique(face_label)]
    if len(masks) < 2:
        return None
    pieces = [(V, F[m]) for m in masks]  # the caller's vertices, each piece's faces
    if _any_crossing(pieces):
        return None
    depth = [sum(_inside(pieces[o], V[G[0, 0]]) for o in range(len(pieces)) if o != p)
             for p, (_, G) in enumerate(pieces)]
    if not any(d % 2 for d in depth):
        return None
    out = F.copy()
    for m, (_, G), d in zip(masks, pieces, depth):
        if (signed_volume(V, G) > 0) != (d % 2 == 0):
            out[m] = G[:, ::-1]
    return out if hollow_solid(V, out) is not None else None
