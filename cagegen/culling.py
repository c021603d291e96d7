"""Conservative collision culling with two nested hierarchies (Nested Cages paper, Results).

Object ``A`` has layers ``A_0 ⊂ A_1 ⊂ ... ⊂ A_k`` (solids; ``A_0`` the input, each cage certified to
contain the layer inside it by :func:`cagegen.verify_nesting`), object ``B`` likewise. If the solids of
one layer pair are disjoint, the solids inside them are too: ``A_i ∩ B_j = ∅ ⇒ A_0 ∩ B_0 = ∅``. So
:func:`cull_collisions` tests the pairs coarse to fine and answers "separated" at the first pair that does
not intersect; only when every pair down to the inputs intersects does it answer "intersecting" (exact:
the last test is on the inputs themselves).

One test of two closed surfaces (:func:`solids_intersect`): their solids intersect iff a triangle of one
meets a triangle of the other (the verifier's exact test, :func:`cagegen._geometry.cross_intersection_pairs`;
touching counts as meeting, so rounding can only make the answer conservative) or, when no triangles meet,
one surface lies inside the other (the winding number of one vertex, exact enough: the vertex is off the
other surface; only tried when one bounding box holds the other). Faces are first filtered by a box: the
solids' intersection at a finer pair lies in the intersection of the bounding boxes of every coarser pair
(``A_i ⊂ A_k``), and two meeting triangles share a point of it, so faces whose boxes miss it cannot meet.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field

import numpy as np

from ._geometry import _engine, as_mesh_arrays, cross_intersection_pairs
from .errors import CageOptionError

__all__ = ["CullingReport", "cull_collisions", "solids_intersect"]


@dataclass
class CullingReport:
    """Outcome of :func:`cull_collisions`.

    Attributes
    ----------
    separated : bool
        True when the inputs' solids are disjoint.
    decided_at : (int, int)
        Layer pair ``(i, j)`` that decided: the first disjoint pair, or ``(0, 0)`` when the inputs intersect.
    tests : list of dict
        One per tested pair, coarse first: ``layers``, ``faces`` (after the box filter), ``crossing``
        (triangle pairs that meet), ``contained``, ``intersect``, ``seconds``.
    seconds : float
    """

    separated: bool
    decided_at: tuple[int, int]
    tests: list = field(default_factory=list)
    seconds: float = 0.0

    def to_dict(self) -> dict:
        """JSON-serialisable dict."""
        return asdict(self)


def _box(V: np.ndarray) -> np.ndarray:
    return np.array([V.min(axis=0), V.max(axis=0)])


def _faces_in_box(V: np.ndarray, F: np.ndarray, box: np.ndarray) -> np.ndarray:
    """Faces whose bounding boxes overlap ``box`` (2, 3)."""
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]  # elementwise min/max: numpy's reduce over a (m, 3, 3)
    hi = np.maximum(np.maximum(a, b), c)          # array's middle axis was most of a test's time
    lo = np.minimum(np.minimum(a, b), c)
    return np.flatnonzero(np.all((hi >= box[0]) & (lo <= box[1]), axis=1))


def _inside(V: np.ndarray, F: np.ndarray, q: np.ndarray) -> bool:
    """Is ``q`` inside the closed surface? Its winding number, the sum of the triangles' signed solid
    angles over 4π (Van Oosterom & Strackee's formula), is an integer up to rounding for a point off the
    surface: one vectorised pass, no tree to build for a single point."""
    a, b, c = (V[F[:, k]] - q for k in range(3))
    la, lb, lc = (np.linalg.norm(x, axis=1) for x in (a, b, c))
    num = np.einsum("ij,ij->i", a, np.cross(b, c))
    den = la * lb * lc + np.einsum("ij,ij->i", a, b) * lc + np.einsum("ij,ij->i", b, c) * la \
        + np.einsum("ij,ij->i", c, a) * lb
    return bool(np.arctan2(num, den).sum() / (2.0 * np.pi) >= 0.5)


def _box_inside(inner: np.ndarray, outer: np.ndarray) -> bool:
    """Is the bounding box of ``inner`` within that of ``outer``? (Needed for one solid to hold the other.)"""
    lo, hi = outer.min(axis=0), outer.max(axis=0)
    return bool(np.all(inner.min(axis=0) >= lo) and np.all(inner.max(axis=0) <= hi))


def solids_intersect(VA, FA, VB, FB, *, box=None, engine: str | None = None) -> dict:
    """Do the solids bounded by two closed surfaces intersect (or touch)? Exact, conservative on touching.

    Parameters
    ----------
    VA : (nA, 3) float, FA : (mA, 3) int, VB : (nB, 3) float, FB : (mB, 3) int
        Closed, outward-oriented, self-intersection-free surfaces.
    box : (2, 3) float, optional
        A box known to contain the solids' intersection (only faces meeting it are tested); default the
        intersection of the two bounding boxes.
    engine : {"filtered", "cgal"}, optional
        The verifier's intersection engine.

    Returns
    -------
    dict
        ``intersect`` (bool), ``crossing`` (triangle pairs that meet), ``contained`` (one inside the
        other, no crossing), ``faces`` (faces tested, A and B), ``box`` (the box used, or None if empty).
    """
    VA, FA = as_mesh_arrays(VA, FA, "A")
    VB, FB = as_mesh_arrays(VB, FB, "B")
    b = np.array([np.maximum(VA.min(0), VB.min(0)), np.minimum(VA.max(0), VB.max(0))])
    if box is not None:
        b = np.array([np.maximum(b[0], box[0]), np.minimum(b[1], box[1])])
    out = {"intersect": False, "crossing": 0, "contained": False, "faces": [0, 0], "box": None}
    if np.any(b[0] > b[1]):  # the boxes miss each other: nothing to test
        return out
    out["box"] = b.tolist()
    fa, fb = _faces_in_box(VA, FA, b), _faces_in_box(VB, FB, b)
    out["faces"] = [len(fa), len(fb)]
    if len(fa) and len(fb):
        out["crossing"] = len(cross_intersection_pairs(VA, FA[fa], VB, FB[fb], engine))
    if not out["crossing"]:  # no surface contact: disjoint solids unless one holds the other
        out["contained"] = ((_box_inside(VA, VB) and _inside(VB, FB, VA[FA[0, 0]]))
                            or (_box_inside(VB, VA) and _inside(VA, FA, VB[FB[0, 0]])))
    out["intersect"] = bool(out["crossing"]) or out["contained"]
    return out


def _distinct(layers) -> list:
    """The layers without repeats of the previous one (a hierarchy whose first tet levels share the input
    surface lists it more than once)."""
    out: list = []
    for V, F in layers:
        if out and np.array_equal(out[-1][0], V) and np.array_equal(out[-1][1], F):
            continue
        out.append((V, F))
    return out


def _pairs(na: int, nb: int) -> list[tuple[int, int]]:
    """Layer pairs coarse to fine: both objects step down together; the one with fewer layers waits at its
    input."""
    steps = max(na, nb)
    return [(max(na - 1 - s, 0), max(nb - 1 - s, 0)) for s in range(steps)]


def cull_collisions(layers_a, layers_b, *, engine: str | None = None) -> CullingReport:
    """Are two objects separated? Their nested layers tested coarse to fine (see the module docstring).

    Parameters
    ----------
    layers_a, layers_b : sequence of (V, F)
        Each object's layers, finest (the input) first, every layer containing the previous one
        (``Hierarchy.surfaces``, or :func:`cagegen.build_cages`' output); a layer repeating the previous
        one is skipped, and ``decided_at`` indexes the remaining layers. Nesting is the caller's
        guarantee (certified by :func:`cagegen.verify_nesting`); it is not re-checked here.
    engine : {"filtered", "cgal"}, optional
        The verifier's exact intersection engine (default ``"filtered"``, no copyleft code).

    Returns
    -------
    CullingReport
        ``separated``, the deciding layer pair and one record per test.

    Examples
    --------
    >>> import trimesh
    >>> s = trimesh.creation.icosphere(subdivisions=2)
    >>> A = [(s.vertices, s.faces), (1.3 * s.vertices, s.faces)]
    >>> B = [(V + [2.8, 0, 0], F) for V, F in A]
    >>> rep = cull_collisions(A, B)
    >>> rep.separated, rep.decided_at          # the outer cages already miss each other
    (True, (1, 1))
    >>> cull_collisions(A, [(V + [2.2, 0, 0], F) for V, F in A]).decided_at   # cages meet, inputs do not
    (0, 0)
    """
    layers_a, layers_b = _distinct(layers_a), _distinct(layers_b)
    if not layers_a or not layers_b:
        raise CageOptionError("cull_collisions needs at least one layer per object")
    engine = _engine(engine)
    t0 = time.perf_counter()
    box = None
    tests = []
    for i, j in _pairs(len(layers_a), len(layers_b)):
        t1 = time.perf_counter()
        r = solids_intersect(*layers_a[i], *layers_b[j], box=box, engine=engine)
        tests.append({"layers": [i, j], "faces": r["faces"], "crossing": r["crossing"],
                      "contained": r["contained"], "intersect": r["intersect"],
                      "seconds": time.perf_counter() - t1})
        if not r["intersect"]:
            return CullingReport(True, (i, j), tests, time.perf_counter() - t0)
        box = np.asarray(r["box"])  # the finer solids' intersection lies in this box
    return CullingReport(False, (0, 0), tests, time.perf_counter() - t0)
