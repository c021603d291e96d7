"""Input audit: is ``(V, F)`` a surface the cage backends and the tet meshers can use?

A cage hierarchy needs a *solid*: a closed, edge- and vertex-manifold, single-piece, consistently and
outward oriented, self-intersection-free triangle mesh with finite coordinates, no zero-area faces
and no coincident vertices. :func:`audit_mesh` measures all of that and lists every problem;
:func:`check_mesh` raises :class:`~cagegen.errors.MeshInputError` naming them (after optional
repairs); :func:`repair_mesh` applies the safe repairs and returns new arrays.

Every check is vectorised (edge keys through ``np.unique``, a k-d tree for coincident vertices,
libigl for vertex manifoldness and the exact self-intersection test of :mod:`cagegen.intersect`).

Example
-------
>>> import numpy as np
>>> from cagegen.audit import audit_mesh
>>> V = np.array([[0., 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
>>> F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
>>> audit_mesh(V, F).ok
True
>>> [p.split(":")[0] for p in audit_mesh(V, F[:3]).problems]
['too few faces', 'open boundary']
"""

from __future__ import annotations

import dataclasses
from dataclasses import asdict, dataclass, field

import numpy as np

from ._geometry import (
    as_mesh_arrays,
    bbox_diagonal,
    double_areas,
    edge_stats,
    n_components,
    self_intersection_pairs,
    signed_volume,
)
from .errors import CageOptionError, MeshInputError

__all__ = ["MeshAudit", "audit_mesh", "audit_self_intersections", "check_mesh", "flip_cap_faces", "repair_mesh"]

# Defaults, all relative to the bounding-box diagonal ``d`` of the mesh.
MERGE_TOL = 1e-10  # vertices closer than MERGE_TOL * d are "coincident"
AREA_TOL = 1e-10  # faces with 2*area < AREA_TOL * (longest edge)**2 are "degenerate" (collinear)
VOLUME_TOL = 1e-12  # |volume| < VOLUME_TOL * d**3 is "zero volume"
MIN_DIAG, MAX_DIAG = 1e-8, 1e8  # absurd scales (float64 geometry predicates lose meaning)
MAX_OFFSET = 1e6  # max |coordinate| / d beyond which the mesh is too far from the origin
MAX_FACES = 5_000_000


@dataclass
class MeshAudit:
    """Everything :func:`audit_mesh` measured about one surface.

    Counts that could not be measured (e.g. geometric figures of a mesh with NaN coordinates, or the
    self-intersection test when it was switched off) are ``None``; ``skipped`` says why.

    Attributes
    ----------
    name : str
    n_vertices, n_faces : int
    bbox_diagonal : float or None
    n_nonfinite_vertices : int
        Vertices with a NaN or infinite coordinate.
    n_degenerate_faces : int or None
        Faces with a repeated index or (near-)zero area.
    n_duplicate_vertices : int or None
        Vertices that would disappear by merging coincident positions.
    n_unreferenced_vertices : int
        Vertices used by no face.
    n_boundary_edges, n_nonmanifold_edges, n_inconsistent_edges : int
        Edges with one face, with three or more faces, and two-face edges traversed twice in the same
        direction.
    n_nonmanifold_vertices : int
        Referenced vertices whose incident faces do not form a single fan.
    n_components : int
        Edge-connected pieces.
    volume : float or None
        Signed enclosed volume (only for closed, consistently oriented meshes with finite coordinates).
    genus : int or None
        Genus of a closed manifold single-component surface.
    n_self_intersections : int or None
        Intersecting face pairs (exact test, :mod:`cagegen.intersect`).
    problems : list of str
        One human-readable line per problem; empty when the mesh is usable.
    skipped : list of str
        Checks that were not run, with the reason.
    """

    name: str
    n_vertices: int
    n_faces: int
    bbox_diagonal: float | None = None
    n_nonfinite_vertices: int = 0
    n_degenerate_faces: int | None = None
    n_duplicate_vertices: int | None = None
    n_unreferenced_vertices: int = 0
    n_boundary_edges: int = 0
    n_nonmanifold_edges: int = 0
    n_nonmanifold_vertices: int = 0
    n_inconsistent_edges: int = 0
    n_components: int = 0
    volume: float | None = None
    genus: int | None = None
    n_self_intersections: int | None = None
    problems: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        """True when no problem was found."""
        return not self.problems

    def to_dict(self) -> dict:
        """JSON-serialisable dict of every field plus ``ok``."""
        d = asdict(self)
        d["ok"] = self.ok
        return d

    def raise_if_failed(self) -> None:
        """Raise :class:`MeshInputError` listing every problem, if there is any."""
        if self.problems:
            lines = "\n  - ".join(self.problems)
            raise MeshInputError(f"{self.name} is not a usable closed surface:\n  - {lines}")

    def __str__(self) -> str:
        head = f"MeshAudit({self.name!r}: {self.n_vertices} vertices, {self.n_faces} faces"
        if self.genus is not None:
            head += f", genus {self.genus}"
        if self.volume is not None:
            head += f", volume {self.volume:.6g}"
        head += ")"
        if self.ok:
            return head + ": ok"
        return head + ":\n  - " + "\n  - ".join(self.problems)


def _duplicate_labels(V: np.ndarray, tol: float) -> np.ndarray:
    """Label each vertex by the smallest index among the vertices within ``tol`` of it (transitively)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    n = V.shape[0]
    pairs = cKDTree(V).query_pairs(r=tol, output_type="ndarray") if tol > 0 else np.empty((0, 2), int)
    if tol == 0 or pairs.size == 0:
        # exact coincidences are still duplicates when tol == 0
        _, first, inv = np.unique(V, axis=0, return_index=True, return_inverse=True)
        return first[inv.ravel()]
    A = sp.coo_matrix((np.ones(len(pairs), np.int8), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, comp = connected_components(A, directed=False)
    rep = np.full(comp.max() + 1, n, dtype=np.int64)
    np.minimum.at(rep, comp, np.arange(n))
    return rep[comp]


def audit_mesh(
    V,
    F,
    *,
    name: str = "input",
    self_intersections: bool = True,
    merge_tol: float = MERGE_TOL,
    area_tol: float = AREA_TOL,
    max_faces: int = MAX_FACES,
) -> MeshAudit:
    """Measure every property a closed input surface must have and list the problems.

    Parameters
    ----------
    V : (n,3) array_like of float
        Vertex positions.
    F : (m,3) array_like of int
        Triangles (indices into ``V``).
    name : str
        Name used in the messages.
    self_intersections : bool
        Run the exact self-intersection test (:mod:`cagegen.intersect`; ~1 s per 10k faces).
    merge_tol : float
        Vertices closer than ``merge_tol`` times the bounding-box diagonal count as duplicates.
    area_tol : float
        Faces whose height is below ``area_tol`` times their longest edge (``2 * area < area_tol *
        longest**2``: collinear corners up to rounding) are degenerate, as are faces with a repeated
        index or all corners within ``merge_tol`` of each other. The test is scale-free: thin but
        valid slivers from marching cubes (height ~1% of the longest edge) pass.
    max_faces : int
        Larger meshes are refused as absurdly large (decimate them first).

    Returns
    -------
    MeshAudit
        ``audit.ok`` is True when the mesh is usable; ``audit.problems`` lists the problems.

    Raises
    ------
    MeshInputError
        Only for structural problems that make every other check impossible: non-arrays, wrong
        shapes or dtypes, empty arrays, face indices out of range.
    """
    V, F = as_mesh_arrays(V, F, name)
    m = F.shape[0]
    a = MeshAudit(name=name, n_vertices=V.shape[0], n_faces=m)
    if m < 4:
        a.problems.append(f"too few faces: {m} (a closed triangle mesh has at least 4)")
    if m > max_faces:
        a.problems.append(f"absurd size: {m} faces > max_faces={max_faces}; decimate the input first")
    d = _audit_scale(a, V)
    _audit_faces(a, V, F, d, area_tol=area_tol, merge_tol=merge_tol)
    referenced = _audit_vertices(a, V, F, d, merge_tol=merge_tol)
    es = _audit_topology(a, F, referenced)
    _audit_volume_genus(a, V, F, d, es, referenced)
    if not self_intersections:
        a.skipped.append(_SI_OFF)
    else:
        _audit_self_intersections(a, V, F, d is not None)
    return a


#: :attr:`MeshAudit.skipped`'s entry of an audit made with ``self_intersections=False``
_SI_OFF = "self-intersections (switched off)"


def _audit_self_intersections(a: MeshAudit, V: np.ndarray, F: np.ndarray, geometric: bool) -> None:
    """The exact self-intersection test, recorded in ``a`` (skipped without the geometric checks or with
    degenerate faces)."""
    if not geometric or a.n_degenerate_faces:
        a.skipped.append("self-intersections (non-finite coordinates or degenerate faces)")
        return
    pairs = self_intersection_pairs(V, F)
    a.n_self_intersections = len(pairs)
    if len(pairs):
        a.problems.append(f"self-intersections: {len(pairs)} intersecting face pairs (first: {pairs[0].tolist()})")


def audit_self_intersections(audit: MeshAudit, V, F) -> MeshAudit:
    """Complete an audit made with ``self_intersections=False``: a copy of ``audit`` with the exact
    self-intersection test of ``(V, F)`` added, as :func:`audit_mesh` with the test would have it.

    A caller that decides from the cheap checks whether it needs the test at all (a scan whose only
    problem is an open boundary is mended first, and the mended surface is tested) pays for it once.

    Parameters
    ----------
    audit : MeshAudit
        ``audit_mesh(V, F, self_intersections=False, ...)`` of exactly these arrays.
    V : (n,3) array_like of float
    F : (m,3) array_like of int

    Returns
    -------
    MeshAudit
        A new audit (``audit`` is not modified).

    Raises
    ------
    CageOptionError
        If ``audit`` was not made with the test switched off, or is of arrays of another size.
    """
    V, F = as_mesh_arrays(V, F, audit.name)
    if _SI_OFF not in audit.skipped or (audit.n_vertices, audit.n_faces) != (len(V), len(F)):
        raise CageOptionError(f"audit_self_intersections needs an audit of these {len(V)} vertices and {len(F)} "
                              f"faces made with self_intersections=False, got {audit!r}")
    a = dataclasses.replace(audit, problems=list(audit.problems),
                            skipped=[s for s in audit.skipped if s != _SI_OFF])
    # the geometric checks ran when the coordinates were finite and of a sane size (a scratch audit: no copy)
    _audit_self_intersections(a, V, F, _audit_scale(MeshAudit(a.name, len(V), len(F)), V) is not None)
    return a


def _audit_scale(a: MeshAudit, V: np.ndarray) -> float | None:
    """Non-finite coordinates and absurd scales; the bounding-box diagonal where the geometric checks make
    sense (finite coordinates, diagonal in ``[MIN_DIAG, MAX_DIAG]``: beyond it their tolerances over- or
    underflow), else None."""
    P = a.problems
    finite_rows = np.isfinite(V).all(axis=1)
    a.n_nonfinite_vertices = int(V.shape[0] - np.count_nonzero(finite_rows))
    if a.n_nonfinite_vertices:
        bad = np.flatnonzero(~finite_rows)[:5].tolist()
        P.append(f"NaN or infinite coordinates in {a.n_nonfinite_vertices} vertices (first: {bad})")
        a.skipped.append("geometric checks (non-finite coordinates)")
        return None
    d = bbox_diagonal(V)
    a.bbox_diagonal = d
    offset = float(np.abs(V).max())
    if d == 0.0:
        P.append("absurd size: all vertices coincide (zero bounding box)")
    elif not (MIN_DIAG <= d <= MAX_DIAG):
        P.append(f"absurd size: bounding-box diagonal {d:.3g} outside [{MIN_DIAG:g}, {MAX_DIAG:g}]; rescale")
    elif offset > MAX_OFFSET * d:
        P.append(
            f"absurd size: mesh of diagonal {d:.3g} sits {offset:.3g} from the origin "
            "(float64 precision lost); translate it"
        )
    if not MIN_DIAG <= d <= MAX_DIAG:
        a.skipped.append("geometric checks (absurd size)")
        return None
    return d


def _audit_faces(a: MeshAudit, V: np.ndarray, F: np.ndarray, d: float | None, *, area_tol: float,
                 merge_tol: float) -> None:
    """Degenerate faces: a repeated index and, at a sane scale ``d``, (near-)zero area or all corners
    within ``merge_tol * d``."""
    degenerate = (F[:, 0] == F[:, 1]) | (F[:, 1] == F[:, 2]) | (F[:, 2] == F[:, 0])
    if d is not None:
        E = V[F[:, [1, 2, 0]]] - V[F]  # (m,3,3) edge vectors
        longest2 = np.einsum("ijk,ijk->ij", E, E).max(axis=1)
        degenerate = (
            degenerate
            | (double_areas(V, F) < area_tol * longest2)
            | (longest2 <= (merge_tol * d) ** 2)
        )
    a.n_degenerate_faces = int(np.count_nonzero(degenerate))
    if a.n_degenerate_faces:
        first = np.flatnonzero(degenerate)[:5].tolist()
        a.problems.append(f"degenerate (zero-area) faces: {a.n_degenerate_faces} (first: {first}; "
                          "repair=True / --repair flips the caps of STL exports)")


def _audit_vertices(a: MeshAudit, V: np.ndarray, F: np.ndarray, d: float | None, *,
                    merge_tol: float) -> np.ndarray:
    """Unreferenced vertices and, at a sane scale ``d``, duplicates; returns the (n,) referenced mask."""
    n = V.shape[0]
    referenced = np.zeros(n, dtype=bool)
    referenced[F.ravel()] = True
    a.n_unreferenced_vertices = int(n - np.count_nonzero(referenced))
    if a.n_unreferenced_vertices:
        a.problems.append(
            f"unreferenced vertices: {a.n_unreferenced_vertices} used by no face "
            "(repair=True drops them)"
        )
    if d is not None:
        labels = _duplicate_labels(V, merge_tol * d)
        a.n_duplicate_vertices = int(n - np.unique(labels).size)
        if a.n_duplicate_vertices:
            a.problems.append(
                f"duplicate vertices: {a.n_duplicate_vertices} vertices coincide with another "
                "(repair=True merges them)"
            )
    return referenced


def _audit_topology(a: MeshAudit, F: np.ndarray, referenced: np.ndarray):
    """Boundary, non-manifold and inconsistently oriented edges, non-manifold vertices, components;
    returns the edge statistics (:func:`cagegen._geometry.edge_stats`)."""
    import igl

    P, n = a.problems, referenced.size
    es = edge_stats(F, n)
    a.n_boundary_edges = es.n_boundary_edges
    a.n_nonmanifold_edges = es.n_nonmanifold_edges
    a.n_inconsistent_edges = es.n_inconsistent_edges
    if es.n_boundary_edges:
        P.append(f"open boundary: {es.n_boundary_edges} boundary edges (the surface must be closed)")
    if es.n_nonmanifold_edges:
        P.append(f"non-manifold edges: {es.n_nonmanifold_edges} edges shared by 3 or more faces")
    if es.n_inconsistent_edges:
        P.append(
            f"inconsistent orientation: {es.n_inconsistent_edges} edges traversed twice in the same "
            "direction (repair=True re-orients)"
        )
    manifold_v = np.ones(n, dtype=bool)
    mv = np.asarray(igl.is_vertex_manifold(F), dtype=bool)  # length max(F)+1
    manifold_v[: mv.size] = mv
    a.n_nonmanifold_vertices = int(np.count_nonzero(~manifold_v & referenced))
    if a.n_nonmanifold_vertices:
        P.append(f"non-manifold vertices: {a.n_nonmanifold_vertices} vertices where several fans meet")
    a.n_components = n_components(F, n)
    if a.n_components > 1:
        P.append(
            f"several connected components: {a.n_components} (a single closed piece is required; "
            "build_cages(..., components='separate') builds one hierarchy per piece)"
        )
    return es


def _audit_volume_genus(a: MeshAudit, V: np.ndarray, F: np.ndarray, d: float | None, es,
                        referenced: np.ndarray) -> None:
    """Signed volume (at a sane scale ``d``) and genus (one component), for closed, manifold and
    consistently oriented surfaces only; genus from the Euler characteristic ``V - E + F = 2 - 2g``."""
    if not (es.closed_manifold and a.n_nonmanifold_vertices == 0):
        a.skipped.append("volume and genus (surface not closed, manifold and consistently oriented)")
        return
    if d is not None:
        a.volume = signed_volume(V, F)
        if abs(a.volume) <= VOLUME_TOL * d**3:
            a.problems.append(f"zero volume: enclosed volume {a.volume:.3g} (flat or collapsed surface)")
        elif a.volume < 0:
            a.problems.append(
                f"inside-out: negative volume {a.volume:.6g}, the faces point inward "
                "(repair=True flips them)"
            )
    if a.n_components == 1:
        chi = int(np.count_nonzero(referenced)) - es.n_edges + F.shape[0]
        a.genus = (2 - chi) // 2


def repair_mesh(
    V,
    F,
    *,
    merge_duplicates: bool = True,
    drop_unreferenced: bool = True,
    orient_outward: bool = True,
    merge_tol: float = MERGE_TOL,
    flip_caps: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Apply the safe repairs and return new arrays (the inputs are never modified).

    Parameters
    ----------
    V : (n,3) array_like of float
    F : (m,3) array_like of int
    merge_duplicates : bool
        Merge vertices closer than ``merge_tol`` times the bounding-box diagonal (keeping the
        lowest index) and drop the faces that collapse to a repeated index.
    drop_unreferenced : bool
        Remove vertices used by no face and re-index ``F``.
    orient_outward : bool
        Make each connected component consistently oriented (breadth-first, ``igl.bfs_orient``), then
        flip the components whose signed volume is negative.
    merge_tol : float
    flip_caps : bool
        Flip the longest edge of each *cap* (a face whose third corner lies on its longest edge, zero
        area: STL exports of CAD parts have them) with the neighbouring face across it
        (:func:`flip_cap_faces`): the surface is the same point set, without the zero-area face.

    Returns
    -------
    V : (n',3) float64 array
    F : (m',3) int64 array
    """
    V, F = as_mesh_arrays(V, F, "input")
    d = bbox_diagonal(V) if np.isfinite(V).all() else float("nan")
    if merge_duplicates and MIN_DIAG <= d <= MAX_DIAG:  # an absurd size is left for the audit to report
        rep = _duplicate_labels(V, merge_tol * d)
        F = rep[F]
        keep = (F[:, 0] != F[:, 1]) & (F[:, 1] != F[:, 2]) & (F[:, 2] != F[:, 0])
        F = F[keep]
        if F.shape[0] == 0:
            raise MeshInputError("input: merging duplicate vertices left no face")
    if drop_unreferenced:
        used = np.unique(F)
        remap = np.full(V.shape[0], -1, dtype=np.int64)
        remap[used] = np.arange(used.size)
        V = V[used]
        F = remap[F]
    if flip_caps and np.isfinite(V).all():
        F = flip_cap_faces(V, F)
    if orient_outward:
        import igl

        es = edge_stats(F, V.shape[0])
        if es.n_inconsistent_edges and es.n_nonmanifold_edges == 0:
            F, _ = igl.bfs_orient(F)
            F = np.asarray(F, dtype=np.int64)
        _, comp = igl.facet_components(F)
        comp = np.asarray(comp)
        c = V.mean(axis=0)
        vol_f = np.einsum("ij,ij->i", V[F[:, 0]] - c, np.cross(V[F[:, 1]] - c, V[F[:, 2]] - c))
        vol_c = np.bincount(comp, weights=vol_f)
        flip = vol_c[comp] < 0
        F = F.copy()
        F[flip] = F[flip][:, ::-1]
    return np.ascontiguousarray(V, dtype=np.float64), np.ascontiguousarray(F, dtype=np.int64)


def check_mesh(
    V,
    F,
    *,
    repair: bool = False,
    name: str = "input",
    self_intersections: bool = True,
    return_audit: bool = False,
    **tols,
):
    """Validate a closed input surface; raise :class:`MeshInputError` naming every problem.

    Parameters
    ----------
    V : (n,3) array_like of float
    F : (m,3) array_like of int
    repair : bool
        First merge duplicate vertices, drop unreferenced vertices and orient outward
        (:func:`repair_mesh`), then audit the result.
    name : str
        Name used in the messages.
    self_intersections : bool
        Include the exact self-intersection test.
    return_audit : bool
        Also return the :class:`MeshAudit`.
    **tols
        ``merge_tol``, ``area_tol``, ``max_faces`` of :func:`audit_mesh`.

    Returns
    -------
    V : (n',3) float64 array
    F : (m',3) int64 array
        New arrays (repaired if ``repair``); the inputs are never modified.
    audit : MeshAudit
        Only with ``return_audit=True``.

    Raises
    ------
    MeshInputError
        The message lists each problem (open boundary, NaN, duplicate vertices, ...).
    """
    if repair:
        V, F = repair_mesh(V, F, merge_tol=tols.get("merge_tol", MERGE_TOL))
    else:
        V, F = as_mesh_arrays(V, F, name)
    audit = audit_mesh(V, F, name=name, self_intersections=self_intersections, **tols)
    audit.raise_if_failed()
    return (V, F, audit) if return_audit else (V, F)


def flip_cap_faces(V: np.ndarray, F: np.ndarray, area_tol: float = AREA_TOL, max_rounds: int = 10) -> np.ndarray:
    """Remove zero-area *caps* by edge flips, leaving the surface the same point set.

    A cap ``(a, b, c)`` has ``c`` on its longest edge ``ab``. With the face ``(b, a, d)`` across ``ab``,
    the pair becomes ``(b, c, d)``, ``(c, a, d)``: the neighbour split at ``c``, so the union of the two
    faces is unchanged and the cap is gone. Faces with a repeated vertex, caps on a boundary or a
    non-manifold edge, and flips that would create an existing edge are left for the audit to report.

    Parameters
    ----------
    V : (n,3) float array
    F : (m,3) int array
    area_tol : float
        A face is a cap when ``2 area < area_tol * longest_edge**2`` (:data:`AREA_TOL`, as the audit).
    max_rounds : int
        Rounds of flips (a flip may leave a neighbouring cap for the next round).

    Returns
    -------
    (m,3) int64 array
        The new faces (a copy; same count, same orientation).
    """
    F = np.array(F, dtype=np.int64)
    for _ in range(max_rounds):
        E = V[F[:, [1, 2, 0]]] - V[F]  # edge k runs from corner k to corner k+1
        L2 = np.einsum("ijk,ijk->ij", E, E)
        caps = np.flatnonzero((double_areas(V, F) < area_tol * L2.max(axis=1))
                              & (F[:, 0] != F[:, 1]) & (F[:, 1] != F[:, 2]) & (F[:, 2] != F[:, 0]))
        if caps.size == 0:
            break
        # directed half-edge (u, v) -> face
        half = {(int(F[f, k]), int(F[f, (k + 1) % 3])): f for f in range(len(F)) for k in range(3)}
        edges = {tuple(sorted(h)) for h in half}
        touched, n_flipped = set(), 0
        for f in caps:
            if f in touched:
                continue
            k = int(np.argmax(L2[f]))
            a, b, c = int(F[f, k]), int(F[f, (k + 1) % 3]), int(F[f, (k + 2) % 3])
            g = half.get((b, a))
            if g is None or g in touched or g == f:
                continue
            d = int(next(x for x in F[g] if x not in (a, b)))
            if tuple(sorted((c, d))) in edges or c == d:
                continue
            F[f], F[g] = (b, c, d), (c, a, d)
            edges.add(tuple(sorted((c, d))))
            touched.update((f, g))
            n_flipped += 1
        if n_flipped == 0:
            break
    return F
