"""Cross-sections and the tight cage of Casti et al. (2019), Sec. 3.3 and 4.

* :func:`auto_bending_nodes`: bending nodes where the local thickness r(p) (radius of the maximal
  inscribed ball) changes fastest along a branch (Sec. 4: critical points of the smoothed r').
* :func:`cross_section`: seeds on a circle orthogonal to the skeleton (radius 20% of r(p), 20 seeds),
  integral lines of ∇f to the surface (points G_p), PCA plane, and the quad maximising the signed
  sums ±λ1 x ± λ2 y (the paper's four maximisations).
* :func:`tight_cage`: tubes between consecutive sections of a chain (side quads), convex-hull
  polyhedra of the incident sections projected on a sphere at branching nodes, quad caps at leaves.
"""

from __future__ import annotations

import itertools

import igl
import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.spatial import ConvexHull

from ..errors import CageError
from .field import GuidingField
from .graph import Skeleton

__all__ = ["CrossSection", "auto_bending_nodes", "cross_section", "flatten_section", "inscribed_radius",
           "section_degenerate", "sections_cross", "tight_cage", "untangle_sections"]


def inscribed_radius(P: np.ndarray, V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Radius of the largest ball centred at each point and inside the surface (distance to M)."""
    d2, _, _ = igl.point_mesh_squared_distance(np.atleast_2d(P), V, F)
    return np.sqrt(d2)


def _chain_polyline(skel: Skeleton, chain) -> np.ndarray:
    return skel.nodes[np.asarray(chain.nodes)]


def _arclength(X: np.ndarray) -> np.ndarray:
    return np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(X, axis=0), axis=1))]


def auto_bending_nodes(skel: Skeleton, V: np.ndarray, F: np.ndarray, spacing: float,
                       min_separation: float = 1.5, rel_threshold: float = 0.15,
                       junction_window: tuple = (1.5, 3.5)) -> tuple[Skeleton, dict]:
    """Place bending nodes where the thickness r changes fastest along each chain (paper Sec. 4).

    The skeleton is resampled at ``spacing``; along every chain r(s) (distance to M) is smoothed,
    differentiated, and the local extrema of r' with |r'| above ``rel_threshold`` become bending nodes,
    kept at least ``min_separation`` x (local radius) from the chain ends and from each other. Every
    chain incident to a branching node gets a bending node where the limb leaves the body (the
    largest |r'| at ``junction_window`` x r of the branching node from it, else the middle of the
    window), so junction polyhedra stay small and their sections do not overlap.

    Returns
    -------
    skel : Skeleton
        Resampled copy with the bending nodes set.
    info : dict
        Per chain: number of samples, bending positions (arc length).
    """
    S = skel.resampled(spacing)
    deg = S.degree
    r = inscribed_radius(S.nodes, V, F)
    bending: set = set(S.bending)
    info = {"chains": []}
    for ch in S.chains():
        ids = np.asarray(ch.nodes)
        X = S.nodes[ids]
        s = _arclength(X)
        L = s[-1]
        if len(ids) < 3:
            continue
        rr = gaussian_filter1d(r[ids], sigma=2.0, mode="nearest")
        dr = np.gradient(rr, s)
        chosen: list = []
        cand = [i for i in range(1, len(ids) - 1)
                if abs(dr[i]) >= rel_threshold and abs(dr[i]) >= abs(dr[i - 1]) and abs(dr[i]) >= abs(dr[i + 1])]
        cand.sort(key=lambda i: -abs(dr[i]))

        def far_enough(i, s=s, ids=ids, L=L, chosen=chosen):
            lim = min_separation * r[ids[i]]
            if s[i] < lim or L - s[i] < lim:
                return False
            return all(abs(s[i] - s[j]) >= min_separation * max(r[ids[i]], r[ids[j]]) for j in chosen)

        for end_pos, end_node in ((0, ch.start), (len(ids) - 1, ch.end)):
            if deg[end_node] >= 3:
                # the limb's attachment: largest |r'| within 3 radii of the branching node, else 1.5 r
                d = np.abs(s - s[end_pos])
                near = [i for i in range(1, len(ids) - 1)
                        if r[end_node] * junction_window[0] <= d[i] <= junction_window[1] * r[end_node]]
                if near:
                    i = max(near, key=lambda i: abs(dr[i]))
                    if abs(dr[i]) < rel_threshold:
                        mid = 0.5 * (junction_window[0] + junction_window[1]) * r[end_node]
                        i = min(near, key=lambda i: abs(d[i] - mid))
                    if all(abs(s[i] - s[j]) > 0.5 * r[ids[i]] for j in chosen):
                        chosen.append(i)
        for i in cand:
            if far_enough(i):
                chosen.append(i)
        for i in chosen:
            if deg[ids[i]] == 2:
                bending.add(int(ids[i]))
        info["chains"].append({"length": float(L), "n_samples": len(ids),
                               "bending_arclength": sorted(float(s[i]) for i in chosen)})
    return S.with_bending(sorted(bending)), info


class JunctionError(CageError):
    """The convex hull at branching node ``junction`` misses an edge of the section at node ``section``."""

    def __init__(self, message: str, junction: int, section: int):
        super().__init__(message, layer=1)
        self.junction, self.section = int(junction), int(section)


class CrossSection:
    """The quad section at a control node.

    Attributes
    ----------
    node : int
        Skeleton node.
    center, tangent : (3,) float arrays
        Node position and unit skeleton direction (oriented along its chain).
    radius : float
        Inscribed-ball radius at the node.
    seeds, hits : (k,3) float arrays
        Circle seeds and where their integral lines meet the surface (G_p).
    quad : (4,3) float array
        The section's quad, counter-clockwise around ``tangent``.
    """

    def __init__(self, node, center, tangent, radius, seeds, hits, quad):
        self.node, self.center, self.tangent, self.radius = node, center, tangent, radius
        self.seeds, self.hits, self.quad = seeds, hits, quad


def _frame(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.eye(3)[np.argmin(np.abs(t))]
    u = np.cross(t, a)
    u /= np.linalg.norm(u)
    return u, np.cross(t, u)


def best_quad(G: np.ndarray, tangent: np.ndarray, ref: np.ndarray | None = None,
              roundness: float = 0.8) -> tuple[np.ndarray, np.ndarray]:
    """The paper's quad of a ring of surface points G_p: PCA plane, four weighted maximisations.

    q0..q3 maximise (+w1 x + w2 y), (−w1 x + w2 y), (−w1 x − w2 y), (+w1 x − w2 y) over the points
    projected on the first two principal axes; a point is not used twice (the next best one is taken).
    The paper weights by the eigenvalues λ1, λ2; we use their square roots (the spreads along the
    axes), which does not collapse two corners onto the far ends of an elongated section.

    For a nearly round ring (spread ratio above ``roundness``) the principal axes are arbitrary; if
    ``ref`` (the previous section's first axis along the chain) is given, it is projected into the PCA
    plane and used as the first axis instead, so consecutive quads are not twisted against each other.

    Returns
    -------
    quad : (4,3) float array
        Ordered counter-clockwise around ``tangent``.
    axis : (3,) float array
        The first in-plane axis used.
    """
    c = G.mean(axis=0)
    w, U = np.linalg.eigh(np.cov((G - c).T))
    order = np.argsort(w)[::-1]
    lam, U = np.maximum(w[order], 0.0), U[:, order]
    l1, l2 = np.sqrt(lam[0]), np.sqrt(lam[1])
    n = np.cross(U[:, 0], U[:, 1])
    if np.dot(n, tangent) < 0:
        U[:, 1] = -U[:, 1]
        n = -n
    e1, e2 = U[:, 0], U[:, 1]
    if ref is not None and l2 > roundness * l1:
        r = ref - np.dot(ref, n) * n
        if np.linalg.norm(r) > 1e-6:
            e1 = r / np.linalg.norm(r)
            e2 = np.cross(n, e1)
    x, y = (G - c) @ e1, (G - c) @ e2
    used: list = []
    for sx, sy in ((1, 1), (-1, 1), (-1, -1), (1, -1)):
        score = sx * l1 * x + sy * l2 * y
        score[used] = -np.inf
        used.append(int(np.argmax(score)))
    return G[used], e1


def cross_section(field: GuidingField, node: int, center: np.ndarray, tangent: np.ndarray,
                  radius: float, n_seeds: int = 20, seed_radius: float = 0.2,
                  ref: np.ndarray | None = None) -> CrossSection:
    """Section at a control node (paper Sec. 3.3, Fig. 4); ``ref``: see :func:`best_quad`.

    Raises
    ------
    CageError
        Fewer than 4 integral lines reached the surface.
    """
    u, w = _frame(tangent)
    th = 2 * np.pi * np.arange(n_seeds) / n_seeds
    for rad in (seed_radius, 0.5 * seed_radius, 0.25 * seed_radius):  # thin parts: seeds closer to S
        seeds = center + rad * radius * (np.cos(th)[:, None] * u + np.sin(th)[:, None] * w)
        hits, ok = field.trace(seeds)
        if ok.sum() >= 4:
            break
    if ok.sum() < 4:
        raise CageError(f"skeleton cage, cross-section at skeleton node {node}: only {int(ok.sum())} of "
                        f"{n_seeds} integral lines reached the surface", layer=1)
    quad, axis = best_quad(hits[ok], tangent, ref=ref)
    cs = CrossSection(node, center, tangent, radius, seeds, hits[ok], quad)
    cs.axis = axis
    return cs


def _quad_normal(q: np.ndarray, towards: np.ndarray) -> np.ndarray:
    """Unit normal of a (possibly non-planar) quad from its diagonals, oriented along ``towards``."""
    n = np.cross(q[2] - q[0], q[3] - q[1])
    n = n / max(np.linalg.norm(n), 1e-300)
    return n if np.dot(n, towards) >= 0 else -n


def sections_cross(a: CrossSection, b: CrossSection, margin: float = 0.25) -> bool:
    """Whether the tube between consecutive sections ``a`` -> ``b`` of a chain folds over itself.

    With n_a, n_b the quads' normals oriented from a to b, the tube is free of this fold when every
    corner of b lies ahead of a's plane and every corner of a behind b's plane, by ``margin`` x the
    smaller inscribed radius of the two sections (the quads are not planar: their corners are on M;
    a smaller margin, 0.05, missed a leaf cap cut by its tube on the elephant); a section tilted by θ
    with half-width w spans w tan θ along the chain, so two sections crossing each other is what makes their side quads cut
    each other and the leaf cap: seen on the zoo at leaves, whose integral lines fan out into the tip).
    """
    u = b.center - a.center
    if np.linalg.norm(u) < 1e-300:
        return True
    na, nb = _quad_normal(a.quad, u), _quad_normal(b.quad, u)
    tol = margin * min(a.radius, b.radius)
    ahead = np.min((b.quad - a.quad.mean(axis=0)) @ na)
    behind = np.max((a.quad - b.quad.mean(axis=0)) @ nb)
    return bool(ahead <= tol or behind >= -tol)


def flatten_section(cs: CrossSection, V: np.ndarray | None = None, F: np.ndarray | None = None) -> None:
    """Replace the section's quad by one in the plane orthogonal to the skeleton (in place).

    The plane is orthogonal to the skeleton tangent t at the mean position of the integral-line ends
    along t; the quad is centred on the skeleton, its axes are the principal axes of the ends projected
    on the plane (the previous section's axis when the projection is nearly round), and its corners lie
    on the ellipse whose semi-axes are the ends' largest extents along those axes, at least the
    inscribed radius r (a disc of radius r about the skeleton node is inside M), at ±45° (the paper's
    quad of an ellipse). Choosing among the projected ends instead gave degenerate (collinear) quads
    where the ends fan into a thin tip. With the surface ``(V, F)``, each corner then moves along its
    ray from the centre to where the ray leaves M (the paper's corners are on M; corners left inside M
    made the flow stall on spot with M inside the cage but cut by it); without it they stay on the
    ellipse, off M.
    """
    t = cs.tangent / np.linalg.norm(cs.tangent)
    c = cs.center + float(np.dot(cs.hits.mean(axis=0) - cs.center, t)) * t
    H = cs.hits - c
    H = H - np.outer(H @ t, t)
    w, U = np.linalg.eigh(H.T @ H)
    e1 = U[:, np.argmax(w)]
    e1 = e1 - np.dot(e1, t) * t
    e1 /= np.linalg.norm(e1)
    ref = getattr(cs, "axis", None)
    x, y = H @ e1, H @ np.cross(t, e1)
    if ref is not None and np.ptp(y) > 0.8 * np.ptp(x):  # nearly round: keep the chain's axis (no twist)
        r = ref - np.dot(ref, t) * t
        if np.linalg.norm(r) > 1e-6:
            e1 = r / np.linalg.norm(r)
    e2 = np.cross(t, e1)
    a = max(float(np.abs(H @ e1).max()), cs.radius)
    b = max(float(np.abs(H @ e2).max()), cs.radius)
    k = 1.0 / np.sqrt(2.0)
    signs = ((1, 1), (-1, 1), (-1, -1), (1, -1))
    cs.quad = np.array([c + k * (sx * a * e1 + sy * b * e2) for sx, sy in signs])
    if V is not None:
        cs.quad = _corners_on_surface(cs.quad, c, cs.center, V, F, step=0.25 * cs.radius)
    cs.axis = e1
    cs.flattened = True


def _corners_on_surface(Q: np.ndarray, c: np.ndarray, node: np.ndarray, V: np.ndarray, F: np.ndarray,
                        step: float, reach: float = 4.0) -> np.ndarray:
    """Move each corner of Q along its ray from the centre (``c``, else the skeleton ``node`` when c is
    outside M) to the ray's first exit from M (samples every ``step`` up to ``reach`` x the corner's
    distance, at most 128 samples, then 30 bisections of the winding number); a ray without an exit
    keeps its corner."""
    o = c if igl.winding_number(V, F, c[None])[0] >= 0.5 else node
    if igl.winding_number(V, F, o[None])[0] < 0.5:
        return Q
    D = Q - o
    L = np.linalg.norm(D, axis=1)
    D = D / L[:, None]
    step = max(step, reach * float(L.max()) / 128)  # at most 128 samples per ray
    s = np.arange(1, int(np.ceil(reach * L.max() / step)) + 1) * step
    w = igl.winding_number(V, F, (o + s[None, :, None] * D[:, None, :]).reshape(-1, 3)).reshape(4, -1)
    found = (w < 0.5).any(axis=1)
    j = np.argmax(w < 0.5, axis=1)  # first sample outside M along each ray
    lo = np.where(j > 0, s[np.maximum(j - 1, 0)], 0.0)
    hi = s[j]
    for _ in range(30):  # bisection, the four rays at once
        mid = 0.5 * (lo + hi)
        inside = igl.winding_number(V, F, o + mid[:, None] * D) >= 0.5
        lo, hi = np.where(inside, mid, lo), np.where(inside, hi, mid)
    return np.where(found[:, None], o + hi[:, None] * D, Q)


def section_degenerate(cs: CrossSection, tol: float = 0.25) -> bool:
    """Whether two corners of the section's quad are closer than ``tol`` x its inscribed radius.

    Corners on an ellipse with semi-axes >= r at ±45° are at least √2 r apart; the paper's quads of
    a tube of radius >= r are alike. Closer corners come from integral lines ending at (nearly) the same
    point of M (seen at small leaves: homer's fingertips, r = 0.003 of the diagonal, had two equal
    corners, so the tube's faces were degenerate and the tight cage "self-intersected").
    """
    q = cs.quad
    d = [np.linalg.norm(q[i] - q[j]) for i in range(4) for j in range(i + 1, 4)]
    return bool(min(d) < tol * cs.radius)


def untangle_sections(sections: dict, chain_controls: list, margin: float = 0.25, V: np.ndarray | None = None,
                      F: np.ndarray | None = None) -> list:
    """Flatten degenerate sections (:func:`section_degenerate`) and sections whose tube to the next
    section along their chain folds (:func:`sections_cross`).

    Per crossing pair, the more tilted section (smaller |normal . tangent|) is flattened
    (:func:`flatten_section`), then the other if they still cross; pairs that still cross are left to
    the assembly's recoveries. ``(V, F)``: the surface; degenerate sections and leaf sections get
    their corners on M (:func:`flatten_section`), bending sections flattened for crossing keep the
    ellipse corners (>= r from the skeleton, inside M). Measured on the zoo: corners left inside M at a
    degenerate section made spot's flow stall (M inside the cage but cut by it), corners moved onto M
    at crossing bending sections next to a junction made cheburashka's junction hull fail (larger
    sections overlap on the junction's sphere). Returns the flattened nodes (in order).
    """
    leaves = {int(e) for ch, _ in chain_controls for e in (ch.start, ch.end)}  # sections there are leaf caps

    def surf(nd):
        return (V, F) if int(nd) in leaves else (None, None)

    done: list = []
    for _, ctrl in chain_controls:
        for nd in ctrl:
            cs = sections[nd]
            if not getattr(cs, "flattened", False) and section_degenerate(cs):
                flatten_section(cs, V, F)
                done.append(int(nd))
    for _, ctrl in chain_controls:
        for a, b in itertools.pairwise(ctrl):
            A, B = sections[a], sections[b]
            if not sections_cross(A, B, margin):
                continue
            u = B.center - A.center

            def tilt(cs, u=u):
                t = cs.tangent / np.linalg.norm(cs.tangent)
                return abs(float(np.dot(_quad_normal(cs.quad, u), t)))

            for nd, cs in sorted(((a, A), (b, B)), key=lambda x: tilt(x[1])):
                if getattr(cs, "flattened", False):
                    continue
                flatten_section(cs, *surf(nd))
                done.append(int(nd))
                if not sections_cross(A, B, margin):
                    break
    return done


def _align(prev: np.ndarray, cur: np.ndarray) -> np.ndarray:
    """Cyclic shift of ``cur`` (same orientation) whose corners best match ``prev``'s directions."""
    a = prev - prev.mean(axis=0)
    b = cur - cur.mean(axis=0)
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    best = max(range(4), key=lambda s: float(np.sum(a * np.roll(b, -s, axis=0))))
    return np.roll(cur, -best, axis=0)


def tight_cage(skel: Skeleton, sections: dict, chain_controls: list, max_steiner_rounds: int = 6,
               max_steiner_per_junction: int = 16) -> dict:
    """Assemble the tight cage from the sections (vertices on M).

    Parameters
    ----------
    skel : Skeleton
    sections : dict node -> CrossSection
    chain_controls : list of (chain, [control nodes in chain order])
    max_steiner_rounds : int
        Rounds of Steiner vertices (midpoints of the section edges a junction hull misses, paper Sec. 3.3).
    max_steiner_per_junction : int
        Cap on the Steiner vertices added for one junction (all rounds); a round that would pass it
        raises :class:`JunctionError` naming the cap (the misses then double every round: the
        sections' projections overlap, which midpoints cannot fix).

    Returns
    -------
    dict with ``V`` (n,3), ``quads`` (q,4) int, ``tris`` (t,3) int (junction faces), ``F`` (m,3) int
    (all faces triangulated, outward), ``section_vertices`` node -> 4 corner vertex indices,
    ``section_rings`` node -> its corners and Steiner vertices in ring order, ``n_steiner``. Tube sides
    and caps holding Steiner vertices are triangulated (in ``tris``); the paper removes the Steiner
    vertices afterwards by edge collapses, we keep them (the cage stays certified as built).

    Raises
    ------
    CageError
        A junction hull misses a section edge, or the assembled surface is not closed and manifold.
    """
    verts, sec_vid = _section_corners(sections, chain_controls)
    extra: dict = {}  # (node, k) -> Steiner vertices on edge k (corner k -> k+1) of that section, in order
    incident = _incident_sections(skel, chain_controls)
    junction_tris, n_steiner, steiner_at = _junctions(skel, verts, sec_vid, extra, incident,
                                                      max_steiner_rounds, max_steiner_per_junction)
    V = np.asarray(verts, dtype=float)
    quads, tris = _tubes_and_caps(V, skel, chain_controls, sec_vid, extra)
    for b in skel.branching:
        tris.extend(junction_tris[b].tolist())
    quads = np.asarray(quads, dtype=np.int64).reshape(-1, 4)
    tris = np.asarray(tris, dtype=np.int64).reshape(-1, 3)
    F = np.vstack([_split_quads(V, quads), tris])
    F = _orient_outward(V, F)
    _check_closed(V, F)
    # orient the quads like the triangles
    quads = _orient_quads(quads, F)
    return {"V": V, "quads": quads, "tris": _match_orientation(tris, F), "F": F, "section_vertices": sec_vid,
            "section_rings": {nd: _ring(sec_vid, extra, nd) for nd in sec_vid}, "n_steiner": n_steiner,
            "n_steiner_per_junction": {int(k): int(v) for k, v in steiner_at.items()}}


def _section_corners(sections: dict, chain_controls: list) -> tuple[list, dict]:
    """The sections' corners as cage vertices, in a consistent order along each chain: ``(verts, sec_vid)``,
    ``sec_vid`` node -> its 4 vertex ids (a section shared by two chains keeps its first order)."""
    verts: list = []
    sec_vid: dict = {}
    for _ch, ctrl in chain_controls:
        prev = None
        for nd in ctrl:
            q = sections[nd].quad
            if nd in sec_vid:  # shared section (between two junctions): keep its order
                prev = np.asarray([verts[i] for i in sec_vid[nd]])
                continue
            if prev is not None:
                q = _align(prev, q)
            sec_vid[nd] = list(range(len(verts), len(verts) + 4))
            verts.extend(q)
            prev = q
    return verts, sec_vid


def _ring(sec_vid: dict, extra: dict, nd) -> list:
    """The vertices of section ``nd`` in ring order: its corners and the Steiner vertices on its edges."""
    out = []
    for k in range(4):
        out.append(sec_vid[nd][k])
        out.extend(extra.get((nd, k), []))
    return out


def _incident_sections(skel: Skeleton, chain_controls: list) -> dict:
    """Branching node -> the end sections of the chains that meet there (a section incident twice is a
    :class:`CageError`)."""
    incident = {}
    for b in skel.branching:
        inc = []
        for ch, ctrl in chain_controls:
            if ch.start == b:
                inc.append(ctrl[0])
            if ch.end == b:
                inc.append(ctrl[-1])
        if len(set(inc)) != len(inc):
            raise CageError(f"skeleton cage, junction at node {b}: a section is incident twice (a chain "
                            "from this node back to it); add bending nodes", layer=1)
        incident[b] = inc
    return incident


def _junctions(skel: Skeleton, verts: list, sec_vid: dict, extra: dict, incident: dict, max_rounds: int,
               max_per_junction: int) -> tuple[dict, int, dict]:
    """Junction triangles: the convex hull of the incident sections projected on a sphere (paper Sec. 3.3,
    Fig. 5); a hull that misses a section edge gets a Steiner vertex at the edge's midpoint (appended to
    ``verts`` and ``extra``), iterated until all section edges are hull edges (paper Sec. 3.3,
    "pathological cases"). Returns ``(junction -> (t,3) triangles, n_steiner, junction -> its Steiner
    vertices)``; :class:`JunctionError` when the rounds or the cap run out."""
    n_steiner = 0
    steiner_at: dict = {}  # junction -> Steiner vertices added for it
    junction_tris: dict = {}
    for rnd in range(max_rounds + 1):
        added = False
        junction_tris = {}
        for b, inc in incident.items():
            rings = [_ring(sec_vid, extra, nd) for nd in inc]
            tris, best = _junction_triangles(skel, np.asarray(verts, dtype=float), rings, b)
            if tris is not None:
                junction_tris[b] = tris
                continue
            missing, bad_sec = best
            if not missing or rnd == max_rounds:
                raise JunctionError(f"skeleton cage, junction at node {b}: the convex hull misses an edge of the "
                                    f"section at node {inc[bad_sec]} (after {n_steiner} Steiner vertices); "
                                    "move or add bending nodes near this junction", b, inc[bad_sec])
            if steiner_at.get(b, 0) + len(missing) > max_per_junction:
                raise JunctionError(f"skeleton cage, junction at node {b}: Steiner-vertex cap reached "
                                    f"({steiner_at.get(b, 0)} added, {len(missing)} more needed, cap "
                                    f"{max_per_junction} per junction); the convex hull misses an edge "
                                    f"of the section at node {inc[bad_sec]}; move or add bending nodes near "
                                    "this junction", b, inc[bad_sec])
            steiner_at[b] = steiner_at.get(b, 0) + len(missing)
            n_new = _add_steiner(verts, sec_vid, extra, inc, missing)
            n_steiner += n_new
            added = added or n_new > 0
        if not added:
            break
    return junction_tris, n_steiner, steiner_at


def _junction_triangles(skel: Skeleton, Vc: np.ndarray, rings: list, b) -> tuple:
    """``(triangles, None)`` of junction ``b``'s hull, or ``(None, (missed edges, failing section))`` of the
    attempt that missed the fewest edges. Sphere centre: the sections' centroid (paper), else the node;
    last, the plain hull (no sphere)."""
    ids = np.array([i for r in rings for i in r])
    best = None
    for c in (Vc[ids].mean(axis=0), skel.nodes[b], None):
        H, keep, missing, bad_sec = _junction_hull(Vc, ids, c, rings)
        if bad_sec is None:
            return H[keep], None
        if c is None and not missing:
            continue
        if best is None or len(missing) < len(best[0]):
            best = (missing, bad_sec)
    return None, best


def _add_steiner(verts: list, sec_vid: dict, extra: dict, inc: list, missing: list) -> int:
    """A Steiner vertex at the middle of each missed edge ``(section index, u, v)``; returns how many."""
    n_new = 0
    for k_sec, u, v in missing:
        nd = inc[k_sec]
        corners = sec_vid[nd]
        for k in range(4):  # the corner edge k holding (u, v)
            seg = [corners[k]] + extra.get((nd, k), []) + [corners[(k + 1) % 4]]
            pos = next((j for j in range(len(seg) - 1) if {seg[j], seg[j + 1]} == {u, v}), None)
            if pos is not None:
                verts.append(0.5 * (np.asarray(verts[u]) + np.asarray(verts[v])))
                lst = extra.setdefault((nd, k), [])
                lst.insert(pos, len(verts) - 1)
                n_new += 1
                break
    return n_new


def _tubes_and_caps(V: np.ndarray, skel: Skeleton, chain_controls: list, sec_vid: dict,
                    extra: dict) -> tuple[list, list]:
    """Tube sides between consecutive sections of each chain (quads; strips of triangles along edges that
    hold Steiner vertices) and the leaves' caps (a quad, or a fan with Steiner vertices)."""
    deg = skel.degree
    quads, tris = [], []
    for ch, ctrl in chain_controls:
        for a, b in itertools.pairwise(ctrl):
            A, B = sec_vid[a], sec_vid[b]
            for k in range(4):
                sa = [A[k]] + extra.get((a, k), []) + [A[(k + 1) % 4]]
                sb = [B[k]] + extra.get((b, k), []) + [B[(k + 1) % 4]]
                if len(sa) == 2 and len(sb) == 2:
                    quads.append([A[k], A[(k + 1) % 4], B[(k + 1) % 4], B[k]])
                else:
                    tris.extend(_zip_strip(V, sa, sb))
        for end in (ch.start, ch.end):
            if deg[end] == 1:  # leaf: cap quad (a fan when it holds Steiner vertices)
                r = _ring(sec_vid, extra, end)
                if len(r) == 4:
                    quads.append(list(r))
                else:
                    tris.extend([r[0], r[j], r[j + 1]] for j in range(1, len(r) - 1))
    return quads, tris


def _zip_strip(V: np.ndarray, sa: list, sb: list) -> list:
    """Triangles of the strip between two polylines running the same way (shorter diagonal first)."""
    out, i, j = [], 0, 0
    while i < len(sa) - 1 or j < len(sb) - 1:
        adv_a = j == len(sb) - 1 or (i < len(sa) - 1 and np.linalg.norm(V[sa[i + 1]] - V[sb[j]])
                                     <= np.linalg.norm(V[sb[j + 1]] - V[sa[i]]))
        if adv_a:
            out.append([sa[i], sa[i + 1], sb[j]])
            i += 1
        else:
            out.append([sa[i], sb[j + 1], sb[j]])
            j += 1
    return out


def _junction_hull(V, ids, c, rings):
    """Hull of the junction's section rings projected on the unit sphere around ``c`` (None: not projected).

    Returns (triangles, mask of the triangles to keep (not inside one section), the missed ring edges
    as (section index, u, v), index of the first failing section or None).
    """
    P = V[ids]
    S = P if c is None else (P - c) / np.linalg.norm(P - c, axis=1, keepdims=True)
    hull = ConvexHull(S)
    H = ids[hull.simplices]
    if c is None and len(hull.vertices) < len(ids):  # a corner inside the hull: no valid junction
        return H, np.zeros(len(H), bool), [], 0
    sec_of = {int(v): k for k, r in enumerate(rings) for v in r}
    owner = np.array([[sec_of[int(v)] for v in tri] for tri in H])
    inside_one = (owner == owner[:, :1]).all(axis=1)
    hull_edges = {tuple(sorted(e)) for tri in H for e in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0]))}
    missing, bad = [], None
    for k, r in enumerate(rings):
        miss = [(k, r[i], r[(i + 1) % len(r)]) for i in range(len(r))
                if tuple(sorted((r[i], r[(i + 1) % len(r)]))) not in hull_edges]
        if miss or int(np.sum(inside_one & (owner[:, 0] == k))) != len(r) - 2:
            missing.extend(miss)
            bad = k if bad is None else bad
    return H, ~inside_one, missing, bad


def _split_quads(V: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """Two triangles per quad, along the shorter diagonal."""
    if len(Q) == 0:
        return np.zeros((0, 3), dtype=np.int64)
    d02 = np.linalg.norm(V[Q[:, 0]] - V[Q[:, 2]], axis=1)
    d13 = np.linalg.norm(V[Q[:, 1]] - V[Q[:, 3]], axis=1)
    a = np.where((d02 <= d13)[:, None], Q[:, [0, 1, 2]], Q[:, [0, 1, 3]])
    b = np.where((d02 <= d13)[:, None], Q[:, [0, 2, 3]], Q[:, [1, 2, 3]])
    return np.vstack([a, b])


def triangulate_quads(V: np.ndarray, quads: np.ndarray) -> np.ndarray:
    """Triangles of quads (shorter diagonal), orientation kept."""
    return _split_quads(V, np.asarray(quads, dtype=np.int64))


def _orient_outward(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    F2, _ = igl.bfs_orient(F)
    F2 = np.asarray(F2, dtype=np.int64)
    vol = np.einsum("ij,ij->i", V[F2[:, 0]], np.cross(V[F2[:, 1]], V[F2[:, 2]])).sum() / 6
    return F2[:, ::-1].copy() if vol < 0 else F2


def _check_closed(V: np.ndarray, F: np.ndarray) -> None:
    from .._geometry import edge_stats

    es = edge_stats(F, len(V))
    if es.n_boundary_edges or es.n_nonmanifold_edges or es.n_inconsistent_edges:
        raise CageError(f"skeleton cage assembly: the tight cage is not a closed manifold ({es.n_boundary_edges} "
                        f"boundary, {es.n_nonmanifold_edges} non-manifold, {es.n_inconsistent_edges} "
                        "inconsistent edges)", layer=1)


def _directed_edges(F: np.ndarray) -> set:
    return {(int(a), int(b)) for tri in F for a, b in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0]))}


def _orient_quads(Q: np.ndarray, F: np.ndarray) -> np.ndarray:
    de = _directed_edges(F)
    out = Q.copy()
    for i, q in enumerate(Q):
        if (int(q[0]), int(q[1])) not in de:
            out[i] = q[::-1]
    return out


def _match_orientation(T: np.ndarray, F: np.ndarray) -> np.ndarray:
    de = _directed_edges(F)
    out = T.copy()
    for i, t in enumerate(T):
        if (int(t[0]), int(t[1])) not in de:
            out[i] = t[::-1]
    return out
