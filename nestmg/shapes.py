"""Procedural closed surfaces for the demo and the tests (implicit function + marching cubes).

Every shape is described by a signed distance (or distance-like) function ``sdf(P) -> (n,)``,
negative inside, and meshed with :func:`skimage.measure.marching_cubes`. The result is a closed,
manifold, single-component, outward-oriented triangle mesh ``(V, F)``.

:func:`nested_isosurfaces` meshes the iso-surfaces ``sdf = d_0 < d_1 < ...`` of one function at
decreasing resolution: a *procedurally nested* hierarchy (each coarser surface strictly contains the
finer one when the offsets exceed the marching-cubes error), used to test multigrid without a cage
backend.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from .errors import NestmgInputError

SDF = Callable[[np.ndarray], np.ndarray]

__all__ = [
    "SHAPES",
    "ball_tets",
    "genus2",
    "hand",
    "mesh_implicit",
    "neck_blobs",
    "nested_isosurfaces",
    "shape_sdf",
    "sphere",
    "star_of_capsules",
    "stick_figure",
    "thin_plate",
    "torus",
    "torus_tets",
]


# ----------------------------------------------------------------------------- implicit functions
def _smooth_min(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum (blend radius ``k``); equals min(a, b) where |a-b| > k."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b * (1 - h) + a * h - k * h * (1 - h)


def _sphere_sdf(P: np.ndarray, c=(0.0, 0.0, 0.0), r: float = 1.0) -> np.ndarray:
    return np.linalg.norm(P - np.asarray(c), axis=1) - r


def _torus_sdf(P: np.ndarray, c=(0.0, 0.0, 0.0), R: float = 1.0, r: float = 0.35) -> np.ndarray:
    Q = P - np.asarray(c)
    q = np.hypot(Q[:, 0], Q[:, 1]) - R
    return np.hypot(q, Q[:, 2]) - r


def _capsule_sdf(P: np.ndarray, a, b, r: float) -> np.ndarray:
    a, b = np.asarray(a, float), np.asarray(b, float)
    ab = b - a
    t = np.clip((P - a) @ ab / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(P - (a + t[:, None] * ab), axis=1) - r


def _rounded_box_sdf(P: np.ndarray, half=(1.0, 0.7, 0.08), rounding: float = 0.05) -> np.ndarray:
    q = np.abs(P) - (np.asarray(half) - rounding)
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
    inside = np.minimum(q.max(axis=1), 0.0)
    return outside + inside - rounding


def shape_sdf(name: str) -> tuple[SDF, np.ndarray]:
    """Implicit function and bounding box of a named procedural shape.

    Parameters
    ----------
    name : str
        One of ``sphere``, ``torus``, ``genus2``, ``neck_blobs``, ``thin_plate``.

    Returns
    -------
    sdf : callable
        ``sdf(P)`` for ``P`` (n,3) returns (n,) values, negative inside.
    bounds : (2,3) float array
        Box that contains the zero level set with a margin.
    """
    if name == "sphere":
        return _sphere_sdf, np.array([[-1.0] * 3, [1.0] * 3])
    if name == "torus":
        return _torus_sdf, np.array([[-1.35, -1.35, -0.35], [1.35, 1.35, 0.35]])
    if name == "genus2":
        def f(P):
            return _smooth_min(_torus_sdf(P, (-0.8, 0, 0), 0.8, 0.3), _torus_sdf(P, (0.8, 0, 0), 0.8, 0.3), 0.1)
        return f, np.array([[-1.9, -1.1, -0.3], [1.9, 1.1, 0.3]])
    if name == "neck_blobs":
        def f(P):
            blobs = np.minimum(_sphere_sdf(P, (-0.9, 0, 0), 0.6), _sphere_sdf(P, (0.9, 0, 0), 0.6))
            return _smooth_min(blobs, _capsule_sdf(P, (-0.9, 0, 0), (0.9, 0, 0), 0.12), 0.08)
        return f, np.array([[-1.5, -0.6, -0.6], [1.5, 0.6, 0.6]])
    if name == "thin_plate":
        return _rounded_box_sdf, np.array([[-1.0, -0.7, -0.08], [1.0, 0.7, 0.08]])
    raise NestmgInputError(f"unknown shape {name!r}; choose from {sorted(SHAPES)}")


# ----------------------------------------------------------------------------- meshing
def mesh_implicit(
    sdf: SDF, bounds: np.ndarray, res: int = 40, level: float = 0.0, relax: int = 5
) -> tuple[np.ndarray, np.ndarray]:
    """Mesh the level set ``sdf = level`` by marching cubes.

    Parameters
    ----------
    sdf : callable
        ``sdf(P)`` for ``P`` (n,3) returns (n,) values, negative inside.
    bounds : (2,3) float array
        Box containing the level set; it is padded by ``|level|`` plus two grid cells so the surface
        never touches the grid boundary (hence is closed).
    res : int
        Number of grid cells along the longest side of the box.
    level : float
        Iso-value (an outward offset when ``sdf`` is a signed distance).
    relax : int
        Smoothing + re-projection iterations that even out the triangles (0 = raw marching cubes).

    Returns
    -------
    V : (n,3) float64 array
    F : (m,3) int64 array
        Closed, outward-oriented, single-component triangle mesh.
    """
    from skimage.measure import marching_cubes

    bounds = np.asarray(bounds, dtype=float)
    if res < 4:
        raise NestmgInputError(f"res must be >= 4, got {res}")
    h = float((bounds[1] - bounds[0]).max()) / res
    lo = bounds[0] - abs(level) - 2 * h
    hi = bounds[1] + abs(level) + 2 * h
    n = np.ceil((hi - lo) / h).astype(int) + 1
    axes = [lo[i] + h * np.arange(n[i]) for i in range(3)]
    G = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    vol = sdf(G).reshape(n) - level
    verts, faces, _, _ = marching_cubes(vol, level=0.0, spacing=(h, h, h), allow_degenerate=False)
    V, F = _clean(verts + lo, faces.astype(np.int64))
    if relax:
        V = _relax(V, F, sdf, level, h, relax)
    return V, F


def _relax(V: np.ndarray, F: np.ndarray, sdf: SDF, level: float, h: float, iters: int) -> np.ndarray:
    """Even out marching-cubes triangles: umbrella smoothing, then projection back onto the level set.

    Marching cubes makes slivers where the surface passes near grid nodes; tet meshers that keep the
    boundary (TetGen) turn those into near-flat tets. Each iteration moves every vertex halfway to
    the mean of its neighbours and takes two Newton steps ``x -= (f(x) - level) ∇f / |∇f|^2``
    (central differences) back onto ``f = level``.
    """
    import scipy.sparse as sp

    n = len(V)
    E = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    A = sp.coo_matrix((np.ones(len(E)), (E[:, 0], E[:, 1])), shape=(n, n)).tocsr()
    A = ((A + A.T) > 0).astype(float)
    deg = np.asarray(A.sum(axis=1)).ravel()
    eps = 1e-3 * h
    offs = np.eye(3) * eps
    for _ in range(iters):
        V = 0.5 * V + 0.5 * (A @ V) / deg[:, None]
        for _ in range(2):
            g = np.stack([(sdf(V + o) - sdf(V - o)) / (2 * eps) for o in offs], axis=1)
            r = sdf(V) - level
            V = V - (r / np.maximum((g * g).sum(axis=1), 1e-12))[:, None] * g
    return V


def _clean(V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge coincident vertices, drop degenerate faces, keep the largest piece, orient outward."""
    import trimesh

    m = trimesh.Trimesh(V, F, process=True, validate=True)
    if len(m.split(only_watertight=False)) > 1:
        parts = m.split(only_watertight=False)
        m = max(parts, key=lambda p: len(p.faces))
    trimesh.repair.fix_normals(m)
    if m.volume < 0:
        m.invert()
    return np.ascontiguousarray(m.vertices, dtype=np.float64), np.ascontiguousarray(m.faces, dtype=np.int64)


def _named(name: str, res: int, level: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    f, b = shape_sdf(name)
    return mesh_implicit(f, b, res=res, level=level)


def sphere(res: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """Unit sphere. Returns ``(V, F)``; ``res`` = grid cells across the bounding box."""
    return _named("sphere", res)


def torus(res: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """Torus (major radius 1, minor 0.35), genus 1. Returns ``(V, F)``."""
    return _named("torus", res)


def genus2(res: int = 56) -> tuple[np.ndarray, np.ndarray]:
    """Two smoothly joined tori: a genus-2 solid. Returns ``(V, F)``."""
    return _named("genus2", res)


def neck_blobs(res: int = 48) -> tuple[np.ndarray, np.ndarray]:
    """Two balls (radius 0.6) joined by a thin neck (radius 0.12). Returns ``(V, F)``."""
    return _named("neck_blobs", res)


def thin_plate(res: int = 60) -> tuple[np.ndarray, np.ndarray]:
    """A thin rounded plate 2 x 1.4 x 0.16. Returns ``(V, F)``."""
    return _named("thin_plate", res)


# ----------------------------------------------------------------------------- articulated shapes
def _capsule_union(segments, radii, blend: float) -> SDF:
    def f(P):
        d = None
        for (a, b), r in zip(segments, radii):
            c = _capsule_sdf(P, a, b, r)
            d = c if d is None else _smooth_min(d, c, blend)
        return d
    return f


def star_of_capsules(res: int = 44):
    """Four capsule arms (radius 0.2, length 1) from a ball of radius 0.4, with its skeleton.

    Returns ``(V, F, S)``; ``S`` is a :class:`cagegen.skeleton.Skeleton`: centre, elbows (bending
    nodes, 0.6 along each arm) and tips.
    """
    from cagegen.skeleton import Skeleton

    arms = [np.array(a, float) for a in ((1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0))]

    def f(P):
        d = np.linalg.norm(P, axis=1) - 0.4
        for a in arms:
            d = _smooth_min(d, _capsule_sdf(P, (0, 0, 0), a, 0.2), 0.08)
        return d

    V, F = mesh_implicit(f, np.array([[-1.25] * 3, [1.25] * 3]), res=res)
    nodes, edges, bend = [np.zeros(3)], [], []
    for a in arms:
        nodes.append(0.6 * a)
        bend.append(len(nodes) - 1)
        edges.append((0, len(nodes) - 1))
        nodes.append(1.0 * a)
        edges.append((len(nodes) - 2, len(nodes) - 1))
    return V, F, Skeleton(np.array(nodes), np.array(edges), bend)


def stick_figure(res: int = 56):
    """Torso, head, two bent arms and two bent legs made of tubes, with its skeleton.

    Returns ``(V, F, S)``; ``S`` is the bones' axes (:class:`cagegen.skeleton.Skeleton`): leaves at
    the capsule end points, the neck a branching node of 4 bones, the pelvis of 3, elbows and knees
    bending nodes.
    """
    from cagegen.skeleton import Skeleton

    J = {
        "pelvis": (0, -0.3, 0), "neck": (0, 0.45, 0), "head": (0, 0.85, 0),
        "elbow_l": (-0.45, 0.25, 0), "hand_l": (-0.75, -0.05, 0),
        "elbow_r": (0.45, 0.25, 0), "hand_r": (0.75, -0.05, 0),
        "knee_l": (-0.2, -0.75, 0.05), "foot_l": (-0.25, -1.2, 0.0),
        "knee_r": (0.2, -0.75, 0.05), "foot_r": (0.25, -1.2, 0.0),
    }
    names = list(J)
    bones = [("pelvis", "neck"), ("neck", "head"), ("neck", "elbow_l"), ("elbow_l", "hand_l"),
             ("neck", "elbow_r"), ("elbow_r", "hand_r"), ("pelvis", "knee_l"), ("knee_l", "foot_l"),
             ("pelvis", "knee_r"), ("knee_r", "foot_r")]
    radii = [0.2, 0.17, 0.1, 0.09, 0.1, 0.09, 0.12, 0.11, 0.12, 0.11]
    f = _capsule_union([(J[a], J[b]) for a, b in bones], radii, 0.06)
    V, F = mesh_implicit(f, np.array([[-1.0, -1.45, -0.35], [1.0, 1.15, 0.35]]), res=res)
    idx = {n: i for i, n in enumerate(names)}
    S = Skeleton(np.array([J[n] for n in names], float), np.array([(idx[a], idx[b]) for a, b in bones]),
                 [idx["elbow_l"], idx["elbow_r"], idx["knee_l"], idx["knee_r"]])
    return V, F, S


def hand(res: int = 56, spacing: float = 0.2, finger_radius: float = 0.08):
    """A palm with four parallel fingers close together (gaps ``spacing - 2 finger_radius``), with its
    skeleton: wrist leaf, palm branching node, finger bases (bending nodes) and tips (leaves).

    Where the fingers meet the palm, M wraps around the concave corners between neighbouring tubes of a
    skeleton cage (the Nested Cages flow stalls there, issue 29). Returns ``(V, F, S)``.
    """
    from cagegen.skeleton import Skeleton

    wrist, palm = (0.0, -0.5, 0.0), (0.0, 0.0, 0.0)
    base = [(x * spacing, 0.15, 0.0) for x in (-1.5, -0.5, 0.5, 1.5)]
    tips = [(x, 0.85, 0.0) for x, _, _ in base]
    segs = [(wrist, palm)] + [(palm, b) for b in base] + list(zip(base, tips))
    f = _capsule_union(segs, [0.2] + [0.12] * 4 + [finger_radius] * 4, 0.04)
    V, F = mesh_implicit(f, np.array([[-0.8, -0.8, -0.3], [0.8, 1.05, 0.3]]), res=res)
    edges = [(0, 1)] + [(1, 2 + i) for i in range(4)] + [(2 + i, 6 + i) for i in range(4)]
    return V, F, Skeleton(np.array([wrist, palm, *base, *tips], float), np.array(edges), [2, 3, 4, 5])


# ----------------------------------------------------------------------------- a CAD-like part
def plate_with_holes(holes: int = 3, segments: int = 16, thickness: float = 0.08, radius: float = 0.3,
                     res: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A flat plate with a row of round through-holes, triangulated as a CAD exporter would (STL).

    The plate is ``holes`` unit squares side by side, each with a hole of ``radius`` (a ``segments``-gon),
    ``thickness`` thick: genus ``holes``. As in an STL export, every flat face is fanned from the square's
    corners (long, thin triangles whose size follows the CAD topology, not the geometry), the side walls
    are one quad (two triangles, aspect ``1 / thickness``) per square side, and the holes' walls one quad
    per segment. Sharp edges everywhere, no vertex inside a flat face. ``res`` is ignored (the CLI's
    ``shape:NAME`` passes one to every shape).

    Returns ``(V, F)``: closed, manifold, outward-oriented, ``2 (holes + 1) + 2 holes segments`` vertices.
    """
    if segments % 4:
        raise NestmgInputError(f"segments must be a multiple of 4, got {segments}")
    q = segments // 4
    corners = [(i, j) for i in range(holes + 1) for j in (0, 1)]  # square corners, shared by neighbours
    cid = {c: k for k, c in enumerate(corners)}
    ang = 2 * np.pi * np.arange(segments) / segments + np.pi / 4  # the first point faces corner (1,1)
    top: list[list[float]] = [[x, y] for x, y in corners]
    circ = []  # per hole: indices of its circle points in `top`
    for h in range(holes):
        c0 = len(top)
        top += [[h + 0.5 + radius * np.cos(a), 0.5 + radius * np.sin(a)] for a in ang]
        circ.append(np.arange(c0, c0 + segments))
    n = len(top)
    T = []  # triangles of the top face (2D indices)
    for h in range(holes):
        # the square's corners counter-clockwise from (1,1), i.e. at 45, 135, 225, 315 degrees
        sq = [cid[(h + 1, 1)], cid[(h, 1)], cid[(h, 0)], cid[(h + 1, 0)]]
        c = circ[h]
        for side in range(4):
            a, b = sq[side], sq[(side + 1) % 4]
            arc = [c[(side * q + k) % segments] for k in range(q + 1)]
            mid = q // 2
            T += [[a, arc[k], arc[k + 1]] for k in range(mid)]  # fan from the side's first corner
            T += [[b, arc[k], arc[k + 1]] for k in range(mid, q)]  # and from its second
            T.append([a, arc[mid], b])
    T = np.array(T)
    P = np.array(top)
    # orient every top triangle counter-clockwise seen from above (+z)
    e1, e2 = P[T[:, 1]] - P[T[:, 0]], P[T[:, 2]] - P[T[:, 0]]
    flip = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0] < 0
    T[flip] = T[flip][:, [0, 2, 1]]
    V = np.vstack([np.c_[P, np.full(n, thickness)], np.c_[P, np.zeros(n)]])
    F = [T, T[:, [0, 2, 1]] + n]  # top (up), bottom (down)

    def wall(i, j):  # the quad over the top edge i -> j (outward when i -> j runs counter-clockwise)
        return [[i, i + n, j], [j, i + n, j + n]]

    outline = ([cid[(i, 0)] for i in range(holes + 1)] + [cid[(holes, 1)]]
               + [cid[(i, 1)] for i in range(holes - 1, -1, -1)])
    for k in range(len(outline)):  # the plate's outline, counter-clockwise seen from above
        F.append(np.array(wall(outline[k], outline[(k + 1) % len(outline)])))
    for c in circ:  # the holes' walls face the hole's axis: clockwise seen from above
        for k in range(segments):
            F.append(np.array(wall(c[(k + 1) % segments], c[k])))
    return V.astype(np.float64), np.vstack(F).astype(np.int64)


SHAPES: dict[str, Callable[..., tuple[np.ndarray, np.ndarray]]] = {
    "sphere": sphere,
    "torus": torus,
    "genus2": genus2,
    "neck_blobs": neck_blobs,
    "thin_plate": thin_plate,
    "plate_holes": plate_with_holes,
}


def nested_isosurfaces(
    name: str, offsets: list[float], resolutions: list[int]
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Iso-surfaces of one shape's implicit function at increasing offsets (finest first).

    Parameters
    ----------
    name : str
        Shape name (see :data:`SHAPES`).
    offsets : list of float
        Increasing iso-values ``d_0 < d_1 < ...``; layer ``i`` is ``sdf = d_i``.
    resolutions : list of int
        Marching-cubes resolution per layer (decreasing for a coarsening hierarchy).

    Returns
    -------
    list of (V, F)
        Finest first. Layer ``i+1`` contains layer ``i`` when ``d_{i+1} - d_i`` exceeds both
        layers' marching-cubes error (about a grid cell squared times the curvature); check with
        :func:`cagegen.verify_nesting`.
    """
    if len(offsets) != len(resolutions):
        raise NestmgInputError("offsets and resolutions must have the same length")
    if np.any(np.diff(offsets) <= 0):
        raise NestmgInputError("offsets must be strictly increasing (coarser layers outside)")
    f, b = shape_sdf(name)
    return [mesh_implicit(f, b, res=r, level=d) for d, r in zip(offsets, resolutions)]


# ----------------------------------------------------------------------------- tet meshes with exact boundary
def _refine_onto(V: np.ndarray, T: np.ndarray, refinements: int, project) -> tuple[list, list]:
    """Red-refine ``refinements`` times, boundary vertices projected after each; every mesh and each P."""
    from solvers.fem import boundary_faces

    from .refine import refine_tets

    meshes, Ps = [(V, T)], []
    for _ in range(refinements):
        V, T, P = refine_tets(V, T)
        bv = np.unique(boundary_faces(T)[0])
        V[bv] = project(V[bv])[0]
        meshes.append((V, T))
        Ps.append(P)
    return meshes[::-1], Ps[::-1]


def ball_tets(refinements: int = 2) -> tuple[list, list]:
    """Tet meshes of the unit ball, every boundary vertex on the sphere: finest first, with prolongations.

    An icosahedron coned to the centre (20 tets), red-refined ``refinements`` times (:mod:`nestmg.refine`),
    new boundary vertices projected radially after each step. The exact linear prolongations between
    consecutive meshes make a ready multigrid hierarchy (``tets, P`` as :class:`nestmg.Hierarchy` has them).

    Returns
    -------
    tets : list of (V (n,3), T (t,4))
        Finest first; the finest has ``20 * 8**refinements`` tets.
    P : list of csr_matrix
    """
    from .curved import sphere_projector
    from .tetmesh import orient_tets

    g = (1 + 5**0.5) / 2
    ico = np.array([[-1, g, 0], [1, g, 0], [-1, -g, 0], [1, -g, 0], [0, -1, g], [0, 1, g], [0, -1, -g],
                    [0, 1, -g], [g, 0, -1], [g, 0, 1], [-g, 0, -1], [-g, 0, 1]], dtype=np.float64)
    ico /= np.linalg.norm(ico, axis=1, keepdims=True)
    from scipy.spatial import ConvexHull

    F = ConvexHull(ico).simplices
    V = np.vstack([[0.0, 0.0, 0.0], ico])
    T = orient_tets(V, np.c_[np.zeros(len(F), dtype=np.int64), F + 1])
    return _refine_onto(V, T, refinements, sphere_projector())


def torus_tets(refinements: int = 1, R: float = 1.0, r: float = 0.35, segments: int = 16) -> tuple[list, list]:
    """Tet meshes of the solid torus (axis z, radii ``R``, ``r``), boundary vertices on the torus; finest first.

    A hexagonal cross-section (6 triangles) swept through ``segments`` prisms, each split into 3 tets
    by the vertex-order rule (conforming), then red-refined with the boundary projected as in
    :func:`ball_tets`.
    """
    from .curved import torus_projector
    from .tetmesh import orient_tets

    ang = np.arange(6) * np.pi / 3
    sec = np.vstack([[0.0, 0.0], np.c_[r * np.cos(ang), r * np.sin(ang)]])  # (7, 2): centre + ring
    tri = np.array([[0, 1 + i, 1 + (i + 1) % 6] for i in range(6)])
    tri = np.sort(tri, axis=1)
    phi = 2 * np.pi * np.arange(segments) / segments
    rho = R + sec[:, 0]
    V = np.stack([np.c_[rho * np.cos(p), rho * np.sin(p), sec[:, 1]] for p in phi]).reshape(-1, 3)
    T = []
    for s in range(segments):
        lo, hi = 7 * s, 7 * ((s + 1) % segments)
        for a, b, c in tri:  # diagonal from the lower bottom vertex to the higher top one: conforming
            T += [[lo + a, lo + b, lo + c, hi + c], [lo + a, lo + b, hi + b, hi + c],
                  [lo + a, hi + a, hi + b, hi + c]]
    T = orient_tets(V, np.array(T, dtype=np.int64))
    return _refine_onto(V, T, refinements, torus_projector(R, r))
