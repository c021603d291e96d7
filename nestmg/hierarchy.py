"""Build a multigrid hierarchy from a closed surface: cages -> tet layers -> prolongations.

``build_hierarchy(V, F, levels=3, method="nested")`` runs the three stages of the pipeline

1. ``cagegen.build_cages``: surfaces ``(V_k, F_k)``, finest (the input) first, each cage certified to
   contain the previous layer (except for ``method="decimate"``, the naive baseline);
2. :func:`nestmg.tetmesh.tetrahedralize` on every layer, target edge length ``h_0 * 2**k``;
3. :func:`nestmg.prolongation.prolongation` between consecutive tet layers.

Certification happens at the tet level too: TetWild's boundary is only within ``epsilon`` of a cage,
so a fine node can fall just outside the coarse tet mesh. For certified methods the coarse layer is
then re-meshed with a 4x smaller envelope (at most ``MeshingOptions.tet_retries`` times); whatever remains is
extrapolated and reported as ``n_outside`` per level.
"""

from __future__ import annotations

import dataclasses
import sys
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
import scipy.sparse as sp

from .cache import cache_key, load_entry, save_entry
from .errors import NestmgInputError
from .memory import check_tet_memory
from .progress import Timer, stage_line, stages
from .prolongation import ProlongationReport, prolongation
from .refine import refine_tets
from .options import MeshingOptions, SizingOptions, as_dict, typed
from .sizing import edge_length_for_tets, plan_hierarchy
from .tetmesh import tetrahedralize

if TYPE_CHECKING:
    from cagegen import CageOptions, MeshAudit

__all__ = ["Hierarchy", "build_cage_surfaces", "build_hierarchy", "cage_options_for", "fine_envelope",
           "predecimate", "tet_hierarchy"]


@dataclass
class Hierarchy:
    """A geometric multigrid hierarchy (finest level first).

    Attributes
    ----------
    surfaces : list of (V, F)
        Layer surfaces; ``surfaces[0]`` is the input.
    tets : list of (V, T)
        Tet mesh of every layer: ``V`` (n_k,3) float, ``T`` (t_k,4) int.
    P : list of (n_k, n_{k+1}) csr_matrix
        ``P[k]`` prolongs level ``k+1`` to level ``k``; restriction is ``P[k].T``.
    prolongation_reports : list of ProlongationReport
        ``n_outside`` and extrapolation distance per level.
    method : str
        Cage backend used.
    cage_info : dict
        Backend figures and the nesting verifier's report.
    timings : dict
        Seconds per stage (``cages``, ``tets``, ``prolongation``).
    """

    surfaces: list[tuple[np.ndarray, np.ndarray]]
    tets: list[tuple[np.ndarray, np.ndarray]]
    P: list[sp.csr_matrix]
    prolongation_reports: list[ProlongationReport]
    method: str
    cage_info: dict = field(default_factory=dict)
    timings: dict = field(default_factory=dict)
    options: dict = field(default_factory=dict)
    frame: dict = field(default_factory=lambda: {"center": [0.0, 0.0, 0.0], "scale": 1.0})

    # ------------------------------------------------------------------ frames
    # ``surfaces`` and ``tets`` are in the input's (user's) coordinates; the pipeline works on a copy
    # centred at the origin with a unit bounding-box diagonal: user = scale * normalised + center.
    def to_normalized(self, V: np.ndarray) -> np.ndarray:
        """Points ``V`` (n,3) of the user's frame in the normalised frame (unit diagonal, centred)."""
        return (np.asarray(V, dtype=np.float64) - np.asarray(self.frame["center"])) / float(self.frame["scale"])

    def to_user(self, Vn: np.ndarray) -> np.ndarray:
        """Points ``Vn`` (n,3) of the normalised frame in the user's frame."""
        return np.asarray(Vn, dtype=np.float64) * float(self.frame["scale"]) + np.asarray(self.frame["center"])

    def _in_frame(self, layers: list, frame: str) -> list[tuple[np.ndarray, np.ndarray]]:
        if frame == "user":
            return list(layers)
        if frame == "normalized":
            return [(self.to_normalized(V), E) for V, E in layers]
        raise NestmgInputError(f"frame must be 'user' or 'normalized', got {frame!r}")

    def tets_in(self, frame: str = "user") -> list[tuple[np.ndarray, np.ndarray]]:
        """Tet layers in the ``"user"`` (input's) or ``"normalized"`` frame (same ``T`` arrays)."""
        return self._in_frame(self.tets, frame)

    def surfaces_in(self, frame: str = "user") -> list[tuple[np.ndarray, np.ndarray]]:
        """Surface layers in the ``"user"`` or ``"normalized"`` frame."""
        return self._in_frame(self.surfaces, frame)

    @property
    def levels(self) -> int:
        """Number of levels."""
        return len(self.tets)

    @property
    def n_outside(self) -> list[int]:
        """Fine nodes extrapolated (outside every coarse tet), per level pair."""
        return [r.n_outside for r in self.prolongation_reports]

    @property
    def surfaces_nested(self) -> bool | None:
        """Whether the cage verifier certified every surface pair (None when not run)."""
        ver = self.cage_info.get("verification")
        return None if ver is None else bool(ver.get("ok"))

    @property
    def fallbacks(self) -> list[dict]:
        """Cage layers built by a backend's fallback (e.g. ``{"layer": 2, "fallback": "lazy"}``); [] if none."""
        from cagegen.build import fallback_layers

        return fallback_layers(self.cage_info)

    @property
    def certified(self) -> bool:
        """True when the surfaces are certified nested *and* no fine node lies outside a coarse tet mesh."""
        return bool(self.surfaces_nested) and all(n == 0 for n in self.n_outside)

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable summary (no arrays)."""
        return {
            "method": self.method,
            "fallbacks": self.fallbacks,
            "levels": self.levels,
            "surface_faces": [len(F) for _, F in self.surfaces],
            "nodes": [len(V) for V, _ in self.tets],
            "tets": [len(T) for _, T in self.tets],
            "prolongation": [r.to_dict() for r in self.prolongation_reports],
            "n_outside": self.n_outside,
            "surfaces_nested": self.surfaces_nested,
            "certified": self.certified,
            "timings": self.timings,
            "cage_info": self.cage_info,
            "options": self.options,
            "frame": {"center": [float(c) for c in self.frame["center"]], "scale": float(self.frame["scale"])},
        }

    def __repr__(self) -> str:
        fb = "".join(f", layer {d['layer']} by fallback {d['fallback']!r}" for d in self.fallbacks)
        lines = [f"Hierarchy(method={self.method!r}{fb}, levels={self.levels}, certified={self.certified})",
                 "level  faces     nodes      tets   nnz(P)  n_outside"]
        for k, ((_, F), (V, T)) in enumerate(zip(self.surfaces, self.tets)):
            nnz = self.P[k].nnz if k < len(self.P) else 0
            nout = self.n_outside[k] if k < len(self.P) else 0
            lines.append(f"{k:>5} {len(F):>6} {len(V):>9} {len(T):>9} {nnz:>8} {nout:>10}")
        return "\n".join(lines)


def _bbox_diag(V: np.ndarray) -> float:
    from cagegen import bbox_diagonal

    return bbox_diagonal(np.asarray(V, dtype=np.float64))  # overflow-safe


def _mesh_layer(V, F, mesher, h, epsilon, use_cache, tetwild_kwargs=None, layer=None):
    """Tet-mesh one layer, through the cache."""
    tw = dict(tetwild_kwargs or {}) if mesher == "tetwild" else {}
    opts = {"stage": "tets", "mesher": mesher, "h": round(h, 12), "epsilon": epsilon, **tw}
    key = cache_key([V, F], opts)
    if use_cache:
        hit = load_entry(key)
        if hit is not None:
            return hit[0]["V"], hit[0]["T"]
    check_tet_memory(V, F, h, mesher, layer=layer)  # refuse before meshing a layer that would not fit
    Vt, T = tetrahedralize(V, F, mesher=mesher, edge_length_abs=h, epsilon=epsilon, **tw)
    if use_cache:
        save_entry(key, {"V": Vt, "T": T}, opts)
    return Vt, T


def _fine_edge(V0: np.ndarray, F0: np.ndarray, sizing: SizingOptions, edge_length_abs: float | None) -> float:
    """Fine target edge: absolute, relative to ``V0``'s diagonal, or the input surface's mean edge."""
    if edge_length_abs is not None:
        return float(edge_length_abs)
    if sizing.edge_length is not None:
        return sizing.edge_length * _bbox_diag(V0)
    return float(np.linalg.norm(V0[F0[:, 1]] - V0[F0[:, 0]], axis=1).mean())  # the input's resolution


def tet_hierarchy(
    surfaces: list[tuple[np.ndarray, np.ndarray]],
    *,
    sizing: SizingOptions | None = None,
    meshing: MeshingOptions | None = None,
    edge_length_abs: float | None = None,
    cache: bool = True,
    progress: bool | None = None,
    t0: float | None = None,
    fine: tuple[np.ndarray, np.ndarray] | None = None,
    fine_epsilon: float | None = None,
) -> tuple[list, list, list, dict]:
    """Tet-mesh every surface layer and build the prolongations between consecutive layers.

    Parameters
    ----------
    surfaces : list of (V, F)
        Closed surfaces, finest first (each coarser one meant to contain the previous).
    sizing : SizingOptions, optional
        ``edge_length`` (fine target edge relative to the bounding-box diagonal of ``surfaces[0]``;
        default: the mean edge length of the input surface, so the fine tets match its resolution),
        ``coarsening`` (None: level ``k`` is meshed at ``h_0 * 2**k``; a number: each *cage* level's
        edge length is chosen from its enclosed volume so that it is expected to have ``coarsening``
        times fewer tets than the level below it actually has -- cages enclose more volume than their
        inner layer, so plain doubling coarsens by less than 8x; same-domain levels always double) and
        ``same_domain_levels`` (how many of the first coarse surfaces are the input again). The other
        fields are :func:`build_hierarchy`'s.
    meshing : MeshingOptions, optional
        Mesher, envelope, extrapolation rule, TetWild knobs; ``tet_retries`` (default 2): with TetWild,
        re-mesh a coarse layer with a 4x smaller envelope while fine nodes remain outside it.
    edge_length_abs : float, optional
        Fine target edge in the surfaces' units (overrides ``sizing.edge_length``).
    cache : bool
        Reuse tet meshes from the on-disk cache.
    progress : bool or None
        Show a progress bar (None: only on a terminal). Stage lines go to the ``nestmg`` logger.
    t0 : float, optional
        ``time.perf_counter()`` at the start of the run, for the elapsed time of the stage lines.
    fine : (V, T), optional
        The caller's own tet mesh of ``surfaces[0]``, used as level 0 unchanged instead of meshing it
        (:func:`nestmg.usermesh.hierarchy_from_tets`).
    fine_epsilon : float, optional
        TetWild's envelope for the levels whose surface is ``surfaces[0]`` (a predecimated input:
        :func:`fine_envelope`); default ``meshing.epsilon``.

    Returns
    -------
    tets : list of (V, T)
    P : list of csr_matrix
    reports : list of ProlongationReport
    timings : dict
        ``tets`` and ``prolongation`` seconds, ``tet_seconds`` and ``edge_lengths`` per level,
        ``tet_retries`` and ``epsilon`` per level.
    """
    sizing, meshing = sizing or SizingOptions(), meshing or MeshingOptions()
    mesher, coarsening, n_same = meshing.mesher, sizing.coarsening, sizing.same_domain_levels
    tet_retries = 2 if meshing.tet_retries is None else meshing.tet_retries
    timer = Timer()
    t0 = time.perf_counter() if t0 is None else t0
    n = len(surfaces)
    tets: list = [None] * n
    hs = [_fine_edge(*surfaces[0], sizing, edge_length_abs)] * n
    eps = [meshing.epsilon] * n
    if fine_epsilon is not None:  # the levels meshed from the input itself
        eps = [fine_epsilon if S is surfaces[0] else e for S, e in zip(surfaces, eps)]
    retries = [0] * n
    t_level = [0.0] * n
    Ps, reps = [], []
    tw = meshing.tetwild_kwargs()

    def mesh(k):
        t = time.perf_counter()
        # coarse TetWild levels are coarsened (else a cage's boundary triangles keep 2-8x the tets asked)
        twk = dict(tw, coarsen=True) if (k > 0 and meshing.coarsen_coarse and mesher == "tetwild") else tw
        if k > 0 and mesher == "tetwild":  # bounded passes on the cage levels (see COARSE_MAX_OPT_ITER)
            twk = dict(twk, max_opt_iter=min(meshing.max_opt_iter, meshing.coarse_max_opt_iter))
        with timer("tets"):
            tets[k] = _mesh_layer(*surfaces[k], mesher, hs[k], eps[k], cache, twk, layer=k)
        t_level[k] += time.perf_counter() - t
        stage_line(f"tets level {k}: {len(tets[k][1]):,} tets / {len(tets[k][0]):,} nodes "
                   f"(edge {hs[k]:.3g}, {mesher}, {time.perf_counter() - t:.1f} s)", t0)

    def prolong(k):
        with timer("prolongation"):
            return prolongation(tets[k - 1][0], tets[k][0], tets[k][1], extrapolation=meshing.extrapolation)

    with stages(n, "tet layers", progress) as bar:
        for k, (V, F) in enumerate(surfaces):
            bar.describe(f"tet layer {k} ({len(F)} faces, {mesher})")
            if k > 0:
                if coarsening is None or k <= n_same:
                    hs[k] = hs[k - 1] * 2.0
                else:  # aim at `coarsening` x fewer tets than level k-1 really has
                    want = max(len(tets[k - 1][1]) / float(coarsening), 50)
                    hs[k] = max(edge_length_for_tets(V, F, int(want), mesher), hs[k - 1])
            if k == 0 and fine is not None:  # the caller's own fine tet mesh, kept as it is
                tets[0] = fine
            else:
                mesh(k)
            bar.advance()
            if k == 0:
                continue
            P, rep = prolong(k)
            while rep.n_outside > 0 and mesher == "tetwild" and retries[k] < tet_retries:
                retries[k] += 1
                eps[k] /= 4
                stage_line(f"level {k}: {rep.n_outside} fine nodes outside; re-meshing with epsilon {eps[k]:.2g}", t0)
                mesh(k)
                P, rep = prolong(k)
            stage_line(f"prolongation {k - 1}<-{k}: {P.shape[0]:,} x {P.shape[1]:,}, n_outside {rep.n_outside}", t0)
            Ps.append(P)
            reps.append(rep)
    timings = dict(timer.seconds)
    timings["tet_retries"] = retries
    timings["epsilon"] = eps
    timings["edge_lengths"] = hs
    timings["tet_seconds"] = t_level
    return tets, Ps, reps, timings


def cage_options_for(method: str, cages: CageOptions | None, meshing: MeshingOptions) -> CageOptions:
    """The cage options a hierarchy uses: ``cages`` (default: the method's defaults) with its clearance.

    With TetWild and a certified method, ``min_gap`` None becomes ``2.5 * meshing.epsilon``: TetWild's
    boundary is only within ``epsilon`` (relative to each layer's bbox diagonal) of its input, outward on
    the fine layer and inward on the cage, so that clearance keeps every fine node inside the coarse tet
    mesh (tet-level nesting).

    Raises
    ------
    cagegen.CageOptionError
        ``cages`` is not an instance of the method's options class.
    """
    import cagegen

    cls = cagegen.options_class(method)
    if cages is None:
        cages = cls()
    elif not isinstance(cages, cls):
        raise cagegen.CageOptionError(f"method {method!r} takes cagegen.{cls.__name__}, got "
                                      f"{type(cages).__name__}")
    if cages.min_gap is None and meshing.mesher == "tetwild" and method not in cagegen.UNCERTIFIED_METHODS:
        cages = dataclasses.replace(cages, min_gap=2.5 * meshing.epsilon)
    return cages


#: :func:`fine_envelope` is at most this many ``epsilon``: the cages keep ``2.5 epsilon`` from the input, so
#: the input's level standing ``2 epsilon`` out and a cage level re-meshed at ``epsilon / 4`` (the tet-level
#: retry) still nest. Widening the clearance instead, to ``1.25 (envelope + epsilon)``, failed lucy.ply's
#: nested cage at 0.0032 (its thin wings; the sdf fallback then ran for minutes).
FINE_ENVELOPE_CAP = 2.0


def fine_envelope(meshing: MeshingOptions, predecimation: dict) -> float:
    """TetWild's envelope for the levels meshed from a predecimated input: its Hausdorff error, within
    ``[epsilon, FINE_ENVELOPE_CAP epsilon]``.

    The predecimated surface is within its Hausdorff error of the input (:func:`predecimate`, at most
    ``max(epsilon, h/4)``); held to a tighter ``epsilon`` of it, TetWild makes tets follow what the
    predecimation kept of a scan's noise (docs/scale.md). An input meshed as it is keeps ``epsilon``.
    """
    eps = float(meshing.epsilon)
    if meshing.mesher != "tetwild" or predecimation.get("faces_out", 0) >= predecimation.get("faces_in", 0):
        return eps
    return min(max(eps, float(predecimation.get("hausdorff") or 0.0)), FINE_ENVELOPE_CAP * eps)


def build_cage_surfaces(
    V: np.ndarray,
    F: np.ndarray,
    levels: int,
    method: str = "nested",
    *,
    sizing: SizingOptions | None = None,
    meshing: MeshingOptions | None = None,
    cages: CageOptions | None = None,
    cache: bool = True,
    progress: bool | None = None,
    t0: float | None = None,
    audit: MeshAudit | None = None,
) -> tuple[list[tuple[np.ndarray, np.ndarray]], dict]:
    """The cage layers of a hierarchy, exactly as :func:`build_hierarchy` builds them (same clearance).

    ``nestmg cages`` and ``nestmg solve`` both go through this function. The input is normalised
    inside (centred, unit bounding-box diagonal) and the layers are returned in the input's coordinates.

    Parameters
    ----------
    V : (n,3) float array
    F : (m,3) int array
        Closed input surface, in the user's coordinates.
    levels : int
        Number of surfaces asked, input included: a ceiling (:func:`nestmg.sizing.plan_levels`); a small
        input gets those that fit, with one stage line saying so and ``info["levels"]`` recording it.
    method : str
        Cage backend (:func:`cagegen.build_cages`).
    sizing : SizingOptions, optional
        Only ``face_counts`` is used (explicit face counts are checked before any work).
    meshing : MeshingOptions, optional
        The tet mesher the layers are meant for: it sets the default clearance (:func:`cage_options_for`).
    cages : cagegen.CageOptions, optional
        The method's options (its class: ``cagegen.options_class(method)``).
    cache : bool
        Reuse cages from the on-disk cache (keyed on the normalised input and the options).
    progress : bool or None
        Progress bars (None: only on a terminal).
    t0 : float, optional
        ``time.perf_counter()`` the stage lines' elapsed seconds count from (default: this call's start).
    audit : cagegen.MeshAudit, optional
        A passed audit of ``(V, F)`` (:func:`cagegen.check_mesh`), handed to :func:`cagegen.build_cages`
        so that the input is audited once per run; used when the normalised copy is ``V`` itself (an
        input already normalised, as :func:`build_hierarchy`'s), else the copy is audited.

    Returns
    -------
    surfaces : list of (V_k, F_k)
        In the input's coordinates, input first.
    info : dict
        The backend's and verifier's info, plus ``frame`` (``center``, ``scale``) and ``cage_options``.
    """
    import cagegen

    from .cavities import merge_surfaces
    from .sizing import plan_levels

    sizing, meshing = sizing or SizingOptions(), meshing or MeshingOptions()
    cages = cage_options_for(method, cages, meshing)
    face_counts = None if sizing.face_counts is None else list(sizing.face_counts)
    V = np.ascontiguousarray(V, dtype=np.float64)
    F = np.ascontiguousarray(F, dtype=np.int64)
    if face_counts is not None:  # explicit counts that cannot be met fail in microseconds, before any repair
        plan_levels(len(F), levels, face_counts=face_counts)
    t_repair = time.perf_counter()
    V, F, solid, audited = _solid_input(V, F, cages, meshing, t0)
    t_repair = time.perf_counter() - t_repair
    V_all, F_all, voids = V, F, _voids(V, F, meshing, t0)
    if voids is not None:  # a solid with voids: the cages of its outer surface contain it
        V, F = voids["outer"]
        audited = None
    if audited is not None:  # a scan closed and audited in its normalised frame: the same arrays go on
        Vn, center, scale, given = audited
    else:
        Vn, center, scale = _normalize(V)
        given = audit if audit is not None and np.array_equal(Vn, V) else None
    # `levels` is a ceiling (the levels that fit F's faces, one line when fewer); explicit face counts are
    # checked here, before the audit: both in microseconds
    lp = plan_levels(len(F), levels, face_counts=face_counts)
    if lp.note:
        stage_line(lp.note, t0)
    levels = lp.levels
    key = cache_key([Vn, F], {"stage": "cages", "method": method, "levels": levels,
                              "face_counts": face_counts, "cages": as_dict(cages)})
    hit = load_entry(key) if cache else None
    if hit is not None:
        arrays, info = hit
        surfaces = [(arrays[f"V{k}"], arrays[f"F{k}"]) for k in range(levels)]
        info = dict(info, cached=True)
    else:
        t_start = time.perf_counter()
        t0 = t_start if t0 is None else t0
        cage_progress = progress
        if progress is None:
            # a terminal: the backend's own bars; a log or a pipe: its per-layer messages as stage lines
            # (silent unless the `nestmg` logger has a handler, which the CLI installs off a terminal)
            cage_progress = True if sys.stderr.isatty() else (lambda msg: stage_line(f"cages ({method}): {msg}", t0))
        surfaces, info = cagegen.build_cages(Vn, F, levels, method=method, face_counts=face_counts,
                                             return_info=True, progress=cage_progress, options=cages,
                                             audit=given)
        info = dict(info, seconds=time.perf_counter() - t_start)
        if cache:
            arrays = {}
            for k, (Vk, Fk) in enumerate(surfaces):
                arrays[f"V{k}"], arrays[f"F{k}"] = Vk, Fk
            save_entry(key, arrays, info)
    # the input layer is the caller's own array (bit for bit, unless repaired), the cages are mapped back
    V0, F0 = surfaces[0]
    same = V0.shape == Vn.shape and F0.shape == F.shape and np.array_equal(F0, F)
    out = [(V, F) if same else (V0 * scale + center, F0)] + [(Vk * scale + center, Fk) for Vk, Fk in surfaces[1:]]
    info = dict(info, frame={"center": center.tolist(), "scale": scale}, cage_options=as_dict(cages),
                levels=lp.to_dict())
    if solid is not None:
        info["solid"] = dict(solid, repair_seconds=t_repair)  # the whole repair, its audits included
    if voids is not None:  # the input layer is the whole solid, voids included
        out[0] = (V_all, F_all) if same else merge_surfaces([out[0], voids["voids"]])
        info["voids"] = {"count": voids["count"], "faces": len(voids["voids"][1])}
    return out, info


def _voids(V: np.ndarray, F: np.ndarray, meshing: MeshingOptions, t0) -> dict | None:
    """A solid with voids (:func:`nestmg.cavities.hollow_solid`): ``outer`` and ``voids`` surfaces (each
    ``(V, F)``, the voids audited), their ``count``; None for any other input (one stage line when found)."""
    from .cavities import audit_voids

    hollow = audit_voids(V, F, outer=False)  # the outer surface is audited where the pipeline audits inputs
    if hollow is None:
        return None
    outer, voids, count = hollow
    if meshing.mesher != "tetwild":
        raise NestmgInputError(f"input: a solid with {count} void(s): mesher={meshing.mesher!r} would fill "
                               "them; mesh it with TetWild (the default), which keeps them")
    stage_line(f"input: a solid with {count} void(s) ({len(voids[1]):,} faces): cages of its outer surface "
               f"({len(outer[1]):,} faces), the voids in the levels meshed from the input", t0)
    return {"outer": outer, "voids": voids, "count": count}


class _Solid(NamedTuple):
    """:func:`_solid_input`'s result: the surface to cage (user's coordinates), what was mended (None:
    nothing) and, for a scan whose holes were closed, ``audited = (Vn, center, scale, audit)``: the
    normalised surface (``V = Vn * scale + center``) and its passed audit, self-intersection test included."""

    V: np.ndarray
    F: np.ndarray
    info: dict | None = None
    audited: tuple | None = None


def _solid_input(V: np.ndarray, F: np.ndarray, cages, meshing: MeshingOptions, t0) -> _Solid:
    """With ``repair`` on, an input whose audit fails for what TetWild can mend (overlapping bodies,
    self-intersections, pinches) is replaced by the boundary of its solid: the exact union of its pieces
    when they are clean closed parts that overlap (:func:`nestmg.solid.exact_union`), else the boundary of
    TetWild's solid (:func:`nestmg.solid.solid_surface`); a scan whose only problem is an open boundary gets
    its holes closed.

    Returns a :class:`_Solid`: the input itself and ``info`` None when nothing had to be mended. One stage
    line says what was done; several disjoint bodies are refused with a one-line error.
    """
    import cagegen

    from .memory import signed_volume
    from .solid import REPAIR_MAX_FACES, UNREPAIRABLE, exact_union, fill_holes, solid_surface

    if not getattr(cages, "repair", False):
        return _Solid(V, F)
    from .cavities import hollow_solid, orient_by_nesting

    if hollow_solid(V, F) is not None:
        return _Solid(V, F)  # a solid with voids is no defect (the repair would fill them): nestmg.cavities
    voids = orient_by_nesting(V, F)  # nested pieces facing out: the inner ones read as voids (even-odd)
    if voids is not None:
        stage_line("repair: pieces inside an odd number of others are voids: turned to face them", t0)
        return _Solid(V, voids)
    Vn, center, scale = _normalize(V)  # TetWild works in the normalised frame
    v_in = signed_volume(Vn, F)  # as given (before the cheap repairs re-orient anything)
    Vr, Fr = cagegen.repair_mesh(Vn, F)
    # the exact self-intersection test (~1 s per 10k faces) once: a scan with holes is tested once closed
    audit = cagegen.audit_mesh(Vr, Fr, self_intersections=False)
    if [p.split(":")[0] for p in audit.problems] == ["open boundary"]:  # a scan's holes, nothing else: close them
        t = time.perf_counter()
        Vr, Fr, holes = fill_holes(Vr, Fr)
        audit = cagegen.audit_mesh(Vr, Fr)
        problems = audit.problems
        stage_line(f"repair: open boundary -> {holes['holes']} hole(s) closed by {holes['patch_faces']:,} faces "
                   f"({holes['patch_area_fraction']:.2%} of the area; least folding, then least area)"
                   + (f"; still: {', '.join(p.split(':')[0] for p in problems)}" if problems else ""), t0)
        if not problems:
            volume = signed_volume(Vr, Fr) * scale**3
            info = dict(holes, method="holes", problems=["open boundary"], faces_in=len(F), faces_out=len(Fr),
                        tets=0, bodies=1, pinch_rounds=0, volume=volume, volume_dropped=0.0, volume_filled=0.0,
                        decimated=None, volume_change=None, seconds=time.perf_counter() - t)
            # the audited normalised copy goes on: the cages need no second test of the same surface
            return _Solid(Vr * scale + center, Fr, info, (Vr, center, scale, audit))
    else:
        problems = cagegen.audit_self_intersections(audit, Vr, Fr).problems
    if not problems or any(p.startswith(UNREPAIRABLE) for p in problems):
        return _Solid(V, F)  # clean (the cheap repairs suffice), or nothing TetWild can mend: audited later
    _refuse_disjoint_bodies(Vr, Fr)  # in seconds, before TetWild would find them
    names = [p.split(":")[0] for p in problems]
    t = time.perf_counter()
    union = exact_union(Vr, Fr)  # clean closed parts that overlap: their exact union, no envelope
    if union is None:
        stage_line(f"repair: {', '.join(names)}; meshing the solid the {len(Fr):,}-face input encloses with "
                   "TetWild" + (f" (decimated towards {REPAIR_MAX_FACES:,} faces first, within its envelope)"
                                if len(Fr) > REPAIR_MAX_FACES else ""), t0)
    W, G, info = union or solid_surface(Vr, Fr, epsilon=meshing.epsilon)
    W = W * scale + center
    info = dict(info, volume=info["volume"] * scale**3, volume_dropped=info["volume_dropped"] * scale**3,
                volume_filled=info["volume_filled"] * scale**3)
    info["problems"] = names
    info["seconds"] = time.perf_counter() - t
    if info["bodies"] > 1:
        raise cagegen.MeshInputError(
            f"input: {info['bodies']} separate bodies (after the repair of: {', '.join(info['problems'])}); "
            "a hierarchy is built for one solid: nestmg.bodies.build_body_hierarchies builds one per body (as "
            "`nestmg solve` and `nestmg cages` do)")
    dropped, filled = info["volume_dropped"] / info["volume"], info["volume_filled"] / info["volume"]
    # against the input's own signed volume (a cavity the cheap repair turned outward and TetWild filled,
    # overlaps counted once): None when the input's orientation gives no volume
    info["volume_change"] = info["volume"] / (v_in * scale**3) - 1.0 if v_in > 0 else None
    change = "" if info["volume_change"] is None else f", volume {info['volume_change']:+.2%} against the input's"
    dec = info.get("decimated")
    if dec and dec["faces_out"] < dec["faces_in"]:
        change += f"; TetWild got it decimated to {dec['faces_out']:,} faces (Hausdorff {dec['hausdorff']:.2g})"
    how = "the exact union of the overlapping parts" if union else "the boundary of the solid TetWild meshed"
    stage_line(f"repair: {', '.join(info['problems'])} -> {how}: "
               f"{len(F):,} -> {len(G):,} faces, volume dropped {dropped:.2%}, voids filled {filled:.2%}{change} "
               f"({info['seconds']:.1f} s)", t0)
    return _Solid(W, G, info)


def _refuse_disjoint_bodies(V: np.ndarray, F: np.ndarray) -> None:
    """One line for an input of several bodies that neither overlap nor nest: no repair makes them one solid."""
    import cagegen
    from cagegen.components import check_components_disjoint

    pieces = cagegen.split_components(V, F)
    if len(pieces) < 2:
        return
    try:
        check_components_disjoint(pieces)
    except cagegen.MeshInputError:
        return  # overlapping or nested pieces: TetWild's solid is their union
    raise cagegen.MeshInputError(
        f"input: {len(pieces)} disjoint bodies; a hierarchy is built for one solid: "
        "nestmg.bodies.build_body_hierarchies builds one per body (as `nestmg solve` and `nestmg cages` do)")


def predecimate(V: np.ndarray, F: np.ndarray, edge_length: float, *, edge_ratio: float = 1.0,
                min_reduction: float = 0.6, max_error: float | None = None) -> tuple[np.ndarray, np.ndarray, dict]:
    """Decimate a surface much finer than the tets it will be meshed into (a cheaper fine mesh).

    TetWild's time grows with the input surface's size, not only with the tets (docs/scale.md): a
    100k-face scan meshed at an edge several times its own costs minutes in envelope tests for
    triangles far smaller than a tet. The surface is decimated (QEM, :func:`cagegen.decimate.decimate_surface`:
    watertight, same genus, no self-intersection) to a mean edge of about ``edge_length / edge_ratio``
    when that removes at least ``1 - min_reduction`` of the faces; otherwise it is returned unchanged.

    Parameters
    ----------
    V : (n,3) float array
    F : (m,3) int array
        Closed surface.
    edge_length : float
        Target tet edge length (absolute).
    edge_ratio : float
        Surface edges kept ``edge_ratio`` times finer than the tets.
    min_reduction : float
        Decimate only if the target face count is below ``min_reduction * len(F)``.
    max_error : float, optional
        Largest accepted Hausdorff distance between the input and the decimated surface (absolute);
        the pipeline passes half of TetWild's envelope, so the fine tets stay within 1.5 epsilon of the
        input. Exceeded: the face count is doubled (at most twice), then the surface is left unchanged.

    Returns
    -------
    V2, F2 : arrays
        The (possibly) decimated surface.
    info : dict
        ``faces_in``, ``faces_out``, ``seconds``, ``hausdorff`` (absolute, input vs result).
    """
    import time as _time

    from cagegen.decimate import decimate_surface

    t = _time.perf_counter()
    E = V[F[:, [1, 2, 0]]] - V[F]
    area = 0.5 * float(np.linalg.norm(np.cross(E[:, 0], -E[:, 2]), axis=1).sum())
    # equilateral triangles of edge l have area sqrt(3)/4 l^2
    target = int(area / (np.sqrt(3) / 4 * (edge_length / edge_ratio) ** 2))
    info = {"faces_in": len(F), "faces_out": len(F), "seconds": 0.0, "hausdorff": 0.0}
    import igl

    for _ in range(3):  # the QEM error of a smooth surface roughly halves when the faces double
        if target >= min_reduction * len(F) or target < 1000:
            break
        # QEM with libigl's intersection-blocking collapses: plain qslim leaves self-intersections on
        # detailed scans and the fallback (shortest-edge midpoints) errs 10x more (docs/scale.md)
        U, G, dinfo = decimate_surface(V, F, target, decimator="qslim", block_intersections=True)
        err = float(igl.hausdorff(V, F, U, G))
        if max_error is None or err <= max_error:
            info.update(faces_out=len(G), seconds=_time.perf_counter() - t, hausdorff=err,
                        decimator=dinfo.get("decimator"))
            return U, G, info
        info.setdefault("rejected", []).append({"faces": len(G), "hausdorff": err})
        target *= 2
    info["seconds"] = _time.perf_counter() - t
    return V, F, info


def _normalize(V: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Centre the bounding box and scale its diagonal to 1 (clear error for empty / NaN / flat input)."""
    from cagegen.errors import MeshInputError

    if V.ndim != 2 or V.shape[1] != 3 or len(V) == 0:
        raise MeshInputError(f"input: vertices must be a non-empty (n,3) array, got shape {V.shape}")
    if not np.isfinite(V).all():
        raise MeshInputError(f"input: {int((~np.isfinite(V)).any(axis=1).sum())} vertices have NaN/inf coordinates")
    from cagegen import bbox_diagonal, normalize

    scale = bbox_diagonal(V)  # overflow-safe (no squaring of 1e154 extents, no numpy warning)
    if not (np.isfinite(scale) and scale > 0):
        raise MeshInputError(f"input: bounding-box diagonal {scale} (all vertices coincide, or overflow)")
    # the audit's scale rules apply to the input as given (the normalised copy would hide them)
    from cagegen.audit import MAX_DIAG, MAX_OFFSET, MIN_DIAG

    if not MIN_DIAG <= scale <= MAX_DIAG:
        raise MeshInputError(f"input: absurd size: bounding-box diagonal {scale:.3g} outside [{MIN_DIAG:g}, "
                             f"{MAX_DIAG:g}]; rescale")
    offset = float(np.abs(V).max())
    if offset > MAX_OFFSET * scale:
        raise MeshInputError(f"input: absurd size: mesh of diagonal {scale:.3g} sits {offset:.3g} from the origin "
                             "(float64 precision lost); translate it")
    return normalize(V, scale)


def _fine_level(levels: int, sizing: SizingOptions, mesher: str) -> tuple[str, bool]:
    """The fine-level rule (``sizing.fine_level`` or the mesher's default) and whether it refines."""
    fine_level = sizing.fine_level
    if fine_level is None:
        # TetGen's radius-edge meshes keep slivers, and refining them keeps them too (torus: two-grid
        # factor 0.73 refined vs 0.53 meshed directly, docs/scale.md); TetGen is fast at any size anyway
        fine_level = "refine" if mesher == "tetwild" else "mesh"
    n_same, fc = sizing.same_domain_levels, sizing.face_counts
    # keep at least one cage level; face counts given for every coarse level mean "all cages"
    refine = (fine_level == "refine" and levels - n_same >= 3
              and (fc is None or len(fc) != levels - n_same - 1))
    if not n_same <= levels - 2:
        raise NestmgInputError(
            f"same_domain_levels must be an integer in [0, levels - 2] = [0, {levels - 2}] (at least one "
            f"cage level), got {n_same!r}"
        )
    return fine_level, refine


def _plan(Vn, F, levels, sizing: SizingOptions, mesher: str, refine: bool, **extra):
    """:func:`nestmg.sizing.plan_hierarchy` for these options (milliseconds, before any expensive stage)."""
    return plan_hierarchy(Vn, F, levels, mesher=mesher, edge_length=sizing.edge_length,
                          max_tets=sizing.max_tets, mesh_time_budget=sizing.mesh_time_budget,
                          meshed_fraction=0.125 if refine else 1.0,
                          mesh_edge_factor=2.0 if refine else 1.0,
                          face_counts=None if sizing.face_counts is None else list(sizing.face_counts),
                          fixed_levels=sizing.same_domain_levels + int(refine), **extra)


def _predecimated(Vn, F, levels, plan, sizing, meshing, cages, refine, timer, t0):
    """The surface actually meshed: an input much finer than the tets is decimated first (QEM, error below
    half of TetWild's envelope), so neither TetWild nor the cages pay for detail no tet can see.

    Returns ``(S0, F0, info, plan, audit)``; the plan is redone when the decimation is refused (TetWild
    then meshes every input face), still before any cage. ``audit``: the input's audit (done before the
    decimation) when the input itself is meshed, for :func:`cagegen.build_cages` not to repeat it.
    """
    import cagegen

    S0, F0, pre = Vn, F, {"faces_in": len(F), "faces_out": len(F), "hausdorff": 0.0}
    audit = None
    if not (sizing.predecimate and meshing.mesher == "tetwild"):
        return S0, F0, pre, plan, audit
    epsilon = meshing.epsilon
    with timer("predecimate"):
        E = Vn[F[:, [1, 2, 0]]] - Vn[F]
        area = 0.5 * float(np.linalg.norm(np.cross(E[:, 0], -E[:, 2]), axis=1).sum())
        h_mesh = plan.edge_length * (2.0 if refine else 1.0)  # the edge TetWild is asked for
        if area / (np.sqrt(3) / 4 * h_mesh**2) < 0.6 * len(F):
            Va, Fa, audit = cagegen.check_mesh(Vn, F, repair=bool(cages.repair), name="input",
                                               return_audit=True)
            if not (np.array_equal(Va, Vn) and np.array_equal(Fa, F)):
                audit = None  # repaired: the audit is of other arrays than the ones meshed
            # error bound: TetWild's envelope, or a quarter of the meshed edge if larger (detail below
            # that is not resolved by the tets anyway, e.g. a scan's noise)
            S0, F0, pre = predecimate(Vn, F, h_mesh, max_error=max(epsilon, 0.25 * h_mesh))
    if pre["faces_out"] < pre["faces_in"]:
        stage_line(f"predecimation: {pre['faces_in']:,} -> {pre['faces_out']:,} faces, Hausdorff "
                   f"{pre['hausdorff']:.2g} of the diagonal ({timer.seconds['predecimate']:.1f} s)", t0)
    elif pre.get("rejected"):
        errors = [round(r["hausdorff"], 4) for r in pre["rejected"]]
        stage_line(f"predecimation refused (Hausdorff {errors} > {max(epsilon, 0.25 * h_mesh):.3g}); keeping "
                   f"the {len(F):,} input faces", t0)
        plan = _plan(Vn, F, levels, sizing, meshing.mesher, refine, surface_faces=len(F))
        stage_line(f"sizing (again): fine edge {plan.edge_length:.3g} ({plan.rule}), expected tets "
                   f"{[f'{n:,}' for n in plan.expected_tets]}", t0)
    return S0, F0, pre, plan, audit if (S0 is Vn and F0 is F) else None


def _refined_fine_level(tets_n, Ps, reps, surfaces_n, tt, plan, timer, t0):
    """Prepend the fine level: one red refinement of the mesh at 2 h_0 (exactly nested, exact P)."""
    with timer("refine"):
        tr = time.perf_counter()
        Vr, Tr, Pr = refine_tets(*tets_n[0])
        rep0 = ProlongationReport(n_fine=len(Vr), n_coarse=len(tets_n[0][0]), n_outside=0, n_on_boundary=0,
                                  max_distance=0.0, max_distance_rel=0.0, extrapolation="none (refinement)",
                                  seconds=time.perf_counter() - tr)
    tt["edge_lengths"] = [plan.edge_length] + tt["edge_lengths"]
    tt["tet_seconds"] = [timer.seconds["refine"]] + tt["tet_seconds"]
    stage_line(f"fine level: red refinement of level 1, {len(Tr):,} tets / {len(Vr):,} nodes "
               f"({timer.seconds['refine']:.1f} s)", t0)
    return [(Vr, Tr)] + tets_n, [Pr] + Ps, [rep0] + reps, [surfaces_n[0]] + surfaces_n


def build_hierarchy(
    V: np.ndarray,
    F: np.ndarray,
    levels: int = 3,
    method: str = "nested",
    *,
    sizing: SizingOptions | None = None,
    meshing: MeshingOptions | None = None,
    cages: CageOptions | None = None,
    cache: bool = True,
    progress: bool | None = None,
) -> Hierarchy:
    """Cages, tet layers and prolongations for the closed surface ``(V, F)``.

    Sizes are decided first (:func:`nestmg.sizing.plan_hierarchy`, a few milliseconds): a request that
    cannot fit the tet / memory budget fails before any cage is built, naming the option to change.
    The work is done on a normalised copy (centred, unit bounding-box diagonal); the returned
    surfaces and tets are in the input's coordinates (:attr:`Hierarchy.frame` records the map,
    :meth:`Hierarchy.tets_in` gives both frames).

    Parameters
    ----------
    V : (n,3) float array
    F : (m,3) int array
        Closed, manifold, single-component surface (audited; a clear error otherwise).
    levels : int
        Number of levels (input + ``levels - 1`` coarser layers: cages, after ``same_domain_levels``), >= 2:
        a ceiling (:func:`nestmg.sizing.plan_levels`): a small input gets the levels whose smallest cage
        keeps >= 100 faces, with one stage line saying so (``options["plan"]["levels"]``).
    method : str
        Cage backend (``nested``, ``decimate``, ...; see ``cagegen.available_backends()``).
    sizing : SizingOptions, optional
        Fine edge length (relative to the diagonal; default the input's mean edge, enlarged to fit
        ``max_tets`` and ``mesh_time_budget``), tet ratio between levels, cage face counts,
        same-domain levels, the fine-level rule (``"refine"``: with TetWild and
        ``levels - same_domain_levels >= 3``, level 1 is the input meshed at ``2 h_0`` and the fine level
        its red refinement, :func:`nestmg.refine.refine_tets`, ~8x cheaper to mesh, docs/scale.md;
        ``"mesh"``: the input meshed at ``h_0``, the default with TetGen) and ``predecimate`` (with
        TetWild, an input much finer than the tets is decimated first, :func:`predecimate`, Hausdorff
        error below ``max(epsilon, h_mesh / 4)``; ``cage_info["predecimation"]`` records it; the cages
        are certified around that surface).
    meshing : MeshingOptions, optional
        Mesher (``"tetwild"``; TetGen is AGPL: opt-in), envelope, extrapolation rule, TetWild knobs,
        ``tet_retries`` (default 2 for certified methods, 0 for ``decimate``).
    cages : cagegen.CageOptions, optional
        The method's options (``cagegen.options_class(method)``, e.g. ``cagegen.NestedOptions``). With
        TetWild and a certified method, ``min_gap`` None means ``2.5 * meshing.epsilon``
        (:func:`cage_options_for`).
    cache : bool
        Reuse cages and tet meshes from the on-disk cache (``$NESTMG_CACHE``), keyed on the options.
    progress : bool or None
        Progress bars (None: only on a terminal). One stage line per stage goes to the ``nestmg``
        logger (the CLI prints them when stderr is not a terminal).

    Returns
    -------
    Hierarchy
        ``options`` holds ``sizing``, ``meshing`` and ``cages`` (``dataclasses.asdict``, with the
        defaults resolved: ``tet_retries``, the clearance) and the size ``plan``.

    Raises
    ------
    nestmg.NestmgInputError
        Bad options (one line, naming the field), ``levels < 2``.
    nestmg.sizing.SizingError
        The sizes cannot fit the budget (raised before any cage is built).
    cagegen.MeshInputError
        Bad input surface.
    cagegen.CageError
        A cage layer could not be built or certified (names the layer).
    """
    import cagegen

    from .cavities import merge_surfaces
    from .small_inputs import cage_fits, refinement_hierarchy

    t0 = time.perf_counter()
    sizing, meshing = typed(sizing, SizingOptions, "sizing"), typed(meshing, MeshingOptions, "meshing")
    if levels < 2:
        raise NestmgInputError(f"levels must be >= 2, got {levels}")
    cages = cage_options_for(method, cages, meshing)
    if meshing.tet_retries is None:
        meshing = dataclasses.replace(meshing, tet_retries=0 if method in cagegen.UNCERTIFIED_METHODS else 2)
    fine_level, refine = _fine_level(levels, sizing, meshing.mesher)
    V = np.ascontiguousarray(V, dtype=np.float64)
    F = np.ascontiguousarray(F, dtype=np.int64)
    Vn, center, scale = _normalize(V)
    if F.ndim != 2 or F.shape[1] != 3 or len(F) == 0 or F.min() < 0 or F.max() >= len(V):
        raise cagegen.MeshInputError(f"input: faces must be a non-empty (m,3) array of vertex indices, got {F.shape}")
    V, F, solid, _ = _solid_input(V, F, cages, meshing, t0)
    if solid is not None:  # the repaired surface is the input from here on (returned as level 0's surface)
        Vn, center, scale = _normalize(V)
    V_all, F_all, voids = V, F, _voids(V, F, meshing, t0)
    if voids is not None:  # a solid with voids: cages of its outer surface; the voids in the input's levels
        V, F = voids["outer"]
        Vn = (V - center) / scale  # the same frame: the voids lie inside the outer surface
    if sizing.face_counts is None and sizing.same_domain_levels == 0 and not cage_fits(len(F)):
        # no cage fits a surface this coarse: one coarse mesh of it and red refinements (nestmg.small_inputs)
        return refinement_hierarchy(V_all, F_all, (V_all - center) / scale, (center, scale), levels, method,
                                    sizing=sizing, meshing=meshing, cages=cages, cache=cache, progress=progress,
                                    t0=t0, solid=solid, voids=voids)
    # 1. sizes first: milliseconds, before any expensive stage
    # the whole solid's volume, faces and wall thickness (voids included) set the sizes
    plan = _plan((V_all - center) / scale, F_all, levels, sizing, meshing.mesher, refine, cage_input_faces=len(F))
    levels_asked, levels = levels, plan.n_levels  # --levels is a ceiling: the levels that fit the input
    if plan.levels["note"]:
        stage_line(plan.levels["note"], t0)
    n_same = sizing.same_domain_levels
    n_surf = levels - n_same - int(refine)  # input + cages
    stage_line(f"sizing: fine edge {plan.edge_length:.3g} of the diagonal ({plan.rule}), expected tets "
               f"{[f'{n:,}' for n in plan.expected_tets]}, peak memory ~{plan.peak_bytes / 2**30:.1f} GB", t0)
    for note in plan.notes:
        stage_line(f"sizing note: {note}", t0)
    timer = Timer()
    # 2. the surface actually meshed
    S0, F0, pre, plan, audit = _predecimated(Vn, F, levels, plan, sizing, meshing, cages, refine, timer, t0)
    eps0 = fine_envelope(meshing, pre)
    if eps0 > meshing.epsilon:
        stage_line(f"TetWild envelope of the input's levels {eps0:.2g} (the predecimation's error)", t0)
    # 3. cages (normalised frame inside build_cage_surfaces; we keep working normalised here)
    with timer("cages"):
        surfaces_u, info = build_cage_surfaces(S0, F0, n_surf, method, sizing=sizing, meshing=meshing,
                                               cages=cages, cache=cache, progress=progress, t0=t0,
                                               audit=audit)
    info["predecimation"] = pre
    if solid is not None:
        info["solid"] = solid
    stage_line(f"cages ({method}): faces {[len(Fk) for _, Fk in surfaces_u]}, "
               f"certified {info.get('certified')} ({timer.seconds['cages']:.1f} s)", t0)
    if voids is not None:  # the levels meshed from the input have the voids; the cages contain them
        Vv, Fv = voids["voids"]
        surfaces_u = [merge_surfaces([surfaces_u[0], ((Vv - center) / scale, Fv)]), *surfaces_u[1:]]
        info["voids"] = {"count": voids["count"], "faces": len(Fv)}
    surfaces_n = [surfaces_u[0]] * n_same + list(surfaces_u)  # same-domain layers first
    # 4. tets and prolongations
    tets_n, Ps, reps, tt = tet_hierarchy(surfaces_n, sizing=sizing, meshing=meshing,
                                         edge_length_abs=plan.edge_length * (2.0 if refine else 1.0),
                                         cache=cache, progress=progress, t0=t0, fine_epsilon=eps0)
    if refine:  # the fine level: one red refinement of the mesh at 2 h_0 (nestmg.refine)
        tets_n, Ps, reps, surfaces_n = _refined_fine_level(tets_n, Ps, reps, surfaces_n, tt, plan, timer, t0)
    timings = {**timer.seconds, **tt, "total": time.perf_counter() - t0}
    # 5. back to the user's frame (the input layer is the caller's array itself unless decimated)
    first = (V_all, F_all) if F0 is F else (surfaces_u[0][0] * scale + center, surfaces_u[0][1])
    n_first = 1 + n_same + int(refine)  # levels whose surface is the meshed input
    surfaces = [first] * n_first + [(Vk * scale + center, Fk) for Vk, Fk in surfaces_n[n_first:]]
    tets = [(Vt * scale + center, T) for Vt, T in tets_n]
    info["frame"] = {"center": center.tolist(), "scale": scale}
    h = Hierarchy(
        surfaces=surfaces, tets=tets, P=Ps, prolongation_reports=reps, method=method, cage_info=info,
        timings=timings,
        options={"levels": levels, "levels_requested": levels_asked, "fine_level": fine_level,
                 "sizing": as_dict(sizing), "meshing": as_dict(meshing), "cages": as_dict(cages),
                 "plan": plan.to_dict()},
        frame={"center": center, "scale": scale},
    )
    stage_line(f"hierarchy: tets {[len(T) for _, T in tets]}, n_outside {h.n_outside}, certified {h.certified}", t0)
    return h
