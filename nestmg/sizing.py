"""Sizing decided first: tet sizes of every level from a tet, memory and time budget.

Everything here is cheap (a volume integral over the input surface), so it runs *before* any cage is
built or any tet meshed, and an impossible request fails in seconds naming the option to change.

The rule (:func:`plan_hierarchy`)
---------------------------------
* Fine edge length ``h_0``: ``--edge-length`` if given; otherwise the input's mean edge length or its
  mean thickness (enclosed volume over area), whichever is smaller (:func:`_resolution_edge`: a CAD
  export's or a low-poly model's triangles say nothing of the solid), enlarged when needed so that the
  estimated fine tet count stays within ``max_tets`` (default 1.5M) *and* the estimated fine meshing time
  within ``mesh_time_budget``.
* Level ``k`` is meshed at ``h_0 * 2**k`` (~8x fewer tets per level, since the cages enclose a
  volume only slightly larger than the layer inside).
* The estimated peak memory of the largest stage (mesher + FEM matrices, :mod:`nestmg.memory`) must
  fit in ``$NESTMG_MEMORY_LIMIT`` or the available memory.
* ``levels`` is a ceiling (:func:`plan_levels`): the cages have 4x fewer faces per level and the
  smallest keeps ``>= cagegen.sizes.MIN_FACES`` (100) faces, so a small input gets the levels that fit
  (one note says so); explicit ``face_counts`` are the user's demand and fail at once if they cannot be met.

Tet counts: a regular tet of edge ``h`` has volume ``h³/(6√2)``; measured ratios of actual tets to
``volume / regular`` are ~1.0 for TetWild (sphere, bunny, gargoyle at 0.03-0.005 of the diagonal) and
~1.8 for TetGen's quality meshes (:data:`COUNT_RATIO`). The memory check uses the conservative
:func:`nestmg.memory.estimate_tets` (2.5x) so it refuses only what cannot fit.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from cagegen.errors import LevelsError
from cagegen.sizes import MIN_FACES, check_face_counts, fitting_levels
from solvers.errors import InsufficientMemoryError
from solvers.memory import check_memory

from .errors import NestmgInputError
from .memory import FEM_BYTES_PER_NODE, TetMeshMemoryError, enclosed_volume, estimate_tet_bytes
from .tetmesh import TetMeshError

__all__ = [
    "COUNT_RATIO",
    "DEFAULT_MAX_TETS",
    "DEFAULT_TIME_BUDGET",
    "LevelsPlan",
    "SizingError",
    "SizingPlan",
    "edge_length_for_tets",
    "enclosed_volume",
    "expected_tets",
    "plan_hierarchy",
    "plan_levels",
]

#: measured tets / (volume / regular-tet volume) at the target edge length
COUNT_RATIO = {"tetwild": 1.1, "tetgen": 1.8}

#: default cap on the fine level's tets
DEFAULT_MAX_TETS = 1_500_000

#: default seconds allowed for meshing the fine level (2 cores; see :func:`fine_mesh_seconds`)
DEFAULT_TIME_BUDGET = 150.0


class SizingError(TetMeshError, ValueError):
    """The requested sizes cannot be met within the budget (raised before any expensive stage)."""


def _regular(h: float) -> float:
    return h**3 / (6.0 * np.sqrt(2.0))


def expected_tets(volume: float, edge_length: float, mesher: str = "tetwild") -> int:
    """Expected tet count of a solid of ``volume`` meshed at target ``edge_length`` by ``mesher``."""
    return int(COUNT_RATIO[mesher] * volume / _regular(edge_length))


def edge_length_for_tets(V: np.ndarray, F: np.ndarray, n_tets: int, mesher: str = "tetwild") -> float:
    """Target edge length at which ``mesher`` is expected to make ``n_tets`` tets of ``(V, F)``'s solid."""
    if n_tets <= 0:
        raise NestmgInputError(f"n_tets must be positive, got {n_tets}")
    vol = enclosed_volume(V, F)
    return float((COUNT_RATIO[mesher] * vol * 6.0 * np.sqrt(2.0) / n_tets) ** (1.0 / 3.0))


@dataclass
class LevelsPlan:
    """How many levels a hierarchy gets (:func:`plan_levels`): ``levels`` <= ``requested``.

    Attributes
    ----------
    requested : int
        Levels asked (a ceiling).
    levels : int
        Levels granted.
    n_faces : int
        Faces of the surface the cages are built around.
    ratio : float
        Face-count ratio between consecutive cages.
    min_faces : int
        Smallest cage of the default face counts.
    face_counts : list of int or None
        The explicit cage face counts, when given (then ``levels == requested``).
    note : str
        One line saying how many levels fit, when fewer than asked ("" otherwise).
    """

    requested: int
    levels: int
    n_faces: int
    ratio: float = 4.0
    min_faces: int = MIN_FACES
    face_counts: list[int] | None = None
    note: str = ""

    def to_dict(self) -> dict:
        """JSON-serialisable copy."""
        return asdict(self)


def plan_levels(
    n_faces: int,
    levels: int,
    *,
    face_counts=None,
    fixed_levels: int = 0,
    ratio: float = 4.0,
    min_faces: int = MIN_FACES,
) -> LevelsPlan:
    """Levels that fit an input of ``n_faces`` faces: ``levels`` is a ceiling, ``face_counts`` a demand.

    Microseconds; the pipeline calls it before any audit, cage or tet mesh.

    Parameters
    ----------
    n_faces : int
        Faces of the surface the cages are built around.
    levels : int
        Levels asked (>= 2), of which ``fixed_levels`` are not cage layers (the refined fine level,
        same-domain levels): the input and ``levels - fixed_levels - 1`` cages.
    face_counts : sequence of int, optional
        Explicit cage face counts (finest first), exactly ``levels - fixed_levels - 1`` of them; they are
        validated (:func:`cagegen.check_face_counts`), never reduced.
    fixed_levels : int
    ratio, min_faces
        Default face counts: ``n_faces / ratio**k``, the smallest ``>= min_faces``.

    Returns
    -------
    LevelsPlan
        ``note`` is one line when fewer levels than asked fit, e.g. "levels: 2 of the 3 asked fit 670
        faces at ratio 4 (smallest cage >= 100 faces)".

        An input too small for even one cage of ``min_faces`` keeps one cage level (no note):
        :func:`cagegen.build_cages` audits it, then refuses it with :class:`cagegen.LevelsError`.

    Raises
    ------
    cagegen.LevelsError
        One line naming the option: explicit ``face_counts`` that cannot be met (not decreasing, not
        below the input's faces, not one per cage level), or ``levels`` leaving no cage level.

    Examples
    --------
    >>> plan_levels(670, 3).note
    'levels: 2 of the 3 asked fit 670 faces at ratio 4 (smallest cage >= 100 faces)'
    >>> plan_levels(20000, 3).levels, plan_levels(670, 4, fixed_levels=1).levels
    (3, 3)
    """
    levels, fixed = int(levels), int(fixed_levels)
    n_surf = levels - fixed  # the input and its cages
    if face_counts is not None:
        counts = list(face_counts)
        shown = " ".join(str(c) for c in counts)
        try:
            counts = check_face_counts(counts, int(n_faces))
        except LevelsError as exc:
            raise LevelsError(f"--face-counts {shown} cannot be met on an input of {n_faces:,} faces: "
                              f"{exc}") from None
        if len(counts) != n_surf - 1:
            raise LevelsError(f"--face-counts {shown} gives {len(counts)} cage face counts, but --levels "
                              f"{levels} has {n_surf - 1} cage levels; give {n_surf - 1} counts or change --levels")
        return LevelsPlan(levels, levels, int(n_faces), float(ratio), int(min_faces), counts)
    if n_surf < 2:
        raise LevelsError(f"--levels {levels} leaves no cage level (levels >= {fixed + 2} needed here)")
    fit = fitting_levels(int(n_faces), n_surf, ratio, min_faces) if n_faces >= 4 else 1
    # not even one cage fits: keep one, and let cagegen.build_cages refuse it after its audit (a broken
    # small input is then named as such, a valid one gets "no cage fits ... asked for by face_counts")
    granted = levels - (n_surf - max(fit, 2))
    note = "" if granted == levels or fit < 2 else (
        f"levels: {granted} of the {levels} asked fit {n_faces:,} faces at ratio {ratio:g} "
        f"(smallest cage >= {min_faces} faces)")
    return LevelsPlan(levels, granted, int(n_faces), float(ratio), int(min_faces), None, note)


@dataclass
class SizingPlan:
    """Sizes of a hierarchy decided before any cage or tet mesh is built (lengths in the input's units).

    Attributes
    ----------
    edge_length : float
        Fine target edge length ``h_0``; level ``k`` uses ``h_0 * 2**k``.
    edge_lengths : list of float
        Target edge length per level.
    expected_tets : list of int
        Expected tets per level (cage levels use the fine volume: an underestimate by the cages'
        volume ratio, 1.0-1.5).
    peak_bytes : int
        Estimated peak memory of the largest meshing stage.
    expected_seconds : float
        Estimated seconds of the fine tet meshing (model in :func:`fine_mesh_seconds`).
    rule : str
        Which constraint set ``h_0``: ``"user"``, ``"input resolution"``, ``"thickness"``, ``"max_tets"``,
        ``"mesh_time_budget"``.
    notes : list of str
    levels : dict or None
        :meth:`LevelsPlan.to_dict` of the levels granted (``levels`` <= ``requested``; ``note``: the one
        line saying how many fit, when fewer than asked).
    """

    edge_length: float
    edge_lengths: list[float]
    expected_tets: list[int]
    peak_bytes: int
    expected_seconds: float
    rule: str
    notes: list[str] = field(default_factory=list)
    levels: dict | None = None

    @property
    def n_levels(self) -> int:
        """Levels granted (``len(edge_lengths)``)."""
        return len(self.edge_lengths)

    def to_dict(self) -> dict:
        """JSON-serialisable copy."""
        return asdict(self)


#: fTetWild seconds ~ A * input faces + B * output tets (2 threads). Measured here (docs/scale.md):
#: 111k-face bunny predecimated to 28.5k faces -> 252k-263k tets in 324-912 s on a shared machine,
#: ENVIRONMENT.md's idle figures 316k tets from 100k faces in 329 s, 1.06M in 614 s, 559k from 7k faces
#: in 437 s: ~0.6-1.2 ms per tet, ~1 ms per input face. The end-to-end runs of docs/scale.md (first
#: version, B = 0.8 ms) gave 0.38 / 0.61 / 1.15 ms per tet (bumpy-cube / bunny / a noisy gargoyle, with
#: 1 ms per face): B is now the slowest of them, so the budget holds on rough surfaces too.
TETWILD_SECONDS_PER_FACE = 1.0e-3
TETWILD_SECONDS_PER_TET = 1.2e-3


def _meshing_seconds(V, F, vol, h, mesher, meshed_fraction, mesh_edge_factor, surface_faces=None) -> float:
    """Estimated seconds of meshing the fine level at fine edge ``h`` (surface predecimated to its edge)."""
    if surface_faces is not None:
        faces = int(surface_faces)
    else:
        E = V[F[:, [1, 2, 0]]] - V[F]
        area = 0.5 * float(np.linalg.norm(np.cross(E[:, 0], -E[:, 2]), axis=1).sum())
        faces = min(len(F), int(area / (np.sqrt(3) / 4 * (mesh_edge_factor * h) ** 2)))
    return fine_mesh_seconds(faces, int(meshed_fraction * expected_tets(vol, h, mesher)), mesher)


def _resolution_edge(V: np.ndarray, F: np.ndarray, vol: float) -> tuple[float, str]:
    """The mesher's edge that the input asks for: its mean edge, at most its mean thickness ``V / A``.

    The mean edge follows the input's triangles, which on a CAD export (long slivers across flat
    faces) or a decimated low-poly model say nothing of the solid: round.stl's mean edge is 0.086 of
    the diagonal for a plate 0.005 thick, and TetWild, asked for that edge, refined where it had to
    (20x the expected tets, one cage level meshed as finely as the level inside it: operator complexity
    2.82). ``V / A`` (half the thickness of a plate, a third of a ball's radius) does not depend on the
    triangulation; a mesher's edge at most ``V / A`` puts about two tets across the solid.
    """
    E = V[F[:, [1, 2, 0]]] - V[F]
    mean_edge = float(np.linalg.norm(E, axis=2).mean())
    area = 0.5 * float(np.linalg.norm(np.cross(E[:, 0], -E[:, 2]), axis=1).sum())
    thickness = vol / area if area > 0 else mean_edge
    if thickness < mean_edge:
        return thickness, "thickness"
    return mean_edge, "input resolution"


def fine_mesh_seconds(n_faces: int, n_tets: int, mesher: str = "tetwild") -> float:
    """Rough wall-time estimate (2 cores) of meshing an ``n_faces`` surface into ``n_tets`` tets."""
    if mesher == "tetgen":
        return 1e-5 * n_tets + 1e-5 * n_faces
    return TETWILD_SECONDS_PER_FACE * n_faces + TETWILD_SECONDS_PER_TET * n_tets


def plan_hierarchy(
    V: np.ndarray,
    F: np.ndarray,
    levels: int,
    *,
    mesher: str = "tetwild",
    edge_length: float | None = None,
    max_tets: int | None = None,
    mesh_time_budget: float | None = None,
    memory_limit: int | str | None = None,
    min_edge_fraction: float = 1e-4,
    meshed_fraction: float = 1.0,
    mesh_edge_factor: float = 1.0,
    surface_faces: int | None = None,
    cage_input_faces: int | None = None,
    face_counts=None,
    fixed_levels: int = 0,
) -> SizingPlan:
    """Decide the levels and every level's target edge length from the budget, before any expensive stage.

    Parameters
    ----------
    V : (n,3) float array
    F : (m,3) int array
        The input surface (closed; any units).
    levels : int
        Number of levels asked: a ceiling (:func:`plan_levels` on ``len(F)``); the plan has the levels
        that fit (``plan.levels``, ``plan.n_levels``).
    mesher : {"tetwild", "tetgen"}
    edge_length : float, optional
        Fine target edge length in the input's units (the user's choice; then ``max_tets`` only
        applies if given explicitly).
    max_tets : int, optional
        Cap on the fine level's expected tets (default :data:`DEFAULT_MAX_TETS` when ``edge_length``
        is not given).
    mesh_time_budget : float, optional
        Seconds allowed for meshing the fine level (estimated by :func:`fine_mesh_seconds` on the
        predecimated surface); the fine edge is enlarged to fit. None: no time constraint.
    memory_limit : int or str, optional
        Bytes (or e.g. ``"8G"``); default ``$NESTMG_MEMORY_LIMIT`` or the available memory.
    min_edge_fraction : float
        Smallest accepted fine edge relative to the bounding-box diagonal (guards against typos).
    meshed_fraction : float
        Fraction of the fine tets the mesher itself makes (1/8 when the fine level is a red refinement of
        a mesh at twice the edge, ``nestmg.refine``); the time estimate uses it.
    mesh_edge_factor : float
        Edge of the mesh the mesher makes, relative to the fine edge (2 with refinement); the surface
        is predecimated to that edge, so the per-face part of the estimate uses it too.
    surface_faces : int, optional
        Faces the mesher will really get (when predecimation was refused); default: the input's faces
        or those of its predecimation to the meshed edge, whichever is fewer.
    cage_input_faces : int, optional
        Faces of the surface the cages are built around (default ``len(F)``; a solid with voids is caged by
        its outer surface, :mod:`nestmg.cavities`): the levels that fit are counted from them.
    face_counts : sequence of int, optional
        Explicit cage face counts (validated at once, see :func:`plan_levels`).
    fixed_levels : int
        Levels that are not cage layers (refined fine level, same-domain levels).

    Returns
    -------
    SizingPlan

    Raises
    ------
    cagegen.LevelsError
        Explicit ``face_counts`` that cannot be met.
    SizingError
        The request cannot fit (names the option to change): an explicit ``edge_length`` whose tets
        exceed an explicit ``max_tets``, or a budget too small for even a coarse mesh.
    nestmg.memory.TetMeshMemoryError
        The fine level would not fit in the memory available.
    """
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    if mesher not in COUNT_RATIO:
        raise NestmgInputError(f"unknown mesher {mesher!r}; choose from {sorted(COUNT_RATIO)}")
    lp = plan_levels(len(F) if cage_input_faces is None else int(cage_input_faces), levels,
                     face_counts=face_counts, fixed_levels=fixed_levels)
    levels = lp.levels
    from cagegen import bbox_diagonal

    diag = bbox_diagonal(V)  # overflow-safe
    vol = enclosed_volume(V, F)
    notes: list[str] = []
    if edge_length is not None:
        h = float(edge_length)
        if not (np.isfinite(h) and h > 0):
            raise SizingError(f"--edge-length must be positive, got {edge_length}")
        if h < min_edge_fraction * diag:
            raise SizingError(
                f"--edge-length {h:.3g} is below {min_edge_fraction:g} of the bounding-box diagonal ({diag:.3g}): "
                f"~{expected_tets(vol, h, mesher):.3g} tets; use a larger --edge-length")
        rule = "user"
        n0 = expected_tets(vol, h, mesher)
        if max_tets is not None and n0 > max_tets:
            raise SizingError(
                f"--edge-length {h:.3g} gives ~{n0:,} fine tets, more than --max-tets {max_tets:,}; use "
                f"--edge-length >= {edge_length_for_tets(V, F, max_tets, mesher):.3g} or raise --max-tets")
    else:
        cap = DEFAULT_MAX_TETS if max_tets is None else int(max_tets)
        if cap < 100:
            raise SizingError(f"--max-tets {cap} is too small for a multigrid hierarchy; use >= 100")
        h_in, rule = _resolution_edge(V, F, vol)
        h_in /= mesh_edge_factor  # the mesher's own edge (mesh_edge_factor x the fine edge)
        h_cap = edge_length_for_tets(V, F, cap, mesher)
        if h_in < h_cap:
            h, rule = h_cap, "max_tets"
        else:
            h = h_in
        if mesh_time_budget is not None:

            def secs(edge: float) -> float:
                return _meshing_seconds(V, F, vol, edge, mesher, meshed_fraction, mesh_edge_factor,
                                        surface_faces)

            if secs(h) > mesh_time_budget:
                # the estimate decreases with h: bisect for the finest edge that fits the budget
                lo, hi = h, h * 2.0
                while secs(hi) > mesh_time_budget:
                    lo, hi = hi, hi * 2.0
                    if hi > diag:
                        raise SizingError(
                            f"meshing this {len(F):,}-face input is estimated above the time budget of "
                            f"{mesh_time_budget:.0f} s at any size; raise --mesh-time-budget")
                for _ in range(30):
                    mid = 0.5 * (lo + hi)
                    if secs(mid) > mesh_time_budget:
                        lo = mid
                    else:
                        hi = mid
                h, rule = hi, "mesh_time_budget"
    n0 = expected_tets(vol, h, mesher)
    hs = [h * 2.0**k for k in range(levels)]
    ns = [max(expected_tets(vol, hk, mesher), 1) for hk in hs]
    if ns[-1] < 20:
        notes.append(f"the coarsest level has only ~{ns[-1]} tets; consider fewer levels")
    # peak memory of the largest stage with a 30% margin on the expected count (the per-tet bytes of
    # nestmg.memory are themselves upper bounds of the measurements)
    peak = estimate_tet_bytes(int(1.3 * meshed_fraction * n0), mesher)
    if meshed_fraction < 1.0:  # the refined fine level: its FEM matrices and ~200 B/tet of refinement arrays
        peak += int(1.3 * n0 * (FEM_BYTES_PER_NODE / 5.5 + 200))
    try:
        check_memory(peak, f"the {mesher} fine tet mesh (~{n0:,} tets at edge length {h:.3g})", limit=memory_limit)
    except InsufficientMemoryError as exc:
        raise TetMeshMemoryError(f"{exc}; use a larger --edge-length or a smaller --max-tets "
                                 f"(or raise $NESTMG_MEMORY_LIMIT)", n_tets=n0, needed=exc.needed,
                                 available=exc.available) from None
    return SizingPlan(edge_length=h, edge_lengths=hs, expected_tets=ns, peak_bytes=int(peak),
                      expected_seconds=_meshing_seconds(V, F, vol, h, mesher, meshed_fraction, mesh_edge_factor, surface_faces),
                      rule=rule, notes=notes, levels=lp.to_dict())
