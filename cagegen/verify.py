"""Nesting verifier: does each cage strictly contain the previous (finer) layer?

Containment rule
----------------
Let ``S_f`` (fine) and ``S_c`` (coarse) be closed, oriented, self-intersection-free surfaces
bounding the solids ``Ω_f`` and ``Ω_c``. The pair is certified *nested* (``Ω_f ⊂ interior Ω_c``)
when all of the following hold:

1. **No crossing**: no triangle of ``S_f`` intersects or touches a triangle of ``S_c`` (exact
   decision: :mod:`cagegen.intersect`'s filtered predicates by default, which also count pairs that
   touch to within rounding as touching; ``intersection_engine="cgal"`` uses the GPL
   ``igl.copyleft.cgal.intersect_other`` instead). Touching counts as failing: a contact has zero
   gap, which tet meshers and point location cannot tell from a crossing.
2. **Fine inside coarse**: every fine vertex has generalized winding number ``w_c >= 1/2`` with
   respect to ``S_c`` (``igl.winding_number``, hierarchical but exact).
3. **Coarse outside fine**: every coarse vertex has ``w_f < 1/2`` with respect to ``S_f``.

Why this suffices: given (1), each connected piece of ``S_f`` avoids ``S_c``, so it lies in a single
region of ``R^3 \\ S_c`` where the winding number is a constant *integer* -- (2) then puts it
inside ``Ω_c``. By the same argument (3) keeps every piece of ``S_c`` out of ``Ω_f`` (this catches
a coarse layer with an inner cavity hidden inside the fine solid, which (1)+(2) alone accept).
Then ``Ω_f`` is a bounded set whose boundary lies in the interior of ``Ω_c`` and which contains no
point of ``S_c``: it cannot reach the outside of ``Ω_c``.

So (2) and (3) need one vertex per connected piece: when (1) holds, each piece's winding number is
summed directly (signed solid angles) at its vertex farthest from the other surface and stands for all
of its vertices; every vertex is evaluated when (1) fails, for the report. Because of (1) the winding
numbers of the tested vertices are integers (1 inside, 0 outside), so the ``1/2`` thresholds leave a
margin of 1/2 for rounding. The reference nested cages come within ~2e-6 of the diagonal of the input,
so the every-vertex evaluation must stay accurate for points almost on the other surface: libigl's exact
``igl.winding_number`` does (measured: 1 +- 1e-13 for a sphere inside a copy scaled by 1 + 1e-13),
whereas the Barnes-Hut ``igl.fast_winding_number`` returned 0.25 for points 1e-8 of the diagonal
inside. The exact evaluation is the default (``exact_winding=True``); the fast one (~6x faster) is an
option for surfaces known to be well separated. A vertex *on* the other surface has winding 1/2, but it
is already reported by (1).

The report also gives the gap between the surfaces. The distance between two disjoint triangle
meshes is attained at a vertex-face or an edge-edge pair: the first part is
``igl.point_mesh_squared_distance`` both ways, the second is searched (k-d tree on edge midpoints,
vectorised segment-segment distances) below ``max(min_gap, 1e-3)`` of the diagonal, where it is
cheap. So gaps under that threshold -- the near-touching regime that matters -- are exact, larger
ones are the vertex-face figure (an upper bound, flagged by ``min_gap_exact=False``). ``min_gap``
(relative to the bounding-box diagonal of layer 0) lets a caller demand clearance, e.g. for a tet
mesher whose boundary is only within ``epsilon`` of its input; the check is exact.

Each layer must also be closed (every edge with two faces) and, with ``check_self``, free of
self-intersections; otherwise winding numbers lose their meaning.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field

import numpy as np

from ._geometry import (
    _engine,
    as_mesh_arrays,
    bbox_diagonal,
    cross_intersection_pairs,
    edge_stats,
    min_edge_edge_distance,
    self_intersection_pairs,
    signed_volume,
    vertex_components,
)
from .errors import CageError, CageOptionError, MeshInputError

__all__ = ["NestingReport", "PairReport", "verify_nesting"]

WINDING_THRESHOLD = 0.5
#: gaps below this fraction of the diagonal (or below ``min_gap``) are computed exactly (edge-edge too)
EXACT_GAP_BELOW = 1e-3


@dataclass
class PairReport:
    """Nesting figures of one consecutive pair (fine layer ``fine``, coarse layer ``fine + 1``).

    Attributes
    ----------
    fine : int
        Index of the fine layer (0 = input); the coarse layer is ``fine + 1``.
    n_faces_fine, n_faces_coarse : int
    min_winding : float
        Smallest winding number of a fine vertex w.r.t. the coarse surface (1 when nested; when the
        surfaces do not cross, each connected piece's value, evaluated at one of its vertices).
    n_outside_vertices : int
        Fine vertices with winding < 1/2 w.r.t. the coarse surface.
    n_coarse_inside_vertices : int
        Coarse vertices with winding >= 1/2 w.r.t. the fine surface.
    n_intersecting_pairs : int
        Intersecting or touching (fine face, coarse face) pairs, exact.
    min_gap : float
        Distance between the two surfaces (0 when they intersect or touch): vertex-to-surface both
        ways, refined by edge-edge distances below ``max(min_gap, 1e-3)`` of the diagonal.
    min_gap_exact : bool
        True when ``min_gap`` is the exact surface distance (always when it is below that threshold);
        otherwise it is the vertex-to-surface distance, an upper bound.
    min_gap_rel : float
        ``min_gap`` divided by the bounding-box diagonal of layer 0.
    self_intersections_fine, self_intersections_coarse : int or None
        Self-intersecting face pairs in each layer (None when ``check_self=False``).
    boundary_edges_fine, boundary_edges_coarse : int
        Open edges in each layer (must be 0).
    volume_fine, volume_coarse : float
        Signed volumes (negative = inside-out).
    seconds : float
        Wall time of this pair's checks.
    ok : bool
    reason : str
        Empty when ``ok``; otherwise every failed condition, naming the layers.
    """

    fine: int
    n_faces_fine: int
    n_faces_coarse: int
    min_winding: float = float("nan")
    n_outside_vertices: int = 0
    n_coarse_inside_vertices: int = 0
    n_intersecting_pairs: int = 0
    min_gap: float = float("nan")
    min_gap_rel: float = float("nan")
    min_gap_exact: bool = False
    self_intersections_fine: int | None = None
    self_intersections_coarse: int | None = None
    boundary_edges_fine: int = 0
    boundary_edges_coarse: int = 0
    volume_fine: float = float("nan")
    volume_coarse: float = float("nan")
    seconds: float = 0.0
    ok: bool = False
    reason: str = ""
    failing_layer: int | None = None

    @property
    def coarse(self) -> int:
        """Index of the coarse layer."""
        return self.fine + 1


@dataclass
class NestingReport:
    """Result of :func:`verify_nesting` over a hierarchy, finest first.

    Attributes
    ----------
    ok : bool
        Every consecutive pair is nested.
    pairs : list of PairReport
        One entry per consecutive pair ``(i, i+1)``.
    bbox_diagonal : float
        Bounding-box diagonal of layer 0 (the unit of ``min_gap_rel``).
    min_gap_required : float
        The ``min_gap`` the pairs were held to (relative).
    seconds : float
        Total wall time.
    """

    ok: bool
    pairs: list[PairReport] = field(default_factory=list)
    bbox_diagonal: float = float("nan")
    min_gap_required: float = 0.0
    seconds: float = 0.0

    def first_failure(self) -> PairReport | None:
        """The first failing pair, or None."""
        return next((p for p in self.pairs if not p.ok), None)

    def raise_if_failed(self) -> None:
        """Raise :class:`CageError` for the first failing pair, naming the layer and the reason."""
        p = self.first_failure()
        if p is None:
            return
        layer = p.failing_layer if p.failing_layer is not None else p.coarse
        raise CageError(f"nesting check failed at layer {layer}: {p.reason}", layer=layer, reason=p.reason)

    def to_dict(self) -> dict:
        """JSON-serialisable dict (NaN and inf become None)."""

        def clean(x):
            if isinstance(x, float) and not np.isfinite(x):
                return None
            if isinstance(x, dict):
                return {k: clean(v) for k, v in x.items()}
            if isinstance(x, list):
                return [clean(v) for v in x]
            return x

        d = {
            "ok": bool(self.ok),
            "bbox_diagonal": self.bbox_diagonal,
            "min_gap_required": self.min_gap_required,
            "seconds": self.seconds,
            "pairs": [asdict(p) for p in self.pairs],
        }
        return clean(d)

    def __str__(self) -> str:
        hdr = (
            f"{'pair':>6} {'faces':>13} {'min_w':>7} {'out':>6} {'c_in':>5} {'cross':>6} "
            f"{'self f/c':>9} {'gap_rel':>9} {'sec':>6}  ok"
        )
        title = f"NestingReport: {'nested' if self.ok else 'NOT nested'} ({len(self.pairs)} pairs, {self.seconds:.2f} s)"
        rows = [title, hdr]
        for p in self.pairs:
            sf = "-" if p.self_intersections_fine is None else str(p.self_intersections_fine)
            sc = "-" if p.self_intersections_coarse is None else str(p.self_intersections_coarse)
            rows.append(
                f"{p.fine:>2}->{p.coarse:<3} {p.n_faces_fine:>6}/{p.n_faces_coarse:<6} {p.min_winding:7.3f} "
                f"{p.n_outside_vertices:>6} {p.n_coarse_inside_vertices:>5} {p.n_intersecting_pairs:>6} "
                f"{sf + '/' + sc:>9} {p.min_gap_rel:9.2e} {p.seconds:6.2f}  {'yes' if p.ok else 'NO'}"
            )
            if not p.ok:
                rows.append(f"       reason: {p.reason}")
        return "\n".join(rows)


@dataclass
class _Layer:
    V: np.ndarray
    F: np.ndarray
    finite: bool
    boundary_edges: int
    nonmanifold_edges: int
    volume: float
    self_pairs: int | None


def _prepare(i: int, V, F, check_self: bool, engine: str | None = None, audited: bool = False) -> _Layer:
    try:
        V, F = as_mesh_arrays(V, F, f"layer {i}")
    except MeshInputError as exc:
        raise CageError(str(exc), layer=i, reason=str(exc)) from exc
    finite = bool(np.isfinite(V).all())
    es = edge_stats(F, V.shape[0])
    vol = signed_volume(V, F) if finite else float("nan")
    self_pairs = None
    if check_self and finite:
        # an audited layer passed check_mesh's exact test on these arrays: no pair, not tested again
        self_pairs = 0 if audited else len(self_intersection_pairs(V, F, engine))
    return _Layer(V, F, finite, es.n_boundary_edges, es.n_nonmanifold_edges, vol, self_pairs)


def _piece_winding(winding, surface: _Layer, query: _Layer, d2: np.ndarray | None) -> np.ndarray:
    """Winding numbers of ``query``'s vertices with respect to ``surface``.

    ``d2`` (squared distances of ``query``'s vertices to ``surface``) is given when the two closed
    surfaces neither cross nor touch (rule 1): then each connected piece of ``query`` lies in one region of
    ``R^3 \\ surface``, where the winding number is a constant integer (the module's argument), so it is
    evaluated at one vertex per piece, the farthest from ``surface`` (the evaluation most accurate), and
    given to the whole piece. Otherwise (diagnostics of a failing pair) every vertex is evaluated.
    """
    if d2 is None:
        return np.asarray(winding(surface.V, surface.F, query.V), dtype=float)
    label = vertex_components(query.F, query.V.shape[0])
    order = np.lexsort((-d2, label))  # by piece, farthest first
    first = order[np.r_[0, np.flatnonzero(np.diff(label[order])) + 1]]
    if len(first) <= DIRECT_WINDING_POINTS:
        w = np.array([_solid_angle_sum(surface.V, surface.F, q) for q in query.V[first]])
    else:
        w = np.asarray(winding(surface.V, surface.F, query.V[first]), dtype=float)
    return w[label]


#: up to this many query points, winding numbers are summed directly (:func:`_solid_angle_sum`, ~4 ms a
#: point on 30k faces) instead of by ``igl.winding_number``, whose hierarchy costs ~70 ms a call there
DIRECT_WINDING_POINTS = 16


def _solid_angle_sum(V: np.ndarray, F: np.ndarray, q: np.ndarray) -> float:
    """Generalized winding number of the point ``q`` w.r.t. the triangles ``(V, F)``: the sum of their
    signed solid angles over 4π, each by Van Oosterom & Strackee's formula (1983), as libigl's exact
    ``winding_number`` evaluates a triangle (accurate away from the surface)."""
    a, b, c = (V[F[:, k]] - q for k in range(3))
    la, lb, lc = (np.linalg.norm(x, axis=1) for x in (a, b, c))
    det = np.einsum("ij,ij->i", a, np.cross(b, c))
    den = (la * lb * lc + np.einsum("ij,ij->i", a, b) * lc + np.einsum("ij,ij->i", b, c) * la
           + np.einsum("ij,ij->i", c, a) * lb)
    return float(np.arctan2(det, den).sum() / (2.0 * np.pi))


def _check_pair(
    i: int, f: _Layer, c: _Layer, diag: float, min_gap: float, exact_winding: bool, engine: str | None = None
) -> PairReport:
    import igl

    winding = igl.winding_number if exact_winding else igl.fast_winding_number

    t0 = time.perf_counter()
    p = PairReport(
        fine=i,
        n_faces_fine=int(f.F.shape[0]),
        n_faces_coarse=int(c.F.shape[0]),
        self_intersections_fine=f.self_pairs,
        self_intersections_coarse=c.self_pairs,
        boundary_edges_fine=f.boundary_edges,
        boundary_edges_coarse=c.boundary_edges,
        volume_fine=f.volume,
        volume_coarse=c.volume,
    )
    fine_bad, coarse_bad = [], []
    for lay, idx, bad in ((f, i, fine_bad), (c, i + 1, coarse_bad)):
        if not lay.finite:
            bad.append(f"layer {idx} has NaN or infinite coordinates")
            continue
        if lay.boundary_edges or lay.nonmanifold_edges:
            bad.append(
                f"layer {idx} is not a closed manifold surface ({lay.boundary_edges} boundary, "
                f"{lay.nonmanifold_edges} non-manifold edges)"
            )
        if lay.self_pairs:
            bad.append(f"layer {idx} self-intersects ({lay.self_pairs} face pairs)")
        if lay.volume <= 0:
            bad.append(f"layer {idx} is inside-out or flat (signed volume {lay.volume:.3g})")

    cross = []
    if f.finite and c.finite:
        p.n_intersecting_pairs = len(cross_intersection_pairs(f.V, f.F, c.V, c.F, engine))
        d2_fc = d2_cf = None
        if not p.n_intersecting_pairs:
            d2_fc = igl.point_mesh_squared_distance(f.V, c.V, c.F)[0]
            d2_cf = igl.point_mesh_squared_distance(c.V, f.V, f.F)[0]
        closed = not (f.boundary_edges or f.nonmanifold_edges or c.boundary_edges or c.nonmanifold_edges)
        w_f = _piece_winding(winding, c, f, d2_fc if closed else None)  # fine vertices w.r.t. the coarse
        w_c = _piece_winding(winding, f, c, d2_cf if closed else None)  # coarse vertices w.r.t. the fine
        p.min_winding = float(w_f.min())
        p.n_outside_vertices = int(np.count_nonzero(w_f < WINDING_THRESHOLD))
        p.n_coarse_inside_vertices = int(np.count_nonzero(w_c >= WINDING_THRESHOLD))
        if p.n_intersecting_pairs:
            p.min_gap = 0.0  # crossing or touching surfaces are at distance 0
            p.min_gap_exact = True
        else:
            d_fc, d_cf = d2_fc.min(), d2_cf.min()
            g_v = float(np.sqrt(max(min(d_fc, d_cf), 0.0)))  # vertex-face part of the distance
            # edge-edge part, searched below ``bound`` only (cost grows with the search radius)
            cap = max(min_gap, EXACT_GAP_BELOW) * diag
            bound = min(g_v, cap)
            g_e = min_edge_edge_distance(f.V, f.F, c.V, c.F, bound)
            p.min_gap = g_e if g_e < bound else g_v
            p.min_gap_exact = bool(g_e < bound or g_v <= cap)
        p.min_gap_rel = p.min_gap / diag if diag > 0 else float("nan")
        if p.n_intersecting_pairs:
            cross.append(
                f"layer {i + 1} intersects layer {i}: {p.n_intersecting_pairs} intersecting or touching "
                "triangle pairs"
            )
        if p.n_outside_vertices:
            cross.append(
                f"layer {i + 1} does not contain layer {i}: {p.n_outside_vertices} of {f.V.shape[0]} fine "
                f"vertices outside (min winding number {p.min_winding:.3f})"
            )
        if p.n_coarse_inside_vertices:
            cross.append(
                f"layer {i + 1} has {p.n_coarse_inside_vertices} vertices inside layer {i}"
            )
        if not p.n_intersecting_pairs and min_gap > 0 and not (p.min_gap_rel >= min_gap):
            cross.append(
                f"layer {i + 1} is closer than min_gap to layer {i}: gap {p.min_gap_rel:.3g} < {min_gap:.3g} "
                "of the diagonal"
            )
    reasons = fine_bad + coarse_bad + cross
    p.ok = not reasons
    p.reason = "; ".join(reasons)
    if reasons:
        # blame the fine layer only if the fine layer alone is broken
        p.failing_layer = i if (fine_bad and not coarse_bad and not cross) else i + 1
    p.seconds = time.perf_counter() - t0
    return p


def verify_nesting(
    layers,
    *,
    min_gap: float = 0.0,
    check_self: bool = True,
    exact_winding: bool = True,
    intersection_engine: str | None = None,
    audited: tuple[int, ...] = (),
) -> NestingReport:
    """Certify that every layer of a hierarchy strictly contains the previous one.

    See the module docstring for the exact rule (no crossing, fine vertices inside, coarse vertices
    outside) and why it is robust for surfaces that nearly touch.

    Parameters
    ----------
    layers : sequence of (V_i, F_i)
        ``V_i`` (n_i,3) float, ``F_i`` (m_i,3) int; finest first (layer 0 is usually the input).
    min_gap : float
        Required clearance between consecutive surfaces, relative to the bounding-box diagonal of
        layer 0. The default 0 accepts any positive gap (touching is always a failure).
    check_self : bool
        Also test each layer for self-intersections (exact decision; a self-intersecting layer fails).
    exact_winding : bool
        Where every vertex is evaluated (a pair that crosses, or more than
        :data:`DIRECT_WINDING_POINTS` connected pieces), use ``igl.winding_number`` (robust for nearly
        touching surfaces); False uses the ~6x faster but approximate ``igl.fast_winding_number``. One
        vertex per piece is summed directly either way.
    intersection_engine : {"filtered", "cgal"}, optional
        Exact intersection tests: ``"filtered"`` (default; :mod:`cagegen.intersect`, no copyleft
        code) or ``"cgal"`` (libigl's GPL CGAL module). None: the default.
    audited : tuple of int
        Layers whose arrays passed :func:`cagegen.check_mesh` (its exact self-intersection test
        included), e.g. ``(0,)`` for the input in :func:`cagegen.build_cages`: their self-intersection
        test is not repeated (their count is 0).

    Returns
    -------
    NestingReport
        ``report.ok``, per-pair figures in ``report.pairs``; ``report.raise_if_failed()`` raises
        :class:`CageError` naming the first failing layer.

    Raises
    ------
    CageError
        A layer is not a pair of arrays of the right shapes (structural problem).
    ValueError
        Fewer than two layers.

    Examples
    --------
    >>> import trimesh
    >>> s = trimesh.creation.icosphere(subdivisions=2)
    >>> rep = verify_nesting([(s.vertices, s.faces), (1.5 * s.vertices, s.faces)])
    >>> rep.ok, round(rep.pairs[0].min_winding, 3)
    (True, 1.0)
    """
    layers = list(layers)
    if len(layers) < 2:
        raise CageOptionError(f"verify_nesting needs at least two layers, got {len(layers)}")
    t0 = time.perf_counter()
    engine = _engine(intersection_engine)
    prepared = [_prepare(i, V, F, check_self, engine, i in audited) for i, (V, F) in enumerate(layers)]
    diag = bbox_diagonal(prepared[0].V) if prepared[0].finite else float("nan")
    pairs = [
        _check_pair(i, prepared[i], prepared[i + 1], diag, float(min_gap), exact_winding, engine)
        for i in range(len(prepared) - 1)
    ]
    return NestingReport(
        ok=all(p.ok for p in pairs),
        pairs=pairs,
        bbox_diagonal=diag,
        min_gap_required=float(min_gap),
        seconds=time.perf_counter() - t0,
    )
