"""The solid a defective surface describes, as a clean closed surface (``repair=True``, ``--repair``).

STL exports of assemblies and scans often describe a solid without bounding it cleanly: bodies that
overlap each other, a surface that crosses itself, fans that touch at a vertex. No cage backend can use
such a surface (:func:`cagegen.audit_mesh` refuses it), but TetWild meshes the solid it describes: its
inside/outside test is the generalised winding number (fTetWild, Hu et al. 2020), so overlapping bodies
become their union. :func:`solid_surface` tet-meshes the input once and returns the boundary of that
tet mesh, made manifold:

1. tets are grouped by shared faces; groups under :data:`SPECK_FRACTION` of the volume are dropped
   (specks that touch the solid at an edge or a vertex only);
2. where tets of the solid touch at an edge or a vertex only (a pinch: the boundary is not manifold
   there), the tets around that vertex are grouped by the faces through it and all but the largest group
   are removed, for at most :data:`PINCH_ROUNDS` rounds;
3. inward-facing pieces of the boundary (voids inside the solid, e.g. left between overlapping bodies)
   are filled.

The result is a new surface within TetWild's envelope ``epsilon`` of the input wherever the input was
already a clean boundary; the report says how much volume steps 1-3 changed.

Closed pieces that are each clean but cross or nest (an assembly of overlapping parts) need no envelope:
:func:`exact_union` returns their boolean union, exact up to round-off, with the parts' own faces and sharp
edges (the Manifold library, ``manifold3d``: coplanar faces resolved by symbolic perturbation), in
milliseconds.
"""

from __future__ import annotations

import functools
import operator

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from cagegen import MeshInputError
from solvers.fem import boundary_faces

from .cavities import merge_surfaces
from .memory import signed_volume
from .tetmesh import tet_volumes

__all__ = ["MAX_PATCH_FRACTION", "UNREPAIRABLE", "exact_union", "fill_holes", "solid_surface"]

#: tet groups (connected through faces) below this fraction of the total volume are dropped
SPECK_FRACTION = 1e-3
#: rounds of pinch removal before giving up
PINCH_ROUNDS = 10
#: audit problems (their first words) that no solid can mend: the input encloses nothing clearly
UNREPAIRABLE = ("open boundary", "absurd size", "too few faces", "zero volume", "NaN")


def _face_adjacency(T: np.ndarray) -> sp.csr_matrix:
    """(t,t) adjacency of tets that share a face."""
    faces = np.sort(T[:, [1, 2, 3, 0, 2, 3, 0, 1, 3, 0, 1, 2]].reshape(-1, 3), axis=1)
    _, key = np.unique(faces, axis=0, return_inverse=True)
    inc = sp.csr_matrix((np.ones(4 * len(T)), (np.repeat(np.arange(len(T)), 4), key.ravel())))
    return (inc @ inc.T).tocsr()


def _drop_specks(V: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, float]:
    """Keep the face-connected tet groups of at least :data:`SPECK_FRACTION` of the volume."""
    _, lab = connected_components(_face_adjacency(T), directed=False)
    vol = np.bincount(lab, weights=np.abs(tet_volumes(V, T)))
    keep = vol >= SPECK_FRACTION * vol.sum()
    return T[keep[lab]], float(vol[~keep].sum())


def _pinched_vertices(F: np.ndarray, n: int) -> np.ndarray:
    """Vertices of the boundary ``F`` where it is not manifold (several fans, or an edge of 3+ faces)."""
    import igl

    bad = np.zeros(n, dtype=bool)
    mv = np.asarray(igl.is_vertex_manifold(F), dtype=bool)
    bad[: mv.size] |= ~mv
    E = np.sort(F[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    uE, count = np.unique(E, axis=0, return_counts=True)
    bad[uE[count > 2].ravel()] = True  # edges of 3 or more faces
    return np.flatnonzero(bad & np.isin(np.arange(n), F))


def _unpinch(V: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, int]:
    """Remove, around every pinched boundary vertex, all tet groups but the largest (grouped by the faces
    through that vertex); returns the tets and the number of rounds."""
    for rounds in range(PINCH_ROUNDS + 1):
        bad = _pinched_vertices(boundary_faces(T)[0], len(V))
        if bad.size == 0:
            return T, rounds
        if rounds == PINCH_ROUNDS:
            break
        vol = np.abs(tet_volumes(V, T))
        VT = sp.csr_matrix((np.ones(T.size), (T.ravel(), np.repeat(np.arange(len(T)), 4))),
                           shape=(len(V), len(T)))
        drop = np.zeros(len(T), dtype=bool)
        for v in bad:
            around = VT.indices[VT.indptr[v]:VT.indptr[v + 1]]
            # two tets through v are joined when they share a face through v: 3 shared nodes, v one of them
            Ta = T[around]
            shared = (Ta[:, None, :, None] == Ta[None, :, None, :]).sum(axis=(2, 3))
            _, lab = connected_components(sp.csr_matrix(shared >= 3), directed=False)
            best = np.argmax(np.bincount(lab, weights=vol[around]))
            drop[around[lab != best]] = True
        if not drop.any():  # one group whose boundary still pinches (a fan around a tunnel): open it
            drop[VT[bad].indices] = True
        T = T[~drop]
    raise MeshInputError(f"input: its solid still pinches at {bad.size} vertices after {PINCH_ROUNDS} rounds "
                         "of repair (bodies touching along edges); export the parts separately or fuse them")


def _fill_voids(V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, int]:
    """Drop the boundary pieces with negative volume (voids inside the solid); returns the compacted
    surface, the volume filled and the number of outward pieces left."""
    from cagegen import split_components

    pieces = split_components(V, F)
    vols = np.array([signed_volume(W, G) for W, G in pieces])  # enclosed volume of each closed piece
    kept = [p for p, v in zip(pieces, vols) if v > 0]
    if not kept:
        raise MeshInputError("input: TetWild found no solid inside it")
    W, G = merge_surfaces(kept)
    return W, G, float(-vols[vols < 0].sum()) + 0.0, len(kept)  # + 0.0: no "-0.00%" on the stage line


#: Holes are filled only when their patches add at most this fraction of the surface's area: a scan with
#: holes (a few percent), not an open sheet (whose "hole" is as large as the sheet itself)
MAX_PATCH_FRACTION = 0.05
#: Longest boundary loop filled (the triangulation's dynamic programme is cubic in it)
MAX_HOLE_VERTICES = 2000


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.divide(v, n, out=np.zeros_like(v), where=n > 0)


def _angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles between unit normals (pi where one is zero: a degenerate triangle)."""
    ang = np.arccos(np.clip(np.einsum("...j,...j->...", a, b), -1.0, 1.0))
    return np.where((np.abs(a).sum(axis=-1) == 0) | (np.abs(b).sum(axis=-1) == 0), np.pi, ang)


def _hole_patch(P: np.ndarray, Nb: np.ndarray) -> np.ndarray:
    """Triangles (local indices) closing the polygon ``P`` (n,3): the triangulation of least largest dihedral
    angle, then least area (Liepa 2003, "Filling holes in meshes", weight (max angle, area) compared
    lexicographically; angles in 0.01 rad bins), by dynamic programming over the sub-polygons ``i..k``.
    ``Nb[j]``: unit normal of the surface's face on the hole's edge ``(j, j+1)``."""
    n = len(P)
    MA, AR, N = np.zeros((n, n)), np.zeros((n, n)), np.zeros((n, n, 3))
    O = np.full((n, n), -1, dtype=np.int64)
    N[np.arange(n - 1), np.arange(1, n)] = Nb[:-1]
    area_unit = 1.0 / max(float(np.ptp(P, axis=0).max()) ** 2, 1e-300)
    for gap in range(2, n):
        i = np.arange(n - gap)
        k = i + gap
        best = np.full(len(i), np.inf)
        for m in (i + d for d in range(1, gap)):
            cross = np.cross(P[m] - P[k], P[i] - P[k])  # triangle (k, m, i): the surface's orientation
            nt = _unit(cross)
            ma = np.maximum.reduce([MA[i, m], MA[m, k], _angle(nt, N[i, m]), _angle(nt, N[m, k])])
            if gap == n - 1:  # the last edge (n-1, 0) borders the surface too
                ma = np.maximum(ma, _angle(nt, Nb[n - 1][None]))
            ar = AR[i, m] + AR[m, k] + 0.5 * np.linalg.norm(cross, axis=1)
            key = np.floor(ma / 0.01) * 1e6 + ar * area_unit
            b = key < best
            best[b], O[i[b], k[b]], MA[i[b], k[b]], AR[i[b], k[b]], N[i[b], k[b]] = key[b], m[b], ma[b], ar[b], nt[b]
    tris, stack = [], [(0, n - 1)]
    while stack:
        i, k = stack.pop()
        if k - i >= 2:
            m = int(O[i, k])
            tris.append((k, m, i))
            stack += [(i, m), (m, k)]
    return np.array(tris, dtype=np.int64)


def fill_holes(V: np.ndarray, F: np.ndarray, max_patch_fraction: float = MAX_PATCH_FRACTION
               ) -> tuple[np.ndarray, np.ndarray, dict]:
    """Close the holes of an open, otherwise clean surface (a scan's missing patches).

    Each boundary loop is closed by :func:`_hole_patch` (no new vertices; the patch's orientation follows
    the surface's). Returns ``(V, G, info)``: ``G`` is ``F`` followed by the patches; ``info`` holds
    ``holes``, ``patch_faces`` and ``patch_area_fraction``.

    Raises
    ------
    MeshInputError
        A loop longer than :data:`MAX_HOLE_VERTICES`, or patches above ``max_patch_fraction`` of the
        surface's area (an open sheet, not a solid with holes).
    """
    import igl

    F = np.asarray(F, dtype=np.int64)
    E = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    face_of = dict(zip(map(tuple, E.tolist()), np.tile(np.arange(len(F)), 3).tolist()))
    normals = _unit(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]))
    patches = []
    for L in igl.boundary_loop_all(F):
        L = np.asarray(L, dtype=np.int64)
        if len(L) > MAX_HOLE_VERTICES:
            raise MeshInputError(f"input: a hole of {len(L)} boundary vertices (at most {MAX_HOLE_VERTICES} are "
                                 "filled): close the surface first")
        if (int(L[0]), int(L[1])) not in face_of:  # walk the loop the way its faces do
            L = L[::-1]
        n = len(L)
        faces = [face_of[(int(L[j]), int(L[(j + 1) % n]))] for j in range(n)]
        patches.append(L[_hole_patch(V[L], normals[faces])])
    P = np.vstack(patches)

    def area(G):
        return 0.5 * float(np.linalg.norm(np.cross(V[G[:, 1]] - V[G[:, 0]], V[G[:, 2]] - V[G[:, 0]]), axis=1).sum())

    fraction = area(P) / max(area(F), 1e-300)
    if fraction > max_patch_fraction:
        raise MeshInputError(f"input: an open surface whose {len(patches)} hole(s) would take {fraction:.0%} of its "
                             f"area to close (at most {max_patch_fraction:.0%}): not a solid with holes")
    info = {"holes": len(patches), "patch_faces": len(P), "patch_area_fraction": fraction}
    return V, np.vstack([F, P]), info


def _edge_pieces(V: np.ndarray, F: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """The pieces of ``(V, F)`` connected through shared edges, each with its own copy of the vertices (pieces
    that touch at a vertex, e.g. after a vertex merge, come apart)."""
    F = np.asarray(F, dtype=np.int64)
    m = len(F)
    E = np.sort(F[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, key = np.unique(E, axis=0, return_inverse=True)
    face_edge = sp.csr_matrix((np.ones(3 * m), (np.repeat(np.arange(m), 3), key.ravel())))
    n, label = connected_components(face_edge @ face_edge.T, directed=False)
    pieces = []
    for k in range(n):
        Fk = F[label == k]
        used, Gk = np.unique(Fk, return_inverse=True)
        pieces.append((np.asarray(V, dtype=float)[used], Gk.reshape(-1, 3)))
    return pieces


def exact_union(V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict] | None:
    """The boolean union of the closed pieces of ``(V, F)`` when they cross or nest and each one is clean.

    Parameters
    ----------
    V : (n,3) float array
    F : (m,3) int array
        Several edge-connected pieces; each must pass :func:`cagegen.audit_mesh` on its own (closed,
        manifold, no self-intersection) and enclose a positive volume (outward).

    Returns
    -------
    (W, G, info) or None
        The union's boundary (one outward surface per disjoint body of the union, and an inward one per void
        the parts enclose), ``info`` as :func:`solid_surface`'s (``method`` "union", ``voids``); None when the
        input is one piece,
        a piece is not clean by itself (TetWild's solid is then the repair), or the union fails the audit.
    """
    import manifold3d

    import cagegen

    pieces = _edge_pieces(V, F)
    if len(pieces) < 2 or any(signed_volume(W, G) <= 0 or cagegen.audit_mesh(W, G).problems for W, G in pieces):
        return None
    solids = [manifold3d.Manifold(manifold3d.Mesh64(vert_properties=np.ascontiguousarray(W, dtype=np.float64),
                                                    tri_verts=np.ascontiguousarray(G, dtype=np.uint64)))
              for W, G in pieces]
    if any(m.status() != manifold3d.Error.NoError for m in solids):
        return None
    for union in (lambda: manifold3d.Manifold.batch_boolean(solids, manifold3d.OpType.Add),
                  lambda: functools.reduce(operator.add, solids)):  # one by one: another triangulation
        mesh = union().to_mesh64()
        W = np.asarray(mesh.vert_properties, dtype=np.float64)[:, :3].copy()
        G = np.asarray(mesh.tri_verts, dtype=np.int64)
        if len(G) == 0:
            return None
        # a void the parts enclose (a sealed box of plates) stays a void: it faces inward (nestmg.cavities)
        signed = [(Wb, Gb, signed_volume(Wb, Gb)) for Wb, Gb in cagegen.split_components(W, G)]
        if not any(cagegen.audit_mesh(Wb, Gb if v > 0 else Gb[:, ::-1]).problems for Wb, Gb, v in signed):
            break
    else:  # coplanar faces triangulated into an overlap both times: TetWild's solid instead
        return None
    info = {"method": "union", "faces_in": len(F), "faces_out": len(G), "tets": 0,
            "bodies": sum(v > 0 for *_, v in signed), "voids": sum(v < 0 for *_, v in signed), "pinch_rounds": 0,
            "volume": signed_volume(W, G), "volume_dropped": 0.0, "volume_filled": 0.0, "decimated": None}
    return W, G, info


#: A repair input of more faces is decimated first (QEM halvings while the Hausdorff distance stays within
#: TetWild's envelope ``epsilon``; the solid's boundary is then within ``2 epsilon`` of the input, and the
#: pipeline's predecimation allows ``max(epsilon, h/4)`` after it anyway): TetWild's time grows with its
#: input's faces (~1 ms each, nestmg.sizing): a 400k-face scan with self-intersections took 454 s.
REPAIR_MAX_FACES = 50_000


def lighter_input(V: np.ndarray, F: np.ndarray, epsilon: float) -> tuple[np.ndarray, np.ndarray, dict | None]:
    """``(V, F)`` halved by QEM decimation, again and again down to :data:`REPAIR_MAX_FACES` faces, while the
    Hausdorff distance to ``(V, F)`` stays within ``epsilon`` (relative to the bounding-box diagonal).
    The input may self-intersect (TetWild resolves that): only closedness and orientation are checked.

    Returns ``(V, F, info)``: info None when ``F`` has at most :data:`REPAIR_MAX_FACES` faces, else
    ``faces_in``, ``faces_out``, ``hausdorff`` (relative, of the surface returned) and ``refused`` (the
    face count and error of the first halving that was not kept, if any).
    """
    import igl

    from cagegen import bbox_diagonal
    from cagegen.decimate import decimate_surface

    if len(F) <= REPAIR_MAX_FACES:
        return V, F, None
    diag = float(bbox_diagonal(V))
    U, G, info = V, F, {"faces_in": len(F), "faces_out": len(F), "hausdorff": 0.0, "refused": None}
    while len(G) > REPAIR_MAX_FACES:
        target = max(REPAIR_MAX_FACES, len(G) // 2)
        try:
            U2, G2, _ = decimate_surface(U, G, target, check_self=False, keep_genus=False, other_decimator=False)
        except Exception:  # noqa: BLE001 -- a decimation that fails leaves the last surface kept
            info["refused"] = {"faces": target, "hausdorff": None}
            break
        err = float(igl.hausdorff(V, F, U2, G2)) / diag
        if err > epsilon:
            info["refused"] = {"faces": len(G2), "hausdorff": err}
            break
        U, G = U2, G2
        info.update(faces_out=len(G), hausdorff=err)
    return U, G, info


def solid_surface(V: np.ndarray, F: np.ndarray, *, epsilon: float = 1e-3, edge_length: float = 0.05,
                  time_limit: float | str | None = "auto") -> tuple[np.ndarray, np.ndarray, dict]:
    """The boundary of the solid that ``(V, F)`` describes, closed, manifold and outward oriented.

    Parameters
    ----------
    V : (n,3) float array
    F : (m,3) int array
        A surface that encloses a solid but need not bound it cleanly: overlapping bodies,
        self-intersections, non-manifold vertices or edges.
    epsilon : float
        TetWild's envelope relative to the bounding-box diagonal: the result lies within it of the
        input where the input was a clean boundary.
    edge_length : float
        TetWild's target edge relative to the diagonal (it refines wherever the envelope needs it).
    time_limit : float, "auto" or None
        As :func:`nestmg.tetmesh.tetrahedralize`.

    Returns
    -------
    W : (p,3) float64 array
    G : (q,3) int64 array
        The new surface: one outward piece per disjoint body (a caller that needs one solid audits it).
    info : dict
        ``faces_in``, ``faces_out``, ``tets``, ``bodies`` (outward pieces), ``pinch_rounds``, and the
        volumes ``volume`` (of the result), ``volume_dropped`` (specks and pinches) and ``volume_filled``
        (voids), all in the units of ``V``.

    Raises
    ------
    MeshInputError
        If TetWild finds no solid or the pinches do not resolve.
    TetMeshError
        If TetWild fails or runs past ``time_limit``.
    """
    from .tetmesh import tetrahedralize
    from .usermesh import boundary_surface

    V, F, lighter = lighter_input(V, F, epsilon)
    Vt, T = tetrahedralize(V, F, edge_length=edge_length, epsilon=epsilon, time_limit=time_limit)
    v0 = float(np.abs(tet_volumes(Vt, T)).sum())
    T, _ = _drop_specks(Vt, T)
    T, rounds = _unpinch(Vt, T)
    T, _ = _drop_specks(Vt, T)  # removing pinched tets can cut a speck loose
    W, G, filled, bodies = _fill_voids(*boundary_surface(Vt, T)[:2])
    kept = float(np.abs(tet_volumes(Vt, T)).sum())
    info = {"method": "tetwild", "faces_in": len(F), "faces_out": len(G), "tets": len(T), "bodies": bodies,
            "pinch_rounds": rounds, "volume": kept + filled, "volume_dropped": v0 - kept,
            "volume_filled": filled + 0.0, "decimated": lighter}
    return W, G, info
